"""Speed-vs-accuracy study of the time-domain plant: integrator x plant step x model rung.

Reference: the exact sampled-data loop of the full FE rung (``zoh`` integrator: matrix
exponential, exact for the held currents and the harmonic unbalance), at the scene's controller
rate.  For each configuration the study reports, at one output node and one spin speed:

* orbit amplitude error (relative) and phase error (rad) of the steady unbalance orbit, and both
  in one: the complex error ``|X - X_ref| / |X_ref|`` (for small errors
  sqrt(amplitude error^2 + phase error^2); the Pareto figure's error axis);
* critical-speed peak location error: stepped-speed runs around the modal rung's first critical,
  the range extended while the largest amplitude sits at its end, the peak then refined by a
  bounded scalar search (``_peak``); a peak still at the edge is reported as such (``peak_note``);
* settle-time error (orbit radius within 5 % of steady, see orbits.orbit_metrics);
* cost: microseconds per plant step and per controller period, real-time factor;
* the sampled loop as simulated (eigenvalues of its one-period map, numerics.sampled_loop):
  growth rate of the dominant mode (> 0: the loop is unstable, the orbit errors are then
  meaningless) and the least-damped mode above ``hf_min_hz`` (the high-frequency flexible mode
  that sampling and lags destabilise), with their errors against the reference, and the
  numerics_warning label when the scheme misreports that mode (numerical damping or error).

Between rungs, ``info["loop_rungs"]`` compares each rung's exact (zoh) sampled loop with the full
rung's: the dominant growth rate and the high-frequency least-damped mode.

The convergence order of each scheme (per rung) is the slope of log(amplitude error against
that rung's own zoh reference) over the two finest steps.

A scene with auxiliary bearings and gravity adds the rotor drop (loop/study_drop.py): per linear
rung, integrator and plant step (the scene's step and three halvings: a contact needs a finer
step than the orbit), the first bounce's figures against the finest step's, with the observed
order; ``info["drop"]``, a section of the table and drop.csv.
"""
from __future__ import annotations

import csv
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .numerics import STABILITY_TOL, match_mode, numerics_warning, sampled_loop
from .orbits import harmonic, orbit_metrics
from .simulation import simulate
from .scene import load_scene
from .system import compile_system


@dataclass
class Row:
    rung: str
    integrator: str
    h: float
    amp_err: float
    phase_err: float
    peak_err: float  # rad/s
    settle_err: float  # s
    us_per_step: float
    us_per_period: float
    rtf: float
    order: float = float("nan")
    loop_growth: float = float("nan")  # 1/s, dominant mode of the simulated sampled loop
    loop_freq: float = float("nan")  # Hz
    hf_freq: float = float("nan")  # Hz, least-damped mode above hf_min_hz
    hf_rate: float = float("nan")  # 1/s, its Re s (> 0 grows)
    loop_growth_err: float = float("nan")  # 1/s, against the reference (full rung, zoh)
    hf_rate_err: float = float("nan")  # relative, against the reference
    numerics: str = ""  # numerics_warning line, if any
    peak_note: str = ""  # set when the peak search ended at the edge of its range
    cplx_err: float = float("nan")  # |X - X_ref| / |X_ref|: amplitude and phase in one


#: a rung's mode is the reference's high-frequency mode when its frequency is within this fraction
#: (the 5 % the rungs are held to, docs/time_domain.md 10.3)
HF_MATCH = 0.05


def zero_rate(g: float, period: float) -> float:
    """A growth rate (1/s) that is zero within the eigenvalue accuracy (STABILITY_TOL per period:
    a neutral mode, e.g. a free rigid-body or integrator pole at mu = 1) as exactly 0.0."""
    return 0.0 if np.isfinite(g) and abs(g) * period <= STABILITY_TOL else float(g)


def _hf(lm, k) -> dict:
    sk = lm.s[k] if k is not None else complex(np.nan, np.nan)
    return dict(hf_freq=abs(sk.imag) / (2 * np.pi), hf_rate=float(sk.real),
                hf_zeta=float(-sk.real / abs(sk)) if k is not None else float("nan"))


def loop_summary(lm, hf_min_hz: float = 200.0, k: int | None | str = "least") -> dict:
    """Dominant growth rate (0 when neutral within roundoff) and a high-frequency mode of a
    sampled loop (LoopModes): mode ``k`` (None: no such mode, its figures NaN), by default the
    least-damped mode above hf_min_hz."""
    if isinstance(k, str):
        k = lm.least_damped(hf_min_hz)
    return dict(growth=zero_rate(lm.growth_rate, lm.period), freq=lm.frequency_hz, stable=lm.stable, hf_index=k,
                **_hf(lm, k))


