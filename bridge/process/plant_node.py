"""The plant process over zenoh, for any duck-typed plant step object.

Plant step object::

    n_axes: int; period: float (controller period, s)
    reset() -> y0 (n_axes displacements); advance(currents) -> y (one period, currents held)
    step_index: int; sim_time: float (s); safe_state()   # called on a fault

Optional fast path: ``plant.advance_shared(u)`` may return its own output buffer (no copy), and a
plant may expose ``status`` (0 = OK), ``FATAL`` (statuses that end the run) and ``fault`` (one-line
text).  The arrays the bridge passes in (``u``) are its own preallocated buffers, overwritten every
period: copy what you keep.  The plant's sim time on the wire is ``step_index * period`` (integer ns).

The process is a small state machine (:class:`ambhil.bridge.process.events.Phase`)::

    STARTING  ``starting/plant`` token (bridge/process/startup.py; the CLI declares it before building
              the model), subscriptions, ``alive/plant``; wait for the peers to be ready
    READY     RunMeta and RUN_START published, plant reset
    RUNNING   ambhil.bridge.process.plant_lockstep.lockstep or .plant_realtime.realtime
    STOPPING  timing flushed, RUN_END, tokens undeclared, summary
    FAULTED   (from any of the above) Event FAULT, plant.safe_state(), then STOPPING

Modes
-----
``lockstep``: the plant publishes sample k and waits for the currents answering seq k
before advancing; with ``delay_samples=n`` it applies the currents computed from sample
k-n (zeros before that).  Deterministic: same trajectory as
:func:`ambhil.bridge.process.reference.run_inprocess`.  It waits as long as the controller's liveliness
token is present (``reply_timeout``, default ``wait_cap_s`` = 5 min, is only a last resort).

``realtime``: the clock starts when the controller has answered sample 0 (until then the
plant holds its start state, ``reset()``, without integrating); then sample k is published
at the absolute deadline ``t0 + k*T``; the reply must arrive before ``t0 + (k+1)*T - guard``;
it is then applied over the interval k -> k+1 (same arithmetic as lockstep with no delay).
A missing reply -> last currents held, overrun counted.  Replies are timestamped on arrival
(zenoh callback) for the round trip.

Watchdog: liveliness DELETE of the controller ends the run at once; so does no reply within
``reply_timeout`` (real time: 10 periods by default); ``summary["fault"]`` is then a one-line
reason (after ``plant.safe_state()``).  Auxiliary bearings' contact: bridge/process/plant_contact.py.
"""
from __future__ import annotations

import json
import os
import queue
import time

import numpy as np

from ambhil.bridge.process import transport as tr
from ambhil.bridge import protocol as pr
from ambhil.bridge.process import deadline
from ambhil.bridge.process import plant_contact, plant_lockstep, plant_realtime
from ambhil.bridge.protocol import record_batch
from ambhil.bridge.protocol import wire
from ambhil.bridge.process.config import (CURRENTS_AT, LOCKSTEP, MODES, PEER_WAIT_CAP_S,  # noqa: F401
                                          REALTIME, PlantNodeConfig)
from ambhil.bridge.process.events import Fault, ForeignCopies, Phase, Stop, versions
from ambhil.bridge.process.pairing import Pairing
from ambhil.bridge.process.startup import GONE, READY, PeerWatch, Presence, wait_matching
from ambhil.bridge.process.timing import CpuWakeLatency, histogram_us, pin_cpus, set_timer_slack, stats_us, window_rates
from ambhil.bridge.process.watchdog import Watchdog, stop_fn as _stop_fn
from ambhil.bridge.protocol.wire import output_view


