"""CLI: ``ambhil simulate SCENE`` and ``ambhil study accuracy SCENE``.

``add_parsers(subparsers)`` registers both; each subparser sets ``func(args) -> exit code``
(0 ok, 1 the run diverged / faulted, 2 user error with a one-line message on stderr).

`simulate` in steps: :func:`_prepare` (the model, and what is refused or warned about before
the run), :func:`_figures` (the verdict and the orbits of the result), :func:`_summary` and
:func:`_print` (what is reported), :func:`_record` (the recording a HIL run would write).
"""
from __future__ import annotations

import math
import re
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ambhil.loop import contact_plots, contact_results, numerics, orbit_plots, orbits, simulation, timing_study
from ambhil.loop.scene import INPUT_ERRORS, load_scene, touchdown_note, with_fault_flags
from ambhil.loop.system import black_box_reason, compile_system
from ambhil.plant.ancf_faults import ANCFFaultyPlant
from ambhil.plant.ancf_step import plant_runner
from ambhil.plant.run_options import RunOptions
from ambhil.plant.faults import FaultyPlant
from ambhil.bridge.cli.arguments import (INTEGRATORS, RUNGS, add_fault_flag, add_law_flag, seconds, speed,
                                         speed_text)
from ambhil.bridge.cli.convention import add_json, add_out, arg_type, command, emit, fail
from ambhil.bridge.cli.run_setup import run_meta
from ambhil.bridge.cli.study_timing import add_parser as add_timing


def _nodes(txt: str | None):
    if not txt:
        return None
    try:
        return tuple(int(k) for k in txt.split(",") if k.strip())
    except ValueError:
        raise ValueError(f"--nodes must be comma-separated node numbers, got {txt!r}") from None


def _run_up(txt: str) -> tuple[float, float, float, float]:
    a = [s.strip() for s in txt.split(",")]
    if len(a) != 4:
        raise ValueError(f"expected W0,W1,T0,T1 (speeds with units, times in s), got {txt!r}")
    try:
        t0, t1 = seconds(a[2]), seconds(a[3])
    except ValueError:
        raise ValueError(f"T0,T1 must be times in s, got {a[2]!r},{a[3]!r}") from None
    return speed(a[0]), speed(a[1]), t0, t1


def _csv(kind: str, allowed: tuple[str, ...] | None = None, conv=str):
    def parse(txt: str):
        items = tuple(conv(s.strip()) for s in txt.split(",") if s.strip())
        bad = [s for s in items if allowed is not None and s not in allowed]
        if not items or bad:
            raise ValueError(f"expected comma-separated {kind}" + (f" from {', '.join(allowed)}" if allowed else "")
                             + f", got {txt!r}")
        return items
    return arg_type(parse, kind)


def _positive_int(txt: str) -> int:
    v = int(txt)
    if v < 1:
        raise ValueError(txt)
    return v


def sig3(x: float) -> str:
    """Three significant figures, plain notation (0.0791, 12.6, 1230); n/a if not a number > 0."""
    if not (isinstance(x, (int, float)) and math.isfinite(x) and x > 0):
        return "n/a"
    digits = max(0, 2 - int(math.floor(math.log10(x))))
    return f"{round(x, digits):.{digits}f}"


def not_steady(pre) -> str | None:
    """The verdict ``simulate`` and ``run`` share on a loop that did not fault: a sampled loop
    predicted unstable before the run (``ambhil.loop.timing_study.precheck``) grows, so the run has no
    steady orbit even if it has not diverged yet: ``"not steady: <the prediction>"`` (the run
    failed, exit 1), else None."""
    if pre is not None and not pre.stable:
        return f"not steady: {pre.line}"
    return None