def rung_hf_mode(ex, ref_s: complex) -> int | None:
    """Index of a rung's exact-loop mode that is the reference's high-frequency mode ``ref_s``: the
    nearest eigenvalue (upper half plane, not on the negative real axis of mu, i.e. not a Nyquist
    alternation) whose frequency is within HF_MATCH of it; None when the rung has no such mode (a
    rigid rung has no flexible modes)."""
    s = ex.s
    ok = (s.imag > 1e-6) & np.isfinite(s.real) & ~((np.abs(ex.mu.imag) <= 1e-12 * np.abs(ex.mu)) & (ex.mu.real < 0))
    idx = np.where(ok & (np.abs(s.imag - ref_s.imag) <= HF_MATCH * abs(ref_s.imag)))[0]
    if not len(idx) or not np.isfinite(ref_s.imag):
        return None
    return int(idx[np.argmin(np.abs(s[idx] - ref_s))])


def _run(m, W, integ, h, node, duration):
    r = simulate(m, duration, W, integrator=integ, h=h, nodes=[node])
    x = r.orbit[:, 0]
    X = harmonic(r.t, x[:, 0], W)
    met = orbit_metrics(r.t, x[:, 0], x[:, 1], W)
    return X, met, r


def _peak(m, speeds, integ, h, node, duration, extend: int = 12) -> tuple[float, str]:
    """Speed of the largest steady orbit amplitude, and a note ("" when found inside the range).

    The amplitude is evaluated on ``speeds``; while the largest sits at an end of the samples, the
    range grows by one spacing on that side (at most ``extend`` times, and not below 0), so a peak
    outside the first window is followed rather than clipped.  The bracketing samples around the
    largest are then searched by a bounded scalar maximisation.  The note says "at the edge" when the
    peak was still at an end after the extensions (the value is then a bound, not a peak)."""
    from scipy.optimize import minimize_scalar
    amp = lambda W: abs(_run(m, W, integ, h, node, duration)[0])
    sp = [float(v) for v in speeds]
    A = [amp(W) for W in sp]
    d = sp[1] - sp[0]
    for _ in range(extend):
        k = int(np.argmax(A))
        if k == 0 and sp[0] - d > 0:
            sp.insert(0, sp[0] - d); A.insert(0, amp(sp[0]))
        elif k == len(sp) - 1:
            sp.append(sp[-1] + d); A.append(amp(sp[-1]))
        else:
            break
    k = int(np.argmax(A))
    if k == 0 or k == len(sp) - 1:
        return float(sp[k]), f"peak at the edge of {sp[0]:.1f}..{sp[-1]:.1f} rad/s: a bound, not a peak"
    r = minimize_scalar(lambda W: -amp(W), bounds=(sp[k - 1], sp[k + 1]), method="bounded",
                        options={"xatol": 1e-5 * sp[k]})
    return (float(r.x), "") if -r.fun >= A[k] else (float(sp[k]), "")


#: timed runs per configuration (after one untimed warm-up run); the cost is their median
TIMING_REPEATS = 3


def _cost(m, W, integ, h, node, duration, repeats: int = TIMING_REPEATS) -> tuple[float, float]:
    """(us per controller period, real-time factor) of the fused loop: one untimed warm-up run
    first (numba dispatch and cache loading, first-touch memory: otherwise the first configuration
    timed in a process pays them), then the median of ``repeats`` timed runs of ``duration``."""
    simulate(m, duration, W, integrator=integ, h=h, nodes=[node])  # warm-up, not timed
    runs = [simulate(m, duration, W, integrator=integ, h=h, nodes=[node]) for _ in range(repeats)]
    us = float(np.median([r.us_per_period for r in runs]))
    rtf = float(np.median([r.real_time_factor for r in runs]))
    return us, rtf


_RUNG_MODELS: dict = {}


def _rung_model(scene, rung: str):
    import hashlib
    import pickle
    key = (hashlib.sha1(pickle.dumps(scene)).hexdigest(), rung)
    if key not in _RUNG_MODELS:
        _RUNG_MODELS[key] = compile_system(scene, rung)
    return _RUNG_MODELS[key]


