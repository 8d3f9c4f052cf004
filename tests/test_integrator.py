"""Integrators: banded algebra, force law, convergence orders, numerical damping, Newton."""
import numpy as np
import pytest
import scipy.linalg as sla

from ambhil.plant import banded as bd
from ambhil.plant import integrator as ig
from ambhil.plant import plan as pl
from ambhil.plant import magnetic_bearing as mb
from ambhil.loop.system import compile_system
from ambhil.loop.scene import parse_scene
import tomllib

SCENE = """
[scene]
name = "td_test"
[model]
rung = "rigid"
[[shaft]]
length = 1.55
outer_diameter = 0.12
elements = 62
[[disc]]
name = "wheel"
node = 30
mass = 40.0
polar_inertia = 1.6
diametral_inertia = 0.85
[[disc]]
name = "coupling"
node = 3
mass = 8.0
polar_inertia = 0.05
diametral_inertia = 0.03
[[amb]]
name = "A"
node = 21
gap = 1.5e-4
bias_current = 2.0
turns = 100
pole_area = 1e-3
[[amb]]
name = "C"
node = 57
gap = 1.5e-4
bias_current = 2.0
turns = 100
pole_area = 1e-3
[sensor]
gain = 1e4
time_constant = 2e-5
[amplifier]
gain = 1.0
time_constant = 1e-4
current_limit = 4.0
[controller]
kp = 2.0
ki = 20.0
kd = 2e-3
derivative_filter = 1e-4
[[unbalance]]
node = 30
magnitude = 0.001
phase = 1.0471975511965976
[damping]
stiffness_proportional = 2e-6
"""


def scene(rung="rigid", **edits):
    """The test scene (a stable two-AMB rotor), with dotted-key edits: {'controller.kd': 1e-3}."""
    doc = tomllib.loads(SCENE)
    doc["model"]["rung"] = rung
    for k, v in edits.items():
        parts = k.split(".")
        d = doc
        for p in parts[:-1]:
            d = d[p][0] if isinstance(d[p], list) else d[p]
        d[parts[-1]] = v
    return parse_scene(doc, "<td_test>")


def model(rung="rigid", **edits):
    return compile_system(scene(rung, **edits))


def test_banded_lu_matches_dense_solve():
    rng = np.random.default_rng(0)
    n, bw = 30, 5
    A = np.zeros((n, n))
    for i in range(n):
        for j in range(max(0, i - bw), min(n, i + bw + 1)):
            A[i, j] = rng.standard_normal()
    A += 10 * np.eye(n)
    R = bd.to_rowband(A, bw)
    x = rng.standard_normal(n)
    y = np.zeros(n)
    bd.band_mv(bd.diag_major(R), bw, x, y, 1.0, False)
    assert np.allclose(y, A @ x, rtol=1e-14, atol=1e-12)
    bd.band_lu(R, bw)
    b = y.copy()
    bd.band_solve(R, bw, b)
    assert np.allclose(b, x, rtol=1e-10)


def test_force_law_is_magnetic_bearing_force():
    k, s0, i0 = 1.2e-5, 1.5e-4, 2.0
    for x in (-1e-4, 0.0, 3e-5):
        for i in (-1.9, 0.0, 0.7):
            assert ig.amb_force(k, s0, i0, x, i) == pytest.approx(mb.force(k, s0, i0, x, i), rel=1e-13)
    # beyond i0 the lower coil is off (it cannot push)
    assert ig.amb_force(k, s0, i0, 0.0, 3.0) == pytest.approx(0.25 * k * 25 / s0**2)


@pytest.mark.parametrize("scheme", ["bdf1", "bdf2", "trapezoidal", "generalized-alpha"])
def test_scalar_amplification_matches_kernel(scheme):
    """The analytic stability function used for the numerical-damping check equals the
    kernel's own step on a single undamped mode (second method)."""
    from ambhil.loop.numerics import scheme_amplification
    # BDF1: |R| = 1/sqrt(1 + (wh)^2) (physics.md 2.3)
    wh = 0.3
    if scheme == "bdf1":
        assert abs(scheme_amplification("bdf1", 1j * wh)) == pytest.approx(1 / np.sqrt(1 + wh**2), rel=1e-14)
    if scheme == "trapezoidal":
        assert abs(scheme_amplification("trapezoidal", 1j * wh)) == pytest.approx(1.0, abs=1e-14)
    # all schemes: R -> e^{lam h} as h -> 0 at the scheme's order
    e = [abs(scheme_amplification(scheme, 1j * w) - np.exp(1j * w)) for w in (0.02, 0.01)]
    order = np.log2(e[0] / e[1]) - 1  # local error O(h^{p+1})
    assert order == pytest.approx(ig.ORDER[scheme], abs=0.15)


def _steady(m, scheme, h, W=350.0):
    from ambhil.loop.orbits import harmonic
    from ambhil.loop.simulation import simulate
    r = simulate(m, 0.5, W, integrator=scheme, h=h, nodes=[21])
    assert r.fault is None
    return harmonic(r.t, r.orbit[:, 0, 0], W)


