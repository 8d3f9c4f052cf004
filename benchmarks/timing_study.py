"""Timing-study throughput (loop/timing_study.py) on the paper 3-AMB scene.

    .venv/bin/python -m benchmarks.timing_study [--scene scenes/paper_3amb.toml] [--repeat 3]

Prints, per rung, the points per second of the grid on one process (stability + sampled
sensitivity + unbalance per point, as `ambhil study timing` computes them), the 30 x 30 x 3
map on the modal rung (rates x latencies x speeds, stability only, target: < 60 s on
one core), and the speed-up of 2 Dask worker processes over the in-process cluster, measured in
one run (medians of --repeat).
"""
from __future__ import annotations

import statistics
import time

import numpy as np

from ambhil.loop import timing_study as ts
from ambhil.loop.scene import load_scene
from benchmarks import common


def timed_run(scene, spec, workers):
    c = ts.client_for(workers)
    try:
        c.submit(lambda: None).result()        # cluster up before the clock starts
        t0 = time.perf_counter()
        res = ts.run(scene, spec, c)
        return time.perf_counter() - t0, res
    finally:
        c.close()


def main(argv=None):
    ap = common.parser(__doc__, repeat=3)
    ap.add_argument("--scene", default="paper_3amb")
    a = ap.parse_args(argv)
    scene = load_scene(common.scene(a.scene))
    common.header("timing_study", "timing-study throughput")
    for rung, rates, delays in (("modal", 6, 6), ("full", 3, 3)):
        spec = ts.StudySpec(rates=np.geomspace(5e3, 40e3, rates), delays=np.linspace(0, 2, delays), rung=rung)
        n = rates * delays
        walls = [timed_run(scene, spec, None)[0] for _ in range(a.repeat)]
        w = statistics.median(walls)
        print(f"{rung:6s} {n} grid points (+ boundaries, zone rates, scene point) in {w:.2f} s "
              f"[{min(walls):.2f}, {max(walls):.2f}]: {n / w:.2f} points/s with sensitivity and boundaries")
    spec = ts.StudySpec(rates=np.geomspace(2e3, 50e3, 30), delays=np.linspace(0, 3, 30), speeds=(0.0, 300.0, 600.0),
                        rung="modal", sensitivity=False, zones=())
    one = [timed_run(scene, spec, None)[0] for _ in range(a.repeat)]
    two = [timed_run(scene, spec, 2)[0] for _ in range(a.repeat)]
    m1, m2 = statistics.median(one), statistics.median(two)
    print(f"modal 30 x 30 x 3 map (2700 points, stability only + 90 boundaries): in-process {m1:.1f} s "
          f"[{min(one):.1f}, {max(one):.1f}] (target < 60 s on one core); 2 workers {m2:.1f} s "
          f"[{min(two):.1f}, {max(two):.1f}]; speed-up {m1 / m2:.2f}")


if __name__ == "__main__":
    main()
