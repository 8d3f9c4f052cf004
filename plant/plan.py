"""Building the integrator's plan: the immutable arrays (``PlantArrays``) the plant kernels of
:mod:`ambhil.plant.integrator` read, from a compiled model, a scheme, a step and the speed, plus the
initial state and the workspaces.

A plan is shared freely (between runners, states, a model's default plan): the kernels write
none of its arrays but the factorisation ``LU``, and that only on a speed run-up, which
refactorises it as the spin speed drifts.  Whoever integrates a run-up therefore does so with a
factorisation of its own (:func:`own_factorisation`: the runner's, or the state's in the pure
``step``), and the plan as built stays as built."""
from __future__ import annotations

import math

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from . import contact_step
from .banded import band_lu, band_mv, band_solve, bandwidth, diag_major, to_rowband
from .auxiliary_bearing import A_LEN
from .integrator import (BDF1, BDF2, C_D, C_TE, C_X, C_Y, F_H, F_TH0, F_W0, F_WNOM, GALPHA, I_AUX, I_BW, I_DENSE, I_F0, I_N, I_NA,
                         I_RUNUP, I_SCHEME, NC, SCHEMES, TRAP, W_LEN, W_OMEGA_F, ZOH, PlantArrays, _add_currents,
                         _add_unbalance, plant_step)
from .params import ParameterError


def galpha_params(rho: float) -> tuple[float, float, float]:
    if not 0.0 <= rho <= 1.0:
        raise ValueError(f"rho_inf must be in [0, 1], got {rho:g}")
    am = 0.5 * (3.0 - rho) / (1.0 + rho)
    af = 1.0 / (1.0 + rho)
    return am, af, 0.5 + am - af


