"""The controller process over zenoh, for any duck-typed controller step object.

Controller step object::

    n_axes: int; reset(); step(y) -> currents (n_axes)

Optional fast path: ``controller.step_shared(y)`` may return its own output buffer (no
copy).  The array passed in (``y``) is the bridge's own preallocated buffer, overwritten
every period: copy what you keep.

The process is a small state machine (:class:`ambhil.bridge.process.events.Phase`)::

    STARTING  ``starting/controller`` token (bridge/process/startup.py; the CLI declares it before
              building the controller), subscriptions, ``alive/controller``; wait for the plant
              to be ready, as long as it is alive
    RUNNING   answer every SensorSample with a CurrentCommand carrying the same seq
    STOPPING  the plant's RUN_END seen (or a stop request): tokens undeclared, summary
    FAULTED   plant lost, plant silent, invalid controller output, a law that failed at a step
              (:class:`ambhil.controller.law.LawError`, its one line naming the law and the step):
              Event FAULT, summary

It waits for samples as long as the plant's liveliness token is present (``sample_timeout``,
default 5 min, is only a last resort) and faults at once when the token goes away.
"""
from __future__ import annotations

import json
import math
import threading
import time

import numpy as np

from ambhil.controller.law import LawError
from ambhil.bridge.process import transport as tr
from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import wire
from ambhil.bridge.protocol.wire import LoopCode
from ambhil.bridge.process.config import ControllerNodeConfig
from ambhil.bridge.process.events import Fault, ForeignCopies, Phase, Stop
from ambhil.bridge.process.pairing import Pairing, attached, meta_pairs
from ambhil.bridge.protocol import auth as au
from ambhil.bridge.process.startup import ABSENT, GONE, READY, PeerWatch, Presence, wait_matching
from ambhil.bridge.process.timing import pin_cpus
from ambhil.bridge.process.watchdog import Watchdog, stop_fn as _stop_fn

SEQ_WINDOW = 1 << 16       # a sample more than this many seq ahead of the last is rejected


def run_controller(controller, cfg: ControllerNodeConfig, *, stop=None, session=None,
                   presence: Presence | None = None) -> dict:
    """Run the controller side: answer every SensorSample with a CurrentCommand carrying
    the same seq.  Ends on the plant's RUN_END event (clean), or with a fault if the plant's
    liveliness token disappears without RUN_END, or (last resort) no sample arrives for
    ``sample_timeout`` s after the first one although the plant is alive.

    ``presence``: the process's :class:`ambhil.bridge.process.startup.Presence` if it declared itself before
    building the controller (then ``session`` is its session); else one is made here.
    ``cfg``: :class:`ambhil.bridge.process.config.ControllerNodeConfig` (``start_timeout``: how
    long the plant may be *absent*, no liveliness token at all).  ``stop``: a callable or event
    that ends the run early."""
    return ControllerNode(controller, cfg, stop=stop, session=session, presence=presence).run()


