"""Auxiliary-bearing contact over zenoh (issue 32, item 6; bridge/process/plant_contact.py): the plant
process publishes every contact start and end as an INFO event at the step simulate's ContactLog
sees it, its contact summary before RUN_END (kept in the recording's ambhil.run_end), the rerun view
shows them (a text log line each, a marker on the station's orbit), and a lockstep drop run is
bit-identical to `simulate` with the same contact events."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ambhil.bridge import protocol as pr
from ambhil.bridge.process.plant_contact import SUMMARY_KEY, event_text, of, summary_text
from ambhil.bridge.recording.rerun_view import contact_event, contact_summary_text, contact_text
from ambhil.bridge.recording.run_end import note_event, run_end_status
from ambhil.loop.scene import load_scene
from ambhil.loop.simulation import simulate
from ambhil.loop.system import compile_system, controller_runner
from ambhil.plant.faults import FaultyPlant
from ambhil.plant.step import PlantRunner

ROOT = Path(__file__).resolve().parents[1]
DROP = ROOT / "scenes" / "rotor_drop.toml"
AUX = ("[amb.auxiliary]\nclearance = 2.5e-4\nstiffness = 1e7\ndamping = 200.0\nfriction = 0.2\n"
       "race_inertia = 1e-4\n")


def rigid_aux_scene(d: Path) -> Path:
    """scenes/net_rigid_1khz.toml (rigid rung, 1 kHz) with an auxiliary bearing at each AMB (soft:
    1e7 N/m, contact time 3 ms, plant step 0.1 ms) and a blade loss at 0.05 s that throws the rotor
    onto them (0.01 kg m: 400 N at 200 rad/s; it bounces and rolls, never reaching the gap)."""
    t = (ROOT / "scenes" / "net_rigid_1khz.toml").read_text()
    assert t.count("pole_area = 5e-4\n") == 2 and 'integrator = "trapezoidal"' in t
    t = t.replace("pole_area = 5e-4\n", "pole_area = 5e-4\n" + AUX)
    t = t.replace('integrator = "trapezoidal"', 'integrator = "bdf2"\nstep = 1e-4')
    t += '\n[[fault]]\nkind = "unbalance_step"\nat = 0.05\nnode = 11\nmagnitude = 0.01\n'
    p = d / "rigid_aux.toml"
    p.write_text(t)
    return p


@pytest.fixture(scope="module")
def rigid(tmp_path_factory):
    return rigid_aux_scene(tmp_path_factory.mktemp("contact"))


def expected(events, period: float) -> list[tuple[int, dict]]:
    """simulate's ContactLog events as the plant publishes them: (step, JSON-safe dict), the step
    the one that ends the period of the event (an end merged without a time: its predecessor's)."""
    out, k = [], 0
    for e in events:
        t = e.get("t_s")
        if t is not None and math.isfinite(t):
            k = math.ceil(t / period - 1e-9)
        out.append((k, json.loads(event_text(e))))
    return out


class Sink:
    def __init__(self):
        self.got = []

    def emit(self, kind, text, step=0, sim_ns=0, force=False):
        self.got.append((kind, text, step, sim_ns, force))


# --------------------------------------------------------------------------- in process
def test_event_text_is_compact_strict_json_with_null_for_what_is_not_a_number():
    e = {"kind": "contact", "bearing": "A", "phase": "end", "t_s": float("nan"), "restitution": float("inf"),
         "peak_force_N": 12.5, "merged": 2}
    text = event_text(e)
    assert " " not in text and text.startswith('{"kind":"contact"')

    def refuse(c):
        raise ValueError(c)
    d = json.loads(text, parse_constant=refuse)          # strict: no NaN / Infinity tokens
    assert d["t_s"] is None and d["restitution"] is None and d["peak_force_N"] == 12.5 and d["merged"] == 2
    s = json.loads(summary_text({"A": {"events": 1, "race_speed_end": float("nan")}}, 2), parse_constant=refuse)
    assert s[SUMMARY_KEY] == {"bearings": {"A": {"events": 1, "race_speed_end": None}}, "events_logged": 2}


def test_a_plant_without_auxiliary_bearings_gets_no_contact_log():
    m = compile_system(load_scene(str(ROOT / "scenes" / "net_rigid_1khz.toml")))
    assert of(PlantRunner(m), Sink(), 1_000_000) is None


def test_the_plant_loop_publishes_the_events_simulate_lists_at_their_steps(rigid):
    """The plant process's hook (PlantContact.fresh around the faulty plant's advance, as in
    bridge/process/plant_node.py) in the loop of simulate: the events, their steps and sim times,
    and the summary are simulate's."""
    scene = load_scene(str(rigid))
    m = compile_system(scene)
    ref = simulate(m, 0.15)
    assert ref.fault is None and len(ref.contact["events"]) >= 4
    fp = FaultyPlant(PlantRunner(m), scene.faults)
    sink = Sink()
    period_ns = int(round(fp.period * 1e9))
    pc = of(fp, sink, period_ns)
    y = np.array(fp.reset())
    advance = pc.fresh(fp.advance_shared)
    ctrl = controller_runner(m)
    ctrl.reset()
    for _ in range(ref.steps):
        y = np.array(advance(ctrl.step_shared(y)))
    got = [(k, json.loads(t)) for kind, t, k, ns, force in sink.got]
    assert all(kind == pr.EventKind.INFO and force and ns == k * period_ns for kind, _, k, ns, force in sink.got)
    assert got == expected(ref.contact["events"], fp.period)
    assert pc.summary() == json.loads(summary_text(ref.contact["summary"], len(ref.contact["events"])))[SUMMARY_KEY]


def test_run_end_keeps_the_plant_contact_summary():
    run = {"plant_end": {"reason": "completed", "steps": 10}, "fault": None, "n_steps": 10}
    text = summary_text({"A": {"events": 3, "peak_force_N": 1234.5}}, 6)
    note_event(run, pr.encode_event(pr.Event(pr.EventKind.INFO, text, "plant", 1, 10, 10_000_000, 0)))
    end = run_end_status(run, "RUN_END event", 10, 10)
    assert end["status"] == "completed"
    assert json.loads(end["contact"]) == {"bearings": {"A": {"events": 3, "peak_force_N": 1234.5}}, "events_logged": 6}
    assert "contact" not in run_end_status({"plant_end": None, "fault": None}, "RUN_END event", 0, 0)


def test_contact_lines_of_the_text_log():
    start = {"kind": "contact", "bearing": "A", "phase": "start", "t_s": 0.05673, "v0_m_s": 0.0744, "merged": 1}
    end = {"kind": "contact", "bearing": "B", "phase": "end", "t_s": None, "start_s": 0.05673, "v0_m_s": 0.0744,
           "v_out_m_s": 0.02, "restitution": 0.27, "peak_force_N": 1235.06, "max_penetration_m": 1.07e-5,
           "energy_J": 1.345, "merged": 3}
    assert contact_text(start) == "contact start A at t=56.73 ms, impact 74.4 mm/s"
    assert contact_text(end) == ("contact end B at t=n/a (from 56.73 ms), peak 1235 N, penetration 10.7 um, impact "
                                 "74.4 mm/s, separation 20 mm/s, restitution 0.27, energy lost 1.34 J (3 events "
                                 "within the period)")
    ev = pr.Event(pr.EventKind.INFO, event_text(start), "plant", 0, 568, 56_800_000, 0)
    assert contact_event(ev) == start
    assert contact_event(pr.Event(pr.EventKind.WARNING, event_text(start), "plant", 0, 0, 0, 0)) is None
    line = contact_summary_text(summary_text({"A": {"events": 6, "peak_force_N": 1235.0, "max_penetration_m": 1.07e-5,
                                                    "friction_energy_J": 6.16, "race_speed_end": 389.8,
                                                    "in_contact_at_end": True}}, 12))
    assert line == ("contact summary: A 6 events, peak 1235 N, penetration 10.7 um, friction 6.16 J, race 389.8 rad/s, "
                    "in contact at the end")


def rrd_contents(path):
    """(the text log's lines, {entity: [marker position]}) of a .rrd's temporal contact markers."""
    import rerun as rr
    store = rr.chunk.RrdReader(str(path)).stream().collect()
    texts, markers = [], {}
    for c in store.stream():
        if c.is_static:
            continue
        if c.entity_path == "/events":
            texts += [t[0] for t in c.to_record_batch().column("TextLog:text").to_pylist()]
        elif "/contact/" in c.entity_path:
            rb = c.to_record_batch()
            markers.setdefault(c.entity_path, []).extend(
                pt for row in rb.column("Points2D:positions").to_pylist() for pt in row)
    return texts, markers


def test_the_recording_of_simulate_has_the_contact_events_and_its_rerun_view_marks_them(rigid, tmp_path):
    """`simulate`'s MCAP carries the contact events as the plant publishes them (INFO, at their steps)
    and the summary in its run_end; its .rrd a text log line per event and a marker per event on
    the station's orbit, at the sensor sample after it (the orbit's own point there)."""
    from ambhil.bridge.recording.load import load_run
    from ambhil.bridge.recording.replay import to_rerun
    from ambhil.bridge.recording.run_end import run_end_of
    from ambhil.bridge.recording.simulated_run import write_simulation
    m = compile_system(load_scene(str(rigid)))
    res = simulate(m, 0.15)
    meta = {"axis_names": [f"{a}-{x}" for a, x in m.axes], "station_names": ["A", "B"],
            "touchdown_clearances_m": [2.5e-4, 2.5e-4], "gaps_m": [5e-4, 5e-4]}
    write_simulation(tmp_path / "s.mcap", "s", res, meta)
    run = load_run(str(tmp_path / "s.mcap"))
    info = [(e.step, json.loads(e.text)) for e in run["events"] if e.kind_name == "INFO"]
    assert info[:-1] == expected(res.contact["events"], res.meta["period"])
    assert info[-1][1][SUMMARY_KEY]["bearings"]["A"]["events"] == res.contact["summary"]["A"]["events"]
    assert json.loads(run_end_of(str(tmp_path / "s.mcap"))["contact"]) == info[-1][1][SUMMARY_KEY]
    out = to_rerun(str(tmp_path / "s.mcap"), str(tmp_path / "s.rrd"))
    texts, markers = rrd_contents(tmp_path / "s.rrd")
    n = len(res.contact["events"])
    assert sum("INFO: contact " in t and "summary" not in t for t in texts) == n
    assert any(t.startswith("[plant] INFO: contact summary: A ") for t in texts), texts
    starts = [e for e in res.contact["events"] if e["phase"] == "start"]
    assert len(markers["/orbit/A/contact/start"]) == sum(e["bearing"] == "A" for e in starts)
    assert len(markers["/orbit/B/contact/end"]) == sum(e["bearing"] == "B" and e["phase"] == "end"
                                                       for e in res.contact["events"])
    # the first touchdown's marker is the orbit point of the sample after it: (x, -y) in um
    k = math.ceil(starts[0]["t_s"] / res.meta["period"] - 1e-9)
    x, y = res.y[k, 0] * 1e6, res.y[k, 1] * 1e6
    assert markers["/orbit/A/contact/start"][0] == pytest.approx([x, -y], abs=1e-3)   # float32 in the .rrd
    assert out["events"] == len(run["events"])


# --------------------------------------------------------------------------- over zenoh (slow)
def cli(*argv, timeout=600):
    return subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", *argv], capture_output=True, text=True,
                          cwd=ROOT, timeout=timeout)


