"""Recorder: MCAP content, rerun mcap convert, SIGKILL + recover."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

TESTS = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, TESTS)
import test_nodes as tn  # noqa: E402
from ambhil.bridge import protocol as pr
from ambhil.bridge.recording import layout as rc
from ambhil.bridge.process import transport as tr
from ambhil.bridge.recording.recover import recover  # noqa: E402
from mcap.reader import make_reader  # noqa: E402


def _recorder_proc(ep, run_id, out, **kw):
    from ambhil.bridge.recording.recorder import RecorderConfig, record
    kw.setdefault("start_timeout", 60)
    s = record(run_id, out, RecorderConfig(connect=ep, **kw))
    print(json.dumps(s))


def rerun_bin() -> str | None:
    cand = os.path.join(os.path.dirname(sys.executable), "rerun")
    if os.path.exists(cand):
        return cand
    try:
        import rerun_cli
        p = os.path.join(os.path.dirname(rerun_cli.__file__), "rerun")
        return p if os.path.exists(p) else None
    except ImportError:
        return shutil.which("rerun")


def run_recorded(tmp_path, run, n=500, ctl_kind="p", **plant_kw):
    """Plant, controller and recorder in three processes on an explicit loopback mesh (the
    topology `ambhil run` uses): the recorder listens, the plant listens and connects to it,
    the controller connects to both; nothing depends on gossip discovery."""
    ep, rep = tn.endpoint(), tn.endpoint()
    out = str(tmp_path / f"{run}.mcap")
    r = tn.py(f"import test_recorder as tr_; tr_._recorder_proc(None, {run!r}, {out!r}, listen={rep!r})")
    c = tn.py(f"t._controller_proc([{ep!r}, {rep!r}], {run!r}, kind={ctl_kind!r})")
    p = tn.py(f"t._plant_proc({ep!r}, {run!r}, {n}, wait_recorder=True, connect={rep!r}, **{plant_kw!r})")
    sp, sc, sr = tn.last_json(p), tn.last_json(c), tn.last_json(r)
    return out, sp, sc, sr


def read_all(path):
    with open(path, "rb") as f:
        rd = make_reader(f)
        summ = rd.get_summary()
        msgs = [(s, c, m) for s, c, m in rd.iter_messages(log_time_order=False)]
        f.seek(0)
        meta = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    return summ, msgs, meta


def wire_by_key(msgs, key):
    """(wire bytes, mcap message) of every recorded message of a wire key (bridge/recording/layout.py);
    the senders' peer ids that end them on the wire come from the recorded RunMeta."""
    metas = [rc.decode_meta(m.data).info for s, c, m in msgs if rc.layout(s) == rc.META]
    peer = rc.peer_ids(metas[0] if metas else {}).get(pr.message_type_for_key(key), pr.NO_PEER)
    return [(rc.wire_of(s, m.data, peer), m) for s, c, m in msgs if rc.channel_key(c) == key]


