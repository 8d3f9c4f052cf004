"""MCAP recorder: subscribes to ``ambhil/<run-id>/**`` (or the plant's RecordBatch) and writes
every message of the run in the recorded layout of :mod:`ambhil.bridge.recording.layout` (docs/hil.md): MCAP
profile ``ros2``, topic ``/`` + key, one ``ros2msg`` schema per recorded type with a
``std_msgs/Header`` stamped in simulation time, named per-axis fields, one StepTiming message per
step; ``log_time`` = the message's simulation time, ``publish_time`` = its wall time (plant
publish / arrival, recorder arrival), ``sequence`` = low 32 bits of its seq.  The wire bytes are
not changed by this: each recorded SensorSample / CurrentCommand restores them exactly
(:func:`ambhil.bridge.recording.layout.wire_payloads`; a recording keeps no MACs).  A payload that does not
decode goes verbatim, with the reason, to ``/ambhil/<run>/malformed/<topic>``.

Authentication (protocol 3, :mod:`ambhil.bridge.recording.gate`): the recorder takes only what
authenticates under the run's secret (``secret``, from the key file) from the run's own plant and
controller: it proves the announced plants by challenge, learns the session key from the proven
plant's RunMeta, and judges every message under it.  Events that fail go to
``/ambhil/foreign/events``, other messages are counted only; ``rejected`` ({reason: n}) and
``auth`` (the run's mode) are in the summary and in ``ambhil.run_end``.  Only the plant's
authenticated RUN_END ends a recording (or the plant's tokens going away, or a stop): a forged
one is recorded apart and changes nothing.  The recorder puts nothing on the wire but its tokens.

Start-up (bridge/process/startup.py): ``starting/recorder`` at once; waits for plant and controller to
be present (their ``starting`` or ``alive`` token) as long as they are alive, then declares
``alive/recorder``.  It never gives up on a peer that is alive, however long its start takes.

End of run: the file's last metadata record ``ambhil.run_end`` says how the run ended, so a
failed or truncated recording is recognisable from the file alone: ``status`` (``completed``:
the run completed and every step is in the file; ``truncated``: the run completed but the file
lacks steps; ``failed``: the run faulted, a peer died or never appeared; ``stopped``: stopped on
request before the end), ``fault``, ``end_reason``, ``steps_planned`` (RunMeta ``n_steps``),
``steps_run`` (the plant's RUN_END), ``steps_recorded`` / ``currents_recorded`` (messages in the
file); :mod:`ambhil.bridge.recording.run_end` makes and reads it.

Crash safety: zstd chunks of at most ``chunk_size`` (64 KiB) bytes and a forced chunk flush
every ``flush_interval`` (20 ms), written through to the kernel, so a SIGKILLed recorder loses at
most ~``flush_interval`` + queueing; :func:`ambhil.bridge.recording.recover.recover` restores the rest.
"""
from __future__ import annotations

import json
import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import Callable, Mapping

from ambhil.bridge.process import transport as tr

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import record_batch
from ambhil.bridge.recording.gate import FOREIGN, SESSION, Gate
from ambhil.bridge.recording.layout import LIBRARY, PROFILE
from ambhil.bridge.recording.run_end import note_event, run_end_status
from ambhil.bridge.recording.writer import Writer as RecordedWriter
from ambhil.bridge.process.pairing import attached
from ambhil.bridge.process.events import Stop
from ambhil.bridge.process.startup import GONE, READY, STARTING, PeerError, PeerWatch, Presence
from mcap.writer import CompressionType, Writer


