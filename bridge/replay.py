"""Replay a recorded run: to a Rerun .rrd (with blueprint), or to a controller under test."""
from __future__ import annotations

import json
import queue
import struct
import time

import numpy as np

from . import transport as tr          # sets ZENOH_RUNTIME before zenoh is imported
from . import protocol as pr
from .pairing import Pairing, attached
from mcap.reader import make_reader


_INT64 = 2 ** 63


class _Malformed(ValueError):
    pass


def _vector(msg, n_by_type: dict, t: str):
    """Reject a sample/command whose seq or step does not fit int64 or whose axis count differs
    from the first one of its type."""
    if not (0 <= msg.seq < _INT64 and 0 <= msg.step < _INT64):
        raise _Malformed("seq or step out of range")
    v = getattr(msg, "displacement" if t == "SensorSample" else "current")
    n = n_by_type.setdefault(t, len(v))
    if len(v) != n:
        raise _Malformed(f"axis count {len(v)} != {n}")
    return msg


def _timing(tm):
    if not 0 <= tm.step < _INT64 or tm.step + len(tm.rtt_ns) >= _INT64:
        raise _Malformed("step out of range")
    if not (len(tm.rtt_ns) == len(tm.tet_ns) == len(tm.wake_lateness_ns) == len(tm.flags)):
        raise _Malformed("timing arrays of different lengths")
    return tm


