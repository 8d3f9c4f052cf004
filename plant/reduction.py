"""Model-order reduction of the FE rotor: the bases behind the rigid and modal rungs.

* rigid: the rigid-body shapes about the centre of gravity (4 lateral DOF, +1 axial).  The
  reduced mass, polar inertia and gyroscopic matrix are exact projections of the FE model; the
  elastic stiffness is zero by definition of the rung.
* modal: Craig-Bampton.  The boundary DOFs (translations at every AMB actuator and sensor node,
  plus the axial AMB) stay physical, so bearing forces and sensor outputs are exact at DC and
  for every retained frequency; the interior is represented by fixed-interface modes up to a
  frequency cutoff.  ``q = T [q_b; eta]``, ``T = [[I, 0], [Psi, Phi]]``, ``Psi = -K_ii^-1 K_ib``.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from .rotor import FERotor, rigid_basis


def craig_bampton(rotor: FERotor, boundary: np.ndarray, cutoff_hz: float) -> np.ndarray:
    n = rotor.ndof
    b = np.asarray(sorted(set(int(i) for i in boundary)))
    i = np.setdiff1d(np.arange(n), b)
    K, M = rotor.K, rotor.M
    Kii = K[i][:, i].tocsc()
    Kib = K[i][:, b].toarray()
    lu = spla.splu(Kii)
    Psi = -lu.solve(Kib)
    w2max = (2 * np.pi * cutoff_hz) ** 2
    w2, Phi = sla.eigh(Kii.toarray(), M[i][:, i].toarray(), subset_by_value=(-np.inf, w2max))
    T = np.zeros((n, len(b) + Phi.shape[1]))
    T[b, : len(b)] = np.eye(len(b))
    T[np.ix_(i, np.arange(len(b)))] = Psi
    T[np.ix_(i, np.arange(len(b), T.shape[1]))] = Phi
    return T


def rigid(rotor: FERotor) -> np.ndarray:
    return rigid_basis(rotor)