@dataclass(frozen=True)
class RecorderConfig:
    """How :func:`record` records a run.

    ``connect`` / ``listen``: the zenoh endpoints of the recorder's own session (when
    :func:`record` is not given one).  Stops (and finishes the file cleanly) on the plant's
    authenticated RUN_END event (``end_on_run_end``), the plant's liveliness token going away (``end_on_plant_lost``), or
    ``max_duration`` s; and on SIGTERM or SIGINT if ``handle_signals`` (and called from the main
    thread).  Declares the ``alive/recorder`` token once the peers listed in ``wait_peers`` are
    seen directly (so their data reaches us from the first step); waits for them as long as they
    are alive (``start_timeout`` counts only their absence).  After the end, ``end_grace_s`` for
    late messages from other peers.  ``flush_interval``, ``chunk_size``: crash safety (the module
    docstring); ``queue_size``: the subscriber's queue.  ``metadata``: more fields of the
    ``ambhil.recorder`` metadata record.  ``echo``: print start-up progress on stderr.

    ``source``: where SensorSample and CurrentCommand come from: ``"plant"`` (default), the
    plant's RecordBatch messages (bridge/protocol/record_batch.py: the recorder stays off the
    loop's path; it subscribes to ``ambhil/<run>/*`` and ``ambhil/<run>/events/*`` only: events,
    meta, timing, record);
    ``"wire"``, subscribed to ``ambhil/<run>/**`` directly (a plant that sends no RecordBatch,
    e.g. one of your own; every put of the loop then also goes to the recorder).

    ``owner_pid``: the `ambhil run` that started this recorder; a SIGTERM that comes because
    it died (the parent-death signal: our parent is no longer that pid) ends the recording with
    ``end_reason`` "ambhil run (pid N) died" after the usual grace for the plant's RUN_END, and
    ``status`` stopped.

    ``secret``: the run's 32-byte secret (``--key-file``), None for an unauthenticated run
    (``insecure``: one that was asked for off loopback); what is not authenticated under it is
    not the run's (the module docstring)."""

    connect: str | list[str] | None = None
    listen: str | list[str] | None = None
    end_on_run_end: bool = True
    end_on_plant_lost: bool = True
    wait_peers: tuple[str, ...] = ("plant", "controller")
    start_timeout: float = 60.0
    end_grace_s: float = 0.2
    flush_interval: float = 0.02
    chunk_size: int = 64 * 1024
    queue_size: int = 1 << 20
    metadata: Mapping[str, object] | None = None
    handle_signals: bool = True
    max_duration: float | None = None
    echo: bool = False
    source: str = "plant"
    owner_pid: int | None = None
    secret: bytes | None = None
    insecure: bool = False

    def __post_init__(self):
        if self.source not in ("plant", "wire"):
            raise ValueError(f"source must be 'plant' or 'wire', got {self.source!r}")


def record(run_id: str, out_path: str, config: RecorderConfig = RecorderConfig(), *,
           stop=None, session=None, on_ready: Callable[[], None] | None = None) -> dict:
    """Record run ``run_id`` into ``out_path`` until stopped, as ``config`` says
    (:class:`RecorderConfig`); also stops on ``stop()`` / ``stop.is_set()``.  ``session``: a zenoh
    session to use (else one of its own, closed at the end); ``on_ready()``: called once the
    recorder is ready (its ``alive/recorder`` token declared).  Returns ``{"path", "messages",
    "per_topic", "source", ..., "end_reason", "status", "fault", "steps_planned", "steps_run",
    "steps_recorded", "rejected" ({reason: n}), "auth" (the run's mode), "write_error", "wall_s"}``.

    A write that fails (a full disk) ends the recording: ``write_error`` names the file and the
    error, the summary's ``status`` is failed, and what the file holds up to its last complete
    chunk is readable by :func:`ambhil.bridge.recording.recover.recover`."""
    return _Recording(run_id, out_path, config, stop, session).run(on_ready)


