"""Banded linear algebra of the full FE rung: row-band storage, band matrix-vector products, an
LU factorisation without pivoting and its substitution, all numba kernels that allocate nothing.

Row-band storage of a matrix A with half-bandwidth bw: ``Ab[i, j - i + bw] = A[i, j]``, shape
``(n, 2 bw + 1)`` (node-major FE DOFs keep every rotor matrix banded).
"""
from __future__ import annotations

import numba as nb
import numpy as np
import scipy.sparse as sp


def to_rowband(A, bw: int) -> np.ndarray:
    """Row-band storage (n, 2 bw + 1) of a square (sparse or dense) matrix."""
    A = A.tocoo() if sp.issparse(A) else sp.coo_matrix(np.asarray(A))
    n = A.shape[0]
    R = np.zeros((n, 2 * bw + 1))
    off = A.col - A.row
    if off.size and np.max(np.abs(off)) > bw:
        raise ValueError(f"matrix has entries outside the band {bw}")
    np.add.at(R, (A.row, off + bw), A.data)
    return R


def bandwidth(*mats) -> int:
    bw = 0
    for A in mats:
        A = A.tocoo() if sp.issparse(A) else sp.coo_matrix(np.asarray(A))
        nz = A.data != 0
        if nz.any():
            bw = max(bw, int(np.max(np.abs(A.col[nz] - A.row[nz]))))
    return bw


@nb.njit(cache=True, _nrt=False)
def band_mv(Ad, bw, x, out, alpha, acc):
    """out (+)= alpha * A x, with A in diagonal-major band storage Ad[k, i] = A[i, i - bw + k]
    (independent updates along each diagonal: no serial reduction)."""
    n = x.shape[0]
    if not acc:
        for i in range(n):
            out[i] = 0.0
    for k in range(2 * bw + 1):
        d = k - bw
        i0 = max(0, -d)
        i1 = min(n, n - d)
        for i in range(i0, i1):
            out[i] += alpha * Ad[k, i] * x[i + d]


def diag_major(R: np.ndarray) -> np.ndarray:
    """Row-band (n, 2bw+1) -> diagonal-major (2bw+1, n)."""
    return np.ascontiguousarray(R.T)


@nb.njit(cache=True, _nrt=False)
def band_lu(A, bw):
    """In-place LU without pivoting of a row-band matrix; returns the smallest |pivot|."""
    n = A.shape[0]
    pmin = np.inf
    for k in range(n):
        piv = A[k, bw]
        if abs(piv) < pmin:
            pmin = abs(piv)
        for i in range(k + 1, min(n, k + bw + 1)):
            l = A[i, k - i + bw] / piv
            A[i, k - i + bw] = l
            if l != 0.0:
                for j in range(k + 1, min(n, k + bw + 1)):
                    A[i, j - i + bw] -= l * A[k, j - k + bw]
    return pmin


@nb.njit(cache=True, _nrt=False)
def band_solve(LU, bw, x):
    """Solve in place with a factor from band_lu (column-oriented substitutions)."""
    n = x.shape[0]
    for j in range(n):
        xj = x[j]
        for i in range(j + 1, min(n, j + bw + 1)):
            x[i] -= LU[i, j - i + bw] * xj
    for j in range(n - 1, -1, -1):
        xj = x[j] / LU[j, bw]
        x[j] = xj
        for i in range(max(0, j - bw), j):
            x[i] -= LU[i, j - i + bw] * xj
