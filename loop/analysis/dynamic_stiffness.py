"""Closed-loop dynamic stiffness of the rotor on its AMB loops, and solves with it.

For motion ``eta = Y e^{s t}`` (``s = i w`` for harmonic motion) at spin speed Omega:

    Z(s, Omega) = s^2 M + s (C + Omega G) + K_eff + Ba diag(k_i H(s)) Cs

``H`` is the per-axis current law (controller/transfer.py) evaluated exactly at ``s``; the
controller states are eliminated, so closed-loop eigenvalues are the roots of det Z(s) = 0.
An na x na law (controller/law_lti.py) gives ``Ba diag(k_i) H(s) Cs`` instead; it couples
bearings that the banded storage keeps apart, so the full rung then solves with sparse LU.
Reduced rungs solve with dense LU (batched over frequencies); the full rung assembles banded
storage from a fixed sparsity pattern and calls LAPACK's gbsv.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.linalg import lapack

from ambhil.controller.transfer import evaluate, evaluate_matrix, is_siso
from ..system import System


def _h_and_derivative(H, s: complex):
    """H(s) and dH/ds: complex numbers for a per-axis law, (na, na) arrays for an na x na one."""
    A, B, C, D = (np.atleast_2d(np.asarray(m, dtype=float)) for m in (H.A, H.B, H.C, H.D))
    if not is_siso(H):
        if A.size == 0:
            return D.astype(complex), np.zeros(D.shape, complex)
        R = s * np.eye(A.shape[0]) - A
        x = np.linalg.solve(R, B)
        return C @ x + D, -(C @ np.linalg.solve(R, x))
    if A.size == 0:
        return complex(D[0, 0]), 0j
    x = np.linalg.solve(s * np.eye(A.shape[0]) - A, B)
    return complex((C @ x)[0, 0] + D[0, 0]), complex(-(C @ np.linalg.solve(s * np.eye(A.shape[0]) - A, x))[0, 0])


class DynamicStiffness:
    """Z(s, Omega) of one model: solves and products, sparse-banded or dense."""

    def __init__(self, model: System):
        self.model = model
        self.sparse = model.sparse
        self.mimo = not is_siso(model.H)
        if self.sparse and self.mimo:
            self.Ms, self.Cm, self.Gm, self.Km = (sp.csc_matrix(A) for A in (model.M, model.C, model.G, model.K_eff))
            self.Ba, self.Cs = sp.csc_matrix(model.Ba), sp.csr_matrix(model.Cs)
        elif self.sparse:
            Ba, Cs = sp.csr_matrix(model.Ba), sp.csr_matrix(model.Cs)
            mats = [sp.csr_matrix(A) for A in (model.M, model.C, model.G, model.K_eff)]
            per_axis = [Ba[:, [j]] @ Cs[[j], :] for j in range(model.n_axes)]
            pat = sum(abs(A) for A in mats + per_axis).tocoo()
            r, c = pat.row, pat.col
            self.l = int(max(0, (r - c).max()))
            self.u = int(max(0, (c - r).max()))
            self.rows = 2 * self.l + self.u + 1  # gbsv storage (2l + u + 1, n), Fortran order
            self.flat = (self.l + self.u + r - c) + c * self.rows
            take = lambda A: np.asarray(sp.csr_matrix(A)[r, c]).ravel()
            self.m, self.c, self.g, self.k = (take(A) for A in mats)
            self.bc = np.array([take(P) for P in per_axis])
            self.Ms, self.Cm, self.Gm = mats[0], mats[1], mats[2]
            self.Ba, self.Cs = Ba, Cs
        else:
            self.M, self.C, self.G, self.K, self.Ba, _, self.Cs = model.dense

    def solve(self, s: complex, spin: float, rhs: np.ndarray, h: complex | None = None) -> np.ndarray:
        """Z(s, Omega)^-1 rhs for one s; rhs (n,) or (n, m)."""
        m = self.model
        if h is None:
            h = _h_and_derivative(m.H, s)[0]
        if self.mimo:
            Hk = m.ki[:, None] * h                      # diag(k_i) H(s)
            if self.sparse:
                Z = (s * s) * self.Ms + s * (self.Cm + spin * self.Gm) + self.Km + self.Ba @ sp.csr_matrix(Hk) @ self.Cs
                return spla.splu(sp.csc_matrix(Z)).solve(np.asarray(rhs, dtype=complex))
            Z = s * s * self.M + s * (self.C + spin * self.G) + self.K + self.Ba @ Hk @ self.Cs
            return np.linalg.solve(Z, rhs)
        hk = h * m.ki
        if self.sparse:
            ab = np.zeros((self.rows, m.n), dtype=complex, order="F")
            ab.ravel(order="F")[self.flat] = s * s * self.m + s * (self.c + spin * self.g) + self.k + hk @ self.bc
            _, _, x, info = lapack.zgbsv(self.l, self.u, ab, np.asarray(rhs, dtype=complex), overwrite_ab=True)
            if info != 0:
                raise np.linalg.LinAlgError(f"dynamic stiffness singular at s = {s:g}")
            return x
        Z = s * s * self.M + s * (self.C + spin * self.G) + self.K + (self.Ba * hk) @ self.Cs
        return np.linalg.solve(Z, rhs)

    def derivative_times(self, s: complex, spin: float, v: np.ndarray, dh: complex | None = None) -> np.ndarray:
        """dZ/ds (s, Omega) @ v."""
        m = self.model
        if dh is None:
            dh = _h_and_derivative(m.H, s)[1]
        if self.mimo:
            f = self.Ba @ (m.ki[:, None] * dh) @ (self.Cs @ v)
            if self.sparse:
                return (2 * s) * (self.Ms @ v) + self.Cm @ v + spin * (self.Gm @ v) + f
            return (2 * s) * (self.M @ v) + (self.C + spin * self.G) @ v + f
        if self.sparse:
            return (2 * s) * (self.Ms @ v) + self.Cm @ v + spin * (self.Gm @ v) + self.Ba @ (dh * m.ki * (self.Cs @ v))
        return (2 * s) * (self.M @ v) + (self.C + spin * self.G) @ v + self.Ba @ (dh * m.ki * (self.Cs @ v))

    def refine(self, s: complex, spin: float, v: np.ndarray, iters: int = 12, tol: float = 1e-11):
        """Eigenpair of det Z(s, Omega) = 0 near (s, v) by nonlinear inverse iteration (Ruhe):
        u = Z(s)^-1 Z'(s) v,  s <- s - (w^H v)/(w^H u),  v <- u (w^H v)/(w^H u).  Quadratic."""
        w = v / np.vdot(v, v)
        v = v / np.vdot(w, v)
        for _ in range(iters):
            h, dh = _h_and_derivative(self.model.H, s)
            u = self.solve(s, spin, self.derivative_times(s, spin, v, dh), h=h)
            d = np.vdot(w, u)
            s_new = s - 1.0 / d
            v = u / d
            if abs(s_new - s) <= tol * abs(s_new):
                return s_new, v
            s = s_new
        return s, v


