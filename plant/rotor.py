"""Finite-element rotor: assembly of shaft elements and rigid discs into sparse matrices.

Node DOFs are ``[x, y, phi_x, phi_y]`` (+ ``z`` when the scene has an axial AMB), node-major,
so every matrix is banded.  The equation of motion of the free rotor is

    M q'' + (C + Omega G) q' + K q = f,     C = alpha M + beta K  (Rayleigh, shaft and discs)

with G skew-symmetric.  Bearings are not part of this file (see magnetic_bearing.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from . import beam_element as be
from . import disc as dk
from .params import ParameterError, PlantSpec

X, Y, PX, PY, Z = 0, 1, 2, 3, 4


@dataclass(frozen=True)
class FERotor:
    node_z: np.ndarray
    dpn: int  # DOFs per node (4 or 5)
    M: sp.csc_matrix
    K: sp.csc_matrix
    G: sp.csc_matrix
    C: sp.csc_matrix
    mass: float
    cog: float  # axial position of the centre of gravity
    polar_inertia: float  # about the spin axis
    transverse_inertia: float  # about a diameter through the COG

    @property
    def ndof(self) -> int:
        return self.M.shape[0]

    def dof(self, node: int, axis: int) -> int:
        return node * self.dpn + axis


def assemble(spec: PlantSpec) -> FERotor:
    axial = spec.axial_amb is not None
    dpn = 5 if axial else 4
    nn = spec.n_nodes
    n = nn * dpn
    rows, cols, mv, kv, gv = [], [], [], [], []

    def add(idx, m, k, g):
        ii, jj = np.meshgrid(idx, idx, indexing="ij")
        rows.append(ii.ravel()); cols.append(jj.ravel())
        mv.append(m.ravel()); kv.append(k.ravel()); gv.append(g.ravel())

    node = 0
    timo = spec.model.beam == "timoshenko"
    for s in spec.sections:
        A, I = be.section_properties(s.outer_diameter, s.inner_diameter)
        l = s.length / s.elements
        phi = be.shear_parameter(s.youngs_modulus, s.shear_modulus, s.outer_diameter, s.inner_diameter, l) if timo else 0.0
        Ke = be.stiffness(s.youngs_modulus, I, l, phi)
        Me = be.translational_mass(s.density, A, l, phi)
        if spec.model.rotary_inertia:
            Me = Me + be.rotary_mass(s.density, I, l, phi)
        ge = be.gyroscopic(s.density, I, l, phi)
        Z4 = np.zeros((4, 4))
        for _ in range(s.elements):
            a, b = node * dpn, (node + 1) * dpn
            xp = np.array([a + X, a + PX, b + X, b + PX])
            yp = np.array([a + Y, a + PY, b + Y, b + PY])
            idx = np.concatenate([xp, yp])
            m8 = np.block([[Me, Z4], [Z4, Me]])
            k8 = np.block([[Ke, Z4], [Z4, Ke]])
            g8 = np.block([[Z4, ge], [-ge, Z4]])
            add(idx, m8, k8, g8)
            if axial:
                zi = np.array([a + Z, b + Z])
                add(zi, be.axial_mass(s.density, A, l), be.axial_stiffness(s.youngs_modulus, A, l), np.zeros((2, 2)))
            node += 1
    for d in spec.discs:
        idx = np.arange(d.node * dpn, (d.node + 1) * dpn)
        add(idx, dk.mass_block(d.mass, d.diametral_inertia, axial), np.zeros((dpn, dpn)),
            dk.gyroscopic_block(d.polar_inertia, axial))
    r, c = np.concatenate(rows), np.concatenate(cols)
    M = sp.csc_matrix((np.concatenate(mv), (r, c)), shape=(n, n))
    K = sp.csc_matrix((np.concatenate(kv), (r, c)), shape=(n, n))
    G = sp.csc_matrix((np.concatenate(gv), (r, c)), shape=(n, n))
    for A_ in (M, K, G):
        A_.eliminate_zeros()
    C = (spec.damping.mass_proportional * M + spec.damping.stiffness_proportional * K).tocsc()

    z = np.asarray(spec.node_z)
    # rigid-body properties from the assembled mass matrix (exact for the FE mass distribution)
    tx = np.zeros(n); tx[X::dpn] = 1.0
    mass = float(tx @ (M @ tx))
    if not (np.isfinite(mass) and mass > 0):   # e.g. sections so large that float sums cancel
        raise ParameterError(f"{spec.path}: the rotor's mass from its shaft sections and discs comes out as "
                             f"{mass:g} kg (not a positive finite number at these section sizes and "
                             f"densities)")
    tt = np.zeros(n); tt[X::dpn] = z; tt[PX::dpn] = 1.0
    cog = float(tx @ (M @ tt)) / mass
    tc = np.zeros(n); tc[X::dpn] = z - cog; tc[PX::dpn] = 1.0
    It = float(tc @ (M @ tc))
    ty = np.zeros(n); ty[Y::dpn] = z - cog; ty[PY::dpn] = 1.0
    Ip = float(tc @ (G @ ty))
    return FERotor(node_z=z, dpn=dpn, M=M, K=K, G=G, C=C, mass=mass, cog=cog,
                   polar_inertia=Ip, transverse_inertia=It)


def rigid_basis(rotor: FERotor) -> np.ndarray:
    """Columns: rigid-body shapes [x_cg, y_cg, phi_x, phi_y] (+ z) about the centre of gravity."""
    n, dpn = rotor.ndof, rotor.dpn
    zc = rotor.node_z - rotor.cog
    T = np.zeros((n, 5 if dpn == 5 else 4))
    T[X::dpn, 0] = 1.0
    T[Y::dpn, 1] = 1.0
    T[X::dpn, 2] = zc; T[PX::dpn, 2] = 1.0
    T[Y::dpn, 3] = zc; T[PY::dpn, 3] = 1.0
    if dpn == 5:
        T[Z::dpn, 4] = 1.0
    return T
