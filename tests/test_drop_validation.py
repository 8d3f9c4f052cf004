"""Rotor drop on the FE plant against a second method (issue 32, item 5).

The FE plant's rigid rung, a rotor symmetric about its mid-span (1 m x 50 mm shaft, a 4.9 kg disc at
mid-span, AMBs at nodes 3 and 19), every AMB axis lost at t = 0 under gravity: translation decouples
from tilt and each auxiliary bearing carries half the rotor, so each station is the point (Jeffcott)
rotor of plant/point_rotor.py with the station's mass (10.12 kg), integrated independently (LSODA,
event location, rtol 1e-10).  Compared: the first bounce's impact time and speed, peak force,
duration, restitution and rebound apex (loop/study_drop.first_bounce), for linear (elastic, damped)
and Hertz contact, per integrator, with tolerances that shrink with the step; the backward whirl
of a held race; the energy balance.

These checks found that the trapezoidal step (bdf2's restart) left the contact force at t_n out of
its explicit half (a contact then acted with half its force: peak and duration +43 %); fixed in
plant/integrator.py (``_add_contact_state``).  Self-convergence alone did not show it: only the
second method did.
"""
import math
from dataclasses import replace

import numpy as np
import pytest

from helpers import scene
from ambhil.loop import study_drop as sd
from ambhil.plant import integrator as ig
from ambhil.plant.auxiliary_bearing import AuxiliaryBearing
from ambhil.plant.model import compile_model
from ambhil.plant.point_rotor import PointRotor, drop, whirl

C, RS, KC = 2.5e-4, 0.025, 1e8
AMB = dict(gap=5e-4, bias_current=2.0, turns=200, pole_area=6e-4)
LAWS = {"elastic": dict(stiffness=KC, damping=0.0),
        "linear": dict(stiffness=KC, damping=2 * 0.1 * math.sqrt(KC * 10.12)),  # damping ratio 0.1
        "hertz": dict(stiffness=2e11, exponent=1.5, restitution=0.9)}
SECOND = ("bdf2", "trapezoidal", "generalized-alpha")
BOUNCE = ("peak_force", "duration", "restitution", "apex")


def levitated(aux: AuxiliaryBearing, speed: float = 0.0, rung: str = "rigid"):
    """The compiled model, AMBs on (the operating point under gravity)."""
    sc = scene(model={"rung": rung, "gravity": 9.81},
               amb=[dict(name="A", node=3, **AMB), dict(name="B", node=19, **AMB)],
               disc=[dict(name="d", node=11, mass=4.9, polar_inertia=0.0245, diametral_inertia=0.0124)],
               speed={"value": speed})
    spec = replace(sc.plant, ambs=tuple(replace(a, auxiliary=aux) for a in sc.plant.ambs))
    return compile_model(spec, period=1e-4)


def model(aux: AuxiliaryBearing, speed: float = 0.0, rung: str = "rigid"):
    """The same with every AMB axis lost: the drop."""
    return sd.drop_model(levitated(aux, speed, rung))


def bearing(law: str, friction: float = 0.0):
    return AuxiliaryBearing(clearance=C, shaft_radius=RS, friction=friction, **LAWS[law])


def test_the_symmetric_rotor_is_two_point_rotors():
    m = model(bearing("elastic"))
    assert sd.station_mass(m, 0) == pytest.approx(sd.station_mass(m, 1), rel=1e-12)
    assert sd.station_mass(m, 0) == pytest.approx(10.117, abs=1e-3)
    g = -m.f_const[1] / sd.station_mass(m, 0)
    assert g == pytest.approx(9.81, rel=1e-9)  # the weight share each AMB carried drops onto its station
    rec = sd.run_drop(m, "generalized-alpha", 1e-5, 0.02)
    a, b = sd.first_bounce(rec, 0), sd.first_bounce(rec, 1)
    for f in sd.FIGURES:
        assert a[f] == pytest.approx(b[f], rel=1e-9)


