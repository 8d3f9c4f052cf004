"""`ambhil study timing SCENE`: the sample-rate and latency study (loop/timing_study.py) from the
command line: parse the grid, run it on Dask, print the table, write CSV/JSON and plots.  The
study is of the linear sampled loop: a black-box law (``--law``, ``[controller] law``) gets the
one-line reason (loop/system.py ``black_box_reason``) instead, exit 2."""
from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np

from ambhil.loop import timing_study as ts
from ambhil.loop import units
from ambhil.loop.units import UnitError
from ambhil.loop.system import black_box_reason
from ambhil.bridge.cli.arguments import add_law_flag, law_label, speed
from ambhil.bridge.cli.convention import CliError, add_json, add_out, command, emit


def parse_rates(text: str) -> np.ndarray:
    """``2k:50k:20`` (20 log-spaced rates) or ``5k,10k,20k`` (sorted); Hz, units as
    :func:`ambhil.loop.units.rate` (``k``, ``M``, ``kHz``, any case)."""
    try:
        rates = units.span(text, lambda t: units.rate(t, "--rates"), "--rates", log=True)
    except UnitError:
        raise UnitError(f"--rates: expected START:STOP:COUNT (e.g. 2k:50k:20) or a list (5k,10k), got {text!r}") from None
    return rates if ":" in text else np.sort(rates)


def _periods(text: str) -> float:
    """A latency in controller periods: ``1.5T``, ``T``, or a bare number (where STOP is in periods)."""
    t = text.strip()
    return units.time_spec(t if t.endswith("T") else f"{t}T", "--delays").value


def parse_delays(text: str) -> tuple[np.ndarray, bool]:
    """``0:3T:24`` (periods) or ``0:150us:16`` / ``0,20us,50us`` (absolute); returns (values, in_periods).
    A range is in periods when its STOP is (``3T``; START may then be a bare number of periods), a
    list when every item but ``0`` is; an empty START is 0."""
    grid = text
    if ":" in text:
        start, _, rest = text.partition(":")
        periods = rest.partition(":")[0].strip().endswith("T")
        grid = f"{start if start.strip() else '0'}:{rest}"
    else:
        periods = all(t.endswith("T") or t == "0" for t in (t.strip() for t in text.split(",")))
    conv = _periods if periods else (lambda t: units.time(t, what="--delays"))
    try:
        return units.span(grid, conv, "--delays"), periods
    except UnitError:
        raise UnitError(f"--delays: expected START:STOP:COUNT with STOP in periods (3T) or time "
                        f"(150us), or a list, got {text!r}") from None


def parse_delays_us(text: str) -> np.ndarray:
    """``--delays-us START:STOP:COUNT``: latencies in microseconds (the same at every rate) -> s."""
    try:
        if text.count(":") != 2:
            raise UnitError
        return units.span(text, float, "--delays-us") * 1e-6
    except UnitError:
        raise UnitError(f"--delays-us: expected START:STOP:COUNT in microseconds, got {text!r}") from None


def measured_latency(mcap: str) -> ts.Latency:
    """The latency a recorded run measured each period: round trip (plant publish -> reply
    received) plus the plant's wake lateness (real time), warm-up excluded; periods whose reply
    was missing (held currents) count as losses."""
    from ambhil.bridge.protocol import FLAG_HELD, FLAG_WARMUP
    from ambhil.bridge.recording.load import load_run
    tim = load_run(mcap)["timing"]
    if tim is None or not len(tim["rtt_ns"]):
        raise ValueError(f"{mcap}: the recording holds no timing data (was it recorded by ambhil run?)")
    live = (tim["flags"] & FLAG_WARMUP) == 0
    held = live & ((tim["flags"] & FLAG_HELD) != 0)
    ok = live & ~held & (tim["rtt_ns"] > 0)
    lat = (tim["rtt_ns"][ok] + np.maximum(tim["lateness_ns"][ok], 0)) * 1e-9
    if not len(lat):
        raise ValueError(f"{mcap}: no period with a measured round trip")
    return ts.Latency(kind="empirical", samples=lat, loss=float(held.sum() / max(live.sum(), 1)))


def _fmt_us(s: float) -> str:
    return f"{s * 1e6:.1f}"


def _latency_cell(lm: float | None) -> tuple[str, str]:
    """(largest latency, in periods) cells; None: stable up to the search limit."""
    if lm is None:
        return f"> {ts.GIVE_UP * 1e3:g} ms", "-"
    return f"{_fmt_us(lm)} us", ""


