"""Rotor drop: convergence of the first bounce with the plant step (the accuracy study's drop section).

Every AMB axis of a linear rung loses its coils at t = 0 (``model_without_axes``: the weight share
each carried becomes the constant force ``f_const = -load``), at the scene's spin speed, from the
operating point at rest, and the rotor falls into its auxiliary bearings.  Per integrator x plant
step the study measures the first contact event of the station that touches first:

* impact time and normal speed (the d = 0 crossing, from the free flight before it: a cubic through
  the last two free steps' d and d');
* peak normal force (the largest step value, refined by the parabola through it and its neighbours);
* contact duration and restitution (the separation crossing, from the free flight after it);
* rebound apex: the largest distance from the race in the free flight after the first event
  (``-min d``, parabola-refined).

The plant has no event location: a contact starts inside a fixed step.  These figures are taken
from the free flight on either side, so what they carry is the integration error of the scheme
and not the step's time quantisation.  The reference of each scheme is its finest step's figure;
the observed order is ``log2`` of successive differences at halved steps (no reference needed);
:func:`point_reference` gives the figures of :func:`ambhil.plant.point_rotor.drop` with a station's
mass (the independent second method: valid when the rotor is symmetric, so that translation
decouples from tilt and each station carries half of it).
"""
from __future__ import annotations

import csv
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ambhil.plant import integrator as ig

FIGURES = ("t_impact", "v_impact", "peak_force", "duration", "restitution", "apex")
UNITS = {"t_impact": "s", "v_impact": "m/s", "peak_force": "N", "duration": "s", "restitution": "",
         "apex": "m"}


def drop_model(model):
    """The model with every AMB axis lost (the drop) and no unbalance run-out in its force constant."""
    from ambhil.plant.faults import model_without_axes
    return model_without_axes(model, range(model.n_axes))


def station_mass(model, j: int = 0) -> float:
    """Mass (kg) the auxiliary-bearing station j carries in a vertical drop of a symmetric rotor:
    equal forces f on every station's y axis give it the acceleration f / m (from Ca M^-1 Ba)."""
    st = stations(model)
    M, _, _, _, Ba, Ca, _ = model.dense
    ys = [ay for _, ay in st]
    acc = np.asarray(Ca)[ys] @ np.linalg.solve(np.asarray(M), np.asarray(Ba)[:, ys] @ np.ones(len(ys)))
    return float(1.0 / acc[j])


def stations(model) -> list[tuple[int, int]]:
    """(x axis, y axis) of each AMB with an auxiliary bearing, in [[amb]] order (the plan's order)."""
    out = []
    for amb in model.spec.ambs:
        if getattr(amb, "auxiliary", None) is None:
            continue
        ix = [k for k, a in enumerate(model.axes) if a[0] == amb.name]
        out.append((ix[0], ix[1]))
    return out


@dataclass
class DropRecord:
    """Per plant step (rows) and station (columns): time, shaft centre, penetration, normal rate,
    normal force; ``energy`` (optional) the mechanical energy of the rotor incl. contact springs."""
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    d: np.ndarray
    dd: np.ndarray
    fn: np.ndarray
    contact: np.ndarray  # (m, NC) at the end
    energy: np.ndarray | None = None
    drive: np.ndarray | None = None  # cumulative work of the drive holding the spin (J)
    fault: str | None = None