# per figure, relative error bound at h = 5 us (t_c / 200 linear, t_c / 85 Hertz); measured in brackets
BDF1_TOL = dict(t_impact=1e-3, v_impact=3e-3, peak_force=0.05, duration=0.02, restitution=0.1, apex=0.15)


@pytest.mark.parametrize("law", list(LAWS))
@pytest.mark.parametrize("scheme", ["bdf1", *SECOND])
def test_first_bounce_matches_the_point_rotor_and_converges(scheme, law):
    """bdf1: first order (errors at 5 us: impact time 3.5e-4, restitution 2-6 %, apex 5-12 %).
    Second order schemes: impact time and speed exact to 1e-5 (trapezoidal and bdf2 integrate the
    free fall exactly); the bounce within 1e-3 for the elastic and Hertz laws, the errors / 8 or more
    over two halvings (observed order >= 1.5; measured 13-21 x).  The damped linear law's force jumps
    by c v0 at a contact start inside a step: first order for every fixed-step scheme (1.5e-3 .. 3e-3
    at 5 us, halving with h)."""
    m = model(bearing(law))
    ref = sd.point_reference(m, 0)
    err = {}
    for h in (2e-5, 5e-6):
        fb = sd.first_bounce(sd.run_drop(m, scheme, h, 0.05))
        err[h] = {f: abs(fb[f] - ref[f]) / abs(ref[f]) for f in sd.FIGURES}
    e = err[5e-6]
    s0, s1 = sum(err[2e-5][f] for f in BOUNCE), sum(e[f] for f in BOUNCE)
    if scheme == "bdf1":
        for f, tol in BDF1_TOL.items():
            assert e[f] < tol, f
        assert s1 < s0 / 2.5  # first order: 4 x over two halvings
        return
    assert e["t_impact"] < 1e-5 and e["v_impact"] < 1e-5
    if law == "linear":
        assert max(e[f] for f in BOUNCE) < 5e-3
        assert s1 < s0 / 2.5
    else:
        assert max(e[f] for f in BOUNCE) < 1e-3
        assert s1 < s0 / 8


@pytest.mark.parametrize("scheme, order", [("trapezoidal", 2), ("generalized-alpha", 2), ("bdf1", 1)])
def test_momentum_the_first_impact_takes_matches_the_point_rotor(scheme, order):
    """Momentum bookkeeping: the normal impulse booked over the first contact (C_IMP) equals the
    momentum the point rotor's bearing takes, m v0 (1 + e) + m g t_c (gravity acts during the
    contact too); measured 2.0e-4 / 7.2e-6 (trapezoidal), 2.1e-4 / 2.4e-5 (generalized-alpha),
    -4.6e-2 / -1.2e-2 (bdf1) at 20 / 5 us."""
    m = model(bearing("elastic"))
    ref = sd.point_reference(m, 0)
    ms = sd.station_mass(m, 0)
    J = ms * ref["v_impact"] * (1 + ref["restitution"]) + ms * ref["gravity"] * ref["duration"]
    err = [sd.run_drop(m, scheme, h, 0.05, stop_after=1).contact[0, ig.C_IMP] / J - 1 for h in (2e-5, 5e-6)]
    assert abs(err[1]) < (5e-5 if order == 2 else 2e-2) and abs(err[1]) < abs(err[0]) / (2.5 if order == 1 else 6)


def test_bdf1_loses_energy_at_every_impact_and_less_with_a_smaller_step():
    """bdf1's numerical damping shows as a restitution below the elastic law's 1 (measured 0.958 at
    10 us, 0.976 at 5 us)."""
    m = model(bearing("elastic"))
    e = [sd.first_bounce(sd.run_drop(m, "bdf1", h, 0.05))["restitution"] for h in (1e-5, 5e-6)]
    assert e[0] < e[1] < 1.0 and 1 - e[1] == pytest.approx((1 - e[0]) / 2, rel=0.3)


