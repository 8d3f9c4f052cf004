"""The Campbell diagram of the full rung by projection on the modes' own shapes
(:func:`campbell_tracked`, what :func:`ambhil.loop.analysis.modal.campbell` does there by
default): one small dense eigenproblem per speed, checked against exact solves and refined on
the full model where a Ritz pair is not an eigenpair yet."""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..system import System
from . import closed_loop as clmod
from .dynamic_stiffness import DynamicStiffness
from .modes import Shapes, Solver
from .selected_eig import SelectedEig


def _eigs_in_disk(A, E, centre: complex, radius: float, k: int = 32, vectors: bool = True):
    """Every eigenpair of ``A x = lam E x`` with ``|lam - centre| <= radius``: ARPACK on the
    shift-inverted operator (A - centre E)^-1 E (one sparse LU; standard mode, which is cheaper
    than ARPACK's generalized mode here).  The k eigenvalues nearest the centre come back; k is
    doubled until some of them lie beyond the disk, so the set inside is complete.  With
    ``vectors=False`` only the eigenvalues (V is None; ARPACK skips the Ritz vectors)."""
    N = A.shape[0]
    # a real centre keeps real arithmetic (LU, Arnoldi): about half the time of a complex one
    dt = float if complex(centre).imag == 0 and not np.iscomplexobj(A.data) else complex
    lu = spla.splu(sp.csc_matrix(A - centre * E, dtype=dt))
    Ed = sp.csr_matrix(E, dtype=dt)  # converted once, not at every product
    op = spla.LinearOperator((N, N), matvec=lambda x: lu.solve(Ed @ x), dtype=dt)
    while True:
        k = min(k, N - 2)
        got = spla.eigs(op, k=k, which="LM", return_eigenvectors=vectors)
        mu, V = got if vectors else (got, None)
        lam = centre + 1.0 / mu
        dist = np.abs(lam - centre)
        if dist.max() > 1.1 * radius or k >= N - 2:
            inside = dist <= radius
            return lam[inside], (V[:, inside] if vectors else None)
        k *= 2


def _rmul(Q, Y: np.ndarray) -> np.ndarray:
    """Q @ Y for real Q (dense or sparse) and complex Y as one real product of Q with the
    interleaved real and imaginary parts (no complex copy of Q, no products with its zero
    imaginary part)."""
    k = Y.shape[1]
    return (Q @ np.ascontiguousarray(Y).view(np.float64)).view(np.complex128).reshape(Q.shape[0], k)


def campbell_tracked(model: System, speeds: np.ndarray, fmax: float, progress=None,
                     check_tol: float = 1e-6, max_depth: int = 4, basis_tol: float = 3e-6,
                     margin: float = 0.8, k0: int = 32, k_real: int = 52) -> dict | None:
    """Campbell diagram of the full rung by projection on the modes' own shapes.

    The closed loop is affine in the spin speed, ``A(W) = A0 + W A1`` with ``E`` constant.  The
    exact eigenpairs in the disk ``|lam - i fmax/2| <= margin fmax`` at the lowest and highest
    speed give the rotor shapes of the upper half plane up to 1.1 fmax (computed from a larger
    disk about the real point -0.2 fmax, in real arithmetic: ``_eigs_in_disk``); their real and
    imaginary parts, orthonormalised (SVD, rank to basis_tol), form a basis Q and the closed
    loop is projected on blkdiag(Q, Q, I) (rotor displacements and rates on Q, controller states
    kept), which keeps the second-order structure.  Each speed then costs one dense eigenproblem
    of size 2 rank(Q) + n_controller: its eigenvalues (Hessenberg QR), then eigenvectors of the
    output region only (``SelectedEig``).  Output region: 0 < Im lam <= fmax and
    ``|lam - i fmax/2| <= 0.8 fmax``, which holds every in-band mode with zeta <= 0.5.
    Checks: at the midpoint of every speed interval the exact eigenvalues are computed again
    (complex shift at the disk's centre, the most accurate solve) and the Ritz values of the
    output region must match them one to one (same count, relative error <= check_tol); where
    they do not, that speed's shapes join the basis and both halves are checked again (at most
    max_depth levels).  At every speed a Ritz pair whose componentwise
    backward error on the full matrices exceeds 1e-6 is refined by nonlinear inverse iteration on
    the banded Z(s) (DynamicStiffness.refine); if that does not settle the pair, the speed is
    solved afresh with ARPACK.  Returns None (the caller falls back) if the checks fail."""
    loop = _affine_loop(model)
    if loop is None:
        return None
    tr = _Tracker(model.n, *loop, fmax, float(speeds.min()), float(speeds.max()), margin, basis_tol, k0, k_real)
    checks = _checked_basis(tr, check_tol, max_depth)
    if checks is None:
        return None
    per_speed = []
    for k, w in enumerate(speeds):
        per_speed.append(tr.ritz(float(w)))
        if progress:
            progress(k + 1, len(speeds))
    return _verified(model, tr, speeds, fmax, per_speed, checks)


