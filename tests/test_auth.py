"""Only the paired controller drives the plant, only the paired plant feeds the controller
(bridge/pairing.py, docs/protocol.md 5.1): the attacks reported in issue 12, repeated.

Each attack runs in lockstep (deterministic), so "changes nothing" is checked bit for bit
against the in-process reference or an unattacked run.  The rogue session poses as the
recorder where it must be connected before the run starts (the plant waits for the recorder's
token), so no test depends on process start-up times."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import numpy as np

TESTS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(TESTS)
sys.path.insert(0, TESTS)

from test_nodes import (PController, SpringPlant, announced_id, endpoint, last_json,  # noqa: E402
                        py)
from bridge import protocol as pr, transport as tr  # noqa: E402
from bridge.reference import run_inprocess  # noqa: E402


def wait_listening(ep, timeout=300.0):
    """Block until something accepts TCP connections on ``ep`` (the plant is listening): a
    zenoh peer that connects too early gives up on that endpoint."""
    import socket
    host, port = ep.split("/", 1)[1].rsplit(":", 1)
    t_end = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((host, int(port)), timeout=1.0):
                return
        except OSError:
            if time.monotonic() > t_end:
                raise AssertionError(f"nothing listens on {ep}")
            time.sleep(0.02)


class Rogue:
    """A second zenoh session on the run: answers every sensor sample with well-formed
    currents carrying the live seq (``hijack``), and can publish crafted messages."""

    def __init__(self, ep, run_id, n_axes=4, hijack=True, attach=None, amps=5.0):
        self.K = pr.keys(run_id)
        wait_listening(ep)
        self.s = tr.open_session(connect=ep)
        self.cur = tr.declare_publisher(self.s, self.K.currents)
        self.sens = tr.declare_publisher(self.s, self.K.sensors)
        self.cc, self.sc = pr.CurrentCodec(n_axes), pr.SensorCodec(n_axes)
        self.answered = 0
        self.attach = attach
        u = np.full(n_axes, amps)

        def _on_sample(smp):
            try:
                m = self.sc.decode(smp.payload.to_bytes())
            except pr.ProtocolError:
                return
            msg = self.cc.encode(m.seq, m.step, m.sim_time_ns, 0, 0, u)
            self.cur.put(msg, attachment=self.attach) if self.attach else self.cur.put(msg)
            self.answered += 1
        self.sub = (tr.declare_callback_subscriber(self.s, self.K.sensors, _on_sample)
                    if hijack else None)
        self.watch = tr.LivelinessWatch(self.s, self.K.alive_all)
        self.token = None

    def start_run(self):
        """Pose as the recorder: the plant (run with wait_recorder) starts now."""
        self.token = tr.declare_token(self.s, self.K.alive_recorder)

    def close(self):
        tr.close_quietly(self.token, self.watch, self.sub, self.cur, self.sens, self.s)


def test_hijacker_replies_are_rejected_and_change_nothing(tmp_path):
    """Issue 12: a second session answering the plant's samples with the live seq was
    accepted as the controller.  Now every such reply is rejected (reason ``peer``), counted,
    and the trajectory is bit-identical to the unattacked in-process reference."""
    ep, run, n = endpoint(), "hijack", 400
    c = py(f"t._controller_proc({ep!r}, {run!r})")
    p = py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r}, wait_recorder=True)")
    rogue = Rogue(ep, run)
    try:
        rogue.watch.wait_for([rogue.K.alive_plant, rogue.K.alive_controller], 120)
        rogue.start_run()
        sp, sc = last_json(p), last_json(c)
    finally:
        rogue.close()
    assert sp["fault"] is None and sp["steps"] == n, sp
    assert sc["fault"] is None and sc["steps"] == n, sc
    assert rogue.answered > 0, "the rogue never saw a sample: the test proved nothing"
    assert sp["rejected"].get("peer", 0) >= 1, sp["rejected"]
    assert sp["rejected_total"] == sp["rejected"]["peer"], sp["rejected"]
    Y, U = run_inprocess(SpringPlant(), PController(), n)
    got = np.load(tmp_path / "tr.npz")
    assert np.array_equal(got["u"], U), "a foreign reply reached the coils"
    assert np.array_equal(got["y"], Y)


def test_absurd_seq_sample_cannot_poison_the_controller(tmp_path):
    """Issue 12: one SensorSample with seq 2^62 from another session made the controller drop
    every real sample.  Now it is rejected: without the plant's peer id as ``peer``, and even
    with the plant's id forged, as ``sequence`` (outside the window), and the run completes
    bit-identically."""
    ep, run, n = endpoint(), "seq62", 300
    c = py(f"t._controller_proc({ep!r}, {run!r})")
    p = py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r}, wait_recorder=True)")
    rogue = Rogue(ep, run, hijack=False)
    try:
        rogue.watch.wait_for([rogue.K.alive_plant, rogue.K.alive_controller], 120)
        tr.wait_matching(rogue.sens, 60)
        plant_id = announced_id(rogue.s, run, "plant")
        bad = rogue.sc.encode(2 ** 62, 2 ** 62, 0, 0, np.zeros(4))
        rogue.sens.put(bad)                               # naive: no peer id
        rogue.sens.put(bad, attachment=plant_id)          # forged peer id: the window catches it
        rogue.start_run()
        sp, sc = last_json(p), last_json(c)
    finally:
        rogue.close()
    assert sp["fault"] is None and sp["steps"] == n, sp
    assert sc["fault"] is None and sc["steps"] == n and sc["gaps"] == 0, sc
    assert sc["rejected"] == {"peer": 1, "sequence": 1}, sc["rejected"]
    Y, U = run_inprocess(SpringPlant(), PController(), n)
    got = np.load(tmp_path / "tr.npz")
    assert np.array_equal(got["y"], Y) and np.array_equal(got["u"], U)


def test_two_announced_controllers_refuse_to_start():
    """Two controllers for one run: the plant pairs with neither and says which ids."""
    ep, run = endpoint(), "twoctl"
    c1 = py(f"t._controller_proc({ep!r}, {run!r})")
    c2 = py(f"t._controller_proc({ep!r}, {run!r})")
    p = py(f"t._plant_proc({ep!r}, {run!r}, 100, wait_recorder=True)")
    rogue = Rogue(ep, run, hijack=False)
    from bridge.pairing import peer_key
    try:
        rogue.watch.wait_for([rogue.K.alive_plant, rogue.K.alive_controller], 120)
        t_end = time.monotonic() + 120          # both announced, then let the plant start
        while len([r for r in rogue.s.liveliness().get(peer_key(run, "controller"), timeout=5.0)
                   if r.ok is not None]) < 2:
            assert time.monotonic() < t_end, "the second controller never announced itself"
            time.sleep(0.02)
        rogue.start_run()
        sp = last_json(p)
    finally:
        rogue.close()
        for c in (c1, c2):
            c.kill()
            c.communicate()
    assert sp["steps"] == 0 and sp["fault"] and "2 controllers announced" in sp["fault"], sp


def test_run_strict_fails_on_foreign_traffic_and_keeps_the_orbit(tmp_path):
    """`ambhil run` with a hijacker attached: the recorded currents are exactly those of an
    unattacked run, the hijacker's replies sit under foreign/ in the recording, the summary
    says so, and --strict makes the run fail (exit 1, files marked .failed)."""
    from bridge.replay import load_run
    scene = os.path.join(ROOT, "scenes", "paper_2amb.toml")
    ambhil = os.path.join(os.path.dirname(sys.executable), "ambhil")
    base = [ambhil, "run", scene, "--duration", "0.05", "--json", "--placement", "none"]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    clean = subprocess.run(base + ["--run-id", "clean", "--out", str(tmp_path)], env=env,
                           capture_output=True, text=True, timeout=900)
    assert clean.returncode == 0, clean.stderr[-2000:]
    ep = endpoint()
    stop = threading.Event()
    box = {}

    def _attack():        # connect as soon as the plant listens; answer every sample
        while not stop.is_set():
            try:
                box["rogue"] = Rogue(ep, "attacked", n_axes=4, amps=3.0)
                return
            except tr.TransportError:
                time.sleep(0.05)
    th = threading.Thread(target=_attack, daemon=True)
    th.start()
    try:
        att = subprocess.run(base + ["--run-id", "attacked", "--out", str(tmp_path), "--strict",
                                     "--endpoint", ep], env=env, capture_output=True, text=True,
                             timeout=900)
    finally:
        stop.set()
        th.join(10)
        if "rogue" in box:
            answered = box["rogue"].answered
            box["rogue"].close()
    summ = json.loads([ln for ln in att.stdout.splitlines() if ln.startswith("{")][-1])
    assert answered > 0, "the hijacker never saw a sample: the test proved nothing"
    assert att.returncode == 1, att.stderr[-2000:]
    assert summ["plant"]["rejected"].get("peer", 0) >= 1, summ["plant"]
    assert any("--strict" in r and "another process published" in r for r in summ["failed"]), summ
    failed_mcap = tmp_path / "attacked.failed.mcap"
    assert failed_mcap.exists()
    a, b = load_run(str(tmp_path / "clean.mcap")), load_run(str(failed_mcap))
    assert np.array_equal(a["currents"]["v"], b["currents"]["v"]), "the hijacker changed the loop"
    assert np.array_equal(a["sensors"]["v"], b["sensors"]["v"])
    from mcap.reader import make_reader
    with open(failed_mcap, "rb") as f:
        topics = {ch.topic for ch in make_reader(f).get_summary().channels.values()}
    assert "ambhil/attacked/foreign/controller/currents" in topics, topics
