"""The ANCF multibody model of a rotor: assembly of quaternion ANCF beam elements
(``plant/ancf_beam.py``) and nodal rigid bodies (``plant/ancf_disc.py``), constraints with
Lagrange multipliers, AMB / unbalance / gravity forces, the global residual and its exact
(complex-step) Jacobian, statics, and the linearisation of the DAE for eigen-analysis.

Unknowns of a step: ``x = [q (8 per node), mu (one per constraint)]``; constraints, in order:
the normalisation ``theta_i . theta_i - 1 = 0`` of every node, the prescribed spin (if any), and
fixed coordinates ``q_k = value`` (clamps in the statics tests; the axial position of the drive
node when the scene has no axial AMB).

Prescribed spin (chosen over a drive torque): the other rungs prescribe the speed (constant or a
run-up ramp), so the ANCF rung does the same.  Every node's attitude is ``theta_i (x) s(t)`` with
``s(t)`` the rotation by the prescribed spin angle ``phi(t)`` about the body axis
(``plant/ancf_disc.py``: an exact change of variables that keeps ``theta`` near identity, so an
implicit integrator does not damp the spin); the drive node (node 1) has no twist about it,
``(A(theta) e1)_y = 2 (x y + w z) = 0``, whose multiplier is the drive torque.  The rest of the
rotor follows through the torsional stiffness; gyroscopic coupling comes from the kinetic energy
(quadratic-velocity and base-spin terms), not from an added matrix.
"""
from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp

from . import ancf_beam as ab
from . import ancf_disc as ad
from . import beam_element as be

ANCFArrays = namedtuple("ANCFArrays", [
    "conn",  # (ne, 2) int64 element nodes
    "prm",  # (ne, P_LEN) element parameters
    "nJ",  # (nn, 3) nodal body inertia diag(J_d, J_d, J_p)
    "nm",  # (nn,) nodal rigid mass (discs)
    "nF",  # (nn, 3) constant external force (gravity on discs, static loads)
    "nM",  # (nn, 3) constant external spatial moment
    "alpha",  # (1,) mass-proportional damping on translations
    "spin",  # (5,) node (-1: none), W0, W1, T0, T1
    "fix_idx", "fix_val",  # fixed coordinates
    "amb_node", "amb_axis",  # (na,) actuator node and axis (0 x, 1 y, 2 z)
    "amb_kx", "amb_ki", "amb_iop", "amb_xop", "amb_kc", "amb_gap", "amb_bias", "amb_ref",
    "amb_nl",  # (1,) 1: nonlinear force law
    "sens_node", "sens_axis",
    "unb_node", "unb_me", "unb_phase",
])


@nb.njit(cache=True)
def speed_profile(sp_, t):
    """(phi, Omega, dOmega/dt) of the prescribed spin: W0 until T0, linear to W1 at T1."""
    W0, W1, T0, T1 = sp_[1], sp_[2], sp_[3], sp_[4]
    if T1 <= T0 or t <= T0:
        return W0 * t, W0, 0.0
    a = (W1 - W0) / (T1 - T0)
    if t < T1:
        tau = t - T0
        return W0 * t + 0.5 * a * tau * tau, W0 + a * tau, a
    tau = T1 - T0
    return W0 * T1 + 0.5 * a * tau * tau + W1 * (t - T1), W1, 0.0


@nb.njit(cache=True)
def n_constraints(S):
    return S.nJ.shape[0] + (1 if S.spin[0] >= 0 else 0) + S.fix_idx.shape[0]


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


