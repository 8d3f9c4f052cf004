"""Closed-loop time domain: lockstep bit-for-bit, purity, frequency-domain consistency, I/O."""
import json

import numpy as np
import pytest

from ambhil.controller import discrete as dc
from ambhil.plant import plan as pl
from ambhil.loop.analysis import modal
from ambhil.loop.orbit_plots import plot_orbits
from ambhil.loop.orbits import harmonic
from ambhil.loop.sim_result import load
from ambhil.loop.simulation import simulate
from ambhil.loop.system import controller_runner
from ambhil.plant.run_options import RunOptions
from ambhil.plant.step import PlantRunner, PlantState, step
from test_integrator import model


@pytest.mark.parametrize("rung,scheme,kw", [
    ("rigid", "bdf1", {}), ("modal", "bdf2", dict(h=5e-5)), ("full", "trapezoidal", {}),
    ("rigid", "generalized-alpha", dict(h=2.5e-5)), ("modal", "zoh", {}),
    ("rigid", "bdf1", dict(nonlinear=True)), ("rigid", "trapezoidal", dict(run_up=(0.0, 600.0, 0.0, 0.05))),
])
def test_lockstep_runners_reproduce_simulate_bit_for_bit(rung, scheme, kw):
    """The bridge's loop (PlantRunner.advance / ControllerRunner.step in Python) and the fused
    in-process loop give identical bits."""
    m = model(rung)
    run_up = kw.pop("run_up", None)
    speed = None if run_up else 350.0
    res = simulate(m, 0.03, speed, run_up=run_up, integrator=scheme, nodes=[21], **kw)
    plant = PlantRunner(m, RunOptions(integrator=scheme, h=kw.get("h"), speed=speed, run_up=run_up,
                                      nonlinear=kw.get("nonlinear")))
    ctrl = controller_runner(m)
    assert plant.n_axes == ctrl.n_axes == m.n_axes and plant.period == ctrl.period
    y = plant.reset(); ctrl.reset()
    ys = [y]
    for _ in range(res.steps):
        y = plant.advance(ctrl.step(y))
        ys.append(y)
    assert np.array_equal(np.array(ys), res.y)
    assert plant.step_index == res.steps and plant.sim_time == pytest.approx(0.03)
    assert plant.fault is None


def test_step_is_pure_and_matches_runner():
    m = model("modal")
    plant = PlantRunner(m, RunOptions(integrator="bdf2", speed=350.0))
    plan = plant.plan
    st = PlantState(pl.initial_state(plan), pl.new_workspace(plan)[1])
    before = st.s.copy()
    cur = np.array([0.01, -0.02, 0.0, 0.03])
    out = PlantState(np.zeros_like(st.s), np.zeros_like(st.ws))
    st2, y = step(plan, st, cur, out=out)
    assert st2 is out and np.array_equal(st.s, before)
    plant.reset()
    assert np.array_equal(plant.advance(cur), y)
    # with a model: its default plan (scene defaults: bdf1 at the controller period)
    from ambhil.plant.step import initial
    st0 = initial(m)
    st1, y1 = step(m, st0, cur)
    p1 = PlantRunner(m); p1.reset()
    assert np.array_equal(p1.advance(cur), y1) and np.all(st0.s == 0)


def test_safe_state_zeroes_control_currents():
    m = model()
    plant = PlantRunner(m, RunOptions(speed=350.0))
    plant.reset()
    assert np.all(plant.safe_state() == 0.0)


def _exact_sampled_fundamental(m, W, node, rate):
    """Frequency-domain steady state of the sampled-data loop's fundamental: plant with the
    controller H_d(e^{i W T}) times the hold's (1 - e^{-i W T})/(i W T) (aliases neglected: the
    plant attenuates them by ~(W/(2 pi rate))^2)."""
    M, C, G, K, Ba, Ca, Cs = m.dense
    T = 1 / rate
    r = controller_runner(m, sample_rate=rate)
    Hd = dc.frequency_response(r.params, np.array([W]), T)[0]
    zoh = (1 - np.exp(-1j * W * T)) / (1j * W * T)
    Z = -W**2 * M + 1j * W * (C + W * G) + K + Ba @ np.diag(m.ki) @ Cs * (Hd * zoh)
    X = np.linalg.solve(Z, m.unbalance_forces(W))
    return (m.fe_rows([m.rotor.dof(node - 1, 0)]) @ X)[0]


