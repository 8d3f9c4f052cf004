"""Replay a recorded run into the rerun viewer: an ambhil MCAP to a .rrd with its blueprint embedded
(:func:`to_rerun`).  The recorded layout is streamed, chunk by chunk, so time and memory stay flat
however long the run; a recording of the earlier layout (wire bytes verbatim) is loaded whole.

What the .rrd shows, and how the viewer lays it out, is :mod:`ambhil.bridge.recording.rerun_view`'s;
replay to a controller under test is :mod:`ambhil.bridge.recording.controller_replay`'s."""
from __future__ import annotations

from collections import Counter

import numpy as np
from mcap.reader import make_reader

from ambhil.bridge.recording import layout as rc
from ambhil.bridge.recording.chunks import iter_chunks
from ambhil.bridge.recording.load import (INT64, axis_names, channels, gather_channel, load_run,
                                          malformed_rows)
from ambhil.bridge.recording.recover import RecordingError, check, truncated_message
from ambhil.bridge.recording.rerun_view import RerunSink


def to_rerun(mcap_path: str, rrd_path: str, *, recording_id: str | None = None,
             application_id: str = "ambhil", orbit_window_s: float = 0.02,
             series_window_s: float = 0.2, station_names: list[str] | None = None,
             block: int = 100_000, progress=None) -> dict:
    """Write ``rrd_path`` from an ambhil MCAP, streamed: the file is read chunk by chunk
    (:func:`ambhil.bridge.recording.chunks.iter_chunks`) and sent to rerun in columns of at most ``block`` rows
    (``send_columns``), so time and memory stay flat however long the run.  Content: the
    ``sim_time`` timeline (duration); displacement (um) and coil current (A) series per axis;
    an orbit view per AMB station (axis pairs (0,1), (2,3), ...; points in um, +y up, a sliding
    window of ``orbit_window_s``) on one scale for all stations with rings, axes and the station's
    clearance circle; round trip, controller TET and wake lateness each in its own panel (us);
    events as a text log; the blueprint is embedded.  ``progress(done, total)``: bytes read.
    A recording of the earlier layout (wire bytes verbatim) is read whole (:func:`load_run`)."""
    import rerun as rr
    if check(mcap_path) == "truncated":
        raise RecordingError(truncated_message(mcap_path))
    try:
        f = open(mcap_path, "rb")
        reader = make_reader(f)
        summary = reader.get_summary()
    except Exception as e:
        raise RecordingError(f"{mcap_path}: unreadable MCAP ({type(e).__name__}: {e}); "
                             f"`ambhil recover {mcap_path}` may restore the readable part") from None
    with f:
        chans = channels(summary) if summary is not None else {}
        legacy = summary is None or any(v[0].startswith("wire:") for v in chans.values())
        run = load_run(mcap_path, raw=False) if legacy else None
        meta, run_id, n = _run_header(reader, summary, chans, run)
        names = axis_names(meta, n)
        n_st = n // 2
        stations = station_names or meta.get("station_names") or [f"station_{i}" for i in range(n_st)]
        stations = [str(s).replace("/", "_").replace(" ", "_") for s in stations][:n_st]

        rec = rr.RecordingStream(application_id, recording_id=recording_id or run_id or "replay")
        rec.save(rrd_path)
        sink = RerunSink(rec, names, stations)
        reasons: Counter = Counter()
        if legacy:
            _send_loaded(sink, run, reasons)
        else:
            _stream(f, summary, chans, sink, reasons, block, progress, n)
        sink.finish(meta, orbit_window_s, series_window_s)
        rec.flush()
        rec.disconnect()
    return {"rrd": rrd_path, "samples": sink.samples, "currents": sink.currents,
            "stations": stations, "events": sink.events, "faults_injected": len(sink.injected),
            "orbit_max_m": [float(r) * 1e-6 for r in sink.r_max], "timing_us": sink.timing_stats,
            "rejected": sum(reasons.values()), "rejected_reasons": dict(reasons)}


