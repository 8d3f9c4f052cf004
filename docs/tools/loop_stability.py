"""Rerun the table of issue 15 (sampled-loop stability across rungs and integrators).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m docs.tools.loop_stability [SCENE] [--duration S]

For each row: what ``simulate(..., stability_check=True)`` reports (the check: the simulated
loop's dominant mode, and the numerics_warning label), the largest sensor displacement in the
first and second half of a 500-period run (as in the issue), and the dominant mode *measured*
from a kicked free response (unbalance removed) by the eigensystem realisation algorithm
(Juang & Pappa 1985; the same identification as tests/test_loop_stability.py).  Default scene:
scenes/rotor62_3amb.toml at 314 rad/s.  Prints a markdown table (docs/time_domain.md section 10).
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from ambhil.loop.scene import load_scene  # noqa: E402
from ambhil.loop.numerics import identify_poles  # noqa: E402
from ambhil.loop.simulation import simulate  # noqa: E402
from ambhil.loop.system import compile_system  # noqa: E402

ROWS = [("modal", "zoh", 1e-4), ("full", "zoh", 1e-4), ("full", "trapezoidal", 1e-4),
        ("full", "trapezoidal", 2.5e-5), ("full", "trapezoidal", 1.25e-5), ("full", "trapezoidal", 5e-5),
        ("full", "generalized-alpha", 2.5e-5), ("full", "bdf2", 2.5e-5), ("full", "bdf1", 1e-4),
        ("modal", "trapezoidal", 1.25e-5), ("modal", "bdf1", 1e-4), ("modal-2k", "zoh", 1e-4)]




def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default=str(ROOT / "scenes" / "rotor62_3amb.toml"))
    ap.add_argument("--speed", type=float, default=314.0)
    ap.add_argument("--duration", type=float, default=0.05, help="s, the run whose displacement is shown")
    ap.add_argument("--measure", type=float, default=0.6, help="s, free response used for the measurement")
    a = ap.parse_args(argv)
    sc = load_scene(a.scene)
    free = sc.with_plant(unbalances=())
    models = {}

    def model(rung, scene):
        key = (rung, scene is free)
        if key not in models:
            if rung == "modal-2k":
                s2 = scene.with_plant(model=dataclasses.replace(scene.plant.model, modal_cutoff=2000.0))
                models[key] = compile_system(s2, "modal")
            else:
                models[key] = compile_system(scene, rung)
        return models[key]

    print(f"scene {Path(a.scene).name}, {a.speed:g} rad/s, controller {sc.controller.sample_rate:g} Hz; "
          f"'modal' = default cutoff, 'modal-2k' = the former 2 kHz cutoff\n")
    print("| rung | integrator | plant step | reported by the check | numerics | max abs y, 1st / 2nd half (um) "
          "| measured from the response | wall |")
    print("|---|---|---|---|---|---|---|---|")
    for rung, integ, h in ROWS:
        t0 = time.perf_counter()
        m = model(rung, sc)
        r = simulate(m, a.duration, a.speed, integrator=integ, h=h, stability_check=True)
        rho = r.meta["loop_spectral_radius"]
        if r.instability and "discrete loop unstable" in r.instability:
            chk = (f"unstable: {r.meta['loop_frequency']:.4g} Hz grows at {r.meta['loop_growth_rate']:.3g} 1/s "
                   f"({rho:.6f} per period)")
        else:
            chk = f"stable ({rho:.6f} per period)"
        y = np.abs(r.y).max(axis=1)
        nh = len(y) // 2
        mf = model(rung, free)
        rng = np.random.default_rng(0)
        rf = simulate(mf, a.measure, a.speed, integrator=integ, h=h, q0=1e-9 * rng.standard_normal(mf.n),
                      v0=1e-6 * rng.standard_normal(mf.n))
        mu = identify_poles(rf.y)
        sd = np.log(complex(mu[np.argmax(np.abs(mu))])) / r.meta["period"]
        meas = f"{abs(sd.imag) / 2 / np.pi:.4g} Hz, {'grows' if sd.real > 0 else 'decays'} at {abs(sd.real):.3g} 1/s"
        lab = r.numerics.split(":")[0] if r.numerics else ""
        print(f"| {rung} | {integ} | {h:g} | {chk} | {lab} | {1e6 * y[:nh].max():.3g} / {1e6 * y[nh:].max():.3g} "
              f"| {meas} | {time.perf_counter() - t0:.0f} s |", flush=True)
        if r.numerics:
            print(f"|  |  |  | {r.numerics} |  |  |  |  |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
