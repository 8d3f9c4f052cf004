"""ISO 14839-3 sensitivity, open-loop margins and stability over the scene's operating speeds.

The closed loop changes with the spin speed (gyroscopic coupling splits every mode into a forward
and a backward whirl), so a figure taken at one speed is not the scene's: paper_3amb's worst
sensitivity is 6.90 at standstill, 4.71 at the top of its range.  The operating speeds
(:func:`operating_intervals`) are the ``[speed]`` value or range, the ``[simulation] speed`` and the
``[simulation] run_up`` range.

:func:`scan` evaluates, at every speed of a coarse grid over each range (``points`` per range,
ends included) and at every named speed: the least-damped closed-loop mode (every mode up to
``fmax``), the sensitivity of every axis (its peaks refined at the loop's poles, sensitivity.py)
and the open loop's margins per axis (margins.py), both from one evaluation of S on a log grid
0.1 Hz - 5 kHz merged with the poles' frequencies.  Then, per axis, the speed of the largest peak
is refined: at an end of a range, one evaluation just inside tells whether the peak still rises
inwards; elsewhere (or when it does) a bounded scalar search between the neighbouring grid speeds
(sensitivity only; every evaluation is kept).  An axis' worst peak is the largest peak over every
evaluated speed, so it is a direct evaluation at the speed reported with it.  The margins are the
least over the grid's speeds (not refined in speed).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from ..system import System
from . import margins as marg
from . import sensitivity as sensmod


def operating_intervals(scene) -> list[tuple[float, float, str]]:
    """The scene's operating speeds as ``(lo, hi, source)`` in rad/s; a single speed has lo == hi."""
    sp, sim = scene.plant.speed, scene.plant.simulation
    out = [(float(sp.value), float(sp.value), "[speed] value") if sp.value is not None
           else (float(sp.start), float(sp.stop), "[speed] range")]
    if sim.speed is not None:
        out.append((float(sim.speed), float(sim.speed), "[simulation] speed"))
    if sim.run_up is not None:
        lo, hi = sorted(float(v) for v in sim.run_up)
        out.append((lo, hi, "[simulation] run_up"))
    merged: dict[tuple[float, float], list[str]] = {}
    for lo, hi, src in out:  # the same speeds named twice: one entry naming both
        merged.setdefault((lo, hi), []).append(src)
    return [(lo, hi, ", ".join(src)) for (lo, hi), src in merged.items()]


def scan_grid(freqs_hz: tuple[float, float] = (0.1, 5000.0), n: int = 400) -> np.ndarray:
    """The frequency grid (rad/s) of the scan: sensitivity peaks and margin crossovers together."""
    return 2 * np.pi * np.logspace(np.log10(freqs_hz[0]), np.log10(freqs_hz[1]), n)


@dataclass(frozen=True)
class SpeedPoint:
    speed: float  # rad/s
    sens: sensmod.SensitivityResult
    open_loop: marg.OpenLoop | None  # on the grid's speeds; None at refinement evaluations
    least: object  # modal.Mode: the least-damped closed-loop mode up to fmax
    unstable: tuple  # modal.Mode with Re lambda > 0


@dataclass(frozen=True)
class AxisWorst:
    axis: tuple[str, str]
    peak: float  # |S|
    zone: str
    freq: float  # rad/s, where |S| peaks
    speed: float  # rad/s, spin speed where this axis' peak is largest


@dataclass(frozen=True)
class MarginWorst:
    """The least margins of one axis over the grid's speeds: (value, rad/s, spin rad/s) or None."""
    axis: tuple[str, str]
    phase_margin: tuple[float, float, float] | None  # smallest, deg
    upper_gm: tuple[float, float, float] | None  # smallest factor > 1
    lower_gm: tuple[float, float, float] | None  # largest factor < 1
    no_crossover_at: tuple[float, ...] = ()  # spin speeds without a gain crossover


@dataclass(frozen=True)
class OverSpeed:
    intervals: tuple[tuple[float, float, str], ...]
    points: tuple[SpeedPoint, ...]  # every evaluated speed, ascending
    axes: tuple[tuple[str, str], ...]
    worst: tuple[AxisWorst, ...]  # per axis
    fmax: float  # rad/s, modes considered up to here

    @property
    def speeds(self) -> np.ndarray:
        return np.array([p.speed for p in self.points])

    @property
    def peaks(self) -> np.ndarray:
        """(n_speeds, n_axes) refined sensitivity peak of every axis at every evaluated speed."""
        return np.array([p.sens.peaks for p in self.points])

    @property
    def worst_axis(self) -> int:
        return int(np.argmax([w.peak for w in self.worst]))

    def at(self, speed: float) -> SpeedPoint:
        """The evaluated point nearest ``speed``."""
        return self.points[int(np.argmin(np.abs(self.speeds - speed)))]

    @property
    def worst_point(self) -> SpeedPoint:
        """The evaluation at the speed of the worst axis' worst peak."""
        return self.at(self.worst[self.worst_axis].speed)

    @property
    def least(self) -> SpeedPoint:
        """The evaluated speed with the least-damped mode."""
        return min(self.points, key=lambda p: p.least.damping_ratio)

    @property
    def unstable(self) -> list[SpeedPoint]:
        return [p for p in self.points if p.unstable]

    def margins(self) -> tuple[MarginWorst, ...]:
        pts = [p for p in self.points if p.open_loop is not None]
        out = []
        for j, ax in enumerate(self.axes):
            pm, up, lo, none = [], [], [], []
            for p in pts:
                m = p.open_loop.margins[j]
                if m.phase_margin:
                    pm.append(m.phase_margin + (p.speed,))
                else:
                    none.append(p.speed)
                if m.upper_gm:
                    up.append(m.upper_gm + (p.speed,))
                if m.lower_gm:
                    lo.append(m.lower_gm + (p.speed,))
            out.append(MarginWorst(ax, min(pm, key=lambda t: abs(t[0])) if pm else None,
                                   min(up) if up else None, max(lo) if lo else None, tuple(none)))
        return tuple(out)