def load_run(mcap_path: str, *, raw: bool = True) -> dict:
    """Decode an ambhil MCAP (the recorded layout of :mod:`bridge.recording`, or the earlier one
    of wire bytes verbatim) into numpy arrays.  Malformed messages (failing protocol
    validation, seq/step beyond int64, axis count differing from the run's, inconsistent timing
    arrays) are skipped and counted in ``rejected`` (by reason in ``rejected_reasons``).  Returns
    dict with keys sensors/currents (``seq``, ``step``, ``t_ns``, ``v`` (N x n_axes), ``raw``
    (the wire bytes, restored exactly; empty with ``raw=False``)), ``timing`` (per-step arrays),
    ``events`` (list of Event), ``meta`` (RunMeta.info or {}), ``run_id``.
    Raises :class:`bridge.recover.RecordingError` (one line, fit for the user) for a file that
    is not MCAP, is truncated (naming ``ambhil recover``) or cannot be read."""
    from collections import Counter
    from . import recording as rc
    from .recover import RecordingError, check, truncated_message
    if check(mcap_path) == "truncated":
        raise RecordingError(truncated_message(mcap_path))
    sens, cur, tim, events, meta, reasons = [], [], [], [], {}, Counter()
    recorded: dict[str, list] = {}          # recorded vector / timing channels: type -> payloads
    malformed = []
    n_by_type: dict = {}
    run_id = None
    try:
        with open(mcap_path, "rb") as f:
            for sch, ch, m in make_reader(f).iter_messages(log_time_order=False):
                lay = rc.layout(sch) if sch is not None else None
                key = rc.key_of(ch.topic)
                if lay == rc.MALFORMED:
                    key = ch.metadata.get("wire_key") or key.replace("/malformed/", "/", 1)
                t = pr.message_type_for_key(key)
                if t is None:
                    continue
                run_id = run_id or key.split("/")[1]
                try:
                    if lay in (rc.SENSORS, rc.CURRENTS, rc.TIMING):
                        recorded.setdefault(lay, []).append(m.data)
                    elif lay == rc.EVENT:
                        events.append(rc.decode_event(m.data))
                    elif lay == rc.META:
                        meta = rc.decode_meta(m.data).info
                    elif lay == rc.MALFORMED:
                        malformed.append((t, rc.decode_malformed(m.data)[2]))
                    else:                                       # the earlier layout: wire bytes
                        _wire(t, m.data, sens, cur, tim, events, n_by_type)
                        if t == "RunMeta":
                            meta = pr.decode_meta(m.data).info
                except _Malformed as e:
                    reasons[f"{t}: {e}"] += 1
                except (ValueError, OverflowError, TypeError, struct.error) as e:   # ProtocolError is a ValueError
                    reasons[f"{t}: {type(e).__name__}"] += 1
    except RecordingError:
        raise
    except Exception as e:
        raise RecordingError(f"{mcap_path}: unreadable MCAP ({type(e).__name__}: {e}); "
                             f"`ambhil recover {mcap_path}` may restore the readable part") from None
    cols = {"SensorSample": [], "CurrentCommand": []}
    for wt, items in (("SensorSample", sens), ("CurrentCommand", cur)):
        if items:
            cols[wt].append((np.array([it[0].seq for it in items], np.uint64),
                             np.array([it[0].step for it in items], np.uint64),
                             np.array([it[0].sim_time_ns for it in items], np.int64),
                             np.array([it[0][-1] for it in items], float), [it[1] for it in items]))
    for rtype in (rc.SENSORS, rc.CURRENTS):
        datas = recorded.get(rtype)
        if not datas:
            continue
        wt = rc.WIRE_OF[rtype]
        n = (len(datas[0]) - (44 if rtype == rc.SENSORS else 52)) // 8
        n_by_type.setdefault(wt, n)
        a = rc.decode_vectors(rtype, n, datas)
        ok = (a["seq"] < _INT64) & (a["step"] < _INT64)
        if n != n_by_type[wt]:
            reasons[f"{wt}: axis count {n} != {n_by_type[wt]}"] += len(a)
            continue
        if not ok.all():
            reasons[f"{wt}: seq or step out of range"] += int((~ok).sum())
            a = a[ok]
        cols[wt].append((a["seq"], a["step"], rc.stamp_ns(a["sec"], a["nanosec"]), np.array(a["v"]),
                         rc.wire_payloads(rtype, a) if raw else []))
    for wt, data in malformed:                 # the recorder could not decode them: why not, as before
        try:
            _wire(wt, data, sens2 := [], cur2 := [], [], [], n_by_type)
            for it in sens2 + cur2:            # decodes after all (another count than the recorder's)
                m = it[0]
                cols[wt].append((np.array([m.seq], np.uint64), np.array([m.step], np.uint64),
                                 np.array([m.sim_time_ns], np.int64), np.array([m[-1]], float), [it[1]]))
        except _Malformed as e:
            reasons[f"{wt}: {e}"] += 1
        except (ValueError, OverflowError, TypeError, struct.error) as e:
            reasons[f"{wt}: {type(e).__name__}"] += 1
    rejected = sum(reasons.values())

    def pack(parts):
        if not parts:
            return {"seq": np.zeros(0, np.int64), "step": np.zeros(0, np.int64),
                    "t_ns": np.zeros(0, np.int64), "v": np.zeros((0, 0)), "raw": []}
        seq = np.concatenate([p[0] for p in parts]).astype(np.int64)
        o = np.argsort(seq, kind="stable")
        raws = [r for p in parts for r in p[4]]
        return {"seq": seq[o], "step": np.concatenate([p[1] for p in parts]).astype(np.int64)[o],
                "t_ns": np.concatenate([p[2] for p in parts])[o],
                "v": np.concatenate([p[3] for p in parts])[o],
                "raw": [raws[i] for i in o] if raw else []}

    timing = None
    tparts = [(np.arange(t.step, t.step + len(t.rtt_ns)), t.rtt_ns, t.tet_ns, t.wake_lateness_ns,
               np.asarray(t.flags, np.uint8), t.period_ns) for t in tim]
    if recorded.get(rc.TIMING):
        a = rc.decode_vectors(rc.TIMING, 0, recorded[rc.TIMING])
        ok = a["step"] < _INT64
        if not ok.all():
            reasons["Timing: step out of range"] += int((~ok).sum())
            rejected += int((~ok).sum())
            a = a[ok]
        if len(a):
            tparts.append((a["step"].astype(np.int64), a["rtt"], a["tet"], a["late"], a["flags"],
                           int(a["period"][0])))
    if tparts:
        step = np.concatenate([p[0] for p in tparts]).astype(np.int64)
        o = np.argsort(step, kind="stable")
        timing = {"step": step[o], "rtt_ns": np.concatenate([p[1] for p in tparts])[o],
                  "tet_ns": np.concatenate([p[2] for p in tparts])[o],
                  "lateness_ns": np.concatenate([p[3] for p in tparts])[o],
                  "flags": np.concatenate([p[4] for p in tparts])[o], "period_ns": tparts[0][5] or 1}
    return {"sensors": pack(cols["SensorSample"]), "currents": pack(cols["CurrentCommand"]),
            "timing": timing, "events": events, "meta": meta, "rejected": rejected,
            "rejected_reasons": dict(reasons), "run_id": run_id}


