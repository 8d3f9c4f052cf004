"""Point-mass (Jeffcott) rotor dropped into an auxiliary bearing, against closed forms derived here:
free fall, the clamped spring-dashpot impact, Hunt-Crossley restitution, the energy balance, the
rebound height's convergence with the solver tolerance, backward whirl at the rolling speed and the
rolling pendulum of a free race."""
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from ambhil.plant.auxiliary_bearing import AuxiliaryBearing
from ambhil.plant.point_rotor import OM, WR, X, Y, PointRotor, drop, whirl

C, M, K, G, RS = 1e-3, 10.0, 1e8, 9.81, 0.01


def linear(z=0.1, **kw):
    return AuxiliaryBearing(clearance=C, stiffness=K, shaft_radius=RS, damping=2 * z * math.sqrt(K * M),
                            friction=kw.pop("friction", 0.0), **kw)


def test_free_fall_first_contact_at_sqrt_2c_over_g():
    res = drop(PointRotor(mass=M, bearing=linear()), 0.02, rtol=1e-10)
    assert res.events[0].start == pytest.approx(math.sqrt(2 * C / G), rel=1e-9, abs=0)
    assert res.events[0].v0 == pytest.approx(math.sqrt(2 * G * C), rel=1e-8)


def clamped_impact(z, v0):
    """Spring-dashpot impact without gravity, force clamped at F_n >= 0.  d = v0/w_d e^(-z w t) sin(w_d t)
    gives F_n = k d + c d' proportional to (1 - 2 z^2) sin th + 2 z sqrt(1 - z^2) cos th, th = w_d t: it
    reaches 0 at th_s = pi - atan2(2 z sqrt(1 - z^2), 1 - 2 z^2), before d = 0 (th = pi).  The shaft then
    flies free at the separation speed and crosses d = 0 after d_s / v_s more."""
    w = math.sqrt(K / M)
    s = math.sqrt(1 - z * z)
    wd = w * s
    th = math.pi - math.atan2(2 * z * s, 1 - 2 * z * z)
    ts = th / wd
    decay = math.exp(-z * w * ts)
    d_s = v0 / wd * decay * math.sin(th)
    v_s = -v0 * decay * (math.cos(th) - z / s * math.sin(th))
    return ts + d_s / v_s, v_s / v0, math.pi / wd, math.exp(-math.pi * z / s)


@pytest.mark.parametrize("z", [0.02, 0.1, 0.3])
def test_linear_impact_duration_and_restitution_match_the_clamped_closed_form(z):
    v0 = 0.2
    res = drop(PointRotor(mass=M, bearing=linear(z), gravity=0.0), 0.01, x0=(0.0, -(C - 1e-6), 0.0, -v0),
               rtol=1e-10)
    ev = res.events[0]
    duration, e, half_period, e_free = clamped_impact(z, v0)
    assert ev.v0 == pytest.approx(v0, rel=1e-9)
    assert ev.end - ev.start == pytest.approx(duration, rel=1e-8)  # measured 1e-11..1e-10
    assert ev.restitution == pytest.approx(e, rel=1e-8)
    # the textbook figures assume the dashpot may pull (separation at d = 0): the clamp ends the force a
    # little earlier and keeps a little more speed; both differences are small for light damping
    assert abs(duration / half_period - 1) < 1.2 * z and 0 <= e - e_free < 0.3 * z
    assert ev.energy_lost == pytest.approx(0.5 * M * v0 ** 2 * (1 - e ** 2), rel=1e-6)


@pytest.mark.parametrize("e", [0.8, 0.9, 0.95, 1.0])
def test_hunt_crossley_restitution_is_the_one_given(e):
    """Lankarani-Nikravesh's damping factor is derived from the hysteresis loop along the undamped path,
    so the restitution it produces differs from e by a second-order term: within 1.5 (1 - e)^2."""
    b = AuxiliaryBearing(clearance=C, stiffness=1e10, exponent=1.5, restitution=e, shaft_radius=RS, friction=0.0)
    res = drop(PointRotor(mass=M, bearing=b, gravity=0.0), 0.01, x0=(0.0, -(C - 1e-6), 0.0, -1.0), rtol=1e-10)
    ev = res.events[0]
    assert ev.restitution == pytest.approx(e, abs=1.5 * (1 - e) ** 2 + 1e-7)
    if e == 1.0:  # elastic Hertz impact: the duration is the closed form 2.943 d_max / v0
        assert ev.end - ev.start == pytest.approx(b.contact_time(M, 1.0), rel=1e-6)


def test_energy_balance_over_many_bounces_with_friction_spin_down_and_a_free_race():
    b = linear(0.05, friction=0.3, race_inertia=2e-4, race_drag=1e-3)
    rotor = PointRotor(mass=M, bearing=b, k_shaft=1e4, c_shaft=5.0, spin=30.0, polar_inertia=0.02,
                       spin_drag=1e-3)
    res = drop(rotor, 0.25, rtol=1e-10)
    assert len(res.events) >= 5
    assert res.y[OM, -1] < 30.0 and res.y[WR, -1] > 0  # the shaft spun down, the race up
    assert res.energy_error() <= 1e-6


