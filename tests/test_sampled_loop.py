"""The exact sampled loop with latency (loop/sampled.py) and the jump-linear jitter model
(loop/jitter.py), each against an independent method."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla
from scipy.integrate import solve_ivp

from ambhil.controller.discrete import ControllerRunner
from ambhil.controller.params import Amplifier, ControllerParams, Sensor
from ambhil.controller.transfer import current_law, evaluate
from ambhil.loop import jitter as jt
from ambhil.loop import sampled as sd
from ambhil.loop.period_map import loop_matrix
from ambhil.loop.system import compile_system, controller_runner
from ambhil.plant.step import make_plan

SCENE = "scenes/paper_3amb.toml"

# one AMB axis, m x'' = k_s x + k_i u, with the paper's kind of PID and lags (shared/reference/timing.md §3)
MASS, KS, KI = 10.0, 4.0e5, 150.0
PID = ControllerParams(kp=8000.0, ki=40000.0, kd=12.0, derivative_filter=1e-4, sample_rate=10_000.0,
                       sensor=Sensor(time_constant=2e-5), amplifier=Amplifier(time_constant=1e-4))


def single_axis(rate: float, pid: ControllerParams = PID) -> sd.SampledLoop:
    A = np.array([[0.0, 1.0], [KS / MASS, 0.0]])
    B = np.array([[0.0], [KI / MASS]])
    plant = sd.ContinuousPlant(A, B, np.array([[1.0, 0.0]]), np.array([[0.0], [1.0 / MASS]]),
                               np.array([[0.0], [1.0 / MASS]]))
    return sd.SampledLoop(plant, sd.controller_of(ControllerRunner(pid, [0.0], sample_rate=rate)),
                          max_latency=4.0 / rate)


@pytest.fixture(scope="module")
def modal():
    return compile_system(SCENE, rung="modal")


def test_loop_map_equals_the_kernels_loop_matrix(modal):
    """Zero latency (and the controller's own delay line): the exact map built from matrix
    exponentials has the spectrum of the one-period map of the simulation kernels (zoh)."""
    for delay in (0, 2):
        m = compile_system(load_with_delay(delay), rung="modal")
        r = controller_runner(m)
        plan = make_plan(m, "zoh", r.period, speed=0.0, nonlinear=False, ratio=1)
        L, span = loop_matrix(m, plan, r, 1)
        ours = sd.SampledLoop(sd.plant_of(m, 0.0), sd.controller_of(r)).mode(0.0)
        rho_k = np.max(np.abs(np.linalg.eigvals(L))) ** (1 / span)
        rho = np.max(np.abs(np.linalg.eigvals(ours)))
        assert rho == pytest.approx(rho_k, rel=1e-10)


def load_with_delay(n):
    from ambhil.loop.scene import load_scene
    return load_scene(SCENE).with_controller(delay_samples=n)


def test_fractional_latency_matches_direct_integration():
    """The hold integrals against an ODE solver: integrate x' = A x + B u piece by piece with the
    old current until t_k + e and the new one after, the controller kernel in between."""
    rate = 10_000.0
    lp = single_axis(rate)
    T, c = lp.T, lp.ctrl
    for tau in (0.3 * T, 1.6 * T):
        F = lp.mode(tau)
        L = lp.layout
        z = np.zeros(L.size)
        z[L.x] = [1e-5, 0.0]
        x, xc = z[L.x].copy(), z[L.xc].copy()
        d, e = sd.split(tau, T)
        pending = [0.0] * (d + 1)  # commands in flight: pending[-1] arrives this period
        applied = 0.0
        for k in range(12):
            y = (lp.plant.C @ x)[0]
            u = (c.Cc @ xc)[0] + c.Dc[0, 0] * y
            xc = c.Ac @ xc + c.Bc[:, 0] * y
            pending = [u] + pending[:-1]  # u_k, ..., u_{k-d}
            new = pending[-1]
            for t0, t1, cur in ((0.0, e, applied), (e, T, new)):
                if t1 > t0:
                    sol = solve_ivp(lambda t, s: lp.plant.A @ s + lp.plant.B[:, 0] * cur, (t0, t1), x,
                                    rtol=1e-11, atol=1e-16, method="DOP853")
                    x = sol.y[:, -1]
            applied = new
            z = F @ z
            np.testing.assert_allclose(z[L.x], x, rtol=1e-7, atol=1e-13)


def test_latency_is_continuous_across_whole_periods():
    lp = single_axis(10_000.0)
    T = lp.T
    for d in (1, 2):
        a = np.max(np.abs(np.linalg.eigvals(lp.mode(d * T - 1e-9 * T))))
        b = np.max(np.abs(np.linalg.eigvals(lp.mode(d * T))))
        assert a == pytest.approx(b, rel=1e-6)


def test_sampled_sensitivity_two_ways(modal):
    """S = (I - P K)^-1 from the plant's eigen-decomposition equals 1 + Cy (zI - F)^-1 G from the
    loop map, for zero, fractional and more-than-one-period latency."""
    lp = sd.SampledLoop(sd.plant_of(modal, 0.0), sd.controller_of(controller_runner(modal)), max_latency=2.5e-4)
    f = np.array([10.0, 51.4, 400.0, 1254.0, 3000.0])
    for tau in (0.0, 0.37e-4, 1.3e-4):
        S1 = sd.sensitivity(lp, tau, f)
        F, E = lp.mode(tau, with_input=True)
        G, L = lp.sensor_input(E), lp.layout
        Cy = np.zeros((L.na, L.size))
        Cy[:, L.x] = lp.plant.C
        S2 = np.array([1 + np.diagonal(Cy @ np.linalg.solve(np.exp(2j * np.pi * fk * lp.T) * np.eye(L.size) - F, G))
                       for fk in f])
        np.testing.assert_allclose(S1, S2, rtol=1e-8)


def test_sampled_loop_converges_to_the_continuous_analyses(modal):
    """At a high rate the sampled sensitivity and unbalance response approach the continuous
    closed-loop ones (loop/analysis), computed by an unrelated frequency-domain solver."""
    from ambhil.loop.analysis.sensitivity import sensitivity
    from ambhil.loop.analysis.unbalance import response
    fast = controller_runner(modal, sample_rate=400_000.0)
    lp = sd.SampledLoop(sd.plant_of(modal, 300.0), sd.controller_of(fast))
    f = np.array([20.0, 80.0, 300.0])
    S_c = sensitivity(modal, 300.0, 2 * np.pi * f).S
    np.testing.assert_allclose(np.abs(sd.sensitivity(lp, 0.0, f)), np.abs(S_c), rtol=0.01)
    amp = sd.unbalance_amplitudes(lp, 0.0, modal.unbalance_forces(300.0), 300.0)
    dofs = list(modal.sens_dof)
    ref = response(modal, [300.0], dofs=dofs)[0]
    np.testing.assert_allclose(np.abs(amp), np.abs(ref), rtol=0.01)


def continuous_delay_margin(pid: ControllerParams) -> float:
    """min over gain crossovers of phase margin / crossover frequency of L = k_i H / (m s^2 - k_s)."""
    H = current_law(pid)
    w = np.logspace(0, 5.5, 200_000)
    Lw = KI * evaluate(H, 1j * w) / (MASS * (1j * w) ** 2 - KS)
    mag = np.abs(Lw)
    k = np.where(np.diff(np.sign(mag - 1.0)) != 0)[0]
    margins = []
    for j in k:
        wc = w[j] + (w[j + 1] - w[j]) * (1 - mag[j]) / (mag[j + 1] - mag[j])
        ph = np.angle(KI * evaluate(H, 1j * wc)[0] / (MASS * (1j * wc) ** 2 - KS))
        pm = (ph + np.pi) % (2 * np.pi)  # phase above -180 deg
        margins.append(pm / wc)
    return min(margins)


def largest_latency(lp: sd.SampledLoop, tau_max: float) -> float:
    rho = lambda tau: np.max(np.abs(np.linalg.eigvals(lp.mode(tau))))
    lo, hi = 0.0, tau_max
    assert rho(lo) < 1 and rho(hi) >= 1
    while hi - lo > 1e-4 * lp.T:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if rho(mid) < 1 else (lo, mid)
    return lo


def test_sampled_delay_boundary_converges_to_the_continuous_delay_margin():
    dm = continuous_delay_margin(PID)
    errs = []
    for rate in (20_000.0, 80_000.0, 320_000.0):
        lp = single_axis(rate)
        # the loop's buffer must hold the margin: rebuild with room for it
        lp = sd.SampledLoop(lp.plant, lp.ctrl, max_latency=1.5 * dm)
        errs.append(abs(largest_latency(lp, 1.5 * dm) - dm) / dm)
    assert errs[0] > errs[1] > errs[2]
    assert errs[-1] < 0.01, errs


# --------------------------------------------------------------------------- jitter
def jump_system(lp, taus, probs, loss=0.0, sigma=1e-6):
    Fs, Ws = [], []
    for tau in taus:
        F, E = lp.mode(tau, with_input=True)
        G = lp.sensor_input(E)
        Fs.append(F)
        Ws.append(sigma ** 2 * G @ G.T)
    p = np.asarray(probs, float) * (1 - loss)
    if loss:
        Fs.append(lp.lost())
        E = np.zeros((lp.layout.size, lp.layout.na))
        if lp.layout.D:
            E[lp.layout.buf(0)] = 1.0
        G = lp.sensor_input(E)
        Ws.append(sigma ** 2 * G @ G.T)
        p = np.append(p, loss)
    return jt.JumpSystem(tuple(Fs), p, tuple(Ws))


def kron_covariance(js):
    n = js.F[0].shape[0]
    K = sum(p * np.kron(F, F) for p, F in zip(js.p, js.F))
    W = sum(p * Wj for p, Wj in zip(js.p, js.W))
    return np.linalg.solve(np.eye(n * n) - K, W.ravel()).reshape(n, n)


def test_no_jitter_covariance_is_the_discrete_lyapunov_solution():
    lp = single_axis(10_000.0)
    js = jump_system(lp, [0.4 * lp.T], [1.0])
    P = jt.stationary_covariance(js)
    scale = np.sqrt(np.maximum(np.diag(P), 1e-30 * np.max(np.diag(P))))
    S, Si = np.diag(scale), np.diag(1.0 / scale)  # in unscaled coordinates the solver is 1.6e-7 off
    ref = S @ sla.solve_discrete_lyapunov(Si @ js.F[0] @ S, Si @ js.W[0] @ Si) @ S
    np.testing.assert_allclose(P, ref, rtol=1e-9, atol=1e-12 * np.abs(P).max())
    assert close(P, kron_covariance_scaled(js, scale), tol=1e-12)


def close(P, Q, tol=1e-6):
    return np.linalg.norm(P - Q) <= tol * np.linalg.norm(Q)


def kron_covariance_scaled(js, scale):
    """The Kronecker solution in coordinates z = S z' with S = diag(scale) (metres, amperes and
    controller states differ by orders of magnitude: unscaled, the n^2 solve loses the digits)."""
    S, Si = np.diag(scale), np.diag(1.0 / scale)
    sj = jt.JumpSystem(tuple(Si @ F @ S for F in js.F), js.p, tuple(Si @ W @ Si for W in js.W))
    return S @ kron_covariance(sj) @ S


def test_jitter_and_loss_covariance_equals_the_kronecker_solution():
    lp = single_axis(10_000.0)
    T = lp.T
    js = jump_system(lp, [0.1 * T, 0.5 * T, 1.2 * T], [0.5, 0.3, 0.2], loss=0.05)
    P = jt.stationary_covariance(js)
    scale = np.sqrt(np.maximum(np.diag(P), 1e-30 * np.max(np.diag(P))))
    assert close(P, kron_covariance_scaled(js, scale))


def test_mean_square_test_agrees_with_the_kronecker_radius():
    """Around the boundary (the probability of a destabilising latency swept, with losses), the
    splitting test and the exact radius of sum p F (x) F decide alike."""
    dm = continuous_delay_margin(PID)
    lp = single_axis(10_000.0)
    lp = sd.SampledLoop(lp.plant, lp.ctrl, max_latency=1.5 * dm)
    T = lp.T
    seen = set()
    for q in np.linspace(0.0, 1.0, 21):
        js = jump_system(lp, [0.2 * T, 1.3 * dm], [1 - q, q], loss=0.02)
        exact = jt.ms_spectral_radius(js)
        ms = jt.ms_test(js)
        if abs(exact - 1) > 1e-3:
            assert ms.stable == (exact < 1), (loss, exact, ms)
            seen.add(exact < 1)
    assert seen == {True, False}  # the sweep crossed the boundary


def test_jump_linear_variance_matches_monte_carlo():
    """Time-domain Monte Carlo of the hybrid loop, integrated period by period with the held
    currents (independent of the assembled maps), random latency and loss each period, sensor
    noise: the displacement variance within its 99 % confidence interval."""
    rate = 10_000.0
    lp = single_axis(rate)
    T, c, pl = lp.T, lp.ctrl, lp.plant
    taus, probs, loss, sigma = [0.1 * T, 0.6 * T, 1.3 * T], [0.5, 0.3, 0.2], 0.05, 1e-6
    js = jump_system(lp, taus, probs, loss, sigma)
    P = jt.stationary_covariance(js)
    var = float((pl.C @ P[lp.layout.x, lp.layout.x] @ pl.C.T)[0, 0])
    holds = {tau: (sd.hold(pl.A, pl.B, sd.split(tau, T)[1]), sd.hold(pl.A, pl.B, T - sd.split(tau, T)[1]))
             for tau in taus}
    Phi_T, G_T = sd.hold(pl.A, pl.B, T)
    rng = np.random.default_rng(7)
    n, burn, batches = 400_000, 5_000, 40
    x, xc, applied = np.zeros(2), np.zeros(c.Ac.shape[0]), 0.0
    hist = [0.0] * 3  # u_k, u_{k-1}, u_{k-2}
    ys = np.empty(n)
    modes = rng.choice(4, size=n, p=list(np.asarray(probs) * (1 - loss)) + [loss])
    noise = rng.normal(0.0, sigma, n)
    for k in range(n):
        y = x[0]
        ys[k] = y
        ym = y + noise[k]
        u = (c.Cc @ xc)[0] + c.Dc[0, 0] * ym
        xc = c.Ac @ xc + c.Bc[:, 0] * ym
        hist = [u] + hist[:2]
        j = modes[k]
        if j == 3:
            x = Phi_T @ x + G_T[:, 0] * applied
            continue
        d = sd.split(taus[j], T)[0]
        (Pe, Ge), (Pr, Gr) = holds[taus[j]]
        new = hist[d]
        x = Pr @ (Pe @ x + Ge[:, 0] * applied) + Gr[:, 0] * new
        applied = new
    y2 = ys[burn:] ** 2
    means = np.array([b.mean() for b in np.array_split(y2, batches)])
    est, half = means.mean(), 2.7 * means.std(ddof=1) / np.sqrt(batches)
    assert abs(est - var) < half + 1e-3 * var, (est, var, half)


# --------------------------------------------------------------------------- force-noise covariance
def quadrature_covariance(A, Q, T):
    """int_0^T e^{A s} Q e^{A^T s} ds by adaptive Gauss-Kronrod quadrature of the integrand
    (scipy.integrate.quad_vec), independent of Van Loan's block exponential."""
    from scipy.integrate import quad_vec
    lam = np.max(np.abs(np.linalg.eigvals(A)))
    pts = [T * 2.0 ** -k for k in range(1, int(np.log2(max(lam * T, 2.0))) + 2)]  # resolve the fast decay

    def f(s):
        E = sla.expm(A * s)
        return E @ Q @ E.T
    return quad_vec(f, 0.0, T, epsrel=1e-11, epsabs=0.0, points=sorted(pts))[0]


