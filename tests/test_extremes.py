"""Numerical stability at the extremes, detected instabilities, BDF1 hiding an unstable mode."""
import numpy as np
import pytest

from ambhil.loop.analysis import modal
from ambhil.loop.orbits import harmonic
from ambhil.loop.simulation import simulate
from ambhil.loop.numerics import check_numerics
from test_integrator import model


def _kick(m, amp=1e-6):
    q0 = np.zeros(m.n)
    q0[:] = np.linalg.lstsq(np.asarray(m.dense[6]), np.full(m.n_axes, amp), rcond=None)[0]
    return q0


def test_bdf1_numerical_damping_hides_an_unstable_flexible_mode():
    """No structural damping: a 2.7 kHz flexible closed-loop mode is unstable (continuous
    eigenvalue Re > 0; the exact and trapezoidal discrete loops grow).  BDF1 at h = 100 us gives
    it zeta_num ~ w h / 2 ~ 0.86 and the simulation decays: the check must say so."""
    m = model("modal", **{"damping.stiffness_proportional": 0.0})
    ld = modal.least_damped(m, 0.0, 2 * np.pi * 4000)
    assert ld.eigenvalue.real > 0
    rep = check_numerics(m, "bdf1")
    assert rep.stable
    assert any("hides" in w for w in rep.warnings), rep.text()
    assert not check_numerics(m, "zoh").stable and not check_numerics(m, "trapezoidal").stable
    q0 = _kick(m)
    b = simulate(m, 0.3, 0.0, integrator="bdf1", q0=q0, nodes=[21])
    assert b.fault is None and np.max(np.abs(b.y[-100:])) < 1e-3 * np.max(np.abs(b.y))
    t = simulate(m, 1.0, 0.0, integrator="trapezoidal", q0=q0, nodes=[21], stability_check=True)
    assert t.fault is not None and "rotor reached the stator" in t.fault and "at t=" in t.fault
    assert t.instability is not None and "AMB" in t.instability
    # the growth frequency read from the signal equals the discrete loop's eigenvalue, which is the
    # continuous mode seen through the trapezoidal rule's frequency warping (2/h) atan(w h/2)
    f_sig = float(t.instability.split("at ~")[1].split(" Hz")[0])
    f_eig = float(t.instability.split("mode at ")[1].split(" Hz")[0])
    h = 1e-4
    f_warp = (2 / h) * np.arctan(ld.eigenvalue.imag * h / 2) / (2 * np.pi)
    assert f_sig == pytest.approx(f_eig, rel=0.02) and f_eig == pytest.approx(f_warp, rel=0.05)


def test_numerical_damping_warning_for_poorly_damped_modes():
    m = model("modal")
    rep = check_numerics(m, "bdf1")
    assert rep.stable and any("exceeds its physical damping" in w for w in rep.warnings)
    # trapezoidal adds no numerical damping; at h = T_c its frequency warping may move the ~1 kHz
    # mode's decay rate (a line, labelled "numerical error", only beyond the 25 % tolerance), at T_c/8
    # nothing is left
    tr = check_numerics(m, "trapezoidal").warnings
    assert not any("numerical damping zeta_num" in w or w.startswith("numerically damped") for w in tr), tr
    assert all(w.startswith("numerical error") for w in tr)
    assert not check_numerics(m, "trapezoidal", h=1.25e-5).warnings


@pytest.mark.parametrize("h", [1e-6, 1e-5, 1e-4, 1e-3])
def test_steps_from_1us_to_1ms_blow_up_only_when_the_discrete_loop_is_unstable(h):
    """Controller and plant at the same step h (rigid rung): the run is bounded exactly when the
    discrete loop's spectral radius is < 1, and a divergent run is reported with when and where."""
    m = model("rigid", **{"controller.sample_rate": 1.0 / h})
    rep = check_numerics(m, "bdf2", h=h)
    dur = min(2000 * h, 0.5) if h < 1e-4 else 1.0
    r = simulate(m, dur, 350.0, integrator="bdf2", h=h, nodes=[21], record_every=max(1, int(1e-4 / h)))
    if rep.stable:
        assert r.fault is None and np.all(np.isfinite(r.y))
        assert np.max(np.abs(r.y)) < 0.5 * 1.5e-4
    else:
        assert r.fault is not None and r.instability is not None
        assert "at t=" in r.fault


def test_plant_step_1us_under_a_10khz_controller():
    m = model("rigid")
    W = 350.0
    a = simulate(m, 0.4, W, integrator="bdf1", h=1e-6, nodes=[21], record_every=1)
    b = simulate(m, 0.4, W, integrator="zoh", nodes=[21])
    assert a.fault is None and a.meta["ratio"] == 100
    Xa, Xb = harmonic(a.t, a.orbit[:, 0, 0], W), harmonic(b.t, b.orbit[:, 0, 0], W)
    assert abs(Xa - Xb) / abs(Xb) < 5e-4  # BDF1 error ~ W h / 2 per ... tiny at 1 us


def test_4000_rad_s():
    for rung, scheme in (("modal", "bdf2"), ("full", "generalized-alpha")):
        m = model(rung)
        assert check_numerics(m, scheme, speed=4000.0).stable if rung == "modal" else True
        r = simulate(m, 0.3, 4000.0, integrator=scheme, nodes=[21, 30])
        assert r.fault is None and np.all(np.isfinite(r.orbit))
        X = harmonic(r.t, r.orbit[:, 1, 0], 4000.0)
        assert 0 < abs(X) < 1.5e-4


@pytest.mark.parametrize("E", [2.11e13, 2.11e9])
def test_very_stiff_and_very_soft_shafts(E):
    """Stiff (100x) and soft (1/100) shafts: BDF2 and trapezoidal stay bounded where the discrete
    loop is stable, and an unstable loop is reported (growing mode), even before it diverges."""
    m = model("modal", **{"shaft.youngs_modulus": E})
    for scheme in ("bdf2", "trapezoidal"):
        r = simulate(m, 0.3, 300.0, integrator=scheme, nodes=[21, 30], q0=_kick(m), record_every=10,
                     stability_check=True)
        if r.meta["loop_spectral_radius"] < 1:
            assert r.fault is None and r.instability is None and np.all(np.isfinite(r.orbit)), (E, scheme)
        else:  # growing slowly or fast: reported either way, with the growing mode
            assert r.instability is not None and "grows at" in r.instability, (E, scheme)


def test_million_steps_rigid_rung():
    """1e6 controller periods (100 s at 10 kHz) in the fused loop: bounded, and the steady orbit
    at the end equals the one after 0.5 s (no drift)."""
    m = model("rigid")
    W = 350.0
    r = simulate(m, 100.0, W, integrator="trapezoidal", nodes=[21], record_every=10)
    assert r.steps == 1_000_000 and r.fault is None
    short = simulate(m, 0.5, W, integrator="trapezoidal", nodes=[21], record_every=10)
    Xl = harmonic(r.t[-5000:], r.orbit[-5000:, 0, 0], W)
    Xs = harmonic(short.t, short.orbit[:, 0, 0], W)
    assert abs(abs(Xl) / abs(Xs) - 1) < 1e-6
