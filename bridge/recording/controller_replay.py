"""Replay a recording to a controller under test (:func:`to_controller`): the recorded sensor
stream re-published in lockstep, the replay posing as the run's plant, and each reply compared with
the recorded current of the same seq.  Conformance (:mod:`ambhil.bridge.recording.conform`) adds
the controller process, the recorded RunMeta and a per-axis table around it."""
from __future__ import annotations

import json
import queue
import threading
import time

import numpy as np

from ambhil.bridge import protocol as pr
from ambhil.bridge.process import transport as tr
from ambhil.bridge.process.pairing import Pairing
from ambhil.bridge.process.startup import GONE
from ambhil.bridge.recording.load import load_run


def to_controller(mcap_path: str, run_id: str, *, listen=None, connect=None,
                  tolerance: float = 1e-9, reply_timeout: float = 1.0, start_timeout: float = 30.0,
                  max_steps: int | None = None, session=None) -> dict:
    """Re-publish the recorded SensorSamples (verbatim wire bytes, seq order) to a controller
    under test on ``ambhil/<run_id>/...`` in lockstep, and compare each reply with the
    recorded CurrentCommand of the same seq.  The replay takes the plant's role (declares
    ``alive/plant``; the controller connects to ``listen``).  ``passed`` is True iff every
    sample sent got a reply, at least one could be compared and ``max_abs_dev <= tolerance``
    (a sample with no recorded current is not compared: ``missing_recorded``)."""
    run = load_run(mcap_path)
    S, C = run["sensors"], run["currents"]
    if not len(S["seq"]):
        raise ValueError(f"{mcap_path}: no sensor samples recorded")
    n = S["v"].shape[1]
    rec_cur = {int(s): C["v"][i] for i, s in enumerate(C["seq"])}
    own = session is None
    if own:
        session = tr.open_session(listen, connect)
    seat = _PlantSeat(session, run_id)
    cc = pr.CurrentCodec(n)
    fault = None
    dev = _Deviation()
    n_sent = 0
    t0 = time.perf_counter()
    try:
        cc.peer = seat.wait_for_controller(start_timeout)   # replies from anyone else: foreign
        total = len(S["seq"]) if max_steps is None else min(max_steps, len(S["seq"]))
        for i in range(total):
            seq = int(S["seq"][i])
            seat.pub.put(S["raw"][i][:-pr.PEER_LEN] + seat.pairing.id)   # sent by the replay, posing as the plant
            n_sent += 1
            m = seat.reply(cc, seq, reply_timeout)
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
    """The plant's place in run ``run_id``, taken by the replay: the sensor and event publishers,
    the currents received, the pairing as the plant, ``alive/plant``, and the controller's
    liveliness watched."""

    def __init__(self, session, run_id: str):
        self.K = K = pr.keys(run_id)
        self.q: queue.SimpleQueue = queue.SimpleQueue()
        self.sub = tr.declare_callback_subscriber(session, K.currents,
                                                  lambda s: self.q.put(s.payload.to_bytes()))
        self.pub = tr.declare_publisher(session, K.sensors)
        self.evp = tr.declare_publisher(session, K.events)
        self.gone = threading.Event()
        self.watch = tr.LivelinessWatch(session, K.alive_all, self._live)
        self.pairing = Pairing(session, run_id, "plant", "controller")   # the replay poses as the plant
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

    def wait_for_controller(self, start_timeout: float) -> bytes:
        """The controller present, paired (its peer id returned) and subscribed to the samples."""
        self.watch.wait_for([self.K.alive_controller], start_timeout)
        peer = self.pairing.wait(self, start_timeout)
        tr.wait_matching(self.pub, start_timeout, "controller")
        return peer

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
            except pr.ForeignError:       # not from the paired controller under test
                self.foreign += 1
                continue
            except pr.ProtocolError:
                self.rejected += 1
                continue
            if m.seq == seq:
                return m

    def close(self) -> None:
        """The end of the replay told (RUN_END), everything declared undeclared."""
        try:
            self.evp.put(pr.encode_event(pr.Event(pr.EventKind.RUN_END, json.dumps({"reason": "replay end"}),
                                                  "replay", 0, 0, 0, time.time_ns())),
                         attachment=self.pairing.id)
            time.sleep(0.05)
        except Exception:
            pass
        tr.close_quietly(self.token, self.pairing, self.watch, self.evp, self.pub, self.sub)
