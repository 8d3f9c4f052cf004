"""MCAP recorder: subscribes to ``ambhil/<run-id>/**`` (or the plant's RecordBatch) and writes
every message of the run in the recorded layout of :mod:`ambhil.bridge.recording.layout` (docs/hil.md): MCAP
profile ``ros2``, topic ``/`` + key, one ``ros2msg`` schema per recorded type with a
``std_msgs/Header`` stamped in simulation time, named per-axis fields, one StepTiming message per
step; ``log_time`` = the message's simulation time, ``publish_time`` = its wall time (plant
publish / arrival, recorder arrival), ``sequence`` = low 32 bits of its seq.  The wire bytes are
not changed by this: each recorded SensorSample / CurrentCommand restores them exactly
(:func:`ambhil.bridge.recording.layout.wire_payloads`).  A payload that does not decode goes verbatim, with the
reason, to ``/ambhil/<run>/malformed/<topic>``.

Start-up (bridge/process/startup.py): ``starting/recorder`` at once; waits for plant and controller to
be present (their ``starting`` or ``alive`` token) as long as they are alive, then declares
``alive/recorder``.  It never gives up on a peer that is alive, however long its start takes.

End of run: the file's last metadata record ``ambhil.run_end`` says how the run ended, so a
failed or truncated recording is recognisable from the file alone: ``status`` (``completed``:
the run completed and every step is in the file; ``truncated``: the run completed but the file
lacks steps; ``failed``: the run faulted, a peer died or never appeared; ``stopped``: stopped on
request before the end), ``fault``, ``end_reason``, ``steps_planned`` (RunMeta ``n_steps``),
``steps_run`` (the plant's RUN_END), ``steps_recorded`` / ``currents_recorded`` (messages in the
file).

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
from typing import Callable

from ambhil.bridge.process import transport as tr
import zenoh  # noqa: E402

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import record_batch
from ambhil.bridge.recording import layout as rc
from ambhil.bridge.process.pairing import attached
from ambhil.bridge.process.events import Stop
from ambhil.bridge.process.startup import GONE, READY, STARTING, PeerError, PeerWatch, Presence
from mcap.writer import CompressionType, Writer



def record(run_id: str, out_path: str, *, connect=None, listen=None, stop=None,
           end_on_run_end: bool = True, end_on_plant_lost: bool = True,
           wait_peers: tuple[str, ...] = ("plant", "controller"), start_timeout: float = 60.0,
           end_grace_s: float = 0.2, flush_interval: float = 0.02, chunk_size: int = 64 * 1024,
           queue_size: int = 1 << 20, metadata: dict | None = None,
           handle_signals: bool = True, session=None, on_ready: Callable[[], None] | None = None,
           max_duration: float | None = None, echo: bool = False, source: str = "plant",
           owner_pid: int | None = None) -> dict:
    """Record run ``run_id`` into ``out_path`` until stopped.

    Stops (and finishes the file cleanly) on: ``stop()`` / ``stop.is_set()``, SIGTERM or
    SIGINT (if ``handle_signals`` and called from the main thread), a RUN_END event
    (``end_on_run_end``), the plant's liveliness token going away (``end_on_plant_lost``),
    or ``max_duration`` s.  Declares the ``alive/recorder`` token once the peers listed
    in ``wait_peers`` are seen directly (so their data reaches us from the first step); waits
    for them as long as they are alive (``start_timeout`` counts only their absence).
    ``echo``: print start-up progress on stderr.  ``source``: where SensorSample and
    CurrentCommand come from: ``"plant"`` (default), the plant's RecordBatch messages
    (bridge/protocol/record_batch.py: the recorder stays off the loop's path; it subscribes to
    ``ambhil/<run>/*`` only: events, meta, timing, record); ``"wire"``, subscribed to
    ``ambhil/<run>/**`` directly (a plant that sends no RecordBatch, e.g. one of your own; every
    put of the loop then also goes to the recorder).  Returns ``{"messages", "per_topic",
    "end_reason", "status", "fault", "steps_planned", "steps_run", "steps_recorded", "path",
    ...}``.

    ``owner_pid``: the `ambhil run` that started this recorder; a SIGTERM that comes because
    it died (the parent-death signal: our parent is no longer that pid) ends the recording with
    ``end_reason`` "ambhil run (pid N) died" after the usual grace for the plant's RUN_END, and
    ``status`` stopped.  A write that fails (a full disk) ends the recording: ``write_error``
    names the file and the error, the summary's ``status`` is failed, and what the file holds up
    to its last complete chunk is readable by :func:`ambhil.bridge.recording.recover.recover`."""
    K = pr.keys(run_id)
    stop_fn = stop.is_set if hasattr(stop, "is_set") else stop
    flags = {"end": None}
    own = session is None
    if own:
        session = tr.open_session(listen, connect)
    presence = Presence(session, run_id, "recorder", echo=echo)
    if source not in ("plant", "wire"):
        raise ValueError(f"source must be 'plant' or 'wire', got {source!r}")
    batched = source == "plant"
    sub = tr.declare_subscriber(session, f"{K.root}/*" if batched else K.all, queue_size)
    # wake-ups are empty session-local payloads on a key the subscriber matches
    waker = tr.Waker(session, K.events if batched else K.wake)
    run = {"plant_end": None, "fault": None, "n_steps": None, "plant_ready": False}

    def wake(reason=None):
        if reason and flags["end"] is None:
            flags["end"] = reason
        waker.wake()

    def _live(role, state):
        # the plant's process is gone (both tokens), or it was ready and its ready token went
        if role == "plant" and end_on_plant_lost and (state == GONE or (
                state == STARTING and run.get("plant_ready"))):
            wake("plant liveliness lost")
        if role == "plant" and state == READY:
            run["plant_ready"] = True
    watch = PeerWatch(session, run_id, _live, me="recorder")
    # announced peer ids (bridge/process/pairing.py): a sensor sample or current command that does not
    # end with its role's announced id (protocol version 2) is recorded on
    # ambhil/<run>/foreign/<topic>, not mixed into the run's own stream (a hijack attempt stays
    # visible, the run's data stays the run's)
    announced: dict[str, set] = {"plant": set(), "controller": set()}

    def _peer(sample):
        parts = str(sample.key_expr).rsplit("/", 2)
        if len(parts) == 3 and parts[1] in announced:
            try:
                pid = bytes.fromhex(parts[2])
            except ValueError:
                return
            if sample.kind == zenoh.SampleKind.PUT:
                announced[parts[1]].add(pid)
    peer_sub = session.liveliness().declare_subscriber(f"{K.root}/peer/*/*", _peer, history=True)
    checked = {K.sensors: ("plant", f"{K.root}/foreign/plant/sensors"),
               K.currents: ("controller", f"{K.root}/foreign/controller/currents")}
    # the plant and controller put again what they reject as foreign (bridge/process/events.py,
    # ForeignCopies) on those keys; with the plant's batches, that is how they reach the file (in
    # "wire" mode the recorder sees the originals and sorts them itself: the copies are skipped)
    foreign_root = f"{K.root}/foreign/"
    fsub = tr.declare_subscriber(session, f"{K.root}/foreign/**", 4096) if batched else None

    def _drain_foreign() -> bool:
        got = False
        while fsub is not None and (s := fsub.try_recv()) is not None:
            data = s.payload.to_bytes()
            if data:
                got = _store(str(s.key_expr), data, time.time_ns()) or got
        return got

    old_handlers = {}
    if handle_signals and threading.current_thread() is threading.main_thread():
        def _sig(signum, frame):
            if owner_pid:   # maybe the parent-death signal: decided after the grace (_owner_gone)
                flags["end"] = flags["end"] or f"parent signal {signal.Signals(signum).name}"
            else:
                flags["end"] = flags["end"] or f"signal {signal.Signals(signum).name}"
        for s in (signal.SIGTERM, signal.SIGINT):
            old_handlers[s] = signal.signal(s, _sig)

    f = open(out_path, "wb")           # flushed to the kernel every flush_interval
    w = Writer(f, compression=CompressionType.ZSTD, chunk_size=chunk_size)
    w.start(profile=rc.PROFILE, library=rc.LIBRARY)
    rw = rc.Writer(w, run_id)
    w.add_metadata("ambhil.recorder", {
        "run_id": run_id, "started_wall_ns": str(time.time_ns()), "key_prefix": K.root,
        "protocol_version": str(pr.PROTOCOL_VERSION),
        "layout": "ros2: header stamp and log_time in simulation time (bridge/recording/layout.py, docs/hil.md)", **{k: str(v) for k, v in (metadata or {}).items()}})
    per_topic: dict[str, int] = {}
    stop_flag = threading.Event()

    # periodic wake so the main loop flushes, checks stop conditions and runs signal handlers
    def _ticker():
        while not stop_flag.wait(flush_interval):
            wake()
    tick = threading.Thread(target=_ticker, daemon=True, name="ambhil-recorder-tick")
    tick.start()

    def _store(key, data, t_log) -> bool:
        """One wire message into the recording (bridge/recording/layout.py); False for the wake key."""
        if key == K.wake:
            return False
        rw.put(key, data, t_log, pr.message_type_for_key(key) or _foreign_type(key))
        per_topic[key] = per_topic.get(key, 0) + 1
        return True

    topic_keys = {t: f"{K.root}/{suffix}" for t, suffix in record_batch.TOPIC_SUFFIX.items()}

    def _store_batch(data) -> None:
        """The plant's RecordBatch: each SensorSample / CurrentCommand into its own channel, in
        the plant's order (publish_time = the plant's publish / receive wall time), transcoded
        a batch at a time."""
        try:
            _, parts = record_batch.runs(data)
        except pr.ProtocolError as e:
            bad["record_batches"] += 1
            presence.progress(f"malformed RecordBatch skipped: {e}")
            return
        for topic, log, where, count, size in parts:
            key = topic_keys[topic]
            wtype = "SensorSample" if topic == record_batch.SENSORS else "CurrentCommand"
            if size is not None:             # back to back, one size: no bytes object per payload
                rw.put_block(key, wtype, data, where, count, size, log)
            else:
                rw.put_many(key, wtype, where, log.tolist())
            per_topic[key] = per_topic.get(key, 0) + count
    bad = {"record_batches": 0, "foreign_batches": 0}

    end_reason = write_error = None
    t_end_deadline = None
    t_start = time.monotonic()
    try:
        def _stopping():
            return flags["end"] is not None or (stop_fn is not None and stop_fn())
        if wait_peers:
            presence.progress(f"waiting for {', '.join(wait_peers)}")
        first = [p for p in wait_peers if p == "plant"]
        watch.wait(first, start_timeout, until=STARTING, stop=_stopping, report=presence.progress)
        try:
            watch.wait([p for p in wait_peers if p not in first], start_timeout, until=STARTING,
                       stop=_stopping, report=presence.progress)
        except PeerError as e:
            if not first:
                raise
            # the plant is there: it will fault on this too; record its end (RUN_END)
            presence.progress(f"{e}; recording the plant's end")
        presence.ready()
        presence.progress("recording")
        if on_ready is not None:
            on_ready()
        recv = sub.recv
        now_ns = time.time_ns
        last_flush = time.monotonic()
        dirty = False
        while True:
            s = recv()
            t_log = now_ns()
            data = s.payload.to_bytes()
            if data:
                key = str(s.key_expr)
                if key == K.record:
                    if batched:
                        if announced["plant"] and attached(s) not in announced["plant"]:
                            bad["foreign_batches"] += 1      # only the run's plant feeds the file
                            continue
                        _store_batch(data)
                        dirty = True
                    continue
                if not batched and key.startswith(foreign_root):
                    continue                  # a copy of a message recorded as it arrived
                chk = checked.get(key)
                if chk is not None:
                    ids = announced[chk[0]]
                    if ids and data[-pr.PEER_LEN:] not in ids:
                        key = chk[1]
                if not _store(key, data, t_log):
                    continue
                dirty = True
                if key == K.meta:
                    try:
                        m = pr.decode_meta(data)
                        w.add_metadata("ambhil.run_meta", {"json": json.dumps(m.info)})
                        run["n_steps"] = m.info.get("n_steps")
                    except pr.ProtocolError:
                        pass
                elif (key == K.events and len(data) > 8 and data[pr.EVENT_KIND_OFFSET + 1] == 0
                      and data[pr.EVENT_KIND_OFFSET] in (pr.EventKind.RUN_END, pr.EventKind.FAULT)):
                    _run_event(run, data)
                    if end_on_run_end and data[pr.EVENT_KIND_OFFSET] == pr.EventKind.RUN_END:
                        flags["end"] = flags["end"] or "RUN_END event"
                continue
            # wake-up: the foreign copies, flush, check end conditions
            dirty = _drain_foreign() or dirty
            t = time.monotonic()
            if dirty and t - last_flush >= flush_interval * 0.9:
                w.flush()
                dirty = False
                last_flush = t
            if flags["end"] is None and stop_fn is not None and stop_fn():
                flags["end"] = "stop requested"
            if flags["end"] is None and max_duration is not None and t - t_start > max_duration:
                flags["end"] = "max duration"
            if flags["end"] is not None:
                if flags["end"].startswith(("signal", "stop")):
                    end_reason = flags["end"]
                    break
                if t_end_deadline is None:        # late messages from other peers
                    t_end_deadline = t + end_grace_s
                elif t >= t_end_deadline:
                    end_reason = flags["end"]
                    break
    except Stop:
        end_reason = flags["end"] or "stop requested"
    except tr.TransportError as e:
        end_reason = f"error: {e}"
        presence.progress(f"giving up: {e}")
    except OSError as e:                  # the file cannot be written (a full disk, an I/O error)
        write_error = f"cannot write {os.path.abspath(out_path)}: {e.strerror or e}"
        end_reason = f"error: {write_error}"
        presence.progress(f"giving up: {write_error}")
    finally:
        stop_flag.set()
        # drain what is already queued (non-blocking), then finish the file
        try:
            while (s := sub.try_recv()) is not None:
                data = s.payload.to_bytes()
                key = str(s.key_expr)
                if not data:
                    continue
                if key == K.record:
                    if batched:
                        _store_batch(data)
                elif _store(key, data, time.time_ns()) and key == K.events and len(data) > 8:
                    _run_event(run, data)
            _drain_foreign()
        except Exception:
            pass
        if owner_pid and str(end_reason).startswith("parent signal"):
            end_reason = (f"ambhil run (pid {owner_pid}) died" if _owner_gone(owner_pid)
                          else str(end_reason).removeprefix("parent "))
        end = run_end_status(run, str(end_reason), rw.per_key.get(K.sensors, 0),
                             rw.per_key.get(K.currents, 0))
        try:
            w.add_metadata("ambhil.recorder_end", {"end_reason": str(end_reason),
                                                   "messages": str(rw.n),
                                                   "ended_wall_ns": str(time.time_ns())})
            w.add_metadata("ambhil.run_end", {k: "" if v is None else str(v) for k, v in end.items()})
            w.finish()
            f.close()
        except OSError as e:              # the end of the file cannot be written either
            write_error = write_error or f"cannot write {os.path.abspath(out_path)}: {e.strerror or e}"
            try:
                f.close()
            except OSError:
                pass
        if write_error:
            end = dict(end, status="failed", fault=end["fault"] or f"recorder: {write_error}")
        for sgn, h in old_handlers.items():
            signal.signal(sgn, h)
        tr.close_quietly(peer_sub, watch, sub, fsub)
        presence.close()
        if own:
            tr.close_quietly(session)
    return {"path": os.path.abspath(out_path), "messages": rw.n, "per_topic": per_topic,
            "source": source, **bad, **end, "write_error": write_error,
            "wall_s": round(time.monotonic() - t_start, 3)}


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


def _run_event(run: dict, data: bytes) -> None:
    """Keep the plant's RUN_END (reason, steps, fault) and the first FAULT text of the run."""
    try:
        e = pr.decode_event(data)
    except pr.ProtocolError:
        return
    if e.kind == pr.EventKind.FAULT and run["fault"] is None:
        run["fault"] = f"{e.source}: {e.text}"
    elif e.kind == pr.EventKind.RUN_END and e.source == "plant":
        try:
            info = json.loads(e.text)
        except ValueError:
            info = {}
        run["plant_end"] = info if isinstance(info, dict) else {}


def run_end_status(run: dict, end_reason: str, sensors: int, currents: int) -> dict:
    """The ``ambhil.run_end`` record: how the run ended and how much of it the file holds."""
    pe = run.get("plant_end")
    steps_run = pe.get("steps") if pe else None
    fault = (pe.get("fault") if pe else None) or run.get("fault")
    recorded = min(sensors, currents)
    if pe is not None:
        reason = pe.get("reason")
        if reason == "completed":
            status = "completed" if isinstance(steps_run, int) and recorded >= steps_run else "truncated"
        elif reason in ("stopped", "interrupted"):
            status = "stopped"
        else:
            status = "failed"
    elif end_reason.startswith(("signal", "stop", "max duration", "ambhil run")):
        status = "stopped"          # the recording stopped before the run ended
    else:                           # plant lost without RUN_END, peers never came, ...
        status = "failed"
        fault = fault or (end_reason[len("error: "):] if end_reason.startswith("error: ")
                          else f"recorder: {end_reason} before the run ended")
    return {"status": status, "fault": fault, "end_reason": end_reason,
            "steps_planned": run.get("n_steps"), "steps_run": steps_run,
            "steps_recorded": sensors, "currents_recorded": currents}