@pytest.mark.parametrize("a", [-3.0, 40.0, -2.0e5, -5.5e8])
def test_noise_covariance_of_a_first_order_system_is_the_analytic_one(a):
    """x' = a x + w, E[w w] = q delta: W(T) = q (1 - e^{2aT}) / (-2a), stable or not; at
    a = -5.5e8 1/s (the full rung's fastest modes) over T = 1e-4 s, e^{-aT} = e^{55000}, which
    the plain Van Loan exponential overflows on."""
    q, T = 2.5, 1e-4
    W = sd.noise_covariance(np.array([[a]]), np.array([[q]]), T)
    assert np.isfinite(W).all()
    assert W[0, 0] == pytest.approx(q * -np.expm1(2 * a * T) / (-2 * a), rel=1e-12)


def test_noise_covariance_equals_quadrature_on_a_stiff_rotor_like_system():
    """A 4-state plant with a lightly damped 1.2 kHz mode, an unstable (AMB negative stiffness)
    mode and a stiff 2e5 1/s one, noise through a force input: the scaled-and-doubled Van Loan
    result equals direct quadrature of the integral."""
    w, z = 2 * np.pi * 1200.0, 0.003
    A = np.array([[0.0, 1.0, 0.0, 0.0],
                  [-w * w, -2 * z * w, 3e4, 0.0],
                  [0.0, 0.0, 0.0, 1.0],
                  [5e3, 0.0, 900.0, -2.0e5]])
    b = np.array([[0.0], [1.0], [0.0], [0.5]])
    Q = b @ b.T * 0.3
    T = 1e-4
    W = sd.noise_covariance(A, Q, T)
    ref = quadrature_covariance(A, Q, T)
    assert np.linalg.norm(W - ref) <= 1e-9 * np.linalg.norm(ref)
    np.testing.assert_allclose(W, W.T, rtol=0, atol=0)


