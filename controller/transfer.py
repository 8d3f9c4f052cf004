"""Continuous per-axis AMB loop of the paper, eq. 7, as scipy.signal LTI objects.

    T(s) = k_x - G_s(s) G_c(s) G_A(s) k_i                    (force per unit displacement)
    G_c = k_p + k_i/s + k_d s/(1 + s T_d),  G_s = A_s/(1 + T_s s),  G_A = alpha_a/(1 + T_a s)

The coil current is ``i = -H(s) x`` with ``H = G_A G_c G_s`` (sensor -> PID -> amplifier), so the
bearing force ``F = k_x x + k_i i = T(s) x``.  Blocks that a scene leaves out (no integral term,
no lag) add no state.  The same parameters drive the discrete controller.
"""
from __future__ import annotations

import numpy as np
import scipy.signal as sig

from .params import Amplifier, ControllerParams, Sensor


def _lag(gain: float, tau: float) -> sig.StateSpace:
    if tau > 0:
        return sig.lti([gain], [tau, 1.0]).to_ss()
    return sig.StateSpace([[]], np.zeros((0, 1)), np.zeros((1, 0)), [[gain]])


def pid(c: ControllerParams) -> sig.StateSpace:
    """G_c(s); the derivative is filtered by 1/(1 + s T_d)."""
    kp, ki, kd, Td = c.kp, c.ki, c.kd, c.derivative_filter
    if kd > 0:
        num = [kp * Td + kd, kp + ki * Td, ki]
        den = [Td, 1.0, 0.0] if ki > 0 else [Td, 1.0]
        if ki == 0:
            num = [kp * Td + kd, kp]
    elif ki > 0:
        num, den = [kp, ki], [1.0, 0.0]
    else:
        return _lag(kp, 0.0)
    return sig.lti(num, den).to_ss()


def sensor(s: Sensor) -> sig.StateSpace:
    return _lag(s.gain, s.time_constant)


def amplifier(a: Amplifier) -> sig.StateSpace:
    return _lag(a.gain, a.time_constant)


def current_law(c: ControllerParams) -> sig.StateSpace:
    """H(s) = G_A G_c G_s: displacement (m) -> commanded coil current (A), to be applied as i = -H x."""
    return amplifier(c.amplifier) * pid(c) * sensor(c.sensor)


def bearing_transfer(kx: float, ki: float, H: sig.StateSpace) -> sig.StateSpace:
    """T(s) = k_x - k_i H(s), eq. 7: bearing force per unit rotor displacement."""
    return sig.StateSpace([[]], np.zeros((0, 1)), np.zeros((1, 0)), [[kx]]) + H * (-ki)


def evaluate(H: sig.StateSpace, s: np.ndarray) -> np.ndarray:
    """H(s) at complex points s (vectorised; no frequency-grid interpolation)."""
    s = np.atleast_1d(np.asarray(s, dtype=complex))
    A, B, C, D = (np.asarray(m, dtype=float) for m in (H.A, H.B, H.C, H.D))
    n = A.shape[0]
    if n == 0:
        return np.full(s.shape, D[0, 0], dtype=complex)
    I = np.eye(n)
    out = np.empty(s.shape, dtype=complex)
    for k, sk in enumerate(s):  # a pole hit exactly (e.g. the integrator at s = 0) gives inf
        try:
            out[k] = (C @ np.linalg.solve(sk * I - A, B))[0, 0] + D[0, 0]
        except np.linalg.LinAlgError:
            out[k] = np.inf
    return out


def is_siso(H: sig.StateSpace) -> bool:
    """A per-axis law (1 x 1, the same on every axis) rather than an na x na one."""
    return np.shape(H.D) == (1, 1)


def evaluate_matrix(H: sig.StateSpace, s: np.ndarray) -> np.ndarray:
    """A MIMO H(s) at complex points s: (n_s, outputs, inputs)."""
    s = np.atleast_1d(np.asarray(s, dtype=complex))
    A, B, C, D = (np.asarray(m, dtype=float) for m in (H.A, H.B, H.C, H.D))
    D = np.atleast_2d(D)
    n = A.shape[0] if A.size else 0
    out = np.empty((len(s),) + D.shape, dtype=complex)
    if n == 0:
        out[:] = D
        return out
    I = np.eye(n)
    for k, sk in enumerate(s):
        try:
            out[k] = C @ np.linalg.solve(sk * I - A, B) + D
        except np.linalg.LinAlgError:
            out[k] = np.inf
    return out
