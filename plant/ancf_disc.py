"""Rigid bodies riding on ANCF nodes: the lumped rotary inertia of the shaft sections and the
rigid discs of the scene (paper eq. 6), with Euler parameters.

A disc is attached rigidly to its node: its Euler parameters are the node's ``theta`` (the
attachment ``p_d = theta_i (x) q_offset`` with ``q_offset = 1`` eliminated by substitution) and
its centre is the node's ``r``.  Per node, with body inertia ``J = diag(J_d, J_d, J_p)`` (spin
axis ``e3``) and mass ``m``, the inertial force is

    m r''                                 (translation)
    4 G^T J G theta'' - 8 G(theta')^T J G(theta') theta      (rotation; body rate w = 2 G theta')

which is Lagrange's equation of ``T = 1/2 m |r'|^2 + 1/2 (2 G theta')^T J (2 G theta')``; the
quaternion normalisation constraint (in ``plant/ancf_model.py``) makes the rank-3 rotational
mass regular.

Base spin: the node's attitude is ``theta (x) s(t)`` with ``s(t)`` the rotation by the prescribed
spin angle ``phi(t)`` about the body axis e3 (an exact change of variables: ``A e3`` and the
element's twist do not depend on ``s``, and ``J`` is axisymmetric).  The body rate becomes
``2 G theta' + Omega e3`` and Lagrange's equations gain ``4 Omega J_p P theta' + 2 Omega' J_p P
theta`` with the constant skew matrix ``P`` (``G(theta)^T e3 = P theta``): the gyroscopic
coupling of the spinning rotor, derived from its kinetic energy.  ``theta`` then stays near
identity and an implicit integrator does not damp the spin itself (integrating the raw spinning
quaternions with BDF1 drags the spin down at a rate of about Omega^2 h / 8).  Gyroscopic coupling is not added as a matrix: it is the quadratic-velocity term.
"""
from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def G_times(w, x, y, z, a0, a1, a2, a3):
    """G(theta) a for a 4-vector a (G = [-v, w I - [v]x])."""
    return (-x * a0 + w * a1 - (y * a3 - z * a2),
            -y * a0 + w * a2 - (z * a1 - x * a3),
            -z * a0 + w * a3 - (x * a2 - y * a1))


@nb.njit(cache=True)
def GT_times(w, x, y, z, m0, m1, m2):
    """G(theta)^T m for a 3-vector m."""
    return (-(x * m0 + y * m1 + z * m2),
            w * m0 + (y * m2 - z * m1),
            w * m1 + (z * m0 - x * m2),
            w * m2 + (x * m1 - y * m0))


@nb.njit(cache=True)
def ET_times(w, x, y, z, m0, m1, m2):
    """E(theta)^T m for a 3-vector m (E = [-v, w I + [v]x]): the generalised force of a spatial
    moment m acting on a node (virtual work m . 2 E dtheta)."""
    return (-(x * m0 + y * m1 + z * m2),
            w * m0 - (y * m2 - z * m1),
            w * m1 - (z * m0 - x * m2),
            w * m2 - (x * m1 - y * m0))


@nb.njit(cache=True)
def node_inertia(qn, vn, an, J, mass, ci, alpha, W, Wd, out):
    """out (8) += inertial force of the node's rigid body (+ alpha m r' translational damping).
    ``W``, ``Wd``: prescribed base spin and its rate (the node attitude is theta (x) spin(t))."""
    for c in range(3):
        out[c] += mass * (ci * an[c] + alpha * vn[c])
    if ci == 0.0:
        return
    w, x, y, z = qn[4], qn[5], qn[6], qn[7]
    # 4 G^T J G theta''
    g0, g1, g2 = G_times(w, x, y, z, an[4], an[5], an[6], an[7])
    r0, r1, r2, r3 = GT_times(w, x, y, z, J[0] * g0, J[1] * g1, J[2] * g2)
    # - 8 G(theta')^T J G(theta') theta
    wd, xd, yd, zd = vn[4], vn[5], vn[6], vn[7]
    h0, h1, h2 = G_times(wd, xd, yd, zd, w, x, y, z)
    s0, s1, s2, s3 = GT_times(wd, xd, yd, zd, J[0] * h0, J[1] * h1, J[2] * h2)
    out[4] += ci * (4.0 * r0 - 8.0 * s0)
    out[5] += ci * (4.0 * r1 - 8.0 * s1)
    out[6] += ci * (4.0 * r2 - 8.0 * s2)
    out[7] += ci * (4.0 * r3 - 8.0 * s3)
    if W != 0.0 or Wd != 0.0:
        # base spin: T gains 2 W J_p (P theta) . theta', P theta = (-z, y, -x, w) (P skew):
        # Lagrange gives 4 W J_p P theta' + 2 W' J_p P theta
        jp = ci * J[2]
        out[4] += jp * (4.0 * W * (-zd) + 2.0 * Wd * (-z))
        out[5] += jp * (4.0 * W * yd + 2.0 * Wd * y)
        out[6] += jp * (4.0 * W * (-xd) + 2.0 * Wd * (-x))
        out[7] += jp * (4.0 * W * wd + 2.0 * Wd * w)


def body_rate(th, thd, W: float = 0.0) -> np.ndarray:
    """Body angular velocity 2 G(theta) theta' + W e3 (W: base spin)."""
    return 2.0 * np.array(G_times(*th, *thd)) + np.array([0.0, 0.0, W])


def kinetic_energy(qn, vn, J, mass, W: float = 0.0) -> float:
    w = body_rate(qn[4:8], vn[4:8], W)
    return 0.5 * mass * float(vn[:3] @ vn[:3]) + 0.5 * float(w @ (np.asarray(J) * w))