# --------------------------------------------------------------------------- simulate
def _prepare(args, model):
    """Refuse what does not fit (a plant step, a fault), then the checks before the run: the
    sampled loop at the run's speed (``--strict``: refuse an unstable one) and the numerics of
    the integrator.  Returns (precheck or None, exit code if refused or None)."""
    runner = plant_runner(model, RunOptions(integrator=args.integrator, h=args.h))  # a step that does not fit is refused first, naming its source
    if model.scene.faults:  # so is a fault that does not fit this plant
        (ANCFFaultyPlant if model.rung == "ancf" else FaultyPlant)(runner, model.scene.faults)
    sim = model.spec.simulation
    if args.run_up is not None or sim.run_up is not None:
        print(f"{args._prog}: note: numerics check skipped: it compares linear time-invariant loops, and this "
              f"run has a speed run-up", file=sys.stderr)
        return None, None
    why = black_box_reason(model.scene, getattr(args, "law", None))
    if why:             # the checks below analyse the linear law, which is not the one in the loop
        print(f"{args._prog}: note: sampled-loop and numerics checks not computed ({why})", file=sys.stderr)
        return None, None
    w = args.speed if args.speed is not None else (sim.speed if sim.speed is not None
                                                   else model.spec.speed.value or 0.0)
    pre = timing_study.precheck(model, w)
    if pre.line:
        print(f"{args._prog}: {'warning' if pre.stable or not args.strict else 'error'}: {pre.line}",
              file=sys.stderr)
    if not pre.stable and args.strict:
        return pre, 1
    note = numerics.numerics_note(model, args.integrator, args.h, speed=w,
                                  nonlinear=bool(args.nonlinear or sim.force_law == "nonlinear"))
    if note:
        print(f"{args._prog}: {note[0]}: {note[1]}", file=sys.stderr)
    return pre, None


@dataclass
class _Figures:
    """The verdict and the figures of a simulation result."""
    planned: int
    bad: str | None
    orbits: list = field(default_factory=list)       # steady orbit per output node (a good, steady run)
    largest: list = field(default_factory=list)      # largest orbit per AMB against its clearance
    segments: list = field(default_factory=list)     # orbits between the faults / run-up phases
    settled: list = field(default_factory=list)      # how the orbit settles after the last change
    contact: object = None                           # contact_results.ContactReport (auxiliary bearings)
    relevitation: object = None                      # contact_results.Relevitation (the AMBs came back)


def _figures(res, model, pre, duration) -> _Figures:
    m = res.meta
    W = m["speed"]
    planned = max(1, int(round(m.get("duration", duration) / m["period"])))
    bad = res.instability or res.fault or not_steady(pre)
    f = _Figures(planned, bad, largest=orbits.touchdown_orbits(res, model.spec.ambs))
    if getattr(res, "contact", None) is not None:      # auxiliary bearings: what happened at them
        f.contact = contact_results.analyse(res)
        back = contact_results.return_time(res)
        if back is not None and f.contact.any_contact:
            f.relevitation = contact_results.relevitation(res, back)
    finished = not bad and res.steps >= planned
    events = res.events or []
    if finished and W > 0 and not m["run_up"] and not events:  # steady-state figures only for a good run
        for j, nd in enumerate(res.nodes):
            met = orbits.orbit_metrics(res.t, res.orbit[:, j, 0], res.orbit[:, j, 1], W)
            f.orbits.append({"node": nd, "radius_m": met["radius"], "settle_time_s": met["settle_time"],
                             "peak_m": met["peak"]})
    stn = [(o["amb"], o["node"], o["touchdown_clearance_m"]) for o in f.largest]
    if (events or m["run_up"]) and stn:  # a run that changes: its orbits between the changes, how it settles after
        f.segments = orbits.orbit_segments(res, stn)
        if finished and len(f.segments) > 1:
            f.settled = orbits.steady_at_end(res, stn, f.segments[-1]["start_s"])
    return f


def _summary(res, model, f: _Figures, files: list[str]) -> dict:
    m, W = res.meta, res.meta["speed"]
    return {"command": "simulate", "ok": not f.bad, "fault": f.bad, "scene": m["scene"], "law": m.get("law"),
            "rung": m["rung"],
            "integrator": m["integrator"], "h_s": m["h"], "controller_rate_hz": 1 / m["period"],
            "speed_rad_s": None if m["run_up"] else W, "run_up": m["run_up"], "periods": res.steps,
            "periods_planned": f.planned, "wall_s": res.wall, "us_per_period": res.us_per_period,
            "real_time_factor": res.real_time_factor if res.steps else None, "orbits": f.orbits,
            "largest_orbits": f.largest, "touchdown_clearance_note": touchdown_note(model.spec.ambs) or None,
            "fault_events": res.events or [], "orbit_segments": f.segments, "steady_orbits_at_end": f.settled,
            "contact": f.contact.as_dict() if f.contact else None,
            "relevitation": asdict(f.relevitation) if f.relevitation else None, "files": files}


