"""Benchmark: the full rung's critical speeds of one rotor at two controller sample rates.

The closed loop of the frequency-domain analyses is continuous (H(s) does not depend on the sample
rate), so its critical speeds, and their cost, must not depend on the rate either: the seed model
(ambhil.loop.analysis.modal.seed_system) takes its cutoff from the analysed range.  Prints, for each rate,
the seed model's size, the median [min, max] of several runs of ``critical_speeds`` from the compiled
model (runs interleaved, so a burst of load falls on every rate alike) and the criticals, then the
ratio of the medians (target <= 1.5).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_criticals.py [--runs 7] [--scene scenes/rotor62_3amb.toml] [--rates 10k,100k]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ambhil.loop.analysis import modal  # noqa: E402
from ambhil.loop.scene import load_scene  # noqa: E402
from ambhil.loop.system import compile_system  # noqa: E402


def rate(text: str) -> float:
    t = text.strip().lower()
    return float(t[:-1]) * 1e3 if t.endswith("k") else float(t)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--scene", default="scenes/rotor62_3amb.toml")
    ap.add_argument("--rates", default="10k,100k", help="controller sample rates, Hz (k = 1000)")
    a = ap.parse_args()
    scene = load_scene(a.scene)
    rates = [rate(r) for r in a.rates.split(",")]
    models = [compile_system(scene.with_controller(sample_rate=r), rung="full") for r in rates]
    for m in models:
        modal.critical_speeds(m)  # warm-up (imports, LAPACK caches)
    times = [[] for _ in models]
    for _ in range(a.runs):
        for k, m in enumerate(models):
            t0 = time.perf_counter()
            modal.critical_speeds(m)
            times[k].append(time.perf_counter() - t0)
    print(f"scene {a.scene} (full rung, {models[0].n} coordinates), {a.runs} runs; critical_speeds seconds: median [min, max]")
    med = []
    for r, m, t in zip(rates, models, times):
        smax = 1.1 * m.scene.analysis.frequency_max
        seed = modal.seed_system(m, smax)
        cs = modal.critical_speeds(m)
        med.append(statistics.median(t))
        print(f"{r / 1e3:6.1f} kHz  seed {seed.n} coordinates  {med[-1]:.3f} [{min(t):.3f}, {max(t):.3f}]  "
              f"criticals {', '.join(f'{c.speed:.4f}' for c in cs)} rad/s")
    print(f"ratio of medians {rates[-1] / 1e3:g} kHz / {rates[0] / 1e3:g} kHz: {med[-1] / med[0]:.2f}  (target <= 1.5)")


if __name__ == "__main__":
    main()