def _affine_loop(model: System):
    """``(A0, A1, E, nx)`` of the closed loop ``A(W) = A0 + W A1``, ``E`` constant (CSR; nx the
    controller states); None where the matrices lack the block structure the checks rely on."""
    n = model.n
    cl0 = clmod.build(model, 0.0, sparse=True)
    nx = cl0.size - 2 * n
    # the speed enters only through the gyroscopic matrix in the rate equation (D = C + W G)
    A0, E = cl0.A.tocsr(), cl0.E.tocsr()
    A1 = sp.block_diag([sp.csr_matrix((n, n)), -sp.csr_matrix(model.G), sp.csr_matrix((nx, nx))], format="csr")
    # the residual check below works by blocks: A0 = [[0, I, 0], [., ., .], [., 0, .]] and
    # E = blkdiag(I, M, I) as closed_loop.build documents; anything else -> the per-speed path
    I_n = sp.identity(n, format="csr")
    if (abs(A0[:n] - sp.hstack([sp.csr_matrix((n, n)), I_n, sp.csr_matrix((n, nx))])).max() != 0
            or (nx and abs(A0[2 * n:, n:2 * n]).max() != 0)
            or abs(E - sp.block_diag([I_n, E[n:2 * n, n:2 * n], sp.identity(nx)])).max() != 0):
        return None
    return A0, A1, E, nx


