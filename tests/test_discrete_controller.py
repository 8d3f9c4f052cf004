"""Discrete controller vs the continuous current law (controller/transfer.py)."""
import numpy as np
import pytest

from ambhil.controller import discrete as dc
from ambhil.loop.system import controller_runner
from ambhil.controller.transfer import current_law, evaluate
from test_integrator import scene, model


def _sine_response(runner, f, amp=1e-6, periods=40):
    """Steady-state complex gain of i/y by driving the runner with a sampled sinusoid (DFT)."""
    T = runner.period
    w = 2 * np.pi * f
    n_per = int(round(1 / (f * T)))
    N = n_per * periods
    k = np.arange(N)
    y = amp * np.cos(w * k * T)
    out = np.array([runner.step(np.full(runner.n_axes, yy))[0] for yy in y])
    sl = slice(N // 2, N)
    e = np.exp(-1j * w * k[sl] * T)
    return (out[sl] @ e) / (y[sl] @ e)


@pytest.mark.parametrize("method", ["tustin", "zoh"])
def test_low_frequency_response_matches_continuous(method):
    s = scene()
    p = dc.discretise(s.controller, method=method)
    H = current_law(s.controller)
    T = 1 / s.controller.sample_rate
    f = np.array([1.0, 5.0, 20.0, 60.0])
    Hd = dc.frequency_response(p, 2 * np.pi * f, T)
    Hc = evaluate(H, 2j * np.pi * f)
    err = np.abs(Hd / Hc - 1)
    if method == "tustin":
        # Tustin: error O((w T)^2) -- below 0.2 % up to 60 Hz at 10 kHz
        assert np.all(err < 2e-3), err
    else:
        # per-block zoh: each strictly proper block (sensor, amplifier) gains ~ one sample of lag,
        # so the error is O(w T) with a large constant: ~ 3 samples of delay in all
        assert np.all(err < 2 * np.pi * f * 6 * T), err  # (integrator too: ~3-4 samples in all)
        assert err[0] < 2e-3


def test_tustin_is_exactly_the_warped_continuous_law():
    s = scene()
    p = dc.discretise(s.controller, method="tustin")
    H = current_law(s.controller)
    T = 1 / s.controller.sample_rate
    w = 2 * np.pi * np.array([10.0, 300.0, 1000.0, 3000.0, 4500.0])
    Hd = dc.frequency_response(p, w, T)
    Hw = evaluate(H, 1j * (2 / T) * np.tan(w * T / 2))
    assert np.allclose(Hd, Hw, rtol=1e-9)
    # and the warping is real: unwarped comparison is off by percents at 3 kHz
    assert abs(Hd[3] / evaluate(H, 1j * w[3])[0] - 1) > 0.05


@pytest.mark.parametrize("method", ["tustin", "zoh"])
def test_step_function_realises_its_frequency_response(method):
    """Second method: simulate the kernel with a sinusoid and compare with H_d(e^{iwT})."""
    m = model()
    r = controller_runner(m, method=method)
    for f in (20.0, 400.0):
        r.reset()
        g = _sine_response(r, f)
        Hd = dc.frequency_response(r.params, np.array([2 * np.pi * f]), r.period)[0]
        assert g == pytest.approx(-Hd, rel=1e-6)


def test_pure_delay_of_n_samples():
    m0 = model()
    m3 = model(**{"controller.delay_samples": 3})
    r0, r3 = controller_runner(m0), controller_runner(m3)
    rng = np.random.default_rng(0)
    ys = 1e-6 * rng.standard_normal((30, m0.n_axes))
    o0 = np.array([r0.step(y) for y in ys])
    o3 = np.array([r3.step(y) for y in ys])
    assert np.array_equal(o3[3:], o0[:-3])
    assert np.all(o3[:3] == 0.0)


def test_pure_step_does_not_modify_its_input():
    m = model()
    r = controller_runner(m)
    x0 = r.state.copy()
    x1, i1 = dc.step(r.params, x0, np.full(m.n_axes, 1e-6))
    assert np.array_equal(x0, r.state) and not np.array_equal(x1, x0)
    assert np.array_equal(i1, r.step(np.full(m.n_axes, 1e-6)))


def _hold_and_release(anti_windup):
    m = model(**{"controller.anti_windup": anti_windup, "amplifier.current_limit": 0.5})
    r = controller_runner(m)
    big = np.full(m.n_axes, 1e-4)  # 100 um: far beyond the current limit
    out = [r.step(big) for _ in range(3000)]
    integ = r.state[1]
    after = [r.step(np.zeros(m.n_axes)) for _ in range(3000)]
    return np.array(out), integ, np.array(after), r


def test_current_saturation_and_anti_windup():
    out, integ_aw, after_aw, r = _hold_and_release(True)
    assert np.max(np.abs(out)) <= 0.5 + 1e-15
    assert r.saturated == 0
    out2, integ_nw, after_nw, _ = _hold_and_release(False)
    assert np.max(np.abs(out2)) <= 0.5 + 1e-15
    # without anti-windup the integrator keeps integrating through the saturation
    assert abs(integ_nw) > 10 * abs(integ_aw)
    # ... and the output stays saturated long after the error is gone; with clamping it recovers
    sat_nw = np.sum(np.abs(after_nw[:, 0]) >= 0.5 - 1e-12)
    sat_aw = np.sum(np.abs(after_aw[:, 0]) >= 0.5 - 1e-12)
    assert sat_aw < 5 and sat_nw > 100


def test_misaligned_controller_starts_at_the_operating_current():
    m = model(**{"amb.misalignment": [5e-5, 0.0]})
    assert abs(m.i_op[0]) > 0.1
    r = controller_runner(m)
    for _ in range(100):
        i = r.step(np.zeros(m.n_axes))
    assert np.allclose(i, m.i_op, rtol=1e-9, atol=1e-12)