def _series(scene, rung: str, integ: str, ratios: tuple[int, ...], rung_ref, refs: dict) -> list["Row"]:
    """One integrator on one rung over the step ratios (a Dask task)."""
    if rung == "ancf":
        from ambhil.plant.dae_integrator import SCHEMES as ANCF_SCHEMES
        if integ not in ANCF_SCHEMES:
            return []  # the ancf rung integrates with bdf1 and generalized-alpha only
    m = _rung_model(scene, rung)
    Xown, ex, k_hf = rung_ref
    W, Tc, node, duration, span = refs["W"], refs["Tc"], refs["node"], refs["duration"], refs["span"]
    Xr, mr, lref = refs["Xr"], refs["mr"], refs["lref"]
    rows, own_err = [], []
    for r in ratios:
        h = Tc / r
        X, met, res = _run(m, W, integ, h, node, duration)
        us, rtf = _cost(m, W, integ, h, node, refs.get("timing_duration", min(duration, 0.1)))
        pk, pk_note = _peak(m, span, integ, h, node, duration)
        lm = sampled_loop(m, integ, h, speed=W, vectors=True, response=True)
        # the row's high-frequency mode: the one that is the reference's (via this rung's exact loop)
        ls = loop_summary(lm, k=None if k_hf is None else match_mode(lm, ex, k_hf, m.n))
        warn = numerics_warning(m, integ, h, speed=W, loop=lm, exact=ex) or ""
        rows.append(Row(rung, integ, h, abs(abs(X) / abs(Xr) - 1), float(abs(np.angle(X / Xr))),
                        pk - refs["peak_ref"], met["settle_time"] - mr["settle_time"],
                        us / r, us, rtf,
                        loop_growth=ls["growth"], loop_freq=ls["freq"], hf_freq=ls["hf_freq"], hf_rate=ls["hf_rate"],
                        loop_growth_err=zero_rate(ls["growth"] - lref["growth"], Tc),
                        hf_rate_err=(ls["hf_rate"] - lref["hf_rate"]) / abs(lref["hf_rate"]), numerics=warn,
                        peak_note=pk_note, cplx_err=float(abs(X / Xr - 1))))
        own_err.append(abs(X - Xown) / abs(Xown))
    if len(ratios) >= 2 and own_err[-1] > 0 and own_err[-2] > 0:
        order = math.log(own_err[-2] / own_err[-1]) / math.log(ratios[-1] / ratios[-2])
        for row in rows:
            row.order = order
    return rows


