"""CLI: ``ambhil test-controller SCENE --faults FILE``: a fault campaign (loop/campaign.py) against
the scene's controller (or ``--law``) in process, or against a controller command through
``ambhil run``; a pass/fail table, exit 1 if any case fails.  ``--relevitation-time`` and
``--max-relevitation-force`` set the re-levitation limits of every case with a drop that ends,
over the campaign file's (the command line is the latest word)."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from dataclasses import replace
from types import SimpleNamespace
from pathlib import Path

import numpy as np

from ambhil.controller.law import LawError
from ambhil.loop.campaign import evaluate, load_campaign, run_case
from ambhil.loop.scene import INPUT_ERRORS, load_scene, touchdown_note
from ambhil.loop.system import compile_system
from ambhil.bridge.cli.arguments import add_law_flag, law_label
from ambhil.bridge.cli.convention import add_json, add_out, arg_type, command, emit, fail, json_safe
from ambhil.loop import units
from ambhil.bridge.cli.keyfile import load_secret
from ambhil.bridge.recording.load import load_run


def _run_external(args, scene, case, k: int, outdir: Path):
    """One case as ``ambhil run`` with the case's faults and ``--controller CMD``; the orbits are the
    recorded sensor readings (the only view of the rotor a HIL run has)."""
    run_id = f"{scene.name}-case{k + 1}"
    argv = [sys.executable, "-m", "ambhil.bridge.cli", "run", args.scene, "--run-id", run_id, "--out", str(outdir),
            "--duration", repr(case.duration), "--json", "--controller", args.controller]
    if args.rung:
        argv += ["--rung", args.rung]
    if args.key_file:                   # else `ambhil run` makes a key per case (the command gets $AMBHIL_KEY_FILE)
        argv += ["--key-file", os.path.abspath(args.key_file)]
    if args.insecure:
        argv += ["--insecure"]
    argv += ["--fault", "none"]         # the case's faults alone, as in process (not the scene's own too)
    for s in case.specs:
        argv += ["--fault", s]
    p = subprocess.run(argv, capture_output=True, text=True)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    summary = json.loads(lines[-1]) if lines else {}
    mcap = next((Path(f) for f in summary.get("files", []) if f.endswith(".mcap")), None)
    if mcap is None or not mcap.exists():
        err = p.stderr.strip().splitlines()[-1] if p.stderr.strip() else f"exit code {p.returncode}"
        raise RuntimeError(f"case {case.name!r}: ambhil run left no recording ({err})")
    run = load_run(str(mcap))
    v = run["sensors"]["v"]
    t = run["sensors"]["t_ns"] * 1e-9
    ns = len(scene.plant.ambs)
    xy = v[:, :2 * ns].reshape(len(v), ns, 2)
    sp = summary.get("plant") or {}
    planned = int(round(case.duration * scene.controller.sample_rate))
    fault = "; ".join(summary.get("failed") or []) or None
    speed = scene.plant.simulation.speed if scene.plant.simulation.speed is not None else scene.plant.speed.value or 0.0
    relev, why = None, ""
    if case.judges_relevitation:
        from ambhil.loop.contact_results import relevitation
        res = recorded_contact(scene, run, t, v, speed)
        if res is None:
            why = "the recording holds no contact events of the plant (a plant without auxiliary bearings?)"
        else:
            relev = relevitation(res, case.t_return)
    cr = evaluate(case, t, xy, [a.clearance for a in scene.plant.ambs], speed, sp.get("steps", 0) >= planned, fault,
                  relev, why)
    cr.events = [json.loads(e.text) | {"step": e.step} for e in run["events"] if e.kind_name == "FAULT_INJECTED"]
    cr.metrics["files"] = summary.get("files", [])
    return cr


def recorded_contact(scene, run, t, v, speed):
    """What a recording of ``ambhil run`` tells of the auxiliary bearings, in the shape of
    ``SimResult.contact`` (loop/contact_results.py reads it): the shaft centre in each bearing from
    the sensor readings of its AMB's axes plus the operating point (exact for collocated sensors, the
    sensor station's motion otherwise), the contact from the plant's contact events (in contact from
    each start to its end, at the event's peak force).  Race speed and energies are not recorded
    (zeros).  None for a scene without auxiliary bearings."""
    evs = []
    for e in run["events"]:
        if e.kind_name == "INFO" and e.text.startswith("{"):
            try:
                d = json.loads(e.text)
            except ValueError:
                continue
            if isinstance(d, dict) and d.get("kind") == "contact":
                evs.append(d)
    names = [a.name for a in scene.plant.ambs if a.auxiliary is not None]
    if not names:
        return None
    m = compile_system(scene)
    axes = [f"{a}:{x}" for a, x in m.axes]
    rows = len(t)
    x = np.zeros((rows, len(names))); y = np.zeros_like(x); fn = np.zeros_like(x)
    for k, nm in enumerate(names):
        ix, iy = axes.index(f"{nm}:x"), axes.index(f"{nm}:y")
        x[:, k] = m.x_op[ix] + v[:, ix]
        y[:, k] = m.x_op[iy] + v[:, iy]
        starts = [e for e in evs if e["bearing"] == nm and e["phase"] == "start"]
        ends = [e for e in evs if e["bearing"] == nm and e["phase"] == "end"]
        for st in starts:
            en = next((e for e in ends if e.get("start_s") == st["t_s"]), None)
            t1 = en["t_s"] if en is not None and en["t_s"] is not None else math.inf
            fn[(t >= st["t_s"] - 1e-12) & (t <= t1)] = (en or {}).get("peak_force_N") or 1.0
    clearance = np.array([scene.plant.amb(nm).auxiliary.clearance for nm in names])
    z = np.zeros_like(x)
    contact = dict(names=tuple(names), clearance=clearance, x=x, y=y, fn=fn, ft=z, d=np.hypot(x, y) - clearance,
                   race_speed=z, friction_power=z, e_friction=z, e_damping=z, events=evs, summary={},
                   shaft_radius=np.array([scene.plant.amb(nm).auxiliary.shaft_radius for nm in names]),
                   race_radius=np.array([scene.plant.amb(nm).auxiliary.race_r for nm in names]))
    return SimpleNamespace(t=np.asarray(t, float), speed=np.full(len(t), float(speed)), contact=contact, events=[],
                           meta={})


def _relevitation_flags(args, cases):
    """The cases with the command line's re-levitation limits (with ``--controller`` judged from the
    recording: :func:`recorded_contact`)."""
    relev = [c for c in cases if c.judges_relevitation]
    flags = {k: getattr(args, k) for k in ("relevitation_time", "max_relevitation_force") if getattr(args, k) is not None}
    if flags and not relev:
        print(f"note: {', '.join('--' + k.replace('_', '-') for k in flags)}: no case of {args.faults} has a drop "
              f"that ends (nothing to re-levitate)", file=sys.stderr)
    return [replace(c, **flags) if c.judges_relevitation else c for c in cases]


def _relevitation_cell(rl, c) -> str:
    """The table's re-levitation cell: time (limit), peak force after the return (limit), whirl."""
    if rl is None:
        return "-"
    if not rl["measured"]:
        return "not measured"
    ts, lim, fl = rl["time_s"], c.relevitation_time, c.max_relevitation_force
    return (("never" if ts is None else f"{ts * 1e3:.1f} ms") + (f" (<= {lim * 1e3:g} ms)" if lim is not None else "")
            + f", {rl['peak_force_N']:.4g} N" + (f" (<= {fl:g} N)" if fl is not None else "")
            + (", backward whirl" if rl["backward_whirl"] else ""))


