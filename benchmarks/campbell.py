"""Campbell diagram on the full rung: ambhil's tracked method (the full rung's default), its
per-speed ARPACK path, and a general-purpose rotordynamics code (ROSS) on the same rotor.

    .venv/bin/python -m benchmarks.campbell [--repeat 5] [--speeds 50]
        [--scene scenes/paper_3amb.toml scenes/rotor3m_3amb.toml] [--ross-python PY] [--dense]

ROSS (``ross-rotordynamics``; 3.1.0 needs Python >= 3.13, not a dependency of ambhil) is run in
``PY`` (default: this Python if it can import ``ross``), e.g. a virtual environment of its own:
``python3.13 -m venv ~/rossvenv && ~/rossvenv/bin/pip install ross-rotordynamics``.  Without
ROSS the benchmark says so and prints ambhil's figures only (exit 0).

For each scene the same rotor is built in ROSS from the compiled scene: one uniform
``ShaftElement`` per FE element (Euler-Bernoulli with rotary inertia, as the scene), the discs as
``DiskElement``, each radial AMB as a ``MagneticBearingElement`` with the scene's gap, bias,
turns, pole area and angle, sensor and amplifier gains, and the controller (PID with derivative
filter, sensor and amplifier lags) as its transfer function; the shaft's stiffness-proportional
damping as the rotor's beta.  ROSS is timed warm (its first ``run_modal`` compiles with numba)
on ``run_campbell`` over the same speeds, asked for as many frequencies as the tracked diagram
draws at rest, on a fresh rotor each run (ROSS caches results per rotor).

Printed per scene, median [min, max] over ``--repeat`` runs: ambhil tracked (timed before and
after ROSS, so a drift of the machine falls on both), per-speed ARPACK and ROSS, the ratios of
the medians, the largest deviation of the tracked result from the per-speed one (modes drawn in
the diagram, zeta <= 0.5), and as a check that the rotors are the same the forward critical
speeds (1X crossings) and the lowest frequencies at rest in both codes (ROSS evaluates the AMB
coefficients at the spin speed and carries no controller states, so away from the 1X line the
two differ by construction).  ``--dense`` also compares both ambhil methods with the dense
eigenvalues of the full closed loop (LAPACK on E^-1 A, balanced; ~0.3 s a speed), the reference
with no ARPACK noise.
"""
from __future__ import annotations

import importlib.util
import json
import math
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np

from benchmarks import common

ROSS_SIDE = r'''
import json, sys, time, math
import numpy as np
import ross as rs
import control
spec = json.loads(sys.stdin.read())
steel = rs.Material(name="scene_steel", rho=spec["rho"], E=spec["E"], G_s=spec["G"])
shaft = [rs.ShaftElement(L=L, idl=di, odl=do, material=steel, shear_effects=False,
                         rotary_inertia=spec["rotary_inertia"], gyroscopic=True)
         for L, di, do in spec["elements"]]
discs = [rs.DiskElement(n=d["node"], m=d["m"], Id=d["Id"], Ip=d["Ip"]) for d in spec["discs"]]
c = spec["controller"]
s = control.tf("s")
C = (c["kp"] + c["ki"] / s + c["kd"] * s / (1 + c["Td"] * s)) / (1 + c["Ts"] * s) / (1 + c["Ta"] * s)
ambs = [rs.MagneticBearingElement(n=b["node"], g0=b["g0"], i0=b["i0"], ag=b["ag"], nw=b["nw"],
                                  alpha=b["alpha"], k_amp=c["k_amp"], k_sense=c["k_sense"],
                                  controller_transfer_function=C, tag=b["name"])
        for b in spec["ambs"]]
make = lambda: rs.Rotor(shaft, discs, ambs, beta=spec["beta"])   # a fresh rotor: ROSS caches results per rotor
speeds = np.array(spec["speeds"])
rotor = make()
rotor.run_modal(0.0)                      # numba compilation, not timed
wd = np.asarray(rotor.run_modal(0.0, num_modes=2 * (spec["frequencies"] + 2)).wd)
f0 = sorted(wd[wd > 1e-3])[:spec["frequencies"]]
rotor.run_campbell(speeds[:3], frequencies=spec["frequencies"])   # warm, not timed
t = []
for _ in range(spec["runs"]):
    rotor = make()
    t0 = time.perf_counter()
    camp = rotor.run_campbell(speeds, frequencies=spec["frequencies"])
    t.append(time.perf_counter() - t0)
# forward 1X crossings: there ROSS's coefficients (taken at whirl = spin speed) are exact
# (ROSS's whirl_values: 0 forward, 1 backward, 0.5 mixed)
cross = []
wd, wh = np.asarray(camp.wd), np.asarray(camp.whirl_values)
for j in range(wd.shape[1]):
    d = wd[:, j] - speeds
    for i in range(len(speeds) - 1):
        if d[i] > 0 >= d[i + 1] and wh[i, j] == 0.0 and wh[i + 1, j] == 0.0:
            cross.append(float(speeds[i] + (speeds[i + 1] - speeds[i]) * d[i] / (d[i] - d[i + 1])))
print(json.dumps({"times": t, "wd0": [float(x) for x in f0], "ndof": int(rotor.ndof),
                  "crossings": sorted(cross)}))
'''


