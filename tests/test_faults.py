"""Scheduled faults (plant/faults.py, loop/scene.py): the physics of the plant-side faults checked
against independent predictions (linearity of the unbalance response, the eigenvalues `analyze`
computes for the scene without the lost AMB), the sensor / amplifier / transport rules, the
parser's one-line errors, and a HIL run that records the fault events and equals `simulate`."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ambhil.loop.analysis import modal
from ambhil.loop.numerics import identify_poles, sampled_loop
from ambhil.loop.scene import SceneError, load_scene, with_fault_flags
from ambhil.loop.orbits import harmonic
from ambhil.loop.simulation import simulate
from ambhil.loop.system import compile_system

ROOT = Path(__file__).resolve().parents[1]
SCENE = str(ROOT / "scenes" / "paper_3amb.toml")


@pytest.fixture(scope="module")
def scene():
    return load_scene(SCENE)


def run_speed(scene) -> float:
    """The spin speed simulate runs the scene at ([simulation] speed, else [speed] value)."""
    sim = scene.plant.simulation
    return sim.speed if sim.speed is not None else scene.plant.speed.value or 0.0


def faulted(scene, *specs, rung="modal"):
    return compile_system(with_fault_flags(scene, list(specs)), rung=rung)


# --------------------------------------------------------------------------- physics
def test_blade_loss_raises_the_steady_orbit_by_the_ratio_of_the_unbalances(scene):
    """Linear scene: an unbalance step at the node and phase of the scene's unbalance multiplies the
    steady orbit by (m + dm)/m; one at another phase by (m + dm e^{i dphi})/m (complex ratio: size
    and phase), to 0.1 % (measured: 3e-5 to 6e-5)."""
    u = scene.plant.unbalances[0]
    W = run_speed(scene)
    t1, T = 0.6, 1.2
    for dm, dphi in ((0.0015, 0.0), (0.001, 2.0)):
        m = faulted(scene, f"unbalance_step:at={t1}s,node={u.node + 1},magnitude={dm},phase={u.phase + dphi}")
        r = simulate(m, T)
        assert r.fault is None and r.steps == int(round(T / m.scene.period))
        assert [e["phase"] for e in r.events] == ["start"]
        for j, node in enumerate(r.nodes):
            before = harmonic(r.t[r.t < t1], r.orbit[r.t < t1, j, 0], W)
            after = harmonic(r.t, r.orbit[:, j, 0], W, t_from=T - 0.3)
            expect = (u.magnitude + dm * np.exp(1j * dphi)) / u.magnitude
            assert abs(after / before - expect) < 1e-3 * abs(expect), (node, after / before, expect)


@pytest.mark.parametrize("lost", ["A", "B"])
def test_losing_one_of_three_ambs_is_stable_exactly_as_analyze_predicts_without_it(scene, lost):
    """A third of the scene's proportional gain: the 3-AMB loop is stable; `analyze`'s eigenvalues of
    the scene *without* AMB A say unstable (an 8 Hz mode growing at 7.7 1/s), without B stable (the
    least damped mode decays at 12 1/s).  After amb_loss (no unbalance, a small initial
    displacement) the simulated loop's dominant pole, identified from its response by ERA, has
    that verdict and frequency, and equals (to 0.1 %) the dominant pole of the exact sampled loop
    of the scene without that AMB (ambhil.loop.numerics.sampled_loop: the continuous analysis leaves out
    the half period of sampling delay, which moves the rate by a few per cent)."""
    sc = scene.with_controller(kp=0.35 * scene.controller.kp).with_plant(unbalances=())
    W = run_speed(sc)
    without = compile_system(sc.with_plant(ambs=tuple(a for a in sc.plant.ambs if a.name != lost)), rung="full")
    assert max(m.eigenvalue.real for m in modal.Solver(compile_system(sc, rung="full")).all(W, 2 * np.pi * 5e3)) < 0
    lam = max(modal.Solver(without).all(W, 2 * np.pi * 5e3), key=lambda m: m.eigenvalue.real).eigenvalue
    exact = sampled_loop(without, "zoh", speed=W)
    model = faulted(sc, f"amb_loss:at=0.05s,axis={lost}", rung="full")
    q0 = np.zeros(model.n)
    q0[model.act_dof[0]] = 2e-6               # a small initial displacement (no unbalance: homogeneous)
    r = simulate(model, 0.8, q0=q0, integrator="trapezoidal")
    assert r.fault is None
    T = sc.period
    keep = [k for k, (nm, _) in enumerate(model.axes) if nm != lost]
    mu = identify_poles(r.y[r.t > 0.06][:, keep])
    s = np.log(mu.astype(complex)) / T
    dom = s[int(np.argmax(np.abs(mu)))]
    assert (lam.real > 0) == (lost == "A") == (dom.real > 0)
    assert abs(abs(dom.imag) - lam.imag) < 0.01 * lam.imag, (dom, lam)
    assert abs(dom.real - exact.growth_rate) < 1e-3 * abs(exact.growth_rate), (dom, exact.growth_rate)
    assert abs(abs(dom.imag) / 2 / np.pi - exact.frequency_hz) < 1e-3 * exact.frequency_hz
    assert abs(dom.real - lam.real) < 0.1 * abs(lam.real), (dom, lam)
    if lost == "B":
        assert np.abs(r.y[-1]).max() < 1e-3 * 2e-6


def test_losing_an_amb_leaves_the_orbit_of_the_scene_without_it(scene):
    """With the unbalance: after amb_loss of B the steady orbits equal those of the scene without B."""
    W = run_speed(scene)
    r = simulate(faulted(scene, "amb_loss:at=0.05s,axis=B", rung="full"), 1.0)
    ref = simulate(compile_system(scene.with_plant(ambs=tuple(a for a in scene.plant.ambs if a.name != "B")),
                                  rung="full"), 1.0, nodes=r.nodes)
    for j, node in enumerate(r.nodes):
        a = harmonic(r.t, r.orbit[:, j, 0], W, t_from=0.7)
        b = harmonic(ref.t, ref.orbit[:, j, 0], W, t_from=0.7)
        assert abs(a - b) < 1e-3 * abs(b), (node, a, b)


# --------------------------------------------------------------------------- sensor, amplifier, transport
def test_sensor_stuck_zero_bias_drift_and_noise_statistics(scene):
    T = scene.period
    base = simulate(compile_system(scene, rung="modal"), 0.05)
    r = simulate(faulted(scene, "sensor_stuck:at=0.01s,axis=A.x,until=0.02s", "sensor_zero:at=0.01s,axis=A.y,until=0.02s",
                         "sensor_bias:at=0.02s,axis=B.x,value=3e-6", "sensor_drift:at=0.02s,axis=B.y,rate=1e-4",
                         "sensor_noise:at=0.03s,axis=C.x,sigma=2e-6,seed=7"), 0.3)
    assert r.fault is None and r.steps == 3000
    k1, k2, k3 = (int(round(t / T)) for t in (0.01, 0.02, 0.03))
    assert np.array_equal(r.y[:k1], base.y[:k1])                         # nothing before the first fault
    assert np.all(r.y[k1:k2, 0] == r.y[k1, 0]) and r.y[k2, 0] != r.y[k1, 0]   # stuck, then released
    assert np.all(r.y[k1:k2, 1] == 0.0) and r.y[k2, 1] != 0.0
    # the plant is in the loop: the other readings differ from the base run after the faults,
    # so compare each against its own true reading (the orbit at the sensor node)
    tr = compile_system(scene, rung="modal")
    assert r.events[0]["kind"] == "sensor_stuck"
    noise = r.y[k3:, 4] - _true_reading(r, tr, 4)[k3:]
    assert np.allclose(noise, 2e-6 * np.random.default_rng(7).standard_normal(len(noise)), rtol=0, atol=1e-15)
    assert abs(noise.mean()) < 4 * 2e-6 / math.sqrt(len(noise)) and abs(noise.std() / 2e-6 - 1) < 0.1
    bias = r.y[k2:, 2] - _true_reading(r, tr, 2)[k2:]
    assert np.allclose(bias, 3e-6, rtol=0, atol=1e-15)
    drift = r.y[k2:, 3] - _true_reading(r, tr, 3)[k2:]
    assert np.allclose(drift, 1e-4 * (r.t[k2:] - k2 * T), rtol=0, atol=1e-15)


def _true_reading(r, model, axis):
    """The true sensor displacement of an axis from the recorded orbits (output nodes)."""
    node = model.spec.ambs[axis // 2].sensor_node + 1
    return r.orbit[:, r.nodes.index(node), axis % 2]


def test_amplifier_limit_and_slew_bound_the_coil_current(scene):
    from ambhil.loop.system import controller_runner
    from ambhil.plant.faults import FaultyPlant
    from ambhil.plant.run_options import RunOptions
    from ambhil.plant.step import PlantRunner
    sc = with_fault_flags(scene, ["amp_limit:at=0.005s,limit=0.05", "amp_slew:at=0.02s,axis=A,rate=20"])
    model = compile_system(sc, rung="modal")
    fp = FaultyPlant(PlantRunner(model, RunOptions(h=model.scene.period / 4)), sc.faults)
    ctrl = controller_runner(model)
    y = fp.reset()
    coil, cmd = [], []
    for k in range(400):
        u = ctrl.step(y)
        prev = fp.coil.copy()
        y = fp.advance(u)
        cmd.append(u)
        coil.append((prev, fp.coil.copy()))
    cmd = np.array(cmd)
    k_lim, k_slew = 50, 200
    assert np.abs(cmd[k_lim:]).max() > 0.05                            # the controller asks for more ...
    assert max(np.abs(c[1]).max() for c in coil[k_lim:]) <= 0.05 + 1e-15   # ... the coils never get it
    T = fp.period
    for prev, now in coil[k_slew:]:
        assert np.all(np.abs(now[:2] - prev[:2]) <= 20 * T + 1e-12)         # A: at most rate x T per period


def test_message_loss_is_a_zero_order_hold_of_the_missed_message(scene):
    """Every reply lost over a window: the plant keeps applying the last command it received, i.e.
    the run equals one whose controller output is held over the window (computed independently)."""
    from ambhil.loop.system import controller_runner
    from ambhil.plant.step import PlantRunner
    model = compile_system(scene, rung="modal")
    T = scene.period
    r = simulate(faulted(scene, "message_loss:at=0.01s,duration=0.003s,direction=currents"), 0.03)
    plant, ctrl = PlantRunner(model), controller_runner(model)
    y = plant.reset()
    ctrl.reset()
    Y = [y]
    held = None
    for k in range(int(round(0.03 / T))):
        u = ctrl.step(y)
        if 100 <= k < 130:
            u = held
        else:
            held = u
        y = plant.advance(u)
        Y.append(y)
    assert np.array_equal(r.y, np.array(Y))
    # sensor direction: the controller sees the sample before the window for the whole window
    r2 = simulate(faulted(scene, "message_loss:at=0.01s,duration=0.003s,direction=sensors"), 0.02)
    assert np.all(r2.y[100:130] == r2.y[99]) and np.any(r2.y[130] != r2.y[99])


def test_message_delay_delays_the_commands_by_whole_periods(scene):
    from ambhil.loop.system import controller_runner
    from ambhil.plant.step import PlantRunner
    model = compile_system(scene, rung="modal")
    r = simulate(faulted(scene, "message_delay:at=0s,periods=2,direction=currents"), 0.02)
    plant, ctrl = PlantRunner(model), controller_runner(model)
    y = plant.reset()
    ctrl.reset()
    U = [model.i_op.copy(), model.i_op.copy()]
    Y = [y]
    for k in range(200):
        U.append(ctrl.step(y))
        y = plant.advance(U[-3])
        Y.append(y)
    assert np.array_equal(r.y, np.array(Y))


def test_no_faults_costs_nothing_and_a_later_fault_changes_nothing_before_it(scene):
    model = compile_system(scene, rung="modal")
    base = simulate(model, 0.03)
    assert base.events is None and "fault_events" not in base.meta
    late = simulate(faulted(scene, "sensor_zero:at=10s,axis=A.x"), 0.03)
    assert np.array_equal(late.y, base.y) and late.events == []


# --------------------------------------------------------------------------- parser
@pytest.mark.parametrize("spec,needle", [
    ("sensor_nois:at=1", "key 'kind': must be one of"),
    ("sensor_noise:at=1,axis=Q.x,sigma=1", "'Q.x' is not an AMB axis or station"),
    ("sensor_noise:at=soon,axis=A.x,sigma=1", "key 'at': must be a time such as 0.2s"),
    ("sensor_noise:axis=A.x,sigma=1", "key 'at': is required"),
    ("amb_loss:at=1,axis=A.x", "'A.x' is not a station"),
    ("sensor_zero:at=1,axis=A.x,foo=2", "key 'foo': unknown key"),
    ("unbalance_step:at=1,node=30,magnitude=1,duration=1s", "permanent"),
    ("message_delay:at=1,periods=0", "key 'periods': must be from 1"),
    ("sensor_zero:at=1,axis=A.x,duration=1,until=2", "either 'duration' or 'until'"),
    ("sensor_zero", "key 'at': is required"),
    ("sensor_zero:at", "expected KIND:key=value"),
])
def test_bad_fault_specs_give_one_line_errors(scene, spec, needle):
    with pytest.raises(SceneError) as e:
        with_fault_flags(scene, [spec])
    msg = str(e.value)
    assert needle in msg and "--fault #1" in msg and "\n" not in msg, msg


def test_bad_fault_table_names_file_index_and_key(tmp_path):
    text = Path(SCENE).read_text() + '\n[[fault]]\nkind = "sensor_zero"\nat = "0.1s"\naxis = "A.x"\n' \
        '\n[[fault]]\nkind = "amp_limit"\nat = "0.1s"\nlimit = -1\n'
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(SceneError) as e:
        load_scene(p)
    assert str(e.value).startswith(f"{p}: [[fault]] #2 amp_limit key 'limit': must be > 0"), str(e.value)
    r = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "simulate", SCENE, "--fault", "coil_loss:at=1,axis=Z.q"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "ambhil simulate: error: command line: --fault #1" in r.stderr


# --------------------------------------------------------------------------- HIL
def test_lockstep_run_with_faults_equals_simulate_and_records_the_events(scene, tmp_path):
    from ambhil.bridge.recording.load import load_run
    specs = ["sensor_noise:at=0.01s,axis=A.x,sigma=1e-6,duration=10ms", "controller_restart:at=0.02s",
             "message_loss:at=0.025,duration=5ms,probability=0.5", "amb_loss:at=0.03,axis=B",
             "unbalance_step:at=0.035,node=30,magnitude=0.002", "amp_limit:at=0.04,limit=0.2"]
    argv = ["run", SCENE, "--duration", "0.05", "--rung", "modal", "--run-id", "faults", "--out", str(tmp_path)]
    for s in specs:
        argv += ["--fault", s]
    r = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", *argv], capture_output=True, text=True, cwd=ROOT,
                       timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    run = load_run(str(tmp_path / "faults.mcap"))
    sim = simulate(faulted(scene, *specs), 0.05)
    assert np.array_equal(run["sensors"]["v"], sim.y[:500])          # bit for bit
    assert np.array_equal(run["currents"]["v"], sim.i[:500])
    inj = [e for e in run["events"] if e.kind_name == "FAULT_INJECTED"]
    got = [(e.step, json.loads(e.text)["kind"], json.loads(e.text)["phase"]) for e in inj]
    assert got == [(e["step"], e["kind"], e["phase"]) for e in sim.events]
    assert any("controller restarted" in e.text for e in run["events"] if e.source == "controller")
    assert run["meta"]["faults"][1]["kind"] == "controller_restart"
    # the rerun replay written by the run: each start/end in the text log, and the marker series
    import rerun as rr
    store = rr.chunk.RrdReader(str(tmp_path / "faults.rrd")).stream().collect()
    texts = []
    for c in store.stream():
        if c.entity_path == "/events" and not c.is_static:
            texts += [t[0] for t in c.to_record_batch().column("TextLog:text").to_pylist()]
    logged = [t for t in texts if "FAULT_INJECTED" in t]
    assert len(logged) == len(sim.events) and any("start amb_loss B" in t for t in logged), texts
    active = []
    for c in store.stream():
        if c.entity_path == "/faults/active" and not c.is_static:
            active += [v[0] for v in c.to_record_batch().column("Scalars:scalars").to_pylist()]
    assert max(active) == 4 and active[-1] == 4   # noise ended at 20 ms, message_loss at 30 ms


# --------------------------------------------------------------------------- speed trip
def test_speed_trip_settles_on_the_orbit_of_the_new_speed(scene):
    """A trip straight down to 0.8 x the speed (over = 0): the steady orbit afterwards is the one a
    run at that speed from the start has (a separate constant-speed simulation)."""
    W = run_speed(scene)
    r = simulate(faulted(scene, f"speed_trip:at=0.3s,to={0.8 * W},over=0"), 0.9)
    ref = simulate(compile_system(scene, rung="modal"), 0.6, 0.8 * W)
    assert r.fault is None and ref.fault is None
    for j in range(len(r.nodes)):
        a = abs(harmonic(r.t, r.orbit[:, j, 0], 0.8 * W, t_from=0.6))
        b = abs(harmonic(ref.t, ref.orbit[:, j, 0], 0.8 * W, t_from=0.3))
        assert abs(a - b) < 0.01 * b, (r.nodes[j], a, b)


def test_speed_trip_coasts_down_linearly_with_a_continuous_phase(scene):
    from ambhil.plant.faults import FaultyPlant
    from ambhil.plant import integrator as ig
    from ambhil.plant.run_options import RunOptions
    from ambhil.plant.step import PlantRunner
    sc = with_fault_flags(scene, ["speed_trip:at=0.1s,to=0,over=0.5s"])
    model = compile_system(sc, rung="modal")
    fp = FaultyPlant(PlantRunner(model), sc.faults)
    W = run_speed(scene)
    before, after = fp._segments[0][1], fp._segments[1][1]
    th0, W0, _ = ig.speed_at(before.fp, 0.1)
    th1, W1, a = ig.speed_at(after.fp, 0.1)
    assert W0 == W1 == W and abs(th1 - th0) < 1e-12 * th0
    assert ig.speed_at(after.fp, 0.35)[1:] == pytest.approx((0.5 * W, -W / 0.5))
    assert ig.speed_at(after.fp, 0.7)[1] == 0.0
    with pytest.raises(Exception, match="zoh"):
        FaultyPlant(PlantRunner(model, RunOptions(integrator="zoh")), sc.faults)


# --------------------------------------------------------------------------- campaign
CAMPAIGN = """
[campaign]
duration = "0.4s"

