"""The exact Jacobian of the ANCF step residual (``plant/ancf_residual.py``): local blocks by
complex step (elements, nodal rigid bodies) and in closed form (AMB stiffness, constraint
gradients and their second derivatives times the multipliers), assembled into a sparse (CSC)
matrix of a pattern built once (:class:`JacobianAssembler`); also the velocity and acceleration
derivatives alone (damping-gyroscopic and mass matrices, :func:`rate_blocks`)."""
from __future__ import annotations

import numba as nb
import numpy as np
import scipy.sparse as sp

from . import ancf_beam as ab
from . import ancf_disc as ad
from .ancf_model import ANCFArrays, n_constraints, speed_profile


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