def run_drop(model, integrator: str, h: float, t_end: float, speed: float | None = None, *,
             energy: bool = False, stop_after: int | None = 2, v0=None) -> DropRecord:
    """Drop the (already dropped: :func:`drop_model`) model and record every plant step until
    ``t_end`` or until ``stop_after`` contact events have started at some station and the first
    has ended (the first bounce and its rebound are then complete)."""
    from ambhil.plant.run_options import RunOptions
    from ambhil.plant.step import PlantRunner, bound_kernel
    from ambhil.plant.auxiliary_bearing import _elastic_energy
    # the controller period's restarts (bdf2's trapezoidal start, generalised-alpha's rates) as in a
    # run; stepped one plant step at a time so that every step is recorded
    ratio = int(round(model.period / h))
    if ratio < 1 or abs(model.period / h - ratio) > 1e-9 * ratio:
        ratio = 1
    r = PlantRunner(model, RunOptions(integrator=integrator, h=h, speed=speed, v0=v0), period=ratio * h)
    step = bound_kernel(ig.plant_step, r.plan, r.s, r.currents, r.work, r.ws, True)
    st = stations(model)
    n = model.n
    M, D, G, K, Ba, Ca, _ = model.dense
    Ca = np.asarray(Ca)
    f0 = np.asarray(model.f_const if model.f_const is not None else np.zeros(model.n_axes))
    aux = r.plan.aux_p
    W = float(r.plan.fp[ig.F_W0])
    cur = r.currents
    N = int(round(t_end / h))
    rows = np.empty((N + 1, 5, len(st)))
    E = np.empty(N + 1) if energy else None
    Wd = np.zeros(N + 1) if energy else None

    def sample(k):
        c = r.contact
        q, v = r.s[:n], r.s[n:2 * n]
        for j, (ax, ay) in enumerate(st):
            xs, ys = c[j, ig.C_X], c[j, ig.C_Y]
            vx, vy = Ca[ax] @ v, Ca[ay] @ v
            rr = math.hypot(xs, ys)
            rows[k, :, j] = xs, ys, c[j, ig.C_D], (xs * vx + ys * vy) / rr if rr > 0 else 0.0, c[j, ig.C_FN]
        if energy:
            E[k] = 0.5 * v @ (M @ v) + 0.5 * q @ (K @ q) - f0 @ (Ca @ q) + sum(
                _elastic_energy(c[j, ig.C_D], aux[j]) for j in range(len(st)))
            if k:  # the drive's work against the friction torque, booked like C_EF (step-end value x h)
                Wd[k] = Wd[k - 1] - h * W * sum(c[j, ig.C_TQ] for j in range(len(st)))
    sample(0)
    k = 0
    while k < N:
        step(r.plan, r.s, cur, r.work, r.ws, k % ratio == 0)
        k += 1
        sample(k)
        if r.fault:
            break
        if stop_after is not None:
            c = r.contact
            if np.any(c[:, ig.C_NEV] >= stop_after) and np.any(c[:, ig.C_TE] >= 0):
                break
    t = np.arange(k + 1) * h
    rw = rows[:k + 1]
    return DropRecord(t, rw[:, 0], rw[:, 1], rw[:, 2], rw[:, 3], rw[:, 4], r.contact.copy(),
                      None if E is None else E[:k + 1], None if Wd is None else Wd[:k + 1], r.fault)


def _cubic_root(t0, h, d0, d1, v0, v1, lo=0.0, hi=1.0):
    """Root (time) and slope of the cubic Hermite through (t0: d0, v0), (t0 + h: d1, v1), the root at
    s = (t - t0)/h in [lo, hi] (an extrapolation when outside [0, 1])."""
    # d(s) = a s^3 + b s^2 + c s + e on s in [0, 1], derivative in units of h
    e, c = d0, v0 * h
    a = 2 * d0 - 2 * d1 + (v0 + v1) * h
    b = -3 * d0 + 3 * d1 - (2 * v0 + v1) * h
    roots = np.roots([a, b, c, e]) if abs(a) > 0 else np.roots([b, c, e])
    real = [float(x.real) for x in roots if abs(x.imag) < 1e-9 * max(1.0, abs(x)) and lo - 1e-9 <= x.real <= hi + 1e-9]
    s = min(real, key=lambda x: abs(x - 0.5 * (lo + hi))) if real else -d0 / (d1 - d0)
    return t0 + s * h, (3 * a * s * s + 2 * b * s + c) / h


