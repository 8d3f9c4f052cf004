"""Closed-loop eigen-analysis: modes, whirl direction, Campbell diagram and critical speeds.

A mode is an eigenvalue ``lambda`` of the closed loop (``Im lambda > 0``) with its shape.  Whirl is
read from the rotor part of the shape: with ``x = Re(X e^{i w t})``, ``y = Re(Y e^{i w t})`` the
forward (with the spin) part of a node's orbit is ``(X + iY)/2`` and the backward part
``(X - iY)/2``; the mode is forward when the forward parts carry most of the orbit energy.
Axial modes (energy mostly in axial DOFs) are labelled ``axial``.  A critical speed is a spin
speed at which a forward mode's damped frequency equals the speed (``Im lambda(Omega) = Omega``);
it is found by a secant iteration on ``Im lambda(Omega) - Omega`` for each mode branch.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from threadpoolctl import threadpool_limits

from ambhil.plant import reduction
from ambhil.plant.rotor import X, Y, Z, rigid_basis
from ..system import System, compile_system
from . import closed_loop as clmod
from .dynamic_stiffness import DynamicStiffness


@dataclass(frozen=True)
class Mode:
    eigenvalue: complex
    whirl: str  # forward | backward | axial | mixed
    forwardness: float  # (F - B)/(F + B) of the orbit energy, in [-1, 1]
    rigid_fraction: float  # share of the mode's kinetic energy in rigid-body motion
    shape: np.ndarray | None = field(default=None, repr=False, compare=False)  # FE DOF amplitudes

    @property
    def frequency_hz(self) -> float:
        return self.eigenvalue.imag / (2 * np.pi)

    @property
    def damping_ratio(self) -> float:
        return -self.eigenvalue.real / abs(self.eigenvalue)


@dataclass(frozen=True)
class CriticalSpeed:
    speed: float  # rad/s
    damping_ratio: float
    kind: str  # rigid | flexible
    mode: Mode

    @property
    def hz(self) -> float:
        return self.speed / (2 * np.pi)


class _Shapes:
    """Whirl and rigid-fraction classification of eigenvectors of one model."""

    def __init__(self, model: System):
        r = model.rotor
        self.model, self.dpn = model, r.dpn
        Tr = rigid_basis(r)
        self.Tr, self.M = Tr, r.M
        self.Mr_f = sla.cho_factor(Tr.T @ (r.M @ Tr))

    def classify(self, lam: complex, v_eta: np.ndarray) -> Mode:
        m = self.model
        q = v_eta if m.T is None else m.T @ v_eta
        fness, whirl = self.whirl(q[:, None])
        Mq = self.M @ q
        e_tot = float(np.real(np.vdot(q, Mq)))
        a = sla.cho_solve(self.Mr_f, self.Tr.T @ Mq)
        e_rig = float(np.real(np.vdot(a, self.Tr.T @ Mq)))
        rf = e_rig / e_tot if e_tot > 0 else 0.0
        return Mode(complex(lam), whirl[0], float(fness[0]), rf, q)

    def whirl(self, q: np.ndarray) -> tuple[np.ndarray, list[str]]:
        """Forwardness and whirl label of each column of q (FE DOF amplitudes, n_dof x m)."""
        x, y = q[X::self.dpn], q[Y::self.dpn]
        fwd = np.sum(np.abs(x + 1j * y) ** 2, axis=0)
        bwd = np.sum(np.abs(x - 1j * y) ** 2, axis=0)
        tot = fwd + bwd
        fness = np.where(tot > 0, (fwd - bwd) / np.where(tot > 0, tot, 1.0), 0.0)
        ax = np.sum(np.abs(q[Z::self.dpn]) ** 2, axis=0) if self.dpn == 5 else np.zeros(q.shape[1])
        labels = ["axial" if a > t else "forward" if f > 0.2 else "backward" if f < -0.2 else "mixed"
                  for a, t, f in zip(ax, tot, fness)]
        return fness, labels


class Solver:
    """Eigen-solutions of the closed loop of one model at any speed (dense or shift-invert)."""

    def __init__(self, model: System, dense_limit: int = 400):
        self.model = model
        self.shapes = _Shapes(model)
        cl0 = clmod.build(model, 0.0, sparse=True)
        self.use_dense = cl0.size <= dense_limit
        if self.use_dense:  # the closed loop is affine in the speed: E^-1 A = A0 + Omega AG
            self._A0 = cl0.dense_standard()
            self._AG = clmod.build(model, 1.0, sparse=True).dense_standard() - self._A0
        self._cache: dict[float, tuple] = {}

    def _dense(self, speed: float):
        if speed not in self._cache:
            As = self._A0 + speed * self._AG
            self._cache = {speed: (None, As, sla.eigvals(As, check_finite=False))}
        return self._cache[speed]

    def near(self, speed: float, sigma: complex, k: int = 6) -> list[Mode]:
        """The k closed-loop modes (Im > 0) nearest to sigma, classified."""
        n = self.model.n
        out = []
        if self.use_dense:
            cl, As, lam = self._dense(speed)
            cand = lam[lam.imag > 1e-6]
            cand = cand[np.argsort(np.abs(cand - sigma))][:k]
            I = np.eye(As.shape[0])
            rng = np.random.default_rng(0)
            for l in cand:
                v = rng.standard_normal(As.shape[0]) + 0j
                lu = sla.lu_factor(As - (l + 1e-9 * abs(l)) * I, check_finite=False)
                for _ in range(2):
                    v = sla.lu_solve(lu, v, check_finite=False); v /= np.linalg.norm(v)
                out.append(self.shapes.classify(l, v[:n]))
        else:
            cl = clmod.build(self.model, speed, sparse=True)
            lam, V = spla.eigs(cl.A.astype(complex), k=2 * k + 2, M=cl.E.astype(complex), sigma=sigma, which="LM")
            keep = np.where(lam.imag > 1e-6)[0]
            keep = keep[np.argsort(np.abs(lam[keep] - sigma))][:k]
            out = [self.shapes.classify(lam[j], V[:n, j]) for j in keep]
        return out

    def all(self, speed: float, fmax: float) -> list[Mode]:
        """All modes with 0 < Im lambda <= fmax (rad/s), classified, sorted by frequency."""
        if self.use_dense:
            _, _, lam = self._dense(speed)
            sel = lam[(lam.imag > 1e-6) & (lam.imag <= fmax)]
            res = [self.near(speed, l, k=1)[0] for l in sel]
            return sorted(res, key=lambda m: m.eigenvalue.imag)
        # one shift-invert solve about the middle of the band; widen until the band is covered
        cl = clmod.build(self.model, speed, sparse=True)
        k = 40
        while True:
            lam, V = spla.eigs(cl.A.astype(complex), k=min(k, cl.size - 2), M=cl.E.astype(complex),
                              sigma=0.5j * fmax, which="LM")
            inside = (lam.imag > 1e-6) & (lam.imag <= fmax)
            reach = np.max(np.abs(lam - 0.5j * fmax))
            if reach > 0.5 * fmax * 1.05 or k >= cl.size - 2:
                break
            k *= 2
        idx = np.where(inside)[0]
        return sorted((self.shapes.classify(lam[j], V[:self.model.n, j]) for j in idx),
                      key=lambda m: m.eigenvalue.imag)

def _branch(solver: Solver, speed: float, target: float) -> Mode | None:
    """The underdamped mode continuing a branch near ``target``; backward and axial modes are
    excluded ('mixed' stays: degenerate isotropic pairs and elliptic whirl of anisotropic
    bearings, both excited by unbalance)."""
    cand = [m for m in solver.near(speed, 1j * target, k=6)
            if m.whirl in ("forward", "mixed") and m.damping_ratio < 0.5]
    if not cand:
        return None
    return min(cand, key=lambda m: abs(m.eigenvalue.imag - target))


def critical_speeds(model: System, count: int | None = None, speed_max: float | None = None,
                    solver: Solver | None = None, tol: float = 1e-9) -> list[CriticalSpeed]:
    """Forward critical speeds (Im lambda(Omega) = Omega) below speed_max, lowest first: every one
    in the range (``count=None``), or the lowest ``count``.

    Reduced rungs use dense eigenvalues of the closed loop.  The full rung takes its seeds from
    a Craig-Bampton model of the same rotor whose cutoff follows speed_max (``seed_system``; not
    the scene's modal cutoff or sample rate) and refines each critical on the full model by
    nonlinear inverse iteration on det Z(s, Omega) = 0 (banded LU, quadratic convergence)."""
    smax = speed_max or 1.1 * model.scene.analysis.frequency_max
    if model.sparse and solver is None:
        return _refined_on_full(model, count, smax, tol)
    solver = solver or Solver(model)
    # seeds: underdamped lateral modes at standstill (forward and backward coincide there)
    if solver.use_dense:  # eigenvalues suffice: a seed without a forward branch is dropped below
        lam = solver._dense(0.0)[2]
        lam = lam[(lam.imag > 1e-6) & (lam.imag <= smax) & (-lam.real < 0.5 * np.abs(lam))]
        seeds = sorted({round(float(l.imag), 6) for l in lam})
    else:
        seeds = sorted({round(m.eigenvalue.imag, 6) for m in solver.all(0.0, smax)
                        if m.damping_ratio < 0.5 and m.whirl != "axial"})
    found: list[CriticalSpeed] = []
    for w0 in seeds:
        if any(abs(c.speed - w0) < 1e-3 * w0 for c in found):
            continue
        s0, m0 = w0, _branch(solver, w0, w0)
        if m0 is None:
            continue
        g0 = m0.eigenvalue.imag - s0
        s1 = m0.eigenvalue.imag
        m1 = m0
        for _ in range(40):
            m1 = _branch(solver, s1, m0.eigenvalue.imag)
            if m1 is None:
                break
            g1 = m1.eigenvalue.imag - s1
            if abs(g1) <= tol * max(s1, 1.0):
                break
            step = -g1 * (s1 - s0) / (g1 - g0) if g1 != g0 else g1
            s0, g0, m0 = s1, g1, m1
            s1 = max(s1 + step, 1e-3)
        else:
            m1 = None
        if m1 is None or s1 > smax:
            continue
        if not any(abs(c.speed - s1) < 1e-4 * s1 for c in found):
            found.append(CriticalSpeed(speed=s1, damping_ratio=m1.damping_ratio,
                                       kind="rigid" if m1.rigid_fraction > 0.5 else "flexible", mode=m1))
        if count is not None and len(found) >= count and min(seeds[-1], smax) <= max(c.speed for c in found):
            break
    found.sort(key=lambda c: c.speed)
    return found if count is None else found[:count]


#: seeds are sought a little beyond the range: a reduced model's frequencies lie above the full
#: one's, so a critical just below speed_max may seed just above it (refined ones beyond are dropped)
_SEED_MARGIN = 1.01


def seed_system(model: System, speed_max: float) -> System:
    """The Craig-Bampton model that seeds the full rung's critical speeds up to ``speed_max``
    (rad/s): its cutoff follows the analysed range (ambhil.plant.reduction.analysis_cutoff of the seed
    range, 1.01 speed_max), not the controller's sample rate (whose default cutoff serves the
    time-domain loop), so a fast controller does not make the seeds a large eigenproblem.  The FE
    rotor is reused."""
    sc = model.scene
    cut = reduction.analysis_cutoff(_SEED_MARGIN * speed_max / (2 * np.pi))
    sc = sc.with_plant(model=replace(sc.plant.model, modal_cutoff=cut))
    return compile_system(sc, rung="modal", rotor=model.rotor)


def _refined_on_full(model: System, count: int | None, smax: float, tol: float) -> list[CriticalSpeed]:
    seeds = critical_speeds(seed_system(model, smax), count=count, speed_max=_SEED_MARGIN * smax)
    ds, shapes = DynamicStiffness(model), _Shapes(model)
    out = []
    for c in seeds:
        s0 = c.speed
        lam, v = ds.refine(c.mode.eigenvalue, s0, c.mode.shape.astype(complex))
        g0, s1 = lam.imag - s0, lam.imag
        for _ in range(30):
            lam, v = ds.refine(lam, s1, v, iters=2)  # inexact inner solves while the speed moves
            g1 = lam.imag - s1
            if abs(g1) <= 1e-6 * s1:
                lam, v = ds.refine(lam, s1, v)
                g1 = lam.imag - s1
                if abs(g1) <= tol * s1:
                    break
            s0, g0, s1 = s1, g1, s1 - g1 * (s1 - s0) / (g1 - g0) if g1 != g0 else s1 + g1
        m = shapes.classify(lam, v)
        if m.whirl in ("forward", "mixed") and s1 <= smax:
            out.append(CriticalSpeed(speed=s1, damping_ratio=m.damping_ratio,
                                     kind="rigid" if m.rigid_fraction > 0.5 else "flexible", mode=m))
    return sorted(out, key=lambda c: c.speed)


def campbell(model: System, speeds: np.ndarray, fmax: float, progress=None, method: str = "auto") -> dict:
    """Closed-loop damped frequencies (rad/s) of all modes below fmax at each speed.

    ``method="auto"``: reduced rungs take dense eigenvalues per speed; the full rung tracks the
    modes in a small basis (``_campbell_tracked``).  ``method="per-speed"``: every speed solved
    afresh with ``Solver.all`` (ARPACK shift-invert on the full rung), the reference."""
    if method not in ("auto", "per-speed"):
        raise ValueError(f"campbell: method must be 'auto' or 'per-speed', not {method!r}")
    speeds = np.asarray(speeds, dtype=float)
    if method == "auto" and model.sparse and len(speeds) > 2:
        with threadpool_limits(limits=1):  # small dense problems: BLAS threads only cost here
            out = _campbell_tracked(model, speeds, fmax, progress)
        if out is not None:
            return out
    solver = Solver(model)
    rows = []
    for k, s in enumerate(speeds):
        for m in solver.all(float(s), fmax):
            rows.append((float(s), m.eigenvalue.imag, m.damping_ratio, m.whirl))
        if progress:
            progress(k + 1, len(speeds))
    return _campbell_dict(rows)


def _campbell_dict(rows, **extra) -> dict:
    a = np.array([(r[0], r[1], r[2]) for r in rows]) if rows else np.zeros((0, 3))
    return {"speed": a[:, 0], "freq": a[:, 1], "zeta": a[:, 2], "whirl": np.array([r[3] for r in rows]), **extra}


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


class _SelectedEig:
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
        if _SelectedEig._fns is None:
            import ctypes
            from numba.extending import get_cython_function_address
            f = lambda name, k: ctypes.CFUNCTYPE(None, *[ctypes.c_void_p] * k)(
                get_cython_function_address("scipy.linalg.cython_lapack", name))
            _SelectedEig._fns = (f("dgehrd", 9), f("dhseqr", 14), f("dhsein", 19), f("dormhr", 14))
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


def _rmul(Q, Y: np.ndarray) -> np.ndarray:
    """Q @ Y for real Q (dense or sparse) and complex Y as one real product of Q with the
    interleaved real and imaginary parts (no complex copy of Q, no products with its zero
    imaginary part)."""
    k = Y.shape[1]
    return (Q @ np.ascontiguousarray(Y).view(np.float64)).view(np.complex128).reshape(Q.shape[0], k)


def _campbell_tracked(model: System, speeds: np.ndarray, fmax: float, progress=None,
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
    output region only (``_SelectedEig``).  Output region: 0 < Im lam <= fmax and
    ``|lam - i fmax/2| <= 0.8 fmax``, which holds every in-band mode with zeta <= 0.5.
    Checks: at the midpoint of every speed interval the exact eigenvalues are computed again
    (complex shift at the disk's centre, the most accurate solve) and the Ritz values of the
    output region must match them one to one (same count, relative error <= check_tol); where
    they do not, that speed's shapes join the basis and both halves are checked again (at most
    max_depth levels).  At every speed a Ritz pair whose componentwise
    backward error on the full matrices exceeds 1e-6 is refined by nonlinear inverse iteration on
    the banded Z(s) (DynamicStiffness.refine); if that does not settle the pair, the speed is
    solved afresh with ARPACK.  Returns None (the caller falls back) if the checks fail."""
    shapes, n = _Shapes(model), model.n
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
    centre, r_out, r_basis = 0.5j * fmax, 0.8 * fmax, margin * fmax
    lo, hi = float(speeds.min()), float(speeds.max())

    def exact(w, vectors=True):
        return _eigs_in_disk(A0 + w * A1, E, centre, r_basis, k=k0, vectors=vectors)

    # anchors: the same eigenpairs from a disk about a real centre that holds the basis area
    # (the disk above with 0 <= Im <= 1.1 fmax), in real arithmetic (half the time of the
    # complex solve).  Only their shapes are used; the midpoint check keeps the complex solve,
    # whose eigenvalues are the more accurate (backward error 1e-16 against 1e-12 here).  The
    # centre -0.2 fmax: closer to the origin the shapes lose accuracy (Ritz values at the anchor
    # 1e-7 off with -0.05 fmax, 1e-9 with -0.2 fmax), farther the disk holds more eigenvalues.
    c_real = -0.2 * fmax
    arc = centre + r_basis * np.exp(1j * np.linspace(0.0, 2 * np.pi, 1441))
    y = 1.1 * fmax - centre.imag
    top = np.sqrt(max(r_basis ** 2 - y ** 2, 0.0)) * np.array([-1.0, 1.0]) + 1j * 1.1 * fmax
    area = np.concatenate([arc[(arc.imag >= 0) & (arc.imag <= 1.1 * fmax)], top])
    r_real = 1.01 * float(np.max(np.abs(area - c_real)))

    def anchor(w):
        return _eigs_in_disk(A0 + w * A1, E, c_real, r_real, k=k_real)

    def region(lam):
        return (lam.imag > 1e-6) & (lam.imag <= fmax) & (np.abs(lam - centre) <= r_out)

    def shape_cols(lam, V):
        # rotor shapes of the upper half plane up to a little above the band (conjugates add
        # nothing: their real and imaginary parts span the same space)
        keep = (lam.imag >= -1e-9 * np.abs(lam)) & (lam.imag <= 1.1 * fmax) & (np.abs(lam - centre) <= r_basis)
        q = V[:n, keep] / np.linalg.norm(V[:n, keep], axis=0)
        return [q.real, q.imag]

    cols = []
    for w in (lo, hi):
        got = anchor(w)
        if got is None:
            return None
        cols += shape_cols(*got)

    def project():
        U, sv, _ = np.linalg.svd(np.hstack(cols), full_matrices=False)
        Q = U[:, :int(np.sum(sv > basis_tol * sv[0]))]
        r = Q.shape[1]
        Wb = np.zeros((2 * n + nx, 2 * r + nx))  # blkdiag(Q, Q, I)
        Wb[:n, :r], Wb[n:2 * n, r:2 * r], Wb[2 * n:, 2 * r:] = Q, Q, np.eye(nx)
        Er = Wb.T @ (E @ Wb)
        S0 = np.linalg.solve(Er, Wb.T @ (A0 @ Wb))
        S1 = np.linalg.solve(Er, Wb.T @ (A1 @ Wb))
        # one diagonal similarity (LAPACK's balancing, scaling only) for every speed
        d = sla.lapack.dgebal(np.abs(S0) + max(abs(lo), abs(hi)) * np.abs(S1), scale=1)[3]
        S0, S1 = S0 / d[:, None] * d, S1 / d[:, None] * d
        return Q, Wb, np.asfortranarray(S0), np.asfortranarray(S1), d

    def ritz(basis, w, vectors=True):
        Q, Wb, S0, S1, d = basis
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

    basis = project()
    se = _SelectedEig(basis[2].shape[0])
    todo, checks = [(lo, hi, 1)], 0
    while todo:
        a, b, depth = todo.pop()
        w = 0.5 * (a + b)
        got = exact(w, vectors=False)  # the eigenvalues decide; shapes only if they are needed
        if got is None:
            return None
        checks += 1
        ref = got[0][region(got[0])]
        lam = ritz(basis, w, vectors=False)[0]
        ok = len(ref) == len(lam) and all(np.min(np.abs(lam - l)) <= check_tol * abs(l) for l in ref)
        if not ok:
            if depth >= max_depth:
                return None
            cols += shape_cols(*exact(w))
            basis = project()
            se = _SelectedEig(basis[2].shape[0])
            todo += [(a, w, depth + 1), (w, b, depth + 1)]

    Q, Wb, S0, S1, _ = basis
    per_speed = []
    for k, w in enumerate(speeds):
        per_speed.append(ritz(basis, float(w)))
        if progress:
            progress(k + 1, len(speeds))
    # every speed's Ritz pairs checked on the full model at once: the componentwise backward
    # error (residual against the size of the terms that cancel in it)
    cnt = [len(lam) for lam, _ in per_speed]
    lam = np.concatenate([l for l, _ in per_speed])
    ws = np.repeat(speeds, cnt)
    Y = np.hstack([y for _, y in per_speed]) if lam.size else np.zeros((S0.shape[0], 0))
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
    res = np.sqrt(r2) / np.maximum(np.sqrt(s2), 1e-300)
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


def least_damped(model: System, speed: float, fmax: float = 1e9) -> Mode:
    """The closed-loop mode of lowest damping ratio below fmax (rad/s) at a speed."""
    return min(Solver(model).all(speed, fmax), key=lambda m: m.damping_ratio)
