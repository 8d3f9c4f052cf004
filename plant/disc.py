"""Rigid disc attached to a shaft node: mass, diametral inertia and the spin (gyroscopic) term.

For spin +Omega about +z and node DOFs ``[x, y, phi_x, phi_y]`` (slopes), a disc obeys
``I_d phi_x'' + I_p Omega phi_y' = M_y`` and ``I_d phi_y'' - I_p Omega phi_x' = -M_x``: the
small-tilt form of ``dH/dt = M`` with ``H = I_p Omega k' + I_d (alpha' i + beta' j)``,
``alpha = -phi_y``, ``beta = phi_x``.  Forward whirl is stiffened, backward whirl softened.
"""
from __future__ import annotations

import numpy as np


def mass_block(mass: float, diametral_inertia: float, axial: bool) -> np.ndarray:
    d = [mass, mass, diametral_inertia, diametral_inertia] + ([mass] if axial else [])
    return np.diag(d)


def gyroscopic_block(polar_inertia: float, axial: bool) -> np.ndarray:
    n = 5 if axial else 4
    g = np.zeros((n, n))
    g[2, 3], g[3, 2] = polar_inertia, -polar_inertia
    return g