def test_recorder_writes_complete_mcap(tmp_path):
    n = 500
    out, sp, sc, sr = run_recorded(tmp_path, "rec1", n)
    assert sp["fault"] is None and sc["fault"] is None, (sp, sc)
    assert sr["end_reason"] in ("RUN_END event", "plant liveliness lost"), sr
    summ, msgs, meta = read_all(out)
    K = pr.keys("rec1")
    by_topic = {}
    for s, c, m in msgs:
        by_topic.setdefault(rc.channel_key(c), []).append((s, c, m))
    assert len(by_topic[K.sensors]) == n and len(by_topic[K.currents]) == n
    assert len(by_topic[K.meta]) == 1
    events = rc.recorded_key(pr.event_key("rec1", "plant"))   # every role's events: one channel
    assert events == f"{K.root}/events"
    kinds = [rc.decode_event(m.data).kind for _, _, m in by_topic[events]]
    assert pr.EventKind.RUN_START in kinds and pr.EventKind.RUN_END in kinds
    assert {rc.decode_event(m.data).source for _, _, m in by_topic[events]} == {"plant", "controller"}
    for topic, typ in ((K.sensors, rc.SENSORS), (K.currents, rc.CURRENTS), (events, rc.EVENT),
                       (K.meta, rc.META), (K.timing, rc.TIMING)):
        s, c, _ = by_topic[topic][0]
        # fixed topic names (one Foxglove layout for every run), the run's key in the metadata
        assert c.topic == "/ambhil/" + topic.split("/", 2)[2] and c.metadata["key"] == topic
        assert "rec1" not in c.topic and c.message_encoding == "cdr" and s.encoding == "ros2msg"
        assert s.name == f"ambhil_msgs/msg/{typ}" and "std_msgs/Header header" in s.data.decode()
    # the wire bytes are restored from the recorded fields; log_time = sim time (1 ms period)
    seqs = [pr.decode_sensor(d).seq for d, _ in wire_by_key(msgs, K.sensors)]
    assert seqs == list(range(n))
    assert [m.log_time for _, _, m in by_topic[K.sensors]] == [k * 1_000_000 for k in range(n)]
    assert [m.publish_time for d, m in wire_by_key(msgs, K.sensors)] == [
        pr.decode_sensor(d).publish_wall_ns for d, _ in wire_by_key(msgs, K.sensors)]
    assert sum(summ.statistics.channel_message_counts.values()) == len(msgs)
    assert "ambhil.recorder" in meta and "ambhil.run_meta" in meta
    assert not [c.topic for _, c, _ in msgs if "foreign" in c.topic]      # nothing rejected
    info = json.loads(meta["ambhil.run_meta"]["json"])
    assert info["run_id"] == "rec1" and info["n_axes"] == 4
    # one StepTiming per step, stamped at step x period
    assert [m.log_time for _, _, m in by_topic[K.timing]] == [k * 1_000_000 for k in range(n)]
    # how the run ended, from the file alone
    end = meta["ambhil.run_end"]
    assert end["status"] == "completed" and end["fault"] == "", end
    assert end["steps_planned"] == end["steps_run"] == end["steps_recorded"] == str(n), end
    assert end["rejected"] == "{}" and end["auth"] == "none", end        # no key, on loopback
    assert sr["status"] == "completed" and sr["steps_recorded"] == n
    assert sr["rejected"] == {} and sr["auth"] == "none", sr


def test_failed_run_is_marked_in_the_mcap(tmp_path):
    """A run that faults: the file says so (status failed, the fault, steps run < planned)."""
    out, sp, sc, sr = run_recorded(tmp_path, "recfail", 400, kind="blowup")
    assert sp["fault"] and "not finite" in sp["fault"], sp
    _, _, meta = read_all(out)
    end = meta["ambhil.run_end"]
    assert end["status"] == "failed" and "plant output not finite at step 50" in end["fault"], end
    assert end["steps_planned"] == "400" and end["steps_run"] == "50", end
    assert sr["status"] == "failed"


def test_run_end_status_rules():
    """completed only when the run completed and every step is in the file."""
    from ambhil.bridge.recording.run_end import run_end_status
    run = {"n_steps": 100, "fault": None, "plant_end": {"reason": "completed", "steps": 100, "fault": None}}
    assert run_end_status(run, "RUN_END event", 100, 100)["status"] == "completed"
    e = run_end_status(run, "RUN_END event", 100, 62)
    assert e["status"] == "truncated" and e["steps_run"] == 100 and e["currents_recorded"] == 62
    run["plant_end"] = {"reason": "fault", "steps": 40, "fault": "boom"}
    assert run_end_status(run, "RUN_END event", 41, 41)["status"] == "failed"
    run["plant_end"] = {"reason": "stopped", "steps": 40, "fault": None}
    assert run_end_status(run, "RUN_END event", 40, 40)["status"] == "stopped"
    run = {"n_steps": 100, "fault": "controller: x", "plant_end": None}
    e = run_end_status(run, "plant liveliness lost", 7, 7)
    assert e["status"] == "failed" and e["fault"] == "controller: x"
    e = run_end_status({"plant_end": None, "fault": None}, "error: plant did not appear within 1 s", 0, 0)
    assert e["status"] == "failed" and e["fault"] == "plant did not appear within 1 s"
    assert run_end_status({"plant_end": None, "fault": None}, "signal SIGTERM", 5, 5)["status"] == "stopped"