class _Evaluator:
    def __init__(self, model: System, fmax: float, freqs: np.ndarray):
        from .modal import Solver
        self.model, self.fmax, self.freqs = model, fmax, freqs
        self.solver = Solver(model)
        self.cache: dict[float, SpeedPoint] = {}

    def __call__(self, speed: float, with_margins: bool = False) -> SpeedPoint:
        speed = float(speed)
        p = self.cache.get(speed)
        if p is not None and (p.open_loop is not None or not with_margins):
            return p
        modes = self.solver.all(speed, self.fmax)
        w = self.freqs
        poles = [m.eigenvalue.imag for m in modes if m.damping_ratio < 0.3 and w[0] <= m.eigenvalue.imag <= w[-1]]
        sens = sensmod.sensitivity(self.model, speed, freqs=w, refine=True, poles=poles)
        ol = marg.open_loop(self.model, speed, freqs=sens.freqs, S=sens.S) if with_margins else None
        least = min(modes, key=lambda m: m.damping_ratio)
        p = SpeedPoint(speed, sens, ol, least, tuple(m for m in modes if m.eigenvalue.real > 0))
        self.cache[speed] = p
        return p


def scan(model: System, intervals=None, points: int = 7, fmax: float = 2 * np.pi * 5000.0,
         freqs: np.ndarray | None = None, refine: bool = True, progress=None) -> OverSpeed:
    """Sensitivity, margins and least damping over the operating speeds (module docstring).
    ``intervals``: ``[(lo, hi, source), ...]`` in rad/s (default: the scene's,
    :func:`operating_intervals`); ``points``: grid speeds per range, ends included."""
    ivs = [tuple(iv) if len(iv) == 3 else (float(iv[0]), float(iv[1]), "") for iv in
           (operating_intervals(model.scene) if intervals is None else intervals)]
    if not ivs:
        raise ValueError("no operating speeds")
    grid = sorted({float(s) for lo, hi, _ in ivs for s in (np.linspace(lo, hi, max(points, 2)) if hi > lo else [lo])})
    ev = _Evaluator(model, fmax, scan_grid() if freqs is None else np.asarray(freqs, dtype=float))
    for k, s in enumerate(grid):
        ev(s, with_margins=True)
        if progress:
            progress(k + 1, len(grid))
    na = model.n_axes
    gpk = np.array([ev(s).sens.peaks for s in grid])
    if refine:
        for j in range(na):
            if j > 0 and model.axes[j][1] == "y" and np.allclose(gpk[:, j], gpk[:, j - 1], rtol=1e-9):
                continue  # isotropic: y is x at every speed
            k = int(np.argmax(gpk[:, j]))
            _refine_axis(ev, j, grid, k, ivs)
    pts = tuple(ev.cache[s] for s in sorted(ev.cache))
    pk = np.array([p.sens.peaks for p in pts])
    worst = []
    for j, ax in enumerate(model.axes):
        k = int(np.argmax(pk[:, j]))
        p = pts[k]
        worst.append(AxisWorst(ax, float(pk[k, j]), sensmod.zone(float(pk[k, j])), float(p.sens.peak_freqs[j]), p.speed))
    return OverSpeed(tuple(ivs), pts, model.axes, tuple(worst), fmax)


def _refine_axis(ev: _Evaluator, j: int, grid: list[float], k: int, ivs) -> None:
    """Refine the speed of axis j's largest peak around grid speed k (every evaluation cached)."""
    s = grid[k]
    span = [(lo, hi) for lo, hi, _ in ivs if hi > lo and lo <= s <= hi]
    if not span:
        return  # a single named speed: nothing to refine
    lo, hi = min(a for a, _ in span), max(b for _, b in span)
    below = [g for g in grid if lo <= g < s]
    above = [g for g in grid if s < g <= hi]
    a = below[-1] if below else s
    b = above[0] if above else s
    f = lambda x: -ev(x).sens.peaks[j]
    f0 = f(s)
    if a == s or b == s:  # an end of the range: does the peak still rise inwards?
        other = b if a == s else a
        inner = s + 0.005 * (other - s)
        if f(inner) >= f0:
            return
        a, b = min(s, other), max(s, other)
    minimize_scalar(f, bounds=(a, b), method="bounded", options={"xatol": 0.005 * (b - a), "maxiter": 14})
