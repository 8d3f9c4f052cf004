"""Energies and angular momentum of an ANCF state (``plant/ancf_model.py``): the checks of the
element and the integrators (conservation without damping, ``v^T M v / 2``)."""
from __future__ import annotations

import numpy as np

from . import ancf_beam as ab
from . import ancf_disc as ad
from .ancf_model import ANCFArrays, speed_profile


def strain_energy(S: ANCFArrays, q) -> float:
    U = 0.0
    for e in range(S.conn.shape[0]):
        i, j = S.conn[e]
        U += ab.element_energy(np.concatenate([q[8 * i:8 * i + 8], q[8 * j:8 * j + 8]]), S.prm[e])
    return U


def kinetic_energy(S: ANCFArrays, q, v, t: float = 0.0) -> float:
    """T = 1/2 v^T M(q) v (beam translational Hermite mass + nodal rigid bodies, base spin
    included)."""
    W = speed_profile(S.spin, t)[1]
    nn = S.nJ.shape[0]
    T = 0.0
    for e in range(S.conn.shape[0]):
        i, j = S.conn[e]
        qe = np.concatenate([q[8 * i:8 * i + 8], q[8 * j:8 * j + 8]])
        ve = np.concatenate([v[8 * i:8 * i + 8], v[8 * j:8 * j + 8]])
        f = np.zeros(16)
        p = S.prm[e].copy(); p[ab.P_EA] = p[ab.P_EI] = p[ab.P_GJ] = 0.0; p[ab.P_BETA] = 0.0; p[ab.P_ALPHA] = 0.0
        p[ab.P_GX:ab.P_GZ + 1] = 0.0
        # M(q) v: the inertia term with a = v and the quadratic-velocity part removed
        f1 = np.zeros(16); ab.element_force(qe, np.zeros(16), ve, p, 1.0, f1)
        T += 0.5 * float(ve @ f1)
    for i in range(nn):
        T += ad.kinetic_energy(q[8 * i:8 * i + 8], v[8 * i:8 * i + 8], S.nJ[i], S.nm[i], W)
    return T


def angular_momentum(S: ANCFArrays, q, v, t: float = 0.0) -> np.ndarray:
    """Angular momentum about the origin (fixed frame): nodal rigid bodies exactly, the beam's
    translational part as sum of (y-space) Hermite mass moments r x (M_h r') over the centreline
    sampled at the element's Gauss points (exact for the consistent mass: computed as
    int rhoA r x r' dx with 6-point Gauss quadrature)."""
    H = np.zeros(3)
    nn = S.nJ.shape[0]
    W = speed_profile(S.spin, t)[1]
    gx, gw = np.polynomial.legendre.leggauss(6)
    xi = 0.5 * (gx + 1); w = 0.5 * gw
    for e in range(S.conn.shape[0]):
        i, j = S.conn[e]
        l, rhoA = S.prm[e, ab.P_L], S.prm[e, ab.P_RHOA]
        Y, Yd = _Y(q, v, i, j)
        for x_, w_ in zip(xi, w):
            Sh = np.array([1 - 3 * x_**2 + 2 * x_**3, l * (x_ - 2 * x_**2 + x_**3), 3 * x_**2 - 2 * x_**3, l * (-x_**2 + x_**3)])
            r = Sh @ Y; rd = Sh @ Yd
            H += rhoA * l * w_ * np.cross(r, rd)
    for i in range(nn):
        th = q[8 * i + 4:8 * i + 8]; thd = v[8 * i + 4:8 * i + 8]
        wb = ad.body_rate(th, thd, W)
        A = ab.rotation_matrix(th)
        H += A @ (S.nJ[i] * wb) + S.nm[i] * np.cross(q[8 * i:8 * i + 3], v[8 * i:8 * i + 3])
    return H


def _Y(q, v, i, j):
    Y = np.zeros((4, 3)); Yd = np.zeros((4, 3))
    for n_, k in enumerate((i, j)):
        qn, vn = q[8 * k:8 * k + 8], v[8 * k:8 * k + 8]
        th, thd = qn[4:], vn[4:]
        t = np.array(ab.axis_e3(*th))
        T = np.zeros((3, 4)); ab.axis_e3_jac(*th, T)
        Y[2 * n_] = qn[:3]; Yd[2 * n_] = vn[:3]
        Y[2 * n_ + 1] = (1 + qn[3]) * t
        Yd[2 * n_ + 1] = vn[3] * t + (1 + qn[3]) * T @ thd
    return Y, Yd
