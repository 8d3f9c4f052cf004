"""The AMBs' shares of the rotor's weight on the linear rungs (rigid, modal, full).

Under ``[model] gravity`` (along -y) the loop's integral action settles with the rotor at zero
displacement at every AMB actuator node, each AMB carrying a share of the weight.  With more than
two AMBs the shares are statically indeterminate: they follow from the shaft's compatibility.  So
they are the reactions of the linear FE rotor (its ``K``; the Hermite-cubic beam of every linear
rung, whatever the rung reduces it to afterwards) under its consistent gravity load
``F = -g M e_y`` (``e_y``: unit y translation of every node, rotations 0) with every AMB
actuator's x and y DOF held:

    K_ff u_f = F_f,  u_h = 0        ->     R = K_hf u_f - F_h   (force of the supports on the rotor)

The ancf rung solves the same problem on its nonlinear model (plant/ancf_statics.gravity_statics);
for the sags of a real rotor (microns) the two agree to ~1e-12 (tests/test_ancf.py).  The linear
rungs keep deviation coordinates about this sagged equilibrium (q = 0 there): the weight and the
AMBs' loads cancel and enter only where an AMB stops carrying its share (``Model.f_const``) and in
the nonlinear force law's remainder (``Model.load``).

Left out: the sensor's offset when it is not at the actuator node (the static sag between the two
nodes, a few microns at most for a rotor its AMBs can carry; the controller holds the sensor, the
model the actuator node at zero).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from .params import PlantSpec
from .rotor import X, Y, Z, FERotor


def gravity_loads(spec: PlantSpec, rotor: FERotor) -> np.ndarray:
    """The force (N) each AMB axis exerts on the rotor at the operating point under ``[model]
    gravity``, in the order of :func:`ambhil.plant.model.bearing_axes` (x, y of each radial AMB,
    then z of the axial AMB): y the reaction of the held FE rotor, x and z 0.  Zeros without
    gravity."""
    load = np.zeros(2 * len(spec.ambs) + (spec.axial_amb is not None))
    g = float(spec.model.gravity or 0.0)
    if g == 0.0:
        return load
    dpn, n = rotor.dpn, rotor.ndof
    ey = np.zeros(n)
    ey[Y::dpn] = 1.0
    F = -g * (rotor.M @ ey)
    held = np.array([a.node * dpn + ax for a in spec.ambs for ax in (X, Y)])
    # the axial DOFs (if any) carry no load and decouple from the lateral ones: left out (their
    # rigid motion would make K_ff singular)
    lateral = np.ones(n, bool)
    if dpn > Z:
        lateral[Z::dpn] = False
    lateral[held] = False
    free = np.flatnonzero(lateral)
    K = sp.csc_matrix(rotor.K)
    u = np.zeros(n)
    u[free] = sla.splu(K[free][:, free].tocsc()).solve(F[free])
    R = K[held] @ u - F[held]
    # the x plane carries no load (K has no x-y coupling): its reactions are 0 exactly
    load[: 2 * len(spec.ambs)][1::2] = R[1::2]
    return load
