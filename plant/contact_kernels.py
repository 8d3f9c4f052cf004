"""The auxiliary bearings' contact in the implicit plant step (docs/physics.md, docs/contact.md):
the force of each station at the scheme's evaluation point with the race speed solved implicitly
(:func:`_station_force`), its residual term and 2x2 Jacobian (:func:`_add_contact`), the Woodbury
correction of the banded factorisation by those Jacobians (:func:`_contact_basis`,
:func:`_woodbury`), and the contact state committed after each step (:func:`_contact_commit`).
Called by :func:`ambhil.plant.integrator.plant_step` only for a plan with auxiliary bearings
(``ip[I_AUX] > 0``), and by the ancf rung (plant/ancf_contact.py)."""
from __future__ import annotations

import math

import numba as nb

from .auxiliary_bearing import A_CC, A_MU, A_N, A_RI, A_RS, A_V0MIN, A_VS, contact as _contact_law, normal_force, \
    race_speed_implicit
from .banded import band_solve
from .plan_layout import (C_D, C_ED, C_EDMAX, C_EE, C_EF, C_EPEAK, C_EV0, C_EVOUT, C_FN, C_FT, C_FX, C_FY, C_IMP,
                          C_NEV, C_PEAK, C_DMAX, C_PF, C_TE, C_TQ, C_TS, C_V0, C_W, C_X, C_Y, F_AF, F_CZD, F_OM,
                          I_AUX, I_N, NC)

# Scheme codes of the evaluation velocity (how v at the force's instant depends on the unknown q+)
V_BDF1, V_TRAP, V_BDF2, V_GALPHA = range(4)


@nb.njit(cache=True, _nrt=False)
def _row(p, a, x):
    """(Ca x)_a: axis a's displacement for generalised coordinates x."""
    acc = 0.0
    for m in range(p.ca_ptr[a], p.ca_ptr[a + 1]):
        acc += p.ca_val[m] * x[p.ca_idx[m]]
    return acc


@nb.njit(cache=True, _nrt=False)
def _row_vw(p, a, vk, x, q, v, h1, h, bh):
    """(Ca v_w)_a: axis a's velocity at the force's instant for the iterate x of q+ (the schemes'
    velocity update, plant_step's "velocities and history", on the row's DOFs only)."""
    acc = 0.0
    for m in range(p.ca_ptr[a], p.ca_ptr[a + 1]):
        k = p.ca_idx[m]
        if vk == V_BDF1:
            w = (x[k] - q[k]) / bh
        elif vk == V_TRAP:
            w = (x[k] - q[k] - 0.5 * h * v[k]) / bh
        elif vk == V_BDF2:
            w = (x[k] - (4.0 * q[k] - h1[k]) / 3.0) / bh
        else:
            af = p.fp[F_AF]
            vn = (x[k] - q[k] - p.fp[F_CZD] * h1[k] - bh * (1.0 - af) * v[k]) / (bh * p.fp[F_OM])
            w = (1.0 - af) * v[k] + af * vn
        acc += p.ca_val[m] * w
    return acc


@nb.njit(cache=True, _nrt=False)
def _station_force(p, j, xs, ys, vx, vy, W, w_old, v0, h):
    """Force of auxiliary bearing j on the shaft with the race speed solved implicitly over h:
    ``(fx, fy, fn, ft, d, dd, w_race, p_friction, p_damping)``.  ``v0``: the event's impact speed
    (0: the event starts now, its speed is the current normal rate)."""
    pa = p.aux_p[j]
    r = math.sqrt(xs * xs + ys * ys)
    dd0 = (xs * vx + ys * vy) / r if r > 0.0 else 0.0
    v0e = v0 if v0 > 0.0 else max(dd0, pa[A_V0MIN])
    fn, fel, d, dd, nx, ny, r = normal_force(xs, ys, vx, vy, v0e, pa)
    if pa[A_N] == 1.0 and pa[A_CC] > 0.0 and 0.0 < d < v0e * h:
        # the linear law's dashpot jumps by c_c v0 at d = 0: ramped in over the penetration of one
        # step at the impact speed, or the implicit step at an impact may have no solution (the
        # shaft pushed out by the dashpot, falling in without it); the ramp vanishes as h -> 0
        fn = max(fel + pa[A_CC] * dd * d / (v0e * h), 0.0)
    if fn <= 0.0:
        w = race_speed_implicit(0.0, 0.0, W, w_old, h, pa)
        # held at 0 by the clamp while d > 0 (the shaft leaving faster than the spring relaxes):
        # the spring's energy is lost from the motion there, dissipated at the rate -F_el d' >= 0
        return 0.0, 0.0, 0.0, 0.0, d, dd0, w, 0.0, (-fel * dd if d > 0.0 else 0.0)
    vt = (xs * vy - ys * vx) / r
    w = race_speed_implicit(fn, vt, W, w_old, h, pa)
    v_rel = vt + pa[A_RS] * W - pa[A_RI] * w
    ft = -pa[A_MU] * fn * math.tanh(v_rel / pa[A_VS])
    return -fn * nx - ft * ny, -fn * ny + ft * nx, fn, ft, d, dd, w, -ft * v_rel, (fn - fel) * dd