def test_steady_state_matches_frequency_domain():
    """Time-domain steady unbalance amplitude and phase equal plant/analysis/unbalance.response
    (continuous H) within 1 % -- with the controller sampled at 200 kHz so that sampling
    (delay ~T/2, Tustin warping) is negligible -- at several speeds including the first
    critical.  At the real 10 kHz rate the comparison is made, tighter, against the sampled-data
    frequency response (discrete controller at e^{i W T} times the hold), since H itself differs
    from the sampled loop by O(W T)."""
    from ambhil.loop.analysis.unbalance import response
    m = model("rigid")
    crit = modal.critical_speeds(m, count=1, speed_max=1000.0)[0].speed
    for W in (150.0, crit, 700.0):
        fd = response(m, [W], nodes=[20]).x[0, 0]
        td = simulate(m, 0.6, W, integrator="zoh", h=5e-6, sample_rate=200_000.0, nodes=[21],
                      record_every=4)
        X = harmonic(td.t, td.orbit[:, 0, 0], W)
        assert abs(X - fd) / abs(fd) < 0.01, (W, X, fd)
        sd = simulate(m, 0.6, W, integrator="zoh", nodes=[21])
        X10 = harmonic(sd.t, sd.orbit[:, 0, 0], W)
        ex = _exact_sampled_fundamental(m, W, 21, 10_000.0)
        assert abs(X10 - ex) / abs(ex) < 2e-3, (W, X10, ex)
        # the y orbit is the forward-whirl quarter period behind (isotropic rotor)
        Y = harmonic(td.t, td.orbit[:, 0, 1], W)
        assert Y == pytest.approx(-1j * X, rel=0.02)


def test_full_rung_steady_state_matches_frequency_domain():
    from ambhil.loop.analysis.unbalance import response
    m = model("full")
    W = 300.0
    fd = response(m, [W], nodes=[20]).x[0, 0]
    td = simulate(m, 0.6, W, integrator="trapezoidal", h=1e-5, sample_rate=100_000.0, nodes=[21], record_every=2)
    X = harmonic(td.t, td.orbit[:, 0, 0], W)
    assert abs(X - fd) / abs(fd) < 0.01


def test_save_load_and_plot(tmp_path):
    m = model("rigid")
    r = simulate(m, 0.05, 350.0, nodes=[21, 30])
    f = r.save(tmp_path)
    back = load(tmp_path)
    assert np.array_equal(back.y, r.y) and back.nodes == (21, 30)
    assert back.meta["integrator"] == "bdf1" and back.meta["h"] == 1e-4
    assert back.orbit.shape == (len(r.t), 2, 2)
    pngs = plot_orbits(r, tmp_path)
    assert [p.name for p in pngs] == ["orbit_node21.png", "orbit_node30.png", "currents.png"] and all(p.stat().st_size > 1000 for p in pngs)


def test_cli_simulate(tmp_path):
    import argparse
    from ambhil.bridge.cli import simulate as commands_time
    from test_integrator import SCENE
    sc = tmp_path / "s.toml"
    sc.write_text(SCENE + "\n[speed]\nvalue = 350.0\n")
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers()
    commands_time.add_parsers(sub)
    args = ap.parse_args(["simulate", str(sc), "--out", str(tmp_path / "o"), "--duration", "0.05",
                          "--integrator", "bdf2", "--h", "5e-5", "--nodes", "21,30"])
    assert args.func(args) == 0
    meta = json.loads(str(np.load(tmp_path / "o" / "simulation.npz")["meta"]))
    assert meta["integrator"] == "bdf2" and meta["ratio"] == 2
    assert (tmp_path / "o" / "orbit_node30.png").exists()
    bad = ap.parse_args(["simulate", str(sc), "--out", str(tmp_path / "o2"), "--h", "3e-5"])
    assert bad.func(bad) == 2


@pytest.mark.parametrize("m_steps", [0, 3, 10])
def test_advance_arriving_is_the_latency_kernel_at_that_arrival(m_steps):
    """Currents taking effect m plant steps into each period (real time, applied at their
    arrival) are the fixed-latency plant (plant/latency.py) with latency m h, fed the same
    commands; m = 0 is a plain advance, m = ratio holds the previous command all period."""
    mdl = model("modal")
    h = 1e-5
    ref = PlantRunner(mdl, RunOptions(integrator="bdf2", h=h, speed=350.0, latency=m_steps * h))
    arr = PlantRunner(mdl, RunOptions(integrator="bdf2", h=h, speed=350.0))
    assert arr.ratio == 10
    rng = np.random.default_rng(1)
    ref.reset(); arr.reset()
    old = np.array(mdl.i_op, dtype=np.float64)      # before any command: the operating point
    for _ in range(40):
        u = rng.normal(0.0, 0.05, arr.n_axes)
        y_ref = ref.advance(u)
        y_arr = arr.advance_arriving(old, u.copy(), m_steps).copy()
        assert np.array_equal(y_arr, y_ref)
        old = u
    if m_steps:
        with pytest.raises(ValueError, match="fixed latency"):
            ref.advance_arriving(old, old, 1)


