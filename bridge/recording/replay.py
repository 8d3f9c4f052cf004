"""Replay a recorded run: to a Rerun .rrd (with blueprint), or to a controller under test."""
from __future__ import annotations

import json
import queue
import struct
import threading
import time

import numpy as np

from ambhil.bridge.process import transport as tr
from ambhil.bridge import protocol as pr
from ambhil.bridge.process.pairing import Pairing
from ambhil.bridge.process.startup import GONE
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
    """Decode an ambhil MCAP (the recorded layout of :mod:`ambhil.bridge.recording.layout`, or the earlier one
    of wire bytes verbatim) into numpy arrays.  Malformed messages (failing protocol
    validation, seq/step beyond int64, axis count differing from the run's, inconsistent timing
    arrays) are skipped and counted in ``rejected`` (by reason in ``rejected_reasons``).  Returns
    dict with keys sensors/currents (``seq``, ``step``, ``t_ns``, ``v`` (N x n_axes), ``raw``
    (the wire bytes, restored exactly; empty with ``raw=False``)), ``timing`` (per-step arrays),
    ``events`` (list of Event), ``meta`` (RunMeta.info or {}), ``run_id``.
    Raises :class:`ambhil.bridge.recording.recover.RecordingError` (one line, fit for the user) for a file that
    is not MCAP, is truncated (naming ``ambhil recover``) or cannot be read."""
    from collections import Counter
    from ambhil.bridge.recording import layout as rc
    from ambhil.bridge.recording.recover import RecordingError, check, truncated_message
    if check(mcap_path) == "truncated":
        raise RecordingError(truncated_message(mcap_path))
    sens, cur, tim, events, meta, reasons = [], [], [], [], {}, Counter()
    recorded: dict[str, list] = {}          # recorded vector / timing channels: type -> payloads
    malformed = []
    n_by_type: dict = {}
    run_id = None
    arrays: dict[str, list] = {}            # the same, decoded chunk by chunk (the fast path)
    try:
        with open(mcap_path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            chans = _channels(summary) if summary is not None else None
            fast = bool(chans) and not any(v[0].startswith("wire:") for v in chans.values())
            if fast:                # chunk by chunk, no Python object per message
                run_id = next(iter(chans.values()))[2].split("/")[1]
                for buf, out in rc.iter_chunks(f, summary):
                    for cid, (starts, ends, _) in out.items():
                        lay, t, _ = chans.get(cid, (None, None, None))
                        if lay in (rc.SENSORS, rc.CURRENTS, rc.TIMING):
                            arrays.setdefault(lay, []).append(_gather(buf, lay, starts, ends, cid))
                        elif lay in (rc.EVENT, rc.META, rc.MALFORMED):
                            for a, b in zip(starts, ends):
                                d = buf[a:b]
                                try:
                                    if lay == rc.EVENT:
                                        events.append(rc.decode_event(d))
                                    elif lay == rc.META:
                                        meta = rc.decode_meta(d).info
                                    else:
                                        malformed.append((t, rc.decode_malformed(d)[2]))
                                except (ValueError, OverflowError, TypeError, struct.error) as e:
                                    reasons[f"{t}: {type(e).__name__}"] += 1
            f.seek(0)
            for sch, ch, m in (() if fast else make_reader(f).iter_messages(log_time_order=False)):
                lay = rc.layout(sch) if sch is not None else None
                key = rc.channel_key(ch)
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
                        d = rc.upgrade(t, m.data)               # protocol version 1 read as 2
                        _wire(t, d, sens, cur, tim, events, n_by_type)
                        if t == "RunMeta":
                            meta = pr.decode_meta(d).info
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
                             np.array([it[0][-2] for it in items], float), [it[1] for it in items]))
    for rtype in (rc.SENSORS, rc.CURRENTS, rc.TIMING):
        if recorded.get(rtype):
            datas = recorded[rtype]
            n = 0 if rtype == rc.TIMING else (len(datas[0]) - (44 if rtype == rc.SENSORS else 52)) // 8
            arrays[rtype] = [rc.decode_vectors(rtype, n, datas)]
    peers = rc.peer_ids(meta)                  # the senders' ids that end the restored wire bytes
    for rtype in (rc.SENSORS, rc.CURRENTS):
        if not arrays.get(rtype):
            continue
        wt = rc.WIRE_OF[rtype]
        a = np.concatenate(arrays[rtype])
        n = a.dtype["v"].shape[0]
        n_by_type.setdefault(wt, n)
        ok = (a["seq"] < _INT64) & (a["step"] < _INT64)
        if n != n_by_type[wt]:
            reasons[f"{wt}: axis count {n} != {n_by_type[wt]}"] += len(a)
            continue
        if not ok.all():
            reasons[f"{wt}: seq or step out of range"] += int((~ok).sum())
            a = a[ok]
        cols[wt].append((a["seq"], a["step"], rc.stamp_ns(a["sec"], a["nanosec"]), np.array(a["v"]),
                         rc.wire_payloads(rtype, a, peers[wt]) if raw else []))
    for wt, data in malformed:                 # the recorder could not decode them: why not, as before
        try:
            _wire(wt, data, sens2 := [], cur2 := [], [], [], n_by_type)
            for it in sens2 + cur2:            # decodes after all (another count than the recorder's)
                m = it[0]
                cols[wt].append((np.array([m.seq], np.uint64), np.array([m.step], np.uint64),
                                 np.array([m.sim_time_ns], np.int64), np.array([m[-2]], float), [it[1]]))
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
    if arrays.get(rc.TIMING):
        a = np.concatenate(arrays[rc.TIMING])
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