class _Tracker:
    """The projection basis of the tracked Campbell diagram and the eigenproblems around it: the
    exact ones on the full matrices (:meth:`exact`, :meth:`anchor`), the projected ones
    (:meth:`ritz`)."""

    def __init__(self, n, A0, A1, E, nx, fmax, lo, hi, margin, basis_tol, k0, k_real):
        self.n, self.A0, self.A1, self.E, self.nx = n, A0, A1, E, nx
        self.fmax, self.lo, self.hi = fmax, lo, hi
        self.basis_tol, self.k0, self.k_real = basis_tol, k0, k_real
        self.centre, self.r_out, self.r_basis = 0.5j * fmax, 0.8 * fmax, margin * fmax
        centre, r_basis = self.centre, self.r_basis
        # anchors: the same eigenpairs from a disk about a real centre that holds the basis area
        # (the disk above with 0 <= Im <= 1.1 fmax), in real arithmetic (half the time of the
        # complex solve).  Only their shapes are used; the midpoint check keeps the complex solve,
        # whose eigenvalues are the more accurate (backward error 1e-16 against 1e-12 here).  The
        # centre -0.2 fmax: closer to the origin the shapes lose accuracy (Ritz values at the anchor
        # 1e-7 off with -0.05 fmax, 1e-9 with -0.2 fmax), farther the disk holds more eigenvalues.
        self.c_real = c_real = -0.2 * fmax
        arc = centre + r_basis * np.exp(1j * np.linspace(0.0, 2 * np.pi, 1441))
        y = 1.1 * fmax - centre.imag
        top = np.sqrt(max(r_basis ** 2 - y ** 2, 0.0)) * np.array([-1.0, 1.0]) + 1j * 1.1 * fmax
        area = np.concatenate([arc[(arc.imag >= 0) & (arc.imag <= 1.1 * fmax)], top])
        self.r_real = 1.01 * float(np.max(np.abs(area - c_real)))
        self.cols = []  # the rotor shapes (real and imaginary parts) the basis spans
        self.basis = self.se = None

    def exact(self, w, vectors=True):
        return _eigs_in_disk(self.A0 + w * self.A1, self.E, self.centre, self.r_basis, k=self.k0, vectors=vectors)

    def anchor(self, w):
        return _eigs_in_disk(self.A0 + w * self.A1, self.E, self.c_real, self.r_real, k=self.k_real)

    def region(self, lam):
        return (lam.imag > 1e-6) & (lam.imag <= self.fmax) & (np.abs(lam - self.centre) <= self.r_out)

    def add_shapes(self, lam, V):
        """Rotor shapes of the upper half plane up to a little above the band join the basis
        (conjugates add nothing: their real and imaginary parts span the same space)."""
        n, fmax, centre, r_basis = self.n, self.fmax, self.centre, self.r_basis
        keep = (lam.imag >= -1e-9 * np.abs(lam)) & (lam.imag <= 1.1 * fmax) & (np.abs(lam - centre) <= r_basis)
        q = V[:n, keep] / np.linalg.norm(V[:n, keep], axis=0)
        self.cols += [q.real, q.imag]

    def project(self):
        """The basis Q of the shapes so far and the loop projected on it, ``basis = (Q, Wb, S0,
        S1, d)``, with a dense eigensolver of its size."""
        n, nx, E, A0, A1, lo, hi = self.n, self.nx, self.E, self.A0, self.A1, self.lo, self.hi
        U, sv, _ = np.linalg.svd(np.hstack(self.cols), full_matrices=False)
        Q = U[:, :int(np.sum(sv > self.basis_tol * sv[0]))]
        r = Q.shape[1]
        Wb = np.zeros((2 * n + nx, 2 * r + nx))  # blkdiag(Q, Q, I)
        Wb[:n, :r], Wb[n:2 * n, r:2 * r], Wb[2 * n:, 2 * r:] = Q, Q, np.eye(nx)
        Er = Wb.T @ (E @ Wb)
        S0 = np.linalg.solve(Er, Wb.T @ (A0 @ Wb))
        S1 = np.linalg.solve(Er, Wb.T @ (A1 @ Wb))
        # one diagonal similarity (LAPACK's balancing, scaling only) for every speed
        d = sla.lapack.dgebal(np.abs(S0) + max(abs(lo), abs(hi)) * np.abs(S1), scale=1)[3]
        S0, S1 = S0 / d[:, None] * d, S1 / d[:, None] * d
        self.basis = Q, Wb, np.asfortranarray(S0), np.asfortranarray(S1), d
        self.se = SelectedEig(S0.shape[0])

    def ritz(self, w, vectors=True):
        """Ritz values (and vectors in the projected coordinates) of the output region at speed w."""
        se, region = self.se, self.region
        Q, Wb, S0, S1, d = self.basis
        S = S0 + w * S1
        lam = se.eigvals(S) if se is not None and se.n == S.shape[0] else None
        if lam is not None:
            sel = np.where(region(lam))[0]
            if not vectors:
                return lam[sel], None
            Yv = se.vectors(sel)
            if Yv is not None:
                return lam[sel], Yv * d[:, None]
        lam, Yv = sla.eig(S, check_finite=False)
        sel = region(lam)
        return lam[sel], Yv[:, sel] * d[:, None]


def _checked_basis(tr: _Tracker, check_tol: float, max_depth: int) -> int | None:
    """The basis from the anchors at the lowest and highest speed, grown where the midpoint check
    of a speed interval fails; returns the number of checks, None if they fail."""
    for w in (tr.lo, tr.hi):
        got = tr.anchor(w)
        if got is None:
            return None
        tr.add_shapes(*got)
    tr.project()
    todo, checks = [(tr.lo, tr.hi, 1)], 0
    while todo:
        a, b, depth = todo.pop()
        w = 0.5 * (a + b)
        got = tr.exact(w, vectors=False)  # the eigenvalues decide; shapes only if they are needed
        if got is None:
            return None
        checks += 1
        ref = got[0][tr.region(got[0])]
        lam = tr.ritz(w, vectors=False)[0]
        ok = len(ref) == len(lam) and all(np.min(np.abs(lam - l)) <= check_tol * abs(l) for l in ref)
        if not ok:
            if depth >= max_depth:
                return None
            tr.add_shapes(*tr.exact(w))
            tr.project()
            todo += [(a, w, depth + 1), (w, b, depth + 1)]
    return checks


