"""Rotating shaft beam element (one bending plane), Euler-Bernoulli or Timoshenko.

Element DOFs per plane: ``[w1, phi1, w2, phi2]`` where ``phi = dw/dz`` is the slope.  Both
bending planes (x-z and y-z) use the same local matrices because both are written in slopes,
so the gyroscopic matrix couples them with the rotary-inertia pattern (see :func:`gyroscopic`).

Timoshenko matrices are those of Przemieniecki (1968) with the shear parameter
``phi_s = 12 E I / (kappa G A l^2)``; ``phi_s = 0`` gives the Euler-Bernoulli element with
rotary inertia (Nelson & McVaugh 1976).  The shear coefficient is Cowper's for a hollow circle.
An optional axial bar element carries the axial DOF when the scene has an axial AMB.
"""
from __future__ import annotations

import math

import numpy as np


def section_properties(outer_diameter: float, inner_diameter: float) -> tuple[float, float]:
    """Area A and second moment of area I of a hollow circular section."""
    D, d = outer_diameter, inner_diameter
    return math.pi * (D**2 - d**2) / 4.0, math.pi * (D**4 - d**4) / 64.0


def cowper_shear_coefficient(outer_diameter: float, inner_diameter: float, poisson: float) -> float:
    m = inner_diameter / outer_diameter
    m2 = (1 + m * m) ** 2
    return 6 * (1 + poisson) * m2 / ((7 + 6 * poisson) * m2 + (20 + 12 * poisson) * m * m)


def shear_parameter(E: float, G: float, outer_diameter: float, inner_diameter: float, length: float) -> float:
    A, I = section_properties(outer_diameter, inner_diameter)
    kappa = cowper_shear_coefficient(outer_diameter, inner_diameter, E / (2 * G) - 1)
    return 12 * E * I / (kappa * G * A * length**2)


def stiffness(E: float, I: float, l: float, phi: float = 0.0) -> np.ndarray:
    c = E * I / (l**3 * (1 + phi))
    return c * np.array([
        [12, 6 * l, -12, 6 * l],
        [6 * l, (4 + phi) * l * l, -6 * l, (2 - phi) * l * l],
        [-12, -6 * l, 12, -6 * l],
        [6 * l, (2 - phi) * l * l, -6 * l, (4 + phi) * l * l],
    ])


def translational_mass(rho: float, A: float, l: float, phi: float = 0.0) -> np.ndarray:
    p = phi
    a = 13 / 35 + 7 * p / 10 + p * p / 3
    b = (11 / 210 + 11 * p / 120 + p * p / 24) * l
    c = 9 / 70 + 3 * p / 10 + p * p / 6
    d = (13 / 420 + 3 * p / 40 + p * p / 24) * l
    e = (1 / 105 + p / 60 + p * p / 120) * l * l
    f = (1 / 140 + p / 60 + p * p / 120) * l * l
    return rho * A * l / (1 + p) ** 2 * np.array([
        [a, b, c, -d],
        [b, e, d, -f],
        [c, d, a, -b],
        [-d, -f, -b, e],
    ])


def _rotary_pattern(l: float, phi: float) -> np.ndarray:
    p = phi
    a = 6 / 5
    b = (1 / 10 - p / 2) * l
    e = (2 / 15 + p / 6 + p * p / 3) * l * l
    f = (-1 / 30 - p / 6 + p * p / 6) * l * l
    return 1 / (l * (1 + p) ** 2) * np.array([
        [a, b, -a, b],
        [b, e, -b, f],
        [-a, -b, a, -b],
        [b, f, -b, e],
    ])


def rotary_mass(rho: float, I: float, l: float, phi: float = 0.0) -> np.ndarray:
    """Rotary inertia of the sections about a diameter (rho I per unit length)."""
    return rho * I * _rotary_pattern(l, phi)


def gyroscopic(rho: float, I: float, l: float, phi: float = 0.0) -> np.ndarray:
    """Plane-coupling block g: with G[x-plane, y-plane] = +g and G[y, x] = -g the shaft obeys
    ``M q'' + Omega G q' + K q = f`` for spin +Omega about +z (polar inertia rho * 2I per length)."""
    return rho * 2 * I * _rotary_pattern(l, phi)


def axial_stiffness(E: float, A: float, l: float) -> np.ndarray:
    return E * A / l * np.array([[1.0, -1.0], [-1.0, 1.0]])


def axial_mass(rho: float, A: float, l: float) -> np.ndarray:
    return rho * A * l / 6 * np.array([[2.0, 1.0], [1.0, 2.0]])
