"""Only the paired controller drives the plant, only the paired plant feeds the controller
(bridge/process/pairing.py, docs/protocol.md 5.1 and 5.3): the attacks reported in issue 12,
repeated against protocol 3 with the project's own codecs (the rogue here seals with a peer id
and the all-zero key, or, where it must, with the keys of an unauthenticated run).  The
attacks of issue 31, written as an outsider's raw zenoh scripts against keyed runs, are in
tests/test_attacks.py.

Each attack runs in lockstep (deterministic), so "changes nothing" is checked bit for bit
against the in-process reference or an unattacked run.  The rogue session poses as the
recorder where it must be connected before the run starts (the plant waits for the recorder's
token), so no test depends on process start-up times.  No key is given: the runs are
unauthenticated (mode ``none``), and still a message without the run's session MAC is
rejected (``peer`` for another id, ``auth`` for a copied id)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

TESTS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(TESTS)
sys.path.insert(0, TESTS)

from test_nodes import (PController, SpringPlant, announced_id, endpoint, last_json,  # noqa: E402
                        py, wait_alive, wait_listening)
from ambhil.bridge import protocol as pr
from ambhil.bridge.process import transport as tr
from ambhil.bridge.process.reference import run_inprocess  # noqa: E402


class Rogue:
    """A second zenoh session on the run: answers every sensor sample with well-formed
    currents carrying the live seq (``hijack``), and can publish crafted messages."""

    def __init__(self, ep, run_id, n_axes=4, hijack=True, attach=None, amps=5.0, listen=None):
        self.K = pr.keys(run_id)
        if listen is None:
            wait_listening(ep)
        self.s = tr.open_session(listen=listen) if listen else tr.open_session(connect=ep)
        self.cur = tr.declare_publisher(self.s, self.K.currents)
        self.sens = tr.declare_publisher(self.s, self.K.sensors)
        # its messages end with the id ``attach`` (forged) or the zero id (naive)
        me = attach if attach else pr.NO_PEER
        self.cc, self.sc = pr.CurrentCodec(n_axes, me=me), pr.SensorCodec(n_axes, me=me)
        self.answered = 0
        u = np.full(n_axes, amps)

        def _on_sample(smp):
            try:
                m = self.sc.decode(smp.payload.to_bytes())
            except pr.ProtocolError:
                return
            msg = self.cc.encode(m.seq, m.step, m.sim_time_ns, 0, 0, u)
            self.cur.put(msg)
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


@pytest.mark.parametrize("shared", [False, True], ids=["python-loop", "c-loop"])
def test_hijacker_replies_are_rejected_and_change_nothing(tmp_path, shared):
    """Issue 12: a second session answering the plant's samples with the live seq was
    accepted as the controller.  Now every such reply is rejected (reason ``peer``), counted,
    and the trajectory is bit-identical to the unattacked in-process reference.  With
    shared-buffer step objects the plant's loop runs in C and hands each foreign reply back
    to Python (bridge/process/plant_lockstep.py)."""
    from ambhil.bridge.protocol import wire
    if shared and not wire.NATIVE:
        pytest.skip("the C extension ambhil.bridge.protocol._wire is not built")
    ep, ep_r, run, n = endpoint(), endpoint(), f"hijack{int(shared)}", 400
    rogue = Rogue(ep, run, listen=ep_r)          # every process links to the rogue directly
    c = py(f"t._controller_proc([{ep!r}, {ep_r!r}], {run!r}, kind={'shared' if shared else 'p'!r})")
    p = py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r}, wait_recorder=True, "
           f"connect={ep_r!r}, kind={'shared' if shared else 'spring'!r})")
    try:
        wait_alive(rogue.watch, [rogue.K.alive_plant, rogue.K.alive_controller], (p, c))
        rogue.start_run()
        sp, sc = last_json(p), last_json(c)
    finally:
        rogue.close()
    assert sp["fault"] is None and sp["steps"] == n, sp
    assert sc["fault"] is None and sc["steps"] == n, sc
    assert rogue.answered > 0, "the rogue never saw a sample: the test proved nothing"
    assert sp["loop"] == ("C" if shared else "python"), sp
    assert sp["rejected"].get("peer", 0) >= 1, sp["rejected"]
    assert sp["rejected_total"] == sp["rejected"]["peer"], sp["rejected"]
    Y, U = run_inprocess(SpringPlant(), PController(), n)
    got = np.load(tmp_path / "tr.npz")
    assert np.array_equal(got["u"], U), "a foreign reply reached the coils"
    assert np.array_equal(got["y"], Y)


def test_absurd_seq_sample_cannot_poison_the_controller(tmp_path):
    """Issue 12: one SensorSample with seq 2^62 from another session made the controller drop
    every real sample.  Now it is rejected: without the plant's peer id as ``peer``; with the
    plant's id forged, as ``auth`` (no session MAC); and even sealed with the session keys of
    this unauthenticated run (all-zero secret, the nonces of RunMeta: what anyone can do
    without a key), as ``sequence`` (outside the window).  The run completes bit-identically."""
    from ambhil.bridge.protocol.auth import RunAuth
    ep, ep_r, run, n = endpoint(), endpoint(), "seq62", 3000
    rogue = Rogue(ep, run, hijack=False, listen=ep_r)
    sealed = []

    def _on_meta(smp):          # the run's keys, computed from RunMeta (no secret: all zero)
        try:
            info = pr.decode_meta(smp.payload.to_bytes()).info
            pid, cid = bytes.fromhex(info["plant_peer_id"]), bytes.fromhex(info["controller_peer_id"])
            a = RunAuth(None, run, "plant", pid)
            a.pair(pid, cid, bytes.fromhex(info["auth"]["nonce_plant"]),
                   bytes.fromhex(info["auth"]["nonce_controller"]))
            rogue.sens.put(pr.encode_sensor(2 ** 62, 2 ** 62, 0, 0, np.zeros(4),
                                            peer=a.seal("plant/sensors")))
            sealed.append(1)
        except Exception as e:           # noqa: BLE001 - reported by the assertion below
            sealed.append(e)
    meta_sub = tr.declare_callback_subscriber(rogue.s, rogue.K.meta, _on_meta)
    c = py(f"t._controller_proc([{ep!r}, {ep_r!r}], {run!r})")
    p = py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r}, wait_recorder=True, "
           f"connect={ep_r!r})")
    try:
        wait_alive(rogue.watch, [rogue.K.alive_plant, rogue.K.alive_controller], (p, c))
        tr.wait_matching(rogue.sens, 60)
        plant_id = announced_id(rogue.s, run, "plant")
        bad = rogue.sc.encode(2 ** 62, 2 ** 62, 0, 0, np.zeros(4))
        rogue.sens.put(bad)                               # naive: not the plant's peer id
        forged = pr.encode_sensor(2 ** 62, 2 ** 62, 0, 0, np.zeros(4), peer=plant_id)
        rogue.sens.put(forged)                            # forged peer id: no MAC of the run
        rogue.start_run()
        sp, sc = last_json(p), last_json(c)
    finally:
        tr.close_quietly(meta_sub)
        rogue.close()
    assert sealed == [1], sealed
    assert sp["fault"] is None and sp["steps"] == n, sp
    assert sc["fault"] is None and sc["steps"] == n and sc["gaps"] == 0, sc
    assert sc["auth"] == "none", sc
    assert sc["rejected"] == {"peer": 1, "auth": 1, "sequence": 1}, sc["rejected"]
    Y, U = run_inprocess(SpringPlant(), PController(), n)
    got = np.load(tmp_path / "tr.npz")
    assert np.array_equal(got["y"], Y) and np.array_equal(got["u"], U)


def test_two_announced_controllers_refuse_to_start():
    """Two controllers for one run: the plant pairs with neither and says which ids.  The
    test's session listens and every process connects to it (no reliance on gossip), and it
    poses as the recorder: the plant starts once both controllers have announced."""
    from ambhil.bridge.process.pairing import peer_key
    ep, ep_t, run = endpoint(), endpoint(), "twoctl"
    K = pr.keys(run)
    s = tr.open_session(listen=ep_t)
    token = None
    procs = [py(f"t._controller_proc([{ep!r}, {ep_t!r}], {run!r})") for _ in range(2)]
    p = py(f"t._plant_proc({ep!r}, {run!r}, 100, wait_recorder=True, connect={ep_t!r})")
    try:
        t_end = time.monotonic() + 300
        while len([r for r in s.liveliness().get(peer_key(run, "controller"), timeout=5.0)
                   if r.ok is not None]) < 2:
            assert time.monotonic() < t_end, "the controllers never announced themselves"
            assert p.poll() is None, p.communicate()
            time.sleep(0.02)
        token = tr.declare_token(s, K.alive_recorder)
        sp = last_json(p)
    finally:
        tr.close_quietly(token, s)
        for c in procs:
            c.kill()
            c.communicate()
    assert sp["steps"] == 0 and sp["fault"] and "2 controllers announced" in sp["fault"], sp


def test_run_strict_fails_on_foreign_traffic_and_keeps_the_orbit(tmp_path):
    """`ambhil run` with a hijacker attached: the recorded currents are exactly those of an
    unattacked run, the rejections are events in the recording, the summary says so, and
    --strict makes the run fail (exit 1, files marked .failed)."""
    from ambhil.bridge.recording.load import load_run
    scene = os.path.join(ROOT, "scenes", "paper_2amb.toml")
    ambhil = os.path.join(os.path.dirname(sys.executable), "ambhil")
    # 0.5 s (5000 lockstep steps): the hijacker's replies overlap the running loop for certain
    # (with 500 steps, 30 ms of wall time, a loaded machine once delivered them all after the end)
    base = [ambhil, "run", scene, "--duration", "0.5", "--json", "--placement", "none"]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    clean = subprocess.run(base + ["--run-id", "clean", "--out", str(tmp_path)], env=env,
                           capture_output=True, text=True, timeout=900)
    assert clean.returncode == 0, clean.stderr[-2000:]
    ep = endpoint()
    stop = threading.Event()
    box = {}
    ready = tmp_path / "rogue-connected"

    def _attack():        # connect as soon as the plant listens; answer every sample
        while not stop.is_set():
            try:
                box["rogue"] = Rogue(ep, "attacked", n_axes=4, amps=3.0)
                ready.touch()
                return
            except tr.TransportError:
                time.sleep(0.05)
    th = threading.Thread(target=_attack, daemon=True)
    th.start()
    # the built-in controller, started only once the hijacker is connected: the plant waits for
    # its controller, so the run cannot be over before the hijacker is there (on a loaded
    # machine it once was: nothing was attacked)
    controller = (f"sh -c 'while [ ! -e {ready} ]; do sleep 0.05; done; exec {sys.executable} -m ambhil.bridge.cli "
                  f"controller {{scene}} --run-id {{run_id}} --connect {{connect}} --json'")
    try:
        att = subprocess.run(base + ["--run-id", "attacked", "--out", str(tmp_path), "--strict",
                                     "--endpoint", ep, "--controller", controller], env=env,
                             capture_output=True, text=True, timeout=900)
    finally:
        stop.set()
        th.join(10)
        if "rogue" in box:
            answered = box["rogue"].answered
            box["rogue"].close()
    summ = json.loads([ln for ln in att.stdout.splitlines() if ln.startswith("{")][-1])
    assert answered > 0, "the hijacker never saw a sample: the test proved nothing"
    assert att.returncode == 1, (answered, summ["plant"].get("rejected"), att.stderr[-2000:])
    assert summ["plant"]["rejected"].get("peer", 0) >= 1, summ["plant"]
    assert any("--strict" in r and "another process published" in r for r in summ["failed"]), summ
    failed_mcap = tmp_path / "attacked.failed.mcap"
    assert failed_mcap.exists()
    a, b = load_run(str(tmp_path / "clean.mcap")), load_run(str(failed_mcap))
    assert np.array_equal(a["currents"]["v"], b["currents"]["v"]), "the hijacker changed the loop"
    assert np.array_equal(a["sensors"]["v"], b["sensors"]["v"])
    rejected = [e for e in b["events"] if e.kind_name == "REJECTED" and "peer" in e.text]
    assert rejected, "the rejections are not in the recording"