def run_plant(plant, cfg: PlantNodeConfig, *, stop=None, session=None,
              presence: Presence | None = None) -> dict:
    """Run the plant side of a HIL run as ``cfg`` (:class:`ambhil.bridge.process.config.PlantNodeConfig`)
    says.  The plant normally *listens* (``listen="tcp/127.0.0.1:PORT"``); controller and recorder connect.
    ``stop``: a callable or event that ends the run early.  Returns a summary dict; ``summary["fault"]`` is
    None or a one-line reason (see :func:`ambhil.bridge.process.events.exit_code`).

    ``presence``: the process's :class:`ambhil.bridge.process.startup.Presence` if it declared itself before
    building the plant (then ``session`` is its session); else one is made here.  ``start_timeout``: how long
    a peer may be *absent* (no liveliness token at all) before the run gives up; a present peer is waited for
    without limit.  ``reply_timeout``: real time, the controller is dead after that long without any reply
    (default 10 periods); lockstep, a last-resort cap on waiting for a live controller (``wait_cap_s``).
    ``currents_at`` (real time): ``"sample"`` applies the reply to sample k over the whole period k -> k+1
    (the simulated loop sees no latency, only held periods); ``"arrival"`` makes the coils take it when it
    arrived, ``ceil((lateness + round trip) / h)`` plant steps into the period (the plant needs
    ``advance_arriving``, e.g. ``PlantRunner``): the loop then sees the latency the machine and the network
    measured, as a real plant would.  ``cpu_wake_us`` (real time): hold a PM QoS request on the CPUs' wake-up
    latency for the run (:class:`ambhil.bridge.process.timing.CpuWakeLatency`; None: none); the summary's
    ``cpu_wake_latency`` says whether it was granted.  ``rt_receive`` (real time): how the loop waits for a
    reply (bridge/process/deadline.py): ``"deadline"`` = blocking FIFO ``recv()`` woken at the window's end
    by a C timer thread on another CPU, ``"callback"`` = a zenoh callback feeding a queue, ``"auto"`` =
    deadline where it can be had; the summary's ``rt_receive`` says which was used."""
    node = PlantNode(plant, cfg, stop=stop, session=session, presence=presence)
    return node.run()


def _check_arrival(plant, cfg: PlantNodeConfig):
    """Currents applied at their arrival need a plant that can take them mid-period."""
    if cfg.currents_at == "arrival":
        if not hasattr(plant, "advance_arriving"):
            raise ValueError("currents applied at their arrival: the plant has no advance_arriving")
        if getattr(plant, "ring", None) is not None:
            raise ValueError("currents applied at their arrival: not with a fixed plant latency (--delay)")