def energy_error(scheme, h, law, friction=0.0, speed=0.0):
    m = model(bearing(law, friction), speed)
    rec = sd.run_drop(m, scheme, h, 0.05, speed, energy=True, stop_after=None)
    c = rec.contact
    lost = c[:, ig.C_EF].sum() + c[:, ig.C_ED].sum() - rec.drive[-1]
    scale = -2 * m.f_const[1] * C  # the weight times the clearance: the energy of the drop
    return rec, lost, scale


def test_trapezoidal_elastic_drop_conserves_energy_to_second_order():
    """No damping, no friction: 1/2 v'Mv + 1/2 q'Kq - f0.(Ca q) + the contact springs' energy stays
    constant over three bounces within 1e-4 of m g c at 5 us (measured 6.3e-5; 7.6e-4 at 20 us)."""
    dev = []
    for h in (2e-5, 5e-6):
        rec, lost, scale = energy_error("trapezoidal", h, "elastic")
        assert rec.contact[0, ig.C_NEV] >= 3 and lost == 0.0
        dev.append(np.max(np.abs(rec.energy - rec.energy[0])) / scale)
    assert dev[1] < 1e-4 and dev[1] < dev[0] / 8


@pytest.mark.parametrize("scheme, law", [("trapezoidal", "linear"),
                                         ("trapezoidal", "hertz"),
                                         ("generalized-alpha", "hertz")])
def test_energy_lost_equals_the_recorded_friction_and_damping_work(scheme, law):
    """Contact damping and friction (mu 0.3, spin 5 rad/s held by the drive, race held):
    E0 - E = C_EF + C_ED - W_drive (the drive's work against the friction torque, booked like C_EF)
    within 1e-3 of C_EF + C_ED at 5 us, shrinking with h (trapezoidal, linear: 1.2e-4, 2.9e-5, 3.6e-6
    at 20, 10, 5 us; generalised-alpha, Hertz: 8.9e-4, 2.8e-4, 6.3e-5)."""
    bal = []
    for h in (2e-5, 5e-6):
        rec, lost, scale = energy_error(scheme, h, law, friction=0.3, speed=5.0)
        dis = rec.contact[:, ig.C_EF].sum() + rec.contact[:, ig.C_ED].sum()
        bal.append(abs(rec.energy[-1] - rec.energy[0] + lost) / dis)
    assert bal[1] < 1e-3 and bal[1] < bal[0] / 4


@pytest.mark.parametrize("scheme", ["generalized-alpha", "bdf2"])
def test_held_race_backward_whirl_matches_the_point_rotor(scheme):
    """mu 0.6, spin 5 rad/s, race held: both methods roll into backward whirl at -R_s Omega / r
    (r = c + the whirl's penetration): point rotor -487.95 rad/s; FE plant within 2e-5 at 10 us
    (generalised-alpha -487.950, bdf2 -487.948 with the fix; -487.02 without)."""
    om = 5.0
    aux = AuxiliaryBearing(clearance=C, stiffness=KC, shaft_radius=RS, damping=2 * 0.05 * math.sqrt(KC * 10.1),
                           friction=0.6)
    m = model(aux, om)
    ms = sd.station_mass(m)
    ref = whirl(drop(PointRotor(mass=ms, bearing=aux, gravity=-m.f_const[1] / ms, spin=om), 0.3))
    assert ref.name == "backward whirl" and ref.frequency == pytest.approx(-RS * om / C, rel=0.03)
    rec = sd.run_drop(m, scheme, 1e-5, 0.3, om, stop_after=None)
    for j in (0, 1):
        fe = sd.orbit_whirl(rec, om, j)
        assert fe["name"] == "backward whirl" and fe["direction"] == -1 and fe["full_clearance"]
        assert fe["frequency"] == pytest.approx(ref.frequency, rel=2e-5)


