"""Closed-loop eigenvalues, unbalance response and sensitivity, each against a second method."""
import numpy as np
import pytest
import scipy.linalg as sla

from ambhil.controller import transfer
from ambhil.loop.analysis import closed_loop, dynamic_stiffness, modal, sensitivity, unbalance
from ambhil.loop.system import compile_system

SCENES = "scenes/paper_{}.toml"


@pytest.fixture(scope="module")
def m3():
    return compile_system(SCENES.format("3amb"))


@pytest.fixture(scope="module")
def m3_modal():
    return compile_system(SCENES.format("3amb"), rung="modal")


def test_current_law_is_eq7():
    m = compile_system(SCENES.format("2amb"), rung="rigid")
    c = m.scene.controller
    sn, am = c.sensor, c.amplifier
    s = 1j * np.array([3.0, 300.0, 3000.0, 30000.0])
    Gc = c.kp + c.ki / s + c.kd * s / (1 + s * c.derivative_filter)
    Gs = sn.gain / (1 + sn.time_constant * s)
    Ga = am.gain / (1 + am.time_constant * s)
    np.testing.assert_allclose(transfer.evaluate(m.H, s), Gs * Gc * Ga, rtol=1e-12)
    T = transfer.bearing_transfer(m.kx[0], m.ki[0], m.H)
    np.testing.assert_allclose(transfer.evaluate(T, s), m.kx[0] - Gs * Gc * Ga * m.ki[0], rtol=1e-10)


def test_eigenvalues_make_dynamic_stiffness_singular(m3_modal):
    """Every closed-loop eigenvalue of the state-space model is a root of det Z(s) (controller
    states eliminated): an independent formulation."""
    speed = 1500.0
    cl = closed_loop.build(m3_modal, speed, sparse=False)
    lam = sla.eigvals(cl.dense_standard())
    lam = lam[(lam.imag > 1.0) & (np.abs(lam) < 2 * np.pi * 2000)]
    assert len(lam) >= 8
    M, C, G, K, Ba, Ca, Cs = m3_modal.dense
    for l in lam:
        h = transfer.evaluate(m3_modal.H, l)[0]
        Z = l * l * M + l * (C + speed * G) + K + (Ba * (h * m3_modal.ki)) @ Cs
        sv = np.linalg.svd(Z, compute_uv=False)
        assert sv[-1] < 1e-9 * sv[0]
    # and a point that is not an eigenvalue is not singular
    l = lam[0] * (1 + 0.05j)
    h = transfer.evaluate(m3_modal.H, l)[0]
    Z = l * l * M + l * (C + speed * G) + K + (Ba * (h * m3_modal.ki)) @ Cs
    sv = np.linalg.svd(Z, compute_uv=False)
    assert sv[-1] > 1e-6 * sv[0]


def test_critical_speeds_two_methods_agree(m3):
    """Full rung: Ruhe refinement on the banded Z(s) vs shift-invert Arnoldi on the state space."""
    ruhe = modal.critical_speeds(m3)
    arnoldi = modal.critical_speeds(m3, solver=modal.Solver(m3))
    assert len(ruhe) == 4
    np.testing.assert_allclose([c.speed for c in ruhe], [c.speed for c in arnoldi], rtol=1e-7)
    for c in ruhe:
        assert c.mode.eigenvalue.imag == pytest.approx(c.speed, rel=1e-8)
        assert c.mode.whirl == "forward"


def test_rungs_agree(m3, m3_modal):
    full = [c.speed for c in modal.critical_speeds(m3)]
    red = [c.speed for c in modal.critical_speeds(m3_modal)]
    np.testing.assert_allclose(red, full, rtol=2e-3)


def test_rigid_rung_equals_stiff_full_rotor():
    from helpers import scene
    over = dict(shaft=[{"length": 1.0, "outer_diameter": 0.08, "elements": 20, "youngs_modulus": 2.11e15}],
                disc=[{"name": "d", "node": 8, "mass": 40.0, "polar_inertia": 0.9, "diametral_inertia": 0.6}],
                controller={"kp": 2.0, "ki": 5.0, "kd": 2e-4, "derivative_filter": 5e-5},
                sensor={"gain": 1e4, "time_constant": 2e-5}, amplifier={"gain": 1.0, "time_constant": 1e-4})
    rigid = modal.critical_speeds(compile_system(scene(**over), rung="rigid"), count=2, speed_max=3000)
    full = modal.critical_speeds(compile_system(scene(**over), rung="full"), count=2, speed_max=3000)
    assert len(rigid) == 2
    np.testing.assert_allclose([c.speed for c in full], [c.speed for c in rigid], rtol=1e-4)


