"""CLI: ``ambhil simulate SCENE --out DIR`` and ``ambhil study accuracy SCENE --out DIR``.

``add_parsers(subparsers)`` registers both; each subparser sets ``func(args) -> exit code``
(0 ok, 1 the run diverged / faulted, 2 user error with a one-line message on stderr).
"""
from __future__ import annotations

import sys


def _nodes(txt: str | None):
    if not txt:
        return None
    try:
        return tuple(int(k) for k in txt.split(",") if k.strip())
    except ValueError:
        raise ValueError(f"--nodes must be comma-separated node numbers, got {txt!r}") from None


def _err(msg: str) -> int:
    print(f"ambhil: error: {msg}", file=sys.stderr)
    return 2


def cmd_simulate(args) -> int:
    from loop.scene import INPUT_ERRORS
    from loop.simulation import orbit_metrics, plot_orbits, simulate
    from loop.system import compile_system
    try:
        model = compile_system(args.scene, args.rung)
        sim = model.spec.simulation
        run_up = None
        if args.run_up:
            a = [float(x) for x in args.run_up.split(",")]
            if len(a) != 4:
                raise ValueError("--run-up needs W0,W1,T0,T1 (rad/s, rad/s, s, s)")
            run_up = tuple(a)
        duration = args.duration or sim.duration
        res = simulate(model, duration, args.speed, run_up=run_up, integrator=args.integrator, h=args.h,
                       nodes=_nodes(args.nodes), nonlinear=True if args.nonlinear else None,
                       record_every=args.record_every or sim.record_every)
    except (*INPUT_ERRORS, ValueError) as e:
        return _err(str(e))
    f = res.save(args.out)
    pngs = plot_orbits(res, args.out)
    W = res.meta["speed"]
    print(f"{res.meta['scene']} [{res.meta['rung']}] {res.meta['integrator']} h={res.meta['h']:g} s, "
          f"controller {1 / res.meta['period']:g} Hz, {res.steps} periods in {res.wall:.3f} s "
          f"({res.us_per_period:.2f} us/period, real-time factor {res.real_time_factor:.1f})")
    if W > 0 and not res.meta["run_up"]:
        for j, nd in enumerate(res.nodes):
            met = orbit_metrics(res.t, res.orbit[:, j, 0], res.orbit[:, j, 1], W)
            print(f"  node {nd}: steady orbit radius {met['radius']:.4g} m, settle time {met['settle_time']:.3f} s, "
                  f"peak {met['peak']:.4g} m")
    print(f"  wrote {f}" + "".join(f", {p.name}" for p in pngs))
    if res.fault or res.instability:
        print(f"  FAULT: {res.instability or res.fault}")
        return 1
    return 0


def cmd_study(args) -> int:
    from loop import study
    from loop.scene import INPUT_ERRORS, load_scene
    try:
        scene = load_scene(args.scene)
        rows, info = study.accuracy(scene, rungs=tuple(args.rungs.split(",")),
                                    integrators=tuple(args.integrators.split(",")),
                                    ratios=tuple(int(r) for r in args.ratios.split(",")),
                                    node=args.node, speed=args.speed, duration=args.duration,
                                    progress=lambda r: print(f"  {r.rung:6} {r.integrator:18} h={r.h:.3g}",
                                                             file=sys.stderr))
    except (*INPUT_ERRORS, ValueError) as e:
        return _err(str(e))
    print(study.table(rows, info))
    for p in study.save(rows, info, args.out):
        print(f"wrote {p}")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("simulate", help="closed-loop transient (plant + discrete controller in one process)")
    p.add_argument("scene")
    p.add_argument("--out", required=True, help="output directory (simulation.npz, orbit_node*.png)")
    p.add_argument("--duration", type=float, help="s (default: [simulation] duration)")
    p.add_argument("--integrator", choices=("bdf1", "bdf2", "trapezoidal", "generalized-alpha", "zoh"))
    p.add_argument("--h", type=float, help="plant step, s (controller period must be a multiple)")
    p.add_argument("--rung", choices=("rigid", "modal", "full"))
    p.add_argument("--speed", type=float, help="constant spin speed, rad/s")
    p.add_argument("--run-up", help="W0,W1,T0,T1: speed ramp W0 -> W1 rad/s between T0 and T1 s")
    p.add_argument("--nodes", help="1-based nodes to record and plot, e.g. 21,39")
    p.add_argument("--nonlinear", action="store_true", help="exact AMB force law (Newton)")
    p.add_argument("--record-every", type=int, help="record every N controller periods")
    p.set_defaults(func=cmd_simulate)

    s = sub.add_parser("study", help="numerical studies of the time-domain plant")
    ss = s.add_subparsers(dest="study", required=True)
    a = ss.add_parser("accuracy", help="integrator x step x rung: error vs cost, convergence order, Pareto plot")
    a.add_argument("scene")
    a.add_argument("--out", default="out/study")
    a.add_argument("--rungs", default="rigid,modal,full")
    a.add_argument("--integrators", default="bdf1,bdf2,trapezoidal,generalized-alpha")
    a.add_argument("--ratios", default="1,2,4", help="plant steps per controller period")
    a.add_argument("--node", type=int, help="1-based output node (default: first AMB)")
    a.add_argument("--speed", type=float, help="rad/s (default: first critical speed)")
    a.add_argument("--duration", type=float, default=0.5)
    a.set_defaults(func=cmd_study)
    from .study_timing import add_parser as add_timing
    add_timing(ss)
