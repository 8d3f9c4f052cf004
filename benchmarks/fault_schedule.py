"""What a fault schedule costs ``simulate``: the fused numba loop (no faults) against the per-period
path taken when faults are scheduled (plant/faults.py around the same kernels).

    .venv/bin/python -m benchmarks.fault_schedule [--repeat 5] [--duration 0.5]

Cases per rung (modal, full) of scenes/paper_3amb.toml, each run ``--repeat`` times interleaved:
``fused`` no faults; ``idle`` one fault scheduled after the end (the per-period path, nothing
active); ``active`` sensor noise on every axis plus an amplifier limit from t = 0.  Prints each
run's µs per controller period, the medians and the ratios to ``fused`` measured in this run.
"""
from __future__ import annotations

import statistics

from benchmarks import common


def main(argv=None) -> None:
    ap = common.parser(__doc__, repeat=5)
    ap.add_argument("--duration", type=float, default=0.5)
    a = ap.parse_args(argv)
    common.header("fault_schedule", "what a fault schedule costs simulate()")
    from ambhil.loop.scene import load_scene, with_fault_flags
    from ambhil.loop.simulation import simulate
    from ambhil.loop.system import compile_system
    scene = load_scene(common.scene("paper_3amb"))
    cases = {"fused": [], "idle": ["sensor_zero:at=100s,axis=A.x"],
             "active": ["sensor_noise:at=0s,axis=A,sigma=1e-7", "sensor_noise:at=0s,axis=B,sigma=1e-7",
                        "sensor_noise:at=0s,axis=C,sigma=1e-7", "amp_limit:at=0s,limit=1.0"]}
    for rung in ("modal", "full"):
        models = {k: compile_system(with_fault_flags(scene, v), rung=rung) for k, v in cases.items()}
        for m in models.values():
            simulate(m, 0.01)                        # kernels loaded, plans built once
        us = {k: [] for k in cases}
        for _ in range(a.repeat):
            for k, m in models.items():
                us[k].append(simulate(m, a.duration).us_per_period)
        med = {k: statistics.median(v) for k, v in us.items()}
        for k in cases:
            print(f"{rung:5s} {k:6s} us/period: " + " ".join(f"{x:.1f}" for x in us[k])
                  + f"  median {med[k]:.1f}  ratio {med[k] / med['fused']:.2f}")


if __name__ == "__main__":
    main()