def _parabola_peak(t, f, k):
    """Vertex value of the parabola through samples k-1, k, k+1 (the sample itself at an end)."""
    if k <= 0 or k >= len(f) - 1:
        return float(f[k])
    a, b, c = f[k - 1], f[k], f[k + 1]
    den = a - 2 * b + c
    if den >= 0:
        return float(b)
    return float(b - 0.125 * (c - a) ** 2 / den)


def first_bounce(rec: DropRecord, j: int | None = None) -> dict:
    """The first contact event's figures (FIGURES) at station j (default: the first to touch)."""
    d, dd, fn, t = rec.d, rec.dd, rec.fn, rec.t
    h = float(t[1] - t[0])
    touched = [int(np.argmax(d[:, s] > 0)) if np.any(d[:, s] > 0) else None for s in range(d.shape[1])]
    if j is None:
        cand = [(k, s) for s, k in enumerate(touched) if k is not None]
        if not cand:
            return {f: math.nan for f in FIGURES} | {"station": -1}
        j = min(cand)[1]
    out = {f: math.nan for f in FIGURES} | {"station": j}
    ks = touched[j]
    if ks is None or ks < 1:
        return out
    dj, vj, fj = d[:, j], dd[:, j], fn[:, j]
    # the free flight before: Hermite through the last free step (ks-1) and the one before it,
    # extrapolated to the crossing
    kb = max(ks - 2, 0)
    ts, vs = _cubic_root(t[kb], h, dj[kb], dj[kb + 1], vj[kb], vj[kb + 1], 1.0, 2.0) if ks >= 2 else \
        _cubic_root(t[ks - 1], h, dj[ks - 1], dj[ks], vj[ks - 1], vj[ks])
    out["t_impact"], out["v_impact"] = ts, vs
    after = np.nonzero(dj[ks:] <= 0)[0]
    ke = ks + int(after[0]) if after.size else None
    kp = ks + int(np.argmax(fj[ks:ke]))
    out["peak_force"] = _parabola_peak(t, fj, kp)
    if ke is None or ke + 1 >= len(t) or dj[ke + 1] > 0:
        return out
    # the free flight after: Hermite through the first two free steps, extrapolated back
    te, ve = _cubic_root(t[ke], h, dj[ke], dj[ke + 1], vj[ke], vj[ke + 1], -1.0, 0.0)
    out["duration"] = te - ts
    out["restitution"] = -ve / vs if vs > 0 else math.nan
    nxt = np.nonzero(dj[ke:] > 0)[0]
    kn = ke + int(nxt[0]) if nxt.size else len(t)
    ka = ke + int(np.argmin(dj[ke:kn]))
    if ka < kn - 1 and ka > ke:  # the apex inside the free flight, not at the end of the record
        out["apex"] = _parabola_peak(t, -dj, ka)
    return out


def point_reference(model, j: int = 0, speed: float = 0.0, t_end: float | None = None, rtol: float = 1e-10) -> dict:
    """The same figures from the point (Jeffcott) rotor with station j's mass and weight share
    (the independent second method: plant/point_rotor.py, event-located, adaptive)."""
    from ambhil.plant.point_rotor import PointRotor, drop, Y
    st = stations(model)
    ax, ay = st[j]
    b = next(a.auxiliary for a in model.spec.ambs if a.name == model.axes[ax][0])
    m = station_mass(model, j)
    g = -float(model.f_const[ay]) / m
    c = b.clearance
    x0 = (float(model.x_op[ax]), float(model.x_op[ay]), 0.0, 0.0)
    t_end = t_end or 6 * math.sqrt(2 * c / g)
    res = drop(PointRotor(mass=m, bearing=b, gravity=g, spin=speed), t_end, x0=x0, rtol=rtol)
    ev = res.events[0]
    out = dict(t_impact=ev.start, v_impact=ev.v0, peak_force=ev.peak_force, duration=ev.end - ev.start,
               restitution=ev.restitution, apex=math.nan, station=j, mass=m, gravity=g)
    if len(res.events) > 1 or math.isfinite(ev.end):
        t2 = res.events[1].start if len(res.events) > 1 else float(res.t[-1])
        tt = np.linspace(ev.end, t2, 20001)
        out["apex"] = float(-np.min(res.penetration(res.sample(tt))))
    return out