def rebound_apex(z, v0):
    """Apex of the first rebound under gravity (closed form): in contact d = -y - c obeys
    m d'' + c d' + k d = m g; with u = d - d_st (d_st = m g / k), u = e^(-z w t)(A cos + B sin)(w_d t),
    u(0) = -d_st, u'(0) = v0; separation where k d + c d' = 0 (root found), then a vertical throw."""
    w = math.sqrt(K / M)
    wd = w * math.sqrt(1 - z * z)
    dst = M * G / K
    A = -dst
    B = (v0 + z * w * A) / wd

    def d(t):
        return dst + math.exp(-z * w * t) * (A * math.cos(wd * t) + B * math.sin(wd * t))

    def dd(t):
        e = math.exp(-z * w * t)
        return e * ((-z * w * A + wd * B) * math.cos(wd * t) + (-z * w * B - wd * A) * math.sin(wd * t))

    f = lambda t: K * d(t) + 2 * z * math.sqrt(K * M) * dd(t)
    ts = brentq(f, 0.5 * math.pi / wd, 1.5 * math.pi / wd, xtol=1e-16)
    return -(C + d(ts)) + dd(ts) ** 2 / (2 * G)


def test_rebound_height_converges_with_the_solver_tolerance_to_the_closed_form():
    z = 0.1
    exact = rebound_apex(z, math.sqrt(2 * G * C))
    err = []
    for rtol in (1e-6, 1e-8, 1e-10):
        res = drop(PointRotor(mass=M, bearing=linear(z)), 0.045, rtol=rtol)
        ev = res.events[0]
        t2 = res.events[1].start
        tt = np.linspace(ev.end, t2, 4001)
        err.append(abs(res.sample(tt)[Y].max() - exact))
    assert err[2] < err[1] < err[0]  # measured 6e-9, 1.7e-10, 3e-13 m
    assert err[2] < 1e-8 * C and err[0] < 1e-4 * C


def test_high_friction_on_a_held_race_goes_into_backward_whirl_at_the_rolling_speed():
    """Race held, rolling without slip: the shaft surface at the contact point is at rest,
    r phi' + R_s Omega = 0, so the centre orbits at phi' = -R_s Omega / r (r = c + penetration)."""
    om = 20.0
    res = drop(PointRotor(mass=M, bearing=linear(0.05, friction=0.6), spin=om), 0.5)
    wh = whirl(res)
    assert wh.name == "backward whirl" and wh.full_clearance and wh.direction == -1
    tt = np.linspace(0.4, 0.5, 2001)
    r = np.hypot(*res.sample(tt)[[X, Y]]).mean()
    assert wh.frequency == pytest.approx(-RS * om / r, rel=5e-4)  # measured 2.6e-5
    assert wh.frequency == pytest.approx(-RS * om / C, rel=1e-2)


def test_low_friction_on_a_held_race_bounces_without_whirl():
    res = drop(PointRotor(mass=M, bearing=linear(0.05, friction=0.3), spin=20.0), 0.3)
    assert whirl(res).name == "no full-clearance whirl"


def test_a_free_race_rolls_with_the_shaft_and_rocks_as_a_rolling_pendulum():
    """A light free race takes the shaft's surface speed instead of driving a whirl.  Rolling without
    slip, R_i w = R_s Omega + r phi', so the race's inertia adds J_i (r/R_i)^2 to the rocking
    pendulum: w_p^2 = g / (r (1 + J_i / (m R_i^2))) (small swings; +theta0^2/16 on the period)."""
    ji, om = 1e-4, 20.0
    b = linear(0.05, friction=0.6, race_inertia=ji)
    res = drop(PointRotor(mass=M, bearing=b, spin=om), 0.6)
    assert whirl(res).name == "no full-clearance whirl"
    tt = np.linspace(0.3, 0.6, 30001)
    s = res.sample(tt)
    r = np.hypot(s[X], s[Y])
    phi_dot = (s[X] * s[3] - s[Y] * s[2]) / r ** 2
    slip = r * phi_dot + RS * om - b.race_r * s[WR]
    assert np.all(r > C) and np.max(np.abs(slip)) < 2e-3 * RS * om  # rolls: slip of order v_s tanh^-1
    theta = np.arctan2(s[X], -s[Y])
    up = tt[1:][(theta[:-1] < 0) & (theta[1:] >= 0)]
    period = np.diff(up).mean()
    th0 = np.abs(theta).max()
    wp = math.sqrt(G / (r.mean() * (1 + ji / (M * b.race_r ** 2))))
    assert period == pytest.approx(2 * math.pi / wp * (1 + th0 ** 2 / 16), rel=2e-3)


def test_whirl_detector_names_a_forward_whirl():
    """No friction, started rolling round the clearance with the spin: orbits forward at about v / r
    (gravity slows it on the way up: v^2 drops by 4 g c / v^2 = 16% at the top)."""
    v = 0.5
    res = drop(PointRotor(mass=M, bearing=linear(0.05), spin=20.0), 0.1,
               x0=(0.0, -(C + M * v ** 2 / C / K), v, 0.0))
    wh = whirl(res)
    assert wh.name == "forward whirl" and wh.direction == 1
    assert wh.frequency == pytest.approx(v / C, rel=0.1)
