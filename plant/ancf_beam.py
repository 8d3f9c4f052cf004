"""Quaternion ANCF Euler-Bernoulli beam element (after Zhao & Ren 2012; see docs/ancf.md).

Node coordinates (8): ``[r (3), eps, theta (4)]``: position of the centreline, axial strain and
the Euler parameters of the cross-section.  The local beam axis is the third material axis
``e3`` (the rotor's spin axis, +z in the reference configuration).  Element coordinates (16):
node 1 then node 2.

Kinematics (coupled position-orientation interpolation): the nodal slope is

    d_i = r'_i = (1 + eps_i) A(theta_i) e3,

so the section stays perpendicular to the centreline at the nodes, and the centreline is the
cubic Hermite interpolation of ``y = [r1, d1, r2, d2]`` on the reference length ``l``.  ``A`` is
the homogeneous rotation matrix of the Euler parameters (a rotation for unit ``theta``).

Strains at a point (``a = r'``, ``b = r''`` from the Hermite interpolation):

* axial ``e = |a| - 1``;
* bending: the rotation rate of the tangent per unit reference length, ``kappa = a x b / |a|^2``
  (fixed-frame vector; the sections of this project are circular, so ``EI`` is isotropic and
  the energy needs only ``|kappa|``);
* torsion: the twist ``psi`` between the two nodal frames after the first frame has been carried
  onto the second tangent by the minimal rotation (discrete parallel transport), constant
  along the element, ``tau = psi / l``.

Energy ``U = 1/2 int (EA e^2 + EI |kappa|^2) dx + 1/2 GJ psi^2 / l`` (4 Gauss points).
Material damping (Kelvin-Voigt with coefficient ``beta``): the stresses are
``EA (e + beta e')``, ``EI (kappa + beta kappa')`` and ``GJ (psi + beta psi') / l``, with
``kappa'`` the rate of the fixed-frame curvature: in small motion this is exactly the linear
rungs' stiffness-proportional damping ``beta K`` (non-rotating, no circulatory force at speed).

Inertia: the translational kinetic energy uses the consistent (Hermite) mass of ``y``; as ``y``
depends on ``(eps, theta)`` through ``d_i``, the generalised mass matrix ``B^T M_h B`` depends on
the configuration and the quadratic-velocity term ``B^T M_h (dB/dt) v`` appears.  The rotary
inertia of the sections is lumped at the nodes (``plant/ancf_disc.py``).

Everything here is written for float64 and complex128 inputs alike: the element Jacobians are
obtained by the complex-step method (exact to rounding; tests/test_ancf.py checks them against
finite differences).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

# element parameter vector layout; reference (stress-free) state of an initially curved element:
# axial strain at the 4 Gauss points (P_E0..), material curvature at the Gauss points (P_K0, 4 x 3),
# twist (P_PSI0) and a flag (P_CURVED) that switches the reference terms on
P_L, P_EA, P_EI, P_GJ, P_RHOA, P_BETA, P_ALPHA, P_GX, P_GY, P_GZ = range(10)
P_E0 = 10
P_K0 = 14
P_PSI0 = 26
P_CURVED = 27
P_LEN = 28

_GX = np.array([0.5 - 0.5 * 0.8611363115940526, 0.5 - 0.5 * 0.3399810435848563,
                0.5 + 0.5 * 0.3399810435848563, 0.5 + 0.5 * 0.8611363115940526])
_GW = np.array([0.5 * 0.3478548451374538, 0.5 * 0.6521451548625461,
                0.5 * 0.6521451548625461, 0.5 * 0.3478548451374538])


# --------------------------------------------------------------------------- quaternion algebra
@nb.njit(cache=True)
def qmul(a0, a1, a2, a3, b0, b1, b2, b3):
    """Quaternion product a (x) b."""
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
            a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
            a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


@nb.njit(cache=True)
def axis_e3(w, x, y, z):
    """t = A(theta) e3 (homogeneous form: |theta|^2 times the unit vector)."""
    return 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), w * w - x * x - y * y + z * z


@nb.njit(cache=True)
def axis_e3_jac(w, x, y, z, T):
    """T = d(A e3)/d theta (3 x 4), linear in theta (so A e3 = T theta / 2)."""
    T[0, 0] = 2 * y; T[0, 1] = 2 * z; T[0, 2] = 2 * w; T[0, 3] = 2 * x
    T[1, 0] = -2 * x; T[1, 1] = -2 * w; T[1, 2] = 2 * z; T[1, 3] = 2 * y
    T[2, 0] = 2 * w; T[2, 1] = -2 * x; T[2, 2] = -2 * y; T[2, 3] = 2 * z


def rotation_matrix(th) -> np.ndarray:
    """A(theta) = (w^2 - v.v) I + 2 v v^T + 2 w [v]x (numpy, for analysis and tests)."""
    w, x, y, z = th
    v = np.array([x, y, z])
    vx = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return (w * w - v @ v) * np.eye(3) + 2 * np.outer(v, v) + 2 * w * vx


def G_matrix(th) -> np.ndarray:
    """G(theta) = [-v, w I - [v]x]: body angular velocity = 2 G theta'."""
    w, x, y, z = th
    vx = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.column_stack([-np.array([x, y, z]), w * np.eye(3) - vx])


