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
    FAULTED   plant lost, plant silent, invalid controller output: Event FAULT, summary

It waits for samples as long as the plant's liveliness token is present (``sample_timeout``,
default 5 min, is only a last resort) and faults at once when the token goes away.
"""
from __future__ import annotations

import json
import math
import time

import numpy as np

from ambhil.bridge.process import transport as tr
from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import wire
from ambhil.bridge.process.events import Fault, ForeignCopies, Phase, Stop
from ambhil.bridge.process.pairing import Pairing, attached
from ambhil.bridge.process.startup import READY, PeerWatch, Presence, wait_matching
from ambhil.bridge.process.timing import pin_cpus
from ambhil.bridge.process.watchdog import Watchdog, stop_fn as _stop_fn

SEQ_WINDOW = 1 << 16       # a sample more than this many seq ahead of the last is rejected


def run_controller(controller, run_id: str, *, connect=None, listen=None,
                   sample_timeout: float = 300.0, start_timeout: float = 30.0, stop=None,
                   cpus=None, session=None, presence: Presence | None = None) -> dict:
    """Run the controller side: answer every SensorSample with a CurrentCommand carrying
    the same seq.  Ends on the plant's RUN_END event (clean), or with a fault if the plant's
    liveliness token disappears without RUN_END, or (last resort) no sample arrives for
    ``sample_timeout`` s after the first one although the plant is alive.

    ``presence``: the process's :class:`ambhil.bridge.process.startup.Presence` if it declared itself before
    building the controller (then ``session`` is its session); else one is made here.
    ``start_timeout``: how long the plant may be *absent* (no liveliness token at all)."""
    return ControllerNode(controller, run_id, connect=connect, listen=listen,
                          sample_timeout=sample_timeout, start_timeout=start_timeout,
                          stop=stop, cpus=cpus, session=session, presence=presence).run()


class ControllerNode:
    """One controller run; use :func:`run_controller`."""

    def __init__(self, controller, run_id, *, connect, listen, sample_timeout, start_timeout,
                 stop, cpus, session, presence):
        self.controller, self.run_id = controller, run_id
        self.connect, self.listen, self.cpus = connect, listen, cpus
        self.sample_timeout, self.start_timeout = sample_timeout, start_timeout
        self.stop_fn = _stop_fn(stop)
        self.K = pr.keys(run_id)
        self.n = int(controller.n_axes)
        self.session, self.own_session = session, session is None
        self.presence, self.own_presence = presence, presence is None
        if presence is not None:
            self.session, self.own_session = presence.session, False
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
        self.me = self.peer = None            # peer ids (bridge/process/pairing.py)
        self.foreign_ends = 0                 # RUN_END events not from the paired plant
        self.foreign_copies = None            # rejected foreign samples -> foreign/ (recording)
        self.restarts: list[int] = []  # steps before which the controller restarts (fault schedule)
        self.n_restarts = 0
        self.loop = None            # "C" when bridge/protocol/_wire.c answers the ordinary samples, else "python"
        self.loop_handbacks = 0     # returns of the C loop to Python (a message or step it does not handle)

    def run(self) -> dict:
        pin_cpus(self.cpus)
        if self.own_session:
            self.session = tr.open_session(self.listen, self.connect)
        if self.own_presence:
            self.presence = Presence(self.session, self.run_id, "controller")
        self.ev = self.presence.events
        try:
            self._start()
            self.phase = Phase.RUNNING
            self._loop()
        except Stop:
            pass
        except Fault as f:
            self.fault = str(f)
        except tr.TransportError as e:
            self.fault = str(e)
        except KeyboardInterrupt:
            self.fault = "interrupted"
        if self.fault:
            self.phase = Phase.FAULTED
            self.ev.emit(pr.EventKind.FAULT, self.fault, force=True)
        self.phase = Phase.STOPPING
        if self.wd is not None:
            self.wd.done = True
        tr.close_quietly(*reversed(self.objs))
        self.presence.close()
        if self.own_session:
            tr.close_quietly(self.session)
        steps = self.steps
        return {"role": "controller", "run_id": self.run_id, "steps": steps,
                "duplicates": self.dups, "gaps": self.gaps,
                "rejected": {k: v for k, v in self.rejected.items() if v},
                "rejected_total": sum(self.rejected.values()),
                "cpu_us_per_step": (round((time.process_time() - self.t_cpu0) / steps * 1e6, 2)
                                    if steps and self.t_cpu0 is not None else None),
                "foreign_run_ends": self.foreign_ends,
                "foreign_copied": self.foreign_copies.copied if self.foreign_copies else 0,
                "paired_plant": None if self.peer is None else self.peer.hex(),
                "restarts": self.n_restarts, "plant_end": self.ended, "fault": self.fault,
                "loop": self.loop, "loop_handbacks": self.loop_handbacks}

    def _start(self):
        """STARTING: subscriptions, declare ``alive/controller``, wait for the plant."""
        K, session = self.K, self.session
        self.sub = tr.declare_subscriber(session, K.sensors, 1024)
        waker = tr.Waker(session, K.sensors)
        self.wd = wd = Watchdog(waker, self.sample_timeout, self.stop_fn)
        self.pub = tr.declare_publisher(session, K.currents)
        self.objs += [self.sub, self.pub]

        def _on_event(s):
            try:
                e = pr.decode_event(s.payload.to_bytes())
            except pr.ProtocolError:
                return
            if e.kind == pr.EventKind.RUN_END and e.source in ("plant", "replay"):
                if self.peer is None or attached(s) != self.peer:
                    self.foreign_ends += 1      # only the paired plant ends the run
                    return
                self.ended = e.text
                wd.wake()
            elif (e.kind == pr.EventKind.FAULT_INJECTED and e.source == "plant"
                  and '"controller_restart"' in e.text and attached(s) == self.peer):
                try:
                    f = json.loads(e.text)
                except ValueError:
                    return
                if f.get("kind") == "controller_restart" and f.get("phase") == "start":
                    # the plant publishes it before sample `step`: reset before answering that one
                    self.restarts.append(e.step)
        # direct: the plant publishes a controller_restart event just before the sample it applies
        # to; run on zenoh's receive thread, the callback has queued the restart before that
        # sample reaches the FIFO the loop reads (zenoh-python's default callback thread could
        # lag behind it under load, and the restart came a step late: a trajectory that differed
        # from `simulate` once in a loaded test run)
        self.objs.append(tr.declare_callback_subscriber(session, K.events, _on_event, direct=True))

        def _live(role, state):
            if role == "plant":
                if state == READY:
                    self.plant_seen = True
                elif self.plant_seen:          # its token went away: the process is gone
                    self.plant_lost = True
                    wd.wake()
        watch = PeerWatch(session, self.run_id, _live, me="controller")
        self.objs.append(watch)
        self.pairing = pairing = Pairing(session, self.run_id, "controller", "plant")
        self.objs.append(pairing)
        self.me = pairing.id
        self.cc.me = self.me                  # the id that ends every reply (protocol 2)
        pairing.announce()
        self.presence.ready()
        self.presence.progress("ready; waiting for plant")
        watch.wait(["plant"], self.start_timeout, stop=self.stop_fn, report=self.presence.progress)
        self.peer = pairing.wait(watch, self.sample_timeout, self.stop_fn)
        self.sc.peer = self.peer              # the only sender whose samples are answered
        self.presence.progress(f"paired with plant {self.peer.hex()}")
        wait_matching(self.pub, watch, "plant", self.sample_timeout, self.stop_fn)
        self.controller.reset()
        self.presence.progress("running")
        wd.start()

    def _loop(self):
        """RUNNING: answer every sample; wake-ups (empty payloads) check the end conditions."""
        controller, wd, ev, rejected = self.controller, self.wd, self.ev, self.rejected
        stop_fn, sample_timeout = self.stop_fn, self.sample_timeout
        recv = self.sub.recv
        wall = time.time_ns
        put = self.pub.put
        # hot path: see SensorCodec.pack_from (no numpy between recv() and put())
        step = getattr(controller, "step_shared", None) or controller.step
        y_in = np.zeros(self.n)
        y_mv = self.sc.view(y_in)
        unpack = self.sc.unpack_into
        cc = self.cc
        c_obj, c_mv = None, None
        # hot path: one codec call per message (bridge/protocol/wire.py, C when built): a well-formed
        # sample with the next seq from the paired plant (its peer id ends the payload,
        # docs/protocol.md 5.1); anything else takes the validating slow path, which names a
        # foreign sender first
        dec_s, enc_c = wire.decode_sensor, wire.encode_current
        me, peer = self.me, self.peer
        wd.active = True
        wmark = wd.progress
        steps = dups = gaps = 0
        last_seq = -1
        restarts = self.restarts
        self.t_cpu0 = time.process_time()
        # the ordinary replies run in C when it is built (bridge/protocol/_wire.c, controller_lockstep):
        # the same calls and stamps as below, back here for anything else, with the received
        # message (or the step's new output object) to go on with
        drive = wire._wire.controller_lockstep if wire.NATIVE else None
        self.loop = "python" if drive is None else "C"
        st = np.zeros(2, np.int64)      # (last_seq, steps) as the C loop leaves them
        resume = None
        fresh = -2                      # replies sent when the C loop last met a new output object
        try:
            while True:
                if drive is not None and c_obj is not None:
                    st[0], st[1] = last_seq, steps
                    try:
                        code, ra, rb, rc = drive(recv, put, y_mv, y_in, step, c_obj, c_mv, me,
                                                 peer, wmark, restarts, st)
                    finally:
                        last_seq, steps = int(st[0]), int(st[1])
                    self.loop_handbacks += 1
                    if code == 1:           # a message for the loop below
                        data, t_rx = ra, rb
                    else:                   # the step of sample ra/rb[0] ran in C
                        resume = code, ra, rb, rc
                        if code == 3:
                            if fresh == steps - 1:
                                # a new output array in two steps running: a step object that
                                # returns one each step (most hand-written controllers); the
                                # Python loop serves it without a C call handing back every step
                                drive, self.loop = None, "python"
                            fresh = steps
                else:
                    smp = recv()
                    data = smp.payload.to_bytes()
                    t_rx = wall()
                if resume is None:
                    h = dec_s(data, last_seq + 1, y_mv, peer)
                else:
                    h = None
                if h is None and resume is None:   # slow path: wake-ups, malformed, duplicates, gaps
                    if not data:
                        if wd.pending > 0:
                            wd.pending -= 1
                            if self.ended is not None:
                                break
                            if self.plant_lost:
                                # RUN_END may still be in flight on the events callback
                                time.sleep(0.02)
                                if self.ended is not None:
                                    break
                                raise Fault(f"plant lost (liveliness) after {steps} samples")
                            if wd.fired_mark == steps and steps > 0:
                                raise Fault(f"plant timeout: no sample for "
                                            f"{sample_timeout * 1e3:g} ms after seq {last_seq}")
                            if stop_fn is not None and stop_fn():
                                break
                            continue
                        rejected["truncated"] += 1
                        ev.emit(pr.EventKind.REJECTED, "sensor sample rejected: empty payload")
                        continue
                    try:
                        hh = unpack(data, y_mv)
                    except pr.ForeignError as e:    # not from the paired plant: never answered
                        rejected[e.reason] += 1
                        if self.foreign_copies is None:     # kept in the recording, under foreign/
                            self.foreign_copies = ForeignCopies(self.session, self.K.root, "plant/sensors")
                        self.foreign_copies(data)
                        ev.emit(pr.EventKind.REJECTED, f"sensor sample rejected: peer: not from the "
                                f"paired plant ({e.detail})")
                        continue
                    except pr.ProtocolError as e:
                        rejected[e.reason] += 1
                        ev.emit(pr.EventKind.REJECTED, f"sensor sample rejected: {e}")
                        continue
                    seq = hh[2]
                    if seq <= last_seq:
                        dups += 1
                        ev.emit(pr.EventKind.DUPLICATE, f"duplicate/stale sample seq {seq} "
                                f"(last {last_seq}) ignored", hh[3], hh[4])
                        continue
                    if seq > last_seq + SEQ_WINDOW:
                        # one absurd seq (a corrupted or forged sample) must not move last_seq
                        rejected["sequence"] += 1
                        ev.emit(pr.EventKind.REJECTED, f"sensor sample rejected: sequence: seq "
                                f"{seq} is more than {SEQ_WINDOW} ahead of the last ({last_seq})",
                                hh[3], hh[4])
                        continue
                    if seq != last_seq + 1:
                        gaps += seq - last_seq - 1
                        ev.emit(pr.EventKind.GAP, f"samples {last_seq + 1}..{seq - 1} missing",
                                hh[3], hh[4])
                    h = hh[2:6]
                if resume is None:
                    last_seq = h[0]
                    if restarts and restarts[0] <= h[1]:    # a scheduled controller restart
                        del restarts[0]
                        controller.reset()
                        self.n_restarts += 1
                        ev.emit(pr.EventKind.INFO, f"controller restarted (state reset) before step {h[1]}", h[1], h[2])
                    try:
                        c = step(y_in)
                        if c is not c_obj:
                            c_mv, c_obj = wire.output_view(cc, c)
                    except (ValueError, TypeError) as e:
                        raise Fault(f"controller output invalid at step {h[1]}: {e}")
                else:
                    code, ra, rb, rc = resume
                    resume = None
                    if code == 3:           # step() returned another object
                        c, h, t_rx = ra, rb, rc
                        try:
                            c_mv, c_obj = wire.output_view(cc, c)
                        except (ValueError, TypeError) as e:
                            raise Fault(f"controller output invalid at step {h[1]}: {e}")
                    elif code == 4:         # step() raised
                        raise Fault(f"controller output invalid at step {rb[1]}: {ra}") from ra
                    else:                   # code 5: the output is not finite
                        h, t_rx = ra, rb
                msg = enc_c(c_mv, last_seq, h[1], h[2], t_rx, wall(), me)
                if msg is None:
                    v = cc._vec.unpack(c_mv)
                    bad = next(i for i, x in enumerate(v) if not math.isfinite(x))
                    raise Fault(f"controller produced non-finite currents at step {h[1]}: "
                                f"axis {bad} = {v[bad]}")
                put(msg)
                steps += 1
                wmark[0] = steps
        finally:
            self.steps, self.dups, self.gaps = steps, dups, gaps