def solve(model: System, omegas, spins, rhs) -> np.ndarray:
    """``Z(i w_k, Omega_k)^-1 rhs_k`` for every k.  ``rhs``: (n_w, n) or (n_w, n, m) complex.
    Returns the same shape as ``rhs``."""
    w = np.asarray(omegas, dtype=float)
    spins = np.broadcast_to(np.asarray(spins, dtype=float), w.shape)
    rhs = np.asarray(rhs, dtype=complex)
    vec = rhs.ndim == 2
    R = rhs[:, :, None] if vec else rhs
    if not is_siso(model.H):
        Hk = model.ki[None, :, None] * evaluate_matrix(model.H, 1j * w)     # (n_w, na, na)
        ds = DynamicStiffness(model)
        if model.sparse:
            X = np.stack([ds.solve(1j * wk, sk, R[k], h=evaluate_matrix(model.H, 1j * wk)[0])
                          for k, (wk, sk) in enumerate(zip(w, spins))])
        else:
            M, C, G, K, Ba, Ca, Cs = model.dense
            ww, ss = w[:, None, None], spins[:, None, None]
            Z = -ww * ww * M + 1j * ww * (C + ss * G) + K + (Ba[None] @ Hk) @ Cs
            X = np.linalg.solve(Z, R)
        return X[:, :, 0] if vec else X
    h = evaluate(model.H, 1j * w)
    if model.sparse:
        ds = DynamicStiffness(model)
        X = np.stack([ds.solve(1j * wk, sk, R[k], h=h[k]) for k, (wk, sk) in enumerate(zip(w, spins))])
    else:
        M, C, G, K, Ba, Ca, Cs = model.dense
        hk = h[:, None] * model.ki[None, :]
        ww, ss = w[:, None, None], spins[:, None, None]
        Z = -ww * ww * M + 1j * ww * (C + ss * G) + K + (Ba[None] * hk[:, None, :]) @ Cs
        X = np.linalg.solve(Z, R)
    return X[:, :, 0] if vec else X
