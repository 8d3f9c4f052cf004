"""Recordings of protocol 3 (docs/protocol.md 5.3): the recorder takes only what authenticates
under the run's key (bridge/recording/gate.py), run_end says what it rejected and how the run
authenticated, and the replay to a controller poses as the plant under the key."""
from __future__ import annotations

import json
import os
import sys
import time

import numpy as np
import pytest

TESTS = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, TESTS)
import test_nodes as tn  # noqa: E402
import test_recorder as trc  # noqa: E402
from test_recorder import read_all  # noqa: E402
from test_replay import write_recording  # noqa: E402
from ambhil.bridge import protocol as pr  # noqa: E402
from ambhil.bridge.process import transport as tr  # noqa: E402
from ambhil.bridge.recording import controller_replay  # noqa: E402
from ambhil.bridge.recording import layout as rc  # noqa: E402
from ambhil.bridge.recording.load import load_run  # noqa: E402



def _keyed_controller_proc(ep, run_id, secret_hex, kp):
    from ambhil.bridge.process.config import ControllerNodeConfig
    from ambhil.bridge.process.controller_node import run_controller
    s = run_controller(tn.PController(kp=kp), ControllerNodeConfig(
        run_id, connect=ep, start_timeout=60, sample_timeout=60.0, secret=bytes.fromhex(secret_hex)))
    print(json.dumps(s))


def test_replay_to_a_controller_with_the_run_key_pairs_under_it_and_one_without_cannot(tmp_path):
    """Protocol 3: the replay poses as the plant under a key (the recording keeps no MACs: it
    seals each sample again).  A controller with the same key pairs (RunMeta sealed by the
    replay), answers every sample, ends on the replay's RUN_END; one with another key never
    proves it: the replay does not pair with it (a stranger) and sends nothing."""
    from ambhil.bridge.protocol import auth as au
    out, _, _, _ = trc.run_recorded(tmp_path, "rpkey", 200)
    key = au.new_secret()
    ep, run = tn.endpoint(), "replay-keyed"
    c = tn.py(f"import test_recording_auth as t_; t_._keyed_controller_proc({ep!r}, {run!r}, {key.hex()!r}, 2e4)")
    res = controller_replay.to_controller(out, run, listen=ep, tolerance=0.0, start_timeout=15, secret=key)
    sc = tn.last_json(c)
    assert sc["fault"] is None and res["passed"] and res["compared"] == 200, (sc, res)
    assert res["auth"] == "key" and res["foreign"] == 0 and res["strangers"] == [], res
    ep, run = tn.endpoint(), "replay-wrong-key"
    c = tn.py(f"import test_recording_auth as t_; t_._keyed_controller_proc({ep!r}, {run!r}, {au.new_secret().hex()!r}, 2e4)")
    res = controller_replay.to_controller(out, run, listen=ep, tolerance=0.0, start_timeout=3, secret=key)
    c.kill()
    assert not res["passed"] and res["sent"] == 0 and "proved the run's key" in res["fault"], res
    assert len(res["strangers"]) == 1, res