def build_plan(model, scheme: str, h: float, *, speed=0.0, run_up=None, nonlinear=False,
               rho_inf: float = 0.8, newton_iterations: int = 10, newton_tol: float = 1e-10,
               refactor_tol: float = 2e-3, dense_max: int | None = 160,
               ratio: int = 1, contact: bool = True) -> PlantArrays:
    """Precompute everything a step needs: banded matrices and factorisation (or the zoh
    propagators).  ``run_up = (W0, W1, T0, T1)``: speed W0 until T0, linear to W1 at T1.
    ``contact=False``: without the model's auxiliary bearings and constant forces (the levitated
    rotor about its operating point, for the loop analyses).

    The plan is never modified afterwards: the kernels write its factorisation ``LU`` only on a
    run-up, and the plant's runner and state each integrate with one of their own
    (:func:`own_factorisation`)."""
    if scheme not in SCHEMES:
        raise ValueError(f"unknown integrator {scheme!r} (choose from {', '.join(SCHEMES)})")
    if not (h > 0 and math.isfinite(h)):
        raise ValueError(f"plant step h must be > 0, got {h!r}")
    code = SCHEMES.index(scheme)
    W0, W1, T0, T1 = (float(speed), float(speed), 0.0, 0.0) if run_up is None else map(float, run_up)
    runup = W0 != W1
    if runup and not T1 > T0:
        raise ValueError(f"run-up needs end time > start time, got {T0:g}..{T1:g} s")
    if code == ZOH and (nonlinear or runup):
        raise ValueError("the zoh (exact) integrator needs a linear time-invariant scene: "
                         "no nonlinear force law, no speed run-up")
    n, na = model.n, model.n_axes
    aux_p, aux_ax, names = auxiliary_stations(model)
    f0 = np.ascontiguousarray(model.constant_forces, dtype=np.float64)
    if not contact:  # the levitated rotor's linear plant (the loop analyses): no contact, no lost weight
        aux_p, aux_ax, names = aux_p[:0], aux_ax[:0], ()
        f0 = np.zeros_like(f0)
    if len(names):
        try:
            contact_step.check(model, h)
        except ValueError as e:
            raise ParameterError(f"{getattr(model.spec, 'path', 'scene')}: {e}") from None
    if code == ZOH and (len(names) or np.any(f0)):
        raise ParameterError(f"{getattr(model.spec, 'path', 'scene')}: [simulation] integrator 'zoh' (exact for a "
                             f"linear time-invariant plant) cannot carry "
                             + ("auxiliary-bearing contact (AMB " + ", ".join(names) + ")" if len(names)
                                else "the weight of a lost AMB (a constant force)")
                             + "; choose bdf1, bdf2, trapezoidal or generalized-alpha")
    Mx, Cx, Gx, Kx = model.M, model.C, model.G, model.K_eff
    Ca, Cs = _dense_rows(model.Ca), _dense_rows(model.Cs)
    U = model.unbalance_forces(1.0)
    am, af, g = galpha_params(rho_inf) if code == GALPHA else (1.0, 1.0, 0.5)
    beta = {BDF1: 1.0, BDF2: 2.0 / 3.0, TRAP: 0.5, GALPHA: g / am, ZOH: 1.0}[code]
    om = af if code == GALPHA else 1.0
    bh = beta * h
    czd = h * (1.0 - g) - h * g * (1.0 - am) / am
    Wn = W0
    bw = bandwidth(Mx, Cx, Gx, Kx)
    rb = lambda A: to_rowband(A, bw)
    Mb, Cb, Gb, Kb = rb(Mx), rb(Cx), rb(Gx), rb(Kx)
    Sb = Mb / (bh * om) + Cb + Wn * Gb + bh * om * Kb
    LU = _checked_lu(model, Sb, bw, Mx / (bh * om) + Cx + Wn * Gx + bh * om * Kx, scheme, h, Wn)
    LU1 = _start_lu(code, Mb, Cb, Gb, Kb, Wn, h, bw)
    ns = 2 * n if code in (BDF1, TRAP, ZOH) else 4 * n
    Db = Cb + Wn * Gb
    GbR = Gb.copy()
    Mb, Cb, Gb, Kb, Db = (diag_major(A) for A in (Mb, Cb, Gb, Kb, Db))
    ca_ptr, ca_idx, ca_val = _csr(Ca, na)
    cs_ptr, cs_idx, cs_val = _csr(Cs, na)
    u_idx = np.flatnonzero((U.real != 0) | (U.imag != 0)).astype(np.int64)
    lti = not nonlinear and not runup and not len(names) and not np.any(f0)
    dense = code == ZOH or (lti and dense_max is not None and ns <= dense_max and (code in (BDF1, TRAP) or ratio == 1))
    ip = np.array([code, n, na, bw, int(bool(nonlinear)), int(runup), int(newton_iterations), 0, ns, len(names),
                   int(bool(np.any(f0)))], dtype=np.int64)
    fp = np.array([h, bh, om, am, af, g, czd, newton_tol, refactor_tol, W0, W1, T0, T1, Wn, 0.0], dtype=np.float64)
    f = lambda a: np.ascontiguousarray(np.asarray(a, dtype=np.float64))
    p = PlantArrays(ip=ip, fp=fp, Mb=Mb, Cb=Cb, Gb=Gb, Kb=Kb, Db=Db, Sb=Sb, LU=LU, LU1=LU1,
                    ki=f(model.ki), kx=f(model.kx), iop=f(model.i_op), xop=f(model.x_op),
                    kc=f(model.force_constant), gap=f(model.gap), bias=f(model.bias),
                    Ur=f(U.real), Ui=f(U.imag), Phi=np.zeros((0, 0)), Gi=np.zeros((0, 0)), Gcs=np.zeros((2, 0)),
                    GbR=GbR, ca_ptr=ca_ptr, ca_idx=ca_idx, ca_val=ca_val,
                    cs_ptr=cs_ptr, cs_idx=cs_idx, cs_val=cs_val, u_idx=u_idx, f0=f0,
                    load=np.ascontiguousarray(model.loads, dtype=np.float64), aux_p=aux_p, aux_ax=aux_ax)
    if code == ZOH:
        Phi, Gi, Gcs = _zoh_propagators(model, h, W0, Ca, U)
    elif dense:
        Phi, Gi, Gcs = _dense_from_kernel(p, ns)
    if dense:
        ip2 = ip.copy(); ip2[I_DENSE] = 1
        p = p._replace(ip=ip2, Phi=f(Phi.T), Gi=f(Gi.T), Gcs=f(Gcs.T))
    return p


def auxiliary_stations(model):
    """The auxiliary bearings of a model's radial AMBs, in [[amb]] order: (parameters (m, A_LEN),
    the x and y axis of each (m, 2), the AMB names)."""
    rows, axes, names = [], [], []
    for a in model.spec.ambs:
        aux = getattr(a, "auxiliary", None)
        if aux is None:
            continue
        rows.append(aux.array())
        axes.append((model.axes.index((a.name, "x")), model.axes.index((a.name, "y"))))
        names.append(a.name)
    p = np.ascontiguousarray(np.array(rows, dtype=np.float64).reshape(len(rows), A_LEN))
    return p, np.ascontiguousarray(np.array(axes, dtype=np.int64).reshape(len(axes), 2)), tuple(names)


def _dense_rows(A) -> np.ndarray:
    """An output or actuator matrix (sparse on the full rung) as a C-contiguous dense array."""
    return np.ascontiguousarray(A.toarray() if sp.issparse(A) else np.asarray(A, float))


