"""Closed-loop critical speeds and the Campbell diagram, from the closed-loop modes of
``loop/analysis/modes.py`` (:class:`Mode`, :class:`Solver`; whirl and rigid fraction there).

A critical speed is a spin speed at which a forward mode's damped frequency equals the speed
(``Im lambda(Omega) = Omega``); it is found by a secant iteration on ``Im lambda(Omega) - Omega``
for each mode branch.  The Campbell diagram is every mode's damped frequency over the speed; the
full rung tracks the modes in a small basis (``loop/analysis/campbell_tracked.py``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from threadpoolctl import threadpool_limits

from ambhil.plant import reduction
from ..system import System, compile_system
from .campbell_tracked import campbell_tracked
from .dynamic_stiffness import DynamicStiffness
from .modes import Mode, Shapes, Solver


@dataclass(frozen=True)
class CriticalSpeed:
    speed: float  # rad/s
    damping_ratio: float
    kind: str  # rigid | flexible
    mode: Mode

    @property
    def hz(self) -> float:
        return self.speed / (2 * np.pi)


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
    ds, shapes = DynamicStiffness(model), Shapes(model)
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
    modes in a small basis (:func:`ambhil.loop.analysis.campbell_tracked.campbell_tracked`).  ``method="per-speed"``: every speed solved
    afresh with ``Solver.all`` (ARPACK shift-invert on the full rung), the reference."""
    if method not in ("auto", "per-speed"):
        raise ValueError(f"campbell: method must be 'auto' or 'per-speed', not {method!r}")
    speeds = np.asarray(speeds, dtype=float)
    if method == "auto" and model.sparse and len(speeds) > 2:
        with threadpool_limits(limits=1):  # small dense problems: BLAS threads only cost here
            out = campbell_tracked(model, speeds, fmax, progress)
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


def least_damped(model: System, speed: float, fmax: float = 1e9) -> Mode:
    """The closed-loop mode of lowest damping ratio below fmax (rad/s) at a speed."""
    return min(Solver(model).all(speed, fmax), key=lambda m: m.damping_ratio)
