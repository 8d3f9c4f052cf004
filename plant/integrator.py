"""Fixed-step implicit integrators for the rotor-AMB plant: one interface, five schemes.

The plant is ``M q'' + D(Omega) q' + K_eff q = Ba [k_i (i - i_op) + r(Ca q, i)] + f_unb(t)``
(``Ba = Ca^T``; ``r`` is zero for the linearised force law and the remainder
``F(x_op + x, i) - k_x x - k_i (i - i_op)`` of the exact force law otherwise).  With
``z = [q; v]`` it reads ``E z' = F(t, z)``, ``E = blkdiag(I, M)``.  The coil currents are held
constant over a step (zero-order hold from the controller).

Every implicit scheme below is written as ``E z+ = P + beta h F(t*, w)`` with ``w = w0 + omega z+``:

========================  ==========================================  ========  =======  =========
scheme                    P (explicit part)                           beta      omega    t*
========================  ==========================================  ========  =======  =========
``bdf1`` (paper)          E z_n                                       1         1        t + h
``bdf2``                  4/3 E z_n - 1/3 E z_{n-1}  (BDF1 first)     2/3       1        t + h
``trapezoidal``           E z_n + h/2 F(t_n, z_n)                     1/2       1        t + h
``generalized-alpha``     E [z + h(1-g) zd - h g (1-am)/am zd]        g/am      af       t + af h
========================  ==========================================  ========  =======  =========

(trapezoidal on the first-order form is Newmark's average-acceleration rule; generalised-alpha
is the first-order form of Jansen, Whiting & Hulbert 2000 with ``am = (3 - rho)/(2(1 + rho))``,
``af = 1/(1 + rho)``, ``g = 1/2 + am - af``, second order and A-stable for ``rho_inf`` in [0, 1].)
The first block row gives ``v+`` explicitly from ``q+``; the second is one equation in ``q+``

    S q+ = b,    S = M/(beta h omega) + D + beta h omega K_eff

whose matrix is banded (node-major FE DOFs) and is factorised once (no pivoting; checked at
build time).  A step is then a few banded products and one banded back-substitution.  Nonlinear
scenes (exact AMB force law, speed run-up) solve the same equation by Newton's method with the
factorised linear Jacobian (chord iteration), a bounded number of iterations and a refactorisation
when the spin speed has drifted; non-convergence is recorded (time, iteration, residual).

``zoh`` is exact for linear time-invariant scenes: ``[z; i; cos; sin]`` is propagated by
``expm(h A_aug)``, the unbalance being an exact harmonic oscillator state.

Auxiliary bearings (a plan with ``ip[I_AUX] > 0``) add their contact force to the implicit step:
:mod:`ambhil.plant.contact_kernels`; the arrays' layout: :mod:`ambhil.plant.plan_layout`.

The kernels are numba functions operating in place on preallocated arrays (no allocation in the
hot path); :mod:`ambhil.plant.plan` builds their arrays from a model, :mod:`ambhil.plant.banded` holds the banded
linear algebra, :mod:`ambhil.plant.step` wraps them in a pure ``step`` and the ``PlantRunner``.
"""
from __future__ import annotations

import math
import numba as nb

from .banded import band_lu, band_mv, band_solve
from .contact_kernels import (V_BDF1, V_TRAP, V_BDF2, V_GALPHA, _row, _row_vw, _station_force, _add_contact, _contact_basis,
                              _woodbury, _stations_clear, _contact_commit, _add_contact_explicit,
                              _add_contact_state)  # noqa: F401