def test_a_forged_run_end_neither_ends_the_recording_nor_enters_the_run_events(tmp_path):
    """Protocol 3: a stranger that copies the plant's peer id (from its token) puts a RUN_END on
    the plant's event key with a random MAC, another on the protocol-2 key, and replays the
    plant's genuine RUN_START (its attachment and all).  The recorder obeys none: the run is
    recorded to its end, the three go to /ambhil/foreign/events (never /ambhil/events), and
    run_end counts them by reason (``auth`` 2, ``sequence`` 1).  Every process links to the
    stranger, which listens, so it is there before the run starts."""
    import threading
    from ambhil.bridge.recording.run_end import run_end_of
    ep, rep, ep_x, run, n = tn.endpoint(), tn.endpoint(), tn.endpoint(), "forged", 10000
    K = pr.keys(run)
    s = tr.open_session(listen=ep_x)
    got, plant_ids, meta_seen = {}, [], threading.Event()

    def on_event(smp):
        data = smp.payload.to_bytes()
        if pr.decode_event(data).kind == pr.EventKind.RUN_START and "start" not in got:
            got["start"] = (data, smp.attachment.to_bytes())
            meta_seen.set()
    subs = [s.declare_subscriber(pr.event_key(run, "plant"), on_event),
            s.liveliness().declare_subscriber(f"{K.root}/peer/plant/*", history=True,
                                              handler=lambda smp: plant_ids.append(
                                                  bytes.fromhex(str(smp.key_expr).rsplit("/", 1)[1])))]
    out = str(tmp_path / f"{run}.mcap")
    r = tn.py(f"import test_recorder as tr_; tr_._recorder_proc([{ep_x!r}], {run!r}, {out!r}, listen={rep!r})")
    c = tn.py(f"t._controller_proc([{ep!r}, {rep!r}, {ep_x!r}], {run!r})")
    p = tn.py(f"t._plant_proc({ep!r}, {run!r}, {n}, wait_recorder=True, connect=[{rep!r}, {ep_x!r}])")
    try:
        t_end = time.monotonic() + 300
        while not meta_seen.wait(0.05):
            assert p.poll() is None and time.monotonic() < t_end, p.communicate()
        plant = plant_ids[0]
        end = pr.encode_event(pr.Event(pr.EventKind.RUN_END, json.dumps({"reason": "completed", "steps": 7}),
                                       "plant", 10**6, 7, 7, time.time_ns()))
        s.put(pr.event_key(run, "plant"), end, attachment=plant + os.urandom(16))   # forged MAC
        s.put(f"{K.root}/events", end, attachment=plant + os.urandom(16))          # protocol 2's key
        s.put(pr.event_key(run, "plant"), got["start"][0], attachment=got["start"][1])  # a replay
        sp, sc, sr = tn.last_json(p), tn.last_json(c), tn.last_json(r)
    finally:
        tr.close_quietly(*subs, s)
    assert sp["fault"] is None and sc["fault"] is None, (sp, sc)
    assert sr["status"] == "completed" and sr["steps_recorded"] == n, sr
    # (a genuine event rejected as ``sequence`` here: its sender put two events out of seq order,
    # e.g. EventSink.emit from two threads without one lock around the seq and the put)
    assert sr["rejected"] == {"auth": 2, "sequence": 1} and sr["auth"] == "none", sr
    end_md = run_end_of(out)
    # the run_end counts the whole run's rejections: the recorder's, the plant's (its RUN_END)
    # and the controller's (its last event; it rejected the forged RUN_END too)
    whole: dict = {}
    for summ in (sr, sp, sc):
        for k, v in (summ.get("rejected") or {}).items():
            whole[k] = whole.get(k, 0) + v
    assert json.loads(end_md["rejected"]) == whole and end_md["auth"] == "none", (end_md, sp, sc)
    assert json.loads(end_md["rejected_by"])["recorder"] == {"auth": 2, "sequence": 1}
    assert sc["rejected"].get("auth", 0) >= 1, sc
    _, msgs, _ = read_all(out)
    by_topic: dict = {}
    arrived: dict = {}
    for _, ch, m in msgs:
        by_topic.setdefault(ch.topic, []).append(rc.decode_event(m.data) if "events" in ch.topic else m)
        if "events" in ch.topic and by_topic[ch.topic][-1].kind == pr.EventKind.RUN_END:
            arrived.setdefault(ch.topic, []).append(m.publish_time)
    # the forged RUN_END came well before the run's own (more than the recorder's end grace)
    assert min(arrived["/ambhil/foreign/events"]) < arrived["/ambhil/events"][0] - 0.3e9, arrived
    foreign = by_topic["/ambhil/foreign/events"]
    assert sorted(e.kind for e in foreign) == sorted([pr.EventKind.RUN_END] * 2 + [pr.EventKind.RUN_START])
    ends = [e for e in by_topic["/ambhil/events"] if e.kind == pr.EventKind.RUN_END]
    assert len(ends) == 1 and json.loads(ends[0].text)["steps"] == n, ends
    from ambhil.bridge.recording.load import load_run
    assert len(load_run(out)["sensors"]["seq"]) == n


def test_run_end_says_what_was_rejected_and_how_the_run_authenticated():
    from ambhil.bridge.recording.run_end import run_end_status
    run = {"n_steps": 10, "fault": None, "plant_end": {"reason": "completed", "steps": 10, "fault": None}}
    e = run_end_status(run, "RUN_END event", 10, 10, {"auth": 3, "sequence": 0}, "key")
    assert e["status"] == "completed" and e["rejected"] == '{"auth":3}' and e["auth"] == "key"
    e = run_end_status(run, "RUN_END event", 10, 10)
    assert e["rejected"] == "{}" and e["auth"] == "unknown"       # a run of an older protocol


