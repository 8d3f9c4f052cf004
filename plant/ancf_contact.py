"""Auxiliary-bearing contact on the ANCF rung: the force of each auxiliary bearing in the step
residual and its 2x2 Jacobian, and the contact state kept after each step.

The physics is the linear rungs' (``plant/auxiliary_bearing.py``, docs/contact.md), through the same
kernel: :func:`ambhil.plant.integrator._station_force` (the contact law with the inner race's speed
solved implicitly, backward Euler, over the step).  Only where it acts differs: an auxiliary bearing
sits at its AMB's actuator node, so its force enters the rows of that node's position coordinates
``8 node + 0`` (x) and ``8 node + 1`` (y), the rows where the AMB force enters
(``plant/ancf_residual.py``).  The shaft centre relative to the bearing centre is the AMB's
stator-relative displacement ``x_op + q[k] - ref`` (the auxiliary bearing is concentric with the
stator), its velocity the scheme's ``v+ = vh + cv q+`` of those coordinates; both at ``t+``, where
the DAE integrators put the equilibrium.

The contact state per station is the linear rungs' ``NC`` floats with the same ``C_*`` meaning
(``plant/integrator.py``), so ``plant/contact_log.py`` and ``loop/simulation.ContactRecord`` read an
ANCF run unchanged.  Left out on this rung as on the linear ones: the friction torque does not act on
the shaft's spin or torsion (the spin is prescribed); it is reported (``C_TQ``).
"""
from __future__ import annotations

import math
from collections import namedtuple

import numba as nb
import numpy as np

from . import integrator as ig
from .auxiliary_bearing import A_C, A_V0MIN, A_VS

#: the stations of a run: ``aux_p`` (m, A_LEN) contact parameters (AuxiliaryBearing.array()),
#: ``aux_ax`` (m, 2) the x and y AMB axis of each (index into the ANCFArrays' amb_* arrays),
#: ``aux_dof`` (m, 2) the ANCF coordinates of those axes (8 node + 0, 8 node + 1).  ``aux_p`` is the
#: attribute :func:`ambhil.plant.integrator._station_force` reads.
ContactArrays = namedtuple("ContactArrays", ["aux_p", "aux_ax", "aux_dof"])


def stations(model, S):
    """(ContactArrays, names) of a model's auxiliary bearings in [[amb]] order (m = 0: none)."""
    from .plan import auxiliary_stations
    aux_p, aux_ax, names = auxiliary_stations(model)
    dof = np.zeros_like(aux_ax)
    for j in range(aux_ax.shape[0]):
        for e in range(2):
            a = aux_ax[j, e]
            if S.amb_axis[a] != e or S.amb_node[a] != S.amb_node[aux_ax[j, 0]]:
                raise ValueError(f"auxiliary bearing {names[j]}: its AMB's x and y axes must act at one node")
            dof[j, e] = 8 * S.amb_node[a] + e
    return ContactArrays(aux_p=aux_p, aux_ax=aux_ax, aux_dof=np.ascontiguousarray(dof)), names


@nb.njit(cache=True)
def _position(S, C, j, q, v):
    ax, ay = C.aux_ax[j, 0], C.aux_ax[j, 1]
    kx, ky = C.aux_dof[j, 0], C.aux_dof[j, 1]
    xs = S.amb_xop[ax] + q[kx] - S.amb_ref[ax]
    ys = S.amb_xop[ay] + q[ky] - S.amb_ref[ay]
    return xs, ys, v[kx], v[ky]


@nb.njit(cache=True)
def add_contact(S, C, c, q, v, cv, W, h, sd, out, jc):
    """out[k] -= sd F_c at every station's x/y rows (the residual's sign of an external force);
    ``jc[j]`` <- the station's 2x2 block of d(out)/dq+ ``-sd (dF/dpos + cv dF/dvel)`` by forward
    differences (the race solved in each; zero out of contact).  ``c``: the contact state before the
    step (race speed, the event's impact speed).  Returns a bit mask of the stations in or near
    contact (penetration > -1e-7 clearance), whose Jacobian is in ``jc``."""
    mask = 0
    for j in range(C.aux_p.shape[0]):
        xs, ys, vx, vy = _position(S, C, j, q, v)
        w_old, v0 = c[j, ig.C_W], c[j, ig.C_V0]
        fx, fy, fn, ft, d, dd, w, pf, pd = ig._station_force(C, j, xs, ys, vx, vy, W, w_old, v0, h)
        for r in range(2):
            for k in range(2):
                jc[j, r, k] = 0.0
        dp = 1e-7 * C.aux_p[j, A_C]
        if d > -dp:
            mask |= 1 << j
            if v0 <= 0.0:  # an event starting in this step: hold its impact speed fixed
                r_ = math.sqrt(xs * xs + ys * ys)
                v0 = max((xs * vx + ys * vy) / r_ if r_ > 0.0 else 0.0, C.aux_p[j, A_V0MIN])
            dv = 1e-4 * C.aux_p[j, A_VS]
            for col in range(4):
                ex = dp if col == 0 else 0.0
                ey = dp if col == 1 else 0.0
                evx = dv if col == 2 else 0.0
                evy = dv if col == 3 else 0.0
                gx, gy, _, _, _, _, _, _, _ = ig._station_force(C, j, xs + ex, ys + ey, vx + evx, vy + evy, W,
                                                                w_old, v0, h)
                sc = -sd / dp if col < 2 else -sd * cv / dv
                jc[j, 0, col % 2] += sc * (gx - fx)
                jc[j, 1, col % 2] += sc * (gy - fy)
        if fn > 0.0:
            out[C.aux_dof[j, 0]] -= sd * fx
            out[C.aux_dof[j, 1]] -= sd * fy
    return mask