def test_lockstep_drop_run_equals_simulate_bit_for_bit_with_its_contact_events(tmp_path):
    """scenes/rotor_drop.toml over zenoh, lockstep, through the drop (0.05 s) and its first bounces:
    sensors and currents bit for bit those of `simulate`; the contact events recorded are
    simulate's res.contact["events"] at their steps, its summary in the run_end and the plant's
    summary; the run's .rrd and `ambhil replay` show them."""
    from ambhil.bridge.recording.load import load_run
    from ambhil.bridge.recording.run_end import run_end_of
    T = 0.08
    r = cli("run", str(DROP), "--duration", str(T), "--run-id", "drop", "--out", str(tmp_path), "--json")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    summary = json.loads([ln for ln in r.stdout.splitlines() if ln.startswith("{")][-1])
    m = compile_system(load_scene(str(DROP)))
    sim = simulate(m, T)
    n = int(round(T / sim.meta["period"]))
    run = load_run(str(tmp_path / "drop.mcap"))
    assert np.array_equal(run["sensors"]["v"], sim.y[:n])          # bit for bit
    assert np.array_equal(run["currents"]["v"], sim.i[:n])
    events = sim.contact["events"]
    assert any(e["phase"] == "start" for e in events) and any(e["phase"] == "end" for e in events)
    got = [(e.step, json.loads(e.text)) for e in run["events"]
           if e.kind_name == "INFO" and e.source == "plant" and e.text.startswith('{"kind":"contact"')]
    assert got == expected(events, sim.meta["period"])
    want = json.loads(summary_text(sim.contact["summary"], len(events)))[SUMMARY_KEY]
    assert json.loads(run_end_of(str(tmp_path / "drop.mcap"))["contact"]) == want
    assert summary["plant"]["contact"] == want
    texts, markers = rrd_contents(tmp_path / "drop.rrd")
    assert sum(t.startswith("[plant] INFO: contact start") for t in texts) == sum(e["phase"] == "start" for e in events)
    assert markers["/orbit/A/contact/start"] and markers["/orbit/B/contact/end"]
    r = cli("replay", str(tmp_path / "drop.mcap"), "--out", str(tmp_path / "again"))
    assert r.returncode == 0 and (tmp_path / "again" / "drop.rrd").exists(), r.stdout + r.stderr
    assert rrd_contents(tmp_path / "again" / "drop.rrd")[0] == texts