@dataclass
class DropRow:
    rung: str
    integrator: str
    h: float
    figure: str
    value: float
    reference: float
    error: float  # value - reference (the reference: the finest step of this integrator)
    order: float = float("nan")  # log2 of successive differences at halved steps (the two coarsest pairs' last)
    point_rotor: float = float("nan")  # the point rotor's figure with the station mass (symmetric rotors)


def _task(model, rung, integ, h, t_end, speed):
    rec = run_drop(model, integ, h, t_end, speed)
    return rung, integ, h, first_bounce(rec), rec.fault


def drop_convergence(system, schemes=("bdf1", "bdf2", "trapezoidal", "generalized-alpha"), steps=None, *,
                     rung: str | None = None, speed: float | None = None, client=None, point: bool = True,
                     progress=None) -> tuple[list[DropRow], dict]:
    """Per scheme x plant step the first bounce's figures, their errors against the finest step's and
    the observed order; the grid runs as tasks on the Dask ``client`` (default: in-process, as the
    accuracy study).  ``steps`` default: the scene's step and three halvings.  ``zoh`` is left out
    (refused with auxiliary bearings)."""
    model = drop_model(system)
    if not stations(model):
        raise ValueError(f"{system.spec.path}: no [[amb]] has an auxiliary bearing: no rotor drop to study")
    rung = rung or system.rung
    h0 = float(system.spec.simulation.step or system.period)
    steps = tuple(sorted(steps or (h0, h0 / 2, h0 / 4, h0 / 8), reverse=True))
    schemes = tuple(s for s in schemes if s != "zoh")
    W = float(speed if speed is not None else (system.spec.speed.value or 0.0))
    g = -float(np.min(model.f_const))
    if not g > 0:
        raise ValueError(f"{system.spec.path}: [model] gravity is 0: the rotor does not fall when its AMBs let go "
                         "(no rotor drop to study)")
    c = max(a.auxiliary.clearance for a in model.spec.ambs if a.auxiliary is not None)
    t_end = 8 * math.sqrt(2 * c / max(g / station_mass(model), 1e-9)) + 0.02
    own = client is None
    if own:
        from .timing_study import client_for
        client = client_for()
    try:
        mf = client.scatter(model, broadcast=True)
        futs = [client.submit(_task, mf, rung, s, h, t_end, W, pure=False) for s in schemes for h in steps]
        from dask.distributed import as_completed
        res = {}
        for f in as_completed(futs):
            rg, s, h, fig, fault = f.result()
            res[(s, h)] = (fig, fault)
            if progress:
                progress(s, h)
    finally:
        if own:
            client.close()
    st0 = res[(schemes[0], steps[-1])][0]["station"]
    ref_pt = point_reference(model, st0, W) if point and st0 >= 0 else {}
    rows, faults = [], {}
    for s in schemes:
        for fgr in FIGURES:
            vals = [res[(s, h)][0][fgr] for h in steps]
            order = math.nan
            if len(steps) >= 3 and abs(steps[0] / steps[1] - 2) < 1e-9:
                d1, d2 = abs(vals[-3] - vals[-2]), abs(vals[-2] - vals[-1])
                if d1 > 0 and d2 > 0:
                    order = math.log2(d1 / d2)
            for h, v in zip(steps, vals):
                rows.append(DropRow(rung, s, h, fgr, v, vals[-1], v - vals[-1], order, ref_pt.get(fgr, math.nan)))
        faults.update({f"{s} h={h:g}": res[(s, h)][1] for h in steps if res[(s, h)][1]})
    info = dict(rung=rung, speed=W, steps=list(steps), schemes=list(schemes), faults=faults,
                point_rotor={k: v for k, v in ref_pt.items()}, t_end=t_end)
    return rows, info


