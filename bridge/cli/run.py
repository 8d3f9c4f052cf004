"""`ambhil run SCENE`: recorder, controller and plant as separate OS processes on an explicit
loopback mesh (the recorder listens; the plant listens and connects to the recorder; the
controller connects to both).  It checks the scene's sampled loop first, shows the peers'
start-up progress, waits for the plant, shuts everything down cleanly (also on Ctrl-C), prints a
summary that says first what failed, and leaves `<run-id>.mcap` and `<run-id>.rrd` (renamed
`.failed.*` for a failed run) in the output folder.

This module is the orchestration, step by step (:func:`run`); the pieces live beside it:
bridge/cli/run_transport.py (the link), keyfile.py (the run's key: a fresh secret per run, in a 0600
file of the run's private folder, handed to the children as its path, deleted when the run
ends), children.py (the processes), run_files.py (the files),
run_verdict.py (what went wrong), run_summary.py (what is printed).
"""
from __future__ import annotations

import os
import shlex
import signal
import sys
import threading
import time
from pathlib import Path

from ambhil.loop import numerics, timing_study
from ambhil.loop.scene import load_scene, with_fault_flags
from ambhil.loop.system import black_box_reason, compile_system, controller_runner
from ambhil.bridge.cli.arguments import delay_text
from ambhil.bridge.cli.children import Child, exit_text, stop_process
from ambhil.bridge.cli.convention import CliError, emit
from ambhil.bridge.cli.keyfile import RunKey, key_path, load_secret
from ambhil.bridge.cli.rt_check import calibrate
from ambhil.bridge.cli.run_files import mark_failed, read_back, restore_unfinished, run_files, write_rrd
from ambhil.bridge.cli.run_setup import (check_currents_at, duration_steps, latency_s, placement_cpus,
                                         plant_runner)
from ambhil.bridge.cli.run_summary import Outcome, print_human, summary
from ambhil.bridge.cli.run_transport import run_transport
from ambhil.bridge.cli.run_verdict import failures, overrun_count, rate_check

PLANT_END_CAP_S = 30.0     # s; last resort: a plant still running this long after its controller died


def _precheck(args, scene, model, latency: float):
    """Before anything starts: the sampled loop at the scene's rate and this latency
    (ambhil.loop.timing_study.precheck), and whether the plant's integrator at its step misreports the
    loop (ambhil.loop.numerics.numerics_note: a warning, or a note that the check was skipped); one line each on stderr."""
    sim = scene.plant.simulation
    if sim.run_up is not None:
        return None
    why = black_box_reason(scene, args.law)
    if why:             # the checks analyse the linear law, which is not the one in the loop
        print(f"{args._prog}: note: sampled-loop and numerics checks not computed ({why})", file=sys.stderr)
        return None
    speed = sim.speed if sim.speed is not None else scene.plant.speed.value or 0.0
    pre = timing_study.precheck(model, speed, latency)
    if pre.line:
        print(f"{args._prog}: {'error' if args.strict and not pre.stable else 'warning'}: {pre.line}", file=sys.stderr)
    note = numerics.numerics_note(model, args.integrator, args.h, speed=speed, nonlinear=sim.force_law == "nonlinear",
                                  latency=latency)
    if note:
        print(f"{args._prog}: {note[0]}: {note[1]}", file=sys.stderr)
    return pre


def _prepare(args):
    """(scene, model, periods, latency in s, precheck): everything refused before a process starts."""
    scene = with_fault_flags(load_scene(args.scene), args.fault)
    model = compile_system(scene, rung=args.rung)
    n = duration_steps(scene, args.duration)
    latency = latency_s(args, scene)
    plant_runner(scene, model, args.integrator, args.h, latency)  # refuse now what the plant would (a step or a fault that does not fit)
    check_currents_at(args, latency)
    if args.law and args.controller:
        raise CliError("--law and --controller both name the controller; give one")
    if not args.controller:     # refuse now a law that cannot be made (LawError: exit 2), not in the child
        ctrl = controller_runner(model, law=args.law)
        getattr(ctrl, "close", lambda: None)()
    return scene, model, n, latency, _precheck(args, scene, model, latency)


