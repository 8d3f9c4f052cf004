"""Contact results of a run with auxiliary bearings (loop/contact_results.py, loop/contact_plots.py)
against synthetic orbits whose answers are known by construction: whirl direction, ratio and the
full-clearance name; bouncing and resting rotors not called whirl; noise; peak force,
penetration and energies; re-levitation time."""
import math

import numpy as np
import pytest

from ambhil.loop.contact_plots import plot_contact
from ambhil.loop.contact_results import analyse, relevitation, return_time, whirl_ratio_series
from ambhil.loop.sim_result import SimResult

C, KC, W = 250e-6, 1e8, 200.0      # clearance m, contact stiffness N/m, spin rad/s


def run(t, x, y, speed=W, d=None, events=None, names=("A",), e_f=None, e_d=None, p_f=None, race=None):
    """A SimResult with ``contact`` filled from shaft-centre paths x, y (N, m) by a linear law."""
    t = np.asarray(t, float)
    x, y = np.atleast_2d(np.asarray(x, float).T).T, np.atleast_2d(np.asarray(y, float).T).T
    n, m = x.shape
    d = np.hypot(x, y) - C if d is None else np.atleast_2d(np.asarray(d, float).T).T
    fn = KC * np.maximum(d, 0.0)
    z = np.zeros((n, m))
    contact = {"names": np.array(names), "clearance": np.full(m, C), "x": x, "y": y, "fn": fn, "ft": z, "d": d,
               "race_speed": z if race is None else race, "friction_power": z if p_f is None else p_f,
               "e_friction": z if e_f is None else e_f, "e_damping": z if e_d is None else e_d,
               "events": events, "summary": {}}
    res = SimResult(t=t, y=np.zeros((n, 2 * m)), i=np.zeros((n, 2 * m)), orbit=np.zeros((n, 0, 2)), nodes=(),
                    speed=np.broadcast_to(np.asarray(speed, float), t.shape).copy(), axes=("A:x", "A:y"),
                    meta={"scene": "synthetic", "rung": "modal", "integrator": "bdf2", "h": 1e-4, "period": 1e-4,
                          "speed": float(np.asarray(speed).flat[0]), "run_up": None, "record_every": 1},
                    fault=None, steps=n, wall=0.0)
    res.contact = contact      # the field the lead adds to SimResult (spec: Simulate)
    return res


def circle(t, rate, pen=1e-6, phase=0.0):
    r = C + pen
    return r * np.cos(rate * t + phase), r * np.sin(rate * t + phase)


T = np.arange(0.0, 1.0, 1e-4)


def test_backward_full_clearance_whirl_at_minus_three_spin():
    res = run(T, *circle(T, -3 * W))
    b = analyse(res).bearings[0]
    v = b.whirl
    assert v.direction == -1 and v.name == "backward whirl (full clearance)" and v.full_clearance
    assert v.ratio == pytest.approx(-3.0, rel=0.01)
    assert v.frequency_hz == pytest.approx(-3 * W / (2 * math.pi), rel=1e-6)
    assert v.revolutions == pytest.approx(3.0, abs=0.05)
    assert b.contact_fraction == 1.0 and b.in_contact_at_end
    assert analyse(res).any_contact and analyse(res).backward_whirl
    assert "BACKWARD WHIRL" in analyse(res).headline()


def test_forward_whirl_at_spin_and_negative_spin_flips_the_name():
    v = analyse(run(T, *circle(T, W))).bearings[0].whirl
    assert v.direction == 1 and v.name == "forward whirl (full clearance)"
    assert v.ratio == pytest.approx(1.0, rel=1e-3)
    v = analyse(run(T, *circle(T, W), speed=-W)).bearings[0].whirl    # spin about -z: same orbit is backward
    assert v.direction == -1 and v.ratio == pytest.approx(-1.0, rel=1e-3)


def test_whirl_with_intermittent_contact_is_not_full_clearance():
    x, y = circle(T, -2 * W, pen=-1e-6)                                 # 1 um inside the clearance ...
    d = np.hypot(x, y) - C + 2e-6 * (np.sin(2 * math.pi * 50 * T) > 0)  # ... touching half the time
    v = analyse(run(T, x, y, d=d)).bearings[0].whirl
    assert v.direction == -1 and v.name == "backward whirl" and not v.full_clearance


def test_noisy_whirl_keeps_direction_and_ratio():
    rng = np.random.default_rng(1)
    x, y = circle(T, -3 * W)
    d = np.hypot(x, y) - C
    x, y = x + 3e-6 * rng.standard_normal(T.size), y + 3e-6 * rng.standard_normal(T.size)
    v = analyse(run(T, x, y, d=d)).bearings[0].whirl
    assert v.direction == -1 and v.ratio == pytest.approx(-3.0, rel=0.01)