def accuracy(scene, rungs=("rigid", "modal", "full"), integrators=("bdf1", "bdf2", "trapezoidal", "generalized-alpha"),
             ratios=(1, 2, 4), node: int | None = None, speed: float | None = None, duration: float = 0.5,
             peak_points: int = 7, progress=None, hf_min_hz: float = 200.0, client=None) -> tuple[list[Row], dict]:
    """The study; the (rung, integrator) series run as tasks on the Dask ``client`` (default: an
    in-process cluster, so that the cost figures are not taken under contention)."""
    from .analysis import modal
    # the orbit study is of the levitated rotor (its steady orbit never reaches an auxiliary bearing,
    # and the exact zoh reference has no contact): its models leave the auxiliary bearings out; the
    # drop section below compiles them with
    scene = scene if hasattr(scene, "plant") else load_scene(scene)
    with_aux, scene = scene, _without_auxiliary(scene)
    full = compile_system(scene, "full")
    Tc = 1.0 / full.scene.controller.sample_rate
    node = node or (full.spec.ambs[0].node + 1)
    crit = modal.critical_speeds(compile_system(scene, "modal"), count=1)
    Wc = crit[0].speed if crit else 300.0
    W = speed or Wc
    Xr, mr, _ = _run(full, W, "zoh", Tc, node, duration)
    span = np.linspace(0.9 * Wc, 1.1 * Wc, peak_points)
    peak_ref, peak_ref_note = _peak(full, span, "zoh", Tc, node, duration)
    rows: list[Row] = []
    ex_full = sampled_loop(full, "zoh", Tc, speed=W, vectors=True, response=True)
    lref = loop_summary(ex_full, hf_min_hz)
    ref_s = ex_full.s[lref["hf_index"]] if lref["hf_index"] is not None else complex(np.nan, np.nan)
    info = dict(speed=W, node=node, critical_speed_fd=Wc, peak_ref=peak_ref, amp_ref=abs(Xr),
                settle_ref=mr["settle_time"], controller_period=Tc, peak_ref_note=peak_ref_note, loop_ref=lref, loop_rungs={}, hf_min_hz=hf_min_hz)
    rung_refs = {}
    for rung in rungs:
        m = full if rung == "full" else compile_system(scene, rung, rotor=full.rotor)
        if rung == "ancf":
            # no exact (zoh) form of the nonlinear DAE: its own reference is the full rung's exact
            # loop, which is its small-motion linearisation (docs/ancf.md); so are its loop figures
            Xown, ex = Xr, ex_full
        else:
            Xown = _run(m, W, "zoh", Tc, node, duration)[0]
            ex = ex_full if rung == "full" else sampled_loop(m, "zoh", Tc, speed=W, vectors=True, response=True)
        k_hf = lref["hf_index"] if ex is ex_full else rung_hf_mode(ex, ref_s)
        lr = loop_summary(ex, k=k_hf)
        lr.update(growth_err=zero_rate(lr["growth"] - lref["growth"], Tc),
                  hf_rate_err=(lr["hf_rate"] - lref["hf_rate"]) / abs(lref["hf_rate"]),
                  hf_freq_err=(lr["hf_freq"] - lref["hf_freq"]) / lref["hf_freq"], n=m.n)
        info["loop_rungs"][rung] = lr
        rung_refs[rung] = (Xown, ex, k_hf)
    # the (rung, integrator) series on Dask: each worker compiles a rung once (_rung_model)
    own_client = client is None
    if own_client:
        from .timing_study import client_for
        client = client_for()
    try:
        sc = client.scatter(scene if hasattr(scene, "plant") else load_scene(scene), broadcast=True)
        refs = dict(W=W, Tc=Tc, node=node, duration=duration, span=span, Xr=Xr, mr=mr, peak_ref=peak_ref,
                    lref=lref, hf_min_hz=hf_min_hz)
        futs = {(rung, integ): client.submit(_series, sc, rung, integ, tuple(ratios), rung_refs[rung], refs, pure=False)
                for rung in rungs for integ in integrators}
        from dask.distributed import as_completed
        for f in as_completed(list(futs.values())):
            for row in f.result():
                if progress:
                    progress(row)
        for key in futs:
            rows += futs[key].result()
        if scene is not with_aux:
            _drop_section(with_aux, rungs, integrators, client, info)
    finally:
        if own_client:
            client.close()
    return rows, info


def _without_auxiliary(scene):
    """The scene with no auxiliary bearings and no faults (a drop scene's [[fault]] drops the rotor:
    the orbit study is of the levitated one), or itself when it has no auxiliary bearings."""
    from dataclasses import replace
    from ambhil.plant.faults import FaultSchedule
    if not any(getattr(a, "auxiliary", None) is not None for a in scene.plant.ambs):
        return scene
    ambs = tuple(replace(a, auxiliary=None) for a in scene.plant.ambs)
    return replace(scene, plant=replace(scene.plant, ambs=ambs), faults=FaultSchedule())


def _drop_section(scene, rungs, integrators, client, info: dict) -> None:
    """The rotor drop's convergence (loop/study_drop.py) per linear rung of the scene with its
    auxiliary bearings into ``info["drop"]``; ``info["drop_note"]`` says why not when it cannot fall."""
    from .study_drop import drop_convergence
    info["drop"] = {}
    full = compile_system(scene, "full")
    for rung in rungs:
        if rung == "ancf":  # its contact runs in its own DAE step: not part of this grid
            continue
        m = full if rung == "full" else compile_system(scene, rung, rotor=full.rotor)
        try:
            # the point rotor is the same physics only for the rigid rung (a flexible rung's station
            # "mass" is its high-frequency apparent mass)
            drows, dinfo = drop_convergence(m, integrators, rung=rung, client=client, point=rung == "rigid")
        except ValueError as e:
            info["drop_note"] = str(e)
            return
        info["drop"][rung] = dict(info=dinfo, rows=[asdict(r) for r in drows])


def _rate(g: float) -> str:
    """A growth rate for the table: 0 when neutral (zero_rate made it exactly 0), else signed."""
    if not np.isfinite(g):
        return "n/a"
    return "0" if g == 0 else f"{g:+.4g}"


def _loop_txt(d: dict, hf: str) -> str:
    g = d["growth"]
    fq = f"{d['freq']:.4g} Hz" if d["freq"] >= 1e-3 else "real"
    dom = ("dominant neutral (0 1/s within roundoff)" if g == 0 else
           f"dominant {'grows' if g > 0 else 'decays'} at {abs(g):.4g} 1/s ({fq})")
    if not np.isfinite(d["hf_freq"]):
        return f"{dom}; no mode within {HF_MATCH:.0%} of the reference's {hf} Hz mode"
    return f"{dom}; HF mode {d['hf_freq']:.4g} Hz, Re s {d['hf_rate']:+.4g} 1/s"