def test_realtime_run_publishes_the_contact_events_and_summary(rigid, tmp_path):
    """Real time (1 kHz, rigid rung): the rotor thrown onto its auxiliary bearings; every contact
    start and end the plant saw is recorded (the summary's count), the summary in the run_end.  Not
    bit for bit (held periods change the loop), so only what the run itself reports is compared."""
    from ambhil.bridge.recording.load import load_run
    from ambhil.bridge.recording.run_end import run_end_of
    r = cli("run", str(rigid), "--duration", "0.15", "--mode", "realtime", "--max-overruns", "off",
            "--run-id", "rt", "--out", str(tmp_path), "--json")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    summary = json.loads([ln for ln in r.stdout.splitlines() if ln.startswith("{")][-1])
    contact = summary["plant"]["contact"]
    assert contact["bearings"]["A"]["events"] >= 1 and contact["bearings"]["A"]["peak_force_N"] > 0
    run = load_run(str(tmp_path / "rt.mcap"))
    got = [json.loads(e.text) for e in run["events"]
           if e.kind_name == "INFO" and e.source == "plant" and e.text.startswith('{"kind":"contact"')]
    assert len(got) == contact["events_logged"]
    assert sum(e["phase"] == "start" and e["bearing"] == "A" for e in got) <= contact["bearings"]["A"]["events"]
    assert json.loads(run_end_of(str(tmp_path / "rt.mcap"))["contact"]) == contact