def _wire(t, data, sens, cur, tim, events, n_by_type) -> None:
    """One message of the earlier layout (wire bytes verbatim) into its list."""
    if t == "SensorSample":
        sens.append((_vector(pr.decode_sensor(data), n_by_type, t), bytes(data)))
    elif t == "CurrentCommand":
        cur.append((_vector(pr.decode_current(data), n_by_type, t), bytes(data)))
    elif t == "Timing":
        tim.append(_timing(pr.decode_timing(data)))
    elif t == "Event":
        events.append(pr.decode_event(data))


def _axis_names(meta: dict, n: int) -> list[str]:
    names = meta.get("axis_names")
    if isinstance(names, list) and len(names) == n:
        return [str(x) for x in names]
    return [f"{'xy'[i % 2]}{i // 2}" for i in range(n)]


def _fault_text(ev) -> str:
    """An event's text; a FAULT_INJECTED one as 'start sensor_noise A.x sigma=1e-06'."""
    if ev.kind != pr.EventKind.FAULT_INJECTED:
        return ev.text
    try:
        f = json.loads(ev.text)
        params = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in (f.get("params") or {}).items())
        return f"{f.get('phase')} {f.get('kind')}" + (f" {f['axis']}" if f.get("axis") else "") + (f" {params}" if params else "")
    except (ValueError, AttributeError, TypeError):
        return ev.text


