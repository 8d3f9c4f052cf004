"""ISO 14839-2 evaluation of vibration: the steady unbalance orbit at every AMB sensor station
against the radial clearance C_min of the touchdown (auxiliary) bearing beside that AMB, the
bearing's own ``touchdown_clearance`` (``RadialAMB.clearance``: half its magnetic gap when the scene
gives none; ``[analysis] touchdown_clearance`` is the default of every AMB).

    D_max = max over the operating speeds of max_t sqrt(x(t)^2 + y(t)^2)   (the orbit's major semi-axis)

Zone by D_max / C_min: A < 0.3, B 0.3-0.4, C 0.4-0.5, D > 0.5.  The criterion (D_max against
C_min at the sensor station) is the standard's; the numeric limits 0.3 / 0.4 / 0.5 are the ones
quoted from a partly legible translation and were NOT verified against the text (the reference
notes, physics.md section 8).  They are parameters here (``LIMITS``) so a verified table drops in.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..system import System
from . import over_speed, unbalance

LIMITS = ((0.3, "A"), (0.4, "B"), (0.5, "C"), (np.inf, "D"))


def zone(ratio: float) -> str:
    for lim, z in LIMITS:
        if ratio < lim:
            return z
    return "D"


def clearance(model: System) -> tuple[float, bool]:
    """(the smallest touchdown clearance of the AMBs in m, every one given in the scene?)."""
    ambs = model.scene.plant.ambs
    return float(min(a.clearance for a in ambs)), all(a.touchdown_clearance is not None for a in ambs)


@dataclass(frozen=True)
class StationVibration:
    amb: str
    node: int  # 0-based sensor node
    d_max: float  # m
    at_speed: float  # rad/s
    ratio: float  # d_max / C_min
    zone: str
    clearance: float = 0.0  # m, C_min: this AMB's touchdown clearance
    clearance_given: bool = False  # given in the scene (else half the magnetic gap, assumed)


@dataclass(frozen=True)
class VibrationResult:
    clearance: float  # m, the smallest touchdown clearance (each station carries its own)
    clearance_given: bool  # every station's given in the scene
    speeds: np.ndarray
    stations: tuple[StationVibration, ...]


def operating_speeds(model: System) -> np.ndarray:
    """The spin speeds (rad/s, > 0) the orbits are judged over: every operating speed of the scene
    (over_speed.operating_intervals: the ``[speed]`` value or range, the ``[simulation]`` speed and
    run-up), each range at ``[speed] points`` speeds."""
    n = model.scene.plant.speed.points
    pts = [np.array([lo]) if lo == hi else np.linspace(lo, hi, n)
           for lo, hi, _ in over_speed.operating_intervals(model.scene)]
    s = np.unique(np.concatenate(pts))
    return s[s > 0]


def evaluate(model: System, speeds=None, unb: unbalance.UnbalanceResult | None = None) -> VibrationResult:
    """D_max at each radial AMB's sensor node over ``speeds`` (default: the scene's operating speed
    or its speed range); ``unb``: an unbalance response that already holds those nodes."""
    c, given = clearance(model)
    nodes = list(dict.fromkeys(a.sensor_node for a in model.scene.plant.ambs))
    if unb is None or not set(nodes) <= set(unb.nodes):
        speeds = operating_speeds(model) if speeds is None else np.asarray(speeds, float)
        unb = unbalance.response(model, speeds, nodes=nodes)
    out = []
    for a in model.scene.plant.ambs:
        j = unb.nodes.index(a.sensor_node)
        r = unb.radius[:, j] if len(unb.speeds) else np.zeros(1)
        k = int(np.argmax(r))
        d = float(r[k])
        ca = a.clearance
        out.append(StationVibration(a.name, a.sensor_node, d, float(unb.speeds[k]) if len(unb.speeds) else 0.0,
                                    d / ca, zone(d / ca), ca, a.touchdown_clearance is not None))
    return VibrationResult(c, given, unb.speeds, tuple(out))