def table(res: ts.StudyResult) -> str:
    sp = res.scene_point
    lines = [f"{res.scene} [{res.rung}]: sampled-loop stability over rate and latency "
             f"(latency beyond the controller's own delay)",
             f"{'rate (Hz)':>10} {'speed (rad/s)':>13} {'largest latency':>16} {'periods':>8} "
             f"{'growth@0 (1/s)':>15} {'S peak@0':>9} {'zone':>5}"]
    unbounded = False
    for g in res.grid:
        p0 = g["points"][0]
        lm = g["largest_latency_s"]
        unbounded |= lm is None
        s = p0.get("sensitivity_peak")
        cell, per = _latency_cell(lm)
        per = per or f"{lm * g['rate_hz']:.2f}"
        lines.append(f"{g['rate_hz']:10.0f} {g['speed_rad_s']:13.1f} {cell:>16} {per:>8} "
                     f"{p0['growth_rate']:15.3g} {'-' if s is None else f'{s:.2f}':>9} {p0.get('zone') or '-':>5}")
    if unbounded:
        lines.append(f"(> {ts.GIVE_UP * 1e3:g} ms: stable at every latency up to the search limit; no boundary)")
    verdict = "STABLE" if sp["stable"] else "UNSTABLE"
    lines.append("")
    lines.append(f"scene's own setting: {sp['rate_hz']:g} Hz, latency {_fmt_us(sp['latency_s'])} us: {verdict}; "
                 f"worst mode {sp['mode_hz']:.1f} Hz, growth {sp['growth_rate']:.3g} 1/s, least damping "
                 f"{sp['min_damping_ratio']:.4f} at {sp['min_damping_hz']:.1f} Hz")
    if sp["stable"] and sp["margin_s"] is None:
        lines.append(f"latency margin: more than {ts.GIVE_UP * 1e3:g} ms (stable at every latency up to the "
                     f"search limit)")
    elif sp["stable"]:
        lines.append(f"latency margin: {_fmt_us(sp['margin_s'])} us = {sp['margin_periods']:.2f} periods "
                     f"(largest tolerable latency at this rate, bisection)")
    else:
        lines.append("latency margin: none (the scene's sampled loop is unstable at its own rate)")
    for z in res.zone_rates:
        r = z["lowest_rate_hz"]
        lines.append(f"lowest rate for ISO 14839-3 zone {z['zone']} at latency {_fmt_us(z['latency_s'])} us: "
                     + (f"{r:.0f} Hz" if r else "-") + (f" ({z['note']})" if z["note"] else ""))
    if len(res.jitter) > 1 or (res.jitter and res.jitter[0]["jitter"] != "none"):
        lines.append("")
        lines.append(f"jitter and loss at {sp['rate_hz']:g} Hz ({res.jitter[0]['noise']} noise):")
        base = res.jitter[0].get("y_std_m")
        for j in res.jitter:
            ys = j.get("y_std_m")
            if ys is None:
                std = ("not computed (no stationary variance)" if not j["ms_stable"]
                       else f"not computed ({_reason(j, 'y_std_m')})")
            else:
                std = f"{ys:.3g} m" + (f" (x{ys / base:.3f})" if base else "")
            lines.append(f"  {j['jitter']:>24}, loss {j['loss']:<6.3g} mean-square "
                         f"{'stable' if j['ms_stable'] else 'UNSTABLE':8} displacement std {std}")
    return "\n".join(lines)


def _reason(point: dict, key: str) -> str:
    """Why ``point[key]`` is None, from its ``not_computed`` text."""
    for part in (point.get("not_computed") or "").split("; "):
        keys, _, why = part.partition(": ")
        if key in keys.split(", "):
            return why
    return "no reason recorded"


def _check_finite(x, where: str = "result") -> None:
    """A study result holds no non-finite number: a figure that could not be computed is None
    with its reason in ``not_computed``.  Anything else is a bug, reported as a failed run."""
    from ambhil.bridge.cli.convention import RUN_FAILED, CliError
    if isinstance(x, dict):
        for k, v in x.items():
            _check_finite(v, f"{where}.{k}")
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            _check_finite(v, f"{where}[{i}]")
    elif isinstance(x, (float, np.floating)) and not math.isfinite(x):
        raise CliError(f"the study computed a non-finite {where} ({x}); it is not reported as a figure",
                       RUN_FAILED)


def write(res: ts.StudyResult, out: Path, law: str | None = None) -> list[Path]:
    from ambhil.loop import timing_plots as tp
    out.mkdir(parents=True, exist_ok=True)
    files = []
    pts = res.points
    f = out / "timing_points.csv"
    with open(f, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(pts[0].keys()))
        w.writeheader()
        w.writerows(pts)
    files.append(f)
    f = out / "timing.json"
    f.write_text(json.dumps(summary(res, law), default=float, indent=1, allow_nan=False))
    files.append(f)
    files.append(tp.rate_latency_map(res, out / "timing_map.png"))
    files.append(tp.margin_against_latency(res, out / "timing_margin.png"))
    v = tp.variance_against_jitter(res, out / "timing_jitter.png")
    if v:
        files.append(v)
    return files


