"""ISO 14839-3 sensitivity function per AMB axis, its peak and zone.

Sensitivity of axis j is the transfer from a disturbance added to that axis' measured
displacement to the disturbed signal, with every loop closed:

    S_j(i w) = 1 - H(i w) k_i,j [Cs Z(w, Omega)^-1 Ba]_jj          (= 1 / (1 + P_jj H), P_jj with
                                                                     the other loops closed)

With an na x na current law (an LTI kind that couples the axes, controller/law_lti.py) the
sensitivity is a matrix, ``S = I - Cs Z^-1 Ba diag(k_i) H``; each axis' S_j is its diagonal entry
``S_jj`` (the disturbance injected at axis j's sensor signal and read there, every loop closed:
what a per-axis ISO 14839-3 measurement gives), not the largest singular value.

Zones by the peak |S|: A < 3 (9.5 dB), B 3-4, C 4-5, D > 5.  The A/B and B/C limits are the
standard's; the C/D limit of 5 (14 dB) is commonly quoted but was not verified against the text.

The peak.  A lightly damped mode makes a peak far narrower than the spacing of any fixed grid (a
mode of damping ratio zeta is 2 zeta w wide; 0.1 % at 800 Hz is 1.6 Hz, while a 600-point log grid
from 1 Hz to 5 kHz is 1.4 % = 11 Hz apart there).  :func:`sensitivity` therefore evaluates |S| on
the grid *and* at every closed-loop pole's damped frequency (``Im lambda`` of every mode with
zeta < 0.3 inside the grid's range), then refines every local maximum of that merged grid (the
five largest per axis) by a bounded scalar search between its neighbours.  The refined peaks are
``SensitivityResult.peaks`` / ``peak_freqs``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from ambhil.controller.transfer import evaluate, evaluate_matrix, is_siso
from ..system import System
from . import dynamic_stiffness

ZONES = ((3.0, "A"), (4.0, "B"), (5.0, "C"), (np.inf, "D"))


def zone(peak: float) -> str:
    for lim, z in ZONES:
        if peak < lim:
            return z
    return "D"


@dataclass(frozen=True)
class SensitivityResult:
    freqs: np.ndarray  # rad/s, the evaluation grid (the fixed grid merged with the pole frequencies)
    S: np.ndarray  # complex, (n_freqs, n_axes)
    axes: tuple[tuple[str, str], ...]
    speed: float
    # refined peak per axis (|S| and rad/s); None: the grid maximum (refine=False)
    peak_values: np.ndarray | None = field(default=None, repr=False)
    peak_at: np.ndarray | None = field(default=None, repr=False)

    @property
    def grid_peaks(self) -> np.ndarray:
        return np.abs(self.S).max(axis=0)

    @property
    def peaks(self) -> np.ndarray:
        return self.grid_peaks if self.peak_values is None else self.peak_values

    @property
    def peak_freqs(self) -> np.ndarray:
        if self.peak_at is not None:
            return self.peak_at
        return self.freqs[np.abs(self.S).argmax(axis=0)]

    @property
    def zones(self) -> list[str]:
        return [zone(p) for p in self.peaks]


def default_freqs(n: int = 600) -> np.ndarray:
    return 2 * np.pi * np.logspace(0, np.log10(5000.0), n)


def _dense(M):
    return M.toarray() if hasattr(M, "toarray") else np.asarray(M)


def evaluate_S(model: System, speed: float, w: np.ndarray) -> np.ndarray:
    """S_j(i w) of every axis at the frequencies w (rad/s), (n_w, n_axes)."""
    w = np.asarray(w, dtype=float)
    Ba, Cs = _dense(model.Ba), _dense(model.Cs)
    X = dynamic_stiffness.solve(model, w, speed, np.broadcast_to(Ba.astype(complex), (len(w),) + Ba.shape))
    G = np.einsum("an,knb->kab", Cs, X)  # (n_w, n_axes, n_axes): Cs Z^-1 Ba
    if not is_siso(model.H):
        Hk = model.ki[None, :, None] * evaluate_matrix(model.H, 1j * w)
        return 1.0 - np.einsum("kjb,kbj->kj", G, Hk)
    h = evaluate(model.H, 1j * w)
    return 1.0 - h[:, None] * model.ki[None, :] * np.diagonal(G, axis1=1, axis2=2)


class _AxisS:
    """S_j(i w) of one axis at one frequency at a time (the peak searches), the banded dynamic
    stiffness built once."""

    def __init__(self, model: System, speed: float):
        self.model, self.speed = model, speed
        self.ds = dynamic_stiffness.DynamicStiffness(model) if model.sparse else None
        self.Ba, self.Cs = _dense(model.Ba).astype(complex), _dense(model.Cs)

    def __call__(self, j: int, w: float) -> complex:
        m = self.model
        if not is_siso(m.H):
            Hm = evaluate_matrix(m.H, np.array([1j * w]))[0]
            b = self.Ba @ (m.ki * Hm[:, j])
            x = (self.ds.solve(1j * w, self.speed, b, h=Hm) if self.ds is not None
                 else dynamic_stiffness.solve(m, [w], self.speed, b[None])[0])
            return complex(1.0 - self.Cs[j] @ x)
        b = self.Ba[:, j]
        h = evaluate(m.H, np.array([1j * w]))[0]
        if self.ds is not None:
            x = self.ds.solve(1j * w, self.speed, b, h=h)
        else:
            x = dynamic_stiffness.solve(m, [w], self.speed, b[None])[0]
        return complex(1.0 - h * m.ki[j] * (self.Cs[j] @ x))


def pole_frequencies(model: System, speed: float, wmin: float, wmax: float, zeta_max: float = 0.3) -> np.ndarray:
    """Damped frequencies (rad/s) of the closed-loop modes with damping ratio < zeta_max in
    [wmin, wmax] (where a sensitivity peak can hide between grid points)."""
    from .modal import Solver
    modes = Solver(model).all(speed, wmax)
    return np.array(sorted(m.eigenvalue.imag for m in modes
                           if m.damping_ratio < zeta_max and wmin <= m.eigenvalue.imag <= wmax))


def sensitivity(model: System, speed: float, freqs: np.ndarray | None = None, refine: bool | None = None,
                poles: np.ndarray | None = None, candidates: int = 5) -> SensitivityResult:
    """S of every axis on ``freqs`` (default: 600 log points, 1 Hz - 5 kHz); with ``refine`` (the
    default when ``freqs`` is not given) the grid also holds the closed-loop poles' damped
    frequencies (``poles``, rad/s; computed when None) and every axis' peak is refined (see the
    module's docstring).  Given ``freqs`` alone, S is evaluated on exactly those frequencies."""
    if refine is None:
        refine = freqs is None
    w = default_freqs() if freqs is None else np.asarray(freqs, dtype=float)
    if not refine:
        return SensitivityResult(freqs=w, S=evaluate_S(model, speed, w), axes=model.axes, speed=speed)
    if poles is None:
        poles = pole_frequencies(model, speed, w.min(), w.max())
    poles = np.asarray(poles, dtype=float)
    poles = poles[(poles >= w.min()) & (poles <= w.max())]
    w = np.unique(np.concatenate([w, poles]))
    S = evaluate_S(model, speed, w)
    A = np.abs(S)
    na = A.shape[1]
    pv, pf = A.max(axis=0).copy(), w[A.argmax(axis=0)].copy()
    axis_S = _AxisS(model, speed)
    for j in range(na):
        if j % 2 == 1 and model.axes[j][1] == "y" and np.allclose(A[:, j], A[:, j - 1], rtol=1e-9):
            pv[j], pf[j] = pv[j - 1], pf[j - 1]  # isotropic bearing: y is x
            continue
        a = A[:, j]
        loc = [k for k in range(len(w)) if (k == 0 or a[k] >= a[k - 1]) and (k == len(w) - 1 or a[k] >= a[k + 1])]
        loc = sorted(loc, key=lambda k: -a[k])[:candidates]
        for k in loc:
            lo, hi = w[max(k - 1, 0)], w[min(k + 1, len(w) - 1)]
            if hi <= lo:
                continue
            r = minimize_scalar(lambda x: -abs(axis_S(j, x)), bounds=(lo, hi),
                                method="bounded", options={"xatol": 1e-9 * hi})
            if -r.fun > pv[j]:
                pv[j], pf[j] = -r.fun, float(r.x)
    return SensitivityResult(freqs=w, S=S, axes=model.axes, speed=speed, peak_values=pv, peak_at=pf)