def _channels(summary) -> dict:
    """{channel id: (recorded layout, wire type, wire key)} of an ambhil recording's channels."""
    from ambhil.bridge.recording import layout as rc
    out = {}
    for cid, ch in summary.channels.items():
        lay = rc.layout(summary.schemas.get(ch.schema_id))
        key = rc.channel_key(ch)
        if lay == rc.MALFORMED:
            key = ch.metadata.get("wire_key") or key.replace("/malformed/", "/", 1)
        wt = pr.message_type_for_key(key)
        if lay is not None and wt is not None:
            out[cid] = (lay, wt, key)
    return out


def _gather(buf, lay, starts, ends, where) -> np.ndarray:
    """One chunk's messages of a fixed-layout recorded channel as a structured array."""
    from ambhil.bridge.recording import layout as rc
    size = ends[0] - starts[0]
    if not (np.asarray(ends) - np.asarray(starts) == size).all():
        raise ValueError(f"channel {where}: recorded messages of unequal size")
    n = 0 if lay == rc.TIMING else (size - (44 if lay == rc.SENSORS else 52)) // 8
    return rc.gather(buf, starts, size, rc.rec_dtype(lay, n))


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


def _nice(x: float) -> float:
    """The smallest of 1, 2, 5 x 10^k that is >= x (x > 0)."""
    e = 10.0 ** np.floor(np.log10(x))
    return float(next(m * e for m in (1, 2, 5, 10) if m * e >= x * (1 - 1e-9)))


def touchdown_clearances(meta: dict, n: int) -> list[tuple[float, bool]]:
    """(touchdown clearance in um, given in the scene?) of the first ``n`` radial stations, from
    RunMeta ``touchdown_clearances_m``; a recording made before it was carried: half the
    magnetic gap ``gaps_m``, the default assumption."""
    c = meta.get("touchdown_clearances_m")
    if isinstance(c, list) and c:
        given = meta.get("touchdown_clearances_given") or [True] * len(c)
        return [(float(x) * 1e6, bool(g)) for x, g in zip(c, given)][:n]
    return [(0.5 * float(g) * 1e6, False) for g in (meta.get("gaps_m") or [])][:n]


