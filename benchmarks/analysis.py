"""The frequency-domain analyses: the unbalance sweep and the critical speeds per rung, and
the full rung's critical speeds at two controller sample rates.

    .venv/bin/python -m benchmarks.analysis [--repeat 7] [--scene scenes/paper_3amb.toml]
        [--rungs full,modal] [--rates-scene scenes/rotor62_3amb.toml] [--rates 10k,100k]

Per rung of ``--scene``: compiling the model, the 400-speed unbalance sweep (0-4000 rad/s, one
output node) and the first four critical speeds, each run from the compiled model (target
< 0.1 s each; ROSS 3.1.0 takes 6.6 s and 4.8 s for the same two on a rotor of this size).

Then the sample-rate check: the closed loop of the analyses is continuous (H(s) does not depend
on the sample rate), so the full rung's critical speeds, and their cost, must not depend on it:
the seed model (``ambhil.loop.analysis.modal.seed_system``) takes its cutoff from the analysed
range.  For each of ``--rates`` on ``--rates-scene``: the seed model's size, ``critical_speeds``
(the rates interleaved run by run) and the criticals, then the ratio of the medians (target
<= 1.5).  ``--rates ''`` leaves it out.
"""
from __future__ import annotations

import os
import statistics
import time

import numpy as np

from benchmarks import common


def per_rung(scene: str, rungs: list[str], repeat: int) -> None:
    from ambhil.loop.analysis import modal, unbalance
    from ambhil.loop.system import compile_system
    speeds = np.linspace(0.0, 4000.0, 400)
    for rung in rungs:
        t = common.timed(lambda: compile_system(scene, rung=rung), repeat)
        m = compile_system(scene, rung=rung)
        common.report(f"{rung} ({m.n} coordinates): compile", t, "s")
        common.report(f"{rung}: unbalance sweep, 400 speeds", common.timed(
            lambda: unbalance.response(m, speeds, nodes=[20]), repeat), "s", note="target < 0.1")
        cs = modal.critical_speeds(m, count=4)
        common.report(f"{rung}: first four critical speeds", common.timed(
            lambda: modal.critical_speeds(m, count=4), repeat), "s",
            note=f"target < 0.1  ({', '.join(f'{c.hz:.2f}' for c in cs)} Hz)")


def over_rates(scene_path: str, rates: list[float], repeat: int) -> None:
    from ambhil.loop.analysis import modal
    from ambhil.loop.scene import load_scene
    from ambhil.loop.system import compile_system
    scene = load_scene(scene_path)
    models = [compile_system(scene.with_controller(sample_rate=r), rung="full") for r in rates]
    for m in models:
        modal.critical_speeds(m)  # warm-up (imports, LAPACK caches)
    times = [[] for _ in models]
    for _ in range(repeat):       # interleaved: a burst of load falls on every rate alike
        for k, m in enumerate(models):
            t0 = time.perf_counter()
            modal.critical_speeds(m)
            times[k].append(time.perf_counter() - t0)
    print(f"{os.path.basename(scene_path)}, full rung ({models[0].n} coordinates): critical_speeds per sample rate")
    for r, m, t in zip(rates, models, times):
        seed = modal.seed_system(m, 1.1 * m.scene.analysis.frequency_max)
        cs = modal.critical_speeds(m)
        common.report(f"{r / 1e3:g} kHz (seed {seed.n} coordinates)", t, "s",
                      note=f"criticals {', '.join(f'{c.speed:.4f}' for c in cs)} rad/s")
    ratio = statistics.median(times[-1]) / statistics.median(times[0])
    print(f"ratio of medians {rates[-1] / 1e3:g} kHz / {rates[0] / 1e3:g} kHz: {ratio:.2f}  (target <= 1.5)")


def main(argv=None):
    from ambhil.loop import units
    ap = common.parser(__doc__, repeat=7)
    ap.add_argument("--scene", default="paper_3amb")
    ap.add_argument("--rungs", default="full,modal")
    ap.add_argument("--rates-scene", default="rotor62_3amb")
    ap.add_argument("--rates", default="10k,100k", help="controller sample rates (10k = 10 kHz)")
    a = ap.parse_args(argv)
    common.header("analysis", "frequency-domain analyses: unbalance sweep, critical speeds")
    per_rung(common.scene(a.scene), common.csv(a.rungs), a.repeat)
    rates = [units.rate(r) for r in common.csv(a.rates)]
    if rates:
        over_rates(common.scene(a.rates_scene), rates, a.repeat)


if __name__ == "__main__":
    main()
