"""Compile every numba kernel once, so that the first real run does not pay for it.

The kernels are cached by numba (``cache=True``) in the packages' ``__pycache__`` folders, so one
warm-up per checkout (the launcher runs it right after installing: ``python -m ambhil.loop.warmup``)
makes the first ``ambhil run`` start in seconds instead of spending its start-up compiling.
"""
from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "paper_3amb.toml"


def warm_up(scene=SCENE) -> float:
    """Run the plant step, the controller step and the fused loop once; returns the seconds spent."""
    from ambhil.plant.step import PlantRunner
    from .simulation import simulate
    from .system import compile_system, controller_runner
    t0 = time.perf_counter()
    m = compile_system(scene, rung="modal")
    plant, ctrl = PlantRunner(m), controller_runner(m)
    plant.reset()
    y = plant.advance(np.array(m.i_op))
    ctrl.step(y)
    simulate(m, 10 * ctrl.period)
    # a law of its own runs between the hardware kernels (controller/law_runner.py); the LTI
    # kinds' kernel too: the built-in PID as a law, and as one transfer block
    from ambhil.controller.law_lti import LTILaw
    from ambhil.controller.law_runner import LawRunner
    from ambhil.controller.pid_law import PIDLaw
    c = m.scene.controller
    pid = {"type": "pid", "kp": c.kp, "ki": c.ki, "kd": c.kd, "derivative_filter": c.derivative_filter}
    lti = replace(c, kind="transfer", lti={"transfer": {"blocks": [pid]}},
                  table={**c.table, "kind": "transfer", "transfer": {"blocks": [pid]}})
    for law, cfg in ((PIDLaw, c), (LTILaw, lti)):
        LawRunner(law, cfg, m.i_op).step(y)
    for scheme in ("bdf1", "generalized-alpha"):  # the ancf rung's kernels (element, residual, Jacobian)
        simulate(compile_system(scene, rung="ancf"), 3 * ctrl.period, integrator=scheme)
    return time.perf_counter() - t0


if __name__ == "__main__":
    print("ambhil: compiling the numba kernels (first run only) ...", file=sys.stderr, flush=True)
    print(f"ambhil: kernels ready ({warm_up():.1f} s)", file=sys.stderr)