_FLAGS = (("hides an instability", "HIDES"), ("false instability", "FALSE"), ("numerical damping", "damping"),
          ("numerical error", "error"))


def _flag(numerics: str) -> str:
    """Short name of a numerics line for the table (the line itself is in accuracy.txt)."""
    head = numerics.split(":")[0]
    return next((f for k, f in _FLAGS if k in head), head[:7]) if numerics else ""


def table(rows: list[Row], info: dict, wide: bool = True) -> str:
    """The study as text.  ``wide=False``: what the CLI prints, lines within 120 columns (error,
    cost, loop columns and short numerics flags); ``wide=True`` (accuracy.txt): every column, and
    the numerics lines and peak-search notes in full."""
    Tc = info["controller_period"]
    ref = info.get("loop_ref", {})
    hf = f"{ref.get('hf_freq', float('nan')):.4g}"
    lines = [f"reference: full rung, exact zoh plant, controller period {Tc:g} s; node {info['node']}, "
             f"speed {info['speed']:.2f} rad/s",
             f"  |X| = {info['amp_ref']:.4g} m, settle {info['settle_ref']:.3f} s, peak at {info['peak_ref']:.2f} rad/s"]
    if ref:
        lines.append("sampled loop (exact zoh), full: " + _loop_txt(ref, hf))
        for rung, d in info.get("loop_rungs", {}).items():
            if rung == "full":
                continue
            vs = (f"; vs full {100 * d['hf_rate_err']:+.1f} %, {100 * d['hf_freq_err']:+.2f} % in f"
                  if np.isfinite(d["hf_freq"]) else "")
            lines.append(f"  {rung} (n={d['n']}): " + _loop_txt(d, hf) + vs)
        if ref["growth"] > 0:
            lines.append("  the sampled loop is UNSTABLE: orbit errors below compare growing transients, not steady orbits")
    na = False

    def hf_err(r):
        nonlocal na
        if np.isfinite(r.hf_rate_err):
            e = 100 * r.hf_rate_err
            return f"{e:+.1f}%" if abs(e) < 1000 else f"{e:+.2g}%"
        na = True
        return "n/a*"
    if wide:
        head = (f"{'rung':6} {'integrator':17} {'h (s)':>8} {'amp err':>8} {'phase err':>9} {'cplx err':>8} "
                f"{'peak err':>9} {'settle err':>10} {'us/step':>8} {'us/period':>9} {'RTF':>7} {'order':>5} "
                f"{'loop 1/s':>9} {'HF Hz':>7} {'HF Re s':>8} {'HF err':>9}  numerics")
        body = [f"{r.rung:6} {r.integrator:17} {r.h:8.3g} {r.amp_err:8.2e} {r.phase_err:9.2e} {r.cplx_err:8.2e} "
                f"{r.peak_err:+8.3f}{'!' if r.peak_note else ' '} {r.settle_err:+10.4f} {r.us_per_step:8.2f} "
                f"{r.us_per_period:9.2f} {r.rtf:7.1f} {r.order:5.2f} {_rate(r.loop_growth):>9} "
                f"{(f'{r.hf_freq:.4g}' if np.isfinite(r.hf_freq) else 'n/a'):>7} {_rate(r.hf_rate):>8} {hf_err(r):>9}  "
                f"{_flag(r.numerics)}" for r in rows]
    else:
        head = (f"{'rung':5} {'integrator':17} {'h (s)':>7} {'cplx err':>8} {'amp err':>8} {'peak err':>9} "
                f"{'settle':>8} {'us/period':>9} {'RTF':>6} {'order':>5} {'loop 1/s':>9} {'HF err':>9} numerics")
        body = [f"{r.rung:5} {r.integrator:17} {r.h:7.2g} {r.cplx_err:8.2e} {r.amp_err:8.2e} "
                f"{r.peak_err:+8.3f}{'!' if r.peak_note else ' '} {r.settle_err:+8.4f} {r.us_per_period:9.2f} "
                f"{r.rtf:6.1f} {r.order:5.2f} {_rate(r.loop_growth):>9} {hf_err(r):>9} {_flag(r.numerics)}"
                for r in rows]
    lines += ["", head] + body
    notes = ["loop 1/s: the simulated loop's dominant growth rate (> 0: unstable; 0: neutral within roundoff)",
             f"HF err: error of the Re s of the reference's {hf} Hz mode, matched in each row's loop"]
    if na:
        notes.append(f"* n/a: the rung has no mode within {HF_MATCH:.0%} of {hf} Hz (a rigid rung has no flexible modes)")
    if any(r.numerics for r in rows):
        notes.append("numerics: damping / error = the mode's rate or the orbit beyond its tolerance; HIDES / FALSE = "
                     "the verdict flips")
    if any(r.peak_note for r in rows):
        notes.append("!: the peak search ended at the edge of its range (peak err is a bound, not an error)")
    lines += [""] + notes
    if info.get("peak_ref_note"):
        lines += ["", f"WARNING: the reference's {info['peak_ref_note']}"]
    if info.get("drop") or info.get("drop_note"):
        from .study_drop import table as drop_table
        for d in (info.get("drop") or {}).values():
            lines += ["", drop_table(d["rows"], d["info"])]
        if info.get("drop_note"):
            lines += ["", f"rotor drop: {info['drop_note']}"]
    if wide:
        if any(r.peak_note for r in rows):
            lines += ["", "peak search:"] + [f"  {r.rung} {r.integrator} h={r.h:.3g}: {r.peak_note}"
                                             for r in rows if r.peak_note]
        if any(r.numerics for r in rows):
            lines += ["", "numerics:"] + [f"  {r.rung} {r.integrator} h={r.h:.3g}: {r.numerics}"
                                          for r in rows if r.numerics]
    return "\n".join(lines)