@pytest.fixture(scope="module")
def full_loop():
    full = compile_system(SCENE, rung="full")
    return sd.SampledLoop(sd.plant_of(full, 327.19), sd.controller_of(controller_runner(full)))


def test_force_noise_covariance_of_the_full_rung_is_finite_symmetric_psd(full_loop):
    """Full rung (504 states, modes up to 4.6e6 1/s), 1e-2 N^2/Hz at every AMB axis, over the
    10 kHz period: finite, symmetric, positive semidefinite, and equal to the same integral
    taken mode by mode on the eigen-decomposition of A, W = V (Q~_ij (e^{(l_i + conj l_j) T} - 1)
    / (l_i + conj l_j)) V^H (a second method; V has condition ~1e9, hence 1e-6)."""
    from ambhil.loop.timing_study import Noise
    W = Noise("force", 1e-2).force_covariance(full_loop)
    assert np.isfinite(W).all()
    np.testing.assert_array_equal(W, W.T)
    ev = np.linalg.eigvalsh(W)
    assert ev.max() > 0 and ev.min() >= -1e-12 * ev.max()
    A, Bw, T = full_loop.plant.A, full_loop.plant.Bw, full_loop.T
    lam, V = np.linalg.eig(A)
    Vi = np.linalg.inv(V)
    Qt = Vi @ (Bw @ Bw.T * 0.5e-2) @ Vi.conj().T
    S = lam[:, None] + lam.conj()[None, :]
    ref = (V @ (Qt * np.expm1(S * T) / S) @ V.conj().T).real
    assert np.linalg.norm(W - ref) <= 1e-6 * np.linalg.norm(ref)
