"""The sampled-data AMB loop with loop latency, exact for held currents (no Pade).

The plant is continuous, ``x' = A x + B u + B_f f`` (``x = [eta; eta']``, ``u`` the control
currents' deviation from the operating point, ``f`` generalised forces), sampled at ``t_k = k T``:
``y_k = C x_k``.  The controller (the discrete kernel of ``controller/discrete.py``, or an LTI
law of the scene between the hardware kernels, saturation off) computes ``u_k`` from ``y_k``.
The current reaches the coil ``tau = d T + e`` later (``0 <= e < T``), so over period k the
coil holds the current applied before, ``a_k``, on ``[t_k, t_k + e)`` and the new one,
``u_{k-d}``, on ``[t_k + e, t_{k+1})`` (Astrom & Wittenmark, *Computer-Controlled Systems*, ch. 2):

    x_{k+1} = Phi x_k + Gamma_1 a_k + Gamma_0 u_{k-d},   a_{k+1} = u_{k-d}
    Phi = e^{A T},  Gamma_0 = int_0^{T-e} e^{A s} ds B,  Gamma_1 = e^{A (T-e)} int_0^e e^{A s} ds B

(each from one matrix exponential of ``[[A, B], [0, 0]]``, Van Loan).  A lost update (the reply
does not arrive; real-time mode holds the last current) is the mode ``x_{k+1} = Phi x_k +
Gamma(T) a_k``, ``a_{k+1} = a_k``.  The loop state is

    z_k = [x_k, xc_k, a_k, u_{k-1}, ..., u_{k-D}]          (D = the largest d in use)

and each timing mode is one linear map ``z_{k+1} = F z_k``: its spectral radius decides
stability, ``ln(lambda) / T`` gives growth rate and frequency of each mode.  The controller's own
``delay_samples`` adds ``delay_samples * T`` to the latency.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg as sla

from ambhil.controller import discrete as dc
from ambhil.controller.discrete import ControllerRunner
from ambhil.controller.law_lti import runner_matrices
from .analysis.sensitivity import zone
from .numerics import STABILITY_TOL


# --------------------------------------------------------------------------- the two sides
@dataclass(frozen=True)
class ContinuousPlant:
    """``x' = A x + B u + Bf f``, ``y = C x`` (u: control current deviations, A; y: sensor m)."""
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    Bf: np.ndarray  # generalised forces -> x'
    Bw: np.ndarray  # force at each AMB actuator (N) -> x'  (force-noise input)

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def n_axes(self) -> int:
        return self.B.shape[1]


def plant_of(system, speed: float) -> ContinuousPlant:
    """The linear plant of a compiled system (any rung) at spin speed ``speed`` (rad/s)."""
    M, Cd, G, K, Ba, Ca, Cs = system.dense
    n = M.shape[0]
    Minv = np.linalg.inv(M)
    A = np.zeros((2 * n, 2 * n))
    A[:n, n:] = np.eye(n)
    A[n:, :n] = -Minv @ K
    A[n:, n:] = -Minv @ (Cd + speed * G)
    Bf = np.vstack([np.zeros((n, n)), Minv])
    Bw = Bf @ Ba
    B = Bw * np.asarray(system.ki)[None, :]
    C = np.hstack([Cs, np.zeros_like(Cs)])
    return ContinuousPlant(A, B, C, Bf, Bw)


@dataclass(frozen=True)
class DiscreteController:
    """The linear controller kernel: ``xc+ = Ac xc + Bc y``, ``u = Cc xc + Dc y`` (per period T)."""
    Ac: np.ndarray
    Bc: np.ndarray
    Cc: np.ndarray
    Dc: np.ndarray
    T: float
    delay_samples: int  # the controller's own output delay (becomes latency here)


