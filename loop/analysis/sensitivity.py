"""ISO 14839-3 sensitivity function per AMB axis, its peak and zone.

Sensitivity of axis j is the transfer from a disturbance added to that axis' measured
displacement to the disturbed signal, with every loop closed:

    S_j(i w) = 1 - H(i w) k_i,j [Cs Z(w, Omega)^-1 Ba]_jj          (= 1 / (1 + P_jj H), P_jj with
                                                                     the other loops closed)

Zones by the peak |S|: A < 3 (9.5 dB), B 3-4, C 4-5, D > 5.  The A/B and B/C limits are the
standard's; the C/D limit of 5 (14 dB) is commonly quoted but was not verified against the text.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controller.transfer import evaluate
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
    freqs: np.ndarray  # rad/s
    S: np.ndarray  # complex, (n_freqs, n_axes)
    axes: tuple[tuple[str, str], ...]
    speed: float

    @property
    def peaks(self) -> np.ndarray:
        return np.abs(self.S).max(axis=0)

    @property
    def peak_freqs(self) -> np.ndarray:
        return self.freqs[np.abs(self.S).argmax(axis=0)]

    @property
    def zones(self) -> list[str]:
        return [zone(p) for p in self.peaks]


def default_freqs(n: int = 600) -> np.ndarray:
    return 2 * np.pi * np.logspace(0, np.log10(5000.0), n)


def sensitivity(model: System, speed: float, freqs: np.ndarray | None = None) -> SensitivityResult:
    w = default_freqs() if freqs is None else np.asarray(freqs, dtype=float)
    Ba = model.Ba.toarray() if hasattr(model.Ba, "toarray") else np.asarray(model.Ba)
    Cs = model.Cs.toarray() if hasattr(model.Cs, "toarray") else np.asarray(model.Cs)
    X = dynamic_stiffness.solve(model, w, speed, np.broadcast_to(Ba.astype(complex), (len(w),) + Ba.shape))
    G = np.einsum("an,knb->kab", Cs, X)  # (n_w, n_axes, n_axes): Cs Z^-1 Ba
    h = evaluate(model.H, 1j * w)
    S = 1.0 - h[:, None] * model.ki[None, :] * np.diagonal(G, axis1=1, axis2=2)
    return SensitivityResult(freqs=w, S=S, axes=model.axes, speed=speed)
