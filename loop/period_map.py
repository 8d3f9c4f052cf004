"""The simulated sampled loop's one-period map: the linear map over one controller period of the
loop the kernels actually integrate (:func:`loop_matrix`, built by running them on unit vectors),
its steady unbalance response (:func:`unbalance_response`), and its eigenvalues as
:class:`LoopModes` (:func:`sampled_loop`; with ``zoh`` the exact, physical sampled loop:
:func:`physical_loop`).  What these say about the integrator (numerical damping, the numerics
warning) is :mod:`ambhil.loop.numerics`.

The kernels run on plans of their own here (the loop's linear time-invariant plan with the
unbalance or the operating currents removed); the model and the plan given are only read.  The
physical loop of a model is computed once per (sample rate, speed, discretisation) and kept in
this module's cache, keyed on the model's identity (a compiled model is immutable, and hashed
by identity) and held no longer than the model: a ``weakref.WeakKeyDictionary`` rather than a
``functools.lru_cache``, which would keep every model it has seen alive (a full-rung model is
megabytes).
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, field

import numpy as np

from ambhil.controller import discrete as dc
from ambhil.controller.law_lti import runner_matrices
from ambhil.plant import integrator as ig
from ambhil.plant import plan as pl
from ambhil.plant.step import make_plan
from .system import System, controller_runner


def loop_matrix(model: System, plan: ig.PlantArrays, ctrl: dc.ControllerRunner, ratio: int) -> tuple[np.ndarray, int]:
    """Linear one-period map of the simulated discrete loop (plant state, controller state),
    built by running the kernels on unit vectors; unbalance removed, scene must be LTI.
    Returns (matrix, periods spanned); the map always spans one controller period (the second
    value is kept for callers that raise the eigenvalues to 1/span).

    The kernels are run with the fault checks neutralised (gaps set to infinity): a unit vector
    puts the rotor metres outside its gap, and ``plant_advance`` stops a period at the first
    touchdown, so with ``ratio > 1`` the columns would otherwise hold a truncated period (a map
    with spurious eigenvalues far outside the unit circle).  The pure delay's ring buffer is read
    back in age order (slot k = the current applied k periods from now), so the map is the true
    one-period map and its eigenvalues carry the right frequencies."""
    if plan.ip[ig.I_NL] or plan.ip[ig.I_RUNUP]:
        raise ValueError("the discrete loop matrix needs a linear time-invariant scene")
    p = pl.own_factorisation(pl.levitated(plan)._replace(Ur=np.zeros_like(plan.Ur), Ui=np.zeros_like(plan.Ui),
                                           Gcs=np.zeros_like(plan.Gcs), iop=np.zeros_like(plan.iop),
                                           gap=np.full_like(plan.gap, np.inf)))
    n = model.n
    scheme = int(p.ip[ig.I_SCHEME])
    ns = 4 * n if scheme in (ig.BDF2, ig.GALPHA) else 2 * n
    if not isinstance(ctrl, dc.ControllerRunner):
        return _law_loop_matrix(model, p, ctrl, ratio, ns), 1
    nd = int(ctrl.params[dc.P_DELAY])
    na = model.n_axes
    nx = len(ctrl.state) - 1
    N = ns + nx
    L = np.zeros((N, N))
    wk, ws = pl.new_workspace(p)
    y = np.zeros(na); cur = np.zeros(na)
    cp = ctrl.params.copy()
    cp[dc.P_ILIM] = cp[dc.P_ULIM] = np.inf  # the linear loop: no saturation
    for j in range(N):
        s = np.zeros(4 * n + 1); x = np.zeros(nx + 1)  # ring index x[-1] = 0: slot k in age order
        s[4 * n] = 1.0
        if j < ns:
            s[j] = 1.0
        else:
            x[j - ns] = 1.0
        ig.sense(p, s, y)
        dc.controller_step(cp, x, y, cur)
        ig.plant_advance(p, s, cur, ratio, wk, ws, y)
        L[:ns, j] = s[:ns]
        xc = x[:nx]
        if nd:
            k = int(x[nx])  # the ring index has moved on by one slot
            xc = xc.copy()
            for a in range(na):
                b = na * dc.NX + a * nd
                xc[b:b + nd] = np.roll(x[b:b + nd], -k)
        L[ns:, j] = xc
    return L, 1


def _law_loop_matrix(model: System, p: ig.PlantArrays, ctrl, ratio: int, ns: int) -> np.ndarray:
    """:func:`loop_matrix` of a law runner with an LTI law: the plant kernels on unit vectors, the
    controller as its linear map read off the runner (:func:`ambhil.controller.law_lti.runner_matrices`);
    state ``[plant, controller, delay ring in age order]`` (slot 0 reaches the coils next)."""
    M, nc, nd = runner_matrices(ctrl)
    na, n = model.n_axes, model.n
    Ac, Bc, Cc, Dc = M[:nc, :nc], M[:nc, nc:], M[nc:, :nc], M[nc:, nc:]
    N = ns + nc + na * nd
    L = np.zeros((N, N))
    wk, ws = pl.new_workspace(p)
    y = np.zeros(na)
    for j in range(N):
        s = np.zeros(4 * n + 1)
        s[4 * n] = 1.0
        z = np.zeros(nc + na * nd)
        if j < ns:
            s[j] = 1.0
        else:
            z[j - ns] = 1.0
        ig.sense(p, s, y)
        xc, ring = z[:nc], z[nc:].reshape(nd, na) if nd else None
        u = Cc @ xc + Dc @ y
        L[ns:ns + nc, j] = Ac @ xc + Bc @ y
        if nd:
            cur = ring[0].copy()
            L[ns + nc:, j] = np.concatenate([ring[1:].ravel(), u])
        else:
            cur = u
        ig.plant_advance(p, s, np.ascontiguousarray(cur), ratio, wk, ws, y)
        L[:ns, j] = s[:ns]
    return L


def unbalance_response(model: System, plan: ig.PlantArrays, ctrl: dc.ControllerRunner, ratio: int,
                       L: np.ndarray) -> np.ndarray | None:
    """Complex amplitudes ``Y`` of the sensor displacements in the steady unbalance response of the
    simulated loop at the plan's constant speed W, at the controller's sampling instants:
    ``y_k = Re(Y e^{i W k T})`` (None without unbalance or spin).  The unbalance's effect over one
    period is read from the kernels as in :func:`loop_matrix`, from zero state with the unbalance
    phase 0, pi/2 and pi at the period start (b = b_c cos phi + b_s sin phi, a constant part
    removed), and the steady state of ``z+ = L z + Re((b_c - i b_s) e^{i phi})`` solved directly."""
    W = float(plan.fp[ig.F_W0])
    if W == 0.0 or not (np.any(plan.Ur) or np.any(plan.Ui)):
        return None
    p = pl.own_factorisation(pl.levitated(plan)._replace(iop=np.zeros_like(plan.iop),
                                                         gap=np.full_like(plan.gap, np.inf)))
    n, na = model.n, model.n_axes
    N = L.shape[0]
    scheme = int(p.ip[ig.I_SCHEME])
    ns = 4 * n if scheme in (ig.BDF2, ig.GALPHA) else 2 * n
    fused = isinstance(ctrl, dc.ControllerRunner)  # else an LTI law: zero state, y = 0 -> no current
    nx = len(ctrl.state) - 1 if fused else 0
    cp = ctrl.params.copy() if fused else None
    if fused:
        cp[dc.P_ILIM] = cp[dc.P_ULIM] = np.inf
    h = float(p.fp[ig.F_H])
    y = np.zeros(na); cur = np.zeros(na)

    def period(phi: float) -> np.ndarray:
        fp = p.fp.copy()
        fp[ig.F_TH0] = phi - W * h  # the period starts at t = h (step count 1, as in loop_matrix)
        pp = p._replace(fp=fp)
        wk, ws = pl.new_workspace(pp)
        s = np.zeros(4 * n + 1); s[4 * n] = 1.0
        x = np.zeros(nx + 1)
        ig.sense(pp, s, y)
        if fused:
            dc.controller_step(cp, x, y, cur)
        ig.plant_advance(pp, s, cur, ratio, wk, ws, y)
        z = np.zeros(N)
        z[:ns] = s[:ns]  # the controller's state stays 0: it saw y = 0
        return z
    b0, b1, b2 = period(0.0), period(0.5 * np.pi), period(np.pi)
    bc, bs = 0.5 * (b0 - b2), b1 - 0.5 * (b0 + b2)
    Z = np.linalg.solve(np.exp(1j * W * ctrl.period) * np.eye(N) - L, bc - 1j * bs)
    out = np.zeros(na, dtype=complex)
    for part, f in ((Z.real, 1.0), (Z.imag, 1j)):
        s = np.zeros(4 * n + 1); s[:n] = part[:n]
        ig.sense(p, s, y)
        out += f * y
    return out


#: a loop is reported unstable when its spectral radius exceeds 1 by more than this (per period):
#: eigenvalues of the loop map are accurate to ~1e-12 here, and 1e-9 per period at 10 kHz is an
#: e-folding time of over a day
STABILITY_TOL = 1e-9


@dataclass
class LoopModes:
    """Eigenvalues of the one-period map of a sampled loop (plant integrated by ``integrator`` at
    step ``h``, discrete controller at ``period``), as ``s = ln(mu) / period``.  ``f_plant``: the
    frequency (Hz) the plant part of each eigenvector moves at, ``Im(q^H M v / q^H M q)`` (equal
    to ``Im s`` for a mode below the Nyquist frequency, larger for a mode aliased into the band);
    ``V``: eigenvectors (plant state first), when asked for."""
    integrator: str
    h: float
    period: float
    mu: np.ndarray
    f_plant: np.ndarray | None = None
    V: np.ndarray | None = field(default=None, repr=False)
    unbalance: np.ndarray | None = field(default=None, repr=False)  # unbalance_response, when asked for

    @property
    def s(self) -> np.ndarray:
        mu = self.mu.astype(complex)
        out = np.full(mu.shape, -np.inf + 0j)
        nz = mu != 0
        out[nz] = np.log(mu[nz]) / self.period
        return out

    @property
    def spectral_radius(self) -> float:
        return float(np.max(np.abs(self.mu))) if len(self.mu) else 0.0

    @property
    def stable(self) -> bool:
        return self.spectral_radius <= 1.0 + STABILITY_TOL

    @property
    def dominant(self) -> int:
        """Index of the eigenvalue of largest modulus (upper half plane of a conjugate pair)."""
        r = np.abs(self.mu)
        cand = np.where(r >= r.max() * (1 - 1e-12))[0]
        return int(cand[np.argmax(self.mu[cand].imag)])

    @property
    def growth_rate(self) -> float:
        """ln(spectral radius) / period, 1/s (negative: the slowest decay)."""
        return float(np.log(self.spectral_radius) / self.period) if self.spectral_radius > 0 else -np.inf

    @property
    def frequency_hz(self) -> float:
        return float(abs(self.s[self.dominant].imag) / (2 * np.pi))

    def least_damped(self, fmin_hz: float = 0.0) -> int | None:
        """Index of the oscillatory mode (frequency > fmin_hz, upper half plane) of lowest damping
        ratio; modes aliased from above the Nyquist frequency (known from ``f_plant``) are skipped."""
        s = self.s
        ok = (s.imag > max(2 * np.pi * fmin_hz, 1e-6)) & np.isfinite(s.real)
        if self.f_plant is not None:
            ok &= self.f_plant <= 1.05 * 0.5 / self.period
        idx = np.where(ok)[0]
        if not len(idx):
            return None
        z = -s[idx].real / np.abs(s[idx])
        return int(idx[np.argmin(z)])

    def describe(self, k: int) -> str:
        sk = self.s[k]
        return f"{abs(sk.imag) / 2 / np.pi:.4g} Hz, {'grows' if sk.real > 0 else 'decays'} at {abs(sk.real):.3g} 1/s"


def sampled_loop(model: System, integrator: str = "zoh", h: float | None = None, *, speed: float | None = None,
                 sample_rate: float | None = None, method: str | None = None, rho_inf: float | None = None,
                 ctrl: dc.ControllerRunner | None = None, plan: ig.PlantArrays | None = None,
                 vectors: bool = False, response: bool = False) -> LoopModes:
    """Eigen-analysis of the sampled loop as simulated: plant ``integrator`` at step ``h`` (default:
    the controller period), the scene's discrete controller (or ``ctrl``), linear force law,
    constant ``speed`` (default: the scene's).  ``integrator="zoh"`` is the exact sampled-data
    loop (the physical one).  ``plan``: use this plan (e.g. a PlantRunner's) instead."""
    ctrl = ctrl or controller_runner(model, sample_rate=sample_rate, method=method)
    if plan is None:
        hh = h or ctrl.period
        ratio = max(1, int(round(ctrl.period / hh)))
        sim = getattr(model.scene, "simulation", None)
        if speed is None:
            speed = getattr(sim, "speed", None)
            speed = speed if speed is not None else (model.spec.speed.value or 0.0)
        plan = make_plan(model, integrator, hh, speed=speed, run_up=(speed, speed, 0.0, 1.0), nonlinear=False,
                         rho_inf=rho_inf, ratio=ratio, contact=False)
    hh = float(plan.fp[ig.F_H])
    ratio = int(round(ctrl.period / hh))
    if ratio < 1 or abs(ctrl.period / hh - ratio) > 1e-9 * ratio:
        raise ValueError(f"controller period {ctrl.period:g} s is not an integer multiple of the plant step {hh:g} s")
    L, _ = loop_matrix(model, plan, ctrl, ratio)
    name = ig.SCHEMES[int(plan.ip[ig.I_SCHEME])]
    unb = unbalance_response(model, plan, ctrl, ratio, L) if response else None
    if not vectors:
        return LoopModes(name, hh, ctrl.period, np.linalg.eigvals(L), unbalance=unb)
    mu, V = np.linalg.eig(L)
    n = model.n
    q, v = V[:n], V[n:2 * n]
    M = model.M
    Mq = np.asarray(M @ q)
    qMq = np.einsum("ij,ij->j", q.conj(), Mq).real
    qMv = np.einsum("ij,ij->j", v.conj(), Mq).conj()  # q^H M v (M symmetric)
    with np.errstate(divide="ignore", invalid="ignore"):
        fp = np.where(qMq > 0, np.abs((qMv / np.where(qMq > 0, qMq, 1.0)).imag) / (2 * np.pi), 0.0)
    return LoopModes(name, hh, ctrl.period, mu, fp, V, unb)


#: each model's physical loops, {(controller period, speed, discretisation): LoopModes}
_physical_loops: "weakref.WeakKeyDictionary[System, dict]" = weakref.WeakKeyDictionary()


def physical_loop(model: System, speed: float | None = None, sample_rate: float | None = None,
                  method: str | None = None) -> LoopModes:
    """The exact (zoh) sampled-data loop of a model with its discrete controller, eigenvectors
    included; computed once per (sample rate, speed, discretisation) and kept in the cache
    beside the model (:data:`_physical_loops`).  The result is shared: read it, do not modify it."""
    ctrl = controller_runner(model, sample_rate=sample_rate, method=method)
    key = (ctrl.period, speed, method)
    loops = _physical_loops.setdefault(model, {})
    if key not in loops:
        loops[key] = sampled_loop(model, "zoh", ctrl.period, speed=speed, ctrl=ctrl, vectors=True, response=True)
    return loops[key]