# --------------------------------------------------------------------------- the three processes
def _plant_argv(args, scene, n: int, latency: float, ep_p: str, ep_r: str, record: bool) -> list[str]:
    """`ambhil plant`'s flags: the parsed values of ours, passed on as values (the latency in s)."""
    argv = ["plant", args.scene, "--listen", ep_p] + (["--connect", ep_r, "--wait-recorder"] if record else []) + [
            "--mode", args.mode, "--currents-at", args.currents_at, "--delay", delay_text(latency),
            "--duration", str(n / scene.controller.sample_rate)] + (["--law", args.law] if args.law else [])
    for spec in args.fault:
        argv += ["--fault", spec]
    for flag, val in (("--rung", args.rung), ("--integrator", args.integrator), ("--max-overruns", overrun_count(args)),
                      ("--reply-timeout", args.reply_timeout), ("--h", args.h)):
        if val is not None:
            argv += [flag, str(val)]
    return argv + ["--cpu-wake-us", "off" if args.cpu_wake_us is None else str(args.cpu_wake_us),
                   "--rt-receive", args.rt_receive]


def _controller_argv(args, run_id: str, connect: list[str], common: list[str], pin: list[str],
                     key) -> tuple[list[str], bool]:
    """(argv, external): ours (`ambhil controller`) or the user's command (``--controller CMD``,
    placeholders filled; the key file's path also in ``$AMBHIL_KEY_FILE``, :meth:`RunKey.env`)."""
    if not getattr(args, "controller", None):
        return (["controller", args.scene, "--connect"] + connect + common
                + (["--rung", args.rung] if args.rung else []) + (["--law", args.law] if args.law else [])
                + pin), False
    try:
        argv = shlex.split(args.controller.format(scene=shlex.quote(str(Path(args.scene).resolve())),
                                                  run_id=run_id, connect=" ".join(connect),
                                                  key_file=shlex.quote(key.path or "")))
    except (KeyError, IndexError, ValueError) as e:
        raise CliError(f"--controller {args.controller!r}: {e!r}; placeholders are {{scene}}, {{run_id}}, "
                       f"{{connect}}, {{key_file}}") from None
    return argv, True


def child_argvs(args, scene, n: int, latency: float, run_id: str, outdir: Path, ep_p: str, ep_r: str,
                record: bool, key) -> dict:
    """{name: (argv, external) or None} of recorder, controller and plant: what each is started
    with.  The run's key reaches them as a file's path (``--key-file PATH``, :class:`RunKey`),
    never as the secret."""
    common = ["--run-id", run_id, "--json", "--start-timeout", str(args.start_timeout)] + key.argv
    if args.secure:
        common += ["--secure", str(Path(args.secure).resolve())]
    cpus = placement_cpus(args.placement)

    def pin(role):
        return ["--cpus", ",".join(map(str, cpus[role]))] if role in cpus else []
    rec = ((["record", "--out", str(outdir), "--listen", ep_r, "--source", args.record_source,
             "--owner-pid", str(os.getpid())] + common + pin("recorder"), False) if record else None)
    ctl = _controller_argv(args, run_id, [ep_p] + ([ep_r] if record else []), common, pin("controller"), key)
    pl = (_plant_argv(args, scene, n, latency, ep_p, ep_r, record) + common + pin("plant"), False)
    return {"recorder": rec, "controller": ctl, "plant": pl}


def _start(argvs: dict, key, verbose: bool) -> tuple[dict, threading.Event]:
    """Recorder (if recording), controller, plant, in that order; ({name: Child or None}, the
    event that echoes their start-up progress)."""
    echo = threading.Event()
    echo.set()                              # show the peers' start-up progress until the run runs
    echo.verbose = verbose
    children = {}
    for name in ("recorder", "controller", "plant"):
        if argvs[name] is None:
            children[name] = None
            continue
        argv, external = argvs[name]
        try:
            children[name] = Child(name, argv, echo, external=external, env=key.env)
        except BaseException:               # e.g. a controller command that cannot be started
            for c in children.values():
                if c is not None:
                    stop_process(c.p)
            raise
    return children, echo