def _print_segments(m, f: _Figures, events) -> None:
    print("  largest orbit per AMB, um (% of the touchdown clearance), "
          + ("between the fault starts and ends:" if events else "before, during and after the run-up:"))
    whats = [", ".join(([f"at {sg['speed_rad_s']:.4g} rad/s"] if m["run_up"] and sg["run_up"] is None else [])
                       + ([f"run-up {sg['run_up'][0]:.4g} -> {sg['run_up'][1]:.4g} rad/s"] if sg["run_up"] else [])
                       + (sg["faults"] or (["no fault"] if events else [])))
             for sg in f.segments]
    wide = max(len(w) for w in whats)
    for sg, what in zip(f.segments, whats):
        print(f"    t {sg['start_s']:.4g}-{sg['end_s']:.4g} s".ljust(20) + what.ljust(wide + 2)
              + "  ".join(f"{o['amb']} {o['largest_radius_m'] * 1e6:6.2f} ({100 * o['fraction_of_touchdown_clearance']:4.1f}%)"
                          for o in sg["orbits"]))
    if f.settled:
        print(f"  steady orbit after t={f.settled[0]['from_s']:.4g} s"
              + (f" at {speed_text(f.settled[0]['speed_rad_s'])}" if m["run_up"] else "") + ": "
              + ", ".join(f"{o['amb']} {o['radius_m'] * 1e6:.2f} um "
                          + (f"(settled in {o['settle_time_s'] - o['from_s']:.3g} s)"
                             if math.isfinite(o["settle_time_s"]) else "(not settled within the run)")
                          for o in f.settled))


def _print(res, model, f: _Figures, npz, written: list) -> None:
    """The summary for a person."""
    m, W, bad, planned = res.meta, res.meta["speed"], f.bad, f.planned
    events = res.events or []
    spd = (f"run-up {speed_text(m['run_up'][0])} -> {speed_text(m['run_up'][1])}" if m["run_up"]
           else f"speed {speed_text(W)}")
    print(f"{m['scene']} [{m['rung']}] {m['integrator']} h={m['h']:g} s, controller {1 / m['period']:g} Hz "
          f"(law {m.get('law')}), {spd}")
    if bad and bad.startswith("not steady: "):
        print(f"  NOT STEADY: {bad.removeprefix('not steady: ')}")
        print(f"  ran {res.steps} of {planned} periods ({res.steps * m['period']:.4g} s simulated); no steady-state "
              f"figures for a loop that grows (it has not diverged yet)")
    elif bad:
        print(f"  FAULT: {bad}")
        print(f"  stopped after {res.steps} of {planned} periods ({res.steps * m['period']:.4g} s simulated); "
              f"no steady-state figures for a run that faulted")
    if f.contact:
        print(f"  {f.contact.headline()}")
        for note in m.get("contact_notes") or ():
            print(f"  note: {note}")
    print(f"  {res.steps} periods in {res.wall:.3g} s wall: {sig3(res.us_per_period)} us/period, "
          f"real-time factor {sig3(res.real_time_factor) if res.steps else 'n/a'}")
    for e in events:
        print(f"  fault {e['phase']:5s} t={e['t_s']:.4g} s (step {e['step']}): {e['kind']}"
              + (f" {e['axis']}" if e["axis"] else "")
              + (" " + ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in e["params"].items())
                 if e["params"] else ""))
    for o in f.orbits:
        st = o["settle_time_s"]
        print(f"  node {o['node']}: steady orbit radius {o['radius_m']:.4g} m, "
              + (f"settle time {st:.3f} s" if math.isfinite(st) else "not settled within the run")
              + f", peak {o['peak_m']:.4g} m")
    for o in f.largest:
        print(f"  orbit {o['amb']:4s} largest radius {o['largest_radius_m'] * 1e6:8.2f} um = "
              f"{100 * o['fraction_of_touchdown_clearance']:5.1f}% of the touchdown clearance "
              f"{o['touchdown_clearance_m'] * 1e6:g} um (node {o['node']})" + (" (of a failed run)" if bad else ""))
    if f.segments:
        _print_segments(m, f, events)
    if f.largest and touchdown_note(model.spec.ambs):
        print(f"  note: {touchdown_note(model.spec.ambs)}")
    for line in (f.contact.lines() if f.contact else []) + (f.relevitation.lines() if f.relevitation else []):
        print(f"  {line}")
    pngs, recs = written
    print(f"  wrote {npz}" + "".join(f", {p.name}" for p in pngs + recs))
    if recs:
        print(f"  open it in the rerun viewer: ambhil view {recs[-1]}  (or the .mcap in Foxglove, docs/hil.md)")


