"""The residual of one implicit step of the ANCF model (``plant/ancf_model.py``): element forces,
nodal rigid bodies, external loads, the AMB force law (linearised or nonlinear, the law of the
other rungs), unbalance and the constraints with their Lagrange multipliers.  Its exact Jacobian
is ``plant/ancf_jacobian.py``."""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from . import ancf_beam as ab
from . import ancf_disc as ad
from .ancf_model import speed_profile


@nb.njit(cache=True)
def _amb_force_x(S, a, xs, cur):
    """Force of AMB axis a at stator-relative displacement xs (generic dtype)."""
    if S.amb_nl[0] == 0:
        return S.amb_kx[a] * (xs - S.amb_xop[a]) + S.amb_ki[a] * (cur[a] - S.amb_iop[a])
    i0 = S.amb_bias[a]
    iu = max(i0 + cur[a], 0.0)
    il = max(i0 - cur[a], 0.0)
    s0 = S.amb_gap[a]
    return 0.25 * S.amb_kc[a] * (iu * iu / ((s0 - xs) * (s0 - xs)) - il * il / ((s0 + xs) * (s0 + xs)))


def amb_force_value(S, a, xs, cur) -> float:
    """Force of AMB axis a (Python, for the integrator's input-jump correction)."""
    if S.amb_nl[0] != 0 and abs(xs) >= S.amb_gap[a]:
        return 0.0
    return float(_amb_force_x(S, a, xs, np.asarray(cur, dtype=np.float64)))


# One numba kernel on purpose (evaluated at every Newton iteration of every step): its parts
# (elements, nodes, AMBs, unbalance, constraints) add into the same rows in a fixed order, which
# the bit-for-bit checks of the ancf rung rely on; the parts are marked by comments.
@nb.njit(cache=True)
def residual(S, x, vh, cv, ah, ca, t, cur, sd, ci, out):
    """Residual of one implicit step, ``out`` (n + nc): rows of q: ``sd * (M q'' + Q_v - Q) +
    Phi_q^T mu``; rows of the constraints: ``Phi(q, t)``.  v = vh + cv q, a = ah + ca q.
    Returns the largest |x|/gap over the AMB axes."""
    nn = S.nJ.shape[0]
    n = 8 * nn
    q = x[:n]
    mu = x[n:]
    v = vh + cv * q
    a = ah + ca * q
    for k in range(out.shape[0]):
        out[k] = 0.0
    fe = np.zeros(16)
    for e in range(S.conn.shape[0]):
        i, j = S.conn[e, 0], S.conn[e, 1]
        qe = np.concatenate((q[8 * i:8 * i + 8], q[8 * j:8 * j + 8]))
        ve = np.concatenate((v[8 * i:8 * i + 8], v[8 * j:8 * j + 8]))
        ae = np.concatenate((a[8 * i:8 * i + 8], a[8 * j:8 * j + 8]))
        ab.element_force(qe, ve, ae, S.prm[e], ci, fe)
        for k in range(8):
            out[8 * i + k] += sd * fe[k]
            out[8 * j + k] += sd * fe[8 + k]
    fn = np.zeros(8)
    ph, W, Wd = speed_profile(S.spin, t)
    for i in range(nn):
        for k in range(8):
            fn[k] = 0.0
        ad.node_inertia(q[8 * i:8 * i + 8], v[8 * i:8 * i + 8], a[8 * i:8 * i + 8], S.nJ[i], S.nm[i], ci,
                        S.alpha[0], W, Wd, fn)
        w, xq, yq, zq = q[8 * i + 4], q[8 * i + 5], q[8 * i + 6], q[8 * i + 7]
        m0, m1, m2 = S.nM[i, 0], S.nM[i, 1], S.nM[i, 2]
        if m0 != 0.0 or m1 != 0.0 or m2 != 0.0:
            e0, e1, e2, e3 = ad.ET_times(w, xq, yq, zq, m0, m1, m2)
            fn[4] -= 2.0 * e0; fn[5] -= 2.0 * e1; fn[6] -= 2.0 * e2; fn[7] -= 2.0 * e3
        for c in range(3):
            fn[c] -= S.nF[i, c]
        for k in range(8):
            out[8 * i + k] += sd * fn[k]
    worst = 0.0
    for a_ in range(S.amb_node.shape[0]):
        k = 8 * S.amb_node[a_] + S.amb_axis[a_]
        xs = S.amb_xop[a_] + q[k] - S.amb_ref[a_]
        g = abs(xs) / S.amb_gap[a_]
        if g > worst:
            worst = g
        if S.amb_nl[0] != 0 and g >= 1.0:
            continue
        out[k] -= sd * _amb_force_x(S, a_, xs, cur)
    if S.unb_node.shape[0] > 0:
        ph, W, Wd = speed_profile(S.spin, t)
        for u in range(S.unb_node.shape[0]):
            i = S.unb_node[u]
            w, xq, yq, zq = q[8 * i + 4], q[8 * i + 5], q[8 * i + 6], q[8 * i + 7]
            c, s = math.cos(ph + S.unb_phase[u]), math.sin(ph + S.unb_phase[u])
            # direction of the unbalance in the fixed frame: A(theta) s(t) [cos ph_u, sin ph_u, 0]
            d0 = (w * w + xq * xq - yq * yq - zq * zq) * c + 2.0 * (xq * yq - w * zq) * s
            d1 = 2.0 * (xq * yq + w * zq) * c + (w * w - xq * xq + yq * yq - zq * zq) * s
            d2 = 2.0 * (xq * zq - w * yq) * c + 2.0 * (yq * zq + w * xq) * s
            me = S.unb_me[u]
            out[8 * i] -= sd * me * (W * W * d0 - Wd * d1)
            out[8 * i + 1] -= sd * me * (W * W * d1 + Wd * d0)
            out[8 * i + 2] -= sd * me * (W * W * d2)
    # constraints
    r = n
    for i in range(nn):
        o = 8 * i + 4
        out[r] = q[o] * q[o] + q[o + 1] * q[o + 1] + q[o + 2] * q[o + 2] + q[o + 3] * q[o + 3] - 1.0
        for k in range(4):
            out[o + k] += 2.0 * q[o + k] * mu[r - n]
        r += 1
    if S.spin[0] >= 0:
        i = int(S.spin[0])
        o = 8 * i + 4
        w, xq, yq, zq = q[o], q[o + 1], q[o + 2], q[o + 3]
        sph, cph = 0.0, 1.0  # the base spin carries phi(t): the drive node has no twist about it
        out[r] = -sph * (w * w + xq * xq - yq * yq - zq * zq) + cph * 2.0 * (xq * yq + w * zq)
        g0 = -sph * 2 * w + cph * 2 * zq
        g1 = -sph * 2 * xq + cph * 2 * yq
        g2 = sph * 2 * yq + cph * 2 * xq
        g3 = sph * 2 * zq + cph * 2 * w
        m = mu[r - n]
        out[o] += g0 * m; out[o + 1] += g1 * m; out[o + 2] += g2 * m; out[o + 3] += g3 * m
        r += 1
    for f in range(S.fix_idx.shape[0]):
        k = S.fix_idx[f]
        out[r] = q[k] - S.fix_val[f]
        out[k] += mu[r - n]
        r += 1
    return worst
