"""Benchmark of the frequency-domain analyses on the three-AMB paper scene.

Times the 400-speed unbalance sweep (0-4000 rad/s, one output node) and the first four critical
speeds, for the full FE rung and the Craig-Bampton modal rung; prints the median and spread of
several runs.  Each run starts from the compiled model (compilation is timed separately).

    .venv/bin/python benchmarks/bench_analysis.py [--runs 7] [--scene scenes/paper_3amb.toml]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from ambhil.loop.analysis import modal, unbalance  # noqa: E402
from ambhil.loop.system import compile_system  # noqa: E402


def timed(fn, runs):
    fn()  # warm-up (imports, caches of LAPACK)
    t = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return statistics.median(t), min(t), max(t)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--scene", default="scenes/paper_3amb.toml")
    a = ap.parse_args()
    speeds = np.linspace(0.0, 4000.0, 400)
    print(f"scene {a.scene}, {a.runs} runs each; seconds: median [min, max]")
    for rung in ("full", "modal"):
        med, lo, hi = timed(lambda: compile_system(a.scene, rung=rung), a.runs)
        m = compile_system(a.scene, rung=rung)
        print(f"{rung:5s} ({m.n} coordinates) compile            {med:.4f} [{lo:.4f}, {hi:.4f}]")
        med, lo, hi = timed(lambda: unbalance.response(m, speeds, nodes=[20]), a.runs)
        print(f"{rung:5s} unbalance sweep, 400 speeds       {med:.4f} [{lo:.4f}, {hi:.4f}]  target < 0.1")
        med, lo, hi = timed(lambda: modal.critical_speeds(m, count=4), a.runs)
        cs = modal.critical_speeds(m, count=4)
        print(f"{rung:5s} first four critical speeds        {med:.4f} [{lo:.4f}, {hi:.4f}]  target < 0.1   "
              f"({', '.join(f'{c.hz:.2f}' for c in cs)} Hz)")
    print("reference (ross-notes.md, ROSS 3.1.0, ~62-node AMB rotor): unbalance 400 speeds 6.64 s, "
          "run_critical_speed 4.80 s")


if __name__ == "__main__":
    main()