def orbit_scale(r_max_um: float, gaps_um, magnetic_um=()) -> tuple[float, float]:
    """(half-width, ring spacing) of the orbit views, in um, common to all stations: the largest
    orbit fills ~80 % of the view; when it reaches 30 % of the smallest touchdown clearance
    (``gaps_um``: the stations' touchdown clearances), the view shows the whole clearance instead,
    and when it goes past a touchdown clearance, the whole magnetic gap (``magnetic_um``)."""
    gaps = [g for g in gaps_um if g and g > 0]
    mags = [g for g in magnetic_um if g and g > 0]
    if gaps and mags and r_max_um > min(gaps):
        half = 1.1 * max(mags + gaps)
    elif gaps and (r_max_um <= 0 or r_max_um >= 0.3 * min(gaps)):
        half = 1.1 * max(gaps)
    else:
        half = 1.25 * max(r_max_um, 1e-3)
    step = _nice(half / 3)
    return float(np.ceil(half / step) * step), step


def _circle(r: float, n: int = 181) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n)
    return np.column_stack([r * np.cos(a), r * np.sin(a)])


_COLORS = [(66, 165, 245), (255, 167, 38), (102, 187, 106), (171, 71, 188), (239, 83, 80), (38, 198, 218)]
_TIMING = (("rtt_us", "rtt", "round trip (us)"),            # plant publish -> reply at the plant
           ("tet_us", "tet", "controller TET (us)"),        # controller execution time
           ("lateness_us", "late", "wake lateness (us)"))   # plant wake - deadline (real time)