def E_matrix(th) -> np.ndarray:
    """E(theta) = [-v, w I + [v]x]: spatial angular velocity = 2 E theta'."""
    w, x, y, z = th
    vx = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.column_stack([-np.array([x, y, z]), w * np.eye(3) + vx])


# --------------------------------------------------------------------------- Hermite shape functions
@nb.njit(cache=True)
def _dshape(xi, l, d1, d2):
    """First and second x-derivatives of the Hermite functions [S1..S4] at xi."""
    d1[0] = (-6 * xi + 6 * xi * xi) / l
    d1[1] = 1 - 4 * xi + 3 * xi * xi
    d1[2] = (6 * xi - 6 * xi * xi) / l
    d1[3] = -2 * xi + 3 * xi * xi
    d2[0] = (-6 + 12 * xi) / (l * l)
    d2[1] = (-4 + 6 * xi) / l
    d2[2] = (6 - 12 * xi) / (l * l)
    d2[3] = (-2 + 6 * xi) / l


def hermite_mass(l: float) -> np.ndarray:
    """Consistent mass of the Hermite cubic per unit rho A, scalar 4 x 4 on [r1, d1, r2, d2]."""
    return l * np.array([
        [13 / 35, 11 * l / 210, 9 / 70, -13 * l / 420],
        [11 * l / 210, l * l / 105, 13 * l / 420, -l * l / 140],
        [9 / 70, 13 * l / 420, 13 / 35, -11 * l / 210],
        [-13 * l / 420, -l * l / 140, -11 * l / 210, l * l / 105],
    ])


