"""Replay: MCAP -> .rrd, and replay to a controller under test (pass / fail on a gain change)."""
from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest

TESTS = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, TESTS)
import test_nodes as tn  # noqa: E402
import test_recorder as trc  # noqa: E402
from ambhil.bridge.recording import controller_replay, replay, rerun_view
from ambhil.bridge.recording.load import load_run
from ambhil.bridge.recording.recover import RecordingError, recover  # noqa: E402


def test_to_rerun_writes_rrd_with_series_and_orbits(tmp_path):
    out, sp, _, _ = trc.run_recorded(tmp_path, "rp1", 300)
    assert sp["fault"] is None
    rrd = str(tmp_path / "rp1.rrd")
    info = replay.to_rerun(out, rrd)
    assert info["samples"] == 300 and info["currents"] == 300
    assert info["stations"] == ["station_0", "station_1"]
    import rerun as rr
    store = rr.chunk.RrdReader(rrd).stream().collect()
    ents = {c.entity_path for c in store.stream()}
    for e in ("/sensors/displacement", "/controller/current", "/orbit/station_0",
              "/orbit/station_1", "/timing/rtt_us", "/events"):
        assert e in ents, (e, ents)
    rows = sum(c.num_rows for c in store.stream() if c.entity_path == "/sensors/displacement"
               and not c.is_static)
    assert rows == 300
    # orbit points are in um (the viewer draws nothing for points at the 1e-6 m scale): they
    # equal the recorded displacements x 1e6, y negated (rerun's 2D views point y down; +y up)
    pts = []
    for c in store.stream():
        if c.entity_path == "/orbit/station_0" and not c.is_static:
            pts += c.to_record_batch().column("Points2D:positions").to_pylist()
    y = load_run(out)["sensors"]["v"][:, :2] * [1, -1]
    got = np.array([p[0] for p in pts])
    assert got.shape == y.shape and np.allclose(got, y * 1e6, rtol=1e-6), (got[:3], y[:3])
    assert 1.0 < np.abs(got).max() < 1e3          # SpringPlant starts at 100 um


def test_load_run_matches_trace(tmp_path):
    out, sp, _, _ = trc.run_recorded(tmp_path, "rp2", 200)
    run = load_run(out)
    from ambhil.bridge.process.reference import run_inprocess
    Y, U = run_inprocess(tn.SpringPlant(), tn.PController(), 200)
    assert np.array_equal(run["sensors"]["v"], Y[:200])
    assert np.array_equal(run["currents"]["v"], U)


def _replay_against(tmp_path, mcap, kp):
    ep, run = tn.endpoint(), f"replay{int(kp)}"
    c = tn.py(f"t._controller_proc({ep!r}, {run!r}, kp={kp!r})")
    res = controller_replay.to_controller(mcap, run, listen=ep, tolerance=1e-9, start_timeout=15)
    sc = tn.last_json(c)
    assert sc["fault"] is None, sc
    return res


def test_replay_to_controller_pass_and_fail(tmp_path):
    out, sp, _, _ = trc.run_recorded(tmp_path, "rp3", 300)
    ok = _replay_against(tmp_path, out, 2e4)
    assert ok["passed"] and ok["compared"] == 300 and ok["max_abs_dev"] == 0.0, ok
    bad = _replay_against(tmp_path, out, 2.2e4)
    assert not bad["passed"] and bad["max_abs_dev"] > 1e-6, bad
    assert bad["worst"]["axis"] in range(4) and bad["worst"]["step"] >= 0


