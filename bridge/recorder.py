"""MCAP recorder: subscribes to ``ambhil/<run-id>/**`` and stores the wire bytes verbatim.

One channel per concrete key expression (topic = key), ros2msg schema per message type,
message_encoding ``cdr``; ``log_time`` = receive wall time (ns), ``publish_time`` = the
message's ``sim_time_ns`` (offset 28 of every ambhil message), ``sequence`` = low 32 bits
of its seq.  Unknown keys under the run are kept with ``message_encoding="application/
octet-stream"`` and no schema.

Crash safety: zstd chunks of at most ``chunk_size`` (64 KiB) bytes and a forced chunk flush
every ``flush_interval`` (20 ms), written through to the kernel, so a SIGKILLed recorder loses at
most ~``flush_interval`` + queueing; :func:`bridge.recover.recover` restores the rest.
"""
from __future__ import annotations

import json
import os
import signal
import struct
import threading
import time
from typing import Callable

from . import transport as tr          # sets ZENOH_RUNTIME before zenoh is imported
from . import protocol as pr
from mcap.writer import CompressionType, Writer

_I64 = struct.Struct("<q")
_U64 = struct.Struct("<Q")


def record(run_id: str, out_path: str, *, connect=None, listen=None, stop=None,
           end_on_run_end: bool = True, end_on_plant_lost: bool = True,
           wait_peers: tuple[str, ...] = ("plant", "controller"), start_timeout: float = 60.0,
           end_grace_s: float = 0.2, flush_interval: float = 0.02, chunk_size: int = 64 * 1024,
           queue_size: int = 1 << 20, metadata: dict | None = None,
           handle_signals: bool = True, session=None, on_ready: Callable[[], None] | None = None,
           max_duration: float | None = None) -> dict:
    """Record run ``run_id`` into ``out_path`` until stopped.

    Stops (and finishes the file cleanly) on: ``stop()`` / ``stop.is_set()``, SIGTERM or
    SIGINT (if ``handle_signals`` and called from the main thread), a RUN_END event
    (``end_on_run_end``), the plant's liveliness token going away (``end_on_plant_lost``),
    or ``max_duration`` s.  Declares the ``alive/recorder`` token once the peers listed
    in ``wait_peers`` are seen directly (so their data reaches us from the first step).
    Returns ``{"messages", "per_topic", "end_reason", "path", ...}``."""
    K = pr.keys(run_id)
    stop_fn = stop.is_set if hasattr(stop, "is_set") else stop
    flags = {"end": None}
    own = session is None
    if own:
        session = tr.open_session(listen, connect)
    sub = tr.declare_subscriber(session, K.all, queue_size)
    waker = tr.Waker(session, K.wake)

    def wake(reason=None):
        if reason and flags["end"] is None:
            flags["end"] = reason
        waker.wake()

    def _live(key, alive):
        if key == K.alive_plant and not alive and end_on_plant_lost:
            wake("plant liveliness lost")
    watch = tr.LivelinessWatch(session, K.alive_all, _live)

    old_handlers = {}
    if handle_signals and threading.current_thread() is threading.main_thread():
        def _sig(signum, frame):
            flags["end"] = flags["end"] or f"signal {signal.Signals(signum).name}"
        for s in (signal.SIGTERM, signal.SIGINT):
            old_handlers[s] = signal.signal(s, _sig)

    f = open(out_path, "wb")           # flushed to the kernel every flush_interval
    w = Writer(f, compression=CompressionType.ZSTD, chunk_size=chunk_size)
    w.start(profile="", library="ambhil-recorder")
    schema_ids = {t: w.register_schema(pr.schema_name(t), "ros2msg", d.encode())
                  for t, d in pr.MSG_DEFS.items()}
    w.add_metadata("ambhil.recorder", {
        "run_id": run_id, "started_wall_ns": str(time.time_ns()), "key_prefix": K.root,
        "protocol_version": str(pr.PROTOCOL_VERSION), **{k: str(v) for k, v in (metadata or {}).items()}})
    channels: dict[str, int] = {}
    per_topic: dict[str, int] = {}
    n_msgs = 0
    token = None
    stop_flag = threading.Event()

    # periodic wake so the main loop flushes, checks stop conditions and runs signal handlers
    def _ticker():
        while not stop_flag.wait(flush_interval):
            wake()
    tick = threading.Thread(target=_ticker, daemon=True, name="ambhil-recorder-tick")
    tick.start()

    end_reason = None
    t_end_deadline = None
    t_start = time.monotonic()
    try:
        peers = [getattr(K, f"alive_{p}") for p in wait_peers]
        t0 = time.monotonic()
        while not set(peers) <= watch.alive:
            if stop_fn is not None and stop_fn() or flags["end"]:
                break
            if time.monotonic() - t0 > start_timeout:
                missing = ", ".join(sorted(set(peers) - watch.alive))
                raise tr.TransportError(f"recorder: peer(s) not seen within {start_timeout:g} s: "
                                        f"{missing}")
            time.sleep(0.005)
        token = tr.declare_token(session, K.alive_recorder)
        if on_ready is not None:
            on_ready()
        recv = sub.recv
        now_ns = time.time_ns
        add = w.add_message
        last_flush = time.monotonic()
        dirty = False
        wake_key = K.wake
        while True:
            s = recv()
            t_log = now_ns()
            data = s.payload.to_bytes()
            if data:
                key = str(s.key_expr)
                cid = channels.get(key)
                if cid is None:
                    if key == wake_key:
                        continue
                    mt = pr.message_type_for_key(key)
                    if mt is None:
                        cid = w.register_channel(key, "application/octet-stream", 0, {})
                    else:
                        cid = w.register_channel(key, "cdr", schema_ids[mt], {"type": mt})
                    channels[key] = cid
                    per_topic[key] = 0
                if len(data) >= 36:
                    pub_t = _I64.unpack_from(data, pr.SIM_TIME_OFFSET)[0]
                    seq = _U64.unpack_from(data, pr.SEQ_OFFSET)[0] & 0xFFFFFFFF
                else:
                    pub_t, seq = 0, 0
                add(cid, t_log, data, pub_t if pub_t >= 0 else 0, seq)
                per_topic[key] += 1
                n_msgs += 1
                dirty = True
                if key == K.meta:
                    try:
                        m = pr.decode_meta(data)
                        w.add_metadata("ambhil.run_meta", {"json": json.dumps(m.info)})
                    except pr.ProtocolError:
                        pass
                elif (end_on_run_end and key == K.events and len(data) > 8
                      and data[pr.EVENT_KIND_OFFSET] == pr.EventKind.RUN_END
                      and data[pr.EVENT_KIND_OFFSET + 1] == 0):
                    flags["end"] = flags["end"] or "RUN_END event"
                continue
            # wake-up: flush, check end conditions
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
    except tr.TransportError as e:
        end_reason = f"error: {e}"
    finally:
        stop_flag.set()
        # drain what is already queued (non-blocking), then finish the file
        try:
            while (s := sub.try_recv()) is not None:
                data = s.payload.to_bytes()
                key = str(s.key_expr)
                if data and key in channels:
                    pub_t = _I64.unpack_from(data, pr.SIM_TIME_OFFSET)[0] if len(data) >= 36 else 0
                    w.add_message(channels[key], time.time_ns(), data, max(pub_t, 0), 0)
                    per_topic[key] += 1
                    n_msgs += 1
        except Exception:
            pass
        w.add_metadata("ambhil.recorder_end", {"end_reason": str(end_reason),
                                               "messages": str(n_msgs),
                                               "ended_wall_ns": str(time.time_ns())})
        w.finish()
        f.close()
        for sgn, h in old_handlers.items():
            signal.signal(sgn, h)
        tr.close_quietly(token, watch, sub)
        if own:
            tr.close_quietly(session)
    return {"path": os.path.abspath(out_path), "messages": n_msgs, "per_topic": per_topic,
            "end_reason": end_reason, "wall_s": round(time.monotonic() - t_start, 3)}