def to_rerun(mcap_path: str, rrd_path: str, *, recording_id: str | None = None,
             application_id: str = "ambhil", orbit_window_s: float = 0.02,
             series_window_s: float = 0.2, station_names: list[str] | None = None) -> dict:
    """Write ``rrd_path`` from an ambhil MCAP: sim time (``sim_time``, duration) timeline,
    displacement/current series, orbit x-vs-y points per AMB station (axis pairs (0,1),
    (2,3), ... with a sliding window of ``orbit_window_s``), latency/TET/lateness series
    (µs), events as a text log; a default blueprint is embedded.  Uses send_columns."""
    import rerun as rr
    import rerun.blueprint as rrb
    run = load_run(mcap_path)
    S, C, T = run["sensors"], run["currents"], run["timing"]
    n = S["v"].shape[1] if len(S["seq"]) else (C["v"].shape[1] if len(C["seq"]) else 0)
    names = _axis_names(run["meta"], n)
    n_st = n // 2
    stations = station_names or run["meta"].get("station_names") or [f"station_{i}" for i in range(n_st)]
    stations = [str(s).replace("/", "_").replace(" ", "_") for s in stations][:n_st]

    def win(s):
        return rrb.VisibleTimeRange("sim_time", start=rrb.TimeRangeBoundary.cursor_relative(seconds=-s),
                                    end=rrb.TimeRangeBoundary.cursor_relative())
    series = [rrb.TimeSeriesView(origin="/sensors/displacement", name="displacement (um)",
                                 time_ranges=win(series_window_s)),
              rrb.TimeSeriesView(origin="/controller/current", name="current",
                                 time_ranges=win(series_window_s))]
    if T is not None:
        series.append(rrb.TimeSeriesView(origin="/timing", name="latency / TET (us)",
                                         time_ranges=win(series_window_s)))
    injected = [ev for ev in run["events"] if ev.kind == pr.EventKind.FAULT_INJECTED]
    if injected:   # scheduled faults (docs/faults.md): how many are active, over the whole run
        series.append(rrb.TimeSeriesView(origin="/faults", name="scheduled faults active"))
    orbit_views = [rrb.Spatial2DView(origin=f"/orbit/{s}", name=f"orbit {s} (um)",
                                     time_ranges=win(orbit_window_s)) for s in stations]
    right = [rrb.Grid(*orbit_views)] if orbit_views else []
    right.append(rrb.TextLogView(origin="/events", name="events"))
    bp = rrb.Blueprint(rrb.Horizontal(rrb.Vertical(*series), rrb.Vertical(*right),
                                      column_shares=[3, 2]),
                       rrb.TimePanel(timeline="sim_time"), collapse_panels=False)

    rec = rr.RecordingStream(application_id, recording_id=recording_id or run["run_id"] or "replay")
    rec.save(rrd_path, default_blueprint=bp)
    if len(S["seq"]):
        rec.log("/sensors/displacement", rr.SeriesLines(names=names), static=True)
        t = rr.TimeColumn("sim_time", duration=S["t_ns"] / 1e9)
        rr.send_columns("/sensors/displacement", indexes=[t],
                        columns=rr.Scalars.columns(scalars=S["v"] * 1e6), recording=rec)  # m -> um
        for i, s in enumerate(stations):
            rr.send_columns(f"/orbit/{s}", indexes=[rr.TimeColumn("sim_time", duration=S["t_ns"] / 1e9)],
                            columns=rr.Points2D.columns(positions=S["v"][:, 2 * i:2 * i + 2] * 1e6),  # um:
                            # the viewer draws nothing for points at the 1e-6 scale (checked in rerun 0.41)
                            recording=rec)
    if len(C["seq"]):
        rec.log("/controller/current", rr.SeriesLines(names=[f"i_{a}" for a in names]), static=True)
        rr.send_columns("/controller/current",
                        indexes=[rr.TimeColumn("sim_time", duration=C["t_ns"] / 1e9)],
                        columns=rr.Scalars.columns(scalars=C["v"]), recording=rec)
    if T is not None and len(T["step"]):
        tt = T["step"] * T["period_ns"] / 1e9
        for name, key in (("rtt_us", "rtt_ns"), ("tet_us", "tet_ns"), ("lateness_us", "lateness_ns")):
            rec.log(f"/timing/{name}", rr.SeriesLines(names=[name]), static=True)
            rr.send_columns(f"/timing/{name}", indexes=[rr.TimeColumn("sim_time", duration=tt)],
                            columns=rr.Scalars.columns(scalars=T[key] / 1e3), recording=rec)
    for ev in run["events"]:
        rec.set_time("sim_time", duration=ev.sim_time_ns / 1e9)
        lvl = "ERROR" if ev.kind == pr.EventKind.FAULT else (
            "WARN" if ev.kind in (pr.EventKind.REJECTED, pr.EventKind.OVERRUN, pr.EventKind.DUPLICATE,
                                  pr.EventKind.GAP, pr.EventKind.PEER_LOST, pr.EventKind.TIMEOUT,
                                  pr.EventKind.WARNING, pr.EventKind.FAULT_INJECTED)
            else "INFO")
        rec.log("/events", rr.TextLog(f"[{ev.source}] {ev.kind_name}: {_fault_text(ev)}", level=lvl))
    if injected:
        # a step series that marks each fault's start and end on the timeline (count of active faults)
        t_ns, active, level = [], [], 0
        for ev in injected:
            try:
                phase = json.loads(ev.text).get("phase")
            except ValueError:
                continue
            if phase == "start":
                level += 1
            elif phase == "end":
                level -= 1
            t_ns += [ev.sim_time_ns, ev.sim_time_ns]
            active += [active[-1] if active else 0, level]
        rec.log("/faults/active", rr.SeriesLines(names=["faults active"]), static=True)
        rr.send_columns("/faults/active", indexes=[rr.TimeColumn("sim_time", duration=np.array(t_ns) / 1e9)],
                        columns=rr.Scalars.columns(scalars=np.array(active, float)), recording=rec)
    if run["meta"]:
        rec.log("/meta", rr.TextDocument(json.dumps(run["meta"], indent=1)), static=True)
    rec.flush()
    rec.disconnect()
    return {"rrd": rrd_path, "samples": int(len(S["seq"])), "currents": int(len(C["seq"])),
            "stations": stations, "events": len(run["events"]), "faults_injected": len(injected),
            "rejected": run["rejected"],
            "rejected_reasons": run["rejected_reasons"]}


