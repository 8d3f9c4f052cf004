"""The plant step: its cost per rung and integrator in the in-process fused loop (``simulate``),
and the controller step (kernel alone), on a scene (default: the three-AMB paper scene,
controller at 10 kHz).

    .venv/bin/python -m benchmarks.plant_step [SCENE] [--repeat 5] [--duration 0.5]
        [--rungs full,modal,rigid] [--integrators bdf1,bdf2,trapezoidal,generalized-alpha,zoh]

Prints medians of ``--repeat`` runs of ``duration`` simulated seconds (after a warm-up run):
microseconds per plant step and per controller period (the plant may take several steps a
period), and the real-time factor of the fused loop (simulated time / wall time).
"""
from __future__ import annotations

import statistics
import time

import numba as nb
import numpy as np

from ambhil.controller import discrete as dc
from ambhil.loop.system import controller_runner
from ambhil.loop.system import compile_system
from ambhil.loop.simulation import simulate
from benchmarks import common


@nb.njit(cache=True)
def _ctrl_loop(p, x, y, cur, n):
    for k in range(n):
        y[0] = 1e-7 * (k % 7)
        dc.controller_step(p, x, y, cur)


def main(argv=None) -> int:
    ap = common.parser(__doc__, repeat=5)
    ap.add_argument("scene", nargs="?", default="paper_3amb")
    ap.add_argument("--duration", type=float, default=0.5)
    ap.add_argument("--rungs", default="full,modal,rigid")
    ap.add_argument("--integrators", default="bdf1,bdf2,trapezoidal,generalized-alpha,zoh")
    a = ap.parse_args(argv)
    a.scene = common.scene(a.scene)
    common.header("plant_step", "the plant step per rung and integrator, the controller step")
    print(f"# scene {a.scene}, {a.duration} s simulated per run, median of {a.repeat}")
    m0 = compile_system(a.scene, "rigid")
    r = controller_runner(m0)
    y = np.zeros(m0.n_axes); cur = np.zeros(m0.n_axes); x = r.state.copy()
    _ctrl_loop(r.params, x, y, cur, 10)
    N = 1_000_000
    ts = []
    for _ in range(a.repeat):
        t0 = time.perf_counter(); _ctrl_loop(r.params, x, y, cur, N); ts.append(time.perf_counter() - t0)
    print(f"controller step ({m0.n_axes} axes, {1 / r.period:g} Hz): {1e6 * statistics.median(ts) / N:.3f} us")
    rows = []
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
            rows.append([rung, m.n, integ, f"{per / ratio:.3f}", f"{per:.3f}", f"{a.duration / w:.1f}"])
            print(f"{rung} {integ}: {per:.3f} us/period", flush=True)
    common.table(["rung", "coordinates", "integrator", "us/plant step", "us/period", "real-time factor"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
