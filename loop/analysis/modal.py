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

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from plant.rotor import X, Y, Z, rigid_basis
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
        x, y = q[X::self.dpn], q[Y::self.dpn]
        fwd = np.sum(np.abs(x + 1j * y) ** 2)
        bwd = np.sum(np.abs(x - 1j * y) ** 2)
        tot = fwd + bwd
        fness = float((fwd - bwd) / tot) if tot > 0 else 0.0
        ax = np.sum(np.abs(q[Z::self.dpn]) ** 2) if self.dpn == 5 else 0.0
        Mq = self.M @ q
        e_tot = float(np.real(np.vdot(q, Mq)))
        a = sla.cho_solve(self.Mr_f, self.Tr.T @ Mq)
        e_rig = float(np.real(np.vdot(a, self.Tr.T @ Mq)))
        rf = e_rig / e_tot if e_tot > 0 else 0.0
        if ax > tot:
            whirl = "axial"
        elif fness > 0.2:
            whirl = "forward"
        elif fness < -0.2:
            whirl = "backward"
        else:
            whirl = "mixed"
        return Mode(complex(lam), whirl, fness, rf, q)


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
    the Craig-Bampton model of the same scene and refines each critical on the full model by
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


def _refined_on_full(model: System, count: int | None, smax: float, tol: float) -> list[CriticalSpeed]:
    seed_model = compile_system(model.scene, rung="modal", rotor=model.rotor)
    seeds = critical_speeds(seed_model, count=count, speed_max=smax)
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


def campbell(model: System, speeds: np.ndarray, fmax: float, progress=None) -> dict:
    """Closed-loop damped frequencies (rad/s) of all modes below fmax at each speed."""
    solver = Solver(model)
    rows = []
    for k, s in enumerate(speeds):
        for m in solver.all(float(s), fmax):
            rows.append((float(s), m.eigenvalue.imag, m.damping_ratio, m.whirl))
        if progress:
            progress(k + 1, len(speeds))
    a = np.array([(r[0], r[1], r[2]) for r in rows]) if rows else np.zeros((0, 3))
    return {"speed": a[:, 0], "freq": a[:, 1], "zeta": a[:, 2], "whirl": np.array([r[3] for r in rows])}


def least_damped(model: System, speed: float, fmax: float = 1e9) -> Mode:
    """The closed-loop mode of lowest damping ratio below fmax (rad/s) at a speed."""
    return min(Solver(model).all(speed, fmax), key=lambda m: m.damping_ratio)
