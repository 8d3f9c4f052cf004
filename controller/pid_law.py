"""The built-in PID of the paper (eq. 7) as a law: ``u = kp e + I[e] + D[e]`` on the negated
sensor output ``e = -y``, ``I = ki/s``, ``D = kd s/(Td s + 1)``, each block discretised by scipy
at the loop's period (:func:`ambhil.controller.discrete.discretise`), the command limited to the
amplifier's input range, and the integrator clamped while the command is limited and the error
drives it further (anti-windup).

The testbench runs the built-in law fused with the sensor and amplifier in one kernel
(:func:`ambhil.controller.discrete.controller_step`, the fast path); this class is the same law
on its own, between the hardware kernels of :mod:`ambhil.controller.hardware`, as any user's law
runs.  Both give the same numbers bit for bit (tests/test_laws.py): the arithmetic is the same in
the same order.  (The fused kernel also counts an amplifier output beyond ``current_limit`` as
saturation for the anti-windup; with the input limited to ``current_limit / gain`` a first-order
lag, ZOH or Tustin with ``T_a >= T/2``, cannot exceed it, so the two never part.)
"""
from __future__ import annotations

import dataclasses

import numba as nb
import numpy as np

from . import discrete as dc
from .law import LawMeta
from .params import ControllerParams


@nb.njit(cache=True, _nrt=False)
def pid_step(p, x, y, u):
    """The PID of all axes in place: state ``x`` (integrator, derivative per axis), sensor
    outputs ``y`` -> amplifier inputs ``u``."""
    ulim = p[dc.P_ULIM]
    for a in range(y.shape[0]):
        o = 2 * a
        e = -y[a]
        xi = x[o]
        ui = p[dc.P_CI] * xi + p[dc.P_DI] * e
        xd = x[o + 1]
        ud = p[dc.P_CD] * xd + p[dc.P_DD] * e
        x[o + 1] = p[dc.P_AD] * xd + p[dc.P_BD] * e
        v = p[dc.P_KP] * e + ui + ud
        sat = v > ulim or v < -ulim
        if sat and p[dc.P_AW] != 0.0 and e * v > 0.0:
            pass
        else:
            x[o] = p[dc.P_AI] * xi + p[dc.P_BI] * e
        u[a] = v


class PIDLaw:
    """The built-in law through the law interface (``PIDLaw(meta)``, ``step(t, y)``, ``reset()``)."""

    def __init__(self, meta: LawMeta):
        t = meta.controller
        cfg = ControllerParams(kp=float(t["kp"]), ki=float(t.get("ki", 0.0)), kd=float(t.get("kd", 0.0)),
                               derivative_filter=float(t.get("derivative_filter", 0.0)),
                               sample_rate=float(t.get("sample_rate", 1.0 / meta.period)),
                               discretisation=str(t.get("discretisation", "tustin")),
                               anti_windup=bool(t.get("anti_windup", True)),
                               sensor=meta.sensor, amplifier=meta.amplifier)
        self.params = dc.discretise(dataclasses.replace(cfg, delay_samples=0))
        self.u_op = np.array(meta.u_op, float)
        self.u = np.zeros(meta.n_axes)
        self.reset()

    def reset(self) -> None:
        """The integrator preloaded so that the law holds ``u_op`` at zero displacement."""
        self.x = np.zeros(2 * len(self.u_op))
        ci = self.params[dc.P_CI]
        if ci != 0.0:
            self.x[0::2] = self.u_op / ci

    def step(self, t: float, y: np.ndarray) -> np.ndarray:
        pid_step(self.params, self.x, y, self.u)
        return self.u