def test_recorder_waits_for_a_slow_starting_plant(tmp_path):
    """Issue 10: recorder, controller and plant started separately, the plant slow to start
    (6 s in its "starting" state, a cold kernel compilation); recorder and controller count only
    absence against their 1 s start timeout, so neither gives up and the file is complete."""
    from ambhil.bridge.process.startup import STARTING, PeerWatch
    ep, rep, run, n = tn.endpoint(), tn.endpoint(), "recslow", 300
    out = str(tmp_path / f"{run}.mcap")
    p = tn.py(f"t._plant_proc({ep!r}, {run!r}, {n}, slow_start=6.0, wait_recorder=True, connect={rep!r})")
    s = tn.connect_session(ep)
    w = PeerWatch(s, run)
    try:
        w.wait(["plant"], 120, until=STARTING)
    finally:
        w.undeclare()
        tr.close_quietly(s)
    r = tn.py(f"import test_recorder as tr_; tr_._recorder_proc(None, {run!r}, {out!r}, listen={rep!r}, "
              f"start_timeout=1.0)")
    c = tn.py(f"t._controller_proc([{ep!r}, {rep!r}], {run!r}, start_timeout=1.0)")
    sp, sc, sr = tn.last_json(p), tn.last_json(c), tn.last_json(r)
    assert sp["fault"] is None and sc["fault"] is None, (sp, sc)
    assert sr["status"] == "completed" and sr["steps_recorded"] == n, sr
    _, _, meta = read_all(out)
    assert meta["ambhil.run_end"]["status"] == "completed"


