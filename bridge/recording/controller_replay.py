"""Replay a recording to a controller under test (:func:`to_controller`): the recorded sensor
stream re-published in lockstep, the replay posing as the run's plant, and each reply compared with
the recorded current of the same seq.  Conformance (:mod:`ambhil.bridge.recording.conform`) adds
the controller process and a per-axis table around it.

Protocol 3 (docs/protocol.md 5.3): the replay takes the plant's part in the authentication too.
It answers challenges and challenges the controller under test (the plant's
:class:`ambhil.bridge.process.pairing.Pairing`), derives the session key from the pairing,
publishes the recorded RunMeta re-addressed to this replay (``auth``: the replay's pairing) with
its MAC, re-publishes each recorded sample with its own id and a MAC under that key (a
recording keeps no MACs), accepts only replies sealed by the paired controller, and puts its
events (source ``replay``) on the plant's event key, attached.  The key is the run's
``secret`` (the controller under test must have the same key file; none: unauthenticated)."""
from __future__ import annotations

import json
import queue
import threading
import time

import numpy as np

from ambhil.bridge import protocol as pr
from ambhil.bridge.process import transport as tr
from ambhil.bridge.process.events import EventSink
from ambhil.bridge.process.pairing import Pairing
from ambhil.bridge.process.startup import GONE
from ambhil.bridge.protocol import auth as au
from ambhil.bridge.recording.load import load_run


def to_controller(mcap_path: str, run_id: str, *, listen=None, connect=None,
                  tolerance: float = 1e-9, reply_timeout: float = 1.0, start_timeout: float = 30.0,
                  max_steps: int | None = None, session=None, secret: bytes | None = None,
                  insecure: bool = False, replies: dict | None = None) -> dict:
    """Re-publish the recorded SensorSamples (the wire bytes, seq order, sealed with the replay's
    id and key) to a controller under test on ``ambhil/<run_id>/...`` in lockstep, and compare
    each reply with the recorded CurrentCommand of the same seq.  The replay takes the plant's
    role (declares ``alive/plant``, pairs as the plant, publishes the recorded RunMeta; the
    controller connects to ``listen``); ``secret``: the run's key (module docstring).
    ``passed`` is True iff every sample sent got a reply, at least one could be compared and
    ``max_abs_dev <= tolerance`` (a sample with no recorded current is not compared:
    ``missing_recorded``).  ``replies``: filled with ``{seq: current}`` of the replies taken."""
    run = load_run(mcap_path)
    S, C = run["sensors"], run["currents"]
    if not len(S["seq"]):
        raise ValueError(f"{mcap_path}: no sensor samples recorded")
    n = S["v"].shape[1]
    rec_cur = {int(s): C["v"][i] for i, s in enumerate(C["seq"])}
    own = session is None
    if own:
        session = tr.open_session(listen, connect)
    seat = _PlantSeat(session, run_id, secret, insecure)
    cc = pr.CurrentCodec(n)
    fault = None
    dev = _Deviation()
    n_sent = 0
    t0 = time.perf_counter()
    try:
        cid = seat.wait_for_controller(start_timeout, run["meta"])
        cc.peer = seat.auth.peer_seal(cid, "controller/currents")   # replies from anyone else: foreign
        total = len(S["seq"]) if max_steps is None else min(max_steps, len(S["seq"]))
        for i in range(total):
            seq = int(S["seq"][i])
            seat.pub.put(seat.sealed(S["raw"][i]))      # sent by the replay, posing as the plant
            n_sent += 1
            m = seat.reply(cc, seq, reply_timeout)
            if replies is not None:
                replies[seq] = np.array(m.current)
            dev.add(seq, int(S["step"][i]), m.current, rec_cur.get(seq))
    except (RuntimeError, tr.TransportError) as e:
        fault = str(e)
    seat.close()
    if own:
        tr.close_quietly(session)
    # a sample whose seq has no recorded current is not compared (counted in missing_recorded):
    # the recording lacks the reference, which says nothing against the controller under test
    passed = fault is None and dev.compared > 0 and dev.max_dev <= tolerance
    return {"passed": passed, "max_abs_dev": dev.max_dev, "worst": dev.worst, "tolerance": tolerance,
            "compared": dev.compared, "missing_recorded": dev.missing, "sent": n_sent,
            "rejected": seat.rejected, "foreign": seat.foreign, "fault": fault,
            "auth": seat.auth.mode, "strangers": [p.hex() for p in seat.pairing.strangers],
            "wall_s": round(time.perf_counter() - t0, 3)}


class _Deviation:
    """The largest deviation of the replies from the recorded currents, and where."""

    def __init__(self):
        self.max_dev, self.worst = 0.0, None
        self.compared = self.missing = 0

    def add(self, seq: int, step: int, current, ref) -> None:
        if ref is None:
            self.missing += 1
            return
        d = np.abs(current - ref)
        j = int(np.argmax(d))
        self.compared += 1
        if self.worst is None or d[j] > self.max_dev:
            self.max_dev = float(d[j])
            self.worst = {"seq": seq, "step": step, "axis": j,
                          "recorded": float(ref[j]), "replayed": float(current[j])}