def to_controller(mcap_path: str, run_id: str, *, listen=None, connect=None,
                  tolerance: float = 1e-9, reply_timeout: float = 1.0, start_timeout: float = 30.0,
                  max_steps: int | None = None, session=None) -> dict:
    """Re-publish the recorded SensorSamples (verbatim wire bytes, seq order) to a controller
    under test on ``ambhil/<run_id>/...`` in lockstep, and compare each reply with the
    recorded CurrentCommand of the same seq.  The replay takes the plant's role (declares
    ``alive/plant``; the controller connects to ``listen``).  ``passed`` is True iff every
    recorded sample got a reply and ``max_abs_dev <= tolerance``."""
    run = load_run(mcap_path)
    S, C = run["sensors"], run["currents"]
    if not len(S["seq"]):
        raise ValueError(f"{mcap_path}: no sensor samples recorded")
    n = S["v"].shape[1]
    rec_cur = {int(s): C["v"][i] for i, s in enumerate(C["seq"])}
    K = pr.keys(run_id)
    own = session is None
    if own:
        session = tr.open_session(listen, connect)
    q: queue.SimpleQueue = queue.SimpleQueue()
    sub = tr.declare_callback_subscriber(session, K.currents,
                                         lambda s: q.put((s.payload.to_bytes(), attached(s))))
    pub = tr.declare_publisher(session, K.sensors)
    evp = tr.declare_publisher(session, K.events)

    def _live(key, alive):
        if key == K.alive_controller and not alive:
            q.put(None)
    watch = tr.LivelinessWatch(session, K.alive_all, _live)
    pairing = Pairing(session, run_id, "plant", "controller")   # the replay poses as the plant
    pairing.announce()
    token = tr.declare_token(session, K.alive_plant)
    cc = pr.CurrentCodec(n)
    fault = None
    max_dev, worst = 0.0, None
    n_cmp = n_missing = n_sent = rejected = foreign = 0
    t0 = time.perf_counter()
    try:
        watch.wait_for([K.alive_controller], start_timeout)
        peer = pairing.wait(None, start_timeout)
        me = pairing.id
        tr.wait_matching(pub, start_timeout, "controller")
        total = len(S["seq"]) if max_steps is None else min(max_steps, len(S["seq"]))
        for i in range(total):
            seq = int(S["seq"][i])
            pub.put(S["raw"][i], attachment=me)
            n_sent += 1
            t_end = time.monotonic() + reply_timeout
            while True:
                rem = t_end - time.monotonic()
                try:
                    data = q.get(timeout=max(rem, 0.0)) if rem > 0 else q.get_nowait()
                except queue.Empty:
                    raise RuntimeError(f"controller timeout: no reply to seq {seq} within "
                                       f"{reply_timeout:g} s") from None
                if data is None:
                    raise RuntimeError(f"controller lost (liveliness) at seq {seq}")
                data, a = data
                if a != peer:                 # not from the paired controller under test
                    foreign += 1
                    continue
                try:
                    m = cc.decode(data)
                except pr.ProtocolError:
                    rejected += 1
                    continue
                if m.seq == seq:
                    break
            ref = rec_cur.get(seq)
            if ref is None:
                n_missing += 1
                continue
            d = np.abs(m.current - ref)
            j = int(np.argmax(d))
            n_cmp += 1
            if worst is None or d[j] > max_dev:
                max_dev = float(d[j])
                worst = {"seq": seq, "step": int(S["step"][i]), "axis": j,
                         "recorded": float(ref[j]), "replayed": float(m.current[j])}
    except (RuntimeError, tr.TransportError) as e:
        fault = str(e)
    try:
        evp.put(pr.encode_event(pr.Event(pr.EventKind.RUN_END, json.dumps({"reason": "replay end"}),
                                         "replay", 0, 0, 0, time.time_ns())),
                attachment=pairing.id)
        time.sleep(0.05)
    except Exception:
        pass
    tr.close_quietly(token, pairing, watch, evp, pub, sub)
    if own:
        tr.close_quietly(session)
    passed = fault is None and n_cmp > 0 and max_dev <= tolerance and n_missing == 0
    return {"passed": passed, "max_abs_dev": max_dev, "worst": worst, "tolerance": tolerance,
            "compared": n_cmp, "missing_recorded": n_missing, "sent": n_sent,
            "rejected": rejected, "foreign": foreign, "fault": fault, "wall_s": round(time.perf_counter() - t0, 3)}