def summary(res: ts.StudyResult, law: str | None = None) -> dict:
    out = {"scene": res.scene, "law": law, "rung": res.rung, "scene_point": res.scene_point,
           "boundaries": [{"rate_hz": g["rate_hz"], "speed_rad_s": g["speed_rad_s"],
                           "largest_latency_s": g["largest_latency_s"], "not_computed": g["not_computed"]}
                          for g in res.grid],
           "zone_rates": res.zone_rates, "jitter": res.jitter, "points": res.points}
    _check_finite(out)
    return out


def cmd_timing(args) -> int:
    from ambhil.loop.scene import load_scene
    scene = load_scene(args.scene)
    why = black_box_reason(scene, args.law)
    if why:
        raise CliError(f"{args.scene}: the timing study is not computed ({why})")
    law = law_label(args.law, scene)
    rates = parse_rates(args.rates)
    if args.delays_us:
        delays, in_periods = parse_delays_us(args.delays_us), False
    else:
        delays, in_periods = parse_delays(args.delays)
    speeds = tuple(speed(s) for s in args.speeds.split(",")) if args.speeds else (
        scene.plant.simulation.speed or scene.plant.speed.nominal or 0.0,)
    if args.jitter_from:
        lat = measured_latency(args.jitter_from)
        if args.loss:
            lat = ts.Latency(kind="empirical", samples=lat.samples, loss=args.loss)
    else:
        lat = ts.parse_latency(args.jitter, args.loss or 0.0)
    kind, _, lev = (args.noise or "sensor:1e-6").partition(":")
    if kind not in ("sensor", "force"):
        raise ValueError(f"--noise must be sensor:STD_M or force:PSD_N2_PER_HZ, got {args.noise!r}")
    spec = ts.StudySpec(rates=rates, delays=delays, in_periods=in_periods, speeds=speeds, rung=args.rung,
                        sensitivity=not args.no_sensitivity, latency=lat, noise=ts.Noise(kind, float(lev or 1e-6)))
    client = ts.client_for(args.workers, args.scheduler)
    try:
        from ambhil.bridge.cli.progress import Progress
        res = ts.run(scene, spec, client, progress=Progress("timing study"))
    finally:
        client.close()
    files = write(res, Path(args.out), law) if args.out else []
    emit(args, json.loads(json.dumps(summary(res, law), default=float)), table(res))
    for f in files:
        print(f"wrote {f}", file=sys.stderr)
    return 0 if res.scene_point["stable"] or not args.strict else 1


def add_parser(ss) -> None:
    """Register ``study timing`` on the ``study`` subcommand's subparsers."""
    a = command(ss, "timing", "sample rate x loop latency (x speed, jitter, loss): stability, sensitivity, margins")
    a.add_argument("scene", metavar="SCENE", help="scene TOML file")
    a.add_argument("--rates", default="2k:50k:20", help="controller rates: START:STOP:COUNT (log-spaced) or a list, Hz")
    a.add_argument("--delays", default="0:3T:24", help="latencies beyond the controller's own delay: START:STOP:COUNT "
                                                      "with STOP in periods (3T) or time (150us), or a list")
    a.add_argument("--delays-us", metavar="START:STOP:COUNT", help="latencies in microseconds (the same at every rate)")
    a.add_argument("--speeds", metavar="LIST", help="spin speeds, comma-separated: 314, 3000rpm, 50Hz "
                                                    "(default: the scene's simulation speed)")
    a.add_argument("--jitter", help="random extra latency each period: uniform:WIDTH or normal:SIGMA (e.g. uniform:20us)")
    a.add_argument("--jitter-from", metavar="RUN.mcap", help="the latency distribution a recorded run measured")
    a.add_argument("--loss", type=float, default=0.0, help="probability that an update is lost (current held)")
    a.add_argument("--noise", default="sensor:1e-6", help="disturbance for the variance figures: sensor:STD_M or force:PSD")
    a.add_argument("--rung", choices=("rigid", "modal", "full"), help="model rung (default: the scene's)")
    add_law_flag(a, "the study's loop (a black-box law is refused with the reason: the study needs a linear law)")
    a.add_argument("--no-sensitivity", action="store_true", help="skip the ISO 14839-3 sensitivity (faster)")
    a.add_argument("--workers", type=int, help="run on a local Dask cluster of N processes (default: in-process)")
    a.add_argument("--scheduler", help="run on an existing Dask cluster, e.g. tcp://host:8786")
    add_out(a, None, "timing_points.csv, timing.json and the plots")
    add_json(a)
    a.add_argument("--strict", action="store_true", help="exit 1 if the scene's own setting is unstable")
    a.set_defaults(func=cmd_timing)