class _PlantSeat:
    """The plant's place in run ``run_id``, taken by the replay: its keys (``auth``), the sensor,
    meta and event publishers, the currents received, the pairing as the plant,
    ``alive/plant``, and the controller's liveliness watched."""

    def __init__(self, session, run_id: str, secret: bytes | None = None, insecure: bool = False):
        self.K = K = pr.keys(run_id)
        self.run_id = run_id
        self.auth = au.RunAuth(secret, run_id, "plant", tr.peer_id(session),
                               None if secret is not None else ("insecure" if insecure else "none"))
        self.q: queue.SimpleQueue = queue.SimpleQueue()
        self.sub = tr.declare_callback_subscriber(session, K.currents,
                                                  lambda s: self.q.put(s.payload.to_bytes()))
        self.pub = tr.declare_publisher(session, K.sensors)
        self.meta_pub = tr.declare_publisher(session, K.meta)
        self.events = EventSink(session, run_id, "replay", self.auth)     # on events/plant
        self.gone = threading.Event()
        self.watch = tr.LivelinessWatch(session, K.alive_all, self._live)
        # the replay poses as the plant: it answers challenges, then announces itself
        self.pairing = Pairing(session, run_id, "plant", "controller", self.auth.me, self.auth)
        self.pairing.announce()
        self.token = tr.declare_token(session, K.alive_plant)
        self.rejected = self.foreign = 0

    def _live(self, key, alive) -> None:
        if key == self.K.alive_controller and not alive:
            self.gone.set()
            self.q.put(None)

    def state(self, role):
        # Pairing.wait's view of the controller: a controller that was ready and went away
        # before announcing (or after withdrawing) its peer id fails the pairing at once
        return GONE if self.gone.is_set() else None

    def wait_for_controller(self, start_timeout: float, meta: dict) -> bytes:
        """The controller present, proven and paired (its peer id returned), told the recorded
        RunMeta (:meth:`publish_meta`) and subscribed to the samples."""
        self.watch.wait_for([self.K.alive_controller], start_timeout)
        peer = self.pairing.wait(self, start_timeout)
        self.auth.pair(self.auth.me, peer, *self.pairing.nonces)
        self.key = self.auth.key("plant/sensors")
        self.publish_meta(meta, peer)
        tr.wait_matching(self.pub, start_timeout, "controller")
        return peer

    def publish_meta(self, meta: dict, peer: bytes) -> None:
        """The recorded RunMeta, re-addressed to this replay (``run_id``; ``replay_of`` the
        original; the ids and ``auth`` of this pairing), sealed under the session key: the
        controller pairs with it (docs/protocol.md 5.3) and a controller that reads its law from
        RunMeta gets it before sample 0 (as from a plant)."""
        info = dict(meta or {}, run_id=self.run_id, replay_of=(meta or {}).get("run_id"),
                    mode="lockstep", plant_peer_id=self.auth.me.hex(), controller_peer_id=peer.hex(),
                    auth=self.auth.describe())
        data = pr.encode_meta(pr.RunMeta(info, wall_ns=time.time_ns()))
        self.meta_pub.put(data, attachment=self.auth.attach("meta", data))

    def sealed(self, raw: bytes) -> bytes:
        """A recorded sample's wire bytes as this replay sends them: its id, its MAC."""
        body = bytes(raw[:-(au.ID_LEN + au.MAC_LEN)]) + self.auth.me
        return body + au.mac(self.key, body)

    def reply(self, cc, seq: int, reply_timeout: float):
        """The paired controller's reply to ``seq`` (others' replies counted as foreign, malformed
        ones as rejected, replies to other seqs skipped); RuntimeError after ``reply_timeout`` s or
        when the controller's liveliness goes."""
        t_end = time.monotonic() + reply_timeout
        while True:
            rem = t_end - time.monotonic()
            try:
                data = self.q.get(timeout=max(rem, 0.0)) if rem > 0 else self.q.get_nowait()
            except queue.Empty:
                raise RuntimeError(f"controller timeout: no reply to seq {seq} within "
                                   f"{reply_timeout:g} s") from None
            if data is None:
                raise RuntimeError(f"controller lost (liveliness) at seq {seq}")
            try:
                m = cc.decode(data)
            except (pr.ForeignError, pr.AuthError):   # not from the paired controller under test
                self.foreign += 1
                continue
            except pr.ProtocolError:
                self.rejected += 1
                continue
            if m.seq == seq:
                return m

    def close(self) -> None:
        """The end of the replay told (RUN_END, attached: the controller obeys only its paired
        plant's), everything declared undeclared."""
        try:
            self.events.emit(pr.EventKind.RUN_END, json.dumps({"reason": "replay end"}), force=True)
            time.sleep(0.05)
        except Exception:
            pass
        tr.close_quietly(self.token, self.pairing, self.watch, self.events.pub, self.meta_pub, self.pub,
                         self.sub)