from .plan_layout import (SCHEMES, BDF1, BDF2, TRAP, GALPHA, ZOH, ORDER, OK, NEWTON_FAIL, NONFINITE, TOUCHDOWN, STATUS_TEXT,
                          W_OMEGA_F, W_STATUS, W_FAIL_T, W_FAIL_IT, W_FAIL_RES, W_FAIL_AX, W_NFAIL,
                          W_MAXIT, W_NREFAC, W_LEN, PlantArrays, I_SCHEME, I_N, I_NA, I_BW, I_NL,
                          I_RUNUP, I_MAXIT, I_DENSE, I_NS, I_AUX, I_F0, C_W, C_V0, C_FX, C_FY, C_FN,
                          C_FT, C_D, C_PF, C_EF, C_ED, C_IMP, C_NEV, C_PEAK, C_DMAX, C_TS, C_TE,
                          C_EPEAK, C_EE, C_EV0, C_EVOUT, C_X, C_Y, C_TQ, C_EDMAX, NC,
                          CONTACT_FIELDS, F_H, F_BH, F_OM, F_AM, F_AF, F_G, F_CZD, F_TOL, F_REFAC,
                          F_W0, F_W1, F_T0, F_T1, F_WNOM, F_TH0)  # noqa: F401 (re-exported)



# --------------------------------------------------------------------------- speed profile
@nb.njit(cache=True, _nrt=False)
def speed_at(fp, t):
    """(theta, Omega, dOmega/dt) of the run-up profile: W0 until T0, linear to W1 at T1, then W1."""
    W0, W1, T0, T1, th0 = fp[F_W0], fp[F_W1], fp[F_T0], fp[F_T1], fp[F_TH0]
    if t <= T0 or T1 <= T0:
        if T1 <= T0 and t > T0:
            return th0 + W0 * T0 + W1 * (t - T0), W1, 0.0
        return th0 + W0 * t, W0, 0.0
    a = (W1 - W0) / (T1 - T0)
    if t < T1:
        tau = t - T0
        return th0 + W0 * t + 0.5 * a * tau * tau, W0 + a * tau, a
    tau = T1 - T0
    return th0 + W0 * T1 + 0.5 * a * tau * tau + W1 * (t - T1), W1, 0.0


@nb.njit(cache=True, _nrt=False)
def _add_unbalance(p, t, scale, out):
    th, W, Wd = speed_at(p.fp, t)
    c, s = math.cos(th), math.sin(th)
    w2 = W * W
    Ur, Ui = p.Ur, p.Ui
    for m in range(p.u_idx.shape[0]):    # elsewhere U is zero: out[k] += 0 changes nothing
        k = p.u_idx[m]
        # W^2 Re(U e^{i th}) + W' Re(-i U e^{i th})
        out[k] += scale * (w2 * (Ur[k] * c - Ui[k] * s) + Wd * (Ur[k] * s + Ui[k] * c))


# --------------------------------------------------------------------------- AMB force law
@nb.njit(cache=True, _nrt=False)
def amb_force(k, s0, i0, x, i):
    """Differential-pair force (plant/magnetic_bearing.force) with each coil only pulling
    (coil currents i0 +- i clamped at 0); equals magnetic_bearing.force for |i| <= i0."""
    iu = max(i0 + i, 0.0)
    il = max(i0 - i, 0.0)
    return 0.25 * k * (iu * iu / ((s0 - x) * (s0 - x)) - il * il / ((s0 + x) * (s0 + x)))


@nb.njit(cache=True, _nrt=False)
def _add_nonlinear(p, qw, cur, scale, out):
    """out += scale * Ca^T r(Ca qw, i); returns the largest |x| / gap over the axes."""
    worst = 0.0
    for a in range(p.ca_ptr.shape[0] - 1):
        xa = 0.0
        for m in range(p.ca_ptr[a], p.ca_ptr[a + 1]):
            xa += p.ca_val[m] * qw[p.ca_idx[m]]
        xs = p.xop[a] + xa
        g = abs(xs) / p.gap[a]
        if g > worst:
            worst = g
        if g >= 1.0:
            continue
        r = (amb_force(p.kc[a], p.gap[a], p.bias[a], xs, cur[a]) - p.load[a]
             - p.kx[a] * xa - p.ki[a] * (cur[a] - p.iop[a]))
        for m in range(p.ca_ptr[a], p.ca_ptr[a + 1]):
            out[p.ca_idx[m]] += scale * p.ca_val[m] * r
    return worst