@pytest.mark.skipif(rerun_bin() is None, reason="rerun CLI not installed")
def test_rerun_mcap_convert(tmp_path):
    out, sp, _, _ = run_recorded(tmp_path, "rr1", 200)
    rrd = str(tmp_path / "rr1.rrd")
    p = subprocess.run([rerun_bin(), "mcap", "convert", out, "-o", rrd], capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert os.path.getsize(rrd) > 1000
    import rerun as rr
    store = rr.chunk.RrdReader(rrd).stream().collect()
    ents = {c.entity_path for c in store.stream()}
    assert any("plant/sensors" in e for e in ents), ents
    assert any("controller/currents" in e for e in ents), ents


def _flood_proc(ep, run_id, rate_hz, seconds):
    """Publish sensor+current pairs at rate_hz (2 messages per tick) until the recorder's token
    goes away (or ``seconds``).  A plant of protocol 3 that is its own controller: it answers the
    recorder's challenge, publishes a RunMeta of a session it made up, and seals both streams."""
    from ambhil.bridge.process.pairing import Responder, peer_key
    from ambhil.bridge.protocol import auth as au
    K = pr.keys(run_id)
    s = tr.open_session(listen=ep)
    me, cid = tr.peer_id(s), bytes(range(1, 17))
    auth = au.RunAuth(None, run_id, "plant", me)
    resp = Responder(s, auth)
    tok = tr.declare_token(s, K.alive_plant)
    tok2 = tr.declare_token(s, K.alive_controller)
    tok3 = tr.declare_token(s, peer_key(run_id, "plant", me))
    ps, pc = tr.declare_publisher(s, K.sensors), tr.declare_publisher(s, K.currents)
    w = tr.LivelinessWatch(s, K.alive_all)
    w.wait_for([K.alive_recorder], 120)
    time.sleep(0.05)
    auth.pair(me, cid, au.nonce(), au.nonce())
    meta = pr.encode_meta(pr.RunMeta({"run_id": run_id, "n_axes": 4, "plant_peer_id": me.hex(),
                                      "controller_peer_id": cid.hex(), "auth": auth.describe()}))
    s.put(K.meta, meta, attachment=auth.attach("meta", meta))
    sc = pr.SensorCodec(4, me=auth.seal("plant/sensors"))
    cc = pr.CurrentCodec(4, me=auth.peer_seal(cid, "controller/currents"))
    y = np.ones(4)
    T = int(1e9 / rate_hz)
    t0 = time.perf_counter_ns()
    k = 0
    while K.alive_recorder in w.alive:
        t = time.perf_counter_ns()
        if t - t0 > seconds * 1e9:
            break
        target = (t - t0) // T
        while k <= target:
            ps.put(sc.encode(k, k, k * T, time.time_ns(), y))
            pc.put(cc.encode(k, k, k * T, 0, 0, y))
            k += 1
        time.sleep(0.0005)
    print(json.dumps({"sent": k}))
    resp.undeclare()
    tr.close_quietly(w, ps, pc, tok, tok2, tok3, s)


def test_sigkill_recover(tmp_path):
    """A recorder killed with SIGKILL mid-recording (20k msg/s) leaves a file without footer;
    recover restores every flushed message, in order, without holes.  How little is lost
    (the last ~20 ms): python -m benchmarks.faults."""
    ep, run = tn.endpoint(), "kill9"
    out, fixed = str(tmp_path / "k.mcap"), str(tmp_path / "fixed.mcap")
    fl = tn.py(f"import test_recorder as tr_; tr_._flood_proc({ep!r}, {run!r}, 10000, 300.0)")
    # the flooder is a plant of "your own" (no RecordBatch): the recorder takes the wire
    r = tn.py(f"import test_recorder as tr_; tr_._recorder_proc({ep!r}, {run!r}, {out!r}, source='wire')")
    t_end = time.monotonic() + 300
    while not (os.path.exists(out) and os.path.getsize(out) > 100_000):   # > ~3000 messages flushed
        assert r.poll() is None and fl.poll() is None and time.monotonic() < t_end, r.communicate()
        time.sleep(0.01)
    t_kill = time.time_ns()
    os.kill(r.pid, signal.SIGKILL)
    r.communicate()
    sent = tn.last_json(fl)["sent"]
    with pytest.raises(Exception):
        with open(out, "rb") as f:
            make_reader(f).get_summary().statistics   # footer missing: not a complete file
            raise RuntimeError("complete")
    n = recover(out, fixed)
    assert n > 1000
    _, msgs, _ = read_all(fixed)
    assert len(msgs) == n
    K = pr.keys(run)
    for key in (K.sensors, K.currents):
        seqs = [pr.decode_any(key, d).seq for d, _ in wire_by_key(msgs, key)]
        assert seqs == list(range(len(seqs))), key          # in order, no holes
        assert 0 < len(seqs) <= sent
    last = max(m.publish_time for _, _, m in msgs)             # wall time
    print(f"recovered {n} messages; last log time {(t_kill - last) / 1e6:.1f} ms before the kill")


def test_recording_is_off_the_loop_path_and_every_message_is_recorded(tmp_path):
    """The recorder subscribes to ``ambhil/<run>/*`` only: the loop's puts (two-chunk keys) never
    go to it; the plant's RecordBatch messages carry them, byte for byte the wire payloads
    (checked against the plant's own trace), each exactly once, and RUN_END comes after them."""
    n = 700
    out, sp, sc, sr = run_recorded(tmp_path, "rb1", n, out_npz=str(tmp_path / "tr.npz"))
    assert sp["fault"] is None and sc["fault"] is None and sr["status"] == "completed", (sp, sr)
    assert sr["source"] == "plant" and sr["record_batches"] == 0
    _, msgs, _ = read_all(out)
    K = pr.keys("rb1")
    assert not [c.topic for _, c, _ in msgs if rc.channel_key(c) == K.record], "batches are unpacked, not stored"
    sens = [pr.decode_sensor(d) for d, _ in wire_by_key(msgs, K.sensors)]
    cur = [(pr.decode_current(d), m) for d, m in wire_by_key(msgs, K.currents)]
    assert [x.seq for x in sens] == list(range(n)) and [c.seq for c, _ in cur] == list(range(n))
    got = np.load(tmp_path / "tr.npz")
    assert np.array_equal(np.array([x.displacement for x in sens]), got["y"][:n])
    assert np.array_equal(np.array([c.current for c, _ in cur]), got["u"])
    # publish_time (wall) of a current = its arrival at the plant: after the sample's publish and
    # before the next sample's; log_time = its sim time
    pub = [x.publish_wall_ns for x in sens]
    assert all(pub[c.seq] <= m.publish_time for c, m in cur)
    assert all(m.publish_time <= pub[c.seq + 1] for c, m in cur[:-1])
    assert all(m.log_time == c.sim_time_ns for c, m in cur)


def test_killed_plant_keeps_what_was_batched(tmp_path):
    """SIGKILL of the plant mid-run: every RecordBatch it published is in the recording (the
    recorder ends on the plant's lost liveliness and finishes the file); what it loses is the
    unpublished batch, at most MAX_AGE_S of wall time.  Progress-based: the kill comes once
    our own subscriber has seen batches covering 300 samples."""
    from ambhil.bridge.protocol import record_batch
    run, ep, rep = "rbkill", tn.endpoint(), tn.endpoint()
    out = str(tmp_path / f"{run}.mcap")
    r = tn.py(f"import test_recorder as tr_; tr_._recorder_proc(None, {run!r}, {out!r}, listen={rep!r})")
    c = tn.py(f"t._controller_proc([{ep!r}, {rep!r}], {run!r})")
    p = tn.py(f"t._plant_proc({ep!r}, {run!r}, 10**6, wait_recorder=True, connect={rep!r})")
    s = tn.connect_session(ep)
    seen = []
    sub = s.declare_subscriber(
        pr.keys(run).record,
        lambda smp: seen.extend(x[2] for x in record_batch.decode(smp.payload.to_bytes())[3]
                                if x[0] == record_batch.SENSORS))
    t_end = time.monotonic() + 300
    while len(seen) < 300:
        assert p.poll() is None and time.monotonic() < t_end, p.communicate()
        time.sleep(0.01)
    os.kill(p.pid, signal.SIGKILL)
    p.communicate()
    sr, sc = tn.last_json(r), tn.last_json(c)
    tr.close_quietly(sub, s)
    assert sr["status"] == "failed" and sc["fault"], (sr, sc)
    _, msgs, _ = read_all(out)
    K = pr.keys(run)
    rec = [d for d, _ in wire_by_key(msgs, K.sensors)]
    seqs = [pr.decode_sensor(d).seq for d in rec]
    assert seqs == list(range(len(seqs))) and len(seqs) >= 300
    # every batch our subscriber saw before the kill (it may have joined mid-run) is in the file,
    # byte for byte but for the mac (a recording keeps none: zero where it was)
    by_seq = dict(zip(seqs, rec))
    for x in seen:
        assert by_seq.get(pr.decode_sensor(x).seq) == bytes(x)[:-16] + bytes(16)


@pytest.mark.parametrize("loop", ["python", "C"])
def test_recording_is_ros2_on_simulation_time_with_named_fields(tmp_path, loop):
    """Issue 14: a recording Foxglove reads natively.  Decoded with the ROS 2 decoder of the mcap
    library (mcap-ros2-support, independent of our codecs): profile ros2, every message a
    ros2msg/cdr message with a std_msgs/Header whose stamp is the simulation time step x period
    (= the MCAP log_time), displacement and current as fields named after the axes (unit
    suffixed) holding exactly the values the plant's trace has, one StepTiming per step.  Both
    plant loops: Python (a trace) and C (shared-buffer step objects, bridge/protocol/_plant_lockstep.c)."""
    from mcap_ros2.decoder import DecoderFactory
    from ambhil.bridge.protocol import wire
    if loop == "C" and not wire.NATIVE:
        pytest.skip("the C extension ambhil.bridge.protocol._wire is not built")
    n, names = 250, ["A-x", "A-y", "B-x", "B-y"]
    kinds = {"kind": "shared", "ctl_kind": "shared"} if loop == "C" else {}
    out, sp, sc, sr = run_recorded(tmp_path, "ros1", n, out_npz=str(tmp_path / "tr.npz"),
                                   meta={"axis_names": names}, **kinds)
    assert sp["fault"] is None and sr["status"] == "completed", (sp, sr)
    assert sp["loop"] == loop, sp
    trace = np.load(tmp_path / "tr.npz")
    period_ns = 1_000_000
    with open(out, "rb") as f:
        rd = make_reader(f, decoder_factories=[DecoderFactory()])
        assert rd.get_header().profile == "ros2"
        got: dict = {}
        for s, c, m, d in rd.iter_decoded_messages(log_time_order=False):
            assert c.message_encoding == "cdr" and s.encoding == "ros2msg" and c.topic.startswith("/ambhil/")
            stamp = d.header.stamp.sec * 1_000_000_000 + d.header.stamp.nanosec
            assert stamp == m.log_time, (c.topic, stamp, m.log_time)
            got.setdefault(c.topic.removeprefix("/ambhil/"), []).append(d)
    sens, cur, tim = got["plant/sensors"], got["controller/currents"], got["timing"]
    assert [d.step for d in sens] == list(range(n)) and [d.seq for d in cur] == list(range(n))
    assert [d.header.stamp.nanosec + d.header.stamp.sec * 10**9 for d in sens] == [k * period_ns for k in range(n)]
    assert [d.header.stamp.nanosec + d.header.stamp.sec * 10**9 for d in cur] == [k * period_ns for k in range(n)]
    y = np.array([[d.a_x_m, d.a_y_m, d.b_x_m, d.b_y_m] for d in sens])
    u = np.array([[d.a_x_amp, d.a_y_amp, d.b_x_amp, d.b_y_amp] for d in cur])
    assert np.array_equal(y, trace["y"][:n]) and np.array_equal(u, trace["u"])
    assert [d.step for d in tim] == list(range(n)) and all(d.period_ns == period_ns for d in tim)
    assert all(d.tet_ns >= 0 and isinstance(d.held, bool) for d in tim)
    # the plant's TET of step k is the controller's own stamps in its reply k
    assert [d.tet_ns for d in tim] == [d.publish_wall_ns - d.recv_wall_ns for d in cur]
    assert [d.kind_name for d in got["events"] if d.kind_name.startswith("RUN_")] == ["RUN_START", "RUN_END"]
    assert json.loads(got["meta"][0].json)["axis_names"] == names


def test_rejected_foreign_messages_are_in_the_recording_under_foreign(tmp_path):
    """A second session answers every sample (currents) and sends the controller one sensor
    sample: plant and controller reject them (reason ``peer``) and the run's summary says "its
    messages are in the recording under foreign/": they are, one recorded message per rejected
    one, on ``/ambhil/foreign/...``, and the run's own streams are those of an unattacked run.
    Every process links to the rogue, which listens, so it is there before the run starts."""
    from test_auth import Rogue
    from ambhil.bridge.process.reference import run_inprocess
    from ambhil.bridge.cli.run_verdict import foreign_report
    ep, rep, ep_x, run, n = tn.endpoint(), tn.endpoint(), tn.endpoint(), "frgn", 300
    rogue = Rogue(ep, run, listen=ep_x)
    out = str(tmp_path / f"{run}.mcap")
    r = tn.py(f"import test_recorder as tr_; tr_._recorder_proc(None, {run!r}, {out!r}, listen={rep!r})")
    c = tn.py(f"t._controller_proc([{ep!r}, {rep!r}, {ep_x!r}], {run!r})")
    p = tn.py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r}, wait_recorder=True, "
              f"connect=[{rep!r}, {ep_x!r}])")
    try:
        tn.wait_alive(rogue.watch, [rogue.K.alive_controller], (p, c, r))
        tr.wait_matching(rogue.sens, 60)
        rogue.sens.put(rogue.sc.encode(0, 0, 0, 0, np.zeros(4)))     # not the plant's peer id
        sp, sc, sr = tn.last_json(p), tn.last_json(c), tn.last_json(r)
    finally:
        rogue.close()
    assert sp["fault"] is None and sc["fault"] is None and sr["status"] == "completed", (sp, sc, sr)
    assert rogue.answered > 0 and sp["rejected"].get("peer", 0) >= 1, (rogue.answered, sp)
    assert sc["rejected"].get("peer") == 1, sc
    assert "its messages are in the recording under foreign/" in foreign_report(sp, sc)
    summ, msgs, _ = read_all(out)
    by_key: dict = {}
    for s, ch, m in msgs:
        by_key.setdefault(ch.topic, []).append(m)
    foreign_cur = by_key.get("/ambhil/foreign/controller/currents", [])
    foreign_sens = by_key.get("/ambhil/foreign/plant/sensors", [])
    assert len(foreign_cur) == sp["rejected"]["peer"] == sp["foreign_copied"], (len(foreign_cur), sp)
    assert len(foreign_sens) == 1 == sc["foreign_copied"], sorted(by_key)
    Y, U = run_inprocess(tn.SpringPlant(), tn.PController(), n)
    from ambhil.bridge.recording.load import load_run
    rec = load_run(out)
    assert np.array_equal(rec["currents"]["v"], U) and np.array_equal(rec["sensors"]["v"], Y[:n])


