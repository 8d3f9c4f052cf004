"""Radial and axial active magnetic bearing: differential force law and its linearisation.

Force of a differential electromagnet pair on the rotor along one axis, with ``x`` the rotor
displacement relative to the stator centre towards the upper magnet, bias current ``i0``,
control current ``i`` and nominal gap ``s0``:

    F(x, i) = (k/4) [ (i0 + i)^2 / (s0 - x)^2  -  (i0 - i)^2 / (s0 + x)^2 ],   k = mu0 N^2 A cos(alpha)

Misalignment: a stator offset ``e`` means the rotor, held on the line of the other bearings
(sensor zero unchanged), sits at ``x = -e`` relative to this stator.  The integral action then
settles at the current that cancels the magnet's bias pull there,

    F(-e, i_op) = 0   =>   i_op = i0 e / s0 = i0 e_bar,

and the exact derivatives at that operating point are

    k_x = dF/dx = k i0^2 / s0^3 / (1 - e_bar^2),     k_i = dF/di = k i0 / s0^2 / (1 - e_bar^2),

which are the paper's eq. 8 and 9 (``1 - e_bar^2`` in the denominator).  :func:`linearise` takes
derivatives of the force law itself at any operating point; the closed forms are only a check.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def force(k: float, s0: float, i0: float, x, i):
    """Differential-pair force (N) at rotor displacement x (m, relative to the stator) and
    control current i (A).  Works on scalars and arrays."""
    return 0.25 * k * ((i0 + i) ** 2 / (s0 - x) ** 2 - (i0 - i) ** 2 / (s0 + x) ** 2)


def force_derivatives(k: float, s0: float, i0: float, x, i):
    """Exact (dF/dx, dF/di) of :func:`force` at (x, i)."""
    kx = 0.5 * k * ((i0 + i) ** 2 / (s0 - x) ** 3 + (i0 - i) ** 2 / (s0 + x) ** 3)
    ki = 0.5 * k * ((i0 + i) / (s0 - x) ** 2 + (i0 - i) / (s0 + x) ** 2)
    return kx, ki


@dataclass(frozen=True)
class OperatingPoint:
    x: float  # rotor displacement relative to the stator at the operating point (m)
    i: float  # control current that holds it (A)
    kx: float  # force-displacement coefficient dF/dx (N/m), positive = destabilising
    ki: float  # force-current coefficient dF/di (N/A)


def operating_point(k: float, s0: float, i0: float, offset: float) -> OperatingPoint:
    """Linearise at the force-free point of a stator offset by ``offset`` from the rotor line."""
    x = -offset
    i = -i0 * x / s0  # cancels the bias pull: F(x, i) = 0
    kx, ki = force_derivatives(k, s0, i0, x, i)
    return OperatingPoint(x=x, i=i, kx=float(kx), ki=float(ki))


def loaded_operating_point(k: float, s0: float, i0: float, offset: float, load: float) -> OperatingPoint:
    """Linearise at the point where the rotor, on the line of the other bearings (``x = -offset``
    relative to this stator), is held with the bearing carrying a static ``load`` (N, along +x of
    this axis, e.g. its share of the rotor's weight): the control current solves
    ``F(-offset, i) = load`` with the exact force law, and (k_x, k_i) are the exact derivatives
    there.  Without offset the law is linear in i at x = 0: ``i = load s0^2 / (k i0)`` and
    ``k_x = k (i0^2 + i^2) / s0^3`` (the loaded pair is stiffer).  A load beyond what the pair
    can give with one coil at twice the bias and the other off (|i| = i0) raises ValueError."""
    x = -offset
    f = lambda i: float(force(k, s0, i0, x, i)) - load
    lo, hi = f(-i0), f(i0)
    if not lo <= 0.0 <= hi:
        fmax = float(force(k, s0, i0, x, i0 if load > 0 else -i0))
        raise ValueError(f"a static load of {load:.4g} N needs a control current beyond the bias current "
                         f"{i0:g} A (the pair saturates at {fmax:.4g} N)")
    from scipy.optimize import brentq
    i = brentq(f, -i0, i0, xtol=1e-15 * max(i0, 1.0), rtol=4 * np.finfo(float).eps) if load != 0.0 else -i0 * x / s0
    kx, ki = force_derivatives(k, s0, i0, x, i)
    return OperatingPoint(x=x, i=float(i), kx=float(kx), ki=float(ki))


def paper_coefficients(k: float, s0: float, i0: float, offset: float) -> tuple[float, float]:
    """Eq. 8-9 of Su et al. in closed form (used as an independent check of operating_point)."""
    eb = offset / s0
    return k / (1 - eb**2) * i0**2 / s0**3, k / (1 - eb**2) * i0 / s0**2


def coil_currents(i0: float, i):
    """Upper and lower coil currents of the differential pair (each coil only pulls: >= 0)."""
    return np.asarray(i0 + i), np.asarray(i0 - i)