def test_bouncing_at_the_bottom_is_not_whirl():
    rng = np.random.default_rng(2)
    hop = 60e-6 * np.abs(np.sin(2 * math.pi * 15 * T))                  # bounces to 60 um above the race
    x = 1e-6 * rng.standard_normal(T.size)
    y = -(C + 1e-6) + hop + 1e-7 * rng.standard_normal(T.size)
    b = analyse(run(T, x, y)).bearings[0]
    assert b.whirl.direction == 0 and b.whirl.name == "bouncing"
    assert 0 < b.contact_fraction < 0.2 and b.events > 10


def test_resting_and_rocking_on_the_bearing_is_not_whirl():
    a = 0.3 * np.sin(2 * math.pi * 5 * T)                                # rocks +-17 degrees at the bottom
    x, y = (C + 2e-6) * np.sin(a), -(C + 2e-6) * np.cos(a)
    v = analyse(run(T, x, y)).bearings[0].whirl
    assert v.direction == 0 and v.name == "resting on the bearing"


def test_levitated_forward_orbit_is_no_contact_and_no_whirl():
    x, y = 0.5 * C * np.cos(W * T), 0.5 * C * np.sin(W * T)
    rep = analyse(run(T, x, y))
    b = rep.bearings[0]
    assert not rep.any_contact and b.whirl.name == "no whirl" and b.events == 0
    assert b.max_radius_m == pytest.approx(0.5 * C) and b.peak_force_N == 0 and b.t_peak_s is None
    assert "no contact" in rep.lines()[1] and "50.0 %" in rep.lines()[1]
    assert rep.headline() == "no contact with the auxiliary bearings"


def test_zero_spin_gives_nan_ratio_and_sparse_record_no_verdict():
    v = analyse(run(T, *circle(T, -600.0), speed=0.0)).bearings[0].whirl
    assert v.direction != 0 and math.isnan(v.ratio)
    ts = np.arange(0.0, 1.0, 4e-3)                                       # 2.4 rad per row at 600 rad/s
    v = analyse(run(ts, *circle(ts, -3 * W))).bearings[0].whirl
    assert v.direction == 0 and "not resolved" in v.name
    assert np.isnan(whirl_ratio_series(run(ts, *circle(ts, -3 * W)), 0)[1]).all()


def test_peak_force_penetration_energies_and_window():
    d = np.full(T.size, -10e-6)
    d[(T >= 0.2) & (T < 0.3)] = 1e-6
    d[4000] = 7e-6                                                       # the peak, at t = 0.4 s
    e_f = np.cumsum(np.where(d > 0, 0.5, 0.0))[:, None]                  # 0.5 J per row in contact
    e_d = 0.1 * e_f
    p_f = np.where(d > 0, 5000.0, 0.0)[:, None]
    x, y = np.zeros(T.size), -(C + d)
    race = np.linspace(0, 50, T.size)[:, None]
    res = run(T, x, y, d=d, e_f=e_f, e_d=e_d, p_f=p_f, race=race)
    b = analyse(res).bearings[0]
    assert b.peak_force_N == pytest.approx(KC * 7e-6) and b.t_peak_s == pytest.approx(0.4)
    assert b.max_penetration_m == pytest.approx(7e-6)
    assert b.events == 2 and b.first_contact_s == pytest.approx(0.2)
    assert b.last_contact_end_s == pytest.approx(0.4001) and not b.in_contact_at_end
    assert b.friction_energy_J == pytest.approx(0.5 * 1001) and b.damping_energy_J == pytest.approx(0.05 * 1001)
    assert b.mean_friction_power_W == pytest.approx(0.5 * 1001 / T[-1])
    assert b.peak_friction_power_W == 5000.0 and b.race_speed_end == pytest.approx(50.0)
    assert b.contact_fraction == pytest.approx(1001 / T.size)
    w = analyse(res, 0.25, 0.35).bearings[0]                               # a window: energy gained in it
    assert w.friction_energy_J == pytest.approx(0.5 * 500) and w.events == 0 and w.peak_force_N == KC * 1e-6
    assert w.first_contact_s == pytest.approx(0.25) and w.last_contact_end_s == pytest.approx(0.3)
    assert w.mean_friction_power_W == pytest.approx(250 / 0.1, rel=2e-3)