class _Recording:
    """One run being recorded: its subscriptions, its file, and what is known of the run (the
    plant's RUN_END, the first FAULT, the planned steps).  :meth:`run` is the recorder's life:
    wait for the peers, receive until the run ends, finish the file."""

    def __init__(self, run_id: str, out_path: str, cfg: RecorderConfig, stop, session):
        self.cfg, self.out_path = cfg, out_path
        self.K = K = pr.keys(run_id)
        self.stop_fn = stop.is_set if hasattr(stop, "is_set") else stop
        self.end: str | None = None           # why the recording is to end (None: not yet)
        self.own = session is None
        self.session = session = tr.open_session(cfg.listen, cfg.connect) if self.own else session
        self.presence = Presence(session, run_id, "recorder", echo=cfg.echo, secret=cfg.secret,
                                 insecure=cfg.insecure)
        self.batched = batched = cfg.source == "plant"
        self.gate = Gate(session, self.presence.auth, wire=not batched)
        self.sub = tr.declare_subscriber(session, f"{K.root}/*" if batched else K.all, cfg.queue_size)
        # the roles' events (ambhil/<run>/events/<role>: two chunks) drained at each wake-up
        self.esub = tr.declare_subscriber(session, K.events, 4096) if batched else None
        # wake-ups are empty session-local payloads on a key the subscriber matches
        self.waker = tr.Waker(session, f"{K.root}/recorder-wake" if batched else K.wake)
        self.run_state = {"plant_end": None, "fault": None, "n_steps": None, "plant_ready": False}
        self.plant_gone = False               # the plant's tokens went (it ended or died)
        self.controller_gone = False          # the controller's tokens went
        self.t_run_end = None                 # when the plant's RUN_END came (monotonic)
        self.signals = 0                      # SIGTERM / SIGINT received
        self.watch = PeerWatch(session, run_id, self._live, me="recorder")
        # the plant and controller put again what they reject as foreign (bridge/process/events.py,
        # ForeignCopies) on those keys; with the plant's batches, that is how they reach the file (in
        # "wire" mode the recorder sees the originals and sorts them itself: the copies are skipped)
        self.foreign_root = f"{K.root}/foreign/"
        self.fsub = tr.declare_subscriber(session, f"{K.root}/foreign/**", 4096) if batched else None
        self.old_handlers = self._install_signal_handlers()
        self.f, self.w, self.rw = self._open_file(run_id)
        self.per_topic: dict[str, int] = {}
        self.topic_keys = {t: f"{K.root}/{suffix}" for t, suffix in record_batch.TOPIC_SUFFIX.items()}
        self.bad = {"record_batches": 0}      # malformed (the plant's own, authenticated)
        # periodic wake so the main loop flushes, checks stop conditions and runs signal handlers
        self.stop_flag = threading.Event()
        self.tick = threading.Thread(target=self._ticker, daemon=True, name="ambhil-recorder-tick")
        self.tick.start()

    # ------------------------------------------------------------------ set-up
    def _install_signal_handlers(self) -> dict:
        old = {}
        if self.cfg.handle_signals and threading.current_thread() is threading.main_thread():
            for s in (signal.SIGTERM, signal.SIGINT):
                old[s] = signal.signal(s, self._sig)
        return old

    def _open_file(self, run_id: str):
        """The file (flushed to the kernel every flush_interval), its MCAP writer and the recorded
        layout's writer on it, the ``ambhil.recorder`` metadata written."""
        f = open(self.out_path, "wb")
        w = Writer(f, compression=CompressionType.ZSTD, chunk_size=self.cfg.chunk_size)
        w.start(profile=PROFILE, library=LIBRARY)
        rw = RecordedWriter(w, run_id)
        w.add_metadata("ambhil.recorder", {
            "run_id": run_id, "started_wall_ns": str(time.time_ns()), "key_prefix": self.K.root,
            "protocol_version": str(pr.PROTOCOL_VERSION),
            "layout": "ros2: header stamp and log_time in simulation time (bridge/recording/layout.py, docs/hil.md)", **{k: str(v) for k, v in (self.cfg.metadata or {}).items()}})
        return f, w, rw

    # ------------------------------------------------------------------ callbacks (other threads)
    def wake(self, reason=None) -> None:
        if reason and self.end is None:
            self.end = reason
        self.waker.wake()

    def _ticker(self) -> None:
        while not self.stop_flag.wait(self.cfg.flush_interval):
            self.wake()

    def _live(self, role, state) -> None:
        # the plant's process is gone (both tokens), or it was ready and its ready token went
        if role == "plant" and (state == GONE or (state == STARTING and self.run_state.get("plant_ready"))):
            self.plant_gone = True
            if self.cfg.end_on_plant_lost:
                self.wake("plant liveliness lost")
            else:
                self.wake()
        if role == "plant" and state == READY:
            self.run_state["plant_ready"] = True
        if role == "controller" and state == GONE:
            self.controller_gone = True
            self.wake()

    def _sig(self, signum, frame) -> None:
        self.signals += 1
        if self.cfg.owner_pid:   # maybe the parent-death signal: decided after the grace (_owner_gone)
            self.end = self.end or f"parent signal {signal.Signals(signum).name}"
        else:
            self.end = self.end or f"signal {signal.Signals(signum).name}"

    # ------------------------------------------------------------------ storing
    def _store(self, key, data, t_log) -> bool:
        """One wire message into the recording (bridge/recording/writer.py); False for the wake key."""
        if key == self.K.wake:
            return False
        self.rw.put(key, data, t_log, pr.message_type_for_key(key) or _foreign_type(key))
        self.per_topic[key] = self.per_topic.get(key, 0) + 1
        return True

    def _store_batch(self, data) -> None:
        """The plant's RecordBatch: each SensorSample / CurrentCommand into its own channel, in
        the plant's order (publish_time = the plant's publish / receive wall time), transcoded
        a batch at a time."""
        try:
            _, parts = record_batch.runs(data)
        except pr.ProtocolError as e:
            self.bad["record_batches"] += 1
            self.presence.progress(f"malformed RecordBatch skipped: {e}")
            return
        for topic, log, where, count, size in parts:
            key = self.topic_keys[topic]
            wtype = "SensorSample" if topic == record_batch.SENSORS else "CurrentCommand"
            if size is not None:             # back to back, one size: no bytes object per payload
                self.rw.put_block(key, wtype, data, where, count, size, log)
            else:
                self.rw.put_many(key, wtype, where, log.tolist())
            self.per_topic[key] = self.per_topic.get(key, 0) + count

    def _drain_side(self) -> bool:
        """The events and the foreign copies received since the last wake-up into the file."""
        got = False
        for sub in (self.esub, self.fsub):
            while sub is not None and (s := sub.try_recv()) is not None:
                data = s.payload.to_bytes()
                if data:
                    got = self._take(s, str(s.key_expr), data, time.time_ns()) or got
        return got

    def _take(self, s, key: str, data: bytes, t_log: int) -> bool:
        """One received message (not a wake-up), judged (:class:`Gate`), into the file; True if
        the file got something."""
        if not self.batched and key.startswith(self.foreign_root):
            return False                  # a copy of a message recorded as it arrived
        return self._keep_all(self.gate.offer(key, data, attached(s), t_log))

    def _keep_all(self, judged) -> bool:
        got = False
        for key, data, t_log, how in judged:
            got = self._keep(key, data, t_log, how) or got
        return got

    def _keep(self, key: str, data: bytes, t_log: int, how: str) -> bool:
        """One judged message into the file: a foreign one on its foreign topic; the run's own
        where it belongs, the plant's authenticated RUN_END obeyed."""
        K = self.K
        if how == FOREIGN:
            return self._store(key, data, t_log)
        if key == K.record:
            if not self.batched:
                return False
            self._store_batch(data)
            return True
        if not self._store(key, data, t_log):
            return False
        if key == K.meta:
            try:
                m = pr.decode_meta(data)
                self.w.add_metadata("ambhil.run_meta", {"json": json.dumps(m.info)})
                self.run_state["n_steps"] = m.info.get("n_steps")
            except pr.ProtocolError:
                pass
        elif (key.startswith(f"{K.root}/events/") and len(data) > 8 and data[pr.EVENT_KIND_OFFSET + 1] == 0
              and data[pr.EVENT_KIND_OFFSET] in (pr.EventKind.RUN_END, pr.EventKind.FAULT,
                                                 pr.EventKind.INFO)):
            kind = data[pr.EVENT_KIND_OFFSET]
            # the run's end and the peers' last words only under the session key (a RUN_END
            # under the run key could be a replay from an earlier run); a FAULT line from either
            if kind == pr.EventKind.FAULT or how == SESSION:
                note_event(self.run_state, data)
            if (self.cfg.end_on_run_end and kind == pr.EventKind.RUN_END
                    and how == SESSION and key == pr.event_key(self.gate.auth.run_id, "plant")):
                self.end = self.end or "RUN_END event"
                self.t_run_end = time.monotonic()
        return True

    # ------------------------------------------------------------------ the recorder's life
    def run(self, on_ready) -> dict:
        end_reason = write_error = None
        t_start = time.monotonic()
        try:
            self._wait_for_peers()
            self.presence.ready()
            self.presence.progress("recording")
            if on_ready is not None:
                on_ready()
            end_reason = self._receive(t_start)
        except Stop:
            end_reason = self.end or "stop requested"
        except tr.TransportError as e:
            end_reason = f"error: {e}"
            self.presence.progress(f"giving up: {e}")
        except OSError as e:                  # the file cannot be written (a full disk, an I/O error)
            write_error = f"cannot write {os.path.abspath(self.out_path)}: {e.strerror or e}"
            end_reason = f"error: {write_error}"
            self.presence.progress(f"giving up: {write_error}")
        finally:
            end, write_error = self._finish(end_reason, write_error)
        return {"path": os.path.abspath(self.out_path), "messages": self.rw.n, "per_topic": self.per_topic,
                "source": self.cfg.source, **self.bad,
                "foreign_batches": self.gate.rejected_topics.get("record", 0), **end, "write_error": write_error,
                "wall_s": round(time.monotonic() - t_start, 3)}

    def _stopping(self) -> bool:
        return self.end is not None or (self.stop_fn is not None and self.stop_fn())

    def _wait_for_peers(self) -> None:
        """The plant first, then the others (as long as they are alive)."""
        cfg, report = self.cfg, self.presence.progress
        if cfg.wait_peers:
            report(f"waiting for {', '.join(cfg.wait_peers)}")
        first = [p for p in cfg.wait_peers if p == "plant"]
        self.watch.wait(first, cfg.start_timeout, until=STARTING, stop=self._stopping, report=report)
        try:
            self.watch.wait([p for p in cfg.wait_peers if p not in first], cfg.start_timeout,
                            until=STARTING, stop=self._stopping, report=report)
        except PeerError as e:
            if not first:
                raise
            # the plant is there: it will fault on this too; record its end (RUN_END)
            report(f"{e}; recording the plant's end")

    def _receive(self, t_start: float) -> str:
        """Record what arrives until the run ends; returns the end reason.  On each wake-up: the
        foreign copies, a flush (at most every flush_interval), the end conditions; an end other
        than a signal or a stop request waits ``end_grace_s`` for late messages from other peers."""
        cfg = self.cfg
        recv, now_ns = self.sub.recv, time.time_ns
        last_flush = time.monotonic()
        dirty = False
        t_end_deadline = None
        while True:
            s = recv()
            t_log = now_ns()
            data = s.payload.to_bytes()
            if data:
                dirty = self._take(s, str(s.key_expr), data, t_log) or dirty
                continue
            # wake-up: what the plant's RunMeta released, the events and foreign copies, flush,
            # check end conditions
            dirty = self._keep_all(self.gate.poll()) or dirty
            dirty = self._drain_side() or dirty
            t = time.monotonic()
            if dirty and t - last_flush >= cfg.flush_interval * 0.9:
                self.w.flush()
                dirty = False
                last_flush = t
            if self.end is None and self.stop_fn is not None and self.stop_fn():
                self.end = "stop requested"
            if self.end is None and cfg.max_duration is not None and t - t_start > cfg.max_duration:
                self.end = "max duration"
            if self.end is not None:
                if self.end.startswith(("signal", "stop")):
                    return self.end
                if self._plant_ending() or self._controller_ending(t):
                    continue
                if t_end_deadline is None:        # late messages from other peers
                    t_end_deadline = t + cfg.end_grace_s
                elif t >= t_end_deadline:
                    return self.end

    def _controller_ending(self, t: float) -> bool:
        """After the plant's RUN_END: is the controller, still alive, yet to send its last event
        (what it rejected, for run_end)?  Waited for while it lives, at most 5 s."""
        return (self.t_run_end is not None and "controller_end" not in self.run_state
                and not self.controller_gone and t - self.t_run_end < 5.0)

    def _plant_ending(self) -> bool:
        """Stopped with the run (a signal from or with our `ambhil run`, which stops or lost the
        plant too): is the plant, ready and alive, still to send its last batches and its
        RUN_END?  Then they are waited for as long as the plant lives, not for a fixed time (a
        loaded machine took longer than any grace); a second signal ends the wait."""
        return (self.end.startswith("parent signal") and self.signals < 2
                and self.run_state.get("plant_ready") and not self.plant_gone
                and self.run_state.get("plant_end") is None)

    # ------------------------------------------------------------------ the end
    def _finish(self, end_reason, write_error) -> tuple[dict, str | None]:
        """Drain what is queued, write the ``ambhil.run_end`` record and finish the file, restore
        the signal handlers, close everything: the run_end record (as the summary's) and the
        write error, if any."""
        self.stop_flag.set()
        self._drain_queued()
        owner = self.cfg.owner_pid
        if owner and str(end_reason).startswith("parent signal"):
            end_reason = (f"ambhil run (pid {owner}) died" if _owner_gone(owner)
                          else str(end_reason).removeprefix("parent "))
        K, rw = self.K, self.rw
        end = run_end_status(self.run_state, str(end_reason), rw.per_key.get(K.sensors, 0),
                             rw.per_key.get(K.currents, 0), self.gate.rejected, self.gate.mode)
        by = json.loads(end["rejected_by"])
        write_error = self._close_file(end_reason, end, write_error)
        # the summary's: dicts; ``rejected`` the recorder's own (the plant's and the controller's
        # are in their summaries), ``rejected_run`` what the run_end counts for the whole run
        end = dict(end, rejected=by.get("recorder", {}), rejected_run=json.loads(end["rejected"]),
                   rejected_by=by)
        if write_error:
            end = dict(end, status="failed", fault=end["fault"] or f"recorder: {write_error}")
        for sgn, h in self.old_handlers.items():
            signal.signal(sgn, h)
        tr.close_quietly(self.watch, self.sub, self.esub, self.fsub)
        self.presence.close()
        if self.own:
            tr.close_quietly(self.session)
        return end, write_error

    def _drain_queued(self) -> None:
        """What is already queued (non-blocking) into the file, then what the gate still holds
        (judged as well as it can be: :meth:`Gate.finish`)."""
        try:
            while (s := self.sub.try_recv()) is not None:
                data = s.payload.to_bytes()
                if data:
                    self._take(s, str(s.key_expr), data, time.time_ns())
            self._drain_side()
        except Exception:
            pass
        try:
            self._keep_all(self.gate.finish())
        except Exception:
            pass

    def _close_file(self, end_reason, end: dict, write_error: str | None) -> str | None:
        """The end metadata records and the summary written, the file closed; the write error
        (the first one) if any."""
        f, w = self.f, self.w
        try:
            w.add_metadata("ambhil.recorder_end", {"end_reason": str(end_reason),
                                                   "messages": str(self.rw.n),
                                                   "ended_wall_ns": str(time.time_ns())})
            w.add_metadata("ambhil.run_end", {k: "" if v is None else str(v) for k, v in end.items()})
            w.finish()
            f.close()
        except OSError as e:              # the end of the file cannot be written either
            write_error = write_error or f"cannot write {os.path.abspath(self.out_path)}: {e.strerror or e}"
            try:
                f.close()
            except OSError:
                pass
        return write_error


def _owner_gone(pid: int) -> bool:
    """Has the process ``pid`` (our parent, `ambhil run`) died?  The parent-death signal comes
    when the thread that started us ends, which may be before the rest of the process: so also
    a process that is exiting (zombie) counts, and one that is no longer our parent."""
    if os.getppid() != pid:
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except (OSError, IndexError):
        return False


def _foreign_type(key: str) -> str | None:
    """Message type of a ``ambhil/<run>/foreign/<topic>`` channel (see :func:`record`)."""
    parts = key.split("/")
    if len(parts) >= 4 and parts[2] == "foreign":
        return pr.TOPIC_TYPES.get("/".join(parts[3:]))
    return None