def test_a_keyed_run_is_recorded_under_its_key_and_a_recorder_without_it_takes_nothing(tmp_path):
    """Plant, controller and recorder with the run's key: the recording is complete and says
    ``auth`` key.  A second recorder with another key (linked to the plant) proves no plant and
    learns no session key: nothing of the run enters its channels, its events (under a key it
    does not have) go to /ambhil/foreign/events, and run_end counts the rest as ``auth``."""
    from ambhil.bridge.protocol import auth as au
    from ambhil.bridge.recording.load import load_run
    from ambhil.bridge.recording.run_end import run_end_of
    ep, rep, rep2, run, n = tn.endpoint(), tn.endpoint(), tn.endpoint(), "keyed", 300
    key, other = au.new_secret(), au.new_secret()
    out, out2 = str(tmp_path / f"{run}.mcap"), str(tmp_path / "other.mcap")
    r = tn.py(f"import test_recorder as tr_; tr_._recorder_proc(None, {run!r}, {out!r}, listen={rep!r}, "
              f"secret=bytes.fromhex({key.hex()!r}))")
    r2 = tn.py(f"import test_recorder as tr_; tr_._recorder_proc(None, {run!r}, {out2!r}, listen={rep2!r}, "
               f"wait_peers=('plant',), secret=bytes.fromhex({other.hex()!r}))")
    c = tn.py(f"import test_recording_auth as t_; t_._keyed_controller_proc([{ep!r}, {rep!r}], {run!r}, {key.hex()!r}, 2e4)")
    p = tn.py(f"t._plant_proc({ep!r}, {run!r}, {n}, wait_recorder=True, connect=[{rep!r}, {rep2!r}], "
              f"secret=bytes.fromhex({key.hex()!r}))")
    sp, sc, sr, sr2 = tn.last_json(p), tn.last_json(c), tn.last_json(r), tn.last_json(r2)
    assert sp["fault"] is None and sc["fault"] is None, (sp, sc)
    assert sr["status"] == "completed" and sr["steps_recorded"] == n and sr["auth"] == "key", sr
    assert sr["rejected"] == {}, sr
    assert run_end_of(out)["auth"] == "key" and run_end_of(out)["rejected"] == "{}"
    assert len(load_run(out)["sensors"]["seq"]) == n
    # the recorder without the key: nothing of the run is the run's
    assert sr2["steps_recorded"] == 0 and sr2["auth"] == "unknown" and sr2["rejected"].get("auth", 0) > 0, sr2
    assert sr2["status"] == "failed", sr2
    _, msgs, _ = read_all(out2)
    topics = {c.topic for _, c, _ in msgs}
    assert "/ambhil/events" not in topics and "/ambhil/meta" not in topics, topics
    assert "/ambhil/foreign/events" in topics, topics