@nb.njit(cache=True)
def jacobian_blocks(S, x, vh, cv, ah, ca, t, cur, sd, ci, EB, NB, CV):
    """Exact local Jacobians: EB (ne, 16, 16) element blocks, NB (nn, 8, 8) node blocks
    (rigid bodies, AMB stiffness, mu * Phi_qq), CV: values of the constraint rows (Phi_q),
    in the order of :func:`constraint_pattern`."""
    nn = S.nJ.shape[0]
    n = 8 * nn
    q = x[:n]
    mu = x[n:]
    v = vh + cv * q
    a = ah + ca * q
    Je = np.zeros((16, 16))
    for e in range(S.conn.shape[0]):
        i, j = S.conn[e, 0], S.conn[e, 1]
        qe = np.concatenate((q[8 * i:8 * i + 8], q[8 * j:8 * j + 8]))
        ve = np.concatenate((v[8 * i:8 * i + 8], v[8 * j:8 * j + 8]))
        ae = np.concatenate((a[8 * i:8 * i + 8], a[8 * j:8 * j + 8]))
        ab.element_jacobian(qe, ve, ae, S.prm[e], ci, cv, ca, Je)
        for r in range(16):
            for c in range(16):
                EB[e, r, c] = sd * Je[r, c]
    hs = 1e-30
    ph, W, Wd = speed_profile(S.spin, t)
    fn = np.zeros(8, dtype=np.complex128)
    for i in range(nn):
        qn = q[8 * i:8 * i + 8].astype(np.complex128)
        vn = v[8 * i:8 * i + 8].astype(np.complex128)
        an = a[8 * i:8 * i + 8].astype(np.complex128)
        for k in range(8):
            qn[k] += 1j * hs; vn[k] += 1j * hs * cv; an[k] += 1j * hs * ca
            for m in range(8):
                fn[m] = 0.0
            ad.node_inertia(qn, vn, an, S.nJ[i], S.nm[i], ci, S.alpha[0], W, Wd, fn)
            for m in range(8):
                NB[i, m, k] = sd * fn[m].imag / hs
            qn[k] = q[8 * i + k]; vn[k] = v[8 * i + k]; an[k] = a[8 * i + k]
        for k in range(4):
            NB[i, 4 + k, 4 + k] += 2.0 * mu[i]
    for a_ in range(S.amb_node.shape[0]):
        i = S.amb_node[a_]
        ax = S.amb_axis[a_]
        xs = S.amb_xop[a_] + q[8 * i + ax] - S.amb_ref[a_]
        if S.amb_nl[0] == 0:
            kx = S.amb_kx[a_]
        else:
            if abs(xs) >= S.amb_gap[a_]:
                continue
            i0, s0 = S.amb_bias[a_], S.amb_gap[a_]
            iu = max(i0 + cur[a_], 0.0); il = max(i0 - cur[a_], 0.0)
            kx = 0.5 * S.amb_kc[a_] * (iu * iu / (s0 - xs) ** 3 + il * il / (s0 + xs) ** 3)
        NB[i, ax, ax] -= sd * kx
    # constraint rows
    c = 0
    for i in range(nn):
        for k in range(4):
            CV[c] = 2.0 * q[8 * i + 4 + k]; c += 1
    r = nn
    if S.spin[0] >= 0:
        i = int(S.spin[0])
        o = 8 * i + 4
        w, xq, yq, zq = q[o], q[o + 1], q[o + 2], q[o + 3]
        sph, cph = 0.0, 1.0
        CV[c] = -sph * 2 * w + cph * 2 * zq
        CV[c + 1] = -sph * 2 * xq + cph * 2 * yq
        CV[c + 2] = sph * 2 * yq + cph * 2 * xq
        CV[c + 3] = sph * 2 * zq + cph * 2 * w
        c += 4
        m = mu[r]
        H = NB[i]
        H[4, 4] += -2 * sph * m; H[5, 5] += -2 * sph * m; H[6, 6] += 2 * sph * m; H[7, 7] += 2 * sph * m
        H[4, 7] += 2 * cph * m; H[7, 4] += 2 * cph * m; H[5, 6] += 2 * cph * m; H[6, 5] += 2 * cph * m
        r += 1
    for f in range(S.fix_idx.shape[0]):
        CV[c] = 1.0; c += 1