class _RerunSink:
    """The entities of a run's .rrd, filled block by block (``send_columns``)."""

    def __init__(self, rec, names: list[str], stations: list[str]):
        import rerun as rr
        self.rr, self.rec, self.names, self.stations = rr, rec, names, stations
        self.r_max = np.zeros(len(stations))
        self.samples = self.currents = 0
        self.timing_rows = self.warmup_rows = 0
        self.timing_stats: dict[str, dict] = {}      # the panels' p99 / max (us), by finish()
        self.timing_values: dict[str, list] = {key: [] for _, key, _ in _TIMING}
        self.injected = []
        self.events = 0
        rec.log("/sensors/displacement", rr.SeriesLines(names=[f"{a} (um)" for a in names]), static=True)
        rec.log("/controller/current", rr.SeriesLines(names=[f"{a} (A)" for a in names]), static=True)
        for name, _, title in _TIMING:
            rec.log(f"/timing/{name}", rr.SeriesLines(names=[title]), static=True)

    def sensors(self, t_s, v_m):
        rr = self.rr
        if not len(t_s):
            return
        um = v_m * 1e6
        rr.send_columns("/sensors/displacement", indexes=[rr.TimeColumn("sim_time", duration=t_s)],
                        columns=rr.Scalars.columns(scalars=um), recording=self.rec)
        for i, s in enumerate(self.stations):
            xy = um[:, 2 * i:2 * i + 2]
            # rerun's 2D views point y down: store (x, -y) so that +y is up, as in every orbit plot
            pos = np.column_stack([xy[:, 0], -xy[:, 1]])
            r = np.hypot(xy[:, 0], xy[:, 1])
            if np.isfinite(r).any():
                self.r_max[i] = max(self.r_max[i], float(np.nanmax(r)))
            rr.send_columns(f"/orbit/{s}", indexes=[rr.TimeColumn("sim_time", duration=t_s)],
                            columns=rr.Points2D.columns(positions=pos), recording=self.rec)
        self.samples += len(t_s)

    def current(self, t_s, amp):
        if len(t_s):
            self.rr.send_columns("/controller/current", indexes=[self.rr.TimeColumn("sim_time", duration=t_s)],
                                 columns=self.rr.Scalars.columns(scalars=amp), recording=self.rec)
            self.currents += len(t_s)

    def timing(self, t_s, cols: dict):
        if len(t_s):
            # the panels' p99 / max are those of the run's summary (bridge/process/plant_node.py): the
            # steps after the warm-up, round trip and TET of the steps that got a reply
            flags = cols.get("flags")
            keep = (np.ones(len(t_s), bool) if flags is None else
                    (np.asarray(flags) & pr.FLAG_WARMUP) == 0)
            answered = keep & (np.asarray(cols["rtt"]) > 0)
            self.warmup_rows += int((~keep).sum())
            for name, key, _ in _TIMING:
                sel = keep if key == "late" else answered
                self.timing_values[key].append(np.asarray(cols[key])[sel] / 1e3)
                self.rr.send_columns(f"/timing/{name}", indexes=[self.rr.TimeColumn("sim_time", duration=t_s)],
                                     columns=self.rr.Scalars.columns(scalars=np.asarray(cols[key]) / 1e3),
                                     recording=self.rec)
            self.timing_rows += len(t_s)

    def event(self, ev):
        rr = self.rr
        self.rec.set_time("sim_time", duration=ev.sim_time_ns / 1e9)
        lvl = "ERROR" if ev.kind == pr.EventKind.FAULT else (
            "WARN" if ev.kind in (pr.EventKind.REJECTED, pr.EventKind.OVERRUN, pr.EventKind.DUPLICATE,
                                  pr.EventKind.GAP, pr.EventKind.PEER_LOST, pr.EventKind.TIMEOUT,
                                  pr.EventKind.WARNING, pr.EventKind.FAULT_INJECTED)
            else "INFO")
        self.rec.log("/events", rr.TextLog(f"[{ev.source}] {ev.kind_name}: {_fault_text(ev)}", level=lvl))
        self.events += 1
        if ev.kind == pr.EventKind.FAULT_INJECTED:
            self.injected.append(ev)

    def finish(self, meta: dict, orbit_window_s: float, series_window_s: float):
        rr, rrb, rec = self.rr, __import__("rerun.blueprint").blueprint, self.rec
        clr = touchdown_clearances(meta, len(self.stations))
        gaps_um = [c for c, _ in clr]                      # the touchdown clearances (um)
        magnetic_um = [g * 1e6 for g in (meta.get("gaps_m") or [])][:len(self.stations)]
        half, step = orbit_scale(float(self.r_max.max()) if len(self.r_max) else 0.0, gaps_um, magnetic_um)
        for i, s in enumerate(self.stations):
            rings = np.arange(step, half + 1e-9, step)
            grey = (110, 110, 110)
            rec.log(f"/orbit/{s}/scale", rr.LineStrips2D(
                [_circle(r) for r in rings] + [[[-half, 0], [half, 0]], [[0, -half], [0, half]]],
                colors=[grey] * (len(rings) + 2), radii=rr.Radius.ui_points(0.5)), static=True)
            d = np.sqrt(0.5)      # ring values on the lower-right diagonal, x and y at the axes' ends
            rec.log(f"/orbit/{s}/scale/labels", rr.Points2D(
                [[d * r, d * r] for r in rings] + [[0.96 * half, 0.0], [0.0, -0.96 * half]],
                labels=[f"{r:g}" for r in rings[:-1]] + [f"{rings[-1]:g} um", "x", "y"],
                radii=rr.Radius.ui_points(1.5), colors=[grey] * len(rings) + [(200, 200, 200)] * 2,
                show_labels=True), static=True)
            if i < len(magnetic_um) and magnetic_um[i] <= half:   # the magnetic gap, apart, where in view
                mg = magnetic_um[i]
                rec.log(f"/orbit/{s}/magnetic_gap", rr.LineStrips2D(
                    [_circle(mg)], colors=[(150, 150, 150)], radii=rr.Radius.ui_points(0.8)), static=True)
                rec.log(f"/orbit/{s}/magnetic_gap/label", rr.Points2D(
                    [[d * mg, -d * mg]], labels=[f"magnetic gap {mg:g} um"], colors=[(150, 150, 150)],
                    radii=rr.Radius.ui_points(1.5), show_labels=True), static=True)
            if i < len(gaps_um):
                g, given = clr[i]
                rec.log(f"/orbit/{s}/clearance", rr.LineStrips2D(
                    [_circle(g)], colors=[(229, 57, 53)], radii=rr.Radius.ui_points(1.5)), static=True)
                # the clearance's value, on its circle when in view, else in the upper-left corner
                at = [-d * g, -d * g] if g <= half else [0.0, 0.92 * half]
                rec.log(f"/orbit/{s}/clearance/label", rr.Points2D(
                    [at], labels=[f"touchdown clearance {g:g} um" + ("" if given else " (assumed: half the gap)")
                                  + ("" if g <= half else " (off scale)")],
                    colors=[(229, 57, 53)], radii=rr.Radius.ui_points(1.5), show_labels=True), static=True)
            rec.log(f"/orbit/{s}", rr.Points2D.from_fields(
                colors=[_COLORS[i % len(_COLORS)]], radii=rr.Radius.ui_points(2.0)), static=True)
        if self.injected:   # a step series that marks each fault's start and end (count of active faults)
            t_ns, active, level = [], [], 0
            for ev in self.injected:
                try:
                    phase = json.loads(ev.text).get("phase")
                except ValueError:
                    continue
                level += 1 if phase == "start" else (-1 if phase == "end" else 0)
                t_ns += [ev.sim_time_ns, ev.sim_time_ns]
                active += [active[-1] if active else 0, level]
            rec.log("/faults/active", rr.SeriesLines(names=["faults active"]), static=True)
            rr.send_columns("/faults/active", indexes=[rr.TimeColumn("sim_time", duration=np.array(t_ns) / 1e9)],
                            columns=rr.Scalars.columns(scalars=np.array(active, float)), recording=rec)
        if meta:
            rec.log("/meta", rr.TextDocument(json.dumps(meta, indent=1)), static=True)
        rr.send_blueprint(self.blueprint(rrb, half, gaps_um, orbit_window_s, series_window_s),
                          make_active=True, make_default=True, recording=rec)

    def blueprint(self, rrb, half, gaps_um, orbit_window_s, series_window_s):
        def win(s):
            return rrb.VisibleTimeRange("sim_time", start=rrb.TimeRangeBoundary.cursor_relative(seconds=-s),
                                        end=rrb.TimeRangeBoundary.cursor_relative())
        series = [rrb.TimeSeriesView(origin="/sensors/displacement", name="displacement (um)",
                                     time_ranges=win(series_window_s)),
                  rrb.TimeSeriesView(origin="/controller/current", name="coil current (A)",
                                     time_ranges=win(series_window_s))]
        if self.injected:   # scheduled faults (docs/faults.md): how many are active, over the whole run
            series.append(rrb.TimeSeriesView(origin="/faults", name="scheduled faults active"))
        bounds = rrb.VisualBounds2D(x_range=[-half, half], y_range=[-half, half])
        orbits = [rrb.Spatial2DView(
            origin=f"/orbit/{s}", visual_bounds=bounds, time_ranges=win(orbit_window_s),
            name=f"orbit {s} (um)")
            for i, s in enumerate(self.stations)]
        # the orbits side by side (rows of at most 3: no empty cell), events under them
        rows = [orbits[k:k + 3] for k in range(0, len(orbits), 3)]
        right = [rrb.Horizontal(*r) for r in rows]
        # timing: one panel each, so that a 7 ms round trip does not flatten a 7 us TET, and each
        # panel's y axis ends at 1.5 x its 99th percentile (the rarer spikes go off the top; the
        # title gives their maximum); p99 and max are the summary's: after the warm-up (real time),
        # steps that got a reply (the panel draws every step)
        timing = []
        for name, key, title in (_TIMING if self.timing_rows else ()):
            v = np.concatenate(self.timing_values[key]) if self.timing_values[key] else np.zeros(0)
            v = v if len(v) else np.zeros(1)
            warm = self.warmup_rows > 0
            p99, top = float(np.percentile(v, 99)), float(v.max())
            self.timing_stats[key] = {"p99": p99, "max": top}
            if key == "late" and not v.any():
                continue        # lockstep: the plant never waits for a deadline
            hi = 1.5 * p99 if p99 > 0 else max(top, 1.0)
            timing.append(rrb.TimeSeriesView(
                origin=f"/timing/{name}", time_ranges=win(series_window_s),
                name=f"{title}: p99 {p99:.4g}, max {top:.4g}" + (" after the warm-up" if warm else ""),
                axis_y=rrb.ScalarAxis(range=(min(0.0, float(v.min())), hi), zoom_lock=False)))
        lower = [rrb.Vertical(*timing)] if timing else []
        lower.append(rrb.TextLogView(origin="/events", name="events"))
        right.append(rrb.Horizontal(*lower))
        return rrb.Blueprint(rrb.Horizontal(rrb.Vertical(*series), rrb.Vertical(*right, row_shares=[2] * len(rows) + [3]),
                                            column_shares=[2, 3]),
                             rrb.TimePanel(timeline="sim_time", state="collapsed"),
                             rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))


