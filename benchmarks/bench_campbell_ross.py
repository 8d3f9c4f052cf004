"""Campbell diagram on the full rung against a general-purpose rotordynamics code on the same
rotor (issue 14: "no faster than a general-purpose rotordynamics code ... reach >= 20x").

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_campbell_ross.py --ross-python PY
        [--runs 5] [--speeds 50] [--scene scenes/paper_3amb.toml ...]

``PY`` is a Python with ROSS (``ross-rotordynamics``; 3.1.0 needs Python >= 3.13, so it lives in
a virtual environment of its own, e.g. ``python3.13 -m venv /tmp/rossvenv && /tmp/rossvenv/bin/pip
install ross-rotordynamics``; not a dependency of ambhil).  For each scene the same rotor is
built in ROSS from the compiled scene: one uniform ``ShaftElement`` per FE element
(Euler-Bernoulli with rotary inertia, as the scene), the discs as ``DiskElement``, each radial
AMB as a ``MagneticBearingElement`` with the scene's gap, bias, turns, pole area and angle,
sensor and amplifier gains, and the controller (PID with derivative filter, sensor and amplifier
lags) as its transfer function; the shaft's stiffness-proportional damping as the rotor's beta.
ROSS is timed warm (its first ``run_modal`` compiles with numba) on ``run_campbell`` over the
same speeds, asked for as many frequencies as the tracked diagram draws at rest.

Printed: ambhil's tracked Campbell (the full rung's default) and per-speed ARPACK path, and ROSS,
medians [min, max] over ``--runs`` (ambhil's runs before and after ROSS's, so a drift of the
machine falls on both), the ratios, and the lowest frequencies at rest in both codes, as a check
that the rotors are the same (ROSS evaluates the AMB coefficients at the spin speed and carries
no controller states, so the frequencies agree only roughly).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

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


def timed(fn, runs):
    fn()
    t = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return t


def fmt(t):
    return f"{statistics.median(t):.4f} [{min(t):.4f}, {max(t):.4f}] s"


def main():
    from ambhil.loop.analysis import modal
    from ambhil.loop.system import compile_system
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ross-python", required=True, help="a Python that can import ross")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--speeds", type=int, default=50)
    ap.add_argument("--scene", nargs="+", default=["scenes/paper_3amb.toml", "scenes/rotor3m_3amb.toml"])
    a = ap.parse_args()
    print(f"{a.runs} runs each, {a.speeds} speeds; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} cores")
    for scene in a.scene:
        m = compile_system(scene, rung="full")
        smax = m.scene.analysis.frequency_max
        speeds, fmax = np.linspace(0.0, smax, a.speeds), 1.1 * smax
        c = modal.campbell(m, speeds, fmax)
        rest = (c["speed"] == 0.0) & (c["zeta"] <= 0.5)
        nf = int(rest.sum())
        track = lambda: modal.campbell(m, speeds, fmax)                       # noqa: E731
        per = lambda: modal.campbell(m, speeds, fmax, method="per-speed")     # noqa: E731
        t_tr, t_ps = timed(track, a.runs), timed(per, a.runs)
        spec = rotor_spec(m, speeds, nf, a.runs)
        env = dict(os.environ, OPENBLAS_NUM_THREADS=os.environ.get("OPENBLAS_NUM_THREADS", "1"))
        r = subprocess.run([a.ross_python, "-W", "ignore", "-c", ROSS_SIDE], input=json.dumps(spec),
                           capture_output=True, text=True, env=env, timeout=3600)
        if r.returncode != 0:
            raise SystemExit(f"ROSS side failed: {r.stderr.strip()[-1500:]}")
        ross = json.loads(r.stdout.strip().splitlines()[-1])
        t_tr2 = timed(track, a.runs)
        t_all = t_tr + t_tr2
        print(f"{Path(scene).stem}: ambhil full rung {m.n} FE DOF + controller states; ROSS "
              f"{ross['ndof']} DOF; 0-{smax:g} rad/s, {nf} modes drawn at rest "
              f"(ROSS asked for frequencies={nf})")
        print(f"  ambhil tracked (default)  {fmt(t_all)}")
        print(f"  ambhil per-speed ARPACK   {fmt(t_ps)}")
        print(f"  ROSS run_campbell (warm)  {fmt(ross['times'])}")
        mt, mr, mp = statistics.median(t_all), statistics.median(ross["times"]), statistics.median(t_ps)
        print(f"  ratios of medians: ROSS / tracked {mr / mt:.1f}x, per-speed / tracked {mp / mt:.1f}x, "
              f"ROSS / per-speed {mr / mp:.1f}x")
        crit = [round(float(x.speed), 1) for x in modal.critical_speeds(m)[:4]]
        print(f"  forward critical speeds (1X crossings), rad/s: ambhil {crit}, ROSS's Campbell "
              f"{[round(x, 1) for x in ross['crossings'][:4]]} (interpolated on its {a.speeds} speeds)")
        ours = np.sort(c["freq"][rest])
        print(f"  lowest frequencies at rest, rad/s: ambhil {np.round(ours[:6], 1).tolist()}, ROSS "
              f"{np.round(ross['wd0'][:6], 1).tolist()} (AMB coefficients at 0 rad/s)")
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