# --- the numerics check before a run: warn only beyond a stated tolerance (docs/time_domain.md 10.2) ---

from pathlib import Path  # noqa: E402

PAPER3 = str(Path(__file__).resolve().parents[1] / "scenes" / "paper_3amb.toml")


def _simulate_cli(tmp_path, *extra) -> int:
    import argparse
    from ambhil.bridge.cli import simulate as commands_time
    ap = argparse.ArgumentParser()
    commands_time.add_parsers(ap.add_subparsers())
    args = ap.parse_args(["simulate", PAPER3, "--out", str(tmp_path), "--duration", "0.002", "--no-record", *extra])
    return args.func(args)


def test_default_scene_simulate_prints_no_numerics_warning(tmp_path, capsys):
    """The README's default scene with its own integrator and step (trapezoidal, h = T) prints no
    numerics line: its least-damped mode decays within the tolerance of the exact sampled loop."""
    assert _simulate_cli(tmp_path) == 0
    err = capsys.readouterr().err
    assert "numerical" not in err and "numerics" not in err, err


def test_the_papers_bdf1_warns_with_its_figures_and_the_tolerance(tmp_path, capsys):
    """--integrator bdf1 (the paper's BDF1 at 100 us) on the same scene: one warning line naming
    the mode, both rates and the tolerance.  The simulated rate is checked against BDF1's own
    amplification 1 / (1 - s h) applied to the exact loop's eigenvalue s (an independent scalar
    reading of the same numerical damping), and it lies beyond the stated 25 % tolerance."""
    import re
    from ambhil.loop.numerics import RATE_TOLERANCE, physical_loop
    from ambhil.loop.system import compile_system
    assert _simulate_cli(tmp_path, "--integrator", "bdf1") == 0
    lines = [x for x in capsys.readouterr().err.splitlines() if "numerical damping" in x]
    assert len(lines) == 1, lines
    line = lines[0]
    assert line.split(": ", 1)[1].startswith("warning: numerical damping: bdf1 at h=0.0001 s adds")
    ex = physical_loop(compile_system(PAPER3), speed=327.19)
    se = ex.s[ex.least_damped()]
    mm = re.search(r"mode \(([0-9.]+) Hz, zeta [0-9.e-]+\): it decays at ([0-9.e+]+) 1/s in the exact sampled loop "
                   r"\(plant integrated exactly, same discrete controller\), decays at ([0-9.e+]+) 1/s in the simulated "
                   r"loop .*; tolerance ([0-9.e+]+) 1/s \(25% of the exact rate\)", line)
    assert mm, line
    f, r_ex, r_sim, tol = (float(g) for g in mm.groups())
    assert f == pytest.approx(se.imag / (2 * np.pi), rel=1e-3) and r_ex == pytest.approx(-se.real, rel=2e-3)
    assert tol == pytest.approx(RATE_TOLERANCE * r_ex, rel=2e-3)
    h = 1e-4
    r_bdf1 = -np.log(abs(1 / (1 - se * h))) / h  # BDF1 on y' = s y, per second
    assert r_sim == pytest.approx(r_bdf1, rel=0.05)
    assert r_sim - r_ex > tol
    assert "trapezoidal at h=0.0001 s (1 step per controller period) keeps that mode's rate within" in line


def test_nonlinear_simulate_says_the_numerics_check_was_skipped(tmp_path, capsys):
    assert _simulate_cli(tmp_path, "--nonlinear", "--rung", "modal") == 0
    err = capsys.readouterr().err
    assert " simulate: note: numerics check skipped" in err and "nonlinear" in err, err
    assert "numerical damping" not in err


def test_numerics_note_resolves_the_ancf_scheme_and_skips_latency():
    """The ancf rung integrates with the scene's scheme when its DAE has it, else bdf1 (what the
    check then judges); a loop latency skips the check, saying so."""
    from ambhil.loop.numerics import numerics_note
    from ambhil.loop.system import compile_system
    from ambhil.plant.ancf_step import default_scheme
    assert default_scheme("trapezoidal") == "bdf1" and default_scheme("generalized-alpha") == "generalized-alpha"
    m = compile_system(PAPER3, "modal")
    assert numerics_note(m, speed=327.19) is None
    level, line = numerics_note(m, "bdf1", speed=327.19)
    assert level == "warning" and line.startswith("numerical damping: bdf1")
    level, line = numerics_note(m, speed=327.19, latency=1e-4)
    assert level == "note" and "a loop latency" in line


