"""Closed-loop modes of one model: eigenvalues of the closed loop with their shapes, classified by
whirl and rigid-body share (:class:`Shapes`), at any speed (:class:`Solver`: dense, or
shift-invert on the full rung).

A mode is an eigenvalue ``lambda`` of the closed loop (``Im lambda > 0``) with its shape.  Whirl is
read from the rotor part of the shape: with ``x = Re(X e^{i w t})``, ``y = Re(Y e^{i w t})`` the
forward (with the spin) part of a node's orbit is ``(X + iY)/2`` and the backward part
``(X - iY)/2``; the mode is forward when the forward parts carry most of the orbit energy.
Axial modes (energy mostly in axial DOFs) are labelled ``axial``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from ambhil.plant.rotor import X, Y, Z, rigid_basis
from ..system import System
from . import closed_loop as clmod


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



class Shapes:
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
        self.shapes = Shapes(model)
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