def _csr(A: np.ndarray, rows: int):
    """(row pointers, column indices, values) of the non-zeros of a dense matrix, row-major
    (each row's columns ascending)."""
    nzr, nzc = np.nonzero(A)
    return np.searchsorted(nzr, np.arange(rows + 1)).astype(np.int64), nzc.astype(np.int64), A[nzr, nzc].copy()


def _checked_lu(model, Sb: np.ndarray, bw: int, S, scheme: str, h: float, W: float) -> np.ndarray:
    """The unpivoted banded LU of the step matrix ``S`` (row-band ``Sb``), checked against a
    pivoted solve of ``S`` itself: refused (ParameterError) when too ill-conditioned."""
    LU = Sb.copy()
    pmin = band_lu(LU, bw)
    S = S.toarray() if sp.issparse(S) else np.asarray(S)
    rhs = np.random.default_rng(1).standard_normal(S.shape[0])
    x = rhs.copy(); band_solve(LU, bw, x)
    xr = sla.solve(S, rhs)
    if not (pmin > 0 and np.linalg.norm(x - xr) <= 1e-6 * np.linalg.norm(xr)):
        where = getattr(getattr(model, "spec", None), "path", None)
        raise ParameterError((f"{where}: " if where else "")
                             + f"step matrix of {scheme} at h={h:g} s and speed {W:g} rad/s is too "
                               f"ill-conditioned for an unpivoted banded LU (a unit slip in [simulation] "
                               f"speed or step?)")
    return LU


def _start_lu(code: int, Mb, Cb, Gb, Kb, W: float, h: float, bw: int) -> np.ndarray:
    """``LU1``: bdf2's trapezoidal (re)start step matrix, factorised; generalised-alpha's M,
    factorised (its consistent rates); an empty array for the other schemes."""
    if code == BDF2:
        LU1 = Mb / (0.5 * h) + Cb + W * Gb + 0.5 * h * Kb
        band_lu(LU1, bw)
    elif code == GALPHA:
        LU1 = Mb.copy()
        band_lu(LU1, bw)
    else:
        LU1 = np.zeros((0, 0))
    return LU1


def levitated(p: PlantArrays) -> PlantArrays:
    """The plan without its auxiliary bearings and constant forces: the levitated rotor's linear
    plant about its operating point, what the loop analyses (eigenvalues, the period map) study;
    its state vector is ``[q, v, h1, h2, k]`` (no contact part)."""
    if not (p.ip[I_AUX] or p.ip[I_F0]):
        return p
    ip = p.ip.copy()
    ip[I_AUX] = 0
    ip[I_F0] = 0
    return p._replace(ip=ip)


def refactorises(p: PlantArrays) -> bool:
    """Whether the kernels rewrite the plan's factorisation ``LU`` as they integrate: on a speed
    run-up they refactorise it in place whenever the spin speed has drifted from the speed of the
    last factorisation (the scalar workspace's ``W_OMEGA_F``)."""
    return bool(p.ip[I_RUNUP])


def own_factorisation(p: PlantArrays) -> PlantArrays:
    """The plan with a copy of its factorisation ``LU`` (at the plan's nominal speed), the one
    array of a plan the kernels write (:func:`refactorises`): the workspace of a run-up, owned by
    whoever integrates with it (a ``PlantRunner``, a ``PlantState``).  Every other array stays
    shared with ``p``, which is then never modified."""
    return p._replace(LU=p.LU.copy())


def _dense_from_kernel(p: PlantArrays, ns: int):
    """The one-step affine map of a linear time-invariant scheme, obtained by running the banded
    kernel on unit vectors (state, current deviations, cos/sin of the unbalance phase at t_n)."""
    n, na = int(p.ip[I_N]), int(p.ip[I_NA])
    h, W = p.fp[F_H], p.fp[F_W0]
    wk = np.zeros((6, 4 * n)); ws = np.zeros(W_LEN)
    p0 = p._replace(Ur=np.zeros(n), Ui=np.zeros(n))
    Phi = np.zeros((ns, ns)); Gi = np.zeros((ns, na)); Gcs = np.zeros((ns, 2))

    def run(pp, s, cur):
        s[4 * n] = 1.0  # t_n = h
        plant_step(pp, s, cur, wk, ws, True)
        return s[:ns]

    for j in range(ns):
        s = np.zeros(4 * n + 1); s[j] = 1.0
        Phi[:, j] = run(p0, s, p.iop.copy())
    for a in range(na):
        cur = p.iop.copy(); cur[a] += 1.0
        Gi[:, a] = run(p0, np.zeros(4 * n + 1), cur)
    for k, th in enumerate((0.0, 0.5 * np.pi)):
        fp = p.fp.copy(); fp[F_TH0] = th - W * h
        Gcs[:, k] = run(p._replace(fp=fp), np.zeros(4 * n + 1), p.iop.copy())
    return Phi, Gi, Gcs