[[case]]
name = "stuck sensor"
faults = ["sensor_stuck:at=0.2s,axis=A.x,duration=5ms"]
max_orbit_fraction = 0.5
recovery_time = "0.15s"

[[case]]
name = "dead sensor"
faults = ["sensor_zero:at=0.2s,axis=A.y"]
max_orbit_fraction = 0.5
"""


def test_campaign_prints_a_pass_fail_table_and_exits_1_on_a_failed_case(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text(CAMPAIGN)
    r = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "test-controller", SCENE, "--faults", str(f), "--rung",
                        "modal", "--json", "--out", str(tmp_path / "o")], capture_output=True, text=True, cwd=ROOT,
                       timeout=300)
    assert r.returncode == 1, r.stdout + r.stderr
    s = json.loads(r.stdout)
    ok, dead = s["results"]
    assert ok["passed"] and ok["recovery_time_s"] <= 0.15 and ok["max_orbit_fraction"] < 0.5
    assert not dead["passed"] and not dead["stable"] and any("not stable" in x for x in dead["failures"])
    assert (tmp_path / "o" / "campaign.json").exists()
    human = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "test-controller", SCENE, "--faults", str(f), "--rung",
                            "modal"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert human.returncode == 1 and "PASS" in human.stdout, human.stdout
    import re   # the rotor reached the stator: at least the 150 um gap, twice the 75 um touchdown clearance
    assert float(re.search(r"FAIL: orbit ([\d.]+) % of the touchdown", human.stdout).group(1)) >= 200.0, human.stdout
    assert "1 of 2 cases passed" in human.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text(CAMPAIGN.replace("axis=A.y", "axis=A.q"))
    e = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "test-controller", SCENE, "--faults", str(bad)],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert e.returncode == 2 and "[[case]] #2 'dead sensor' faults[0] sensor_zero key 'axis'" in e.stderr, e.stderr


def test_campaign_against_a_controller_command_agrees_with_in_process(tmp_path):
    """--controller runs each case as `ambhil run` with that command as the controller (here the
    reference controller): the same verdicts and, lockstep being bit-identical, the same orbits."""
    f = tmp_path / "c.toml"
    f.write_text(CAMPAIGN.replace('duration = "0.4s"', 'duration = "0.3s"').split("[[case]]\nname = \"dead")[0])
    base = [sys.executable, "-m", "ambhil.bridge.cli", "test-controller", SCENE, "--faults", str(f), "--rung", "modal",
            "--json"]
    inproc = subprocess.run(base, capture_output=True, text=True, cwd=ROOT, timeout=300)
    cmd = f"{sys.executable} -m ambhil.bridge.cli controller {{scene}} --run-id {{run_id}} --connect {{connect}}"
    ext = subprocess.run(base + ["--controller", cmd, "--out", str(tmp_path / "o")], capture_output=True, text=True,
                         cwd=ROOT, timeout=600)
    a, b = json.loads(inproc.stdout)["results"], json.loads(ext.stdout)["results"]
    assert [x["passed"] for x in a] == [x["passed"] for x in b] and ext.returncode == inproc.returncode, ext.stderr
    for x, y in zip(a, b):
        assert abs(x["max_orbit_fraction"] - y["max_orbit_fraction"]) < 1e-9 * x["max_orbit_fraction"]
        assert [(e["kind"], e["phase"], e["step"]) for e in x["events"]] == \
            [(e["kind"], e["phase"], e["step"]) for e in y["events"]]


def test_one_touchdown_clearance_in_analyze_simulate_and_campaign(tmp_path):
    """Distinct per-AMB touchdown clearances (A its own 60 um, B the [analysis] default 70 um, C its
    own 50 um): analyze, simulate and the campaign judge each AMB against the same value, and a
    20 ms stuck sensor that stays under 50 % of the 150 um magnetic gap fails the 50 % criterion
    against A's touchdown clearance."""
    txt = (ROOT / "scenes" / "paper_3amb.toml").read_text().replace('rung = "full"', 'rung = "modal"', 1)
    line = "touchdown_clearance = 7.5e-5"
    assert txt.count(line) == 3
    txt = txt.replace(line, "touchdown_clearance = 6e-5", 1).replace(line, "", 1).replace(line, "touchdown_clearance = 5e-5", 1)
    txt = txt.replace("[analysis]\n", "[analysis]\ntouchdown_clearance = 7e-5\n", 1).replace('sweep_amb = "B"\n', "")
    sc = tmp_path / "td.toml"
    sc.write_text(txt)
    own = {"A": 6e-5, "B": 7e-5, "C": 5e-5}
    camp = tmp_path / "c.toml"
    camp.write_text('[campaign]\nduration = "0.4s"\n\n[[case]]\nname = "stuck"\n'
                    'faults = ["sensor_stuck:at=0.2s,axis=A.x,duration=20ms"]\nmax_orbit_fraction = 0.5\n')

    def cli(*a):
        r = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", *a, "--json"], capture_output=True, text=True,
                           cwd=ROOT, timeout=300)
        return r, json.loads(r.stdout.splitlines()[-1])

    r, an = cli("analyze", str(sc))
    assert r.returncode == 0, r.stderr
    vib = an["scenes"][0]["vibration_iso14839_2"]
    assert {s["amb"]: s["touchdown_clearance_m"] for s in vib["stations"]} == own
    r, cm = cli("test-controller", str(sc), "--faults", str(camp))
    assert r.returncode == 1 and cm["touchdown_clearances_m"] == own, r.stderr
    case = cm["results"][0]
    r, sim = cli("simulate", str(sc), "--duration", "0.4", "--fault", "sensor_stuck:at=0.2s,axis=A.x,duration=20ms",
                 "--out", str(tmp_path / "sim"))
    largest = {o["amb"]: o for o in sim["largest_orbits"]}
    assert {k: o["touchdown_clearance_m"] for k, o in largest.items()} == own
    # the same run in both: the campaign's figure is simulate's largest radius over its own clearance
    assert case["max_orbit_fraction"] == pytest.approx(max(o["fraction_of_touchdown_clearance"]
                                                           for o in largest.values()), rel=1e-12)
    ra = largest["A"]["largest_radius_m"]
    assert ra / 1.5e-4 < 0.5 < ra / 6e-5 and case["max_orbit_fraction"] == pytest.approx(ra / 6e-5, rel=1e-12)
    assert not case["passed"] and "of the touchdown clearance > 50 %" in case["failures"][0]
    # the orbit plots of that run: the red circle and the title are A's touchdown clearance, the
    # magnetic gap a grey dashed circle apart (drawn at the orbit's scale once it exceeds 30 %)
    import matplotlib.figure
    from ambhil.loop.orbit_plots import plot_orbits
    from ambhil.loop.sim_result import load
    seen = []
    save = matplotlib.figure.Figure.savefig
    try:
        matplotlib.figure.Figure.savefig = lambda fig, *a, **k: seen.append(
            [(ax.get_title(), [ln.get_label() for ln in ax.get_lines()]) for ax in fig.axes])
        plot_orbits(load(tmp_path / "sim"), tmp_path / "plots", nodes=[21], gaps={21: 1.5e-4}, clearances={21: 6e-5})
    finally:
        matplotlib.figure.Figure.savefig = save
    title, labels = seen[0][1]
    assert f"= {100 * ra / 6e-5:.1f} % of the touchdown clearance 60 um" in title
    assert "touchdown clearance 60 um" in labels and "magnetic gap 150 um" in labels


