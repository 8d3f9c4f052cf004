"""Reproduce the tuning of the paper scenes (docs/paper.md).

Fits the shaft diameter, the wheel mass and width at node 30, the balance-piston mass at node 48
and the PID gains kp, kd of scenes/paper_2amb.toml so that its four critical speeds match the
paper's Table 2 and the first rigid critical has a damping ratio of 0.07.  Prints the fitted
values; it does not rewrite the scene files.

    .venv/bin/python scenes/tune_paper.py          (about a minute)
"""
from __future__ import annotations

import copy
import sys
import tomllib
from pathlib import Path

import numpy as np
import scipy.linalg as sla
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ambhil.loop.analysis import modal  # noqa: E402
from ambhil.loop.system import compile_system  # noqa: E402
from ambhil.plant.rotor import assemble  # noqa: E402
from ambhil.loop.scene import parse_scene  # noqa: E402

BASE = tomllib.load(open(ROOT / "scenes" / "paper_2amb.toml", "rb"))
TARGET = np.array(BASE["analysis"]["reference_criticals"])
R_WHEEL, R_PISTON, W_PISTON = 0.2, 0.18, 0.15


def scene(p, rung="modal"):
    D, m, w, m48, kp, kd = p
    d = copy.deepcopy(BASE)
    d["shaft"][0]["outer_diameter"] = D
    wheel, _, piston = d["disc"]
    wheel.update(mass=m, polar_inertia=m * R_WHEEL**2 / 2, diametral_inertia=m * (3 * R_WHEEL**2 + w**2) / 12)
    piston.update(mass=m48, polar_inertia=m48 * R_PISTON**2 / 2,
                  diametral_inertia=m48 * (3 * R_PISTON**2 + W_PISTON**2) / 12)
    d["controller"].update(kp=kp, kd=kd)
    d["model"]["rung"] = rung
    return parse_scene(d, "tune")


def free_forward_criticals(sc):
    """Forward synchronous criticals of the free rotor, one plane: K phi = W^2 (M - G_p) phi."""
    r = assemble(sc)
    n = r.ndof
    ix = np.sort(np.r_[np.arange(0, n, 4), np.arange(2, n, 4)])
    iy = np.sort(np.r_[np.arange(1, n, 4), np.arange(3, n, 4)])
    w2 = sla.eigvals(r.K[ix][:, ix].toarray(), r.M[ix][:, ix].toarray() - r.G[ix][:, iy].toarray())
    w2 = np.sort(w2.real[(np.abs(w2.imag) < 1e-6 * np.abs(w2)) & (w2.real > 1.0)])
    return np.sqrt(w2[:2]) / (2 * np.pi)


def rigid_criticals(sc):
    return modal.critical_speeds(compile_system(sc, rung="rigid"), count=2, speed_max=3000)


def main():
    p0 = np.array([0.15, 500.0, 0.65, 50.0, 3.0, 1.5e-3])
    lo = [0.08, 50, 0.2, 5, 0.1, 1e-5]
    hi = [0.25, 1500, 1.2, 400, 50, 0.05]

    def geometry(g):
        sc = scene(np.r_[g, p0[4:]])
        f, r = free_forward_criticals(sc), rigid_criticals(sc)
        return np.log([f[0] / TARGET[2], f[1] / TARGET[3], (r[1].hz / r[0].hz) / (TARGET[1] / TARGET[0])])

    g = least_squares(geometry, p0[:4], bounds=(lo[:4], hi[:4]), x_scale=p0[:4], diff_step=1e-3).x

    def gains(k):
        cs = rigid_criticals(scene(np.r_[g, k]))
        return [np.log(cs[0].hz / TARGET[0]), np.log(cs[1].hz / TARGET[1]), 0.3 * (cs[0].damping_ratio - 0.07)]

    k = least_squares(gains, p0[4:], bounds=(lo[4:], hi[4:]), x_scale=p0[4:], diff_step=1e-3).x

    def everything(p):
        cs = modal.critical_speeds(compile_system(scene(p)), count=4, speed_max=6000)
        f = np.array([c.hz for c in cs] + [3000.0] * (4 - len(cs)))
        return np.r_[np.log(f / TARGET), 0.3 * (cs[0].damping_ratio - 0.07)]

    p1 = np.r_[g, k]
    p = least_squares(everything, p1, bounds=(lo, hi), x_scale=np.abs(p1), diff_step=1e-3, max_nfev=40).x
    cs = modal.critical_speeds(compile_system(scene(p, "full")), count=4)
    for name, v in zip(("outer_diameter", "wheel mass", "wheel width", "piston mass", "kp", "kd"), p):
        print(f"{name:15s} {v:.6g}")
    print("critical speeds (full rung, Hz):", ", ".join(f"{c.hz:.2f}" for c in cs), " target:", TARGET)


if __name__ == "__main__":
    main()