def test_a_run_failed_after_its_recording_says_failed_in_run_end(tmp_path):
    """`ambhil run` fails a run the recorder saw complete (too many overruns, a loop that grows,
    --strict): the renamed `.failed.mcap`'s ``ambhil.run_end`` says failed and why, the
    recorder's own record is kept as ``ambhil.rec_end``, and the file stays a valid MCAP
    (CRCs checked by a seeking and a streaming reader) with every message.  A run_end that
    already says failed is left alone."""
    from pathlib import Path
    from mcap.reader import NonSeekingReader
    from ambhil.bridge.recording.recover import check
    from ambhil.bridge.recording.run_end import run_end_of
    from ambhil.bridge.recording.load import load_run
    from ambhil.bridge.cli.run_files import mark_failed
    out, sp, _, sr = run_recorded(tmp_path, "verdict", 200)
    assert sr["status"] == "completed", sr
    before = load_run(out)
    why = "the loop did not keep 1000 Hz: 90 of 180 periods overran (50.00 % > --max-overruns 1 %)"
    (failed,) = mark_failed(Path(out), why=why)
    assert failed.name == "verdict.failed.mcap" and check(str(failed)) == "complete"
    with open(failed, "rb") as f:
        meta = [(m.name, dict(m.metadata)) for m in make_reader(f, validate_crcs=True).iter_metadata()]
        f.seek(0)
        n_seek = sum(1 for _ in make_reader(f, validate_crcs=True).iter_messages())
        f.seek(0)
        streamed = NonSeekingReader(f, validate_crcs=True)
        n_stream = sum(1 for _ in streamed.iter_messages())
    ends = dict(meta)
    assert ends["ambhil.run_end"]["status"] == "failed" and ends["ambhil.run_end"]["fault"] == why, ends
    assert ends["ambhil.run_end"]["recorder_status"] == "completed"
    assert ends["ambhil.rec_end"]["status"] == "completed"
    assert [nm for nm, _ in meta].count("ambhil.run_end") == 1
    assert n_seek == n_stream == sr["messages"], (n_seek, n_stream, sr["messages"])
    after = load_run(str(failed))
    assert np.array_equal(after["currents"]["v"], before["currents"]["v"])
    assert np.array_equal(after["sensors"]["v"], before["sensors"]["v"])
    # the same verdict again changes nothing; a run_end that says failed for fewer reasons than
    # the run's (the plant's fault, but also too many overruns) gets them all
    from ambhil.bridge.recording.run_end import mark_run_failed
    size = failed.stat().st_size
    assert mark_run_failed(str(failed), why) is None and failed.stat().st_size == size
    more = f"{why}; plant: controller timeout"
    assert mark_run_failed(str(failed), more)["fault"] == more
    assert run_end_of(str(failed))["fault"] == more and run_end_of(str(failed))["status"] == "failed"
    assert load_run(str(failed))["sensors"]["v"].shape == before["sensors"]["v"].shape


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux)")
def test_a_file_that_cannot_be_written_ends_the_recording_naming_it():
    """A full disk (/dev/full: every write fails with ENOSPC): no traceback, the summary names
    the file and the error, its status is failed (the run cannot be recorded)."""
    from ambhil.bridge.recording.recorder import RecorderConfig, record
    s = record("devfull", "/dev/full", RecorderConfig(wait_peers=(), max_duration=0.2, handle_signals=False,
                                                      end_on_plant_lost=False))
    assert s["write_error"] == "cannot write /dev/full: No space left on device", s
    assert s["status"] == "failed" and "No space left on device" in s["fault"], s


def test_the_owner_of_an_orphaned_recorder_is_gone_only_when_it_is():
    from ambhil.bridge.recording.recorder import _owner_gone
    assert not _owner_gone(os.getppid())                       # our parent lives
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    assert _owner_gone(p.pid)                                   # not our parent (and dead)