def _malformed_rows(wt: str, data: bytes, n_by_type: dict, reasons) -> list:
    """A payload the recorder could not decode: why not (counted in ``reasons``, as load_run
    does), or its message if it decodes after all (another axis count than the recorder's)."""
    rows: list = []
    try:
        _wire(wt, data, rows, rows, [], [], n_by_type) if wt in ("SensorSample", "CurrentCommand") else None
        if wt not in ("SensorSample", "CurrentCommand"):
            pr.decode_any(wt, data)
    except _Malformed as e:
        reasons[f"{wt}: {e}"] += 1
    except (ValueError, OverflowError, TypeError, struct.error) as e:
        reasons[f"{wt}: {type(e).__name__}"] += 1
    return [r[0] for r in rows]


def to_rerun(mcap_path: str, rrd_path: str, *, recording_id: str | None = None,
             application_id: str = "ambhil", orbit_window_s: float = 0.02,
             series_window_s: float = 0.2, station_names: list[str] | None = None,
             block: int = 100_000, progress=None) -> dict:
    """Write ``rrd_path`` from an ambhil MCAP, streamed: the file is read chunk by chunk
    (:func:`ambhil.bridge.recording.layout.iter_chunks`) and sent to rerun in columns of at most ``block`` rows
    (``send_columns``), so time and memory stay flat however long the run.  Content: the
    ``sim_time`` timeline (duration); displacement (um) and coil current (A) series per axis;
    an orbit view per AMB station (axis pairs (0,1), (2,3), ...; points in um, +y up, a sliding
    window of ``orbit_window_s``) on one scale for all stations with rings, axes and the station's
    clearance circle; round trip, controller TET and wake lateness each in its own panel (us);
    events as a text log; the blueprint is embedded.  ``progress(done, total)``: bytes read.
    A recording of the earlier layout (wire bytes verbatim) is read whole (:func:`load_run`)."""
    import rerun as rr
    from collections import Counter
    from ambhil.bridge.recording import layout as rc
    from ambhil.bridge.recording.recover import RecordingError, check, truncated_message
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
        chans = _channels(summary) if summary is not None else {}
        legacy = summary is None or any(v[0].startswith("wire:") for v in chans.values())
        meta, run_id = {}, next((v[2].split("/")[1] for v in chans.values()), None)
        if not legacy:
            for cid, (lay, _, key) in chans.items():
                if lay == rc.META:
                    for _, _, m in reader.iter_messages(topics=[summary.channels[cid].topic]):
                        meta = rc.decode_meta(m.data).info
                        break
        else:
            run = load_run(mcap_path, raw=False)
            meta, run_id = run["meta"], run["run_id"]
        n = int(meta.get("n_axes") or 0)
        if not n:
            for cid, (lay, wt, key) in chans.items():
                if lay in (rc.SENSORS, rc.CURRENTS):
                    n = len(rc.axes_of(summary.channels[cid]) or [])
                    break
        if legacy:
            S = run["sensors"]
            n = S["v"].shape[1] if len(S["seq"]) else (run["currents"]["v"].shape[1] if len(run["currents"]["seq"]) else n)
        names = _axis_names(meta, n)
        n_st = n // 2
        stations = station_names or meta.get("station_names") or [f"station_{i}" for i in range(n_st)]
        stations = [str(s).replace("/", "_").replace(" ", "_") for s in stations][:n_st]

        rec = rr.RecordingStream(application_id, recording_id=recording_id or run_id or "replay")
        rec.save(rrd_path)
        sink = _RerunSink(rec, names, stations)
        reasons: Counter = Counter()
        if legacy:
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
        else:
            _stream(f, summary, chans, sink, reasons, block, progress, n)
        sink.finish(meta, orbit_window_s, series_window_s)
        rec.flush()
        rec.disconnect()
    return {"rrd": rrd_path, "samples": sink.samples, "currents": sink.currents,
            "stations": stations, "events": sink.events, "faults_injected": len(sink.injected),
            "orbit_max_m": [float(r) * 1e-6 for r in sink.r_max], "timing_us": sink.timing_stats,
            "rejected": sum(reasons.values()), "rejected_reasons": dict(reasons)}