def cmd_simulate(args) -> int:
    try:
        model = compile_system(with_fault_flags(load_scene(args.scene), args.fault), args.rung)
        sim = model.spec.simulation
        duration = args.duration or sim.duration
        pre, refused = _prepare(args, model)
        if refused is not None:
            return refused
        res = simulation.simulate(model, duration, args.speed, run_up=args.run_up, integrator=args.integrator,
                                  h=args.h, nodes=_nodes(args.nodes), nonlinear=True if args.nonlinear else None,
                                  record_every=args.record_every or sim.record_every, law=args.law)
    except (*INPUT_ERRORS, ValueError) as e:
        return fail(args, str(e))
    npz = res.save(args.out)
    pngs = orbit_plots.plot_orbits(res, args.out, gaps=_gaps_at_nodes(model, res.nodes),
                                  clearances=_clearances_at_nodes(model, res.nodes))
    pngs += contact_plots.plot_contact(res, args.out)   # auxiliary bearings only
    f = _figures(res, model, pre, duration)
    recs = _record(args, model, res)
    files = [str(npz)] + [str(p) for p in pngs] + [str(p) for p in recs]
    emit(args, _summary(res, model, f, files), lambda: _print(res, model, f, npz, [pngs, recs]))
    return 1 if f.bad else 0


def _gaps_at_nodes(model, nodes) -> dict:
    """{1-based node: magnetic gap (m)} of the output nodes that carry an AMB."""
    return {a.node + 1: a.gap for a in model.spec.ambs if a.node + 1 in nodes}


def _clearances_at_nodes(model, nodes) -> dict:
    """{1-based node: touchdown clearance (m)} of the output nodes that carry an AMB."""
    return {a.node + 1: a.clearance for a in model.spec.ambs if a.node + 1 in nodes}


def _record(args, model, res) -> list:
    """``simulation.mcap`` + ``simulation.rrd``: the layout of a HIL run's recording (docs/hil.md)."""
    if getattr(args, "no_record", False):
        return []
    from ambhil.bridge.recording.replay import to_rerun         # mcap, rerun: only when writing
    from ambhil.bridge.recording.simulated_run import write_simulation
    from ambhil.bridge.cli.progress import Progress    # rich: slow to import, only when drawing
    out = Path(args.out)
    mcap, rrd = out / "simulation.mcap", out / "simulation.rrd"
    run_id = re.sub(r"[^A-Za-z0-9_.-]", "_", f"{model.scene.name}-simulate")[:64]
    meta = run_meta(model.scene, model, args.integrator, law=args.law)
    meta.update(rung=model.rung, integrator=res.meta["integrator"], speed_rad_s=res.meta["speed"])
    write_simulation(mcap, run_id, res, meta)
    with Progress(f"writing {rrd.name}") as bar:
        to_rerun(str(mcap), str(rrd), recording_id=run_id, progress=bar)
    return [mcap, rrd]


def cmd_study(args) -> int:
    from ambhil.loop import study                                 # dask, matplotlib: only for a study
    from ambhil.bridge.cli.progress import Progress    # rich: slow to import, only when drawing
    total = len(args.rungs) * len(args.integrators) * len(args.ratios)
    bar = Progress("accuracy study")
    done = [0]

    def progress(r):
        done[0] += 1
        bar(done[0], total, f"{r.rung} {r.integrator} h={r.h:.3g}")
    try:
        scene = load_scene(args.scene)
        client = timing_study.client_for(args.workers, args.scheduler)
        try:
            with bar:
                rows, info = study.accuracy(scene, rungs=args.rungs, integrators=args.integrators, ratios=args.ratios,
                                            node=args.node, speed=args.speed, duration=args.duration,
                                            progress=progress, client=client)
        finally:
            client.close()
    except (*INPUT_ERRORS, ValueError) as e:
        return fail(args, str(e))
    files = [str(p) for p in study.save(rows, info, args.out)]

    def human():
        print(study.table(rows, info, wide=False))
        for p in files:
            print(f"wrote {p}")
        print(f"every column, the numerics lines and the peak-search notes in full: {files[1]}")
    emit(args, {"command": "study accuracy", "info": info, "rows": [asdict(r) for r in rows], "files": files}, human)
    return 0