# --------------------------------------------------------------------------- element kernel
@nb.njit(cache=True)
def _slopes(qe, ve, ae, dY, vY, aY, T1, T2, with_acc):
    """Y = [r1, d1, r2, d2] (4 x 3), its rate and (with_acc) its second rate, plus T_i."""
    for n in range(2):
        o = 8 * n
        eps = qe[o + 3]
        w, x, y, z = qe[o + 4], qe[o + 5], qe[o + 6], qe[o + 7]
        t0, t1, t2 = axis_e3(w, x, y, z)
        T = T1 if n == 0 else T2
        axis_e3_jac(w, x, y, z, T)
        for c in range(3):
            dY[2 * n, c] = qe[o + c]
            dY[2 * n + 1, c] = (1.0 + eps) * (t0 if c == 0 else (t1 if c == 1 else t2))
        ed = ve[o + 3]
        for c in range(3):
            vY[2 * n, c] = ve[o + c]
            tc = t0 if c == 0 else (t1 if c == 1 else t2)
            Tth = T[c, 0] * ve[o + 4] + T[c, 1] * ve[o + 5] + T[c, 2] * ve[o + 6] + T[c, 3] * ve[o + 7]
            vY[2 * n + 1, c] = ed * tc + (1.0 + eps) * Tth
        if with_acc:
            # d'' = eps'' t + 2 eps' T theta' + (1 + eps) (T theta'' + T(theta') theta')
            wd, xd, yd, zd = ve[o + 4], ve[o + 5], ve[o + 6], ve[o + 7]
            s0, s1, s2 = axis_e3(wd, xd, yd, zd)  # T(theta') theta' = 2 A(theta') e3
            ea = ae[o + 3]
            for c in range(3):
                aY[2 * n, c] = ae[o + c]
                tc = t0 if c == 0 else (t1 if c == 1 else t2)
                sc = s0 if c == 0 else (s1 if c == 1 else s2)
                Tth = T[c, 0] * ve[o + 4] + T[c, 1] * ve[o + 5] + T[c, 2] * ve[o + 6] + T[c, 3] * ve[o + 7]
                Tta = T[c, 0] * ae[o + 4] + T[c, 1] * ae[o + 5] + T[c, 2] * ae[o + 6] + T[c, 3] * ae[o + 7]
                aY[2 * n + 1, c] = ea * tc + 2.0 * ed * Tth + (1.0 + eps) * (Tta + 2.0 * sc)