#: the contact state's kernel of the linear rungs (``plant.integrator._contact_commit``) reads a plan;
#: this is the part of one it reads, for a "plant" whose coordinates are the stations' x and y alone
#: (identity rows, q and v gathered from the ANCF state before each commit), so both rungs keep the
#: contact state with the very same code
StationPlan = namedtuple("StationPlan", ["ip", "fp", "aux_p", "aux_ax", "xop", "ca_ptr", "ca_idx", "ca_val"])


class ContactState:
    """The (m, NC) contact state of the stations (``c``) and its commit after each step."""

    def __init__(self, S, C, q0):
        m = C.aux_p.shape[0]
        self.C, self.m, self.n = C, m, 2 * m
        self.sv = np.zeros(4 * self.n + 1 + m * ig.NC)  # [q, v, h1, h2, k, aux] of the station plan
        self.c = self.sv[4 * self.n + 1:].reshape(m, ig.NC)
        self.c[:, ig.C_TE] = -1.0  # no contact event has ended yet
        self.dof = np.ascontiguousarray(C.aux_dof.ravel())
        self.set_arrays(S)
        xy = (self.plan.xop + q0[self.dof]).reshape(m, 2)  # where the shaft starts in each bearing
        self.c[:, ig.C_X], self.c[:, ig.C_Y] = xy[:, 0], xy[:, 1]
        self.c[:, ig.C_D] = np.hypot(xy[:, 0], xy[:, 1]) - C.aux_p[:, A_C]

    def set_arrays(self, S) -> None:
        """The station plan for the model arrays S (its spin profile, the AMBs' x_op and ref)."""
        n, m, C = self.n, self.m, self.C
        ip = np.zeros(11, dtype=np.int64)
        ip[ig.I_N], ip[ig.I_AUX] = n, m
        fp = np.zeros(15)
        fp[ig.F_W0], fp[ig.F_W1], fp[ig.F_T0], fp[ig.F_T1] = S.spin[1], S.spin[2], S.spin[3], S.spin[4]
        ax = C.aux_ax.ravel()
        self.plan = StationPlan(ip=ip, fp=fp, aux_p=C.aux_p, aux_ax=np.arange(n, dtype=np.int64).reshape(m, 2),
                                xop=np.ascontiguousarray(S.amb_xop[ax] - S.amb_ref[ax]),
                                ca_ptr=np.arange(n + 1, dtype=np.int64), ca_idx=np.arange(n, dtype=np.int64),
                                ca_val=np.ones(n))

    def commit(self, q, v, t1: float, h: float) -> None:
        """The contact state after a step that ended at t1 with the ANCF (q, v)."""
        n = self.n
        self.sv[0:n] = q[self.dof]
        self.sv[n:2 * n] = v[self.dof]
        ig._contact_commit(self.plan, self.sv, t1, h, ig.speed_at(self.plan.fp, t1)[1])


def jacobian_positions(csc, C) -> np.ndarray:
    """(m, 2, 2) positions in ``csc.data`` of the x/y rows and columns of every station (the AMB
    node's 8x8 block is in the step matrix's pattern, so they exist)."""
    pos = np.zeros((C.aux_dof.shape[0], 2, 2), dtype=np.int64)
    for j in range(C.aux_dof.shape[0]):
        for r in range(2):
            for k in range(2):
                row, col = C.aux_dof[j, r], C.aux_dof[j, k]
                lo, hi = csc.indptr[col], csc.indptr[col + 1]
                i = lo + int(np.searchsorted(csc.indices[lo:hi], row))
                if i >= hi or csc.indices[i] != row:
                    raise RuntimeError("contact Jacobian entry outside the step matrix's pattern")
                pos[j, r, k] = i
    return pos
