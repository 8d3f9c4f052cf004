"""Open loop of each AMB axis, its gain and phase margins, and stability against speed.

Open loop of axis j, the loop broken at that axis' controller output with every other axis
closed (how AMB loops are commissioned and how ISO 14839-3 reads them):

    L_j(i w) = H(i w) k_i,j [Cs Z_j(i w, Omega)^-1 Ba]_jj,     Z_j = Z without axis j's feedback,

in the negative-feedback convention (the closed loop is stable when 1 + L_j has the right number
of encirclements).  Since ``S_j = 1/(1 + L_j)`` (sensitivity.py), ``L_j = 1/S_j - 1``; the test
computes ``L_j`` directly from ``Z_j`` as the second method.  With an na x na law (controller/law_lti.py)
``L_j = 1/S_jj - 1`` is the loop broken at axis j's sensor signal (the law's input j), every
other signal closed.

Margins.  The rotor on its AMBs is open-loop unstable (negative bearing stiffness), so L_j has a
*lower* gain margin as well as an upper one: at every phase crossover (L_j on the negative real
axis) the loop gain may be scaled by ``1/|L_j|`` before a closed-loop pole reaches the imaginary
axis; factors > 1 are upper gain margins, factors < 1 lower ones (the gain may only be reduced
that far).  The phase margin is the smallest ``|180 deg + arg L_j|`` over the gain crossovers
(``|L_j| = 1``).  Crossovers are bracketed on the frequency grid and solved by Brent's method.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from ..system import System
from . import sensitivity as sensmod


@dataclass(frozen=True)
class AxisMargins:
    axis: tuple[str, str]
    gain_margins: tuple[tuple[float, float], ...]  # (factor, rad/s) at every phase crossover
    phase_margins: tuple[tuple[float, float], ...]  # (deg, rad/s) at every gain crossover

    @property
    def upper_gm(self) -> tuple[float, float] | None:
        """Smallest factor > 1 (the gain may rise that much), with its frequency."""
        up = [g for g in self.gain_margins if g[0] > 1]
        return min(up) if up else None

    @property
    def lower_gm(self) -> tuple[float, float] | None:
        """Largest factor < 1 (the gain may fall to that), with its frequency."""
        lo = [g for g in self.gain_margins if g[0] < 1]
        return max(lo) if lo else None

    @property
    def phase_margin(self) -> tuple[float, float] | None:
        return min(self.phase_margins, key=lambda p: abs(p[0])) if self.phase_margins else None


@dataclass(frozen=True)
class OpenLoop:
    freqs: np.ndarray  # rad/s
    L: np.ndarray  # complex (n_w, n_axes)
    axes: tuple[tuple[str, str], ...]
    speed: float
    margins: tuple[AxisMargins, ...]


def default_freqs(n: int = 1200) -> np.ndarray:
    return 2 * np.pi * np.logspace(-1, np.log10(5000.0), n)


def open_loop(model: System, speed: float, freqs: np.ndarray | None = None, S: np.ndarray | None = None) -> OpenLoop:
    """L_j of every axis on ``freqs`` (default 1200 log points, 0.1 Hz - 5 kHz) and its margins;
    ``S``: the sensitivity already evaluated on ``freqs`` (sensitivity.evaluate_S), reused."""
    w = default_freqs() if freqs is None else np.asarray(freqs, dtype=float)
    L = 1.0 / (sensmod.evaluate_S(model, speed, w) if S is None else np.asarray(S)) - 1.0
    axis_S = sensmod._AxisS(model, speed)
    out = []
    for j, ax in enumerate(model.axes):
        if j > 0 and ax[1] == "y" and np.allclose(L[:, j], L[:, j - 1], rtol=1e-9, atol=0):
            out.append(AxisMargins(ax, out[-1].gain_margins, out[-1].phase_margins))
            continue
        l = L[:, j]
        gms, pms = [], []
        im = l.imag
        for k in np.where(np.sign(im[:-1]) * np.sign(im[1:]) < 0)[0]:
            wc = brentq(lambda x: (1.0 / axis_S(j, x) - 1.0).imag, w[k], w[k + 1], xtol=1e-12 * w[k + 1])
            lc = (1.0 / axis_S(j, wc) - 1.0)
            if lc.real < 0 and abs(lc.imag) <= 1e-6 * abs(lc):  # a crossing, not a pole of L (zero of S)
                gms.append((1.0 / abs(lc), wc))
        g = np.log(np.abs(l))
        for k in np.where(np.sign(g[:-1]) * np.sign(g[1:]) < 0)[0]:
            wc = brentq(lambda x: np.log(abs((1.0 / axis_S(j, x) - 1.0))), w[k], w[k + 1], xtol=1e-12 * w[k + 1])
            ph = np.degrees(np.angle((1.0 / axis_S(j, wc) - 1.0)))  # (-180, 180]
            pms.append((180.0 - abs(ph) if ph != 0 else 180.0, wc))  # distance from -180 deg
        out.append(AxisMargins(ax, tuple(gms), tuple(pms)))
    return OpenLoop(freqs=w, L=L, axes=model.axes, speed=speed, margins=tuple(out))


@dataclass(frozen=True)
class StabilityMap:
    speeds: np.ndarray  # rad/s
    zeta: np.ndarray  # least damping ratio at each speed
    freq: np.ndarray  # rad/s, damped frequency of that mode
    whirl: list[str]
    fmax: float  # rad/s, modes considered up to here


def stability_over_speed(model: System, speeds, fmax: float = 2 * np.pi * 5000.0, progress=None) -> StabilityMap:
    """Least damping ratio of the closed loop (every mode up to fmax) at each speed."""
    from .modal import Solver
    solver = Solver(model)
    speeds = np.asarray(speeds, dtype=float)
    z, f, wh = np.empty(len(speeds)), np.empty(len(speeds)), []
    for k, s in enumerate(speeds):
        m = min(solver.all(float(s), fmax), key=lambda m: m.damping_ratio)
        z[k], f[k] = m.damping_ratio, m.eigenvalue.imag
        wh.append(m.whirl)
        if progress:
            progress(k + 1, len(speeds))
    return StabilityMap(speeds, z, f, wh, fmax)