@nb.njit(cache=True)
def _twist(qe, ve, gq, GJl, beta, psi0):
    """Torsion: psi (and its rate); adds the generalised torsion forces to gq (16); returns psi."""
    a0, a1, a2, a3 = qe[4], qe[5], qe[6], qe[7]
    b0, b1, b2, b3 = qe[12], qe[13], qe[14], qe[15]
    t1x, t1y, t1z = axis_e3(a0, a1, a2, a3)
    t2x, t2y, t2z = axis_e3(b0, b1, b2, b3)
    # minimal rotation t1 -> t2 (unnormalised): p = [1 + t1.t2, t1 x t2]
    p0 = 1.0 + t1x * t2x + t1y * t2y + t1z * t2z
    p1 = t1y * t2z - t1z * t2y
    p2 = t1z * t2x - t1x * t2z
    p3 = t1x * t2y - t1y * t2x
    # u = conj(theta1) (x) conj(p) (x) theta2 = [cos psi/2, 0, 0, sin psi/2] * scale
    k0, k1, k2, k3 = qmul(a0, -a1, -a2, -a3, p0, -p1, -p2, -p3)
    u0, u1, u2, u3 = qmul(k0, k1, k2, k3, b0, b1, b2, b3)
    psi = 2.0 * np.arctan(u3 / u0)
    den = u0 * u0 + u3 * u3
    # rates: same chain with the rates of theta1, theta2, p
    da0, da1, da2, da3 = ve[4], ve[5], ve[6], ve[7]
    db0, db1, db2, db3 = ve[12], ve[13], ve[14], ve[15]
    T1 = np.zeros((3, 4), dtype=qe.dtype)
    T2 = np.zeros((3, 4), dtype=qe.dtype)
    axis_e3_jac(a0, a1, a2, a3, T1)
    axis_e3_jac(b0, b1, b2, b3, T2)
    dt1 = T1[:, 0] * da0 + T1[:, 1] * da1 + T1[:, 2] * da2 + T1[:, 3] * da3
    dt2 = T2[:, 0] * db0 + T2[:, 1] * db1 + T2[:, 2] * db2 + T2[:, 3] * db3
    dp0 = dt1[0] * t2x + dt1[1] * t2y + dt1[2] * t2z + t1x * dt2[0] + t1y * dt2[1] + t1z * dt2[2]
    dp1 = dt1[1] * t2z - dt1[2] * t2y + t1y * dt2[2] - t1z * dt2[1]
    dp2 = dt1[2] * t2x - dt1[0] * t2z + t1z * dt2[0] - t1x * dt2[2]
    dp3 = dt1[0] * t2y - dt1[1] * t2x + t1x * dt2[1] - t1y * dt2[0]
    e0, e1, e2, e3 = qmul(da0, -da1, -da2, -da3, p0, -p1, -p2, -p3)
    f0, f1, f2, f3 = qmul(a0, -a1, -a2, -a3, dp0, -dp1, -dp2, -dp3)
    dk0, dk3 = e0 + f0, e3 + f3
    dk1, dk2 = e1 + f1, e2 + f2
    g0, g1, g2, g3 = qmul(dk0, dk1, dk2, dk3, b0, b1, b2, b3)
    h0, h1, h2, h3 = qmul(k0, k1, k2, k3, db0, db1, db2, db3)
    du0, du3 = g0 + h0, g3 + h3
    psid = 2.0 * (u0 * du3 - u3 * du0) / den
    # generalised force: T * dpsi/dq with T = GJ/l (psi + beta psi')
    tq = GJl * (psi - psi0 + beta * psid)
    gu0, gu3 = tq * 2.0 * (-u3) / den, tq * 2.0 * u0 / den
    # u = k (x) theta2: g_theta2 = conj(k) (x) g_u ; g_k = g_u (x) conj(theta2)
    r0, r1, r2, r3 = qmul(k0, -k1, -k2, -k3, gu0, 0.0 * gu0, 0.0 * gu0, gu3)
    gq[12] += r0; gq[13] += r1; gq[14] += r2; gq[15] += r3
    gk0, gk1, gk2, gk3 = qmul(gu0, 0.0 * gu0, 0.0 * gu0, gu3, b0, -b1, -b2, -b3)
    # k = c1 (x) cp: g_c1 = g_k (x) conj(cp) = g_k (x) p ; g_cp = conj(c1) (x) g_k = theta1 (x) g_k
    c0, c1, c2, c3 = qmul(gk0, gk1, gk2, gk3, p0, p1, p2, p3)
    gq[4] += c0; gq[5] -= c1; gq[6] -= c2; gq[7] -= c3  # conj: c1 = conj(theta1)
    s0, s1, s2, s3 = qmul(a0, a1, a2, a3, gk0, gk1, gk2, gk3)
    gp0, gp1, gp2, gp3 = s0, -s1, -s2, -s3  # cp = conj(p)
    # p = [1 + t1.t2, t1 x t2]
    gt1x = gp0 * t2x + (t2y * gp3 - t2z * gp2)
    gt1y = gp0 * t2y + (t2z * gp1 - t2x * gp3)
    gt1z = gp0 * t2z + (t2x * gp2 - t2y * gp1)
    gt2x = gp0 * t1x + (gp2 * t1z - gp3 * t1y)
    gt2y = gp0 * t1y + (gp3 * t1x - gp1 * t1z)
    gt2z = gp0 * t1z + (gp1 * t1y - gp2 * t1x)
    for j in range(4):
        gq[4 + j] += T1[0, j] * gt1x + T1[1, j] * gt1y + T1[2, j] * gt1z
        gq[12 + j] += T2[0, j] * gt2x + T2[1, j] * gt2y + T2[2, j] * gt2z
    return psi