def save(rows: list[Row], info: dict, out_dir) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    d = Path(out_dir); d.mkdir(parents=True, exist_ok=True)
    with open(d / "accuracy.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(asdict(rows[0]).keys()))
        w.writeheader()
        for r in rows:
            w.writerow(asdict(r))
    (d / "accuracy.txt").write_text(table(rows, info) + "\n")
    drop = [r for v in (info.get("drop") or {}).values() for r in v["rows"]]
    if drop:
        with open(d / "drop.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(drop[0].keys()))
            w.writeheader()
            w.writerows(drop)
    fig, ax = plt.subplots(figsize=(8.5, 6))
    marks = {"rigid": "s", "modal": "o", "full": "^", "ancf": "D"}
    cols = {"bdf1": "C0", "bdf2": "C1", "trapezoidal": "C2", "generalized-alpha": "C3", "zoh": "C4"}
    Tc = info["controller_period"]
    pts = []
    for r in rows:
        err = max(r.cplx_err if np.isfinite(r.cplx_err) else max(r.amp_err, r.phase_err), 1e-16)
        pts.append((r.us_per_period, err))
        ax.loglog(r.us_per_period, err, marks.get(r.rung, "x"), color=cols.get(r.integrator, "k"), ms=7,
                  mec="k", mew=0.4)
        ratio = Tc / r.h
        ax.annotate(f"T/{ratio:.0f}" if abs(ratio - round(ratio)) < 1e-6 and ratio > 1.5 else "T",
                    (r.us_per_period, err), textcoords="offset points", xytext=(5, 3), fontsize=7, color="0.3")
    pts = sorted(pts)
    front, best = [], np.inf
    for c, e in pts:
        if e < best:
            front.append((c, e)); best = e
    ax.loglog(*zip(*front), "k--", lw=0.8, label="Pareto front")
    ax.axvline(Tc * 1e6, color="r", lw=1, ls=":", label=f"real time: {Tc * 1e6:g} us per period")
    for k in dict.fromkeys(r.integrator for r in rows):
        ax.plot([], [], "o", color=cols.get(k, "k"), label=k)
    for k in dict.fromkeys(r.rung for r in rows):
        ax.plot([], [], marks.get(k, "x"), color="grey", label=f"rung {k}")
    ax.set_xlabel(f"cost: microseconds per controller period ({1e-3 / Tc:g} kHz: real time = {Tc * 1e6:g} us)")
    ax.set_ylabel("steady orbit error |X - X_ref| / |X_ref|\n(amplitude and phase in one)")
    ax.set_title(f"Accuracy against cost; reference: full rung, exact zoh; labels: plant step h (T = {Tc * 1e6:g} us)",
                 fontsize=9)
    ax.legend(fontsize=8); ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout(); fig.savefig(d / "pareto.png", dpi=110); plt.close(fig)
    return [d / "accuracy.csv", d / "accuracy.txt", d / "pareto.png"] + ([d / "drop.csv"] if drop else [])