@pytest.mark.parametrize("name,kd_scale", [("2amb", 1.0), ("3amb", 1.0), ("2amb", 0.5)])
def test_unbalance_peaks_match_critical_speeds(name, kd_scale):
    """Peaks of the frequency-domain unbalance response sit at the eigen-analysis critical speeds
    within 1% for lightly damped modes (zeta <= 0.08; a single-DOF oscillator's displacement peak
    under unbalance lies ~1.5 zeta^2 above its damped frequency, so heavier damping moves it
    further).  With half the derivative gain every critical is lightly damped and must match."""
    from dataclasses import replace
    from ambhil.loop.scene import load_scene
    sc = load_scene(SCENES.format(name))
    sc = sc.with_controller(kd=sc.controller.kd * kd_scale)
    m = compile_system(sc, rung="modal")
    crit = modal.critical_speeds(m)
    assert len(crit) == 4
    if kd_scale < 1:
        assert all(c.damping_ratio <= 0.08 for c in crit)
    speeds = np.linspace(1.0, 4000.0, 4000)
    res = unbalance.response(m, speeds, nodes=list(m.scene.analysis.output_nodes))
    peaks = [p for j in range(len(res.nodes)) for p, _ in res.peaks(j)]
    for c in crit:
        if c.damping_ratio > 0.08:
            continue
        near = min(peaks, key=lambda p: abs(p - c.speed))
        assert near == pytest.approx(c.speed, rel=0.01), (c.hz, near / 2 / np.pi)


def test_unbalance_full_vs_reduced_and_linear_in_unbalance(m3, m3_modal):
    speeds = np.array([200.0, 330.0, 1400.0, 2270.0])
    a = unbalance.response(m3, speeds, nodes=[20, 29]).x
    b = unbalance.response(m3_modal, speeds, nodes=[20, 29]).x
    np.testing.assert_allclose(np.abs(b), np.abs(a), rtol=0.02)


def test_sensitivity_two_formulas_agree(m3_modal):
    """S_j = 1 - H k_i [Cs Z^-1 Ba]_jj (all loops closed) equals 1/(1 + P_jj H) with P_jj the
    plant seen by loop j when only the other loops are closed."""
    m = m3_modal
    w = 2 * np.pi * np.array([10.0, 50.0, 120.0, 400.0, 2000.0])
    res = sensitivity.sensitivity(m, 1000.0, freqs=w)
    M, C, G, K, Ba, Ca, Cs = m.dense
    h = transfer.evaluate(m.H, 1j * w)
    for j in (0, 3):
        for k, wk in enumerate(w):
            others = np.array([0.0 if a == j else h[k] * m.ki[a] for a in range(m.n_axes)])
            Z = -wk * wk * M + 1j * wk * (C + 1000.0 * G) + K + (Ba * others) @ Cs
            P = Cs[j] @ np.linalg.solve(Z, Ba[:, j] * m.ki[j])
            assert res.S[k, j] == pytest.approx(1 / (1 + P * h[k]), rel=1e-8)


def test_sensitivity_zones():
    assert [sensitivity.zone(p) for p in (1.5, 3.5, 4.5, 6.0)] == ["A", "B", "C", "D"]


def test_paper_trend_third_amb():
    """Paper, Table 2: a third AMB raises both rigid criticals; flexible ones move < 1%."""
    c2 = modal.critical_speeds(compile_system(SCENES.format("2amb")))
    c3 = modal.critical_speeds(compile_system(SCENES.format("3amb")))
    assert [c.kind for c in c2] == ["rigid", "rigid", "flexible", "flexible"]
    assert c3[0].speed > 1.05 * c2[0].speed and c3[1].speed > 1.05 * c2[1].speed
    for a, b in zip(c2[2:], c3[2:]):
        assert abs(b.speed / a.speed - 1) < 0.01


def test_paper_2amb_reproduces_table_2():
    m = compile_system(SCENES.format("2amb"))
    cs = modal.critical_speeds(m)
    np.testing.assert_allclose([c.hz for c in cs], m.scene.analysis.reference_criticals, rtol=0.01)


def test_banded_and_dense_solves_agree(m3):
    rhs = np.random.default_rng(1).standard_normal((3, m3.n)) + 0j
    w = np.array([100.0, 900.0, 3000.0])
    a = dynamic_stiffness.solve(m3, w, 700.0, rhs)
    dense = compile_system(SCENES.format("3amb"))
    object.__setattr__(dense, "M", dense.M)  # same model, solved densely below
    M, C, G, K, Ba, Ca, Cs = m3.dense
    h = transfer.evaluate(m3.H, 1j * w)
    for k, wk in enumerate(w):
        Z = -wk * wk * M + 1j * wk * (C + 700.0 * G) + K + (Ba * (h[k] * m3.ki)) @ Cs
        np.testing.assert_allclose(a[k], np.linalg.solve(Z, rhs[k]), rtol=1e-8, atol=1e-14)


@pytest.mark.parametrize("rung", ["rigid", "modal", "full"])
def test_compiled_model_is_immutable(rung):
    m = compile_system(SCENES.format("2amb"), rung=rung)
    with pytest.raises((ValueError, AttributeError)):
        (m.M.data if hasattr(m.M, "data") and not isinstance(m.M, np.ndarray) else m.M)[0] = 1.0
    with pytest.raises(ValueError):
        m.kx[0] = 0.0
    with pytest.raises(Exception):
        m.rung = "full"