# --------------------------------------------------------------------------- bad files (issue 10 item 4)
def write_recording(path, n, *, run_id="bad1", n_axes=4, bad_seq_at=None, bad_axes_at=None, layout="ros2",
                    meta=None):
    """A small ambhil recording written like the recorder does (bridge/recording/layout.py: profile ros2,
    stamped recorded messages; ``layout="wire"``: the earlier layout, wire bytes verbatim, topic =
    key; ``"wire-v1"`` / ``"wire-v2"``: the same with protocol version 1 / 2 messages): n sensor samples and n current commands; optionally one current command with seq
    2**64-1 and one sensor sample with a different axis count."""
    from mcap.writer import CompressionType, Writer
    from ambhil.bridge import protocol as pr
    from ambhil.bridge.recording import layout as rc
    from ambhil.bridge.recording.writer import Writer as RecordedWriter
    K = pr.keys(run_id)
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD, chunk_size=2048)   # several chunks
        w.start(profile=rc.PROFILE if layout == "ros2" else "", library="test")
        if layout == "ros2":
            rw = RecordedWriter(w, run_id)

            def put(key, data, t, seq):
                rw.put(key, data, t)
            if meta is not None:                   # a RunMeta first, as the recorder writes it
                rw.put(K.meta, pr.encode_meta(pr.RunMeta(dict(meta, run_id=run_id, n_axes=n_axes))), 0)
        else:
            sch = {t: w.register_schema(pr.schema_name(t), "ros2msg", d.encode()) for t, d in pr.MSG_DEFS.items()}
            cs = w.register_channel(K.sensors, "cdr", sch["SensorSample"])
            cc = w.register_channel(K.currents, "cdr", sch["CurrentCommand"])

            def put(key, data, t, seq):
                if layout == "wire-v1":            # version 1: no sender id after the vector
                    data = data[:4] + b"\x01\x00" + data[6:-32]
                elif layout == "wire-v2":          # version 2: the id, no mac
                    data = data[:4] + b"\x02\x00" + data[6:-16]
                w.add_message(cs if key == K.sensors else cc, t, data, t, seq)
        for k in range(n):
            t = 10_000 * k
            y = 1e-6 * np.sin(0.1 * k + np.arange(n_axes if k != bad_axes_at else n_axes + 2))
            put(K.sensors, pr.encode_sensor(k, k, t, t, y), t, k)
            seq = 2 ** 64 - 1 if k == bad_seq_at else k
            put(K.currents, pr.encode_current(seq, k, t, t, t, np.cos(0.1 * k + np.arange(n_axes))), t + 1, k)
        w.finish()
    return path


def _main(capsys, *argv):
    from ambhil.bridge.cli import main as cli
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _err(err, command):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"ambhil {command}: error: ") and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("layout", ["ros2", "wire"])
def test_malformed_messages_are_skipped_and_counted(tmp_path, capsys, layout):
    """One current command with seq 2**64-1 (an OverflowError in load_run before) and one sensor
    sample with 6 axes instead of 4: the recording converts, without them, and says so (in the
    recorded layout and in the earlier one of wire bytes verbatim)."""
    mcap = write_recording(tmp_path / "m.mcap", 50, bad_seq_at=7, bad_axes_at=9, layout=layout)
    run = load_run(str(mcap))
    assert run["rejected"] == 2 and len(run["sensors"]["seq"]) == 49 and len(run["currents"]["seq"]) == 49
    assert 7 not in run["currents"]["seq"] and 9 not in run["sensors"]["seq"]
    assert run["rejected_reasons"] == {"CurrentCommand: seq or step out of range": 1,
                                       "SensorSample: axis count 6 != 4": 1}
    code, out, err = _main(capsys, "replay", mcap)
    assert code == 0 and (tmp_path / "m.rrd").exists(), out + err
    assert "49 samples" in out and "skipped 2 malformed message(s)" in out
    code, out, err = _main(capsys, "replay", mcap, "--out", tmp_path / "j", "--json")
    s = json.loads(out)
    assert code == 0 and len(out.splitlines()) == 1 and s["rejected"] == 2 and (tmp_path / "j" / "m.rrd").exists()