def test_contact_log_events_count_and_peaks_between_rows():
    d = np.full(T.size, -10e-6)
    d[2000:2100] = 1e-6
    ev = [{"kind": "contact", "bearing": "A", "phase": "start", "t_s": 0.19995, "merged": 1},
          {"kind": "contact", "bearing": "A", "phase": "end", "t_s": 0.21002, "peak_force_N": 900.0,
           "max_penetration_m": 9e-6, "merged": 1},
          {"kind": "contact", "bearing": "A", "phase": "start", "t_s": 0.5, "merged": 3},   # 3 short hits
          {"kind": "contact", "bearing": "A", "phase": "end", "t_s": 0.5, "peak_force_N": 2000.0,
           "max_penetration_m": 2e-5, "merged": 3},
          {"kind": "contact", "bearing": "B", "phase": "start", "t_s": 0.7, "merged": 1}]
    b = analyse(run(T, np.zeros(T.size), -(C + d), d=d, events=ev)).bearings[0]
    assert b.events == 4 and b.first_contact_s == pytest.approx(0.19995)
    assert b.peak_force_N == 2000.0 and b.t_peak_s == 0.5 and b.max_penetration_m == 2e-5
    assert b.last_contact_end_s == 0.5


def lift_off(t_lift=0.5, tau=0.02):
    """Resting at the bottom, whirling backward 0.2-0.3 s, lifted to the centre from t_lift (radius
    C exp(-(t - t_lift)/tau))."""
    x, y = np.zeros(T.size), -(C + 1e-6) * np.ones(T.size)
    wh = (T >= 0.2) & (T < 0.3)
    x[wh], y[wh] = circle(T[wh], -3 * W)
    up = T >= t_lift
    y[up] = -C * np.exp(-(T[up] - t_lift) / tau)
    return x, y


def test_relevitation_time_peak_and_backward_whirl():
    res = run(T, *lift_off())
    res.events = [{"kind": "drop", "axis": None, "params": {}, "phase": "start", "t_s": 0.1, "step": 1000, "index": 1},
                  {"kind": "drop", "axis": None, "params": {}, "phase": "end", "t_s": 0.4, "step": 4000, "index": 1}]
    assert return_time(res) == 0.4
    assert return_time(run(T, *lift_off())) is None                      # no drop
    res2 = run(T, *lift_off())
    res2.events = res.events + [{"kind": "drop", "axis": None, "params": {}, "phase": "start", "t_s": 0.6,
                                 "step": 6000, "index": 2}]                # a second drop, for good
    assert return_time(res2) is None
    rl = relevitation(res, 0.4)
    t_settle = 0.5 + 0.02 * math.log(1 / 0.3)                          # radius < 0.3 C from here
    assert rl.time_s == pytest.approx(t_settle - 0.4, abs=2e-4)
    assert rl.peak_force_N == pytest.approx(KC * 1e-6) and not rl.backward_whirl and rl.ok
    assert rl.held_s == pytest.approx(T[-1] - t_settle, abs=2e-4)
    assert rl.last_contact_s == pytest.approx(0.5, abs=2e-4)                  # the last row with d > 0
    stopped = analyse(res, 0.0, 0.45).bearings[0]                         # whirled, then came to rest on it
    assert stopped.whirl.name == "resting on the bearing" and stopped.whirl.direction == 0
    [ep] = stopped.whirl_episodes
    assert ep.name == "backward whirl (full clearance)" and ep.ratio == pytest.approx(-3.0, rel=1e-3)
    assert ep.t_to_s == pytest.approx(0.3, abs=0.011)
    early = relevitation(res, 0.15)                                        # the whirl at 0.2-0.3 s is after it
    assert early.backward_whirl and not early.ok
    assert "re-levitated" in rl.lines()[0] and "no backward whirl" in rl.lines()[1]


def test_relevitation_never_when_the_run_ends_on_the_bearing_or_off_centre():
    x, y = np.zeros(T.size), -(C + 1e-6) * np.ones(T.size)
    rl = relevitation(run(T, x, y), 0.4)
    assert rl.time_s is None and not rl.ok and "NOT re-levitated" in rl.lines()[0]
    y = np.where(T < 0.5, y, -0.5 * C)                                   # off the bearing but at half clearance
    assert relevitation(run(T, x, y), 0.4).time_s is None


def test_two_bearings_and_the_whirl_ratio_series():
    xa, ya = circle(T, -3 * W)
    xb, yb = 0.2 * C * np.cos(W * T), 0.2 * C * np.sin(W * T)
    res = run(T, np.column_stack([xa, xb]), np.column_stack([ya, yb]), names=("A", "B"))
    rep = analyse(res)
    assert [b.whirl.direction for b in rep.bearings] == [-1, 0]
    assert "TOUCHDOWN on the auxiliary bearing A" in rep.headline()
    t, ratio = whirl_ratio_series(res, 0)
    assert np.nanmedian(ratio) == pytest.approx(-3.0, rel=1e-3) and np.isnan(ratio[0])
    assert np.isnan(whirl_ratio_series(res, 1)[1]).all()
    text = "\n".join(rep.lines())
    assert "backward whirl (full clearance)" in text and "B    clearance 250 um: no contact" in text