# One function on purpose: element_force is the ANCF rung's innermost kernel, evaluated 16 times
# per element per Jacobian (complex step) and generic over float64 and complex128; its Gauss-point
# loop shares a dozen scalars between the stretch, curvature, damping and reference-curvature
# terms, which helpers would pass back and forth as tuples.  Kept whole for speed and so that the
# numbers stay bit-identical; the stages are marked by comments.
@nb.njit(cache=True)
def element_force(qe, ve, ae, prm, ci, out):
    """Generalised element force ``out`` (16) = inertia (times ci) + elastic + damping - gravity:
    the element's part of ``M(q) q'' + Q_v - Q(q, q')``.  Generic over float64 / complex128."""
    l = prm[P_L]
    EA, EI, GJ, rhoA, beta, alpha = prm[P_EA], prm[P_EI], prm[P_GJ], prm[P_RHOA], prm[P_BETA], prm[P_ALPHA]
    Y = np.zeros((4, 3), dtype=qe.dtype)
    vY = np.zeros((4, 3), dtype=qe.dtype)
    aY = np.zeros((4, 3), dtype=qe.dtype)
    T1 = np.zeros((3, 4), dtype=qe.dtype)
    T2 = np.zeros((3, 4), dtype=qe.dtype)
    _slopes(qe, ve, ae, Y, vY, aY, T1, T2, ci != 0.0)
    gY = np.zeros((4, 3), dtype=qe.dtype)  # generalised force on Y
    # inertia (consistent Hermite mass) + mass-proportional damping + gravity
    if ci != 0.0 or alpha != 0.0:
        Mh = hermite_mass_nb(l)
        for i in range(4):
            for j in range(4):
                m = rhoA * Mh[i, j]
                for c in range(3):
                    gY[i, c] += m * (ci * aY[j, c] + alpha * vY[j, c])
    gx, gy, gz = prm[P_GX], prm[P_GY], prm[P_GZ]
    if gx != 0.0 or gy != 0.0 or gz != 0.0:
        wts = (0.5 * l, l * l / 12.0, 0.5 * l, -l * l / 12.0)
        for i in range(4):
            gY[i, 0] -= rhoA * wts[i] * gx
            gY[i, 1] -= rhoA * wts[i] * gy
            gY[i, 2] -= rhoA * wts[i] * gz
    # elastic + Kelvin-Voigt damping, Gauss quadrature
    d1 = np.zeros(4); d2 = np.zeros(4)
    gth = np.zeros(8, dtype=qe.dtype)  # direct forces on theta1, theta2 (reference curvature)
    for g in range(4):
        _dshape(_GX[g], l, d1, d2)
        wl = _GW[g] * l
        a0 = d1[0] * Y[0, 0] + d1[1] * Y[1, 0] + d1[2] * Y[2, 0] + d1[3] * Y[3, 0]
        a1 = d1[0] * Y[0, 1] + d1[1] * Y[1, 1] + d1[2] * Y[2, 1] + d1[3] * Y[3, 1]
        a2 = d1[0] * Y[0, 2] + d1[1] * Y[1, 2] + d1[2] * Y[2, 2] + d1[3] * Y[3, 2]
        b0 = d2[0] * Y[0, 0] + d2[1] * Y[1, 0] + d2[2] * Y[2, 0] + d2[3] * Y[3, 0]
        b1 = d2[0] * Y[0, 1] + d2[1] * Y[1, 1] + d2[2] * Y[2, 1] + d2[3] * Y[3, 1]
        b2 = d2[0] * Y[0, 2] + d2[1] * Y[1, 2] + d2[2] * Y[2, 2] + d2[3] * Y[3, 2]
        n2 = a0 * a0 + a1 * a1 + a2 * a2
        na = np.sqrt(n2)
        e = na - 1.0
        k0 = (a1 * b2 - a2 * b1) / n2
        k1 = (a2 * b0 - a0 * b2) / n2
        k2 = (a0 * b1 - a1 * b0) / n2
        N = EA * e
        m0, m1, m2 = EI * k0, EI * k1, EI * k2
        if prm[P_CURVED] != 0.0:
            # reference curvature: energy 1/2 EI |kappa - A(th^) kappa0|^2 with the section frame
            # A(th^) of the normalised linear interpolation of the nodal Euler parameters
            N -= EA * prm[P_E0 + g]
            xi = _GX[g]
            c0, c1, c2 = _ref_curvature(qe, xi, prm[P_K0 + 3 * g], prm[P_K0 + 3 * g + 1], prm[P_K0 + 3 * g + 2])
            m0 -= EI * c0; m1 -= EI * c1; m2 -= EI * c2
        if beta != 0.0:
            ad0 = d1[0] * vY[0, 0] + d1[1] * vY[1, 0] + d1[2] * vY[2, 0] + d1[3] * vY[3, 0]
            ad1 = d1[0] * vY[0, 1] + d1[1] * vY[1, 1] + d1[2] * vY[2, 1] + d1[3] * vY[3, 1]
            ad2 = d1[0] * vY[0, 2] + d1[1] * vY[1, 2] + d1[2] * vY[2, 2] + d1[3] * vY[3, 2]
            bd0 = d2[0] * vY[0, 0] + d2[1] * vY[1, 0] + d2[2] * vY[2, 0] + d2[3] * vY[3, 0]
            bd1 = d2[0] * vY[0, 1] + d2[1] * vY[1, 1] + d2[2] * vY[2, 1] + d2[3] * vY[3, 1]
            bd2 = d2[0] * vY[0, 2] + d2[1] * vY[1, 2] + d2[2] * vY[2, 2] + d2[3] * vY[3, 2]
            aad = a0 * ad0 + a1 * ad1 + a2 * ad2
            N += EA * beta * aad / na
            kd0 = (ad1 * b2 - ad2 * b1 + a1 * bd2 - a2 * bd1) / n2 - 2.0 * k0 * aad / n2
            kd1 = (ad2 * b0 - ad0 * b2 + a2 * bd0 - a0 * bd2) / n2 - 2.0 * k1 * aad / n2
            kd2 = (ad0 * b1 - ad1 * b0 + a0 * bd1 - a1 * bd0) / n2 - 2.0 * k2 * aad / n2
            m0 += EI * beta * kd0
            m1 += EI * beta * kd1
            m2 += EI * beta * kd2
        if prm[P_CURVED] != 0.0:
            _ref_curvature_grad(qe, _GX[g], prm[P_K0 + 3 * g], prm[P_K0 + 3 * g + 1], prm[P_K0 + 3 * g + 2],
                                -wl * m0, -wl * m1, -wl * m2, gth)
        # dU/da = N a/|a| + (b x m)/n2 - 2 (kappa.m) a/n2 ; dU/db = (m x a)/n2
        km = k0 * m0 + k1 * m1 + k2 * m2
        fa = N / na - 2.0 * km / n2
        ga0 = fa * a0 + (b1 * m2 - b2 * m1) / n2
        ga1 = fa * a1 + (b2 * m0 - b0 * m2) / n2
        ga2 = fa * a2 + (b0 * m1 - b1 * m0) / n2
        gb0 = (m1 * a2 - m2 * a1) / n2
        gb1 = (m2 * a0 - m0 * a2) / n2
        gb2 = (m0 * a1 - m1 * a0) / n2
        for i in range(4):
            gY[i, 0] += wl * (d1[i] * ga0 + d2[i] * gb0)
            gY[i, 1] += wl * (d1[i] * ga1 + d2[i] * gb1)
            gY[i, 2] += wl * (d1[i] * ga2 + d2[i] * gb2)
    # Y -> q: r_i direct; d_i = (1 + eps_i) t_i(theta_i)
    for k in range(16):
        out[k] = 0.0
    for n in range(2):
        o = 8 * n
        T = T1 if n == 0 else T2
        eps = qe[o + 3]
        w, x, y, z = qe[o + 4], qe[o + 5], qe[o + 6], qe[o + 7]
        t0, t1, t2 = axis_e3(w, x, y, z)
        for c in range(3):
            out[o + c] += gY[2 * n, c]
        gd0, gd1, gd2 = gY[2 * n + 1, 0], gY[2 * n + 1, 1], gY[2 * n + 1, 2]
        out[o + 3] += gd0 * t0 + gd1 * t1 + gd2 * t2
        for j in range(4):
            out[o + 4 + j] += (1.0 + eps) * (T[0, j] * gd0 + T[1, j] * gd1 + T[2, j] * gd2)
    for j in range(4):
        out[4 + j] += gth[j]
        out[12 + j] += gth[4 + j]
    if GJ != 0.0:
        _twist(qe, ve, out, GJ / l, beta, prm[P_PSI0])