class PlantNode:
    """One plant run: the state (buffers, counters, zenoh objects) the loops share, and the
    phase transitions around them.  Use :func:`run_plant`."""

    def __init__(self, plant, cfg: PlantNodeConfig, *, stop=None, session=None, presence=None):
        _check_arrival(plant, cfg)
        self.rt_receive, self.timer_cpu, self.rt_receive_why = (     # the receive used, its why
            deadline.choose(cfg.rt_receive, cfg.cpus) if cfg.mode == REALTIME else (None, None, None))
        self.dl = None        # bridge.process._deadline.DeadlineTimer of the real-time "deadline" receive
        self.cpu_qos = None
        self.plant, self.stop_fn, self.K = plant, _stop_fn(stop), pr.keys(cfg.run_id)
        self.n = n = int(plant.n_axes)
        self.period = period = float(plant.period)
        self.period_ns = int(round(period * 1e9))
        self.cfg = cfg = cfg.settled(period)    # reply_timeout, warmup_steps, cpu_wake_us settled
        self.presence, self.own_presence = presence, presence is None
        self.session = session if presence is None else presence.session
        self.own_session = session is None and presence is None
        self.sc, self.cc = pr.SensorCodec(n), pr.CurrentCodec(n)
        self.rejected = {r: 0 for r in pr.REASONS}
        self.counts = {"duplicates": 0, "late_replies": 0, "held": 0, "late_wakes": 0,
                       "foreign_peers": 0}
        self.foreign_copies = None          # rejected foreign replies -> foreign/ (recording)
        self.me = self.peer = None          # seals of the loop codecs: id + topic key (protocol 3)
        self.me_id = self.peer_id = None    # the peer ids (bridge/process/pairing.py)
        self.auth = None                    # the run's keys (bridge/protocol/auth.py), from presence
        self.strangers: list[bytes] = []    # announced as controller, failed the pairing proof
        # per step: wake lateness, round trip, controller TET (ns), flags; the trace of y and u
        self.lat, self.rtt, self.tet = (np.zeros(cfg.n_steps, np.int64) for _ in range(3))
        self.flags = np.zeros(cfg.n_steps, np.uint8)
        self.Y = np.empty((cfg.n_steps + 1, n)) if cfg.trace else None
        self.U = np.empty((cfg.n_steps, n)) if cfg.trace else None
        self.peer_lost = False
        self.loop = "python"        # lockstep: "C" when bridge/protocol/_plant_lockstep.c runs the ordinary steps
        self.loop_handbacks = 0     # steps the C loop handed back to Python (see plant_lockstep.py)
        self.phase, self.fault, self.end_reason = Phase.STARTING, None, "completed"
        self.steps_done = self.overruns = self.sim_ns = 0
        self.wall_s, self.cpu_s, self.t_wall0 = 0.0, None, None
        self.wd, self.objs, self.ev, self.contact = None, [], None, None   # contact: plant_contact.py
        self.tbatch = {"seq": 0, "start": 0}
        self.marks = []       # (steps done, perf_counter_ns) at each Timing flush: rate windows
        self.replies = []     # lockstep: reply tuples of the current timing batch (for TET)
        self.timing_pub = None
        self.rb = None        # bridge.protocol.record_batch.Batcher, made in _start

    # ------------------------------------------------------------------ the state machine
    def run(self) -> dict:
        cfg = self.cfg
        pin_cpus(cfg.cpus)
        if cfg.mode == REALTIME:
            set_timer_slack(1000)
            self.cpu_qos = CpuWakeLatency(cfg.cpu_wake_us)
        if self.own_session:
            self.session = tr.open_session(cfg.listen, cfg.connect)
        if self.own_presence:
            self.presence = Presence(self.session, cfg.run_id, "plant", secret=cfg.secret,
                                     insecure=cfg.insecure)
        self.ev = self.presence.events
        self.auth = auth = self.presence.auth
        if hasattr(self.plant, "on_event"):    # a plant with scheduled faults (plant/faults.py)
            ev = self.ev
            self.plant.on_event = lambda step, sim_ns, text: ev.emit(pr.EventKind.FAULT_INJECTED, text, step,
                                                                    sim_ns, force=True)
        self.contact = plant_contact.of(self.plant, self.ev, self.period_ns)
        try:
            self._start()                      # STARTING
            self.phase = Phase.READY
            self._announce()
            self._reset_plant()
            self.phase = Phase.RUNNING
            self.presence.progress(f"running ({cfg.mode}, {cfg.n_steps} steps)")
            self.t_wall0 = time.perf_counter()
            self.t_cpu0 = time.process_time()
            self.marks.append((0, time.perf_counter_ns()))
            loop = plant_lockstep.lockstep if cfg.mode == LOCKSTEP else plant_realtime.realtime
            loop(self)
            if cfg.trace:
                self.Y[self.steps_done] = self.y
            self._measure(cpu=True)
        except Stop:
            self.end_reason = "stopped"
            self._measure(cpu=True)
        except Fault as f:
            self.fault = str(f)
            self._measure(cpu=False)
        except tr.TransportError as e:
            self.fault = str(e)
        except KeyboardInterrupt:
            # Ctrl-C, or SIGTERM (`ambhil run` stopping it, its parent gone): a stop on request,
            # not a fault of the loop; RUN_END says "interrupted", the summary has its steps
            self.end_reason = "interrupted"
            self._measure(cpu=True)
        self.fault_wall_ns = None
        if self.fault is not None:
            self._faulted()
        self.phase = Phase.STOPPING
        self._shutdown()
        return self._summary()

    def _measure(self, cpu: bool):
        if self.t_wall0 is not None:
            self.wall_s = time.perf_counter() - self.t_wall0
            if cpu:
                self.cpu_s = time.process_time() - self.t_cpu0

    def _start(self):
        """STARTING: subscriptions and publishers, ``alive/plant``, wait for the peers to be
        ready (as long as they are alive: bridge/process/startup.py)."""
        K, session, cfg = self.K, self.session, self.cfg
        if cfg.mode == LOCKSTEP:
            self.sub = tr.declare_subscriber(session, K.currents, 1024)
            waker = tr.Waker(session, K.currents)
            self.wd = Watchdog(waker, cfg.reply_timeout, self.stop_fn)
            self.wd.active = True
            on_lost = self.wd.wake
        elif self.rt_receive == "deadline":
            self.sub = tr.declare_subscriber(session, K.currents, 1024)
            waker = tr.Waker(session, K.currents)
            self.dl = deadline.DeadlineTimer(lambda _seq, _w=waker: _w.wake(), self.period_ns,
                                             self.timer_cpu)
            on_lost = waker.wake
        else:
            self.rxq = rxq = queue.SimpleQueue()
            _now = time.perf_counter_ns

            def _cb(s, _q=rxq, _now=_now):
                _q.put((_now(), s.payload.to_bytes()))
            self.sub = tr.declare_callback_subscriber(session, K.currents, _cb)
            on_lost = lambda: rxq.put((time.perf_counter_ns(), None))  # noqa: E731
        self.pub = tr.declare_publisher(session, K.sensors)
        self.meta_pub = tr.declare_publisher(session, K.meta)
        self.timing_pub = tr.declare_publisher(session, K.timing)
        # the loop's traffic for the recorder, in batches off the critical path
        auth = self.auth
        self.rb = record_batch.Batcher(tr.declare_publisher(session, K.record),
                                       attach=lambda d, _a=auth: _a.attach("record", d))
        self.objs += [self.sub, self.pub, self.meta_pub, self.timing_pub, self.rb.pub]
        ready = {"controller": False}

        def _live(role, state):
            if role == "controller":
                if state == READY:
                    ready["controller"] = True
                elif ready["controller"] and self.peer_id is not None:
                    self.peer_lost = True          # its token went away: the process is gone
                    on_lost()                      # (before pairing it may have been a stranger's)
        self.peers = watch = PeerWatch(session, cfg.run_id, _live, me="plant")
        self.objs.append(watch)
        self.pairing = pairing = Pairing(session, cfg.run_id, "plant", "controller", auth.me, auth)
        self.objs.append(pairing)
        self.me_id = pairing.id
        pairing.on_stranger = self._stranger
        pairing.announce()
        self.presence.ready()
        need = ["controller"] + (["recorder"] if cfg.wait_recorder else [])
        self.presence.progress(f"ready; waiting for {', '.join(need)}")
        watch.wait(need, cfg.start_timeout, stop=self.stop_fn, report=self.presence.progress)
        self.peer_id = pairing.wait(watch, cfg.wait_cap_s, self.stop_fn,
                                    absent_timeout=cfg.start_timeout)
        if watch.state("controller") == GONE:
            self.peer_lost = True
        # the session key: both ids, both nonces of the challenge the controller answered
        auth.pair(self.me_id, self.peer_id, *pairing.nonces)
        self.me = self.sc.me = auth.seal("plant/sensors")     # id + mac end every sample
        self.peer = self.cc.peer = auth.peer_seal(self.peer_id, "controller/currents")
        pairing.on_extra = self._extra_controller
        for pid in list(pairing.extra):
            self._extra_controller(pid)
        self.presence.progress(f"paired with controller {self.peer_id.hex()} "
                               f"({'authenticated' if auth.keyed else 'unauthenticated: no key'})")
        wait_matching(self.pub, watch, "controller", cfg.wait_cap_s, self.stop_fn)
        if self.peer_lost:
            raise Fault("controller lost before start")

    def _announce(self):
        """READY: RunMeta and RUN_START."""
        cfg = self.cfg
        info = {"run_id": cfg.run_id, "mode": cfg.mode, "n_axes": self.n,
                "plant_peer_id": self.me_id.hex(), "controller_peer_id": self.peer_id.hex(),
                "auth": self.auth.describe(),
                "period_s": self.period, "rate_hz": 1.0 / self.period, "n_steps": cfg.n_steps,
                "delay_samples": cfg.delay_samples, "reply_timeout_s": cfg.reply_timeout,
                "versions": versions(), "wall_start_ns": time.time_ns()}
        info.update(cfg.meta or {})
        data = pr.encode_meta(pr.RunMeta(info, wall_ns=time.time_ns()))
        self.meta_pub.put(data, attachment=self.auth.attach("meta", data))
        self.ev.emit(pr.EventKind.RUN_START, json.dumps({"mode": cfg.mode,
                                                         "n_steps": cfg.n_steps}), force=True)

    def _reset_plant(self):
        """The plant at its start state; codec views of its output and of the reply buffer."""
        plant, n = self.plant, self.n
        self.y = y = np.asarray(plant.reset(), dtype=float)
        if y.shape != (n,):
            raise Fault(f"plant.reset() returned shape {y.shape}, expected ({n},)")
        # hot path (see bridge/protocol/wire.py): vectors move as bytes through memoryviews of
        # preallocated arrays; timing rows are written through memoryviews, not numpy
        self.advance = getattr(plant, "advance_shared", None) or plant.advance
        if self.contact is not None:     # a fresh contact log, read after every period (C loop too)
            self.advance = self.contact.fresh(self.advance)
        self.fatal = tuple(getattr(plant, "FATAL", ()))
        self.has_status = hasattr(plant, "status")
        self.y_mv, self.y_obj = output_view(self.sc, y)
        self.rx = np.zeros(n)                   # received currents (scratch)
        self.rx_mv = self.cc.view(self.rx)
        self.newton_warned = False

    def _faulted(self):
        """FAULTED: Event FAULT, then the plant's safe state."""
        self.phase = Phase.FAULTED
        self.fault_wall_ns = time.time_ns()
        self.ev.emit(pr.EventKind.FAULT, self.fault, self.steps_done, self.sim_ns, force=True)
        try:
            self.plant.safe_state()
        except Exception as e:  # still report the original fault
            self.fault += f" (safe_state raised {type(e).__name__}: {e})"
        self.end_reason = "fault"

    def _shutdown(self):
        """STOPPING: last timing batch, RUN_END, tokens and session closed."""
        if self.cpu_qos is not None:
            self.cpu_qos.release()
        try:
            if self.timing_pub is not None:
                self.flush_timing(self.steps_done)
        except Exception:
            pass
        try:
            if self.rb is not None:
                self.rb.flush(time.time_ns())     # before RUN_END: same link, same order
        except Exception:
            pass
        if self.wd is not None:
            self.wd.done = True
        if self.dl is not None:
            self.dl.close()
        if self.contact is not None:         # the recording's run_end keeps it
            self.contact.emit_summary(self.steps_done, self.sim_ns)
        self.ev.emit(pr.EventKind.RUN_END, json.dumps({"reason": self.end_reason,
                                                       "steps": self.steps_done,
                                                       "fault": self.fault,
                                                       "rejected": {k: v for k, v in
                                                                    self.rejected.items() if v}}),
                     self.steps_done, self.sim_ns, force=True)
        time.sleep(self.cfg.end_grace_s)     # let the controller/recorder see RUN_END before DELETE
        tr.close_quietly(*reversed(self.objs))
        self.presence.close()
        if self.own_session:
            tr.close_quietly(self.session)

    def _summary(self) -> dict:
        cfg = self.cfg
        steps_done, rtt, tet, lat = self.steps_done, self.rtt, self.tet, self.lat
        ok = slice(min(cfg.warmup_steps, steps_done), steps_done)
        wall_s, cpu_s = self.wall_s, self.cpu_s
        summary = {
            "role": "plant", "run_id": cfg.run_id, "mode": cfg.mode, "steps": steps_done,
            "n_steps": cfg.n_steps, "period_s": self.period, "delay_samples": cfg.delay_samples,
            "currents_at": cfg.currents_at,
            "loop": self.loop, "loop_handbacks": self.loop_handbacks,
            "wall_s": round(wall_s, 6),
            "cpu_us_per_step": round(cpu_s / steps_done * 1e6, 2) if steps_done and cpu_s else None,
            "steps_per_s": round(steps_done / wall_s, 1) if wall_s > 0 else 0.0,
            # steps/s over 0.1 s windows (from the Timing flushes): p90 = the run's quiet spells
            "steps_per_s_windows": window_rates(self.marks),
            # the marks themselves for benchmarks that time-slice runs (python -m benchmarks.sliced)
            **({"rate_marks": self.marks} if os.environ.get("AMBHIL_RATE_MARKS") else {}),
            "warmup_steps": cfg.warmup_steps, "overruns": self.overruns, **self.counts,
            "latency_us": stats_us(rtt[ok][rtt[ok] > 0]) if steps_done else {"n": 0},
            "tet_us": stats_us(tet[ok][rtt[ok] > 0]) if steps_done else {"n": 0},
            "lateness_us": stats_us(lat[ok]) if cfg.mode == REALTIME and steps_done else {"n": 0},
            "latency_histogram_us": histogram_us(rtt[ok][rtt[ok] > 0]),
            "rejected": {k2: v for k2, v in self.rejected.items() if v},
            "rejected_total": sum(self.rejected.values()),
            "foreign_copied": self.foreign_copies.copied if self.foreign_copies else 0,
            "auth": None if self.auth is None else self.auth.mode,
            "strangers": [p.hex() for p in self.strangers],
            "paired_controller": None if self.peer_id is None else self.peer_id.hex(),
            "events_suppressed": self.ev.suppressed,
            "fault": self.fault, "fault_wall_ns": self.fault_wall_ns,
            "end_reason": self.end_reason,
            "contact": None if self.contact is None else self.contact.summary(),
            "cpu_wake_latency": None if self.cpu_qos is None else self.cpu_qos.status,
            "rt_receive": None if self.rt_receive is None else
            {"mode": self.rt_receive, "timer_cpu": self.timer_cpu, "why": self.rt_receive_why,
             **({} if self.dl is None else self.dl.stats())},
        }
        if cfg.trace:
            summary["trace"] = {"y": self.Y[:steps_done + 1], "u": self.U[:steps_done]}
        return summary

    # ------------------------------------------------------------------ used by the loops
    def flush_timing(self, upto):
        """Publish the Timing batch of steps ``tbatch["start"]..upto-1``."""
        tb = self.tbatch
        a = tb["start"]
        if self.replies:
            self.tet[a:a + len(self.replies)] = [r[4] - r[3] for r in self.replies]
            self.replies.clear()
        if upto <= a:
            return
        if wire.NATIVE:          # one C call: this runs on the loop's thread every 200 steps
            msg = wire._wire.pack_timing(tb["seq"], a, a * self.period_ns, self.period_ns,
                                         self.overruns, self.lat[a:upto], self.rtt[a:upto],
                                         self.tet[a:upto], self.flags[a:upto])
        else:
            msg = pr.encode_timing(pr.Timing(a, a * self.period_ns, self.period_ns, self.overruns,
                                             self.lat[a:upto], self.rtt[a:upto], self.tet[a:upto],
                                             self.flags[a:upto], tb["seq"]))
        tb["seq"] += 1
        tb["start"] = upto
        self.marks.append((upto, time.perf_counter_ns()))
        try:
            self.timing_pub.put(msg, attachment=self.auth.attach("timing", msg))
        except Exception:
            pass

    def foreign(self, e: pr.ProtocolError, data=None) -> pr.ProtocolError:
        """Why a reply that is not the paired controller's is rejected (``e``: the codec's
        reason: ``peer``, ``auth``, or a header no sender of this run writes); ``data``, the
        reply, goes to the recording under ``foreign/``
        (:class:`ambhil.bridge.process.events.ForeignCopies`), never into the run's channels."""
        if data is not None:
            if self.foreign_copies is None:
                self.foreign_copies = ForeignCopies(self.session, self.K.root, "controller/currents",
                                                    auth=self.auth)
            self.foreign_copies(data)
        if isinstance(e, pr.ForeignError):
            return pr.ForeignError(f"not from the paired controller ({e.detail}; another process "
                                   f"publishes on {self.K.currents})")
        if e.reason == "auth":
            return type(e)(f"{e.detail}: not sealed with this run's key (a forger, or a "
                           f"controller with another key file)")
        return e

    def _stranger(self, pid: bytes):
        """A controller announced itself and failed the pairing proof (no or another key)."""
        self.strangers.append(pid)
        text = (f"stranger {pid.hex()} announced as controller but failed the pairing proof (no "
                f"key, or another key file); ignored")
        self.ev.emit(pr.EventKind.WARNING, text, force=True)
        if self.peer_id is None:            # on stderr too: the operator sees why nothing starts
            self.presence.progress(f"{text}; waiting for a controller with the run's key")

    def _extra_controller(self, pid: bytes):
        """A second controller announced itself after pairing (on a zenoh thread)."""
        self.counts["foreign_peers"] += 1
        self.ev.emit(pr.EventKind.WARNING, f"a second controller {pid.hex()} announced itself "
                     f"for this run; its messages are rejected (paired with "
                     f"{self.peer_id.hex()})", force=True)

    def reject(self, e: pr.ProtocolError, k):
        self.rejected[e.reason] += 1
        self.ev.emit(pr.EventKind.REJECTED, f"currents rejected at step {k}: {e}", k)

    def check_output(self, y, k):
        """After an advance: a new output object -> new view; a non-OK plant status -> fault
        or (once) a warning.  Returns the view of ``y``."""
        self.y = y
        if y is not self.y_obj:
            try:
                self.y_mv, self.y_obj = output_view(self.sc, y)
            except (ValueError, TypeError) as e:
                raise Fault(f"plant output invalid at step {k}: {e}")
        plant = self.plant
        if self.has_status and plant.status:
            rep = getattr(plant, "fault", None) or f"status {plant.status}"
            if plant.status in self.fatal:
                raise Fault(f"{rep} (step {k + 1})")
            if not self.newton_warned:
                self.newton_warned = True
                self.ev.emit(pr.EventKind.WARNING, f"plant: {rep} (step {k + 1})", k + 1,
                             int(round(float(plant.sim_time) * 1e9)), force=True)
        return self.y_mv

    def advance_checked(self, u, k):
        """``plant.advance`` with its failures turned into faults; returns ``(y, view)``."""
        try:
            y = self.advance(u)
        except Exception as e:
            raise Fault(f"plant.advance raised at step {k}: {type(e).__name__}: {e}")
        return y, self.check_output(y, k)

    def advance_arriving_checked(self, old, u, m, k):
        """``plant.advance_arriving`` with its failures turned into faults; returns ``(y, view)``."""
        try:
            y = self.plant.advance_arriving(old, u, m)
            if self.contact is not None:
                self.contact.after_period()
        except Exception as e:
            raise Fault(f"plant.advance_arriving raised at step {k}: {type(e).__name__}: {e}")
        return y, self.check_output(y, k)

    def encode_fault(self, k, sim_ns, y_mv):
        """The slow-path encode of sample k: raises the non-finite fault with details."""
        try:
            return self.sc.pack_from(k, self.plant.step_index, sim_ns, time.time_ns(), y_mv)
        except pr.NonFiniteError as e:
            raise Fault(f"plant output not finite at step {k} (t = {sim_ns * 1e-9:.6g} s): {e}")