def test_simulate_with_faults_prints_orbits_between_fault_events_and_marks_them_on_time_plots(tmp_path, capsys,
                                                                                              monkeypatch):
    """`simulate --fault`: the summary gives the largest orbit per AMB between the fault starts and
    ends (each the largest recorded radius over its window, recomputed from simulation.npz) and the
    steady orbit after the last fault event; every time plot (whirl radius, coil currents,
    currents.png) marks each fault's start and end with a vertical line and names the fault."""
    import matplotlib.figure
    import matplotlib.pyplot as plt
    from ambhil.bridge.cli import main as cli
    from ambhil.loop.sim_result import load
    from test_cli import _largest_um, _segment_rows
    figs, save = [], matplotlib.figure.Figure.savefig
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: (figs.append(fig), save(fig, *a, **k))[1])
    close = plt.close
    monkeypatch.setattr(plt, "close", lambda *a: None)        # keep the figures for inspection
    o = tmp_path / "o"
    code = cli.main(["simulate", SCENE, "--rung", "modal", "--duration", "0.4", "--no-record", "--out", str(o),
                     "--fault", "sensor_noise:at=0.1s,duration=30ms,axis=A.x,sigma=2e-6", "--fault", "amb_loss:at=0.2s,axis=B"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "between the fault starts and ends:" in out, out
    rows = _segment_rows(out)
    assert [(r[0], r[1], r[2]) for r in rows] == [(0, 0.1, "no fault"), (0.1, 0.13, "sensor_noise A.x"),
                                                 (0.13, 0.2, "no fault"), (0.2, 0.4, "amb_loss B")], out
    res = load(o)
    for k, (t0, t1, _, amb) in enumerate(rows):
        for name, node in (("A", 21), ("B", 39), ("C", 57)):
            assert amb[name] == pytest.approx(_largest_um(res, node, t0, t1, k == len(rows) - 1), abs=0.006)
    assert "steady orbit after t=0.2 s: A " in out, out
    time_axes = [(f, a) for f in figs for a in f.axes if a.get_xlabel() == "t (s)"]
    assert len(figs) == 5 and len(time_axes) == 4 + 3 + 1    # 4 whirl radii, 3 AMBs' currents, currents.png's last row
    for f in figs:
        for a in f.axes:
            if a.get_xlabel() != "t (s)" and not (a.get_ylabel().startswith("AMB ") and a.get_ylabel().endswith("(A)")):
                continue
            vlines = {round(float(ln.get_xdata()[0]), 9) for ln in a.get_lines()
                      if len(ln.get_xdata()) == 2 and ln.get_xdata()[0] == ln.get_xdata()[1]}
            assert {0.1, 0.13, 0.2} <= vlines, (f._suptitle.get_text(), a.get_ylabel(), vlines)
        texts = [t.get_text().strip() for a in f.axes for t in a.texts]
        assert "sensor_noise A.x" in texts and "amb_loss B (to the end)" in texts, texts
    for f in figs:
        close(f)


@pytest.mark.parametrize("spec", ["amb_loss:at=0s,axis=B", "coil_loss:at=0s,axis=A.y"])
def test_a_loss_from_the_first_sample_integrates_with_the_faulted_factorisation(scene, spec):
    """A coil or AMB loss active from t = 0 on the full rung (a banded plan, whose solves use its
    factorisation ``LU``) runs, bit for bit, like a fault-free run of the model whose coils are off
    from the outset (``model_without_axes``: the plant the fault switches to).  The reference is
    independent of the path checked: it never goes through ``FaultyPlant``, its runner resets and
    factorises its own plan.  Before the fix ``FaultyPlant.reset`` let ``PlantRunner.reset`` copy
    the healthy plan's factorisation into the faulted plan, which then solved with the healthy
    matrix until the fault ended."""
    from ambhil.plant.faults import NO_FAULTS, model_without_axes
    model = faulted(scene, spec, rung="full")
    lost = sorted({a for f in model.scene.faults.faults for a in f.axes})
    assert lost and model.scene.faults.faults[0].start_step(scene.period) == 0
    r = simulate(model, 0.02)
    healthy = compile_system(scene, rung="full", rotor=model.rotor)
    ref = simulate(model_without_axes(healthy, lost), 0.02, faults=NO_FAULTS)
    assert r.fault is None and ref.fault is None and len(r.events) == 1
    assert np.array_equal(r.y, ref.y) and np.array_equal(r.orbit, ref.orbit) and np.array_equal(r.i, ref.i)