@nb.njit(cache=True)
def _ref_curvature(qe, xi, r0, r1, r2):
    """A(w) kappa0 / |w|^2 with w = (1 - xi) theta1 + xi theta2 (A homogeneous quadratic)."""
    w0 = (1 - xi) * qe[4] + xi * qe[12]
    w1 = (1 - xi) * qe[5] + xi * qe[13]
    w2 = (1 - xi) * qe[6] + xi * qe[14]
    w3 = (1 - xi) * qe[7] + xi * qe[15]
    nw = w0 * w0 + w1 * w1 + w2 * w2 + w3 * w3
    vv = w1 * r0 + w2 * r1 + w3 * r2
    s = w0 * w0 - (w1 * w1 + w2 * w2 + w3 * w3)
    c0 = s * r0 + 2 * w1 * vv + 2 * w0 * (w2 * r2 - w3 * r1)
    c1 = s * r1 + 2 * w2 * vv + 2 * w0 * (w3 * r0 - w1 * r2)
    c2 = s * r2 + 2 * w3 * vv + 2 * w0 * (w1 * r1 - w2 * r0)
    return c0 / nw, c1 / nw, c2 / nw


@nb.njit(cache=True)
def _ref_curvature_grad(qe, xi, r0, r1, r2, m0, m1, m2, gth):
    """gth += d/dtheta [m . A(w) kappa0 / |w|^2] (m held fixed)."""
    w0 = (1 - xi) * qe[4] + xi * qe[12]
    w1 = (1 - xi) * qe[5] + xi * qe[13]
    w2 = (1 - xi) * qe[6] + xi * qe[14]
    w3 = (1 - xi) * qe[7] + xi * qe[15]
    nw = w0 * w0 + w1 * w1 + w2 * w2 + w3 * w3
    mv = m0 * r0 + m1 * r1 + m2 * r2
    wv = w1 * r0 + w2 * r1 + w3 * r2
    mw = m0 * w1 + m1 * w2 + m2 * w3
    vxm0, vxm1, vxm2 = r1 * m2 - r2 * m1, r2 * m0 - r0 * m2, r0 * m1 - r1 * m0
    s = (w0 * w0 - (w1 * w1 + w2 * w2 + w3 * w3)) * mv + 2 * mw * wv + 2 * w0 * (w1 * vxm0 + w2 * vxm1 + w3 * vxm2)
    g0 = 2 * w0 * mv + 2 * (w1 * vxm0 + w2 * vxm1 + w3 * vxm2)
    g1 = -2 * w1 * mv + 2 * m0 * wv + 2 * mw * r0 + 2 * w0 * vxm0
    g2 = -2 * w2 * mv + 2 * m1 * wv + 2 * mw * r1 + 2 * w0 * vxm1
    g3 = -2 * w3 * mv + 2 * m2 * wv + 2 * mw * r2 + 2 * w0 * vxm2
    f = 2 * s / (nw * nw)
    G0, G1, G2, G3 = g0 / nw - f * w0, g1 / nw - f * w1, g2 / nw - f * w2, g3 / nw - f * w3
    gth[0] += (1 - xi) * G0; gth[1] += (1 - xi) * G1; gth[2] += (1 - xi) * G2; gth[3] += (1 - xi) * G3
    gth[4] += xi * G0; gth[5] += xi * G1; gth[6] += xi * G2; gth[7] += xi * G3


