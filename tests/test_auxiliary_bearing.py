"""Auxiliary-bearing contact law: forces, signs and powers against vector mechanics written out
independently here (cross products of the surface velocities), and the one-line errors of bad input."""
import math

import numpy as np
import pytest

from ambhil.plant import auxiliary_bearing as ab

C, K, RS = 1e-3, 1e8, 0.02


def bearing(validate=True, **kw):
    kw = {"clearance": C, "stiffness": K, "shaft_radius": RS, "damping": 500.0, "friction": 0.3, **kw}
    b = ab.AuxiliaryBearing(**kw)
    return b.validate() if validate else b


def test_no_force_inside_the_clearance():
    out = ab.contact(0.3 * C, -0.5 * C, 1.0, -2.0, 100.0, 0.0, 1.0, bearing().array())
    assert out[4] < 0 and all(v == 0.0 for i, v in enumerate(out) if i != 4)


def test_linear_normal_force_pushes_the_shaft_back_to_the_centre():
    d = 2e-6
    b = bearing(damping=0.0, friction=0.0)
    fx, fy, fn, ft, dd, *_ = ab.contact(0.0, -(C + d), 0.0, 0.0, 0.0, 0.0, 0.0, b.array())
    assert dd == pytest.approx(d, rel=1e-6) and fn == pytest.approx(K * d, rel=1e-6)
    assert fx == pytest.approx(0.0, abs=1e-9) and fy == pytest.approx(K * d, rel=1e-6)  # at the bottom: up


def test_dashpot_never_pulls_and_its_dissipation_stays_positive():
    d, vout = 1e-6, -10.0  # leaving fast: k d + c d' < 0
    b = bearing()
    fx, fy, fn, ft, dd, tsh, tra, pf, pdmp = ab.contact(C + d, 0.0, vout, 0.0, 0.0, 0.0, 1.0, b.array())
    assert K * d + 500.0 * vout < 0
    assert fn == 0.0 and fx == 0.0 and fy == 0.0
    assert pdmp == pytest.approx(-K * d * vout) and pdmp > 0  # the spring's energy is lost, not returned


def test_hertz_force_is_continuous_at_first_touch_and_damps_by_the_impact_speed():
    b = bearing(exponent=1.5, damping=None, restitution=0.8, friction=0.0, stiffness=1e10)
    p = b.array()
    assert ab.contact(C + 1e-15, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, p)[2] < 1e-10  # no jump at d = 0
    d, v0 = 1e-6, 0.5
    fn_in = ab.contact(C + d, 0.0, v0, 0.0, 0.0, 0.0, v0, p)[2]
    assert fn_in == pytest.approx(1e10 * d ** 1.5 * (1 + 0.75 * (1 - 0.64)), rel=1e-12)
    assert b.elastic_energy(d) == pytest.approx(1e10 * d ** 2.5 / 2.5)


def _vector_reference(x, y, vx, vy, om, wr, b):
    """Slip velocity, friction torques and power from 3-D vectors: shaft surface point velocity
    v + Omega z x (R_s n), race point velocity w z x (R_i n)."""
    z = np.array([0.0, 0.0, 1.0])
    r = math.hypot(x, y)
    n = np.array([x / r, y / r, 0.0])
    t = np.cross(z, n)
    v_shaft = np.array([vx, vy, 0.0]) + np.cross(om * z, RS * n)
    v_race = np.cross(wr * z, b.race_r * n)
    return float((v_shaft - v_race) @ t), n, t, v_shaft, v_race


@pytest.mark.parametrize("seed", range(6))
def test_slip_velocity_torques_and_friction_power_match_vector_mechanics(seed):
    rng = np.random.default_rng(seed)
    b = bearing(race_inertia=1e-3, slip_velocity=0.5)  # a wide tanh so v_rel can be read back
    ang = rng.uniform(-math.pi, math.pi)
    r = C + rng.uniform(1e-7, 1e-5)
    x, y = r * math.cos(ang), r * math.sin(ang)
    vx, vy, om, wr = rng.normal(0, 0.2), rng.normal(0, 0.2), rng.normal(0, 10), rng.normal(0, 10)
    fx, fy, fn, ft, d, tsh, tra, pf, pdmp = ab.contact(x, y, vx, vy, om, wr, 1.0, b.array())
    v_rel, n, t, v_shaft, v_race = _vector_reference(x, y, vx, vy, om, wr, b)
    assert fn > 0
    assert ft == pytest.approx(-0.3 * fn * math.tanh(v_rel / 0.5), rel=1e-9)  # opposes the slip
    f = np.array([fx, fy, 0.0])
    assert f == pytest.approx(-fn * n + ft * t, rel=1e-9, abs=1e-9 * fn)
    f_t = ft * t  # friction on the shaft at its surface point R_s n; its reaction on the race at R_i n
    assert tsh == pytest.approx(np.cross(RS * n, f_t)[2], rel=1e-9)
    assert tra == pytest.approx(np.cross(b.race_r * n, -f_t)[2], rel=1e-9)
    assert pf == pytest.approx(-(f_t @ v_shaft + (-f_t) @ v_race), rel=1e-9) and pf >= 0


def test_defaults_held_race_and_race_radius():
    b = bearing()
    p = b.array()
    assert p[ab.A_RI] == pytest.approx(RS + C) and p[ab.A_JI] == 0.0 and p[ab.A_CC] == 500.0
    assert ab.race_drag_torque(3.0, bearing(race_inertia=1e-3, race_drag=0.2).array()) == pytest.approx(-0.6)


def test_contact_time_of_the_linear_law_is_the_undamped_half_period():
    assert bearing().contact_time(10.0, 0.3) == pytest.approx(math.pi * math.sqrt(10.0 / K))


@pytest.mark.parametrize("key, value, why", [
    ("clearance", 0.0, "must be > 0"),
    ("stiffness", -1e8, "must be > 0"),
    ("shaft_radius", -0.01, "must be > 0"),
    ("exponent", 0.5, "must be in 1..2"),
    ("damping", -1.0, "must be >= 0"),
    ("friction", 1.5, "must be in 0..1"),
    ("friction", -0.1, "must be in 0..1"),
    ("slip_velocity", 0.0, "must be > 0"),
    ("race_radius", 0.01, "must be > shaft_radius"),
    ("race_inertia", 0.0, "must be > 0"),
    ("race_drag", -1.0, "must be >= 0"),
    ("impact_speed_floor", 0.0, "must be > 0"),
    ("stiffness", float("nan"), "finite number"),
    ("friction", True, "finite number"),
])
def test_each_bad_value_is_a_one_line_error_naming_its_key(key, value, why):
    with pytest.raises(ValueError) as e:
        bearing(False, **{key: value}).validate("[[amb]] A auxiliary")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"[[amb]] A auxiliary.{key} = ") and why in msg


def test_restitution_and_damping_belong_to_their_own_law():
    with pytest.raises(ValueError, match=r"^aux\.restitution = 1\.5: must be in \(0, 1\]"):
        bearing(False, exponent=1.5, damping=None, restitution=1.5).validate("aux")
    with pytest.raises(ValueError, match=r"^aux\.restitution = 0\.8: is the Hertz law's e"):
        bearing(False, restitution=0.8).validate("aux")
    with pytest.raises(ValueError, match=r"^aux\.damping = 500\.0: is the linear law's c_c"):
        bearing(False, exponent=1.5).validate("aux")