def add_parsers(sub) -> None:
    p = command(sub, "simulate", "closed-loop transient (plant + discrete controller in one process)")
    p.add_argument("scene", metavar="SCENE", help="scene TOML file")
    add_out(p, "out/simulate", "simulation.npz, orbit_node*.png, contact_*.png and the recording "
                               "simulation.mcap + .rrd")
    p.add_argument("--duration", type=arg_type(seconds, "s"), metavar="S",
                   help="simulated time, s (default: [simulation] duration)")
    p.add_argument("--integrator", choices=INTEGRATORS, help="plant integrator (default: [simulation] integrator)")
    p.add_argument("--h", type=arg_type(seconds, "s"), metavar="S",
                   help="plant step, s; the controller period must be a multiple (default: [simulation] step)")
    p.add_argument("--rung", choices=RUNGS, help="model rung (default: [model] rung)")
    p.add_argument("--speed", type=speed, metavar="SPEED",
                   help="constant spin speed: 314, 314rad/s, 3000rpm or 50Hz (default: [simulation] speed)")
    p.add_argument("--run-up", type=arg_type(_run_up, "run-up"), metavar="W0,W1,T0,T1",
                   help="speed ramp W0 -> W1 (speeds with units as --speed) between T0 and T1 s")
    p.add_argument("--nodes", help="1-based nodes to record and plot, e.g. 21,39 (default: [simulation] output_nodes)")
    p.add_argument("--nonlinear", action="store_true", help="exact AMB force law (Newton) instead of the linearised one")
    add_fault_flag(p)
    add_law_flag(p)
    p.add_argument("--record-every", type=int, metavar="N",
                   help="record every N controller periods (default: [simulation] record_every)")
    p.add_argument("--strict", action="store_true",
                   help="refuse to run when the sampled loop at the scene's rate is unstable (checked before the run)")
    p.add_argument("--no-record", action="store_true",
                   help="write no simulation.mcap / .rrd (the recording a HIL run writes, docs/hil.md)")
    add_json(p)
    p.set_defaults(func=cmd_simulate)

    s = command(sub, "study", "numerical studies of the time-domain plant")
    ss = s.add_subparsers(dest="study", required=True, metavar="STUDY")
    a = command(ss, "accuracy", "integrator x step x rung: error vs cost, convergence order, Pareto plot")
    a.add_argument("scene", metavar="SCENE", help="scene TOML file")
    add_out(a, "out/study", "accuracy.csv, accuracy.txt and the Pareto plot")
    a.add_argument("--rungs", type=_csv("rungs", RUNGS), default="rigid,modal,full", metavar="LIST",
                   help="model rungs, comma-separated (add ancf for the nonlinear multibody rung: bdf1 and "
                        "generalized-alpha only, and far slower)")
    a.add_argument("--integrators", type=_csv("integrators", INTEGRATORS), default=",".join(INTEGRATORS[:4]), metavar="LIST",
                   help="plant integrators, comma-separated")
    a.add_argument("--ratios", type=_csv("positive integers", None, _positive_int), default="1,2,4", metavar="LIST",
                   help="plant steps per controller period, comma-separated")
    a.add_argument("--node", type=int, help="1-based output node (default: the first AMB's node)")
    a.add_argument("--speed", type=speed, metavar="SPEED",
                   help="spin speed: 314, 314rad/s, 3000rpm or 50Hz (default: the first critical speed)")
    a.add_argument("--duration", type=arg_type(seconds, "s"), default=0.5, metavar="S",
                   help="simulated time of each run, s")
    a.add_argument("--workers", type=int, help="run the series on a local Dask cluster of N processes "
                                               "(default: in-process; the cost figures are then not taken under contention)")
    a.add_argument("--scheduler", help="run on an existing Dask cluster, e.g. tcp://host:8786")
    add_json(a)
    a.set_defaults(func=cmd_study)
    add_timing(ss)