def test_the_gate_holds_what_comes_before_the_runmeta_and_judges_every_message():
    """The recorder's judge (bridge/recording/gate.py), fed directly, on one loopback session
    that is also the plant (its responder answers the gate's challenge): held until the RunMeta
    of the proven plant, then in order; K_run events recorded, never as session ones; forged,
    replayed, wrong-key and wrong-id messages rejected by reason; --source wire samples checked
    by their seal."""
    from ambhil.bridge.process.pairing import Responder, peer_key
    from ambhil.bridge.protocol import auth as au
    from ambhil.bridge.recording.gate import FOREIGN, RUN, SESSION, Gate
    run, key = "gate1", au.new_secret()
    K = pr.keys(run)
    s = tr.open_session(listen=tn.endpoint())
    plant_id, ctl_id = os.urandom(16), os.urandom(16)
    plant = au.RunAuth(key, run, "plant", plant_id)
    ctl = au.RunAuth(key, run, "controller", ctl_id)
    resp = Responder(s, plant)
    tok = s.liveliness().declare_token(peer_key(run, "plant", plant_id))
    gate = Gate(s, au.RunAuth(key, run, "recorder", os.urandom(16)), wire=True)
    try:
        def ev(who, seq, kind=pr.EventKind.INFO, src=None):
            d = pr.encode_event(pr.Event(kind, "x", src or who.role, seq, 0, 0, 0))
            return d, who.attach(f"events/{who.role}", d)
        early = ev(plant, 0)                                    # under K_run, before pairing
        assert gate.offer(pr.event_key(run, "plant"), *early, 1) == []   # held
        np_, nc = au.nonce(), au.nonce()
        plant.pair(plant_id, ctl_id, np_, nc)
        ctl.pair(plant_id, ctl_id, np_, nc)
        meta = pr.encode_meta(pr.RunMeta({"plant_peer_id": plant_id.hex(), "controller_peer_id": ctl_id.hex(),
                                          "auth": plant.describe()}))
        forged = pr.encode_meta(pr.RunMeta({"plant_peer_id": plant_id.hex(), "controller_peer_id": ctl_id.hex(),
                                            "auth": dict(plant.describe(), nonce_plant=au.nonce().hex())}))
        stranger = au.RunAuth(au.new_secret(), run, "plant", plant_id)      # another key, the plant's id
        stranger.pair(plant_id, ctl_id, au.nonce(), au.nonce())
        gate.offer(K.meta, forged, stranger.attach("meta", forged), 2)
        out = gate.offer(K.meta, meta, plant.attach("meta", meta), 3)
        t_end = time.monotonic() + 10
        while not out and time.monotonic() < t_end:             # until the challenge proved the plant
            time.sleep(0.01)
            out = gate.poll()
        assert [(k, t, how) for k, _, t, how in out] == [
            (pr.event_key(run, "plant"), 1, RUN), (K.meta, 3, SESSION)], out
        assert gate.rejected == {"auth": 1} and gate.mode == "key"
        judge = lambda k, d, a: [(kk.rsplit("/", 2)[-2:], how) for kk, _, _, how in gate.offer(k, d, a, 9)]  # noqa: E731
        end = ev(plant, 5, pr.EventKind.RUN_END)
        assert judge(pr.event_key(run, "plant"), *end) == [(["events", "plant"], SESSION)]
        assert judge(pr.event_key(run, "plant"), *end) == [(["foreign", "events"], FOREIGN)]     # replayed
        assert judge(pr.event_key(run, "plant"), end[0], plant_id + bytes(16)) == [(["foreign", "events"], FOREIGN)]
        assert judge(pr.event_key(run, "plant"), *ev(plant, 6, src="controller")) == [(["foreign", "events"], FOREIGN)]
        assert judge(pr.event_key(run, "controller"), *ev(ctl, 1)) == [(["events", "controller"], SESSION)]
        assert judge(f"{K.root}/events", *ev(plant, 7)) == [(["foreign", "events"], FOREIGN)]  # protocol 2's key
        tm = b"\0" * 64
        assert judge(K.timing, tm, plant.attach("timing", tm)) == [([run, "timing"], SESSION)]
        assert judge(K.timing, tm, ctl.attach("timing", tm)) == []          # not the plant's: counted only
        sc = pr.SensorCodec(4, me=plant.seal("plant/sensors"))
        good = sc.encode(0, 0, 0, 0, np.zeros(4))
        assert judge(K.sensors, good, None) == [(["plant", "sensors"], SESSION)]
        bad_mac = good[:-1] + bytes([good[-1] ^ 1])
        assert judge(K.sensors, bad_mac, None) == [(["plant", "sensors"], FOREIGN)]
        other = pr.SensorCodec(4, me=au.RunAuth(au.new_secret(), run, "plant", plant_id).seal("plant/sensors"))
        assert judge(K.sensors, other.encode(1, 1, 0, 0, np.zeros(4)), None) == [(["plant", "sensors"], FOREIGN)]
        cc = pr.CurrentCodec(4, me=ctl.seal("controller/currents"))
        assert judge(K.currents, cc.encode(0, 0, 0, 0, 0, np.zeros(4)), None) == [(["controller", "currents"], SESSION)]
        assert judge(K.currents, pr.CurrentCodec(4, me=os.urandom(16)).encode(0, 0, 0, 0, 0, np.zeros(4)),
                     None) == [(["controller", "currents"], FOREIGN)]
        assert gate.rejected == {"auth": 7, "sequence": 1, "peer": 1}, gate.rejected
        assert gate.rejected_topics["timing"] == 1
    finally:
        gate.finish()
        resp.undeclare()
        tr.close_quietly(tok, s)