def test_convergence_orders():
    """Steady unbalance orbit error against the exact (zoh) sampled-data loop, refining the plant
    step at a fixed 10 kHz controller: BDF1 ~1, BDF2, trapezoidal, gen-alpha ~2."""
    m = model("rigid")
    ref = _steady(m, "zoh", 1e-4)
    for scheme, p in (("bdf1", 1), ("bdf2", 2), ("trapezoidal", 2), ("generalized-alpha", 2)):
        e = [abs(_steady(m, scheme, 1e-4 / r) - ref) / abs(ref) for r in (4, 8, 16)]
        slope = np.log2(e[-2] / e[-1])
        assert slope == pytest.approx(p, abs=0.3), (scheme, e)


def test_zoh_is_exact_for_any_step_ratio():
    m = model("rigid")
    a = _steady(m, "zoh", 1e-4)
    b = _steady(m, "zoh", 2.5e-5)
    assert abs(a - b) / abs(a) < 1e-9


def test_dense_and_banded_paths_agree():
    """Reduced rungs use a pre-multiplied dense map; it must equal the banded kernel."""
    m = model("modal")
    p_dense = pl.build_plan(m, "trapezoidal", 1e-4, speed=300.0)
    p_band = pl.build_plan(m, "trapezoidal", 1e-4, speed=300.0, dense_max=0)
    assert p_dense.ip[ig.I_DENSE] == 1 and p_band.ip[ig.I_DENSE] == 0
    rng = np.random.default_rng(3)
    n = m.n
    s1 = np.zeros(4 * n + 1); s1[:2 * n] = 1e-6 * rng.standard_normal(2 * n)
    s2 = s1.copy()
    wk, ws = pl.new_workspace(p_band)
    y = np.zeros(m.n_axes)
    for k in range(50):
        cur = 0.01 * rng.standard_normal(m.n_axes)
        ig.plant_advance(p_dense, s1, cur, 1, wk, ws, y)
        ig.plant_advance(p_band, s2, cur, 1, wk, ws, y)
    assert np.allclose(s1[:2 * n], s2[:2 * n], rtol=1e-9, atol=1e-18)


def test_nonlinear_law_reduces_to_linear_for_small_motion_and_newton_converges():
    from ambhil.loop.orbits import harmonic
    from ambhil.loop.simulation import simulate
    m = model("rigid", **{"unbalance.magnitude": 1e-6})
    W = 350.0
    lin = simulate(m, 0.4, W, integrator="bdf2", h=5e-5, nodes=[21])
    nl = simulate(m, 0.4, W, integrator="bdf2", h=5e-5, nodes=[21], nonlinear=True)
    assert nl.fault is None and 1 <= nl.meta["max_newton_iterations"] <= 5
    a, b = harmonic(lin.t, lin.orbit[:, 0, 0], W), harmonic(nl.t, nl.orbit[:, 0, 0], W)
    assert abs(a - b) / abs(a) < 1e-3
    # large unbalance (orbit ~ 20 % of the gap): the force-law nonlinearity is visible
    m2 = model("rigid", **{"unbalance.magnitude": 4e-3})
    lin = simulate(m2, 0.4, W, integrator="bdf2", h=5e-5, nodes=[21])
    nl = simulate(m2, 0.4, W, integrator="bdf2", h=5e-5, nodes=[21], nonlinear=True)
    a, b = harmonic(lin.t, lin.orbit[:, 0, 0], W), harmonic(nl.t, nl.orbit[:, 0, 0], W)
    assert abs(a - b) / abs(a) > 2e-3


def test_newton_non_convergence_is_reported():
    from ambhil.loop.simulation import simulate
    m = model("rigid", **{"unbalance.magnitude": 4e-3})
    r = simulate(m, 0.05, 350.0, integrator="bdf1", nodes=[21], nonlinear=True,
                 plan=pl.build_plan(m, "bdf1", 1e-4, speed=350.0, nonlinear=True, newton_iterations=1,
                                    newton_tol=1e-14))
    assert r.fault is not None and r.fault.startswith("Newton did not converge at t=")
    assert "iterations" in r.fault and "residual" in r.fault


def test_run_up_matches_constant_speed_at_its_ends_and_refactorises():
    """A run-up holding a constant speed after the ramp reaches the constant-speed steady state."""
    from ambhil.loop.orbits import harmonic
    from ambhil.loop.simulation import simulate
    m = model("rigid")
    W = 350.0
    ru = simulate(m, 0.6, None, run_up=(250.0, W, 0.0, 0.1), integrator="trapezoidal", h=5e-5, nodes=[21])
    cs = simulate(m, 0.6, W, integrator="trapezoidal", h=5e-5, nodes=[21])
    assert ru.fault is None and ru.meta["refactorisations"] > 0
    assert ru.speed[0] == 250.0 and ru.speed[-1] == W
    # phases differ by the angle lost during the ramp: compare amplitudes, and phase after shifting
    a, b = harmonic(ru.t, ru.orbit[:, 0, 0], W), harmonic(cs.t, cs.orbit[:, 0, 0], W)
    assert abs(a) == pytest.approx(abs(b), rel=1e-4)
    lost = 0.5 * (W - 250.0) * 0.1  # theta_runup(t) = W t - lost for t > 0.1
    assert np.angle(a * np.exp(1j * lost) / b) == pytest.approx(0.0, abs=1e-4)


