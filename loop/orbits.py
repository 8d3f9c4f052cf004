"""What a simulated run's orbits and times say: steady-state harmonic fits, orbit metrics (settle
time, steady radius), the largest orbits against the touchdown clearance (over the run, and per
stretch between fault events and run-up ends), and the windows of the scheduled faults."""
from __future__ import annotations

import math

import numpy as np

from .sim_result import SimResult


def harmonic(t, x, w, t_from: float | None = None) -> complex:
    """Complex amplitude X of x(t) ~ Re(X e^{i w t}) + c, least squares over t >= t_from
    (default: the last half), trimmed to whole periods."""
    t = np.asarray(t); x = np.asarray(x)
    t_from = t[len(t) // 2] if t_from is None else t_from
    T = 2 * np.pi / w
    tend = t[-1]
    nper = math.floor((tend - t_from) / T)
    if nper >= 1:
        t_from = tend - nper * T
    m = t >= t_from - 1e-12
    A = np.column_stack([np.cos(w * t[m]), np.sin(w * t[m]), np.ones(m.sum())])
    a, b, _ = np.linalg.lstsq(A, x[m], rcond=None)[0]
    return complex(a, -b)


def orbit_metrics(t, x, y, w, band: float = 0.05, tail: float = 0.2) -> dict:
    """Steady orbit radius (mean radius over the last `tail` fraction, whole revolutions) and
    settle time: start of the first revolution after which every revolution's peak radius stays
    within +-band of the steady radius."""
    t = np.asarray(t); r = np.hypot(x, y)
    T = 2 * np.pi / w if w > 0 else (t[-1] - t[0]) / 50
    edges = np.arange(t[0], t[-1] + 1e-12, T)
    if len(edges) < 3:
        return dict(radius=float(np.mean(r)), settle_time=float("nan"), peak=float(np.max(r)))
    idx = np.searchsorted(t, edges)
    peaks = np.array([r[a:b].max() for a, b in zip(idx[:-1], idx[1:]) if b > a])
    starts = edges[:len(peaks)]
    ntail = max(2, int(len(peaks) * tail))
    steady = float(np.mean(peaks[-ntail:]))
    bad = np.where(np.abs(peaks - steady) > band * steady)[0]
    settle = float(starts[bad[-1] + 1]) if len(bad) and bad[-1] + 1 < len(starts) else (
        float(starts[0]) if not len(bad) else float("nan"))
    return dict(radius=steady, settle_time=settle, peak=float(np.max(r)))


def touchdown_orbits(res: SimResult, ambs) -> list[dict]:
    """The largest orbit radius over the run at each AMB whose node is an output node, against
    that AMB's touchdown clearance (``RadialAMB.clearance``): the figure a fault campaign judges
    (``ambhil.loop.campaign``) and ``ambhil run`` prints."""
    out = []
    for a in ambs:
        if a.node + 1 in res.nodes:
            j = res.nodes.index(a.node + 1)
            r = np.hypot(res.orbit[:, j, 0], res.orbit[:, j, 1])
            r = float(np.nanmax(r)) if np.isfinite(r).any() else float("nan")
            out.append({"amb": a.name, "node": a.node + 1, "largest_radius_m": r, "touchdown_clearance_m": a.clearance,
                        "touchdown_clearance_given": a.touchdown_clearance is not None,
                        "fraction_of_touchdown_clearance": r / a.clearance})
    return out


def orbit_segments(res: SimResult, stations) -> list[dict]:
    """The largest orbit per AMB between the instants where the run changes: each scheduled
    fault's start and end, and a run-up's ramp start and end (:func:`time_marks`).  ``stations``:
    ``(AMB name, 1-based node, touchdown clearance m)`` of the AMBs at output nodes.  Each segment:
    ``{start_s, end_s, faults (labels of the faults active), speed_rad_s (None on the ramp),
    run_up (W0, W1) on the ramp, orbits: [{amb, node, largest_radius_m, fraction_of_touchdown_clearance,
    at_s, speed_rad_s}]}``.  A run without faults or run-up is one segment."""
    t = np.asarray(res.t)
    if not len(t):
        return []
    t_end = float(t[-1])
    marks = time_marks(res)
    cuts = sorted({0.0, t_end} | {v for m in marks for v in (m["start_s"], m["end_s"])
                                  if v is not None and 0.0 < v < t_end})
    ru = res.meta.get("run_up")
    out = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        sel = (t >= a - 1e-12) & ((t < b - 1e-12) if b < t_end else (t <= b))
        if not sel.any():
            continue
        mid = 0.5 * (a + b)
        seg = {"start_s": a, "end_s": b,
               "faults": [m["label"] for m in marks if m["kind"] == "fault"
                          and m["start_s"] <= mid < (m["end_s"] if m["end_s"] is not None else np.inf)],
               "speed_rad_s": None, "run_up": None, "orbits": []}
        if ru and ru[2] <= mid < ru[3]:
            seg["run_up"] = [float(ru[0]), float(ru[1])]
        else:
            seg["speed_rad_s"] = float(np.asarray(res.speed)[sel][0]) if len(res.speed) else None
        idx = np.where(sel)[0]
        for name, nd, clr in stations:
            if nd not in res.nodes:
                continue
            j = res.nodes.index(nd)
            r = np.hypot(res.orbit[idx, j, 0], res.orbit[idx, j, 1])
            ok = np.isfinite(r)
            k = idx[ok][int(np.argmax(r[ok]))] if ok.any() else None
            big = float(np.max(r[ok])) if ok.any() else float("nan")
            seg["orbits"].append({"amb": name, "node": nd, "largest_radius_m": big,
                                  "fraction_of_touchdown_clearance": big / clr if clr else float("nan"),
                                  "at_s": float(t[k]) if k is not None else None,
                                  "speed_rad_s": float(res.speed[k]) if k is not None and len(res.speed) else None})
        out.append(seg)
    return out


def steady_at_end(res: SimResult, stations, start_s: float) -> list[dict]:
    """Steady orbit and settle time per AMB over ``[start_s, end]`` (:func:`orbit_metrics` at the
    final speed): how a run settles after its last fault event or its run-up.  Empty where the
    speed varies there or the stretch is shorter than three revolutions."""
    t = np.asarray(res.t)
    sel = t >= start_s - 1e-12
    w = float(res.speed[-1]) if len(res.speed) else 0.0
    if not w > 0 or sel.sum() < 3 or not np.allclose(res.speed[sel], w, rtol=1e-9) \
            or (t[-1] - start_s) < 3 * 2 * np.pi / w:
        return []
    out = []
    for name, nd, _ in stations:
        if nd not in res.nodes:
            continue
        j = res.nodes.index(nd)
        met = orbit_metrics(t[sel], res.orbit[sel, j, 0], res.orbit[sel, j, 1], w)
        out.append({"amb": name, "node": nd, "radius_m": met["radius"], "settle_time_s": met["settle_time"],
                    "from_s": float(start_s), "speed_rad_s": w})
    return out


def fault_windows(events, t_end: float | None = None) -> list[dict]:
    """Each scheduled fault's window from ``SimResult.events`` (its start and end events paired
    by the fault's index): ``{index, kind, axis, label, start_s, end_s}``, ``end_s`` None for a
    fault still active at the end of the run (``t_end``, if given, is then its ``until_s``)."""
    out: dict = {}
    for e in events or ():
        k = e.get("index", (e["kind"], e.get("axis")))
        w = out.setdefault(k, {"index": k, "kind": e["kind"], "axis": e.get("axis"), "start_s": None, "end_s": None,
                               "label": e["kind"] + (f" {e['axis']}" if e.get("axis") else "")})
        w["start_s" if e["phase"] == "start" else "end_s"] = float(e["t_s"])
    wins = [w for w in out.values() if w["start_s"] is not None]
    for w in wins:
        w["until_s"] = w["end_s"] if w["end_s"] is not None else t_end
    return sorted(wins, key=lambda w: (w["start_s"], str(w["index"])))


def time_marks(res: SimResult) -> list[dict]:
    """What the time plots mark: every fault's window (from ``res.events`` or the saved meta's
    ``fault_events``) and a run-up's ramp, ``{label, start_s, end_s, kind}`` (end None: to the end)."""
    t_end = float(res.t[-1]) if len(res.t) else None
    marks = [dict(w, kind="fault") for w in fault_windows(res.events or res.meta.get("fault_events"), t_end)]
    ru = res.meta.get("run_up")
    if ru:
        marks.append({"label": "run-up", "start_s": float(ru[2]), "end_s": float(ru[3]), "kind": "run-up"})
    return marks