def test_replay_truncated_file_names_recover_and_recover_restores_it(tmp_path, capsys):
    full = write_recording(tmp_path / "full.mcap", 400)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(RecordingError, match="truncated"):
        load_run(str(cut))
    code, out, err = _main(capsys, "replay", cut)
    assert code == 2 and out == "" and not (tmp_path / "cut.rrd").exists()
    line = _err(err, "replay")
    assert "truncated MCAP" in line and f"ambhil recover {cut}" in line
    code, out, err = _main(capsys, "recover", cut, "--json")
    s = json.loads(out)
    fixed = tmp_path / "cut.recovered.mcap"
    assert code == 0 and s["destination"] == str(fixed) and s["source_was"] == "truncated"
    assert 0 < s["messages"] < 800 and cut.read_bytes() == data[: len(data) * 2 // 3]  # source untouched
    a, b = load_run(str(fixed)), load_run(str(full))
    from mcap.reader import make_reader
    with open(fixed, "rb") as f:
        assert make_reader(f).get_header().profile == "ros2"      # the recorded layout's profile kept
    k = len(a["sensors"]["seq"])
    assert k > 0 and np.array_equal(a["sensors"]["v"], b["sensors"]["v"][:k])


@pytest.mark.parametrize("content,why", [(b"", "empty file"), (b"\x00" * 300, "MCAP magic"),
                                        (bytes(range(256)) * 20, "MCAP magic")])
def test_not_an_mcap_file(tmp_path, capsys, content, why):
    f = tmp_path / "x.mcap"
    f.write_bytes(content)
    for cmd in ("replay", "recover"):
        code, out, err = _main(capsys, cmd, f)
        assert code == 2 and out == ""
        line = _err(err, cmd)
        assert f"{f}: not an MCAP file" in line and why in line
    assert f.read_bytes() == content and sorted(p.name for p in tmp_path.iterdir()) == ["x.mcap"]


def test_recover_never_writes_over_its_source(tmp_path, capsys, monkeypatch):
    mcap = write_recording(tmp_path / "run.mcap", 100)
    data = mcap.read_bytes()
    monkeypatch.chdir(tmp_path)
    for dst in (mcap, "run.mcap", "./run.mcap"):
        code, out, err = _main(capsys, "recover", "run.mcap", dst, "--force")
        assert code == 2 and "is the source recording" in _err(err, "recover")
    link = tmp_path / "link.mcap"
    link.symlink_to(mcap)
    code, out, err = _main(capsys, "recover", mcap, link, "--force")
    assert code == 2 and "is the source recording" in _err(err, "recover")
    with pytest.raises(RecordingError):
        recover(str(mcap), str(link))
    assert mcap.read_bytes() == data and load_run(str(mcap))["sensors"]["v"].shape == (100, 4)
    # an existing destination is kept unless --force
    other = tmp_path / "other.mcap"
    other.write_bytes(b"keep me")
    code, out, err = _main(capsys, "recover", mcap, other)
    assert code == 2 and "exists" in _err(err, "recover") and other.read_bytes() == b"keep me"
    code, out, err = _main(capsys, "recover", mcap, other, "--force")
    assert code == 0 and "recovered 200 messages" in out and "was complete" in out
    assert len(load_run(str(other))["sensors"]["seq"]) == 100


def test_recover_that_finds_nothing_fails_and_writes_nothing(tmp_path, capsys):
    from ambhil.bridge.recording.recover import MAGIC
    f = tmp_path / "stub.mcap"
    f.write_bytes(MAGIC + b"\x01" + b"\xff" * 8)       # a header record cut in its length field
    keep = tmp_path / "out.mcap"
    keep.write_bytes(b"previous")
    code, out, err = _main(capsys, "recover", f, keep, "--force")
    assert code == 1 and out == "" and "recovered nothing" in _err(err, "recover")
    assert keep.read_bytes() == b"previous" and sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap", "stub.mcap"]


def _rrd_rows(rrd):
    """{entity: (sim times in ns, values)} of every temporal Scalars / Points2D column, by time."""
    import rerun as rr
    out = {}
    for c in rr.chunk.RrdReader(str(rrd)).stream().collect().stream():
        if c.is_static:
            continue
        rb = c.to_record_batch()
        col = next((n for n in rb.schema.names if n in ("Scalars:scalars", "Points2D:positions")), None)
        if col is None or "sim_time" not in rb.schema.names:
            continue
        t = np.array(rb.column("sim_time").cast("int64").to_pylist())
        v = [np.array(x, float).ravel() for x in rb.column(col).to_pylist()]
        out.setdefault(c.entity_path, []).extend(zip(t, v))
    res = {}
    for e, rows in out.items():
        rows.sort(key=lambda r: r[0])
        res[e] = (np.array([r[0] for r in rows]), np.array([r[1] for r in rows]))
    return res


def test_streamed_conversion_has_the_content_of_the_whole_file_conversion(tmp_path):
    """Issue 14: to_rerun streams the file (chunks, send_columns blocks).  Blocks of 7 rows over
    a recording of many chunks give exactly the rows of one block, which equal load_run's arrays
    (um, y up for orbits; us for timing); a recording of the earlier layout (wire bytes,
    converted whole as before) gives the same content as the same data in the recorded layout."""
    out, sp, _, _ = trc.run_recorded(tmp_path, "rps", 400)
    assert sp["fault"] is None
    a, b = tmp_path / "a.rrd", tmp_path / "b.rrd"
    seen = []
    replay.to_rerun(out, str(a), block=7, progress=lambda d, t: seen.append((d, t)))
    replay.to_rerun(out, str(b), block=10**9)
    A, B = _rrd_rows(a), _rrd_rows(b)
    assert seen and seen[-1][0] == seen[-1][1] and len(seen) > 3          # several chunks, progress to the end
    assert set(A) == set(B) >= {"/sensors/displacement", "/controller/current", "/orbit/station_0",
                                "/orbit/station_1", "/timing/rtt_us", "/timing/tet_us"}
    for e in A:
        assert np.array_equal(A[e][0], B[e][0]) and np.array_equal(A[e][1], B[e][1]), e
    run = load_run(out)
    S, C, T = run["sensors"], run["currents"], run["timing"]
    t, v = A["/sensors/displacement"]
    assert np.array_equal(t, S["t_ns"]) and np.allclose(v, S["v"] * 1e6, rtol=1e-12, atol=0)
    t, v = A["/controller/current"]
    assert np.array_equal(t, C["t_ns"]) and np.array_equal(v, C["v"])
    t, v = A["/orbit/station_1"]
    assert np.allclose(v, S["v"][:, 2:4] * [1e6, -1e6], rtol=1e-6, atol=0)        # float32 positions
    t, v = A["/timing/tet_us"]
    assert np.array_equal(t, T["step"] * T["period_ns"]) and np.allclose(v[:, 0], T["tet_ns"] / 1e3)
    # the same data in both layouts: the same content
    w, r = tmp_path / "w.mcap", tmp_path / "r.mcap"
    write_recording(w, 300, layout="wire")
    write_recording(r, 300, layout="ros2")
    replay.to_rerun(str(w), str(tmp_path / "w.rrd"))
    replay.to_rerun(str(r), str(tmp_path / "r.rrd"), block=50)
    W, R = _rrd_rows(tmp_path / "w.rrd"), _rrd_rows(tmp_path / "r.rrd")
    assert set(W) == set(R) and len(W["/sensors/displacement"][0]) == 300
    for e in W:
        assert np.array_equal(W[e][0], R[e][0]) and np.array_equal(W[e][1], R[e][1]), e


def test_orbit_scale_is_common_and_shows_the_clearance_when_the_orbit_nears_it():
    half, step = rerun_view.orbit_scale(8.45, [150.0, 150.0, 150.0])
    assert half == 15.0 and step == 5.0          # the 8.45 um orbit fills 56 %, the 1.1 um one 7 %
    half, step = rerun_view.orbit_scale(60.0, [150.0, 120.0])
    assert half >= 165.0 and half - step < 165.0  # 60 um >= 30 % of 120 um: the whole clearance
    assert rerun_view.orbit_scale(0.0, [])[0] > 0
    assert rerun_view.orbit_scale(60.0, [75.0], [150.0])[0] == rerun_view.orbit_scale(60.0, [75.0])[0]  # gap not needed
    assert rerun_view.orbit_scale(80.0, [75.0], [150.0])[0] >= 165.0   # past the clearance: the whole gap


def _static_labels(rrd) -> dict:
    """{entity: labels} of the static Points2D labels of an .rrd."""
    import rerun as rr
    out = {}
    for c in rr.chunk.RrdReader(str(rrd)).stream().collect().stream():
        rb = c.to_record_batch()
        if c.is_static and "Points2D:labels" in rb.schema.names:
            out[c.entity_path] = [x for row in rb.column("Points2D:labels").to_pylist() for x in (row or [])]
    return out


def test_orbit_views_draw_the_touchdown_clearance_and_the_magnetic_gap_apart(tmp_path):
    """The red circle is each station's touchdown clearance (RunMeta ``touchdown_clearances_m``),
    the magnetic gap a grey one of its own; a recording from before the clearance was carried shows
    half the gap, said to be assumed."""
    meta = {"station_names": ["A", "B"], "gaps_m": [1.5e-4, 1.5e-4], "touchdown_clearances_m": [6e-5, 4e-6],
            "touchdown_clearances_given": [True, True]}
    new = write_recording(tmp_path / "new.mcap", 50, meta=meta)       # orbits of ~1.4 um
    replay.to_rerun(str(new), str(tmp_path / "new.rrd"))
    lab = _static_labels(tmp_path / "new.rrd")
    # the ~1.4 um orbit reaches 30 % of B's 4 um clearance: the view takes in both clearances (66 um)
    assert lab["/orbit/A/clearance/label"] == ["touchdown clearance 60 um"]
    assert lab["/orbit/B/clearance/label"] == ["touchdown clearance 4 um"]
    assert "/orbit/A/magnetic_gap/label" not in lab                          # 150 um: outside the view
    # an orbit past the touchdown clearance: the view takes in the magnetic gap (2 um) as well
    old = write_recording(tmp_path / "old.mcap", 50, meta={"station_names": ["A", "B"], "gaps_m": [2e-6, 2e-6]})
    replay.to_rerun(str(old), str(tmp_path / "old.rrd"))
    lab = _static_labels(tmp_path / "old.rrd")
    assert lab["/orbit/A/clearance/label"] == ["touchdown clearance 1 um (assumed: half the gap)"]
    assert lab["/orbit/A/magnetic_gap/label"] == ["magnetic gap 2 um"]
    assert rerun_view.touchdown_clearances({"gaps_m": [1.5e-4]}, 1) == [(75.0, False)]


def test_batch_transcoding_equals_one_by_one_also_for_malformed_payloads(tmp_path):
    """The recorder transcodes a RecordBatch at once (recording.Writer.put_many): the file reads
    back exactly as when each payload is put alone, malformed ones (NaN, another axis count, cut
    short) kept aside with their reason, and the wire bytes of the good ones restored exactly."""
    import struct
    from mcap.writer import Writer
    from ambhil.bridge import protocol as pr
    from ambhil.bridge.recording import layout as rc
    from ambhil.bridge.recording.writer import Writer as RecordedWriter
    K = pr.keys("pm")
    good = [pr.encode_sensor(k, k, 1000 * k, 7 * k, np.sin(np.arange(4) + k)) for k in range(40)]
    nan = bytearray(good[5])
    struct.pack_into("<d", nan, 52 + 8, float("nan"))
    datas = good[:5] + [bytes(nan)] + good[6:20] + [pr.encode_sensor(99, 99, 0, 0, np.ones(6))] + good[20:30] \
        + [good[30][:-3]] + good[31:]
    walls = list(range(len(datas)))
    paths = []
    for how in ("one", "many"):
        p = tmp_path / f"{how}.mcap"
        with open(p, "wb") as f:
            w = Writer(f)
            w.start(profile=rc.PROFILE, library="test")
            rw = RecordedWriter(w, "pm")
            if how == "one":
                for d, t in zip(datas, walls):
                    rw.put(K.sensors, d, t)
            else:
                for k in range(0, len(datas), 16):
                    rw.put_many(K.sensors, "SensorSample", datas[k:k + 16], walls[k:k + 16])
            w.finish()
        paths.append(p)
    a, b = load_run(str(paths[0])), load_run(str(paths[1]))
    assert a["rejected"] == b["rejected"] == 3 and a["rejected_reasons"] == b["rejected_reasons"]
    assert np.array_equal(a["sensors"]["seq"], b["sensors"]["seq"]) and len(a["sensors"]["seq"]) == 38
    # restored exactly but for the mac (a recording keeps none)
    assert a["sensors"]["raw"] == b["sensors"]["raw"] == [g[:-16] + bytes(16) for k, g in enumerate(good)
                                                          if k not in (5, 30)]


def _copy_mcap(src, dst, *, topic=lambda ch: ch.topic, metadata=lambda ch: dict(ch.metadata),
               keep=lambda ch, m: True):
    """A copy of an MCAP with each channel's topic and metadata as given and only the messages
    ``keep`` keeps (schemas and metadata records as they are)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer
    with open(src, "rb") as f, open(dst, "wb") as g:
        rd = make_reader(f)
        s = rd.get_summary()
        w = Writer(g)
        w.start(profile=rd.get_header().profile, library="test")
        sm = {sid: w.register_schema(sc.name, sc.encoding, sc.data) for sid, sc in s.schemas.items()}
        cm = {cid: w.register_channel(topic(ch), ch.message_encoding, sm[ch.schema_id], metadata(ch))
              for cid, ch in s.channels.items()}
        for _, ch, m in rd.iter_messages(log_time_order=False):
            if keep(ch, m):
                w.add_message(cm[ch.id], m.log_time, m.data, m.publish_time, m.sequence)
        for md in rd.iter_metadata():
            w.add_metadata(md.name, dict(md.metadata))
        w.finish()
    return dst


def _as_run_id_topics(src, dst):
    """The same recording in the layout before fixed topic names: every topic ``/`` + the zenoh
    key (run id included) and no ``key`` in the channel metadata."""
    return _copy_mcap(src, dst, topic=lambda ch: "/" + ch.metadata["key"],
                      metadata=lambda ch: {k: v for k, v in ch.metadata.items() if k != "key"})


def test_fixed_topic_names_and_recordings_with_run_id_topics_still_read(tmp_path):
    """A recording's topics are the same for every run (a Foxglove layout or rosbag script fits
    all); the run id is in the metadata.  Recordings whose topics carried the run id read alike."""
    from mcap.reader import make_reader
    path = write_recording(tmp_path / "fixed.mcap", 40, run_id="run-A7")
    with open(path, "rb") as f:
        topics = sorted(c.topic for c in make_reader(f).get_summary().channels.values())
    assert topics == ["/ambhil/controller/currents", "/ambhil/plant/sensors"], topics
    old = _as_run_id_topics(path, tmp_path / "old.mcap")
    with open(old, "rb") as f:
        assert all("run-A7" in c.topic for c in make_reader(f).get_summary().channels.values())
    a, b = load_run(str(path)), load_run(str(old))
    assert a["run_id"] == b["run_id"] == "run-A7"
    for k in ("sensors", "currents"):
        assert len(a[k]["seq"]) == 40 and np.array_equal(a[k]["v"], b[k]["v"]) and a[k]["raw"] == b[k]["raw"]
    for p in (path, old):
        replay.to_rerun(str(p), str(tmp_path / (p.stem + ".rrd")))
        assert (tmp_path / (p.stem + ".rrd")).stat().st_size > 0


# --------------------------------------------------------------------------- conformance: every FAIL says why
def _without_last_currents(src, dst, k):
    """The recording with its last ``k`` recorded currents left out (as a real-time run whose
    last replies never reached the plant)."""
    from mcap.reader import make_reader
    with open(src, "rb") as f:
        cur = [m.sequence for _, ch, m in make_reader(f).iter_messages(log_time_order=False)
               if ch.topic.endswith("controller/currents")]
    last = set(sorted(cur)[-k:])
    return str(_copy_mcap(src, dst, keep=lambda ch, m: not (ch.topic.endswith("controller/currents")
                                                              and m.sequence in last)))


def _conform_against(mcap, kp, run):
    from ambhil.bridge.recording.conform import conform
    ep = tn.endpoint()
    c = tn.py(f"t._controller_proc({ep!r}, {run!r}, kp={kp!r})")      # started by hand
    res = conform(mcap, run, listen=ep, tolerance=0.0, start_timeout=120)
    assert tn.last_json(c)["fault"] is None
    return res


def test_conformance_names_why_it_fails_and_what_it_could_not_compare(tmp_path):
    """A recording that lacks its last 3 currents: the same controller passes bit for bit on
    the samples that have one, and the verdict says which samples were not compared and why
    (before: FAIL, "297 of 300 samples compared, largest deviation 0 A", no reason); a changed
    gain fails naming the cause: the axes, how many samples, the largest deviation with its
    seq, step and time."""
    from ambhil.bridge.recording.conform import table
    out, sp, _, _ = trc.run_recorded(tmp_path, "cf1", 300)
    cut = _without_last_currents(out, tmp_path / "cut.mcap", 3)
    ok = _conform_against(cut, 2e4, "conf-ok")
    lines = table(ok)
    assert ok["passed"] and ok["compared"] == 297 and ok["sent"] == 300, ok
    assert lines[0].startswith("conformance PASS: 297 of 300 samples compared"), lines
    assert ok["not_compared"]["count"] == 3 and ok["not_compared"]["seqs"] == [297, 298, 299]
    assert any(ln.startswith("  not compared: 3 samples (seq 297-299): the recording ends before "
                             "their replies") for ln in lines), lines
    bad = _conform_against(out, 2.2e4, "conf-bad")
    lines = table(bad)
    assert not bad["passed"] and lines[0].startswith("conformance FAIL: currents deviate by more than 0 A on "), lines
    top = max(bad["axes"], key=lambda a: a["max_abs_dev"])
    assert f"largest {top['max_abs_dev']:.3g} A on axis {top['axis']} at seq {top['seq']}, step {top['step']}, t = " in lines[0]
    assert "of 300 compared samples (first at seq " in lines[0]


@pytest.mark.parametrize("case, cause", [
    ({"fault": "controller timeout: no reply to seq 17 within 1 s"}, "controller timeout: no reply to seq 17"),
    ({"fault": "the controller exited with code 3: boom"}, "the controller exited with code 3: boom"),
    ({"compared": 0, "not_compared": {"count": 5, "seqs": [0, 1, 2, 3, 4], "seq_text": "0-4", "why": "x"}},
     "no sample could be compared: the recording has no current for any sample sent"),
])
def test_every_conformance_fail_names_its_cause(case, cause):
    """Each way a conformance can fail puts its cause in the verdict line (the table alone)."""
    from ambhil.bridge.recording.conform import causes, table
    res = {"passed": False, "tolerance": 0.0, "compared": 10, "sent": 10, "fault": None,
           "axes": [{"axis": "A-x", "max_abs_dev": 0.0, "seq": None, "over": 0, "first_over": None}], **case}
    res["causes"] = causes(res)
    first = table(res)[0]
    assert first.startswith("conformance FAIL: ") and cause in first, first


def test_viewer_timing_percentiles_are_the_summarys(tmp_path):
    """The .rrd's timing panel titles give the p99 / max of the run's summary: steps after the
    warm-up, round trip and TET of the steps that got a reply (before: every step, so a
    real-time run's viewer said p99 184 / max 4.14e3 us where its summary said 179.7 / 539.8)."""
    import rerun as rr
    from ambhil.bridge import protocol as pr
    from ambhil.bridge.process.timing import stats_us
    rng = np.random.default_rng(3)
    n, warm = 2000, 300
    rtt = rng.gamma(4.0, 15e3, n).astype(np.int64)
    rtt[:warm] += 3_000_000                      # the warm-up's slow first steps
    held = rng.random(n) < 0.05
    rtt[held] = 0                                # no reply: currents held
    tet = rng.gamma(3.0, 1e3, n).astype(np.int64)
    late = rng.gamma(2.0, 5e3, n).astype(np.int64)
    flags = np.where(np.arange(n) < warm, pr.FLAG_WARMUP, 0).astype(np.uint8) | np.where(held, pr.FLAG_HELD, 0).astype(np.uint8)
    rec = rr.RecordingStream("ambhil-test")
    rec.save(str(tmp_path / "t.rrd"))
    sink = rerun_view.RerunSink(rec, ["A-x", "A-y"], ["A"])
    t = np.arange(n) * 1e-4
    sink.timing(t[:700], {"rtt": rtt[:700], "tet": tet[:700], "late": late[:700], "flags": flags[:700]})
    sink.timing(t[700:], {"rtt": rtt[700:], "tet": tet[700:], "late": late[700:], "flags": flags[700:]})
    sink.finish({"gaps_m": [1.5e-4]}, 0.02, 0.2)
    rec.disconnect()
    ok = slice(warm, n)                          # as bridge/process/plant_node.py's summary
    want = {"rtt": stats_us(rtt[ok][rtt[ok] > 0]), "tet": stats_us(tet[ok][rtt[ok] > 0]),
            "late": stats_us(late[ok])}
    for key, st in want.items():
        got = sink.timing_stats[key]
        assert abs(got["p99"] - st["p99"]) < 0.01 and abs(got["max"] - st["max"]) < 0.01, (key, got, st)


def test_a_malformed_timing_payload_is_skipped_and_counted_in_the_replay(tmp_path, capsys):
    """A recording holding one Timing payload the recorder could not decode (kept on the
    key's malformed channel): the replay to .rrd skips it and counts it by name like the other
    types' malformed messages (before: ``KeyError: 'Timing'`` in the streamed replay)."""
    from mcap.writer import Writer
    from ambhil.bridge import protocol as pr
    from ambhil.bridge.recording import layout as rc
    from ambhil.bridge.recording.writer import Writer as RecordedWriter
    K = pr.keys("tm")
    mcap = tmp_path / "t.mcap"
    with open(mcap, "wb") as f:
        w = Writer(f)
        w.start(profile=rc.PROFILE, library="test")
        rw = RecordedWriter(w, "tm")
        for k in range(20):
            rw.put(K.sensors, pr.encode_sensor(k, k, 10_000 * k, 10_000 * k, 1e-6 * np.sin(k + np.arange(4))),
                   10_000 * k)
        assert rw.put(K.timing, b"\x00\x01\x00\x00 not a timing batch", 200_000) is None   # malformed
        w.finish()
    info = replay.to_rerun(str(mcap), str(tmp_path / "t.rrd"))
    assert info["samples"] == 20 and (tmp_path / "t.rrd").exists()
    assert info["rejected"] == 1 and list(info["rejected_reasons"]) and \
        all(k.startswith("Timing: ") for k in info["rejected_reasons"]), info["rejected_reasons"]
    code, out, err = _main(capsys, "replay", mcap, "--out", tmp_path / "o")
    assert code == 0 and "skipped 1 malformed message(s): Timing: " in out, out + err