def cmd_test_controller(args) -> int:
    try:
        scene = load_scene(args.scene)
        if args.law and args.controller:
            return fail(args, "--law and --controller both name the controller under test; give one")
        cases = load_campaign(args.faults, scene)
        cases = _relevitation_flags(args, cases)
        if args.key_file and args.insecure:
            return fail(args, "--key-file and --insecure: give one (a key, or explicitly none)")
        if args.controller:
            load_secret(args.key_file)      # a key file that cannot be used: refused before the first case
        system = None if args.controller else compile_system(scene, rung=args.rung)
    except (*INPUT_ERRORS, ValueError) as e:
        return fail(args, str(e))
    outdir = Path(args.out) if args.out else None
    if outdir is not None:
        outdir.mkdir(parents=True, exist_ok=True)
    results = []
    for k, case in enumerate(cases):
        print(f"case {k + 1}/{len(cases)}: {case.name} ...", file=sys.stderr, flush=True)
        try:
            if args.controller:
                results.append(_run_external(args, scene, case, k, outdir or Path("recordings")))
            else:
                results.append(run_case(system, case, law=args.law))
        except (*INPUT_ERRORS, ValueError) as e:
            return fail(args, f"{args.faults}: case {case.name!r}: {e}")
        except LawError as e:           # a law that cannot be made (a law failing at a step fails its case)
            return fail(args, str(e))
        except RuntimeError as e:
            return fail(args, str(e), 1)
    rows = []
    cells = {}
    for r in results:
        m, c = r.metrics, r.case
        rl = m.get("relevitation")
        if rl is not None:
            rl = {**rl, "limit_time_s": c.relevitation_time, "limit_peak_force_N": c.max_relevitation_force,
                  "no_backward_whirl": c.no_backward_whirl}
        cells[c.name] = _relevitation_cell(rl, c)
        rows.append({"case": c.name, "passed": r.passed, "faults": list(c.specs),
                     "max_orbit_fraction": m["max_orbit_fraction"], "limit_orbit_fraction": c.max_orbit_fraction,
                     "recovery_time_s": m["recovery_time_s"], "limit_recovery_time_s": c.recovery_time,
                     "stable": m["stable"], "must_stay_stable": c.must_stay_stable, "relevitation": rl,
                     "failures": r.failures,
                     "events": r.events, **({"files": m["files"]} if "files" in m else {})})
    n_fail = sum(not r.passed for r in results)
    summary = {"command": "test-controller", "ok": n_fail == 0, "scene": scene.name,
               "mode": "ambhil run --controller" if args.controller else "in-process",
               "law": f"--controller {args.controller}" if args.controller else law_label(args.law, scene),
               "touchdown_clearances_m": {a.name: a.clearance for a in scene.plant.ambs},
               "touchdown_clearance_note": touchdown_note(scene.plant.ambs) or None,
               "cases": len(results), "failed": n_fail, "results": rows}
    if outdir is not None:
        (outdir / "campaign.json").write_text(json.dumps(json_safe(summary), allow_nan=False, indent=1))

    def human():
        from rich import box                    # rich: only for the table (slow to import)
        from rich.console import Console
        from rich.table import Table
        from rich.markup import escape           # a message may hold brackets ([[amb]], [amb.auxiliary])
        tab = Table(title=f"{scene.name}: fault campaign {Path(args.faults).name} "
                          f"({summary['mode']}, law {summary['law']})", box=box.SIMPLE_HEAVY)
        relev = any(r["relevitation"] is not None for r in rows)
        for col in ("case", "orbit / touchdown clearance", "recovery", "stable") \
                + (("re-levitation, peak force",) if relev else ()) + ("verdict",):
            tab.add_column(col, justify="left" if col in ("case", "verdict") else "right", no_wrap=col != "verdict")
        for r in rows:
            lim = r["limit_orbit_fraction"]
            rec, rl = r["recovery_time_s"], r["limit_recovery_time_s"]
            tab.add_row(r["case"],
                        f"{100 * r['max_orbit_fraction']:.1f} %" + (f" (<= {100 * lim:g} %)" if lim is not None else ""),
                        ("never" if math.isinf(rec) else f"{rec * 1e3:.1f} ms") + (f" (<= {rl * 1e3:g} ms)" if rl is not None else ""),
                        ("yes" if r["stable"] else "NO") + ("" if r["must_stay_stable"] else " (not required)"),
                        *((escape(cells[r["case"]]),) if relev else ()),
                        "PASS" if r["passed"] else escape("FAIL: " + "; ".join(r["failures"])))
        Console(width=max(120, Console().width), highlight=False).print(tab)
        print("touchdown clearance " + ", ".join(f"{a.name} {a.clearance * 1e6:g} um" for a in scene.plant.ambs)
              + (f" ({touchdown_note(scene.plant.ambs)})" if touchdown_note(scene.plant.ambs) else ""))
        for r in rows:                          # what relevitation() says of each re-levitation case
            if r["relevitation"] is not None and r["relevitation"]["measured"]:
                print(f"{r['case']}:")
                for ln in r["relevitation"]["lines"]:
                    print(f"  {ln}")
        print(f"{len(rows) - n_fail} of {len(rows)} cases passed" + (f"; wrote {outdir / 'campaign.json'}" if outdir else ""))
    emit(args, summary, human)
    return 1 if n_fail else 0