class ControllerNode:
    """One controller run; use :func:`run_controller`."""

    def __init__(self, controller, cfg: ControllerNodeConfig, *, stop=None, session=None, presence=None):
        self.cfg, self.controller = cfg, controller
        self.stop_fn = _stop_fn(stop)
        self.K = pr.keys(cfg.run_id)
        self.n = int(controller.n_axes)
        self.presence, self.own_presence = presence, presence is None
        self.session = session if presence is None else presence.session
        self.own_session = session is None and presence is None
        self.sc, self.cc = pr.SensorCodec(self.n), pr.CurrentCodec(self.n)
        self.rejected = {r: 0 for r in pr.REASONS}
        self.ended = None              # the plant's RUN_END text
        self.plant_lost = False
        self.plant_seen = False
        self.phase = Phase.STARTING
        self.objs = []
        self.wd = None
        self.fault = None
        self.steps = self.dups = self.gaps = 0
        self.t_cpu0 = None
        self.me = self.peer = None            # seals of the loop codecs: id + topic key (protocol 3)
        self.me_id = self.peer_id = None      # the peer ids (bridge/process/pairing.py)
        self.auth = None                      # the run's keys (bridge/protocol/auth.py), from presence
        self.metas: list = []                 # RunMeta (payload, attachment) not yet judged
        self.meta = None                      # the RunMeta paired with (dict)
        self.strangers: list[bytes] = []      # plants whose RunMeta failed the pairing proof
        self.foreign_ends = 0                 # RUN_END events not from the paired plant
        self.foreign_events = 0               # events rejected (unauthenticated, replayed, wrong role)
        self.plant_event_seq = -1             # the last authenticated plant event's seq
        self.pending = None                   # a seq that jumped ahead, not yet confirmed (spec 5)
        self.last_after = -1                  # the last answered seq after a slow-path sample
        self.foreign_copies = None            # rejected foreign samples -> foreign/ (recording)
        self.restarts: list[int] = []  # steps before which the controller restarts (fault schedule)
        self.n_restarts = 0
        self.loop = None            # "C" when bridge/protocol/_controller_lockstep.c answers the ordinary samples, else "python"
        self.loop_handbacks = 0     # returns of the C loop to Python (a message or step it does not handle)

    def run(self) -> dict:
        pin_cpus(self.cfg.cpus)
        if self.own_session:
            self.session = tr.open_session(self.cfg.listen, self.cfg.connect)
        if self.own_presence:
            self.presence = Presence(self.session, self.cfg.run_id, "controller",
                                     secret=self.cfg.secret, insecure=self.cfg.insecure)
        self.ev = self.presence.events
        self.auth = self.presence.auth
        try:
            self._start()
            self.phase = Phase.RUNNING
            self._loop()
        except Stop:
            pass
        except Fault as f:
            self.fault = str(f)
        except LawError as e:           # the law failed at a step (raised, NaN, wrong shape): named
            self.fault = str(e)
        except tr.TransportError as e:
            self.fault = str(e)
        except KeyboardInterrupt:
            self.fault = "interrupted"
        if self.fault:
            self.phase = Phase.FAULTED
            self.ev.emit(pr.EventKind.FAULT, self.fault, force=True)
        self.phase = Phase.STOPPING
        # its last event: what it rejected, for the recording's run_end (docs/protocol.md 5)
        self.ev.emit(pr.EventKind.INFO, json.dumps({"controller_end": {
            "steps": self.steps, "rejected": {k: v for k, v in self.rejected.items() if v},
            "strangers": [p.hex() for p in self.strangers]}}), force=True)
        if self.wd is not None:
            self.wd.done = True
        tr.close_quietly(*reversed(self.objs))
        self.presence.close()
        if self.own_session:
            tr.close_quietly(self.session)
        steps = self.steps
        return {"role": "controller", "run_id": self.cfg.run_id, "steps": steps,
                "duplicates": self.dups, "gaps": self.gaps,
                "rejected": {k: v for k, v in self.rejected.items() if v},
                "rejected_total": sum(self.rejected.values()),
                "cpu_us_per_step": (round((time.process_time() - self.t_cpu0) / steps * 1e6, 2)
                                    if steps and self.t_cpu0 is not None else None),
                "foreign_run_ends": self.foreign_ends,
                "foreign_events": self.foreign_events,
                "foreign_copied": self.foreign_copies.copied if self.foreign_copies else 0,
                "paired_plant": None if self.peer_id is None else self.peer_id.hex(),
                "auth": None if self.auth is None else self.auth.mode,
                "strangers": [p.hex() for p in self.strangers],
                "restarts": self.n_restarts, "plant_end": self.ended, "fault": self.fault,
                "loop": self.loop, "loop_handbacks": self.loop_handbacks}

    def _start(self):
        """STARTING: subscriptions, declare ``alive/controller``, wait for the plant."""
        K, session, cfg = self.K, self.session, self.cfg
        self.sub = tr.declare_subscriber(session, K.sensors, 1024)
        waker = tr.Waker(session, K.sensors)
        self.wd = wd = Watchdog(waker, cfg.sample_timeout, self.stop_fn)
        self.pub = tr.declare_publisher(session, K.currents)
        self.objs += [self.sub, self.pub]

        def _on_event(s):
            self._event(s, wd)
        # direct: the plant publishes a controller_restart event just before the sample it applies
        # to; run on zenoh's receive thread, the callback has queued the restart before that
        # sample reaches the FIFO the loop reads (zenoh-python's default callback thread could
        # lag behind it under load, and the restart came a step late: a trajectory that differed
        # from `simulate` once in a loaded test run)
        self.objs.append(tr.declare_callback_subscriber(session, K.events, _on_event, direct=True))
        # RunMeta: the plant proves the secret by sealing it under the session key of a
        # challenge this controller answered (bridge/process/pairing.py, meta_pairs)
        self._meta_cond = cond = threading.Condition()

        def _on_meta(s, _c=cond):
            with _c:
                self.metas.append((s.payload.to_bytes(), attached(s)))
                _c.notify_all()
        self.objs.append(tr.declare_callback_subscriber(session, K.meta, _on_meta))

        def _live(role, state):
            if role == "plant":
                if state == READY:
                    self.plant_seen = True
                elif self.plant_seen and self.peer_id is not None:
                    self.plant_lost = True     # its token went away: the process is gone
                    wd.wake()                  # (before pairing it may have been a stranger's)
        watch = PeerWatch(session, cfg.run_id, _live, me="controller")
        self.objs.append(watch)
        auth = self.auth
        self.pairing = pairing = Pairing(session, cfg.run_id, "controller", "plant", auth.me, auth)
        self.objs.append(pairing)
        self.me_id = pairing.id
        pairing.announce()                    # the responder, then peer/controller/<id>
        self.presence.ready()
        self.presence.progress("ready; waiting for plant")
        watch.wait(["plant"], cfg.start_timeout, stop=self.stop_fn, report=self.presence.progress)
        self._pair_by_meta(watch)
        self.me = self.cc.me = auth.seal("controller/currents")   # id + mac end every reply
        self.peer = self.sc.peer = auth.peer_seal(self.peer_id, "plant/sensors")
        self.presence.progress(f"paired with plant {self.peer_id.hex()} "
                               f"({'authenticated' if auth.keyed else 'unauthenticated: no key'})")
        wait_matching(self.pub, watch, "plant", cfg.sample_timeout, self.stop_fn)
        self.controller.reset()
        self.presence.progress("running")
        wd.start()

    def _pair_by_meta(self, watch):
        """Wait for the RunMeta that pairs (:func:`meta_pairs`) as long as the plant is alive;
        a RunMeta that does not is rejected (reason ``auth``) and its sender named a stranger."""
        cfg, auth, responder = self.cfg, self.auth, self.pairing.responder
        t_end = time.monotonic() + cfg.sample_timeout
        t_gone = None
        cond = self._meta_cond
        while True:
            with cond:
                todo, self.metas = self.metas, []
            for payload, att in todo:
                meta = meta_pairs(auth, responder, payload, att)
                if meta is not None:
                    self.peer_id, self.meta = bytes(att[:au.ID_LEN]), meta
                    if watch.state("plant") == GONE:
                        self.plant_lost = True
                    return
                self._reject_meta(att)
            if watch.state("plant") in (GONE, ABSENT):
                # the plant went away unpaired: at once, unless strangers came (and went): then
                # the real plant is waited for as an absent one (start_timeout)
                now = time.monotonic()
                t_gone = now if t_gone is None else t_gone
                if not self.strangers or now - t_gone > cfg.start_timeout:
                    raise Fault("plant lost (liveliness) before it proved the run's key"
                                + (f" (strangers: {', '.join(p.hex() for p in self.strangers)})"
                                   if self.strangers else ""))
            else:
                t_gone = None
            if self.stop_fn is not None and self.stop_fn():
                raise Stop()
            if time.monotonic() > t_end:
                raise Fault(f"no RunMeta sealed with the run's key within {cfg.sample_timeout:g} s"
                            + (f" (strangers: {', '.join(p.hex() for p in self.strangers)})"
                               if self.strangers else ""))
            with cond:
                if not self.metas:
                    cond.wait(0.01)

    def _reject_meta(self, att):
        self.rejected["auth"] += 1
        pid = bytes(att[:au.ID_LEN]) if att is not None and len(att) >= au.ID_LEN else None
        if pid is not None and pid not in self.strangers:
            self.strangers.append(pid)
            self.ev.emit(pr.EventKind.WARNING, f"stranger {pid.hex()} sent a RunMeta that failed "
                         f"the pairing proof (no key); ignored", force=True)
        self.ev.emit(pr.EventKind.REJECTED, "run meta rejected: auth: not sealed for a "
                     "challenge this controller answered")

    def _event(self, s, wd):
        """An Event on ``ambhil/<run>/events/<role>`` (zenoh's receive thread).  Only the paired
        plant's, sealed under the session key, with a seq above the last one, is obeyed (its
        RUN_END ends the run, its controller_restart resets the law); anything else that would
        have been obeyed is rejected and counted (docs/protocol.md 5.3)."""
        topic = pr.topic_of(s.key_expr)
        if topic != "events/plant":
            return                              # the controller's own events, or no one's
        payload = s.payload.to_bytes()
        try:
            e = pr.decode_event(payload)
        except pr.ProtocolError:
            return
        obeyable = (e.kind == pr.EventKind.RUN_END
                    or (e.kind == pr.EventKind.FAULT_INJECTED and '"controller_restart"' in e.text))
        if not obeyable:
            return
        why = None
        if self.peer_id is None:
            why = "auth: before pairing"
        elif e.source not in ("plant", "replay"):
            why = f"auth: source {e.source!r} on the plant's key"
        elif self.auth.check(topic, payload, attached(s), self.peer_id) != "session":
            why = "auth: not sealed by the paired plant"
        elif e.seq <= self.plant_event_seq:
            why = f"sequence: event seq {e.seq} replayed (last {self.plant_event_seq})"
        if why is not None:
            self.foreign_events += 1
            if e.kind == pr.EventKind.RUN_END:
                self.foreign_ends += 1          # only the paired plant ends the run
            self.rejected[why.split(":", 1)[0]] += 1
            self.ev.emit(pr.EventKind.REJECTED, f"event {e.kind_name} rejected: {why}")
            return
        self.plant_event_seq = e.seq
        if e.kind == pr.EventKind.RUN_END:
            self.ended = e.text
            wd.wake()
            return
        try:
            f = json.loads(e.text)
        except ValueError:
            return
        if f.get("kind") == "controller_restart" and f.get("phase") == "start":
            # the plant publishes it before sample `step`: reset before answering that one
            self.restarts.append(e.step)

    def _loop(self):
        """RUNNING: answer every sample; wake-ups (empty payloads) check the end conditions
        (:meth:`_slow_sample`).  The ordinary replies run in C where it is built
        (:class:`wire.ControllerLockstep`): the same calls and stamps as the Python loop below,
        back here with a :class:`wire.LoopCode` for anything else, with the received message
        (or the step's new output object) to go on with."""
        controller, cc, restarts = self.controller, self.cc, self.restarts
        recv, put, wall = self.sub.recv, self.pub.put, time.time_ns
        # hot path: see SensorCodec.pack_from (no numpy between recv() and put())
        step = getattr(controller, "step_shared", None) or controller.step
        y_in = np.zeros(self.n)
        y_mv = self.sc.view(y_in)
        c_obj, c_mv = None, None
        # hot path: one codec call per message (bridge/protocol/wire.py, C when built): a well-formed
        # sample with the next seq from the paired plant (its peer id ends the payload,
        # docs/protocol.md 5.1); anything else takes the validating slow path, which names a
        # foreign sender first
        dec_s, enc_c = wire.decode_sensor, wire.encode_current
        me, peer = self.me, self.peer
        self.wd.active = True
        wmark = self.wd.progress
        steps = 0
        last_seq = -1
        self.t_cpu0 = time.process_time()
        cl = None if not wire.NATIVE else wire.ControllerLockstep(
            recv=recv, put=put, y_mv=y_mv, y_in=y_in, step=step, me=me, peer=peer, wmark=wmark,
            restarts=restarts)
        self.loop = "python" if cl is None else "C"
        fresh = -2                      # replies sent when the C loop last met a new output object
        try:
            while True:
                h = None                # the header of the sample answered, once its step ran
                if cl is not None and c_obj is not None:
                    cl.c_obj, cl.c_mv, cl.last_seq, cl.steps = c_obj, c_mv, last_seq, steps
                    try:
                        code = cl.run()
                    finally:
                        last_seq, steps = cl.last_seq, cl.steps
                    self.loop_handbacks += 1
                    if code == LoopCode.SLOW:       # a message for the Python loop
                        data, t_rx = cl.data, cl.t_rx
                    else:                           # the step of sample cl.h ran in C
                        h, t_rx = cl.h, cl.t_rx
                        if code == LoopCode.RAISED:
                            raise Fault(f"controller output invalid at step {h[1]}: {cl.exc}") from cl.exc
                        if code == LoopCode.CHECK:  # step() returned another object
                            c = cl.c
                            if fresh == steps - 1:
                                # a new output array in two steps running: a step object that
                                # returns one each step (most hand-written controllers); the
                                # Python loop serves it without a C call handing back every step
                                cl, self.loop = None, "python"
                            fresh = steps
                            try:
                                c_mv, c_obj = wire.output_view(cc, c)
                            except (ValueError, TypeError) as e:
                                raise Fault(f"controller output invalid at step {h[1]}: {e}")
                        # LoopCode.NONFINITE: the encode below names the axis
                else:
                    smp = recv()
                    data = smp.payload.to_bytes()
                    t_rx = wall()
                if h is None:
                    h = dec_s(data, last_seq + 1, y_mv, peer)
                    if h is not None:
                        last_seq = h[0]
                    else:                       # slow path: wake-ups, malformed, duplicates, gaps
                        h = self._slow_sample(data, y_mv, last_seq, steps)
                        if h is None:
                            continue
                        last_seq = self.last_after  # an unconfirmed jump does not move it
                    if restarts and restarts[0] <= h[1]:    # a scheduled controller restart
                        self._restart(h)
                    try:
                        c = step(y_in)
                        if c is not c_obj:
                            c_mv, c_obj = wire.output_view(cc, c)
                    except (ValueError, TypeError) as e:
                        raise Fault(f"controller output invalid at step {h[1]}: {e}")
                msg = enc_c(c_mv, h[0], h[1], h[2], t_rx, wall(), me)
                if msg is None:
                    raise self._nonfinite(c_mv, h)
                put(msg)
                steps += 1
                wmark[0] = steps
        finally:
            self.steps = steps

    def _slow_sample(self, data, y_mv, last_seq, steps):
        """A message that is not the next fast-path sample, validated and classified: a
        wake-up (empty payload) checks the end conditions, a rejected, duplicate or too far
        ahead sample is counted and reported; a gap is reported.  Returns the header ``(seq,
        step, sim_time_ns, publish_wall_ns)`` of a sample to answer (decoded into ``y_mv``),
        or None (wait for the next message); raises :class:`Stop` at the run's end (the
        plant's RUN_END, a stop request) and :class:`Fault`."""
        rejected, ev = self.rejected, self.ev
        if not data:
            if self.wd.pending > 0:
                self._woken(last_seq, steps)
            else:
                rejected["truncated"] += 1
                ev.emit(pr.EventKind.REJECTED, "sensor sample rejected: empty payload")
            return None
        try:
            hh = self.sc.unpack_into(data, y_mv)
        except pr.ProtocolError as e:
            rejected[e.reason] += 1
            if e.reason in au.UNSEALED:         # not the paired plant's: never answered
                if self.foreign_copies is None:     # kept in the recording, under foreign/
                    self.foreign_copies = ForeignCopies(self.session, self.K.root, "plant/sensors",
                                                        auth=self.auth)
                self.foreign_copies(data)
                what = ("peer: not from the paired plant" if e.reason == "peer" else
                        "auth: not sealed with this run's key" if e.reason == "auth" else str(e))
                ev.emit(pr.EventKind.REJECTED, f"sensor sample rejected: {what} ({e.detail})")
            else:
                ev.emit(pr.EventKind.REJECTED, f"sensor sample rejected: {e}")
            return None
        return self._sequence(hh, last_seq)

    def _sequence(self, hh, last_seq):
        """The sequence rule of a sealed sample off the fast path (docs/protocol.md 5.1): the
        header to answer, with ``last_after`` the last answered seq of the confirmed stream, or
        None.  A jump ahead is answered but moves that seq only once the next sample confirms
        it, so no single message can make the genuine samples stale for more than one period."""
        ev, seq, pending = self.ev, hh[2], self.pending
        if pending is not None and pending > last_seq and seq == pending + 1:
            self.pending, self.last_after = None, seq      # the jump is confirmed
            return hh[2:6]
        if seq <= last_seq or seq == pending:
            self.dups += 1
            ev.emit(pr.EventKind.DUPLICATE, f"duplicate/stale sample seq {seq} "
                    f"(last {last_seq}) ignored", hh[3], hh[4])
            return None
        if seq > last_seq + SEQ_WINDOW:
            # one absurd seq (a corrupted or forged sample) must not move last_seq
            self.rejected["sequence"] += 1
            ev.emit(pr.EventKind.REJECTED, f"sensor sample rejected: sequence: seq "
                    f"{seq} is more than {SEQ_WINDOW} ahead of the last ({last_seq})",
                    hh[3], hh[4])
            return None
        if seq != last_seq + 1:
            self.gaps += seq - last_seq - 1
            ev.emit(pr.EventKind.GAP, f"samples {last_seq + 1}..{seq - 1} missing",
                    hh[3], hh[4])
            self.pending, self.last_after = seq, last_seq   # answered; confirmed by seq + 1
            return hh[2:6]
        self.pending, self.last_after = None, seq
        return hh[2:6]

    def _woken(self, last_seq, steps):
        """A watchdog wake-up: :class:`Stop` when the plant ended the run or a stop is
        requested, :class:`Fault` when the plant is lost or silent too long; else nothing."""
        self.wd.pending -= 1
        if self.ended is not None:
            raise Stop()
        if self.plant_lost:
            # RUN_END may still be in flight on the events callback
            time.sleep(0.02)
            if self.ended is not None:
                raise Stop()
            raise Fault(f"plant lost (liveliness) after {steps} samples")
        if self.wd.fired_mark == steps and steps > 0:
            raise Fault(f"plant timeout: no sample for "
                        f"{self.cfg.sample_timeout * 1e3:g} ms after seq {last_seq}")
        if self.stop_fn is not None and self.stop_fn():
            raise Stop()

    def _restart(self, h):
        """The scheduled controller restart (fault schedule) before the step of sample ``h``."""
        del self.restarts[0]
        self.controller.reset()
        self.n_restarts += 1
        self.ev.emit(pr.EventKind.INFO, f"controller restarted (state reset) before step {h[1]}", h[1], h[2])

    def _nonfinite(self, c_mv, h) -> Fault:
        """The fault of a reply whose currents are not finite (nothing was sent)."""
        v = self.cc._vec.unpack(c_mv)
        bad = next(i for i, x in enumerate(v) if not math.isfinite(x))
        return Fault(f"controller produced non-finite currents at step {h[1]}: "
                     f"axis {bad} = {v[bad]}")