def controller_of(runner: ControllerRunner) -> DiscreteController:
    """Read the linear map of the controller kernel off the kernel itself (unit inputs, current
    limits off, its delay line taken out and returned as ``delay_samples``).  A law runner whose
    law is an LTI law of the scene (controller/law_lti.py) is read the same way, off its hardware
    kernels and its law (:func:`ambhil.controller.law_lti.runner_matrices`); any other law is
    not linear: TypeError."""
    if not isinstance(runner, ControllerRunner):
        M, nx, nd = runner_matrices(runner)
        return DiscreteController(M[:nx, :nx], M[:nx, nx:], M[nx:, :nx], M[nx:, nx:], runner.period, nd)
    p = runner.params.copy()
    nd = int(p[dc.P_DELAY])
    p[dc.P_DELAY] = 0
    p[dc.P_ILIM] = p[dc.P_ULIM] = np.inf
    na = runner.n_axes
    nx = dc.state_size(na, 0) - 1
    cols = []
    for j in range(nx + na):
        x = np.zeros(nx + 1)
        y = np.zeros(na)
        if j < nx:
            x[j] = 1.0
        else:
            y[j - nx] = 1.0
        u = np.zeros(na)
        dc.controller_step(p, x, y, u)
        cols.append(np.concatenate([x[:nx], u]))
    M = np.array(cols).T  # [[Ac, Bc], [Cc, Dc]]: the kernel is linear in (state, displacement)
    return DiscreteController(M[:nx, :nx], M[:nx, nx:], M[nx:, :nx], M[nx:, nx:], runner.period, nd)


# --------------------------------------------------------------------------- hold integrals
def hold(A: np.ndarray, B: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """``(e^{A s}, int_0^s e^{A r} dr B)`` from one matrix exponential (Van Loan)."""
    n, m = B.shape
    E = np.zeros((n + m, n + m), dtype=np.result_type(A, B))
    E[:n, :n] = A * s
    E[:n, n:] = B * s
    X = sla.expm(E)
    return X[:n, :n], X[:n, n:]


def noise_covariance(A: np.ndarray, Qc: np.ndarray, T: float,
                     radius: float | None = None) -> np.ndarray:
    """``W = int_0^T e^{A s} Qc e^{A^T s} ds``: the covariance a continuous white noise of
    intensity ``Qc`` adds to the state over one period.

    Van Loan's block exponential ``expm([[-A, Qc], [0, A^T]] h)`` holds ``e^{-A h}``, which
    overflows for a stiff plant at the full period (a mode at -4.6e6 1/s over T = 1e-4 s is
    e^456).  So it is taken over ``h = T / 2^k`` with ``|lambda|_max h <= 1`` (``radius``: the
    spectral radius of A if known), and the period is rebuilt by doubling,
    ``W(2t) = W(t) + e^{A t} W(t) e^{A^T t}``: a sum of positive semidefinite terms, no
    cancellation.  The result is symmetrised; a non-finite result raises ``FloatingPointError``."""
    A, Qc = np.asarray(A, float), np.asarray(Qc, float)
    n = A.shape[0]
    r = float(np.max(np.abs(np.linalg.eigvals(A)))) if radius is None else float(radius)
    k = max(0, int(np.ceil(np.log2(r * T)))) if r * T > 1.0 else 0
    h = T / 2 ** k
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n], M[:n, n:], M[n:, n:] = -A * h, Qc * h, A.T * h
    X = sla.expm(M)
    Phi = X[n:, n:].T  # e^{A h}
    W = Phi @ X[:n, n:]
    for _ in range(k):
        W = W + Phi @ W @ Phi.T
        Phi = Phi @ Phi
    W = 0.5 * (W + W.T)
    if not np.all(np.isfinite(W)):
        raise FloatingPointError(f"the noise covariance over T = {T:g} s is not finite "
                                 f"(spectral radius of A {r:.3g} 1/s, {k} doublings)")
    return W


def split(tau: float, T: float) -> tuple[int, float]:
    """``tau = d T + e`` with ``0 <= e < T`` (e snapped to 0 within 1e-9 T)."""
    d = int(np.floor(tau / T + 1e-9))
    e = tau - d * T
    return d, (0.0 if e < 1e-9 * T else e)


# --------------------------------------------------------------------------- the loop maps
@dataclass(frozen=True)
class Layout:
    """Where each block of the loop state z lives."""
    nx: int
    nc: int
    na: int
    D: int  # buffered past commands u_{k-1..k-D}

    @property
    def size(self) -> int:
        return self.nx + self.nc + self.na * (1 + self.D)

    @property
    def x(self) -> slice:
        return slice(0, self.nx)

    @property
    def xc(self) -> slice:
        return slice(self.nx, self.nx + self.nc)

    @property
    def a(self) -> slice:
        o = self.nx + self.nc
        return slice(o, o + self.na)

    def buf(self, j: int) -> slice:
        """u_{k-1-j}"""
        o = self.nx + self.nc + self.na * (1 + j)
        return slice(o, o + self.na)


