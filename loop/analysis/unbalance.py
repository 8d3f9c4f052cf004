"""Steady-state unbalance response in the frequency domain.

At spin speed Omega the whirl frequency equals the spin: ``Z(Omega, Omega) Y = F(Omega)`` with the
closed-loop dynamic stiffness of dynamic_stiffness.py and the forward unbalance forces of
``Model.unbalance_forces``.  The orbit of a node is an ellipse; its major semi-axis
``|X + iY|/2 + |X - iY|/2`` (0-peak) is reported as the radius.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..system import System
from ambhil.plant.rotor import X, Y
from . import dynamic_stiffness


@dataclass(frozen=True)
class UnbalanceResult:
    speeds: np.ndarray  # rad/s
    nodes: tuple[int, ...]  # 0-based FE nodes
    x: np.ndarray  # complex amplitude of x, (n_speeds, n_nodes)
    y: np.ndarray

    @property
    def radius(self) -> np.ndarray:
        """Major semi-axis of the orbit (0-peak), (n_speeds, n_nodes)."""
        return 0.5 * (np.abs(self.x + 1j * self.y) + np.abs(self.x - 1j * self.y))

    @property
    def minor(self) -> np.ndarray:
        """Minor semi-axis of the orbit (0-peak), (n_speeds, n_nodes); equals the radius for a
        circular orbit (isotropic bearings under forward unbalance)."""
        return 0.5 * np.abs(np.abs(self.x + 1j * self.y) - np.abs(self.x - 1j * self.y))

    def peaks(self, node_index: int = 0, min_prominence: float = 0.05) -> list[tuple[float, float]]:
        """(speed, radius) of local maxima, refined by a parabola through the three samples."""
        r = self.radius[:, node_index]
        s = self.speeds
        out = []
        for k in range(1, len(r) - 1):
            if r[k] > r[k - 1] and r[k] >= r[k + 1]:
                lo = min(r[: k].min(), r[k:].min())
                if r[k] - lo < min_prominence * r[k]:
                    continue
                y0, y1, y2 = r[k - 1], r[k], r[k + 1]
                den = y0 - 2 * y1 + y2
                d = 0.5 * (y0 - y2) / den if den != 0 else 0.0
                out.append((float(s[k] + d * (s[k + 1] - s[k - 1]) / 2), float(y1)))
        return out


def response(model: System, speeds, dofs=None, nodes=None):
    """Unbalance response at FE DOFs (complex, (n_speeds, n_dofs)) or, with ``nodes``, an
    :class:`UnbalanceResult` of the x/y orbits at those FE nodes (0-based)."""
    speeds = np.asarray(speeds, dtype=float)
    if nodes is not None:
        dofs = [model.rotor.dof(k, a) for k in nodes for a in (X, Y)]
    R = model.fe_rows(list(dofs))
    out = np.zeros((len(speeds), len(dofs)), dtype=complex)
    pos = speeds > 0  # no unbalance force at standstill (and H has its integrator pole at 0)
    if pos.any():
        s = speeds[pos]
        F = np.stack([model.unbalance_forces(v) for v in s])
        out[pos] = dynamic_stiffness.solve(model, s, s, F) @ R.T
    if nodes is None:
        return out
    return UnbalanceResult(speeds=speeds, nodes=tuple(nodes), x=out[:, 0::2], y=out[:, 1::2])
