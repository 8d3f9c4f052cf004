"""Benchmark of the full-rung Campbell diagram (issue 14): the tracked method (modal.campbell's
default on the full rung) against every speed solved afresh with ARPACK (method="per-speed"),
in one run.  Prints medians [min, max] of several runs, the ratio of the medians and the largest
deviation of the tracked result from the per-speed one (modes drawn in the diagram, zeta <= 0.5).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_campbell.py [--runs 5] [--speeds 50] [--scene scenes/paper_3amb.toml ...] [--dense]

``--dense`` also compares both methods with the dense eigenvalues of the full closed loop
(LAPACK on E^-1 A, balanced; ~0.3 s a speed), the reference with no ARPACK noise.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from ambhil.loop.analysis import modal  # noqa: E402
from ambhil.loop.system import compile_system  # noqa: E402


def timed(fns, runs):
    """Median, min, max seconds of each function; the runs interleave the functions, so a burst
    of load from other jobs falls on all of them alike."""
    for fn in fns:
        fn()
    t = [[] for _ in fns]
    for _ in range(runs):
        for k, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            t[k].append(time.perf_counter() - t0)
    return [(statistics.median(x), min(x), max(x)) for x in t]


def dense_reference(m, speeds, fmax):
    """Every closed-loop mode with 0 < Im <= fmax from a dense eigensolution at each speed, as a
    campbell() dict (whirl not classified)."""
    import scipy.linalg as sla
    from ambhil.loop.analysis import closed_loop
    sp_, f_, z_ = [], [], []
    for s in speeds:
        lam = sla.eigvals(closed_loop.build(m, float(s), sparse=True).dense_standard())
        lam = lam[(lam.imag > 1e-6) & (lam.imag <= fmax)]
        sp_ += [s] * len(lam)
        f_ += list(lam.imag)
        z_ += list(-lam.real / np.abs(lam))
    return {"speed": np.array(sp_), "freq": np.array(f_), "zeta": np.array(z_)}


def deviation(new, ref, speeds):
    worst_f, worst_z = 0.0, 0.0
    for s in speeds:
        a = (new["speed"] == s) & (new["zeta"] <= 0.5)
        b = (ref["speed"] == s) & (ref["zeta"] <= 0.5)
        if a.sum() != b.sum():
            return f"mode count differs at {s:.1f} rad/s: {a.sum()} vs {b.sum()}"
        fa, fb = np.sort(new["freq"][a]), np.sort(ref["freq"][b])
        za, zb = new["zeta"][a][np.argsort(new["freq"][a])], ref["zeta"][b][np.argsort(ref["freq"][b])]
        worst_f = max(worst_f, float(np.max(np.abs(fa - fb) / fb)) if len(fb) else 0.0)
        worst_z = max(worst_z, float(np.max(np.abs(za - zb))) if len(zb) else 0.0)
    return f"same mode count at every speed; max |df|/f {worst_f:.1e}, max |dzeta| {worst_z:.1e}"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--speeds", type=int, default=50)
    ap.add_argument("--scene", nargs="+", default=["scenes/paper_3amb.toml", "scenes/rotor3m_3amb.toml"])
    ap.add_argument("--dense", action="store_true", help="compare with dense eigenvalues too (slow)")
    a = ap.parse_args()
    print(f"{a.runs} runs each; seconds for {a.speeds} speeds: median [min, max]; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    for scene in a.scene:
        m = compile_system(scene, rung="full")
        smax = m.scene.analysis.frequency_max
        speeds, fmax = np.linspace(0.0, smax, a.speeds), 1.1 * smax
        old, new = timed([lambda: modal.campbell(m, speeds, fmax, method="per-speed"),
                          lambda: modal.campbell(m, speeds, fmax)], a.runs)
        c = modal.campbell(m, speeds, fmax)
        print(f"{Path(scene).stem} ({m.n} FE DOF, 0-{smax:g} rad/s, modes below {fmax:g} rad/s)")
        print(f"  per-speed ARPACK  {old[0]:.4f} [{old[1]:.4f}, {old[2]:.4f}]  {1e3 * old[0] / a.speeds:.2f} ms/speed")
        print(f"  tracked           {new[0]:.4f} [{new[1]:.4f}, {new[2]:.4f}]  {1e3 * new[0] / a.speeds:.2f} ms/speed"
              f"  (projected size {c['basis_size']}, {c['checks']} check(s), {c['refined']} refined, "
              f"{c['fallback']} fallback)")
        ref = modal.campbell(m, speeds, fmax, method="per-speed")
        print(f"  ratio of medians  {old[0] / new[0]:.1f}x;  {deviation(c, ref, speeds)}")
        if a.dense:
            d = dense_reference(m, speeds, fmax)
            print(f"  against dense eigenvalues: tracked {deviation(c, d, speeds)}")
            print(f"                             per-speed {deviation(ref, d, speeds)}")
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
