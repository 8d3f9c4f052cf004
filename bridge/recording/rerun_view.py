"""What a run's .rrd shows (:func:`ambhil.bridge.recording.replay.to_rerun`): the entities, filled
block by block (:class:`RerunSink`), and the blueprint that lays them out.

The entities: the ``sim_time`` timeline (duration); displacement (um) and coil current (A) series
per axis; an orbit view per AMB station (axis pairs (0,1), (2,3), ...; points in um, +y up) on
one scale for all stations (:func:`orbit_scale`) with rings, axes, the magnetic gap and the
station's touchdown clearance (:func:`touchdown_clearances`); round trip, controller TET and
wake lateness each in its own panel (us); the scheduled faults active; events as a text log;
the RunMeta as a text document.

Auxiliary-bearing contact (the plant's INFO events ``{"kind": "contact", ...}``,
bridge/process/plant_contact.py): each start and end is a line of the text log (a start as a
warning), and a marker on that bearing's station orbit (``/orbit/<station>/contact/start`` red,
``.../end`` green) at the sensor sample that follows the event: the rotor where the sensors saw it
as it touched down or lifted off, shown while the orbit's time window holds that sample."""
from __future__ import annotations

import json

import numpy as np

from ambhil.bridge import protocol as pr


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


def _fig(x, scale: float, unit: str, fmt: str = ".4g") -> str:
    return "n/a" if x is None else f"{x * scale:{fmt}} {unit}"


def contact_event(ev) -> dict | None:
    """The contact event an Event carries (the plant's INFO ``{"kind": "contact", ...}``), else None."""
    if ev.kind != pr.EventKind.INFO or not ev.text.startswith('{"kind":"contact"'):
        return None
    try:
        d = json.loads(ev.text)
    except ValueError:
        return None
    return d if isinstance(d, dict) and d.get("phase") in ("start", "end") else None


def contact_text(d: dict) -> str:
    """A contact event as a line: 'contact start A at t=56.75 ms, impact 69.4 mm/s' or its end with
    the event's figures."""
    merged = f" ({d['merged']} events within the period)" if (d.get("merged") or 1) > 1 else ""
    head = f"contact {d['phase']} {d.get('bearing')} at t={_fig(d.get('t_s'), 1e3, 'ms')}"
    if d["phase"] == "start":
        return f"{head}, impact {_fig(d.get('v0_m_s'), 1e3, 'mm/s', '.3g')}{merged}"
    return (f"{head} (from {_fig(d.get('start_s'), 1e3, 'ms')}), peak {_fig(d.get('peak_force_N'), 1, 'N')}, "
            f"penetration {_fig(d.get('max_penetration_m'), 1e6, 'um', '.3g')}, impact "
            f"{_fig(d.get('v0_m_s'), 1e3, 'mm/s', '.3g')}, separation {_fig(d.get('v_out_m_s'), 1e3, 'mm/s', '.3g')}, "
            f"restitution {_fig(d.get('restitution'), 1, '', '.3g').strip()}, energy lost "
            f"{_fig(d.get('energy_J'), 1, 'J', '.3g')}{merged}")


def contact_summary_text(text: str) -> str | None:
    """The plant's ``{"contact_summary": ...}`` event as a line per bearing, else None."""
    if not text.startswith('{"contact_summary"'):
        return None
    try:
        b = json.loads(text)["contact_summary"]["bearings"]
        return "contact summary: " + "; ".join(
            f"{k} {v['events']} events, peak {_fig(v.get('peak_force_N'), 1, 'N')}, penetration "
            f"{_fig(v.get('max_penetration_m'), 1e6, 'um', '.3g')}, friction "
            f"{_fig(v.get('friction_energy_J'), 1, 'J', '.3g')}, race {_fig(v.get('race_speed_end'), 1, 'rad/s')}"
            + (", in contact at the end" if v.get("in_contact_at_end") else "") for k, v in b.items())
    except (ValueError, KeyError, TypeError, AttributeError):
        return None


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