@nb.njit(cache=True, _nrt=False)
def _add_contact(p, s, qw, x, q, v, h1, vk, h, bh, W, scale, out, jc, jac):
    """out += scale * Ca_c^T F_c for every auxiliary-bearing station at the iterate x (positions qw).
    With ``jac``: jc[4 j: 4 j + 4] <- the station's 2x2 Jacobian term of the step residual,
    -(bh om dF/dpos + dF/dvel), by forward differences (0 out of contact).  Returns the bit mask of
    the stations in or near contact (penetration > -1e-7 clearance: their Jacobian is non-zero)."""
    n = p.ip[I_N]
    om = p.fp[F_OM]
    mask = 0
    for j in range(p.ip[I_AUX]):
        ax, ay = p.aux_ax[j, 0], p.aux_ax[j, 1]
        b = 4 * n + 1 + j * NC
        xs = p.xop[ax] + _row(p, ax, qw)
        ys = p.xop[ay] + _row(p, ay, qw)
        vx = _row_vw(p, ax, vk, x, q, v, h1, h, bh)
        vy = _row_vw(p, ay, vk, x, q, v, h1, h, bh)
        w_old, v0 = s[b + C_W], s[b + C_V0]
        fx, fy, fn, ft, d, dd, w, pf, pd = _station_force(p, j, xs, ys, vx, vy, W, w_old, v0, h)
        dp = 1e-7 * p.aux_p[j, 0]
        if d > -dp:
            mask |= 1 << j
        if jac:
            for e in range(4):
                jc[4 * j + e] = 0.0
        if jac and d > -dp:
            # the Jacobian by forward differences (the race solved in each): columns x, y, vx, vy
            if v0 <= 0.0:  # an event starting in this step: hold its impact speed fixed
                r = math.sqrt(xs * xs + ys * ys)
                v0 = max((xs * vx + ys * vy) / r if r > 0.0 else 0.0, p.aux_p[j, A_V0MIN])
            dv = 1e-4 * p.aux_p[j, A_VS]
            for col in range(4):
                e_x = dp if col == 0 else 0.0
                e_y = dp if col == 1 else 0.0
                e_vx = dv if col == 2 else 0.0
                e_vy = dv if col == 3 else 0.0
                gx, gy, _, _, _, _, _, _, _ = _station_force(p, j, xs + e_x, ys + e_y, vx + e_vx, vy + e_vy, W,
                                                             w_old, v0, h)
                if col < 2:
                    sc = -bh * om / dp
                else:
                    sc = -1.0 / dv
                jc[4 * j + (col % 2)] += sc * (gx - fx)        # row x
                jc[4 * j + 2 + (col % 2)] += sc * (gy - fy)    # row y
        if fn > 0.0:
            for m in range(p.ca_ptr[ax], p.ca_ptr[ax + 1]):
                out[p.ca_idx[m]] += scale * p.ca_val[m] * fx
            for m in range(p.ca_ptr[ay], p.ca_ptr[ay + 1]):
                out[p.ca_idx[m]] += scale * p.ca_val[m] * fy
    return mask


