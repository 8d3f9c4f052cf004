"""Eigenvalues of a real dense matrix, and right eigenvectors of selected ones only, by LAPACK
routines scipy.linalg does not wrap (the dense eigenproblems of the tracked Campbell diagram,
``loop/analysis/campbell_tracked.py``)."""
from __future__ import annotations

import numpy as np


class SelectedEig:
    """Eigenvalues of a real dense n x n matrix, and right eigenvectors of the selected ones only.

    ``sla.eig`` computes every eigenvector: Schur vectors during the QR iteration, then all n
    vectors, about 2x the flops of the eigenvalues.  Here: Hessenberg reduction (``dgehrd``),
    eigenvalues only (``dhseqr``), then inverse iteration on the Hessenberg form for the selected
    eigenvalues (``dhsein``, O(n^2) each) and the back-transformation of those vectors
    (``dormhr``).  LAPACK through scipy.linalg.cython_lapack (scipy.linalg wraps neither dhseqr
    nor dhsein), called with ctypes on buffers allocated once; the caller falls back to
    ``sla.eig`` when a routine reports a failure (``None`` returned)."""

    _fns = None

    def __init__(self, n: int):
        if SelectedEig._fns is None:
            import ctypes
            from numba.extending import get_cython_function_address
            f = lambda name, k: ctypes.CFUNCTYPE(None, *[ctypes.c_void_p] * k)(
                get_cython_function_address("scipy.linalg.cython_lapack", name))
            SelectedEig._fns = (f("dgehrd", 9), f("dhseqr", 14), f("dhsein", 19), f("dormhr", 14))
        self.n = n
        # every buffer lives as long as the object; LAPACK gets their addresses (ints)
        i32 = lambda v: np.array([v], dtype=np.int32)
        self._ints = [i32(n), i32(1), i32(0), i32(0), i32(0)]  # n, 1, info, m, mm
        lw = max(64 * n, (n + 2) * n)
        self._work, self._lwork = np.empty(lw), i32(lw)
        self._Hr, self._H, self._Hw = (np.empty((n, n), order="F") for _ in range(3))
        self._tau, self._wr, self._wi = np.empty(max(n - 1, 1)), np.empty(n), np.empty(n)
        self._wr2, self._wi2, self._dummy = np.empty(n), np.empty(n), np.empty(1)
        self._select, self._ifl, self._ifr = (np.zeros(n + 1, np.int32) for _ in range(3))
        self._ch = {c: np.frombuffer(c, dtype=np.uint8).copy() for c in (b"E", b"N", b"R", b"Q", b"L")}
        self._below = np.flatnonzero(np.tril(np.ones((n, n), bool), -2).ravel(order="F"))
        ad = lambda a: a.ctypes.data
        self._a = {k: ad(v) for k, v in dict(
            n=self._ints[0], one=self._ints[1], info=self._ints[2], m=self._ints[3], mm=self._ints[4],
            work=self._work, lwork=self._lwork, Hr=self._Hr, H=self._H, Hw=self._Hw, tau=self._tau,
            wr=self._wr, wi=self._wi, wr2=self._wr2, wi2=self._wi2, dummy=self._dummy,
            select=self._select, ifl=self._ifl, ifr=self._ifr).items()}
        self._a.update({c.decode(): ad(v) for c, v in self._ch.items()})

    def eigvals(self, S: np.ndarray):
        """Eigenvalues of S; keeps the Hessenberg form for ``vectors``. None if LAPACK fails."""
        a, info = self._a, self._ints[2]
        self._Hr[...] = S
        self._fns[0](a["n"], a["one"], a["n"], a["Hr"], a["n"], a["tau"], a["work"], a["lwork"], a["info"])
        if info[0]:
            return None
        self._H[...] = self._Hr
        self._H.ravel(order="K")[self._below] = 0.0  # the reflectors below the subdiagonal
        self._Hw[...] = self._H
        self._fns[1](a["E"], a["N"], a["n"], a["one"], a["n"], a["Hw"], a["n"], a["wr"], a["wi"],
                     a["dummy"], a["one"], a["work"], a["lwork"], a["info"])
        if info[0]:
            return None
        return self._wr + 1j * self._wi

    def vectors(self, sel: np.ndarray):
        """Right eigenvectors (columns, complex) of the eigenvalues ``sel`` (ascending indices
        into the last ``eigvals`` result, each with Im >= 0).  None if LAPACK fails."""
        a, info, n = self._a, self._ints[2], self.n
        if len(sel) == 0:
            return np.zeros((n, 0), dtype=complex)
        self._select[:] = 0
        self._select[sel] = 1
        cplx = self._wi[sel] != 0
        mm = int(len(sel) + np.sum(cplx))
        self._ints[4][0] = mm
        vr = np.zeros((n, max(mm, 1)), order="F")
        self._wr2[...], self._wi2[...] = self._wr, self._wi  # dhsein may perturb close eigenvalues
        self._fns[2](a["R"], a["Q"], a["N"], a["select"], a["n"], a["H"], a["n"], a["wr2"], a["wi2"],
                     a["dummy"], a["one"], vr.ctypes.data, a["n"], a["mm"], a["m"], a["work"], a["ifl"],
                     a["ifr"], a["info"])
        if info[0] or self._ints[3][0] != mm:
            return None
        self._fns[3](a["L"], a["N"], a["n"], a["mm"], a["one"], a["n"], a["Hr"], a["n"], a["tau"],
                     vr.ctypes.data, a["n"], a["work"], a["lwork"], a["info"])
        if info[0]:
            return None
        # one column per real eigenvalue, (re, im) column pairs per complex one, in order
        first = np.concatenate([[0], np.cumsum(np.where(cplx, 2, 1))[:-1]]).astype(int)
        V = vr[:, first].astype(complex)
        V[:, cplx] += 1j * vr[:, first[cplx] + 1]
        return V
