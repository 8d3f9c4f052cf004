"""Replay: MCAP -> .rrd, and replay to a controller under test (pass / fail on a gain change)."""
from __future__ import annotations

import os
import sys

import numpy as np

TESTS = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, TESTS)
import test_nodes as tn  # noqa: E402
import test_recorder as trc  # noqa: E402
from bridge import replay  # noqa: E402


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
    # equal the recorded displacements x 1e6
    pts = []
    for c in store.stream():
        if c.entity_path == "/orbit/station_0" and not c.is_static:
            pts += c.to_record_batch().column("Points2D:positions").to_pylist()
    y = replay.load_run(out)["sensors"]["v"][:, :2]
    got = np.array([p[0] for p in pts])
    assert got.shape == y.shape and np.allclose(got, y * 1e6, rtol=1e-6), (got[:3], y[:3])
    assert 1.0 < np.abs(got).max() < 1e3          # SpringPlant starts at 100 um


def test_load_run_matches_trace(tmp_path):
    out, sp, _, _ = trc.run_recorded(tmp_path, "rp2", 200)
    run = replay.load_run(out)
    from bridge.reference import run_inprocess
    Y, U = run_inprocess(tn.SpringPlant(), tn.PController(), 200)
    assert np.array_equal(run["sensors"]["v"], Y[:200])
    assert np.array_equal(run["currents"]["v"], U)


def _replay_against(tmp_path, mcap, kp):
    ep, run = tn.endpoint(), f"replay{int(kp)}"
    c = tn.py(f"t._controller_proc({ep!r}, {run!r}, kp={kp!r})")
    res = replay.to_controller(mcap, run, listen=ep, tolerance=1e-9, start_timeout=15)
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
