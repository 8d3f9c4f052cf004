"""The hardware around a control law: the sensor and the amplifier of each axis, as the
controller process emulates them (controller/law.py says what a law sees).

    sensor      y = G_s[d]                          (gain A_s, lag T_s; d: rotor displacement, m)
    law         u = law.step(t, y)                  (the user's, or the built-in PID)
    amplifier   u_s = clip(u, +-u_max)              (u_max = current_limit / alpha_a, its input range)
                i = clip(G_A[u_s], +-current_limit)  (gain alpha_a, lag T_a)
                i = i_prev + clip(i - i_prev, +-slew_rate T)   (the slew limit, if any)
    delay       the current of sample k reaches the coils at sample k + delay_samples

The blocks are the very coefficients of the built-in controller
(:func:`ambhil.controller.discrete.discretise`: scipy's Tustin or ZOH of each first-order block),
evaluated with the same arithmetic in the same order, so the built-in PID run as a law between
these kernels gives the fused kernel's numbers (tests/test_laws.py).

State (one flat float64 vector, :func:`initial_state`): per axis ``[sensor, amplifier, previous
current]``, then the delay ring (``n_axes x delay`` currents) and its index.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from . import discrete as dc

NH = 3          # hardware states per axis: sensor lag, amplifier lag, the last current (slew)


def hardware_params(p: np.ndarray, slew_rate: float, period: float) -> np.ndarray:
    """The discrete controller's parameter vector with the slew limit per sample appended
    (``inf`` = none)."""
    return np.append(np.asarray(p, float), slew_rate * period if math.isfinite(slew_rate) else np.inf)


def state_size(n_axes: int, delay: int) -> int:
    return n_axes * NH + n_axes * delay + 1


@nb.njit(cache=True, _nrt=False)
def sensor_step(p, h, d, y):
    """The sensors of all axes in place: displacements ``d`` -> sensor outputs ``y``."""
    for a in range(d.shape[0]):
        o = a * NH
        xs = h[o]
        y[a] = p[dc.P_CS] * xs + p[dc.P_DS] * d[a]
        h[o] = p[dc.P_AS] * xs + p[dc.P_BS] * d[a]


@nb.njit(cache=True, _nrt=False)
def amplifier_step(p, h, u, cur):
    """The amplifiers of all axes in place: amplifier inputs ``u`` -> coil currents ``cur``
    (after the delay).  Returns the number of axes limited (input range, current or slew)."""
    na = u.shape[0]
    nd = int(p[dc.P_DELAY])
    ilim, ulim = p[dc.P_ILIM], p[dc.P_ULIM]
    slew = p[dc.P_LEN]
    nsat = 0
    for a in range(na):
        o = a * NH
        sat = False
        ua = u[a]
        if ua > ulim:
            ua = ulim
            sat = True
        elif ua < -ulim:
            ua = -ulim
            sat = True
        xa = h[o + 1]
        i = p[dc.P_CA] * xa + p[dc.P_DA] * ua
        h[o + 1] = p[dc.P_AA] * xa + p[dc.P_BA] * ua
        if i > ilim:
            i = ilim
            sat = True
        elif i < -ilim:
            i = -ilim
            sat = True
        if slew < np.inf:
            prev = h[o + 2]
            if i > prev + slew:
                i = prev + slew
                sat = True
            elif i < prev - slew:
                i = prev - slew
                sat = True
            h[o + 2] = i
        if sat:
            nsat += 1
        if nd > 0:
            base = na * NH + a * nd
            k = int(h[h.shape[0] - 1])
            cur[a] = h[base + k]
            h[base + k] = i
        else:
            cur[a] = i
    if nd > 0:
        h[h.shape[0] - 1] = (h[h.shape[0] - 1] + 1.0) % nd
    return nsat


@nb.njit(cache=True, _nrt=False)
def first_nonfinite(u):
    """The index of the first non-finite value of ``u``, or -1 (what a law returned, checked
    before it reaches the amplifier)."""
    for a in range(u.shape[0]):
        if not np.isfinite(u[a]):
            return a
    return -1


def initial_state(p: np.ndarray, i_op) -> np.ndarray:
    """Hardware in equilibrium at zero displacement with the coil current ``i_op`` per axis:
    the amplifier's state and the delay ring hold it (the same preload as the fused kernel,
    :func:`ambhil.controller.discrete.initial_state`)."""
    i_op = np.asarray(i_op, float).reshape(-1)
    na, nd = len(i_op), int(p[dc.P_DELAY])
    h = np.zeros(state_size(na, nd))
    for a, i0 in enumerate(i_op):
        h[a * NH + 2] = i0
        if i0 == 0.0:
            continue
        amp_dc = p[dc.P_DA] + (p[dc.P_CA] * p[dc.P_BA] / (1 - p[dc.P_AA]) if p[dc.P_AA] != 1 else 0.0)
        u = i0 / amp_dc
        if p[dc.P_BA] != 0.0:
            h[a * NH + 1] = p[dc.P_BA] * u / (1 - p[dc.P_AA])
        if nd:
            h[na * NH + a * nd: na * NH + (a + 1) * nd] = i0
    return h


def input_at(p: np.ndarray, i_op) -> np.ndarray:
    """The amplifier input that holds ``i_op`` in steady state (the fused kernel's preload)."""
    amp_dc = p[dc.P_DA] + (p[dc.P_CA] * p[dc.P_BA] / (1 - p[dc.P_AA]) if p[dc.P_AA] != 1 else 0.0)
    return np.asarray(i_op, float).reshape(-1) / amp_dc