def table(rows: list[DropRow], info: dict) -> str:
    """The drop section of the study as text: one line per integrator x step, the figures' errors."""
    rows = [r if isinstance(r, DropRow) else DropRow(**r) for r in rows]
    pr = info.get("point_rotor") or {}
    lines = [f"rotor drop ({info['rung']} rung, every AMB axis lost at t = 0, {info['speed']:.4g} rad/s): "
             "first bounce, relative error against the finest step of each integrator"]
    if pr:
        lines.append("  point rotor (station mass {:.4g} kg): ".format(pr.get("mass", math.nan)) + ", ".join(
            f"{f} {pr[f]:.6g}{(' ' + UNITS[f]) if UNITS[f] else ''}" for f in FIGURES if f in pr))
    head = f"  {'integrator':17} {'h (s)':>8} " + " ".join(f"{f:>12}" for f in FIGURES)
    lines += [head]
    by = {}
    for r in rows:
        by.setdefault((r.integrator, r.h), {})[r.figure] = r
    for (s, h), d in by.items():
        lines.append(f"  {s:17} {h:8.3g} " + " ".join(
            f"{d[f].error / abs(d[f].reference) if d[f].reference else d[f].error:+12.2e}" for f in FIGURES))
    orders = {}
    for r in rows:
        orders.setdefault(r.integrator, {})[r.figure] = r.order
    lines.append("  observed order (log2 of successive differences, finest steps):")
    for s, d in orders.items():
        lines.append(f"  {s:17} {'':8} " + " ".join(f"{d[f]:12.2f}" for f in FIGURES))
    if pr:
        lines.append("  finest step against the point rotor (the same physics only for a symmetric rotor without "
                     "unbalance):")
        for s in orders:
            fin = {r.figure: r for r in rows if r.integrator == s and r.h == min(info["steps"])}
            lines.append(f"  {s:17} {min(info['steps']):8.3g} " + " ".join(
                f"{(fin[f].value - fin[f].point_rotor) / abs(fin[f].point_rotor):+12.2e}" for f in FIGURES))
    for k, v in (info.get("faults") or {}).items():
        lines.append(f"  fault {k}: {v}")
    return "\n".join(lines)


def save(rows: list[DropRow], info: dict, out_dir) -> list[Path]:
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    with open(d / "drop.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(asdict(rows[0]).keys()))
        w.writeheader()
        for r in rows:
            w.writerow(asdict(r))
    (d / "drop.txt").write_text(table(rows, info) + "\n")
    return [d / "drop.csv", d / "drop.txt"]


def orbit_whirl(rec: DropRecord, spin: float, j: int = 0, revolutions: int = 3) -> dict:
    """Whirl of station j over the last ``revolutions`` orbit revolutions of the record, as
    :func:`ambhil.plant.point_rotor.whirl` does it: frequency (rad/s, signed, + counter-clockwise)
    from the unwrapped orbit angle, direction against the spin, full clearance when d >= 0 over
    the last whirl period."""
    phi = np.unwrap(np.arctan2(rec.y[:, j], rec.x[:, j]))
    t = rec.t
    i0 = np.nonzero(np.abs(phi[-1] - phi) >= 2 * math.pi * revolutions)[0]
    i0 = int(i0[-1]) if i0.size else 0
    freq = float((phi[-1] - phi[i0]) / (t[-1] - t[i0]))
    turned = abs(phi[-1] - phi[i0]) >= 2 * math.pi
    full = bool(turned and freq != 0 and np.all(rec.d[t >= t[-1] - 2 * math.pi / abs(freq), j] >= 0.0))
    direction = 0 if not turned else (1 if freq * spin > 0 else -1)
    name = "no full-clearance whirl" if not full else ("backward whirl" if direction < 0 else "forward whirl")
    return dict(direction=direction, frequency=freq, ratio=freq / spin if spin else math.nan, full_clearance=full,
                name=name)