@nb.njit(cache=True)
def rate_blocks(S, q, v, a, t, ci, wrt, EB, NB):
    """Exact local Jacobians of the q rows ``M(q) q'' + Q_v - Q`` with respect to the velocity
    (``wrt`` 1) or the acceleration (``wrt`` 2) alone, q held: EB (ne, 16, 16) element blocks,
    NB (nn, 8, 8) node blocks (rigid bodies; the AMB and constraint terms depend on q only).
    Complex step on v or a only, so the mass (wrt 2) and damping-gyroscopic (wrt 1) matrices come
    out to rounding of their own size, not as a difference of stiffness-dominated Jacobians."""
    hs = 1e-30
    qc16 = np.zeros(16, dtype=np.complex128)
    vc16 = np.zeros(16, dtype=np.complex128)
    ac16 = np.zeros(16, dtype=np.complex128)
    out = np.zeros(16, dtype=np.complex128)
    for e in range(S.conn.shape[0]):
        i, j = S.conn[e, 0], S.conn[e, 1]
        for k in range(8):
            qc16[k] = q[8 * i + k]; qc16[8 + k] = q[8 * j + k]
            vc16[k] = v[8 * i + k]; vc16[8 + k] = v[8 * j + k]
            ac16[k] = a[8 * i + k]; ac16[8 + k] = a[8 * j + k]
        for k in range(16):
            if wrt == 1:
                vc16[k] += 1j * hs
            else:
                ac16[k] += 1j * hs
            ab.element_force(qc16, vc16, ac16, S.prm[e], ci, out)
            for r in range(16):
                EB[e, r, k] = out[r].imag / hs
            vc16[k] = vc16[k].real
            ac16[k] = ac16[k].real
    ph, W, Wd = speed_profile(S.spin, t)
    fn = np.zeros(8, dtype=np.complex128)
    for i in range(S.nJ.shape[0]):
        qn = q[8 * i:8 * i + 8].astype(np.complex128)
        vn = v[8 * i:8 * i + 8].astype(np.complex128)
        an = a[8 * i:8 * i + 8].astype(np.complex128)
        for k in range(8):
            if wrt == 1:
                vn[k] += 1j * hs
            else:
                an[k] += 1j * hs
            for m in range(8):
                fn[m] = 0.0
            ad.node_inertia(qn, vn, an, S.nJ[i], S.nm[i], ci, S.alpha[0], W, Wd, fn)
            for m in range(8):
                NB[i, m, k] = fn[m].imag / hs
            vn[k] = v[8 * i + k]; an[k] = a[8 * i + k]