# --- study accuracy: every figure reads right (docs/time_domain.md 9) ---

def test_accuracy_study_rigid_rows_have_no_false_hf_error_and_no_tiny_growth():
    """A rigid rung has no flexible mode: its rows show the reference's HF mode as n/a (not the
    5 kHz Nyquist alternation against 1262 Hz), and a neutral loop's growth rate (|mu| = 1 within
    roundoff) is 0, never a tiny positive number that reads as unstable.  The printed table fits
    120 columns; the long lines go to accuracy.txt."""
    from ambhil.loop import study
    rows, info = study.accuracy(PAPER3, rungs=("rigid",), integrators=("trapezoidal",), ratios=(1,),
                                duration=0.05, peak_points=3)
    (r,) = rows
    assert np.isnan(r.hf_rate_err) and np.isnan(r.hf_freq)
    assert r.loop_growth == 0.0 and info["loop_rungs"]["rigid"]["growth"] == 0.0
    assert np.isnan(info["loop_rungs"]["rigid"]["hf_rate_err"])
    assert info["loop_ref"]["hf_freq"] == pytest.approx(1262, rel=0.01)
    short = study.table(rows, info, wide=False)
    assert "n/a*" in short and "no mode within 5% of" in short
    assert max(len(x) for x in short.splitlines()) <= 120, short
    row = [x for x in short.splitlines() if x.startswith("rigid")][0].split()
    assert row[-2] == "0" and row[-1] == "n/a*"


def test_accuracy_timing_warms_up_before_it_times_and_takes_the_median(monkeypatch):
    """The cost figure never includes the first run of a configuration (numba dispatch, caches):
    one untimed warm-up run, then the median of TIMING_REPEATS timed runs."""
    from types import SimpleNamespace
    from ambhil.loop import study
    seq = iter([1000.0, 12.0, 10.0, 11.0])  # the first call would be the slow one
    calls = []

    def fake(*a, **k):
        calls.append(a)
        us = next(seq)
        return SimpleNamespace(us_per_period=us, real_time_factor=100.0 / us)
    monkeypatch.setattr(study, "simulate", fake)
    us, rtf = study._cost(None, 300.0, "bdf1", 1e-4, 21, 0.01)
    assert len(calls) == 1 + study.TIMING_REPEATS == 4
    assert us == 11.0 and rtf == pytest.approx(100.0 / 11.0)


def test_orbit_error_beyond_its_tolerance_warns_and_matches_the_simulated_orbits():
    """BDF1 at h = T on the rigid rung: the least-damped mode's rate is within its tolerance, but
    the steady unbalance orbit is ~8 % small.  The check predicts the orbit from the loop maps
    (unbalance_response); the prediction is compared with the orbits of two simulations (BDF1
    and exact zoh, harmonic fits at the sensors): the same error to 1e-3, beyond the 5 % tolerance,
    and the line says so.  Trapezoidal at the same step stays within it (no line)."""
    import re
    from ambhil.loop.numerics import ORBIT_TOLERANCE, numerics_warning, sampled_loop
    from ambhil.loop.system import compile_system
    m = compile_system(PAPER3, "rigid")
    W, T = 327.19, 1e-4
    fits = {}
    for sc in ("zoh", "bdf1"):
        r = simulate(m, 1.0, W, integrator=sc, h=T)
        half = len(r.t) // 2
        fits[sc] = np.array([harmonic(r.t[half:], r.y[half:, a], W) for a in range(r.y.shape[1])])
        pred = sampled_loop(m, sc, T, speed=W, response=True).unbalance
        assert np.linalg.norm(pred - fits[sc]) < 1e-4 * np.linalg.norm(fits[sc])
    err_sim = np.linalg.norm(fits["bdf1"] - fits["zoh"]) / np.linalg.norm(fits["zoh"])
    assert err_sim > ORBIT_TOLERANCE
    line = numerics_warning(m, "bdf1", T, speed=W)
    assert line is not None and line.startswith("numerical error: bdf1 at h=0.0001 s: the steady unbalance response")
    got = float(re.search(r"complex error ([0-9.]+)%; tolerance 5%", line).group(1)) / 100
    assert got == pytest.approx(err_sim, abs=1e-3)
    assert numerics_warning(m, "trapezoidal", T, speed=W) is None