@pytest.mark.parametrize("old", ["wire-v1", "wire-v2"])
def test_version_1_and_2_recordings_of_the_earlier_layout_read_as_version_3(tmp_path, old):
    """Protocol version 2 appended the sender's peer id to SensorSample / CurrentCommand, version
    3 a MAC after it.  A recording that holds version-1 or -2 wire bytes verbatim still loads,
    with the same values, and its restored wire bytes are version 3 (the id of no sender / the
    recorded id, and a zero mac: a recording keeps no MACs), which the replay re-addresses and
    seals with its own id and key."""
    from ambhil.bridge import protocol as pr
    a = load_run(str(write_recording(tmp_path / "v3.mcap", 30, layout="wire")))
    b = load_run(str(write_recording(tmp_path / "old.mcap", 30, layout=old)))
    assert b["rejected"] == 0 and len(b["sensors"]["seq"]) == 30
    for k in ("sensors", "currents"):
        assert np.array_equal(a[k]["v"], b[k]["v"]) and np.array_equal(a[k]["seq"], b[k]["seq"])
        assert [r[:-16] for r in a[k]["raw"]] == [r[:-16] for r in b[k]["raw"]]
        assert all(r[-16:] == bytes(16) for r in b[k]["raw"])
    m = pr.decode_sensor(b["sensors"]["raw"][3])
    assert m.seq == 3 and b["sensors"]["raw"][3][4:6] == b"\x03\x00" and m.peer == pr.NO_PEER



def test_a_wire_recording_checks_each_sample_by_its_seal(tmp_path):
    """``--source wire``: the recorder takes the loop's messages off the wire and checks each
    one's id and MAC under the session key it learnt from the RunMeta: a keyed run's are all
    the run's, bit for bit the plant's trace, nothing foreign."""
    from ambhil.bridge.protocol import auth as au
    ep, rep, run, n = tn.endpoint(), tn.endpoint(), "wirekey", 300
    key = au.new_secret()
    out = str(tmp_path / f"{run}.mcap")
    r = tn.py(f"import test_recorder as tr_; tr_._recorder_proc(None, {run!r}, {out!r}, listen={rep!r}, "
              f"source='wire', secret=bytes.fromhex({key.hex()!r}))")
    c = tn.py(f"import test_recording_auth as t_; t_._keyed_controller_proc([{ep!r}, {rep!r}], {run!r}, "
              f"{key.hex()!r}, 2e4)")
    p = tn.py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r}, wait_recorder=True, "
              f"connect={rep!r}, secret=bytes.fromhex({key.hex()!r}))")
    sp, sc, sr = tn.last_json(p), tn.last_json(c), tn.last_json(r)
    assert sp["fault"] is None and sc["fault"] is None, (sp, sc)
    assert sr["status"] == "completed" and sr["steps_recorded"] == n and sr["rejected"] == {}, sr
    assert sr["source"] == "wire" and sr["auth"] == "key", sr
    rec, trace = load_run(out), np.load(tmp_path / "tr.npz")
    assert np.array_equal(rec["sensors"]["v"], trace["y"][:n]) and np.array_equal(rec["currents"]["v"], trace["u"])
    _, msgs, _ = read_all(out)
    assert not [c.topic for _, c, _ in msgs if "foreign" in c.topic]


def test_a_protocol_2_payload_kept_as_malformed_still_reads(tmp_path):
    """A recording of protocol 2 holds the verbatim payloads the recorder could not transcode
    (another axis count) with a 16-byte trailer (the id, no mac): load_run upgrades them to
    version 3 and reads them as before (the sample of 6 axes counted, not lost in a traceback)."""
    from mcap.writer import Writer
    from ambhil.bridge.recording.writer import Writer as RecordedWriter
    K, p = pr.keys("p2"), tmp_path / "p2.mcap"
    v3 = pr.encode_sensor(9, 9, 9000, 0, np.ones(6))
    v2 = v3[:4] + b"\x02\x00" + v3[6:-16]
    with open(p, "wb") as f:
        w = Writer(f)
        w.start(profile=rc.PROFILE, library="test")
        rw = RecordedWriter(w, "p2")
        for k in range(3):
            rw.put(K.sensors, pr.encode_sensor(k, k, 1000 * k, 0, np.zeros(4)), 0)
        rw.malformed(K.sensors, v2, "axes: 6 axes, the run has 4", 0)
        w.finish()
    run = load_run(str(p))
    assert list(run["sensors"]["seq"]) == [0, 1, 2] and run["rejected"] == 1, run["rejected_reasons"]
    assert list(run["rejected_reasons"]) == ["SensorSample: axis count 6 != 4"], run["rejected_reasons"]