@nb.njit(cache=True, _nrt=False)
def _contact_basis(p, LU, bw, wk):
    """wk[6 + c] <- S^-1 Ca_c^T for the 2m station axes c (the Woodbury basis of this step)."""
    n = p.ip[I_N]
    for j in range(p.ip[I_AUX]):
        for e in range(2):
            a = p.aux_ax[j, e]
            z = wk[6 + 2 * j + e, :n]
            for k in range(n):
                z[k] = 0.0
            for m in range(p.ca_ptr[a], p.ca_ptr[a + 1]):
                z[p.ca_idx[m]] = p.ca_val[m]
            band_solve(LU, bw, z)


@nb.njit(cache=True, _nrt=False)
def _woodbury(p, wk, dx, jc):
    """dx <- (S + Ca_c^T Jc Ca_c)^-1 r given dx = S^-1 r: dx - Z (I + Jc Ca_c Z)^-1 Jc Ca_c dx with
    Z = S^-1 Ca_c^T (wk[6 + c]); Jc block-diagonal, 2x2 per station.  Dense elimination with partial
    pivoting on the 2m x 2m system (m stations: at most a few)."""
    n = p.ip[I_N]
    m2 = 2 * p.ip[I_AUX]
    sc = wk[6 + m2]
    A = sc[0:m2 * m2]
    c = sc[m2 * m2:m2 * m2 + m2]
    g = sc[m2 * m2 + m2:m2 * m2 + 2 * m2]
    for i in range(m2):
        c[i] = _row(p, p.aux_ax[i // 2, i % 2], dx)
    for i in range(m2):
        j = i // 2
        r0 = 4 * j + 2 * (i % 2)
        # row i of Jc: jc[r0], jc[r0 + 1] on the station's two axes 2j, 2j + 1
        g[i] = jc[r0] * c[2 * j] + jc[r0 + 1] * c[2 * j + 1]
        for k in range(m2):
            z0 = _row(p, p.aux_ax[j, 0], wk[6 + k, :n])
            z1 = _row(p, p.aux_ax[j, 1], wk[6 + k, :n])
            A[i * m2 + k] = (1.0 if i == k else 0.0) + jc[r0] * z0 + jc[r0 + 1] * z1
    # solve A w = g in place (w in g)
    for col in range(m2):
        piv = col
        for r in range(col + 1, m2):
            if abs(A[r * m2 + col]) > abs(A[piv * m2 + col]):
                piv = r
        if piv != col:
            for k in range(m2):
                A[col * m2 + k], A[piv * m2 + k] = A[piv * m2 + k], A[col * m2 + k]
            g[col], g[piv] = g[piv], g[col]
        d = A[col * m2 + col]
        for r in range(col + 1, m2):
            f = A[r * m2 + col] / d
            if f != 0.0:
                for k in range(col, m2):
                    A[r * m2 + k] -= f * A[col * m2 + k]
                g[r] -= f * g[col]
    for col in range(m2 - 1, -1, -1):
        acc = g[col]
        for k in range(col + 1, m2):
            acc -= A[col * m2 + k] * g[k]
        g[col] = acc / A[col * m2 + col]
    for k in range(m2):
        wkk = g[k]
        if wkk != 0.0:
            z = wk[6 + k, :n]
            for i in range(n):
                dx[i] -= z[i] * wkk


@nb.njit(cache=True, _nrt=False)
def _stations_clear(p, qw):
    """Whether every auxiliary-bearing station is out of contact at positions qw."""
    for j in range(p.ip[I_AUX]):
        ax, ay = p.aux_ax[j, 0], p.aux_ax[j, 1]
        xs = p.xop[ax] + _row(p, ax, qw)
        ys = p.xop[ay] + _row(p, ay, qw)
        if xs * xs + ys * ys > p.aux_p[j, 0] * p.aux_p[j, 0]:
            return False
    return True


@nb.njit(cache=True, _nrt=False)
def _contact_commit(p, s, t1, h, W):
    """After a step to t1: each station's contact state at the new (q, v) into the state vector
    (force, race speed, powers, the works and impulse over the step, contact events); ``W`` the
    spin speed at t1."""
    n = p.ip[I_N]
    q = s[0:n]
    v = s[n:2 * n]
    for j in range(p.ip[I_AUX]):
        ax, ay = p.aux_ax[j, 0], p.aux_ax[j, 1]
        b = 4 * n + 1 + j * NC
        xs = p.xop[ax] + _row(p, ax, q)
        ys = p.xop[ay] + _row(p, ay, q)
        vx = _row(p, ax, v)
        vy = _row(p, ay, v)
        v0 = s[b + C_V0]
        fx, fy, fn, ft, d, dd, w, pf, pd = _station_force(p, j, xs, ys, vx, vy, W, s[b + C_W], v0, h)
        s[b + C_W] = w
        s[b + C_FX], s[b + C_FY], s[b + C_FN], s[b + C_FT], s[b + C_D] = fx, fy, fn, ft, d
        s[b + C_PF] = pf
        s[b + C_X], s[b + C_Y] = xs, ys
        s[b + C_TQ] = p.aux_p[j, A_RS] * ft
        if fn > 0.0:
            s[b + C_EF] += h * pf
            s[b + C_ED] += h * pd
            s[b + C_IMP] += h * fn
            if v0 <= 0.0:  # a contact event starts
                s[b + C_NEV] += 1.0
                s[b + C_TS] = t1
                s[b + C_V0] = max(dd, p.aux_p[j, A_V0MIN])
                s[b + C_EV0] = dd
                s[b + C_EPEAK] = 0.0
                s[b + C_EE] = 0.0
                s[b + C_EDMAX] = 0.0
            if fn > s[b + C_EPEAK]:
                s[b + C_EPEAK] = fn
            s[b + C_EE] += h * (pf + pd)
            if fn > s[b + C_PEAK]:
                s[b + C_PEAK] = fn
            if d > s[b + C_DMAX]:
                s[b + C_DMAX] = d
            if d > s[b + C_EDMAX]:
                s[b + C_EDMAX] = d
        else:
            s[b + C_ED] += h * pd  # the clamped tail of an event (d > 0, F_n = 0)
        if fn <= 0.0 and v0 > 0.0:  # the event ends
            s[b + C_TE] = t1
            s[b + C_EVOUT] = max(-dd, 0.0)  # d' < 0: leaving
            s[b + C_V0] = 0.0


@nb.njit(cache=True, _nrt=False)
def _add_contact_explicit(p, s, q, v, W, out):
    """out += Ca_c^T F_c at (q, v) and spin speed W with the state's race speeds (generalised-alpha's
    consistent rates)."""
    n = p.ip[I_N]
    for j in range(p.ip[I_AUX]):
        ax, ay = p.aux_ax[j, 0], p.aux_ax[j, 1]
        b = 4 * n + 1 + j * NC
        xs = p.xop[ax] + _row(p, ax, q)
        ys = p.xop[ay] + _row(p, ay, q)
        v0 = s[b + C_V0]
        fx, fy, fn, ft, d, t_s, t_r, pf, pd = _contact_law(xs, ys, _row(p, ax, v), _row(p, ay, v), W, s[b + C_W],
                                                           v0 if v0 > 0.0 else 1.0, p.aux_p[j])
        for m in range(p.ca_ptr[ax], p.ca_ptr[ax + 1]):
            out[p.ca_idx[m]] += p.ca_val[m] * fx
        for m in range(p.ca_ptr[ay], p.ca_ptr[ay + 1]):
            out[p.ca_idx[m]] += p.ca_val[m] * fy


@nb.njit(cache=True, _nrt=False)
def _add_contact_state(p, s, scale, out):
    """out += scale * Ca_c^T F_c(z_n): the contact force of the state (committed after the last step),
    the trapezoidal rule's h/2 F(t_n, z_n) part."""
    n = p.ip[I_N]
    for j in range(p.ip[I_AUX]):
        ax, ay = p.aux_ax[j, 0], p.aux_ax[j, 1]
        b = 4 * n + 1 + j * NC
        fx, fy = s[b + C_FX], s[b + C_FY]
        for m in range(p.ca_ptr[ax], p.ca_ptr[ax + 1]):
            out[p.ca_idx[m]] += scale * p.ca_val[m] * fx
        for m in range(p.ca_ptr[ay], p.ca_ptr[ay + 1]):
            out[p.ca_idx[m]] += scale * p.ca_val[m] * fy