def reference_state(qe, prm) -> None:
    """Make the element stress-free in the configuration qe (an initially curved element): store
    its axial strain, material curvature and twist at the Gauss points in prm."""
    l = prm[P_L]
    Y = np.zeros((4, 3)); z16 = np.zeros(16)
    T1 = np.zeros((3, 4)); T2 = np.zeros((3, 4))
    _slopes(qe, z16, z16, Y, np.zeros((4, 3)), np.zeros((4, 3)), T1, T2, False)
    d1 = np.zeros(4); d2 = np.zeros(4)
    for g in range(4):
        _dshape(_GX[g], l, d1, d2)
        a = d1 @ Y; b = d2 @ Y
        n2 = a @ a
        prm[P_E0 + g] = np.sqrt(n2) - 1.0
        kap = np.cross(a, b) / n2
        w = (1 - _GX[g]) * qe[4:8] + _GX[g] * qe[12:16]
        A = rotation_matrix(w / np.linalg.norm(w))
        prm[P_K0 + 3 * g:P_K0 + 3 * g + 3] = A.T @ kap
    prm[P_PSI0] = _twist(qe, z16, np.zeros(16), 0.0, 0.0, 0.0)
    prm[P_CURVED] = 1.0


@nb.njit(cache=True)
def hermite_mass_nb(l):
    M = np.empty((4, 4))
    M[0, 0] = 13 / 35; M[0, 1] = 11 * l / 210; M[0, 2] = 9 / 70; M[0, 3] = -13 * l / 420
    M[1, 1] = l * l / 105; M[1, 2] = 13 * l / 420; M[1, 3] = -l * l / 140
    M[2, 2] = 13 / 35; M[2, 3] = -11 * l / 210
    M[3, 3] = l * l / 105
    for i in range(4):
        for j in range(i):
            M[i, j] = M[j, i]
    for i in range(4):
        for j in range(4):
            M[i, j] *= l
    return M


