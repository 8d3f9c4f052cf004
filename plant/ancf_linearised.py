"""Small-motion eigen-analysis of the ANCF model: the DAE linearised about a static (zero speed)
or steady spinning configuration, restricted to the null space of the constraint gradient, with
the mass and damping-gyroscopic matrices as derivatives of their own (``JacobianAssembler.
rate_matrix``); and the classification of its mode shapes (kind, whirl)."""
from __future__ import annotations

import numpy as np

from .ancf_jacobian import JacobianAssembler
from .ancf_model import ANCFArrays, n_constraints


def linearised_modes(S: ANCFArrays, q0, n_modes: int = 20):
    """Natural frequencies (rad/s) and mode shapes of the DAE linearised about the static
    configuration q0 at zero speed: K, M from the exact Jacobians, restricted to the null space
    of the constraint gradient (the constrained eigenproblem).  M is the acceleration derivative
    itself (``JacobianAssembler.rate_matrix``), not a difference of Jacobians, so it keeps its
    digits on fine meshes where K is many orders larger.  Returns (w, V) with V in q."""
    import scipy.linalg as sla
    n = q0.shape[0]
    nc = int(n_constraints(S))
    asm = JacobianAssembler(S)
    z = np.zeros(n)
    cur = np.zeros(max(1, S.amb_node.shape[0]))
    x = np.concatenate([q0, np.zeros(nc)])
    J0 = asm.matrix(x, z, 0.0, z, 0.0, 0.0, cur, 1.0, 1.0).toarray()
    K = J0[:n, :n]
    M = asm.rate_matrix(q0, z, z, 0.0, "a").toarray()
    Phq = J0[n:, :n]
    N = sla.null_space(Phq)
    Kr, Mr = N.T @ K @ N, N.T @ M @ N
    Kr, Mr = 0.5 * (Kr + Kr.T), 0.5 * (Mr + Mr.T)
    lam, Vr = sla.eigh(Kr, Mr)
    w = np.sqrt(np.abs(lam)) * np.sign(lam)
    return w[:n_modes], (N @ Vr)[:, :n_modes]


def mode_kind(S: ANCFArrays, v) -> str:
    """'bending' | 'torsion' | 'axial' | 'rigid' by the dominant part of a mode shape."""
    V = v.reshape(-1, 8)
    lat = np.sum(V[:, 0:2] ** 2) + np.sum(V[:, 5:7] ** 2)
    tor = np.sum(V[:, 7] ** 2)
    ax = np.sum(V[:, 2:4] ** 2)
    return ("bending", "torsion", "axial")[int(np.argmax([lat, tor, ax]))]


def linearised_eigen(S: ANCFArrays, q0, t: float = 0.0):
    """Eigenvalues and shapes (in q) of the DAE linearised about the steady state ``q0, v = 0`` of
    the base-spin formulation (autonomous at constant speed: the spin is carried by the base, so
    the straight spinning rotor is an equilibrium): ``M x'' + D x' + K x = 0`` on the null space of
    the constraint gradient, D holding the gyroscopic terms that follow from the kinetic energy.
    M and D are the acceleration and velocity derivatives themselves (``JacobianAssembler.
    rate_matrix``), not differences of stiffness-dominated Jacobians."""
    import scipy.linalg as sla
    n = q0.shape[0]
    nc = int(n_constraints(S))
    asm = JacobianAssembler(S)
    z = np.zeros(n)
    cur = np.zeros(max(1, S.amb_node.shape[0]))
    x = np.concatenate([q0, np.zeros(nc)])
    J0 = asm.matrix(x, z, 0.0, z, 0.0, t, cur, 1.0, 1.0).toarray()
    K = J0[:n, :n]
    M = asm.rate_matrix(q0, z, z, t, "a").toarray()
    D = asm.rate_matrix(q0, z, z, t, "v").toarray()
    N = sla.null_space(J0[n:, :n])
    Mr, Dr, Kr = N.T @ M @ N, N.T @ D @ N, N.T @ K @ N
    m = Mr.shape[0]
    A = np.block([[np.zeros((m, m)), np.eye(m)], [-Kr, -Dr]])
    B = np.block([[np.eye(m), np.zeros((m, m))], [np.zeros((m, m)), Mr]])
    lam, V = sla.eig(A, B)
    return lam, N @ V[:m]


def whirl(S: ANCFArrays, v) -> float:
    """Forwardness (F - B)/(F + B) of a mode shape's lateral orbits (+1 forward with the spin)."""
    Vn = v.reshape(-1, 8)
    X, Y = Vn[:, 0], Vn[:, 1]
    F = np.sum(np.abs(X + 1j * Y) ** 2)
    B = np.sum(np.abs(X - 1j * Y) ** 2)
    return float((F - B) / (F + B + 1e-300))
