"""Cost of the ANCF rung against the full FE rung on the 62-element paper rotor on three AMBs.

    .venv/bin/python -m benchmarks.ancf [SCENE] [--repeat 3] [--duration 1.0] [--speed 327.19]

Closed loop (the scene's controller, BDF1, h = the scene's step = 1e-4 s), ``simulate`` for
``duration`` s simulated per run, medians over ``repeat`` runs after a warm-up run (numba
compilation excluded).  Prints plant steps per second, wall time per simulated second and the
real-time factor (simulated time / wall time) for both rungs, the ANCF Newton statistics and the
ratio of the two costs measured in the same run.
"""
from __future__ import annotations

import statistics
import time

from ambhil.loop.simulation import simulate
from ambhil.loop.system import compile_system
from benchmarks import common


def main(argv=None) -> int:
    ap = common.parser(__doc__, repeat=3)
    ap.add_argument("scene", nargs="?", default="paper_3amb")
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--speed", type=float, default=None)
    ap.add_argument("--integrator", default="bdf1")
    a = ap.parse_args(argv)
    a.scene = common.scene(a.scene)
    common.header("ancf", "the ANCF rung against the full FE rung, whole simulate()")
    print(f"# scene {a.scene}: {a.duration} s simulated per run, {a.integrator}, median of {a.repeat} "
          f"(after one warm-up run)")
    walls = {}
    for rung in ("full", "ancf"):
        m = compile_system(a.scene, rung=rung)
        simulate(m, 0.01, speed=a.speed, integrator=a.integrator)  # warm-up (compilation)
        ws, last = [], None
        for _ in range(a.repeat):
            t0 = time.perf_counter()
            last = simulate(m, a.duration, speed=a.speed, integrator=a.integrator)
            ws.append(time.perf_counter() - t0)
        w = statistics.median(ws)
        walls[rung] = w
        nsteps = last.steps * last.meta["ratio"]
        extra = ""
        if rung == "ancf":
            mt = last.meta
            extra = (f"  n={mt['n']} coords + {mt['constraints']} constraints, Newton {mt['newton_mean']:.2f} it/step "
                     f"(max {mt['max_newton_iterations']}), {mt['refactorisations']} factorisations, "
                     f"constraint drift {mt['constraint_drift']:.1e}")
        common.report(f"{rung}: wall per run", ws, "s", note=f"{nsteps / w:.0f} plant steps/s, real-time factor "
                      f"{a.duration / w:.3f}{extra}")
    print(f"ancf / full cost ratio: {walls['ancf'] / walls['full']:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