def rotor_spec(m, speeds, frequencies, runs) -> dict:
    """The scene's rotor in the terms of ROSS's elements (see the module docstring)."""
    p, c = m.scene.plant, m.scene.controller
    if len({(s.youngs_modulus, s.shear_modulus, s.density) for s in p.sections}) != 1:
        raise SystemExit(f"{m.scene.path}: sections of different materials are not mapped to ROSS here")
    if p.damping.mass_proportional:
        raise SystemExit(f"{m.scene.path}: mass-proportional damping is not mapped to ROSS here")
    els = []
    for s in p.sections:
        els += [(s.length / s.elements, s.inner_diameter, s.outer_diameter)] * s.elements
    s0 = p.sections[0]
    return {"E": s0.youngs_modulus, "G": s0.shear_modulus, "rho": s0.density, "elements": els,
            "rotary_inertia": bool(p.model.rotary_inertia), "beta": p.damping.stiffness_proportional,
            "discs": [{"node": d.node, "m": d.mass, "Id": d.diametral_inertia, "Ip": d.polar_inertia}
                      for d in p.discs],
            "ambs": [{"name": a.name, "node": a.node, "g0": a.gap, "i0": a.bias_current,
                      "ag": a.pole_area, "nw": a.turns, "alpha": math.radians(a.pole_angle)}
                     for a in p.ambs],
            "controller": {"kp": c.kp, "ki": c.ki, "kd": c.kd, "Td": c.derivative_filter,
                           "Ts": c.sensor.time_constant, "Ta": c.amplifier.time_constant,
                           "k_amp": c.amplifier.gain, "k_sense": c.sensor.gain},
            "speeds": [float(x) for x in speeds], "frequencies": int(frequencies), "runs": runs}


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


def ross_python(given: str | None) -> str | None:
    """The Python to run ROSS in, or None if there is none."""
    if given:
        return given
    return sys.executable if importlib.util.find_spec("ross") is not None else None


def run_ross(python: str, spec: dict) -> dict:
    r = subprocess.run([python, "-W", "ignore", "-c", ROSS_SIDE], input=json.dumps(spec),
                       capture_output=True, text=True, env=common.child_env(), timeout=3600)
    if r.returncode != 0:
        raise SystemExit(f"ROSS side failed: {common.tail(r.stderr, 1500)}")
    return common.last_json(r.stdout)


def one_scene(scene: str, a, ross_py: str | None) -> None:
    from ambhil.loop.analysis import modal
    from ambhil.loop.system import compile_system
    m = compile_system(common.scene(scene), rung="full")
    smax = m.scene.analysis.frequency_max
    speeds, fmax = np.linspace(0.0, smax, a.speeds), 1.1 * smax
    c = modal.campbell(m, speeds, fmax)
    rest = (c["speed"] == 0.0) & (c["zeta"] <= 0.5)
    nf = int(rest.sum())
    track = lambda: modal.campbell(m, speeds, fmax)                       # noqa: E731
    per = lambda: modal.campbell(m, speeds, fmax, method="per-speed")     # noqa: E731
    t_tr, t_ps = common.timed(track, a.repeat), common.timed(per, a.repeat)
    ross = run_ross(ross_py, rotor_spec(m, speeds, nf, a.repeat)) if ross_py else None
    t_tr += common.timed(track, a.repeat)
    print(f"{Path(scene).stem}: full rung, {m.n} FE DOF + controller states; 0-{smax:g} rad/s, "
          f"{a.speeds} speeds, {nf} modes drawn at rest, {c['basis_size']} projected size")
    common.report("  ambhil tracked (default)", t_tr, "s")
    common.report("  ambhil per-speed ARPACK", t_ps, "s")
    mt, mp = statistics.median(t_tr), statistics.median(t_ps)
    ref = per()
    print(f"  per-speed / tracked {mp / mt:.1f}x; tracked against per-speed: {deviation(c, ref, speeds)}")
    if ross is not None:
        common.report(f"  ROSS run_campbell, warm ({ross['ndof']} DOF)", ross["times"], "s")
        mr = statistics.median(ross["times"])
        print(f"  ROSS / tracked {mr / mt:.1f}x, ROSS / per-speed {mr / mp:.1f}x")
        crit = [round(float(x.speed), 1) for x in modal.critical_speeds(m)[:4]]
        print(f"  forward critical speeds (1X crossings), rad/s: ambhil {crit}, ROSS's Campbell "
              f"{[round(x, 1) for x in ross['crossings'][:4]]} (interpolated on its {a.speeds} speeds)")
        ours = np.sort(c["freq"][rest])
        print(f"  lowest frequencies at rest, rad/s: ambhil {np.round(ours[:6], 1).tolist()}, ROSS "
              f"{np.round(ross['wd0'][:6], 1).tolist()} (AMB coefficients at 0 rad/s)")
    if a.dense:
        d = dense_reference(m, speeds, fmax)
        print(f"  against dense eigenvalues: tracked {deviation(c, d, speeds)}")
        print(f"                             per-speed {deviation(ref, d, speeds)}")


def main(argv=None):
    ap = common.parser(__doc__, repeat=5)
    ap.add_argument("--speeds", type=int, default=50)
    ap.add_argument("--scene", nargs="+", default=["paper_3amb", "rotor3m_3amb"])
    ap.add_argument("--ross-python", help="a Python that can import ross (default: this one, if it can)")
    ap.add_argument("--dense", action="store_true", help="compare with dense eigenvalues too (slow)")
    a = ap.parse_args(argv)
    common.header("campbell", "full-rung Campbell diagram: tracked, per-speed ARPACK, ROSS")
    ross_py = ross_python(a.ross_python)
    if ross_py is None:
        print("# ROSS is not installed here (pip install ross-rotordynamics in a Python >= 3.13 and pass "
              "--ross-python): ambhil's figures only")
    for scene in a.scene:
        one_scene(scene, a, ross_py)


if __name__ == "__main__":
    main()