class RerunSink:
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
        self.contacts = 0               # contact events (start and end) seen
        self._pending = []              # contact markers awaiting their sensor sample: (t_s, i, phase)
        self._block = None              # the last sensor block: (t_s, [(x, -y) um per station])
        rec.log("/sensors/displacement", rr.SeriesLines(names=[f"{a} (um)" for a in names]), static=True)
        rec.log("/controller/current", rr.SeriesLines(names=[f"{a} (A)" for a in names]), static=True)
        for name, _, title in _TIMING:
            rec.log(f"/timing/{name}", rr.SeriesLines(names=[title]), static=True)

    def sensors(self, t_s, v_m):
        rr = self.rr
        if not len(t_s):
            return
        um = v_m * 1e6
        blk = []
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
            blk.append(pos)
        self.samples += len(t_s)
        self._block = (np.asarray(t_s, dtype=float), blk)
        self._markers(final=False)

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
        c = contact_event(ev)
        if c is not None:
            lvl = "WARN" if c["phase"] == "start" else "INFO"
            self._contact(c, ev.sim_time_ns / 1e9)
        text = contact_text(c) if c is not None else (
            ev.kind == pr.EventKind.INFO and contact_summary_text(ev.text) or _fault_text(ev))
        self.rec.log("/events", rr.TextLog(f"[{ev.source}] {ev.kind_name}: {text}", level=lvl))
        self.events += 1
        if ev.kind == pr.EventKind.FAULT_INJECTED:
            self.injected.append(ev)

    def _contact(self, c: dict, t_event: float) -> None:
        """A contact event's marker, queued for the sensor sample at or after its time."""
        self.contacts += 1
        name = str(c.get("bearing")).replace("/", "_").replace(" ", "_")
        if name in self.stations:
            t = c.get("t_s")
            self._pending.append((t if t is not None else t_event, self.stations.index(name), c["phase"]))
            self._markers(final=False)

    def _markers(self, final: bool) -> None:
        """Log the queued contact markers whose sensor sample is in the last block (``final``: all,
        at the last sample there is)."""
        if not self._pending or self._block is None:
            return
        rr, rec = self.rr, self.rec
        t, blk = self._block
        keep = []
        for te, i, phase in self._pending:
            if not len(t) or (te > t[-1] and not final):
                keep.append((te, i, phase))
                continue
            j = min(int(np.searchsorted(t, te - 1e-12)), len(t) - 1)
            rec.set_time("sim_time", duration=float(t[j]))
            rec.log(f"/orbit/{self.stations[i]}/contact/{phase}", rr.Points2D(
                [blk[i][j]], colors=[(229, 57, 53) if phase == "start" else (67, 160, 71)],
                radii=rr.Radius.ui_points(6.0), labels=["touchdown" if phase == "start" else "lift-off"],
                show_labels=True))
        self._pending = keep

    def finish(self, meta: dict, orbit_window_s: float, series_window_s: float):
        """The static parts, once every row is in: each station's orbit scale (rings, axes, the
        magnetic gap and the touchdown clearance, on one scale for all), the active faults, the
        RunMeta, the blueprint."""
        rr, rrb, rec = self.rr, __import__("rerun.blueprint").blueprint, self.rec
        self._markers(final=True)
        clr = touchdown_clearances(meta, len(self.stations))
        gaps_um = [c for c, _ in clr]                      # the touchdown clearances (um)
        magnetic_um = [g * 1e6 for g in (meta.get("gaps_m") or [])][:len(self.stations)]
        half, step = orbit_scale(float(self.r_max.max()) if len(self.r_max) else 0.0, gaps_um, magnetic_um)
        for i, s in enumerate(self.stations):
            self._orbit_scale(i, s, half, step, clr, magnetic_um)
        if self.injected:   # a step series that marks each fault's start and end (count of active faults)
            self._faults_active()
        if meta:
            rec.log("/meta", rr.TextDocument(json.dumps(meta, indent=1)), static=True)
        rr.send_blueprint(self.blueprint(rrb, half, gaps_um, orbit_window_s, series_window_s),
                          make_active=True, make_default=True, recording=rec)

    def _orbit_scale(self, i: int, s: str, half: float, step: float, clr, magnetic_um) -> None:
        """Station ``s``'s orbit view: rings every ``step`` um up to ``half``, the axes, the
        magnetic gap (where in view) and the touchdown clearance ``clr[i]``, the points' colour."""
        rr, rec = self.rr, self.rec
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
        if i < len(clr):
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

    def _faults_active(self) -> None:
        """A step series of how many scheduled faults are active (each start and end marked)."""
        rr, rec = self.rr, self.rec
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