@nb.njit(cache=True, _nrt=False)
def _add_currents(p, cur, scale, out):
    """out += scale * Ca^T (k_i (i - i_op) [+ f0]) (f0 only where a scene has one: a lost AMB's weight)"""
    f0 = p.ip[I_F0] != 0
    for a in range(p.ca_ptr.shape[0] - 1):
        f = scale * p.ki[a] * (cur[a] - p.iop[a])
        if f0:
            f += scale * p.f0[a]
        for m in range(p.ca_ptr[a], p.ca_ptr[a + 1]):
            out[p.ca_idx[m]] += p.ca_val[m] * f


# --------------------------------------------------------------------------- one plant step
@nb.njit(cache=True, _nrt=False)
def _galpha_rates(p, s, cur, t, wk):
    """Consistent rates q' = v, v' = M^-1 F(t, q, v, i) for generalised-alpha."""
    n, bw = p.ip[I_N], p.ip[I_BW]
    q = s[0:n]
    v = s[n:2 * n]
    f = wk[5, :n]
    th, W, Wd = speed_at(p.fp, t)
    band_mv(p.Kb, bw, q, f, -1.0, False)
    if p.ip[I_RUNUP] == 0:
        band_mv(p.Db, bw, v, f, -1.0, True)
    else:
        band_mv(p.Cb, bw, v, f, -1.0, True)
        band_mv(p.Gb, bw, v, f, -W, True)
    _add_unbalance(p, t, 1.0, f)
    _add_currents(p, cur, 1.0, f)
    if p.ip[I_NL] != 0:
        _add_nonlinear(p, q, cur, 1.0, f)
    if p.ip[I_AUX] > 0:
        _add_contact_explicit(p, s, q, v, W, f)
    band_solve(p.LU1, bw, f)
    for k in range(n):
        s[2 * n + k] = v[k]
        s[3 * n + k] = f[k]



@nb.njit(cache=True, _nrt=False)
def _refactor(p, W, ws):
    n, bw = p.ip[I_N], p.ip[I_BW]
    dW = W - p.fp[F_WNOM]
    for i in range(n):
        for k in range(2 * bw + 1):
            p.LU[i, k] = p.Sb[i, k] + dW * p.GbR[i, k]
    band_lu(p.LU, bw)
    ws[W_OMEGA_F] = W
    ws[W_NREFAC] += 1.0