def _backward_errors(tr: _Tracker, lam, ws, Y):
    """The componentwise backward error on the full model (residual against the size of the terms
    that cancel in it) of every Ritz pair ``lam``, ``Y`` (speeds ``ws``), and their rotor shapes."""
    n, A0, A1, E, Q = tr.n, tr.A0, tr.A1, tr.E, tr.basis[0]
    r = Q.shape[1]
    q, v, c = _rmul(Q, Y[:r]), _rmul(Q, Y[r:2 * r]), np.ascontiguousarray(Y[2 * r:])
    # by blocks: A0 = [[0, I, 0], [Aq, Av, Ac], [Cq, 0, Cc]], A1 = blkdiag(0, G1, 0) and
    # E = blkdiag(I, M, I); one sparse product per block column (q, v, c)
    bq, bv, bc = (sp.vstack(b, format="csr") for b in (
        [A0[n:2 * n, :n], A0[2 * n:, :n]], [A0[n:2 * n, n:2 * n], A1[n:2 * n, n:2 * n], E[n:2 * n, n:2 * n]],
        [A0[n:2 * n, 2 * n:], A0[2 * n:, 2 * n:]]))
    Pq, Pv, Pc = _rmul(bq, q), _rmul(bv, v), _rmul(bc, c)
    aq, av, ac, al = np.abs(q), np.abs(v), np.abs(c), np.abs(lam)
    Sq, Sv, Sc = abs(bq) @ aq, abs(bv) @ av, abs(bc) @ ac
    r2 = (np.sum(np.abs(v - q * lam) ** 2, axis=0)
          + np.sum(np.abs(Pq[:n] + Pv[:n] + Pc[:n] + Pv[n:2 * n] * ws - Pv[2 * n:] * lam) ** 2, axis=0)
          + np.sum(np.abs(Pq[n:] + Pc[n:] - c * lam) ** 2, axis=0))
    s2 = (np.sum((av + aq * al) ** 2, axis=0)
          + np.sum((Sq[:n] + Sv[:n] + Sc[:n] + Sv[n:2 * n] * ws + Sv[2 * n:] * al) ** 2, axis=0)
          + np.sum((Sq[n:] + Sc[n:] + ac * al) ** 2, axis=0))
    return np.sqrt(r2) / np.maximum(np.sqrt(s2), 1e-300), q


def _verified(model: System, tr: _Tracker, speeds, fmax, per_speed, checks) -> dict:
    """Every speed's Ritz pairs checked on the full model at once (:func:`_backward_errors`): a
    pair that is not an eigenpair yet is refined by nonlinear inverse iteration, a speed where
    that does not settle it is solved afresh with ARPACK."""
    shapes, region, S0 = Shapes(model), tr.region, tr.basis[2]
    cnt = [len(lam) for lam, _ in per_speed]
    lam = np.concatenate([l for l, _ in per_speed])
    ws = np.repeat(speeds, cnt)
    Y = np.hstack([y for _, y in per_speed]) if lam.size else np.zeros((S0.shape[0], 0))
    res, q = _backward_errors(tr, lam, ws, Y)
    whirl = np.array(shapes.whirl(q)[1], dtype=object)
    spk = np.repeat(np.arange(len(speeds)), cnt)  # speed index of every Ritz pair
    redo = np.zeros(len(speeds), dtype=bool)
    ds, refined = None, 0
    for j in np.where(res > 1e-6)[0]:  # a Ritz pair that is not an eigenpair yet: refine it on the full model
        if redo[spk[j]]:
            continue
        ds = ds or DynamicStiffness(model)
        l2, v2 = ds.refine(complex(lam[j]), float(ws[j]), q[:, j].astype(complex))
        if not (abs(l2 - lam[j]) <= 1e-3 * abs(lam[j]) and region(np.array([l2]))[0]):
            redo[spk[j]] = True  # not trustworthy at this speed: it is solved afresh below
            continue
        lam[j] = l2
        whirl[j] = shapes.whirl(v2[:, None])[1][0]
        refined += 1
    keep = ~redo[spk]
    sk, ls, wh = spk[keep], lam[keep], whirl[keep]
    solver = None
    for k in np.where(redo)[0]:
        solver = solver or Solver(model)
        ms = solver.all(float(speeds[k]), fmax)
        sk = np.concatenate([sk, np.full(len(ms), k)])
        ls = np.concatenate([ls, [m.eigenvalue for m in ms]])
        wh = np.concatenate([wh, np.array([m.whirl for m in ms], dtype=object)])
    o = np.lexsort((ls.imag, sk))  # by speed (in the given order), then by frequency
    ls = ls[o]
    return {"speed": speeds[sk[o]].astype(float), "freq": ls.imag.copy(), "zeta": -ls.real / np.abs(ls),
            "whirl": np.array(list(wh[o])),
            "basis_size": S0.shape[0], "checks": checks, "refined": refined, "fallback": int(redo.sum())}