@nb.njit(cache=True)
def element_energy(qe, prm):
    """Strain energy of one element (float64; for tests and energy balances)."""
    l = prm[P_L]
    EA, EI, GJ = prm[P_EA], prm[P_EI], prm[P_GJ]
    z16 = np.zeros(16)
    Y = np.zeros((4, 3)); vY = np.zeros((4, 3)); aY = np.zeros((4, 3))
    T1 = np.zeros((3, 4)); T2 = np.zeros((3, 4))
    _slopes(qe, z16, z16, Y, vY, aY, T1, T2, False)
    d1 = np.zeros(4); d2 = np.zeros(4)
    U = 0.0
    for g in range(4):
        _dshape(_GX[g], l, d1, d2)
        a = d1[0] * Y[0] + d1[1] * Y[1] + d1[2] * Y[2] + d1[3] * Y[3]
        b = d2[0] * Y[0] + d2[1] * Y[1] + d2[2] * Y[2] + d2[3] * Y[3]
        n2 = a[0] * a[0] + a[1] * a[1] + a[2] * a[2]
        e = math.sqrt(n2) - 1.0
        k = np.cross(a, b) / n2
        if prm[P_CURVED] != 0.0:
            e -= prm[P_E0 + g]
            c0, c1, c2 = _ref_curvature(qe, _GX[g], prm[P_K0 + 3 * g], prm[P_K0 + 3 * g + 1], prm[P_K0 + 3 * g + 2])
            k = k - np.array([c0, c1, c2])
        U += 0.5 * _GW[g] * l * (EA * e * e + EI * (k[0] * k[0] + k[1] * k[1] + k[2] * k[2]))
    if GJ != 0.0:
        g16 = np.zeros(16)
        psi = _twist(qe, z16, g16, 0.0, 0.0, 0.0) - prm[P_PSI0]
        U += 0.5 * GJ / l * psi * psi
    return U


@nb.njit(cache=True)
def element_jacobian(qe, ve, ae, prm, ci, cv, ca, J):
    """J (16 x 16) = d element_force / d q+ when q+ drives v = v^ + cv q+ and a = a^ + ca q+
    (complex step, step 1e-30: exact to rounding)."""
    hs = 1e-30
    qc = qe.astype(np.complex128)
    vc = ve.astype(np.complex128)
    ac = ae.astype(np.complex128)
    out = np.zeros(16, dtype=np.complex128)
    for k in range(16):
        qc[k] += 1j * hs
        vc[k] += 1j * hs * cv
        ac[k] += 1j * hs * ca
        element_force(qc, vc, ac, prm, ci, out)
        for i in range(16):
            J[i, k] = out[i].imag / hs
        qc[k] = qe[k]
        vc[k] = ve[k]
        ac[k] = ae[k]