def _watch(children: dict) -> tuple[str | None, dict[str, str]]:
    """Wait for the plant to end; (how the user stopped the run or None, {peer: how it ended} for
    a peer that ended (not 0) while the plant ran).  SIGTERM (kill, a `timeout` wrapper, a script
    whose background jobs ignore SIGINT) stops the run as Ctrl-C does: the plant ends with
    RUN_END, the summary is printed, files kept."""
    pl, ctl, rec = children["plant"], children["controller"], children["recorder"]
    interrupted, early = None, {}
    on_term, how = None, ["Ctrl-C"]
    if threading.current_thread() is threading.main_thread():
        def _term(signum, frame):
            how[0] = "SIGTERM"
            raise KeyboardInterrupt
        on_term = signal.signal(signal.SIGTERM, _term)
    t_early = None
    try:
        while pl.p.poll() is None:
            for c in (ctl, rec) if rec is not None else (ctl,):
                if c.name not in early and c.p.poll() is not None and c.p.returncode != 0:
                    early[c.name] = exit_text(c.p.returncode)
                    t_early = time.monotonic()
                    if c is rec:    # the loop would go on unrecorded: stop the plant as Ctrl-C does
                        print(f"ambhil run: recorder {early[c.name]}; stopping the plant", file=sys.stderr)
                        stop_process(pl.p, signal.SIGINT)
                    else:           # the plant sees it (liveliness) and ends the run with the reason
                        print(f"ambhil run: controller {early[c.name]}", file=sys.stderr)
            if t_early is not None and time.monotonic() - t_early > PLANT_END_CAP_S:
                stop_process(pl.p, signal.SIGINT)   # last resort: the plant did not end by itself
                t_early = float("inf")
            time.sleep(0.05)
    except KeyboardInterrupt:
        interrupted = how[0]
        print("ambhil run: interrupted, stopping plant, controller and recorder ...", file=sys.stderr)
        stop_process(pl.p, signal.SIGINT)
    finally:
        if on_term is not None:
            signal.signal(signal.SIGTERM, on_term)
    return interrupted, early


def _results(children: dict) -> dict:
    """name -> (summary or None, stderr, exit code) of each process, once it ended."""
    results = {name: children[name].result(timeout=10.0 if name != "recorder" else 20.0)
               for name in ("plant", "controller", "recorder") if children[name] is not None}
    results.setdefault("recorder", (None, "", None))
    return results


# --------------------------------------------------------------------------- the run
def run(args) -> int:
    from ambhil.bridge.process import transport as tr      # zenoh: only when a run starts
    load_secret(key_path(args, env=False))  # a key file that cannot be used: refused before anything is built
    scene, model, n, latency, pre = _prepare(args)
    if pre is not None and not pre.stable and args.strict:
        return 1
    cal = None
    if args.mode == "realtime":             # can this machine hold the rate? (bridge/cli/rt_check.py)
        cal = calibrate(scene, model, args, placement_cpus(args.placement).get("plant"), latency=latency)
        print(f"{args._prog}: {'note' if cal['can_hold'] else 'warning'}: {cal['line']}", file=sys.stderr)
    run_id = args.run_id or f"{scene.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    outdir = Path(args.out)
    mcap, rrd = run_files(outdir, run_id)
    transport, ep_p, ep_r = run_transport(args, run_id)
    record = not args.no_record
    with RunKey(args, run_id) as key:       # the per-run key file is deleted when the run ends, also on failure
        argvs = child_argvs(args, scene, n, latency, run_id, outdir, ep_p, ep_r, record, key)
        children, echo = _start(argvs, key, bool(getattr(args, "verbose", False)))
        interrupted, early = _watch(children)
        echo.clear()
        results = _results(children)
        auth = key.describe(args.secure)
    tr.remove_socket_files(ep_p, ep_r)
    sr = results["recorder"][0]
    if record and (sr is None or sr.get("write_error")) and mcap.exists():  # restore what it wrote
        restore_unfinished(mcap)
    rrd_ok, conv = write_rrd(mcap, rrd, run_id) if mcap.exists() else (False, {})
    reasons, recorded, foreign, incomplete = failures(results, early, interrupted, pre, args.strict, mcap, record)
    orbits, injected, orbit_err = read_back(mcap, scene, conv, rrd_ok)
    rate = rate_check(args, scene, model, results["plant"][0], orbits, latency)
    if rate and not rate["kept"]:
        reasons.insert(0, rate["reason"])   # the first thing to know: these are not the scene's results
    files = ([mcap] if mcap.exists() else []) + ([rrd] if rrd_ok else [])
    if reasons:
        files = mark_failed(*files, why="; ".join(reasons))
    o = Outcome(args, scene, model, run_id, latency, transport, record, pre, cal, results, interrupted,
                reasons, recorded, foreign, incomplete, orbits, injected, orbit_err, rate, files, auth)
    emit(args, summary(o), lambda: print_human(o))
    if reasons:
        print(f"ambhil run: error: run {'stopped' if interrupted else 'failed'}: {'; '.join(reasons)}", file=sys.stderr)
        return 130 if interrupted else 1
    return 0