class SampledLoop:
    """The sampled loop of one plant and controller at the controller's period: the one-period
    map ``F`` for any latency (``mode``) or a lost update (``lost``), with a shared state layout
    so that maps of different latencies can be mixed (jitter)."""

    def __init__(self, plant: ContinuousPlant, ctrl: DiscreteController, max_latency: float = 0.0,
                 modal_holds: bool = False):
        self.plant, self.ctrl, self.T = plant, ctrl, ctrl.T
        self.use_modal_holds = modal_holds
        d_max, e_max = split(max_latency + ctrl.delay_samples * ctrl.T, ctrl.T)
        self.layout = Layout(plant.n, ctrl.Ac.shape[0], plant.n_axes, d_max + (1 if e_max > 0 else 0))
        self.Phi, self.Gam_T = hold(plant.A, plant.B, self.T)
        # u_k = K z_k (+ Dc y-disturbance): the command computed this period
        L = self.layout
        self.K = np.zeros((L.na, L.size))
        self.K[:, L.x] = ctrl.Dc @ plant.C
        self.K[:, L.xc] = ctrl.Cc
        self._base = self._common()
        self._holds: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def _common(self) -> np.ndarray:
        """Rows every mode shares: the controller state and the shift of the command buffer."""
        L, c = self.layout, self.ctrl
        F = np.zeros((L.size, L.size))
        F[L.xc, L.x] = c.Bc @ self.plant.C
        F[L.xc, L.xc] = c.Ac
        if L.D:  # the buffer shifts; its head, u_k, is added per mode
            for j in range(1, L.D):
                F[L.buf(j), L.buf(j - 1)] = np.eye(L.na)
        return F

    def holds(self, e: float) -> tuple[np.ndarray, np.ndarray]:
        """``(Gamma_0, Gamma_1)`` for a fractional latency e (cached).  By Van Loan's exponentials;
        with ``modal_holds`` (for many latencies: a bisection, a grid) from the eigen-decomposition
        of A when it reproduces the exponential (one O(n^2) product per e instead of two
        exponentials).  The choice is fixed per loop, so results never depend on call history."""
        if e not in self._holds:
            if e == 0:
                self._holds[e] = (self.Gam_T, np.zeros_like(self.Gam_T))
            elif self.use_modal_holds and self._modal_holds:
                lam, V, Vinv = self.eig_A
                VB = Vinv @ self.plant.B

                def gam(s):  # int_0^s e^{A r} dr B = V diag((e^{lam s} - 1)/lam) V^-1 B
                    f = np.where(np.abs(lam * s) > 1e-8, np.expm1(lam * s) / np.where(lam == 0, 1, lam),
                                 s * (1 + lam * s / 2))
                    return V @ (f[:, None] * VB)
                G0 = gam(self.T - e).real
                G1 = (V @ (np.exp(lam * (self.T - e))[:, None] * (Vinv @ gam(e)))).real
                self._holds[e] = (G0, G1)
            else:
                _, G_e = hold(self.plant.A, self.plant.B, e)
                Ph_r, G0 = hold(self.plant.A, self.plant.B, self.T - e)
                self._holds[e] = (G0, Ph_r @ G_e)
        return self._holds[e]

    @cached_property
    def _modal_holds(self) -> bool:
        """Whether the eigen-decomposition reproduces the exponential hold (checked once, at e = T)."""
        lam, V, Vinv = self.eig_A
        if not np.all(np.isfinite(Vinv)) or np.linalg.norm(V, 1) * np.linalg.norm(Vinv, 1) > 1e8:
            return False
        VB = Vinv @ self.plant.B
        f = np.where(np.abs(lam) > 0, np.expm1(lam * self.T) / np.where(lam == 0, 1, lam), self.T)
        G = (V @ (f[:, None] * VB)).real
        return bool(np.linalg.norm(G - self.Gam_T) <= 1e-9 * np.linalg.norm(self.Gam_T))

    @cached_property
    def eig_A(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lam, V = np.linalg.eig(self.plant.A)
        return lam, V, np.linalg.inv(V)

    def _select(self, d: int) -> np.ndarray:
        """Rows that select u_{k-d} (d >= 1) from z_k."""
        L = self.layout
        if d > L.D:
            raise ValueError(f"latency of {d} periods exceeds the loop's buffer ({L.D})")
        R = np.zeros((L.na, L.size))
        R[:, L.buf(d - 1)] = np.eye(L.na)
        return R

    def mode(self, tau: float, with_input: bool = False):
        """``F`` for a loop latency ``tau`` (s) beyond the controller's own delay; with
        ``with_input`` also ``E`` (size x n_axes): how this period's command u_k enters z_{k+1}
        (``F = F_0 + E K``; a disturbance on the measured signal enters as ``E Dc`` plus ``Bc``)."""
        d, e = split(tau + self.ctrl.delay_samples * self.T, self.T)
        L, F = self.layout, self._base.copy()
        E = np.zeros((L.size, L.na))
        if L.D:
            E[L.buf(0)] = np.eye(L.na)
        G0, G1 = self.holds(e)
        F[L.x, L.a] = G1
        F[L.x, L.x] = self.Phi
        if d == 0:
            E[L.x] = G0
            E[L.a] = np.eye(L.na)
        else:
            R = self._select(d)
            F[L.x] += G0 @ R
            F[L.a] = R
        F += E @ self.K
        return (F, E) if with_input else F

    def lost(self) -> np.ndarray:
        """``F`` of a period whose update did not arrive: the applied current is held."""
        L, F = self.layout, self._base.copy()
        F[L.x, L.x] = self.Phi
        F[L.x, L.a] = self.Gam_T
        F[L.a, L.a] = np.eye(L.na)
        if L.D:  # the command computed this period still enters the pipeline
            F[L.buf(0)] = self.K
        return F

    def sensor_input(self, E: np.ndarray) -> np.ndarray:
        """How a disturbance (noise) on the measured displacements enters z_{k+1}, given ``E``."""
        G = E @ self.ctrl.Dc
        G[self.layout.xc] += self.ctrl.Bc
        return G

    def periods(self, tau: float) -> int:
        """d: whole periods of latency (the controller's own delay included)."""
        return split(tau + self.ctrl.delay_samples * self.T, self.T)[0]


# --------------------------------------------------------------------------- what a point reports
@dataclass(frozen=True)
class Stability:
    spectral_radius: float  # per period
    growth_rate: float  # 1/s of the worst mode (ln radius / T)
    frequency_hz: float  # of the worst mode
    min_damping_ratio: float  # over oscillatory modes
    min_damping_hz: float

    @property
    def stable(self) -> bool:
        # within round-off of a neutral mode (a free rigid-body motion at mu = 1 to the last bits:
        # "grows at 4.44e-12 1/s") is not growth: the tolerance of loop.numerics, one verdict
        return self.spectral_radius <= 1.0 + STABILITY_TOL


def stability(F: np.ndarray, T: float, eig: np.ndarray | None = None) -> Stability:
    mu = np.linalg.eigvals(F) if eig is None else eig
    mu = mu[np.abs(mu) > 1e-12]
    k = int(np.argmax(np.abs(mu)))
    s = np.log(mu.astype(complex)) / T
    osc = np.abs(s.imag) > 1e-9 / T
    if osc.any():
        z = -s.real[osc] / np.abs(s[osc])
        j = int(np.argmin(z))
        zmin, fz = float(z[j]), float(abs(s[osc][j].imag) / (2 * np.pi))
    else:
        zmin, fz = 1.0, 0.0
    return Stability(float(abs(mu[k])), float(s[k].real), float(abs(s[k].imag) / (2 * np.pi)), zmin, fz)


def sensitivity(loop: SampledLoop, tau: float, freqs_hz: np.ndarray) -> np.ndarray:
    """ISO 14839-3 sensitivity of the sampled loop, ``S_jj(e^{i w T})`` per axis (n_f, n_axes): the
    transfer from a disturbance added to axis j's measured displacement to the disturbed signal,
    every loop closed, ``S = (I - P(z) K(z))^-1`` with the sampled plant ``P(z) = C (zI - Phi)^-1
    (Gamma_0 z^-d + Gamma_1 z^-d-1)`` and the controller ``u = K(z) y``."""
    T, pl, c = loop.T, loop.plant, loop.ctrl
    d, e = split(tau + c.delay_samples * T, T)
    G0, G1 = loop.holds(e)
    lam, V, Vinv = loop.eig_A
    mu = np.exp(lam * T)  # Phi = V e^{lam T} V^-1: one decomposition for every frequency
    CV = pl.C @ V
    W0, W1 = Vinv @ G0, Vinv @ G1
    z = np.exp(2j * np.pi * np.asarray(freqs_hz, float) * T)
    nc, na = c.Ac.shape[0], pl.n_axes
    Wz = W0[None] * z[:, None, None] ** -d + W1[None] * z[:, None, None] ** (-d - 1)
    P = (CV[None] / (z[:, None] - mu[None, :])[:, None, :]) @ Wz
    Kz = c.Cc @ np.linalg.solve(z[:, None, None] * np.eye(nc) - c.Ac, c.Bc) + c.Dc
    return np.diagonal(np.linalg.inv(np.eye(na) - P @ Kz), axis1=1, axis2=2)


def sensitivity_peak(loop: SampledLoop, tau: float, points: int = 800) -> tuple[float, float, str, np.ndarray]:
    """Largest sampled-loop sensitivity up to Nyquist: ``(peak, at Hz, ISO zone, per-axis peaks)``.
    The grid is log-spaced and holds the frequency of every lightly damped loop mode, then the
    peak is refined by a bounded scalar search (a sharp mode is not missed between grid points)."""
    from scipy.optimize import minimize_scalar
    T = loop.T
    fny = 0.5 / T
    mu = np.linalg.eigvals(loop.mode(tau))
    mu = mu[np.abs(mu) > 0.5]
    s = np.log(mu.astype(complex)) / T
    light = np.abs(s.imag) / (2 * np.pi) > 0.5
    light &= (-s.real / np.maximum(np.abs(s), 1e-300)) < 0.3
    f = np.unique(np.clip(np.concatenate([np.logspace(0, np.log10(fny), points),
                                           np.abs(s.imag[light]) / (2 * np.pi)]), 1.0, fny))
    A = np.abs(sensitivity(loop, tau, f))
    per_axis = A.max(axis=0)
    j = int(np.argmax(per_axis))
    k = int(np.argmax(A[:, j]))
    lo, hi = f[max(k - 1, 0)], f[min(k + 1, len(f) - 1)]
    if hi > lo:
        r = minimize_scalar(lambda x: -abs(sensitivity(loop, tau, [x])[0, j]), bounds=(lo, hi),
                            method="bounded", options={"xatol": 1e-6 * hi})
        if -r.fun > per_axis[j]:
            per_axis[j], f_peak = -r.fun, float(r.x)
        else:
            f_peak = float(f[k])
    else:
        f_peak = float(f[k])
    peak = float(per_axis[j])
    return peak, f_peak, zone(peak), per_axis


def unbalance_amplitudes(loop: SampledLoop, tau: float, forces: np.ndarray, speed: float) -> np.ndarray:
    """Steady sensor amplitudes (complex, per axis) at the samples under the harmonic generalised
    force ``Re(forces e^{i speed t})`` (e.g. ``System.unbalance_forces(speed)``)."""
    F = loop.mode(tau)
    L = loop.layout
    A, bf = loop.plant.A, loop.plant.Bf @ np.asarray(forces, complex)
    n = A.shape[0]
    E = np.zeros((n + 1, n + 1), dtype=complex)
    E[:n, :n] = A * loop.T
    E[:n, n] = bf * loop.T
    E[n, n] = 1j * speed * loop.T
    g = sla.expm(E)[:n, n]  # int_0^T e^{A (T-s)} bf e^{i W s} ds
    rhs = np.zeros(L.size, dtype=complex)
    rhs[L.x] = g
    Z = np.linalg.solve(np.exp(1j * speed * loop.T) * np.eye(L.size) - F, rhs)
    return loop.plant.C @ Z[L.x]
