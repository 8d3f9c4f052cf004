"""Timing-study throughput (loop/timing_study.py) on the paper 3-AMB scene.

    .venv/bin/python benchmarks/bench_timing.py [--scene scenes/paper_3amb.toml] [--runs 3]

Prints, per rung, the points per second of the grid on one process (stability + sampled
sensitivity + unbalance per point, as `ambhil study timing` computes them), the 30 x 30 x 3
map on the modal rung (rates x latencies x speeds, stability only, the issue's target: < 60 s on
one core), and the speed-up of 2 Dask worker processes over the in-process cluster, measured in
one run (medians of --runs).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

import numpy as np  # noqa: E402

from ambhil.loop import timing_study as ts  # noqa: E402
from ambhil.loop.scene import load_scene  # noqa: E402


def timed_run(scene, spec, workers):
    c = ts.client_for(workers)
    try:
        c.submit(lambda: None).result()        # cluster up before the clock starts
        t0 = time.perf_counter()
        res = ts.run(scene, spec, c)
        return time.perf_counter() - t0, res
    finally:
        c.close()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="scenes/paper_3amb.toml")
    ap.add_argument("--runs", type=int, default=3)
    a = ap.parse_args()
    scene = load_scene(a.scene)
    print(f"scene {a.scene}; medians of {a.runs} runs; {os.cpu_count()} CPUs")
    for rung, rates, delays in (("modal", 6, 6), ("full", 3, 3)):
        spec = ts.StudySpec(rates=np.geomspace(5e3, 40e3, rates), delays=np.linspace(0, 2, delays), rung=rung)
        n = rates * delays
        walls = [timed_run(scene, spec, None)[0] for _ in range(a.runs)]
        w = statistics.median(walls)
        print(f"{rung:6s} {n} grid points (+ boundaries, zone rates, scene point) in {w:.2f} s "
              f"[{min(walls):.2f}, {max(walls):.2f}]: {n / w:.2f} points/s with sensitivity and boundaries")
    spec = ts.StudySpec(rates=np.geomspace(2e3, 50e3, 30), delays=np.linspace(0, 3, 30), speeds=(0.0, 300.0, 600.0),
                        rung="modal", sensitivity=False, zones=())
    one = [timed_run(scene, spec, None)[0] for _ in range(a.runs)]
    two = [timed_run(scene, spec, 2)[0] for _ in range(a.runs)]
    m1, m2 = statistics.median(one), statistics.median(two)
    print(f"modal 30 x 30 x 3 map (2700 points, stability only + 90 boundaries): in-process {m1:.1f} s "
          f"[{min(one):.1f}, {max(one):.1f}] (target < 60 s on one core); 2 workers {m2:.1f} s "
          f"[{min(two):.1f}, {max(two):.1f}]; speed-up {m1 / m2:.2f}")


if __name__ == "__main__":
    main()