@pytest.mark.parametrize("rung,latency", [("rigid", 0.0), ("modal", 0.0), ("full", 0.0), ("modal", 1.5e-4)])
def test_runner_bound_kernel_is_the_dispatched_kernel_bit_for_bit(rung, latency):
    """PlantRunner calls the numba kernel's compiled code for its argument types directly
    (ambhil.plant.step.bound_kernel, no per-call type resolution): 200 periods with varying currents
    give the very bits of the kernels called through their dispatchers."""
    from pathlib import Path
    from ambhil.loop.scene import load_scene
    from ambhil.plant.latency import advance_late
    from ambhil.plant.run_options import RunOptions
    from ambhil.plant.step import PlantRunner
    scene = load_scene(Path(__file__).resolve().parents[1] / "scenes" / "paper_3amb.toml")
    model = compile_system(scene, rung=rung)
    h = model.period / 2 if latency else None
    a, b = PlantRunner(model, RunOptions(h=h, latency=latency)), PlantRunner(model, RunOptions(h=h, latency=latency))
    assert a._advance is not ig.plant_advance
    rng = np.random.default_rng(3)
    for k in range(200):
        u = np.array(model.i_op) + 0.05 * rng.standard_normal(model.n_axes)
        ya = a.advance(u)
        b.currents = u
        if b.ring is None:
            st = ig.plant_advance(b.plan, b.s, u, b.ratio, b.work, b.ws, b.y)
        else:
            st = advance_late(b.plan, b.s, u, b.ring, b.step_index, *b.late, b.ratio, b.work, b.ws, b.y)
        b.step_index += 1
        assert st == a.status
        assert np.array_equal(ya, b.y) and np.array_equal(a.s, b.s)


@pytest.mark.parametrize("rung", ["full", "modal", "rigid"])
def test_sparse_sensor_rows_and_unbalance_equal_the_dense_formulas(rung):
    """The kernel reads Cs and the unbalance vectors through their non-zeros only (the full rung:
    one DOF per sensor row, two unbalanced DOFs out of 252); checked against the model's own
    dense Cs and unbalance forces with numpy, on a random state and phase."""
    from ambhil.plant.step import make_plan
    m = compile_system("scenes/paper_3amb.toml", rung)
    p = make_plan(m, "bdf1")
    n = int(p.ip[ig.I_N])
    rng = np.random.default_rng(7)
    s = rng.standard_normal(4 * n + 1)
    y = np.zeros(m.n_axes)
    ig.sense(p, s, y)
    Cs = m.Cs.toarray() if hasattr(m.Cs, "toarray") else np.asarray(m.Cs)
    np.testing.assert_allclose(y, Cs @ s[:n], rtol=1e-15, atol=0)
    assert len(p.cs_idx) == np.count_nonzero(Cs)
    t = 0.0123
    out = rng.standard_normal(n)
    ref = out.copy()
    ig._add_unbalance(p, t, 0.37, out)
    th, W, Wd = ig.speed_at(p.fp, t)
    U = m.unbalance_forces(1.0)
    ref += 0.37 * (W * W * (U * np.exp(1j * th)).real + Wd * (-1j * U * np.exp(1j * th)).real)
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-300)
    assert set(p.u_idx.tolist()) == set(np.flatnonzero(U != 0).tolist())


def test_trapezoidal_exact_force_law_is_second_order():
    """With the exact force law (orbit ~ 20 % of the gap, the remainder visible) trapezoidal
    converges at order 2 with the plant step, against its own finest step: its remainder enters at
    both ends of the step (h/2 r(q_n) + h/2 r(q+)).  With the t_n half left out (as it once was)
    the error stays first order (slope ~1)."""
    from ambhil.loop.orbits import harmonic
    from ambhil.loop.simulation import simulate
    m = model("rigid", **{"unbalance.magnitude": 4e-3})
    W = 350.0
    amp = lambda h: harmonic(*(lambda r: (r.t, r.orbit[:, 0, 0]))(
        simulate(m, 0.3, W, integrator="trapezoidal", h=h, nodes=[21], nonlinear=True)), W)
    ref = amp(1e-4 / 64)
    e = [abs(amp(1e-4 / r) - ref) / abs(ref) for r in (2, 4, 8)]
    assert np.log2(e[-2] / e[-1]) == pytest.approx(2, abs=0.35), e
