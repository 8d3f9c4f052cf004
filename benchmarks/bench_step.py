"""Time-domain step cost on a scene (default: the three-AMB paper scene, controller at 10 kHz).

    .venv/bin/python benchmarks/bench_step.py [SCENE] [--repeat 5] [--duration 0.5]

Prints medians: microseconds per plant step and per controller step (kernel alone), and the
in-process real-time factor of the fused loop (simulated time / wall time) per rung and integrator.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numba as nb
import numpy as np

from ambhil.controller import discrete as dc
from ambhil.loop.system import controller_runner
from ambhil.loop.system import compile_system
from ambhil.loop.simulation import simulate


@nb.njit(cache=True)
def _ctrl_loop(p, x, y, cur, n):
    for k in range(n):
        y[0] = 1e-7 * (k % 7)
        dc.controller_step(p, x, y, cur)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", nargs="?", default="scenes/paper_3amb.toml")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--duration", type=float, default=0.5)
    ap.add_argument("--rungs", default="full,modal,rigid")
    ap.add_argument("--integrators", default="bdf1,bdf2,trapezoidal,generalized-alpha,zoh")
    a = ap.parse_args(argv)
    print(f"scene {a.scene}, {a.duration} s simulated per run, median of {a.repeat}")
    m0 = compile_system(a.scene, "rigid")
    r = controller_runner(m0)
    y = np.zeros(m0.n_axes); cur = np.zeros(m0.n_axes); x = r.state.copy()
    _ctrl_loop(r.params, x, y, cur, 10)
    N = 1_000_000
    ts = []
    for _ in range(a.repeat):
        t0 = time.perf_counter(); _ctrl_loop(r.params, x, y, cur, N); ts.append(time.perf_counter() - t0)
    print(f"controller step ({m0.n_axes} axes, {1 / r.period:g} Hz): {1e6 * statistics.median(ts) / N:.3f} us")
    print(f"{'rung':6} {'n':>4} {'integrator':18} {'us/plant step':>13} {'us/period':>10} {'RTF':>8}")
    for rung in a.rungs.split(","):
        m = compile_system(a.scene, rung)
        W = m.spec.speed.value or 0.0
        for integ in a.integrators.split(","):
            simulate(m, 0.01, W, integrator=integ)  # compile / warm up
            walls, ratio = [], 1
            for _ in range(a.repeat):
                res = simulate(m, a.duration, W, integrator=integ, record_every=10)
                walls.append(res.wall); ratio = res.meta["ratio"]
            w = statistics.median(walls)
            per = 1e6 * w / res.steps
            print(f"{rung:6} {m.n:4d} {integ:18} {per / ratio:13.3f} {per:10.3f} {a.duration / w:8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