def constraint_pattern(S: ANCFArrays) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) of every constraint-gradient entry, in the order jacobian_blocks fills CV
    (row = constraint index, column = coordinate)."""
    nn = S.nJ.shape[0]
    rows, cols = [], []
    for i in range(nn):
        rows += [i] * 4; cols += list(range(8 * i + 4, 8 * i + 8))
    r = nn
    if S.spin[0] >= 0:
        i = int(S.spin[0])
        rows += [r] * 4; cols += list(range(8 * i + 4, 8 * i + 8)); r += 1
    for k in S.fix_idx:
        rows.append(r); cols.append(int(k)); r += 1
    return np.array(rows, dtype=np.int64), np.array(cols, dtype=np.int64)


class JacobianAssembler:
    """Sparse (CSC) step matrix from the local blocks, with a fixed pattern built once."""

    def __init__(self, S: ANCFArrays):
        self.S = S
        nn = S.nJ.shape[0]
        self.n = 8 * nn
        self.nc = int(n_constraints(S))
        ne = S.conn.shape[0]
        rows, cols = [], []
        for e in range(ne):
            idx = np.concatenate([np.arange(8 * S.conn[e, 0], 8 * S.conn[e, 0] + 8),
                                  np.arange(8 * S.conn[e, 1], 8 * S.conn[e, 1] + 8)])
            rows.append(np.repeat(idx, 16)); cols.append(np.tile(idx, 16))
        for i in range(nn):
            idx = np.arange(8 * i, 8 * i + 8)
            rows.append(np.repeat(idx, 8)); cols.append(np.tile(idx, 8))
        cr, cc = constraint_pattern(S)
        rows.append(self.n + cr); cols.append(cc)  # Phi_q
        rows.append(cc); cols.append(self.n + cr)  # Phi_q^T
        self.rows = np.concatenate(rows); self.cols = np.concatenate(cols)
        self.EB = np.zeros((ne, 16, 16)); self.NB = np.zeros((nn, 8, 8)); self.CV = np.zeros(len(cr))
        N = self.n + self.nc
        # map the COO entries to CSC data positions once
        A = sp.csc_matrix((np.ones(len(self.rows)), (self.rows, self.cols)), shape=(N, N))
        A.sum_duplicates(); A.sort_indices()
        self.csc = A
        lin = self.cols * N + self.rows
        keys = A.indices + N * np.repeat(np.arange(N), np.diff(A.indptr))
        order = np.argsort(keys)
        self.pos = order[np.searchsorted(keys[order], lin)]

    def matrix(self, x, vh, cv, ah, ca, t, cur, sd, ci) -> sp.csc_matrix:
        jacobian_blocks(self.S, x, vh, cv, ah, ca, t, cur, sd, ci, self.EB, self.NB, self.CV)
        vals = np.concatenate([self.EB.ravel(), self.NB.ravel(), self.CV, self.CV])
        data = np.bincount(self.pos, weights=vals, minlength=self.csc.nnz)
        return sp.csc_matrix((data, self.csc.indices, self.csc.indptr), shape=self.csc.shape)

    def rate_matrix(self, q, v, a, t, wrt: str) -> sp.csc_matrix:
        """n x n: the derivative of the q rows (``M(q) q'' + Q_v - Q``, sd = ci = 1) with respect
        to the velocity (``wrt="v"``: damping and gyroscopic matrix) or the acceleration
        (``wrt="a"``: the mass matrix M(q)) at (q, v, a, t), q held (:func:`rate_blocks`)."""
        if wrt not in ("v", "a"):
            raise ValueError(f"rate_matrix: wrt must be 'v' or 'a', not {wrt!r}")
        f = lambda x: np.ascontiguousarray(x, dtype=np.float64)
        rate_blocks(self.S, f(q), f(v), f(a), float(t), 1.0, 1 if wrt == "v" else 2, self.EB, self.NB)
        vals = np.concatenate([self.EB.ravel(), self.NB.ravel(), np.zeros(2 * len(self.CV))])
        data = np.bincount(self.pos, weights=vals, minlength=self.csc.nnz)
        A = sp.csc_matrix((data, self.csc.indices, self.csc.indptr), shape=self.csc.shape)
        return A[:self.n, :self.n].tocsc()


# --------------------------------------------------------------------------- building the model
@dataclass
class Beam:
    """A straight shaft segment for :func:`build`: length, element count and section data."""
    length: float
    elements: int
    EA: float
    EI: float
    GJ: float
    rhoA: float
    rhoI: float  # rho I per unit length (diametral; polar = 2 rhoI)


def build(beams, *, discs=(), beta=0.0, alpha=0.0, gravity=(0.0, 0.0, 0.0), spin=None, fixed=(),
          ambs=None, unbalances=(), node_force=None, node_moment=None, z0=0.0):
    """ANCFArrays of a straight shaft along +z made of ``beams`` (list of Beam).
    ``discs``: (node, mass, J_p, J_d); ``spin``: None or (node, W0, W1, T0, T1): the base spin
    profile of every node, and the drive node whose twist about it is held (-1: none);
    ``fixed``: (coordinate index, value); ``ambs``: dict of per-axis arrays (see ANCFArrays);
    ``unbalances``: (node, me, phase).  Returns (S, node_z)."""
    prm, z, conn = [], [z0], []
    nJ = [np.zeros(3)]
    node = 0
    for b in beams:
        l = b.length / b.elements
        for _ in range(b.elements):
            p = np.zeros(ab.P_LEN)
            p[ab.P_L], p[ab.P_EA], p[ab.P_EI], p[ab.P_GJ], p[ab.P_RHOA] = l, b.EA, b.EI, b.GJ, b.rhoA
            p[ab.P_BETA], p[ab.P_ALPHA] = beta, alpha
            p[ab.P_GX:ab.P_GZ + 1] = gravity
            prm.append(p)
            conn.append((node, node + 1))
            jl = 0.5 * l * np.array([b.rhoI, b.rhoI, 2.0 * b.rhoI])
            nJ[-1] = nJ[-1] + jl
            nJ.append(jl.copy())
            z.append(z[-1] + l)
            node += 1
    nn = node + 1
    nJ = np.array(nJ)
    nm = np.zeros(nn)
    for (k, m, Jp, Jd) in discs:
        nm[k] += m
        nJ[k] += (Jd, Jd, Jp)
    nF = np.zeros((nn, 3)) if node_force is None else np.asarray(node_force, float).copy()
    nF += nm[:, None] * np.asarray(gravity, float)[None, :]
    nM = np.zeros((nn, 3)) if node_moment is None else np.asarray(node_moment, float).copy()
    spn = np.array([-1.0, 0, 0, 0, 0]) if spin is None else np.array(spin, float)
    fi = np.array([f[0] for f in fixed], dtype=np.int64)
    fv = np.array([f[1] for f in fixed], dtype=float)
    A = ambs or {}
    ia = lambda k: np.asarray(A.get(k, []), dtype=np.int64)
    fa = lambda k: np.asarray(A.get(k, []), dtype=float)
    S = ANCFArrays(conn=np.array(conn, dtype=np.int64), prm=np.array(prm), nJ=nJ, nm=nm, nF=nF, nM=nM,
                   alpha=np.array([alpha]), spin=spn, fix_idx=fi, fix_val=fv,
                   amb_node=ia("node"), amb_axis=ia("axis"), amb_kx=fa("kx"), amb_ki=fa("ki"), amb_iop=fa("iop"),
                   amb_xop=fa("xop"), amb_kc=fa("kc"), amb_gap=fa("gap"), amb_bias=fa("bias"), amb_ref=fa("ref"),
                   amb_nl=np.array([int(A.get("nonlinear", 0))], dtype=np.int64),
                   sens_node=ia("sens_node"), sens_axis=ia("sens_axis"),
                   unb_node=np.array([u[0] for u in unbalances], dtype=np.int64),
                   unb_me=np.array([u[1] for u in unbalances], dtype=float),
                   unb_phase=np.array([u[2] for u in unbalances], dtype=float))
    return S, np.array(z)


def beams_of_spec(spec) -> list[Beam]:
    out = []
    for s in spec.sections:
        A, I = be.section_properties(s.outer_diameter, s.inner_diameter)
        out.append(Beam(s.length, s.elements, s.youngs_modulus * A, s.youngs_modulus * I,
                        s.shear_modulus * 2 * I, s.density * A, s.density * I))
    return out


def straight_state(S: ANCFArrays, node_z) -> np.ndarray:
    """q of the unstressed straight shaft along +z, identity attitudes."""
    nn = S.nJ.shape[0]
    q = np.zeros(8 * nn)
    q[2::8] = node_z
    q[4::8] = 1.0
    return q


def spin_velocity(S: ANCFArrays, W: float) -> np.ndarray:
    """v of a rigid spin W about +z of the straight shaft in its reference attitude."""
    nn = S.nJ.shape[0]
    v = np.zeros(8 * nn)
    v[7::8] = 0.5 * W
    return v


# --------------------------------------------------------------------------- statics
def solve_static(S: ANCFArrays, q0, loads_scale=None, steps: int = 1, tol: float = 1e-10, maxit: int = 50):
    """Static equilibrium (no inertia) by Newton with load stepping: the external nodal loads
    (nF, nM, gravity) are scaled by k/steps.  Returns (q, multipliers)."""
    n = q0.shape[0]
    nc = int(n_constraints(S))
    x = np.concatenate([q0, np.zeros(nc)])
    asm = JacobianAssembler(S)
    z = np.zeros(n)
    import scipy.sparse.linalg as spla
    for k in range(1, steps + 1):
        s = k / steps
        Sk = S._replace(nF=S.nF * s, nM=S.nM * s, prm=_scaled_gravity(S.prm, s))
        asm.S = Sk
        R = np.zeros(n + nc)
        prev = np.inf
        for it in range(maxit):
            residual(Sk, x, z, 0.0, z, 0.0, 0.0, np.zeros(max(1, S.amb_node.shape[0])), 1.0, 0.0, R)
            A = asm.matrix(x, z, 0.0, z, 0.0, 0.0, np.zeros(max(1, S.amb_node.shape[0])), 1.0, 0.0)
            dx = spla.spsolve(A, -R)
            x += dx
            d, scale = np.max(np.abs(dx[:n])), max(1.0, np.max(np.abs(x[:n])))
            if d < tol * scale or (it > 3 and d > 0.5 * prev and d < 1e-7 * scale):
                break  # converged, or stagnating at the rounding level of the residual
            prev = d
        else:
            raise RuntimeError(f"static Newton did not converge at load step {k}/{steps}")
    asm.S = S
    return x[:n], x[n:]


def _scaled_gravity(prm, s):
    p = prm.copy()
    p[:, ab.P_GX:ab.P_GZ + 1] *= s
    return p


# --------------------------------------------------------------------------- energies
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


# --------------------------------------------------------------------------- from a scene
def from_model(model, speed: float = 0.0, run_up=None, nonlinear: bool = False):
    """ANCFArrays of a compiled scene model (``model.spec``; AMB axes, operating points and
    force constants from the model, so the force law is the very one of the other rungs).
    ``run_up = (W0, W1, T0, T1)``.  Returns (S, q0)."""
    from .params import ParameterError
    spec = model.spec
    if spec.axial_amb is not None:
        raise ParameterError(f"{spec.path}: [model] rung 'ancf' does not support an [axial_amb] yet")
    W0, W1, T0, T1 = (float(speed), float(speed), 0.0, 0.0) if run_up is None else map(float, run_up)
    g = float(getattr(spec.model, "gravity", 0.0) or 0.0)
    dpn = model.rotor.dpn
    act, sens = np.asarray(model.act_dof), np.asarray(model.sens_dof)
    gop = model.extras.get("gravity") if g else None
    # linearised law f = f_op + kx (x - x_op) + ki (i - i_op): f_op (the AMB's share of the weight)
    # folded into the current offset, so the kernels are those of the unloaded law
    iop = model.i_op if gop is None else np.asarray(model.i_op) - gop.load / np.asarray(model.ki)
    ambs = dict(node=act // dpn, axis=act % dpn, kx=model.kx, ki=model.ki, iop=iop, xop=model.x_op,
                kc=model.force_constant, gap=model.gap, bias=model.bias, ref=np.zeros(len(act)),
                nonlinear=int(bool(nonlinear)), sens_node=sens // dpn, sens_axis=sens % dpn)
    drive = 0
    S, z = build(beams_of_spec(spec), discs=[(d.node, d.mass, d.polar_inertia, d.diametral_inertia) for d in spec.discs],
                 beta=spec.damping.stiffness_proportional, alpha=spec.damping.mass_proportional,
                 gravity=(0.0, -g, 0.0), spin=(drive, W0, W1, T0, T1), fixed=[(8 * drive + 2, spec.node_z[0])],
                 ambs=ambs, unbalances=[(u.node, u.magnitude, u.phase) for u in spec.unbalances],
                 z0=spec.node_z[0])
    if not np.allclose(z, spec.node_z, atol=1e-12):
        raise ParameterError(f"{spec.path}: node positions of the ancf mesh differ from the FE rotor's")
    if g and gop is None:
        raise ParameterError(f"{spec.path}: [model] gravity needs the model compiled at rung 'ancf' "
                             f"(its gravity operating point), got rung {model.rung!r}")
    return S, (straight_state(S, z) if gop is None else np.array(gop.q))


def gravity_statics(spec, steps: int = 1):
    """Static equilibrium under ``[model] gravity`` with the rotor held at zero displacement (x and
    y) at the radial AMBs' nodes: what the PIDs' integral action settles to.  The AMB nodes are
    held by constraints ``q = 0`` (the axial position and the twist at the drive node as in
    :func:`from_model`); the AMB reactions are the constraint multipliers, so the statically
    indeterminate shares of the weight follow from the shaft's compatibility.  Returns
    ``(reactions, q)``: the force (N) each AMB axis exerts on the rotor, in the order of
    :func:`ambhil.plant.model.bearing_axes`, and the sagged configuration."""
    from .params import ParameterError
    g = float(spec.model.gravity or 0.0)
    if spec.axial_amb is not None:
        raise ParameterError(f"{spec.path}: [model] rung 'ancf' does not support an [axial_amb] yet")
    for a in spec.ambs:
        if a.sensor_node != a.node:
            raise ParameterError(f"{spec.path}: AMB {a.name}: gravity on the ancf rung needs the sensor at the "
                                 f"actuator node (sensor_node {a.sensor_node + 1} != node {a.node + 1})")
    drive = 0
    held = [(8 * a.node + ax, 0.0) for a in spec.ambs for ax in (0, 1)]
    S, z = build(beams_of_spec(spec), discs=[(d.node, d.mass, d.polar_inertia, d.diametral_inertia) for d in spec.discs],
                 gravity=(0.0, -g, 0.0), spin=(drive, 0.0, 0.0, 0.0, 0.0),
                 fixed=[(8 * drive + 2, spec.node_z[0])] + held, z0=spec.node_z[0])
    q, mu = solve_static(S, straight_state(S, z), steps=steps)
    # residual rows: internal - external + Phi_q^T mu = 0 with Phi = q[k] - 0, so the force the
    # support exerts on the rotor is -mu
    return -mu[len(mu) - len(held):], q


def fe_view(S: ANCFArrays, q) -> np.ndarray:
    """The ANCF state as FE node DOFs [x, y, phi_x, phi_y] per node (phi = slope of the axis)."""
    nn = S.nJ.shape[0]
    Q = q.reshape(nn, 8)
    w, x, y, z = Q[:, 4], Q[:, 5], Q[:, 6], Q[:, 7]
    tx, ty, tz = 2 * (x * z + w * y), 2 * (y * z - w * x), w * w - x * x - y * y + z * z
    out = np.zeros((nn, 4))
    out[:, 0], out[:, 1] = Q[:, 0], Q[:, 1]
    out[:, 2], out[:, 3] = tx / tz, ty / tz
    return out.ravel()


# --------------------------------------------------------------------------- small-motion eigen-analysis
def linearised_modes(S: ANCFArrays, q0, n_modes: int = 20):
    """Natural frequencies (rad/s) and mode shapes of the DAE linearised about the static
    configuration q0 at zero speed: K, M from the exact Jacobians, restricted to the null space
    of the constraint gradient (the constrained eigenproblem).  M is the acceleration derivative
    itself (``JacobianAssembler.rate_matrix``), not a difference of Jacobians, so it keeps its
    digits on fine meshes where K is many orders larger.  Returns (w, V) with V in q."""
    import scipy.linalg as sla
    n = q0.shape[0]
    nc = int(n_constraints(S))
    asm = JacobianAssembler(S)
    z = np.zeros(n)
    cur = np.zeros(max(1, S.amb_node.shape[0]))
    x = np.concatenate([q0, np.zeros(nc)])
    J0 = asm.matrix(x, z, 0.0, z, 0.0, 0.0, cur, 1.0, 1.0).toarray()
    K = J0[:n, :n]
    M = asm.rate_matrix(q0, z, z, 0.0, "a").toarray()
    Phq = J0[n:, :n]
    N = sla.null_space(Phq)
    Kr, Mr = N.T @ K @ N, N.T @ M @ N
    Kr, Mr = 0.5 * (Kr + Kr.T), 0.5 * (Mr + Mr.T)
    lam, Vr = sla.eigh(Kr, Mr)
    w = np.sqrt(np.abs(lam)) * np.sign(lam)
    return w[:n_modes], (N @ Vr)[:, :n_modes]


def mode_kind(S: ANCFArrays, v) -> str:
    """'bending' | 'torsion' | 'axial' | 'rigid' by the dominant part of a mode shape."""
    V = v.reshape(-1, 8)
    lat = np.sum(V[:, 0:2] ** 2) + np.sum(V[:, 5:7] ** 2)
    tor = np.sum(V[:, 7] ** 2)
    ax = np.sum(V[:, 2:4] ** 2)
    return ("bending", "torsion", "axial")[int(np.argmax([lat, tor, ax]))]


def linearised_eigen(S: ANCFArrays, q0, t: float = 0.0):
    """Eigenvalues and shapes (in q) of the DAE linearised about the steady state ``q0, v = 0`` of
    the base-spin formulation (autonomous at constant speed: the spin is carried by the base, so
    the straight spinning rotor is an equilibrium): ``M x'' + D x' + K x = 0`` on the null space of
    the constraint gradient, D holding the gyroscopic terms that follow from the kinetic energy.
    M and D are the acceleration and velocity derivatives themselves (``JacobianAssembler.
    rate_matrix``), not differences of stiffness-dominated Jacobians."""
    import scipy.linalg as sla
    n = q0.shape[0]
    nc = int(n_constraints(S))
    asm = JacobianAssembler(S)
    z = np.zeros(n)
    cur = np.zeros(max(1, S.amb_node.shape[0]))
    x = np.concatenate([q0, np.zeros(nc)])
    J0 = asm.matrix(x, z, 0.0, z, 0.0, t, cur, 1.0, 1.0).toarray()
    K = J0[:n, :n]
    M = asm.rate_matrix(q0, z, z, t, "a").toarray()
    D = asm.rate_matrix(q0, z, z, t, "v").toarray()
    N = sla.null_space(J0[n:, :n])
    Mr, Dr, Kr = N.T @ M @ N, N.T @ D @ N, N.T @ K @ N
    m = Mr.shape[0]
    A = np.block([[np.zeros((m, m)), np.eye(m)], [-Kr, -Dr]])
    B = np.block([[np.eye(m), np.zeros((m, m))], [np.zeros((m, m)), Mr]])
    lam, V = sla.eig(A, B)
    return lam, N @ V[:m]


def whirl(S: ANCFArrays, v) -> float:
    """Forwardness (F - B)/(F + B) of a mode shape's lateral orbits (+1 forward with the spin)."""
    Vn = v.reshape(-1, 8)
    X, Y = Vn[:, 0], Vn[:, 1]
    F = np.sum(np.abs(X + 1j * Y) ** 2)
    B = np.sum(np.abs(X - 1j * Y) ** 2)
    return float((F - B) / (F + B + 1e-300))