def _run_header(reader, summary, chans, run) -> tuple[dict, str | None, int]:
    """The run's RunMeta info, run id and axis count: from its RunMeta channel (``run``: the whole
    run loaded, a recording of the earlier layout: from it), the axis count from RunMeta, else a
    vector channel's metadata, else the loaded arrays."""
    meta, run_id = {}, next((v[2].split("/")[1] for v in chans.values()), None)
    if run is None:
        for cid, (lay, _, key) in chans.items():
            if lay == rc.META:
                for _, _, m in reader.iter_messages(topics=[summary.channels[cid].topic]):
                    meta = rc.decode_meta(m.data).info
                    break
    else:
        meta, run_id = run["meta"], run["run_id"]
    n = int(meta.get("n_axes") or 0)
    if not n:
        for cid, (lay, wt, key) in chans.items():
            if lay in (rc.SENSORS, rc.CURRENTS):
                n = len(rc.axes_of(summary.channels[cid]) or [])
                break
    if run is not None:
        S = run["sensors"]
        n = S["v"].shape[1] if len(S["seq"]) else (run["currents"]["v"].shape[1] if len(run["currents"]["seq"]) else n)
    return meta, run_id, n


def _send_loaded(sink: RerunSink, run: dict, reasons: Counter) -> None:
    """A run loaded whole (:func:`load_run`) into ``sink``."""
    S, C, T = run["sensors"], run["currents"], run["timing"]
    sink.sensors(S["t_ns"] / 1e9, S["v"])
    sink.current(C["t_ns"] / 1e9, C["v"])
    if T is not None:
        sink.timing(T["step"] * T["period_ns"] / 1e9,
                    {"rtt": T["rtt_ns"], "tet": T["tet_ns"], "late": T["lateness_ns"],
                     "flags": T["flags"]})
    for ev in run["events"]:
        sink.event(ev)
    reasons.update(run["rejected_reasons"])


def _stream(f, summary, chans, sink, reasons, block, progress, n_axes) -> None:
    """The recorded layout, chunk by chunk, into ``sink`` in blocks of about ``block`` rows."""
    pend = {rc.SENSORS: [], rc.CURRENTS: [], rc.TIMING: []}
    rows = {k: 0 for k in pend}
    n_by_type: dict = {}
    extra = {"SensorSample": [], "CurrentCommand": []}

    def flush(lay):
        parts = pend[lay]
        if not parts:
            return
        a = np.concatenate(parts)
        pend[lay], rows[lay] = [], 0
        if lay == rc.TIMING:
            ok = a["step"] < INT64
            if not ok.all():
                reasons["Timing: step out of range"] += int((~ok).sum())
                a = a[ok]
            sink.timing(rc.stamp_ns(a["sec"], a["nanosec"]) / 1e9,
                        {"rtt": a["rtt"], "tet": a["tet"], "late": a["late"], "flags": a["flags"]})
            return
        wt = rc.WIRE_OF[lay]
        ok = (a["seq"] < INT64) & (a["step"] < INT64)
        if not ok.all():
            reasons[f"{wt}: seq or step out of range"] += int((~ok).sum())
            a = a[ok]
        t = rc.stamp_ns(a["sec"], a["nanosec"]) / 1e9
        (sink.sensors if lay == rc.SENSORS else sink.current)(t, np.asarray(a["v"]))

    malformed = []
    for buf, out in iter_chunks(f, summary, progress):
        for cid, (starts, ends, _) in out.items():
            info = chans.get(cid)
            if info is None:
                continue
            lay, wt, _ = info
            if lay in pend:
                a = gather_channel(buf, lay, starts, ends, info[2])
                if lay != rc.TIMING:
                    n_by_type.setdefault(wt, a.dtype["v"].shape[0])
                pend[lay].append(a)
                rows[lay] += len(starts)
                if rows[lay] >= block:
                    flush(lay)
            elif lay == rc.EVENT:
                for s, e in zip(starts, ends):
                    sink.event(rc.decode_event(buf[s:e]))
            elif lay == rc.MALFORMED:
                malformed += [(wt, rc.decode_malformed(buf[s:e])[2]) for s, e in zip(starts, ends)]
    for lay in pend:
        flush(lay)
    for k in n_by_type:
        n_by_type[k] = n_by_type[k] or n_axes
    for wt, data in malformed:              # counted in reasons; samples / commands that decode after all kept
        rows_back = malformed_rows(wt, data, n_by_type, reasons)
        if wt in extra:
            extra[wt] += rows_back
    for m in extra["SensorSample"]:
        sink.sensors(np.array([m.sim_time_ns / 1e9]), np.array([m.displacement]))
    for m in extra["CurrentCommand"]:
        sink.current(np.array([m.sim_time_ns / 1e9]), np.array([m.current]))