def _positive(v: float) -> float:
    if not v > 0 or not math.isfinite(v):
        raise ValueError(f"must be > 0 and finite, got {v:g}")
    return v


def add_parsers(sub) -> None:
    p = command(sub, "test-controller", "run a fault campaign against a controller: pass/fail table")
    p.add_argument("scene", metavar="SCENE", help="scene TOML file")
    p.add_argument("--faults", required=True, metavar="FILE",
                   help="campaign file: [[case]] tables with faults and criteria (docs/faults.md)")
    p.add_argument("--controller", metavar="CMD",
                   help="run each case as `ambhil run --controller CMD` against this controller command "
                        "(placeholders {scene}, {run_id}, {connect}); default: the scene's controller in process")
    p.add_argument("--rung", choices=("rigid", "modal", "full"), help="model rung (default: [model] rung)")
    add_law_flag(p, "every case")
    p.add_argument("--relevitation-time", type=arg_type(lambda v: _positive(units.quantity(v, "time", "--relevitation-time")),
                                                        "time"), metavar="TIME",
                   help="limit on the time to lift the rotor off the auxiliary bearings after a drop's end, for "
                        "every case with a drop that ends (0.2s, 150ms; default: the campaign file's, else 0.2 s)")
    p.add_argument("--max-relevitation-force", type=arg_type(lambda v: _positive(float(v)), "force"), metavar="N",
                   help="limit on the peak auxiliary-bearing contact force after a drop's end, N, for every case "
                        "with a drop that ends (default: the campaign file's, else none: reported only)")
    p.add_argument("--key-file", metavar="FILE",
                   help="with --controller: every case's `ambhil run --key-file FILE` (default: a fresh key per "
                        "case; the command finds its file in $AMBHIL_KEY_FILE); in process no key is needed")
    p.add_argument("--insecure", action="store_true", help="with --controller: every case's `ambhil run --insecure`")
    add_out(p, None, "campaign.json (and with --controller the runs' recordings; default: recordings/)")
    add_json(p)
    p.set_defaults(func=cmd_test_controller)