def test_plots_are_written(tmp_path):
    res = run(T, *lift_off())
    res.contact["shaft_radius"], res.contact["race_radius"] = np.array([0.02]), np.array([0.02 + C])
    files = plot_contact(res, tmp_path)
    assert [p.name for p in files] == ["contact_orbits.png", "contact_force.png", "whirl_ratio.png"]
    assert all(p.stat().st_size > 10_000 for p in files)
    res.contact = None
    assert plot_contact(res, tmp_path) == []


def test_simulate_prints_touchdown_first_then_the_report_and_relevitation(capsys):
    from types import SimpleNamespace
    from ambhil.bridge.cli import simulate
    res = run(T, *lift_off())
    res.events = [{"kind": "drop", "axis": None, "params": {}, "phase": "start", "t_s": 0.1, "step": 1000, "index": 1},
                  {"kind": "drop", "axis": None, "params": {}, "phase": "end", "t_s": 0.4, "step": 4000, "index": 1}]
    model = SimpleNamespace(spec=SimpleNamespace(ambs=[]))
    f = simulate._figures(res, model, None, 1.0)
    simulate._print(res, model, f, "out/simulation.npz", [[], []])
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith("  TOUCHDOWN on the auxiliary bearing A from t=0 s: peak 100 N (A); BACKWARD WHIRL")
    text = "\n".join(out)
    assert "  auxiliary bearings, t 0-0.9999 s:" in text and "earlier: backward whirl (full clearance)" in text
    assert "  re-levitation after the AMBs came back at t=0.4 s: re-levitated in 0.1241 s" in text
    s = simulate._summary(res, model, f, [])
    assert s["contact"]["bearings"][0]["name"] == "A" and s["relevitation"]["time_s"] == pytest.approx(0.1241, abs=1e-3)


def from_drop(res, dt=1e-4):
    """The record a simulate run would hold of a point-rotor drop (plant/point_rotor.py): rows every
    ``dt``, the contact log from the drop's events, the energies from its work states."""
    from ambhil.plant.point_rotor import OM, W_CD, W_F, WR, X, Y
    b = res.rotor.bearing
    t = np.arange(0.0, float(res.t[-1]) + 1e-12, dt)
    s = res.sample(t)
    d = np.hypot(s[X], s[Y]) - b.clearance
    ev = []
    for e in res.events:
        ev.append({"kind": "contact", "bearing": "A", "phase": "start", "t_s": e.start, "merged": 1})
        if math.isfinite(e.end):
            ev.append({"kind": "contact", "bearing": "A", "phase": "end", "t_s": e.end, "merged": 1,
                       "peak_force_N": e.peak_force, "max_penetration_m": e.max_penetration})
    out = run(t, s[X], s[Y], speed=s[OM], d=d, events=ev, e_f=s[W_F][:, None], e_d=s[W_CD][:, None],
              race=s[WR][:, None])
    out.contact["clearance"] = np.array([b.clearance])
    out.contact["fn"] = b.stiffness * np.maximum(d, 0.0)[:, None]      # spring part: enough for the tests
    return out


@pytest.mark.parametrize("mu", [0.6, 0.3])
def test_point_rotor_drop_agrees_with_its_own_whirl_verdict(mu):
    """The validated point-rotor drop (docs/contact.md): held race, 20 rad/s; mu 0.6 whirls backward
    at the rolling speed -R_s Omega / r, mu 0.3 bounces."""
    from ambhil.plant.auxiliary_bearing import AuxiliaryBearing
    from ambhil.plant.point_rotor import W_F, PointRotor, drop, whirl
    c, m, k, rs, om = 1e-3, 10.0, 1e8, 0.01, 20.0
    b = AuxiliaryBearing(clearance=c, stiffness=k, shaft_radius=rs, damping=2 * 0.05 * math.sqrt(k * m), friction=mu)
    res = drop(PointRotor(mass=m, bearing=b, spin=om), 0.5 if mu > 0.5 else 0.3)
    rep = analyse(from_drop(res))
    bc, ref = rep.bearings[0], whirl(res)
    assert bc.events == len(res.events) and bc.first_contact_s == pytest.approx(math.sqrt(2 * c / 9.81), rel=1e-6)
    assert bc.peak_force_N >= max(e.peak_force for e in res.events if math.isfinite(e.end))
    if mu > 0.5:
        assert ref.name == "backward whirl" and bc.whirl.name == "backward whirl (full clearance)"
        assert bc.whirl.frequency_hz == pytest.approx(ref.frequency / (2 * math.pi), rel=1e-3)
        assert bc.whirl.ratio == pytest.approx(-rs / c, rel=1e-2)
    else:
        assert ref.name == "no full-clearance whirl" and bc.whirl.direction == 0
        assert bc.whirl.name in ("bouncing", "resting on the bearing")
    assert bc.friction_energy_J == pytest.approx(float(res.y[W_F, -1]), rel=1e-6)