def _zoh_propagators(model, h, W, Ca, U):
    """Exact discretisation of [z; i; c; s]' = A_aug [z; i; c; s] over h (scipy.linalg.expm)."""
    M, D, K = model.dense[0], np.asarray(model.D(W).toarray() if model.sparse else model.D(W)), model.dense[3]
    n, na = model.n, model.n_axes
    Minv = sla.cho_solve(sla.cho_factor(M), np.eye(n))
    m = 2 * n + na + 2
    A = np.zeros((m, m))
    A[:n, n:2 * n] = np.eye(n)
    A[n:2 * n, :n] = -Minv @ K
    A[n:2 * n, n:2 * n] = -Minv @ D
    A[n:2 * n, 2 * n:2 * n + na] = Minv @ (Ca.T * model.ki)
    # unbalance W^2 (Ur cos th - Ui sin th); th' = W: [c, s]' = [[0, -W], [W, 0]] [c, s]
    A[n:2 * n, 2 * n + na] = Minv @ (W * W * U.real)
    A[n:2 * n, 2 * n + na + 1] = Minv @ (-W * W * U.imag)
    A[2 * n + na, 2 * n + na + 1] = -W
    A[2 * n + na + 1, 2 * n + na] = W
    E = sla.expm(A * h)
    return E[:2 * n, :2 * n], E[:2 * n, 2 * n:2 * n + na], E[:2 * n, 2 * n + na:]


def state_size(n: int, stations: int = 0) -> int:
    """Length of the state vector: q, v, h1, h2 (n each), the step count, NC per auxiliary bearing."""
    return 4 * n + 1 + NC * stations


def initial_state(p: PlantArrays, q0=None, v0=None, cur=None) -> np.ndarray:
    """State vector at t = 0; generalised-alpha gets consistent rates (q' = v, v' = M^-1 F)."""
    n = int(p.ip[I_N])
    m = int(p.ip[I_AUX])
    s = np.zeros(state_size(n, m))
    for j in range(m):
        s[4 * n + 1 + j * NC + C_TE] = -1.0  # no contact event has ended yet
    if q0 is not None:
        s[:n] = q0
    if v0 is not None:
        s[n:2 * n] = v0
    for j in range(m):  # where the shaft starts in each auxiliary bearing
        b = 4 * n + 1 + j * NC
        xy = [p.xop[a] + sum(p.ca_val[k] * s[p.ca_idx[k]] for k in range(p.ca_ptr[a], p.ca_ptr[a + 1]))
              for a in p.aux_ax[j]]
        s[b + C_X], s[b + C_Y] = xy
        s[b + C_D] = math.hypot(*xy) - p.aux_p[j, 0]
    if p.ip[I_SCHEME] == GALPHA:
        cur = p.iop.copy() if cur is None else np.asarray(cur, float)
        bw = int(p.ip[I_BW])
        f = np.zeros(n)
        band_mv(p.Cb, bw, s[n:2 * n].copy(), f, -1.0, True)
        band_mv(p.Gb, bw, s[n:2 * n].copy(), f, -p.fp[F_W0], True)
        band_mv(p.Kb, bw, s[:n].copy(), f, -1.0, True)
        _add_unbalance(p, 0.0, 1.0, f)
        _add_currents(p, cur, 1.0, f)
        Md = np.zeros((n, n))
        for i in range(n):
            for k in range(2 * bw + 1):
                j = i - bw + k
                if 0 <= j < n:
                    Md[i, j] = p.Mb[k, i]
        s[2 * n:3 * n] = s[n:2 * n]
        s[3 * n:4 * n] = sla.solve(Md, f, assume_a="sym")
    return s


def new_workspace(p: PlantArrays) -> tuple[np.ndarray, np.ndarray]:
    n = int(p.ip[I_N])
    m = int(p.ip[I_AUX])
    ws = np.zeros(W_LEN)
    ws[W_OMEGA_F] = p.fp[F_WNOM]
    if m == 0:
        return np.zeros((6, max(4 * n, 1))), ws
    # rows 6..6+2m: the Woodbury basis; 6+2m: the small system's scratch; 7+2m: the contact Jacobians
    width = max(4 * n, 4 * m * m + 4 * m, 4 * m, 1)
    return np.zeros((6 + 2 * m + 2, width)), ws