def _stream(f, summary, chans, sink, reasons, block, progress, n_axes) -> None:
    """The recorded layout, chunk by chunk, into ``sink`` in blocks of about ``block`` rows."""
    from ambhil.bridge.recording import layout as rc
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
            ok = a["step"] < _INT64
            if not ok.all():
                reasons["Timing: step out of range"] += int((~ok).sum())
                a = a[ok]
            sink.timing(rc.stamp_ns(a["sec"], a["nanosec"]) / 1e9,
                        {"rtt": a["rtt"], "tet": a["tet"], "late": a["late"], "flags": a["flags"]})
            return
        wt = rc.WIRE_OF[lay]
        ok = (a["seq"] < _INT64) & (a["step"] < _INT64)
        if not ok.all():
            reasons[f"{wt}: seq or step out of range"] += int((~ok).sum())
            a = a[ok]
        t = rc.stamp_ns(a["sec"], a["nanosec"]) / 1e9
        (sink.sensors if lay == rc.SENSORS else sink.current)(t, np.asarray(a["v"]))

    malformed = []
    for buf, out in rc.iter_chunks(f, summary, progress):
        for cid, (starts, ends, _) in out.items():
            info = chans.get(cid)
            if info is None:
                continue
            lay, wt, _ = info
            if lay in pend:
                a = _gather(buf, lay, starts, ends, info[2])
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
    for wt, data in malformed:
        extra[wt] += _malformed_rows(wt, data, n_by_type, reasons) if wt in extra else (
            _malformed_rows(wt, data, n_by_type, reasons))
    for m in extra["SensorSample"]:
        sink.sensors(np.array([m.sim_time_ns / 1e9]), np.array([m.displacement]))
    for m in extra["CurrentCommand"]:
        sink.current(np.array([m.sim_time_ns / 1e9]), np.array([m.current]))


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
    K = pr.keys(run_id)
    own = session is None
    if own:
        session = tr.open_session(listen, connect)
    q: queue.SimpleQueue = queue.SimpleQueue()
    sub = tr.declare_callback_subscriber(session, K.currents,
                                         lambda s: q.put(s.payload.to_bytes()))
    pub = tr.declare_publisher(session, K.sensors)
    evp = tr.declare_publisher(session, K.events)

    gone = threading.Event()

    def _live(key, alive):
        if key == K.alive_controller and not alive:
            gone.set()
            q.put(None)
    watch = tr.LivelinessWatch(session, K.alive_all, _live)

    class _ControllerState:
        # Pairing.wait's view of the controller: a controller that was ready and went away
        # before announcing (or after withdrawing) its peer id fails the pairing at once
        def state(self, role):
            return GONE if gone.is_set() else None
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
        peer = pairing.wait(_ControllerState(), start_timeout)
        me = pairing.id
        cc.peer = peer                        # replies from anyone else are counted as foreign
        tr.wait_matching(pub, start_timeout, "controller")
        total = len(S["seq"]) if max_steps is None else min(max_steps, len(S["seq"]))
        for i in range(total):
            seq = int(S["seq"][i])
            pub.put(S["raw"][i][:-pr.PEER_LEN] + me)     # sent by the replay, posing as the plant
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
                try:
                    m = cc.decode(data)
                except pr.ForeignError:       # not from the paired controller under test
                    foreign += 1
                    continue
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
    # a sample whose seq has no recorded current is not compared (counted in missing_recorded):
    # the recording lacks the reference, which says nothing against the controller under test
    passed = fault is None and n_cmp > 0 and max_dev <= tolerance
    return {"passed": passed, "max_abs_dev": max_dev, "worst": worst, "tolerance": tolerance,
            "compared": n_cmp, "missing_recorded": n_missing, "sent": n_sent,
            "rejected": rejected, "foreign": foreign, "fault": fault, "wall_s": round(time.perf_counter() - t0, 3)}