# One function on purpose: plant_step is the hot kernel of every run (the fused loop, the plant
# process, the lockstep reference), called once per plant step at up to tens of kHz.  Split into
# @njit helpers, the array views and scalars that flow between its stages (the right-hand side,
# the chord Newton, the history update, the health checks) would cross call boundaries that
# numba/LLVM may or may not inline, and the results must stay bit-identical to the recordings
# and the lockstep runs; the stages are marked by "# ---" comments instead.
@nb.njit(cache=True, _nrt=False)
def plant_step(p, s, cur, wk, ws, restart):
    """Advance the state vector ``s`` by one plant step h in place, currents ``cur`` held.

    ``s = [q, v, h1, h2, k, aux]`` (h1, h2: previous q, v for bdf2; q', v' for generalised-alpha;
    ``k`` the step count, time t = k h; ``aux``: NC floats per auxiliary-bearing station, ``C_*``).
    ``wk`` is scratch (6 rows of n; with m auxiliary bearings 2m + 2 more: the Woodbury basis, the
    small system, the contact Jacobians; plan.new_workspace), ``ws`` the scalar workspace.
    Returns a status code (OK, NEWTON_FAIL, NONFINITE, TOUCHDOWN)."""
    ip, fp = p.ip, p.fp
    scheme, n, bw = ip[I_SCHEME], ip[I_N], ip[I_BW]
    h = fp[F_H]
    kst = s[4 * n]
    t = kst * h
    q = s[0:n]
    v = s[n:2 * n]
    h1 = s[2 * n:3 * n]
    h2 = s[3 * n:4 * n]
    status = OK
    # multistep / rate memory does not survive the jump of the held current at a controller
    # update: bdf2 restarts with one trapezoidal step, generalised-alpha re-initialises its rates
    first = scheme == BDF2 and (kst == 0.0 or restart)
    if scheme == GALPHA and restart and ip[I_DENSE] == 0:
        _galpha_rates(p, s, cur, t, wk)
    if ip[I_DENSE] != 0 and (not first or restart):
        # dense affine step (exact zoh, or a linear scheme pre-multiplied out)
        Phi, Gi, Gcs = p.Phi, p.Gi, p.Gcs
        ns = ip[I_NS]
        z = wk[0]
        th, W, Wd = speed_at(fp, t)
        c, sn = math.cos(th), math.sin(th)
        # Phi, Gi, Gcs are stored transposed: z = Phi s + Gi du + Gcs [c, s] as column updates
        for r in range(ns):
            z[r] = Gcs[0, r] * c + Gcs[1, r] * sn
        for a in range(Gi.shape[0]):
            du = cur[a] - p.iop[a]
            for r in range(ns):
                z[r] += Gi[a, r] * du
        for j in range(ns):
            sj = s[j]
            for r in range(ns):
                z[r] += Phi[j, r] * sj
        for r in range(ns):
            s[r] = z[r]
    else:
        bh, om = fp[F_BH], fp[F_OM]
        tstar = t + h
        if first:  # BDF2 (re)starts with one trapezoidal step
            bh = 0.5 * h
        if scheme == GALPHA:
            tstar = t + fp[F_AF] * h
        mvec, dvec, bvec, x, qw = wk[0, :n], wk[1, :n], wk[2, :n], wk[3, :n], wk[4, :n]
        # --- explicit right-hand side b = M m + D* d + K k + bh g* (+ h/2 g_n)
        if scheme == BDF1:
            for k in range(n):
                mvec[k] = q[k] / bh + v[k]
                dvec[k] = q[k]
        elif scheme == TRAP or first:
            for k in range(n):
                mvec[k] = 2.0 * q[k] / h + 2.0 * v[k]
                dvec[k] = q[k]  # D*(q + h/2 v) - h/2 D_n v  (run-up correction below)
        elif scheme == BDF2:
            for k in range(n):
                P1 = (4.0 * q[k] - h1[k]) / 3.0
                mvec[k] = P1 / bh + (4.0 * v[k] - h2[k]) / 3.0
                dvec[k] = P1
        else:  # GALPHA
            af, czd = fp[F_AF], fp[F_CZD]
            for k in range(n):
                P1 = q[k] + czd * h1[k]
                mvec[k] = P1 / (bh * om) + (1.0 - af) * v[k] / af + v[k] + czd * h2[k]
                dvec[k] = P1
        band_mv(p.Mb, bw, mvec, bvec, 1.0, False)
        th_s, W_s, Wd_s = speed_at(fp, tstar)
        if ip[I_RUNUP] == 0:
            band_mv(p.Db, bw, dvec, bvec, 1.0, True)
        else:
            band_mv(p.Cb, bw, dvec, bvec, 1.0, True)
            band_mv(p.Gb, bw, dvec, bvec, W_s, True)
        if scheme == TRAP or first:
            th_n, W_n, Wd_n = speed_at(fp, t)
            if W_n != W_s:
                for k in range(n):
                    mvec[k] = v[k]
                band_mv(p.Gb, bw, mvec, bvec, 0.5 * h * (W_s - W_n), True)
            band_mv(p.Kb, bw, q, bvec, -0.5 * h, True)
            _add_unbalance(p, t, 0.5 * h, bvec)
            _add_unbalance(p, tstar, 0.5 * h, bvec)
            _add_currents(p, cur, h, bvec)
            if ip[I_NL] != 0:  # the exact force law's remainder at t_n (its t+ half is in the residual)
                _add_nonlinear(p, q, cur, 0.5 * h, bvec)
            if ip[I_AUX] > 0:  # the contact force at t_n (committed with the last step)
                _add_contact_state(p, s, 0.5 * h, bvec)
        elif scheme == GALPHA:
            band_mv(p.Kb, bw, q, bvec, -bh * (1.0 - fp[F_AF]), True)
            _add_unbalance(p, tstar, bh, bvec)
            _add_currents(p, cur, bh, bvec)
        else:
            _add_unbalance(p, tstar, bh, bvec)
            _add_currents(p, cur, bh, bvec)
        LU = p.LU1 if first else p.LU
        nst = ip[I_AUX]
        if ip[I_NL] == 0 and ip[I_RUNUP] == 0 and nst == 0:
            for k in range(n):
                x[k] = bvec[k]
            band_solve(LU, bw, x)
        else:
            # chord Newton on R(q+) = S(W*) q+ - b - bh Ca^T r(Ca q_w, i), Jacobian S(W_f)
            if ip[I_RUNUP] != 0 and not first and abs(W_s - ws[W_OMEGA_F]) * bh * om > fp[F_REFAC]:
                _refactor(p, W_s, ws)
            if nst > 0:
                # predictor: the step without contact (and with the linear force law), which out of
                # contact and without a run-up or a nonlinear force law is the solution itself
                for k in range(n):
                    x[k] = bvec[k]
                band_solve(LU, bw, x)
            else:
                for k in range(n):
                    x[k] = q[k] + h * v[k]  # predictor
            cm = 1.0 / (bh * om)
            maxit = ip[I_MAXIT]
            vk = V_BDF1
            jc = wk[0]
            zdone = False
            jmask = -1  # the stations whose Jacobian is in jc (-1: none computed in this step)
            mask = 0
            if nst > 0:  # contact: the exact Jacobian (Woodbury), a few more iterations at an impact
                maxit += 20
                if scheme == GALPHA:
                    vk = V_GALPHA
                elif scheme == TRAP or first:
                    vk = V_TRAP
                elif scheme == BDF2:
                    vk = V_BDF2
                jc = wk[6 + 2 * nst + 1]
            conv = False
            res = 0.0
            it = 0
            r = wk[5, :n]
            for it in range(1, maxit + 1):
                if nst > 0 and it == 1 and ip[I_NL] == 0 and ip[I_RUNUP] == 0:
                    # the predictor is the linear step's solution: done if it stays out of contact
                    for k in range(n):
                        qw[k] = (1.0 - fp[F_AF]) * q[k] + fp[F_AF] * x[k] if scheme == GALPHA else x[k]
                    if _stations_clear(p, qw):
                        conv = True
                        it = 0
                        break
                for k in range(n):
                    qw[k] = x[k] * cm
                band_mv(p.Mb, bw, qw, r, 1.0, False)
                if ip[I_RUNUP] == 0:
                    band_mv(p.Db, bw, x, r, 1.0, True)
                else:
                    band_mv(p.Cb, bw, x, r, 1.0, True)
                    band_mv(p.Gb, bw, x, r, W_s, True)
                band_mv(p.Kb, bw, x, r, bh * om, True)
                if scheme == GALPHA:
                    af = fp[F_AF]
                    for k in range(n):
                        qw[k] = (1.0 - af) * q[k] + af * x[k]
                else:
                    for k in range(n):
                        qw[k] = x[k]
                for k in range(n):
                    r[k] = bvec[k] - r[k]
                if ip[I_NL] != 0:
                    worst = _add_nonlinear(p, qw, cur, bh, r)
                    if worst >= 1.0:
                        status = TOUCHDOWN
                        break
                active = False
                if nst > 0:
                    # the contact Jacobian: fresh in the first two iterations and from the sixth on
                    # (chord iterations in between), and whenever the stations in contact change
                    jac = it <= 2 or it >= 6
                    mask = _add_contact(p, s, qw, x, q, v, h1, vk, h, bh, W_s, bh, r, jc, jac)
                    if jac:
                        jmask = mask
                    elif mask != jmask:
                        _add_contact(p, s, qw, x, q, v, h1, vk, h, bh, W_s, 0.0, r, jc, True)
                        jmask = mask
                    active = mask != 0
                res = 0.0
                for k in range(n):
                    if abs(r[k]) > res:
                        res = abs(r[k])
                band_solve(LU, bw, r)
                if active:
                    if not zdone:
                        _contact_basis(p, LU, bw, wk)
                        zdone = True
                    _woodbury(p, wk, r, jc)
                dmax = 0.0
                xmax = 0.0
                for k in range(n):
                    x[k] += r[k]
                    if abs(r[k]) > dmax:
                        dmax = abs(r[k])
                    if abs(x[k]) > xmax:
                        xmax = abs(x[k])
                if dmax <= fp[F_TOL] * xmax or dmax == 0.0:
                    conv = True
                    break
            if it > ws[W_MAXIT]:
                ws[W_MAXIT] = it
            if not conv and status == OK:
                status = NEWTON_FAIL
                ws[W_NFAIL] += 1.0
                if ws[W_STATUS] == OK:
                    ws[W_FAIL_T] = t + h
                    ws[W_FAIL_IT] = it
                    ws[W_FAIL_RES] = res
        # --- velocities and history
        if scheme == GALPHA:
            af, g = fp[F_AF], fp[F_G]
            czd = fp[F_CZD]
            for k in range(n):
                P1 = q[k] + czd * h1[k]
                vnew = (x[k] - P1 - bh * (1.0 - af) * v[k]) / (bh * om)
                qd = (x[k] - q[k] - h * (1.0 - g) * h1[k]) / (h * g)
                vd = (vnew - v[k] - h * (1.0 - g) * h2[k]) / (h * g)
                h1[k] = qd
                h2[k] = vd
                q[k] = x[k]
                v[k] = vnew
        else:
            for k in range(n):
                if scheme == BDF1:
                    P1 = q[k]
                elif scheme == TRAP or first:
                    P1 = q[k] + 0.5 * h * v[k]
                elif scheme == BDF2:
                    P1 = (4.0 * q[k] - h1[k]) / 3.0
                else:
                    P1 = q[k] + 0.5 * h * v[k]
                vnew = (x[k] - P1) / bh
                if scheme == BDF2:
                    h1[k] = q[k]
                    h2[k] = v[k]
                q[k] = x[k]
                v[k] = vnew
    s[4 * n] = kst + 1.0
    if ip[I_AUX] > 0:
        _contact_commit(p, s, (kst + 1.0) * h, h, speed_at(fp, (kst + 1.0) * h)[1])
    # --- health checks: finite state, rotor inside the gap
    bad = False
    for k in range(2 * n):
        if not math.isfinite(s[k]):
            bad = True
            break
    if bad:
        status = NONFINITE
    elif status != TOUCHDOWN:
        for a in range(p.ca_ptr.shape[0] - 1):
            xa = p.xop[a]
            for m in range(p.ca_ptr[a], p.ca_ptr[a + 1]):
                xa += p.ca_val[m] * q[p.ca_idx[m]]
            if abs(xa) >= p.gap[a]:
                status = TOUCHDOWN
                ws[W_FAIL_AX] = a
                break
    if status != OK and status != NEWTON_FAIL and ws[W_STATUS] == OK:
        ws[W_STATUS] = status
        ws[W_FAIL_T] = (kst + 1.0) * h
    elif status == NEWTON_FAIL and ws[W_STATUS] == OK:
        ws[W_STATUS] = status
    return status


@nb.njit(cache=True, _nrt=False)
def sense(p, s, y):
    """Sensor displacements y = Cs q (Cs's non-zeros, in column order: the sum of the dense row
    without its zero terms)."""
    for a in range(p.cs_ptr.shape[0] - 1):
        acc = 0.0
        for m in range(p.cs_ptr[a], p.cs_ptr[a + 1]):
            acc += p.cs_val[m] * s[p.cs_idx[m]]
        y[a] = acc


@nb.njit(cache=True, _nrt=False)
def plant_advance(p, s, cur, nsub, wk, ws, y):
    """nsub plant steps with the currents held, then the sensor readings into y; returns status."""
    st = OK
    for j in range(nsub):
        r = plant_step(p, s, cur, wk, ws, j == 0)
        if r != OK and r != NEWTON_FAIL:
            st = r
            break
        if r == NEWTON_FAIL:
            st = r
    sense(p, s, y)
    return st
