"""Loop latency on the plant side: a coil current reaches the coil ``tau = d T + m h`` after the
controller computed it (``T`` the input period, ``h`` the plant step, ``0 <= m < T/h``).

Over period k the coil holds ``u_{k-d-1}`` for the first ``m`` plant steps and ``u_{k-d}`` for
the rest; before any command has arrived it holds the operating-point current.  The commands in
flight live in a ring of ``D = d + 1 (+1 if m > 0)`` rows, row ``j % D`` holding ``u_j``.  This is
the held-current timing model of ``loop/sampled.py`` (exact there; here integrated by the plant's
scheme), shared by the plant process and the in-process loop.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .integrator import NONFINITE, OK, TOUCHDOWN, plant_advance
from .params import ParameterError


def split_latency(tau: float, period: float, h: float) -> tuple[int, int]:
    """``(d, m)`` with ``tau = d period + m h``; m must be a whole number of plant steps."""
    if not tau >= 0:
        raise ParameterError(f"latency must be >= 0 s, got {tau!r}")
    d = int(np.floor(tau / period + 1e-9))
    e = tau - d * period
    m = int(round(e / h))
    if e < 1e-9 * period:
        m = 0
    elif abs(m * h - e) > 1e-6 * h or m >= round(period / h):
        raise ParameterError(f"latency {tau:g} s = {d} periods + {e:g} s: the fraction must be a whole number "
                             f"of plant steps (h = {h:g} s); choose a finer step or another latency")
    return d, m


def new_ring(d: int, m: int, i_op) -> np.ndarray:
    """The commands-in-flight ring, every row at the operating point."""
    D = d + 1 + (1 if m > 0 else 0)
    return np.tile(np.asarray(i_op, np.float64), (D, 1))


@nb.njit(cache=True, _nrt=False)
def advance_late(p, s, cur, ring, k, d, m, ratio, wk, ws, y):
    """Period k: store this period's command ``cur`` (= u_k), then m plant steps with u_{k-d-1}
    and ratio - m with u_{k-d}; sensor readings into y; returns the status."""
    D = ring.shape[0]
    na = cur.shape[0]
    slot = k % D
    for a in range(na):
        ring[slot, a] = cur[a]
    st = OK
    if m > 0:
        st = plant_advance(p, s, ring[(k - d - 1 + D * (d + 2)) % D], m, wk, ws, y)
        if st == NONFINITE or st == TOUCHDOWN:
            return st
    st2 = plant_advance(p, s, ring[(k - d + D * (d + 2)) % D], ratio - m, wk, ws, y)
    return st2 if st2 != OK else st