def test_low_friction_bounces_without_whirl_in_both_methods():
    om = 5.0
    aux = AuxiliaryBearing(clearance=C, stiffness=KC, shaft_radius=RS, damping=2 * 0.05 * math.sqrt(KC * 10.1),
                           friction=0.1)
    m = model(aux, om)
    ms = sd.station_mass(m)
    ref = whirl(drop(PointRotor(mass=ms, bearing=aux, gravity=-m.f_const[1] / ms, spin=om), 0.3))
    rec = sd.run_drop(m, "generalized-alpha", 1e-5, 0.3, om, stop_after=None)
    assert ref.name == sd.orbit_whirl(rec, om)["name"] == "no full-clearance whirl"


def test_drop_convergence_grid_reports_the_observed_order():
    """The accuracy study's drop section (Dask grid, in-process cluster)."""
    rows, info = sd.drop_convergence(levitated(bearing("hertz")), schemes=("bdf1", "generalized-alpha"), steps=(2e-5, 1e-5, 5e-6),
                                     speed=0.0)
    order = {(r.integrator, r.figure): r.order for r in rows}
    assert 0.8 < order[("bdf1", "restitution")] < 1.3
    assert order[("generalized-alpha", "duration")] > 1.6
    assert info["point_rotor"]["mass"] == pytest.approx(10.117, abs=1e-3)
    assert "observed order" in sd.table(rows, info)


def test_a_bearing_too_soft_lets_the_rotor_reach_the_stator_and_the_run_says_so(tmp_path):
    """The run ends only at a real limit: with auxiliary bearings 1e4 times too soft (1e4 N/m: the
    weight share would need 10 mm) the shaft passes the clearance and reaches the magnetic gap; the
    fault names the AMB, the axis and that it went through its auxiliary bearing."""
    from pathlib import Path
    from ambhil.loop.scene import load_scene
    from ambhil.loop.simulation import simulate
    from ambhil.loop.system import compile_system
    txt = (Path(__file__).parents[1] / "scenes" / "rotor_drop.toml").read_text()
    assert txt.count("stiffness = 1e8") == 2
    f = tmp_path / "soft.toml"
    f.write_text(txt.replace("stiffness = 1e8", "stiffness = 1e4").replace("damping = 1e4", "damping = 10.0"))
    res = simulate(compile_system(load_scene(f)), 0.12)
    assert res.fault is not None and res.fault.startswith("rotor reached the stator"), res.fault
    assert "axis y, through its auxiliary bearing" in res.fault and res.steps < 1200
    assert res.contact["summary"]["A"]["events"] >= 1


@pytest.mark.parametrize("mu, whirls", [(0.29, False), (0.32, True)])
def test_whirl_onset_in_friction_agrees_with_the_point_rotor(mu, whirls):
    """The onset of backward whirl (held race, 5 rad/s, dropped from the centre): both methods
    bounce at mu <= 0.302 and roll into full-clearance backward whirl at mu >= 0.305 (measured on
    a grid of 0.2 .. 0.5; no published criterion was at hand to check against, docs/contact.md).
    Checked 4 % either side of that onset."""
    om = 5.0
    aux = AuxiliaryBearing(clearance=C, stiffness=KC, shaft_radius=RS, damping=2 * 0.05 * math.sqrt(KC * 10.1),
                           friction=mu)
    m = model(aux, om)
    ms = sd.station_mass(m)
    ref = whirl(drop(PointRotor(mass=ms, bearing=aux, gravity=-m.f_const[1] / ms, spin=om), 0.3))
    fe = sd.orbit_whirl(sd.run_drop(m, "generalized-alpha", 1e-5, 0.3, om, stop_after=None), om, 0)
    name = "backward whirl" if whirls else "no full-clearance whirl"
    assert ref.name == fe["name"] == name, (ref.name, fe["name"])
