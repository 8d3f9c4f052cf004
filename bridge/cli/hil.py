"""CLI of the HIL processes: `plant`, `controller`, `record`, `run` (bridge/cli/run.py), `replay`,
`recover`."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

from ambhil.loop.scene import SceneError, load_scene, with_fault_flags

MODES = ("lockstep", "realtime")
LISTEN_HELP = ("endpoint to listen on, for peers that join later (default: a free port on each local "
               "address that reaches a tcp --connect endpoint: loopback on one host, the "
               "network interface towards the plant across hosts)")
PLACEMENTS = ("auto", "none")


def _cpu_list(text: str) -> list[int]:
    try:
        cpus = [int(c) for c in text.split(",") if c.strip()]
    except ValueError:
        raise SystemExit(f"--cpus: expected a comma-separated list of CPU numbers, got {text!r}")
    avail = os.sched_getaffinity(0)
    bad = [c for c in cpus if c not in avail]
    if not cpus or bad:
        raise SystemExit(f"--cpus {text}: CPU(s) {bad or text} not available (this process may use "
                         f"{sorted(avail)})")
    return cpus


def _positive_ms(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not v > 0:
        raise SystemExit(f"--reply-timeout: expected a positive number of ms, got {text!r}")
    return v


def _cpu_wake_us(text: str) -> int | None:
    """``--cpu-wake-us``: a whole number of microseconds >= 0, or ``off``."""
    if text.strip().lower() in ("off", "none"):
        return None
    try:
        v = int(text)
    except ValueError:
        v = -1
    if v < 0:
        raise SystemExit(f"--cpu-wake-us: expected a whole number of us >= 0 or 'off', got {text!r}")
    return v


def overrun_limit(text: str) -> tuple[str, float] | None:
    """``run --max-overruns``: ``1%`` -> ("percent", 1.0) (judged at the end), ``20`` ->
    ("count", 20) (the plant halts after 20), ``off`` -> None."""
    t = str(text).strip().lower()
    if t in ("off", "none"):
        return None
    try:
        if t.endswith("%"):
            v = float(t[:-1])
            if 0 <= v <= 100:
                return ("percent", v)
        elif t.isdigit():
            return ("count", int(t))
    except ValueError:
        pass
    raise SystemExit(f"--max-overruns: expected a share such as 1%, a count such as 20, or off, got {text!r}")


def placement_cpus(placement: str) -> dict:
    """``--cpus`` per role for ``ambhil run``.  Lockstep and real-time loops are fastest with
    plant and controller on one core (tooling.md §1.5c: cross-core wake-ups dominate); the
    recorder then gets the remaining cores so it never delays the loop."""
    avail = sorted(os.sched_getaffinity(0))
    if placement == "none" or len(avail) < 2:
        return {}
    loop, rest = avail[-1], avail[:-1]
    return {"plant": [loop], "controller": [loop], "recorder": rest}


def _json_out(summary: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(summary, default=str), flush=True)


def _duration_steps(scene, duration: float | None) -> int:
    d = duration if duration is not None else (scene.plant.simulation.duration or 1.0)
    if not d > 0:
        raise SceneError(f"{scene.path}: --duration must be > 0 s, got {d}")
    return max(1, int(round(d * scene.controller.sample_rate)))


def latency_of(text: str, scene) -> float:
    """``--delay``: ``2`` or ``1.5`` (controller periods), ``1.5T``, ``150us``, ``0.2ms`` -> seconds."""
    from ambhil.loop.timing_study import parse_time
    T = 1.0 / scene.controller.sample_rate
    t = str(text).strip()
    try:
        v = float(t) * T if t.replace(".", "", 1).isdigit() else parse_time(t, T)
    except ValueError:
        v = float("nan")
    if not v >= 0:
        raise SceneError(f"--delay: expected a latency such as 2, 1.5T, 150us or 0.2ms, got {text!r}")
    return v


def check_currents_at(args, scene) -> None:
    """``--currents-at arrival`` needs real time and no fixed ``--delay`` (the arrival is the latency)."""
    from ambhil.bridge.cli.main import CliError
    if args.currents_at == "arrival" and (args.mode != "realtime" or latency_of(args.delay, scene)):
        raise CliError("--currents-at arrival: only with --mode realtime and without --delay "
                       "(the measured arrival is the latency)")


def run_meta(scene, model, args) -> dict:
    """Metadata carried by the RunMeta message and the MCAP file."""
    plant = scene.plant
    stations = [a.name for a in plant.ambs] + ([plant.axial_amb.name] if plant.axial_amb else [])
    return {
        "scene": scene.name, "scene_path": str(Path(scene.path).resolve()),
        "scene_toml": Path(scene.path).read_text() if Path(scene.path).exists() else "",
        "rung": model.rung, "integrator": getattr(args, "integrator", None) or plant.simulation.integrator,
        "latency_s": latency_of(args.delay, scene) if getattr(args, "delay", None) else 0.0,
        "controller_rate_hz": scene.controller.sample_rate,
        "axis_names": [f"{a}-{x}" for a, x in model.axes],
        "station_names": stations,
        "gaps_m": [a.gap for a in plant.ambs],
        "touchdown_clearances_m": [a.clearance for a in plant.ambs],
        "touchdown_clearances_given": [a.touchdown_clearance is not None for a in plant.ambs],
        "speed_rad_s": plant.simulation.speed or plant.speed.nominal,
        "faults": [f.describe() for f in scene.faults.faults],
        "controller": controller_meta(scene, model.rung),
    }


def controller_meta(scene, rung: str | None = None) -> dict:
    """RunMeta ``controller``: the scene's discrete law as the built-in controller computes it
    (docs/protocol.md §5.2), so that a controller in any language needs no scene parser.  ``rung``:
    the plant's rung (under [model] gravity the ancf rung's operating currents carry the weight)."""
    from ambhil.controller.discrete import describe
    from ambhil.loop.system import controller_runner
    r = controller_runner(scene, rung=rung)  # what `ambhil controller SCENE [--rung R]` runs
    return describe(r.params, r.i_op, r.config)


# --------------------------------------------------------------------------- plant / controller
def _kernel_text(module: str, fn: str, what: str) -> str:
    """Progress line for loading ``what``: says when numba compiles (no cache index yet)."""
    try:
        import importlib
        disp = getattr(importlib.import_module(module), fn)
        cached = os.path.exists(disp._cache._cache_file._index_path)
    except Exception:
        cached = None
    if cached:
        return f"loading {what} (cached)"
    return f"compiling {what} (first run only) ..."


def _secure(args, role: str) -> None:
    """``--secure DIR``: every zenoh session of this process uses mutual TLS and access control."""
    if getattr(args, "secure", None):
        from ambhil.bridge.process.security import SecurityError, configure
        try:
            configure(args.secure, role, args.run_id)
        except SecurityError as e:
            from ambhil.bridge.cli.main import CliError
            raise CliError(str(e)) from None


def _presence(args, role: str):
    """Declare this process at once (``starting/<role>``), before any heavy work.  CPU pinning
    (``--cpus``) comes later, once the model is built (:func:`_pin`)."""
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge.process.startup import Presence
    _secure(args, role)
    try:
        return Presence.open(args.run_id, role, listen=args.listen, connect=args.connect or None)
    except (tr.TransportError, ValueError) as e:
        raise SystemExit(f"ambhil {role}: {e}")


def _pin(args) -> None:
    """``--cpus``: pin every thread of this process (zenoh's included), after the model was
    built: BLAS sizes its thread pool to the CPUs it sees at start, and the plan's rounding
    depends on that pool (a lockstep run must reproduce an unpinned in-process run bit for bit)."""
    from ambhil.bridge.process.timing import pin_cpus
    pin_cpus(getattr(args, "cpus", None), all_threads=True)


def plant_runner(scene, model, args):
    """The plant step object of a HIL run: a PlantRunner, wrapped in a FaultyPlant when the scene or
    ``--fault`` schedules faults (plant/faults.py; the same code as ``simulate`` with faults)."""
    from ambhil.plant.ancf_step import plant_runner as runner_of
    from ambhil.plant.faults import FaultyPlant
    # the loop latency lives in the plant (currents reach the coils late), as in simulate()
    runner = runner_of(model, integrator=args.integrator, h=args.h, latency=latency_of(args.delay, scene))
    if scene.faults and model.rung == "ancf":
        raise ValueError(f"{scene.path}: scheduled faults are not supported on the ancf rung yet")
    return FaultyPlant(runner, scene.faults) if scene.faults else runner


def _term_as_interrupt() -> None:
    """SIGTERM (``kill``, `ambhil run` stopping its plant, the parent-death signal of a killed
    `ambhil run`) ends this process as Ctrl-C does: a clean stop with its summary, not a death
    without one."""
    import signal
    import threading
    if threading.current_thread() is threading.main_thread():
        def _term(signum, frame):
            raise KeyboardInterrupt
        signal.signal(signal.SIGTERM, _term)


def _plant(args) -> int:
    from ambhil.bridge.cli.main import HARD_EXIT, INTERRUPTED
    HARD_EXIT[0] = True                 # a zenoh process: end without interpreter shutdown (cli.entry)
    from ambhil.bridge.process.events import exit_code
    _term_as_interrupt()
    from ambhil.bridge.process.plant_node import run_plant
    scene = with_fault_flags(load_scene(args.scene), args.fault)
    n = _duration_steps(scene, args.duration)
    check_currents_at(args, scene)
    presence = _presence(args, "plant")
    try:
        presence.progress("building the model")
        from ambhil.loop.system import compile_system
        model = compile_system(scene, rung=args.rung)
        runner = plant_runner(scene, model, args)
        presence.progress(_kernel_text("ambhil.plant.integrator", "plant_advance", "the plant kernels"))
        runner.reset(); runner.advance(np.zeros(runner.n_axes))  # compile/load the kernels before going live
        _pin(args)
        s = run_plant(runner, args.run_id, mode=args.mode, currents_at=args.currents_at,
                      n_steps=n, max_overruns=args.max_overruns,
                      wait_recorder=args.wait_recorder, meta=run_meta(scene, model, args),
                      start_timeout=args.start_timeout, cpus=args.cpus, presence=presence,
                      reply_timeout=None if args.reply_timeout is None else args.reply_timeout / 1e3,
                      cpu_wake_us=args.cpu_wake_us, rt_receive=args.rt_receive)
    finally:
        presence.close(session_too=True)
    _json_out(s, args.json)
    if not args.json:
        print(f"plant: {s['steps']}/{s['n_steps']} steps, {s['mode']}, {s['steps_per_s']:.0f} steps/s, "
              f"overruns {s['overruns']}" + (f"; FAULT: {s['fault']}" if s["fault"] else ""))
    return INTERRUPTED if s.get("end_reason") == "interrupted" else exit_code(s)


def _controller(args) -> int:
    from ambhil.bridge.cli.main import HARD_EXIT
    HARD_EXIT[0] = True                 # a zenoh process: end without interpreter shutdown (cli.entry)
    from ambhil.bridge.process.controller_node import run_controller
    from ambhil.bridge.process.events import exit_code
    scene = load_scene(args.scene)
    presence = _presence(args, "controller")
    try:
        presence.progress("building the controller")
        from ambhil.loop.system import controller_runner
        runner = controller_runner(scene, rung=args.rung)
        presence.progress(_kernel_text("ambhil.controller.discrete", "controller_step", "the controller kernel"))
        runner.reset(); runner.step(np.zeros(runner.n_axes))  # compile/load the kernel before going live
        if args.gain_scale != 1.0:  # a deliberately changed controller (regression-test demo)
            runner = _Scaled(runner, args.gain_scale)
        _pin(args)
        s = run_controller(runner, args.run_id, start_timeout=args.start_timeout, cpus=args.cpus,
                           presence=presence)
    finally:
        presence.close(session_too=True)
    _json_out(s, args.json)
    if not args.json:
        print(f"controller: {s.get('steps', s.get('answered', '?'))} samples answered"
              + (f"; FAULT: {s['fault']}" if s.get("fault") else ""))
    return exit_code(s)


class _Scaled:
    """A controller whose output is scaled: the 'changed gain' of a regression test."""

    def __init__(self, inner, k):
        self.inner, self.k, self.n_axes = inner, k, inner.n_axes

    def reset(self):
        return self.inner.reset()

    def step(self, y):
        return self.k * self.inner.step(y)


def _record(args) -> int:
    from ambhil.bridge.cli.main import HARD_EXIT
    HARD_EXIT[0] = True                 # a zenoh process: end without interpreter shutdown (cli.entry)
    from ambhil.bridge.recording.recorder import record
    from ambhil.bridge.process.timing import pin_cpus
    _secure(args, "recorder")
    pin_cpus(args.cpus)
    s = record(args.run_id, args.out, listen=args.listen, connect=args.connect or None,
               start_timeout=args.start_timeout, echo=True, source=args.source, owner_pid=args.owner_pid)
    if args.owner_pid and str(s.get("end_reason")).startswith("ambhil run") and os.path.exists(s["path"]):
        s["files"] = _orphaned(s["path"], args.run_id)
    _json_out(s, args.json)
    if not args.json:
        print(f"recorder: {s['messages']} messages -> {s['path']} ({s['end_reason']}); run {s['status']}"
              + (f": {s['fault']}" if s.get("fault") else "")
              + (f"; {s['steps_recorded']} of {s['steps_run']} steps recorded"
                 if s.get("steps_run") is not None and s["steps_recorded"] < s["steps_run"] else ""))
    return 0 if s.get("path") and not s.get("write_error") else 1


def _orphaned(path: str, run_id: str) -> list[str]:
    """The recorder of an `ambhil run` that died (killed, SIGKILL): nobody else will finish the
    run's files, so it does what the run would have: the recording renamed
    ``<run-id>.failed.mcap`` (its ``ambhil.run_end`` says stopped and why) and its
    ``.failed.rrd`` written.  Returns the files."""
    from ambhil.bridge.cli.run import mark_failed
    mcap = Path(path)
    files = mark_failed(mcap)
    out = [str(f) for f in files]
    if files:
        try:
            from ambhil.bridge.recording.replay import to_rerun
            rrd = files[0].with_suffix(".rrd")
            to_rerun(str(files[0]), str(rrd), recording_id=run_id)
            out.append(str(rrd))
        except Exception:           # nobody reads our stderr any more: the summary says what was written
            pass
    return out


def _run(args) -> int:
    from ambhil.bridge.cli.run import run
    return run(args)


# --------------------------------------------------------------------------- replay / recover
def _replay(args) -> int:
    from ambhil.bridge.recording import replay
    from ambhil.bridge.cli.main import CliError, emit
    from ambhil.bridge.recording.recover import RecordingError, check, truncated_message
    if not args.to_controller:
        src = Path(args.mcap)
        outdir = Path(args.out) if args.out else src.parent
        rrd = outdir / (src.stem + ".rrd")
        try:
            if check(str(src)) == "truncated":
                raise RecordingError(truncated_message(str(src)))
            outdir.mkdir(parents=True, exist_ok=True)
            from ambhil.bridge.cli.progress import Progress
            with Progress(f"writing {rrd.name}") as bar:
                info = replay.to_rerun(str(src), str(rrd), progress=bar)
        except RecordingError as e:
            raise CliError(str(e)) from None
        skipped = info["rejected"]
        emit(args, {"command": "replay", **info}, [
            f"wrote {rrd}: {info['samples']} samples, stations {', '.join(info['stations'])}"
            + (f"; skipped {skipped} malformed message(s): "
               + ", ".join(f"{k} x{v}" for k, v in info["rejected_reasons"].items()) if skipped else ""),
            f"open it in the rerun viewer: ambhil view {rrd}"])
        return 0
    return _conform(args)


def _conform(args) -> int:
    """``replay --to-controller``: the sensor stream into a controller process (``--scene``: the
    built-in one; ``--controller-cmd``: any; neither: one started by hand), currents compared
    per axis (bridge/recording/conform.py)."""
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge.cli.main import CliError, emit
    from ambhil.bridge.recording.conform import ConformanceError, conform, controller_command, table
    from ambhil.bridge.recording.recover import RecordingError
    if args.scene and args.controller_cmd:
        raise CliError("--scene and --controller-cmd both name the controller under test; give one")
    if args.gain_scale != 1.0 and not args.scene:
        raise CliError("--gain-scale scales the built-in controller: it needs --scene")
    if not args.tolerance >= 0:
        raise CliError(f"--tolerance: expected a current >= 0 A, got {args.tolerance}")
    ep = args.listen or tr.tcp_endpoint(tr.free_port())
    run_id = args.run_id or f"replay-{os.getpid()}"
    argv = None
    if args.scene:
        argv = [sys.executable, "-m", "ambhil.bridge.cli", "controller", args.scene, "--run-id", run_id,
                "--connect", ep] + (["--gain-scale", str(args.gain_scale)] if args.gain_scale != 1.0 else [])
    elif args.controller_cmd:
        argv = controller_command(args.controller_cmd, run_id, ep)
    else:
        print(f"waiting for a controller: run it with --run-id {run_id} --connect {ep} "
              f"(e.g. ambhil controller SCENE --run-id {run_id} --connect {ep})", file=sys.stderr)
    try:
        res = conform(args.mcap, run_id, listen=ep, argv=argv, tolerance=args.tolerance,
                      start_timeout=args.start_timeout)
    except (RecordingError, ValueError) as e:
        raise CliError(str(e)) from None
    except (ConformanceError, tr.TransportError) as e:
        raise CliError(str(e), 1) from None
    emit(args, {"command": "replay --to-controller", **res}, table(res))
    return 0 if res["passed"] else 1


def _certs(args) -> int:
    from ambhil.bridge.cli.main import CliError, emit
    from ambhil.bridge.process.security import SecurityError, make_certs
    try:
        out = make_certs(args.dir, host=args.host, days=args.days, force=args.force)
    except SecurityError as e:
        raise CliError(str(e)) from None
    emit(args, {"command": "certs", "files": out},
         lambda: print(f"certificates for plant, controller, recorder (valid for {args.host}) in {args.dir}: "
                       f"{', '.join(os.path.basename(f) for f in out)}"))
    return 0


def _recover(args) -> int:
    from ambhil.bridge.cli.main import CliError, RUN_FAILED, emit
    from ambhil.bridge.recording.recover import RecordingError, check, recover, same_file
    src = args.src
    dst = args.dst or str(Path(src).with_suffix(".recovered.mcap"))
    try:
        state = check(src)
        if Path(dst).exists() and not same_file(src, dst) and not args.force:
            raise RecordingError(f"{dst}: exists; give another destination or --force to replace it")
        n = recover(src, dst, keep_empty=False)
    except RecordingError as e:
        raise CliError(str(e)) from None
    if n == 0:
        raise CliError(f"{src}: recovered nothing (no complete chunk before the truncation); "
                       f"nothing written", RUN_FAILED)
    emit(args, {"command": "recover", "source": src, "destination": dst, "messages": n,
                "source_was": state},
         f"recovered {n} messages from {src} into {dst}"
         + (f" ({src} was complete: this is a copy)" if state == "complete" else ""))
    return 0


def add_fault_flag(p) -> None:
    p.add_argument("--fault", action="append", default=[], metavar="KIND:key=value,...",
                   help="schedule a fault (repeatable; after the scene's [[fault]] tables), e.g. "
                        "sensor_noise:at=0.2s,axis=A.x,sigma=2e-6 or amb_loss:at=0.1s,axis=B (docs/faults.md)")


def add_parsers(sub) -> None:
    from ambhil.bridge.cli.main import add_json, add_out, arg_type, command
    role_needs_id = ("plant", "controller", "record")

    def common(p, scene=True):
        role = p.prog.split()[-1]
        if scene:
            p.add_argument("scene", metavar="SCENE", help="scene TOML file")
        p.add_argument("--run-id", required=role in role_needs_id,
                       help="run identifier (key expressions ambhil/<run-id>/...)"
                            + ("" if role in role_needs_id else "; default: <scene>-<date>-<time>"))
        add_json(p)
        p.add_argument("--start-timeout", type=float, default=30.0, metavar="S",
                       help="s a peer may be absent (no liveliness token) before giving up; a peer "
                            "that is there, even still starting, is waited for as long as it lives")
        p.add_argument("--secure", metavar="DIR",
                       help="mutual TLS with the certificates in DIR (`ambhil certs DIR`) and zenoh access "
                            "control allowing each role only its own keys of the run; endpoints must be "
                            "tls/HOST:PORT (docs/hil.md, Secure runs)")
        if role in role_needs_id:
            p.add_argument("--cpus", type=arg_type(_cpu_list, "cpus"), help="pin this process (all its threads) to "
                           "these CPUs, e.g. 1 or 0,1 (set before zenoh starts its threads)")

    def plant_flags(p):
        p.add_argument("--mode", choices=MODES, default="lockstep",
                       help="lockstep: each step waits for the controller's reply; realtime: paced by the wall clock")
        p.add_argument("--duration", type=float, metavar="S", help="simulated s (default: [simulation] duration or 1 s)")
        p.add_argument("--delay", default="0", metavar="LATENCY",
                       help="loop latency: the currents reach the coils this late: periods (2, 1.5), 1.5T, 150us or "
                            "0.2ms; a fraction of a period must be a whole number of plant steps (see --h)")
        p.add_argument("--h", type=float, metavar="S",
                       help="plant step, s; the controller period must be a multiple (default: [simulation] step)")
        p.add_argument("--cpu-wake-us", type=arg_type(_cpu_wake_us, "us"), default=0, metavar="US",
                       help="realtime: while the run lasts, ask the kernel (PM QoS, /dev/cpu_dma_latency) to keep "
                            "the CPUs' wake-up latency <= US (0: idle CPUs poll, no sleep states); 'off' for no "
                            "request; needs write access to the device (root), the summary says if granted")
        p.add_argument("--rt-receive", choices=("auto", "deadline", "callback"), default="auto",
                       help="realtime: how the plant waits for a reply: deadline = blocking receive woken "
                            "at the window's end by a timer thread on another CPU (bridge/process/deadline.py), "
                            "callback = zenoh callback and queue; auto = deadline where possible (the "
                            "summary says which)")
        p.add_argument("--currents-at", choices=("sample", "arrival"), default="sample",
                       help="realtime: when the simulated coils take the controller's reply: sample = over "
                            "the whole period from the sample (the loop sees no latency but --delay); arrival "
                            "= when it arrived (wake lateness + round trip, rounded up to the plant step --h): "
                            "the machine's and network's latency, as a real plant sees it")
        p.add_argument("--rung", choices=("rigid", "modal", "full", "ancf"), help="model rung (default: [model] rung)")
        p.add_argument("--integrator", choices=("bdf1", "bdf2", "trapezoidal", "generalized-alpha", "zoh"),
                       help="plant integrator (default: [simulation] integrator)")
        add_fault_flag(p)

    p = command(sub, "plant", "the plant process: integrates the rotor, publishes sensor displacements")
    common(p)
    p.add_argument("--listen", required=True, help="zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--connect", nargs="*", default=[], metavar="ENDPOINT",
                   help="endpoints to connect to (e.g. the recorder)")
    plant_flags(p)
    p.add_argument("--reply-timeout", type=arg_type(_positive_ms, "ms"), metavar="MS",
                   help="real time: declare the controller dead after MS without any reply (default "
                        "10 controller periods); lockstep: last-resort cap on waiting for a live "
                        "controller (default 300000 = 5 min; a dead one is caught by liveliness)")
    p.add_argument("--max-overruns", type=int, metavar="N", help="realtime: halt after N overruns (default: never)")
    p.add_argument("--wait-recorder", action="store_true", help="start only once a recorder is present")
    p.set_defaults(func=_plant)

    p = command(sub, "controller", "the discrete PID controller process: returns coil currents")
    common(p)
    p.add_argument("--connect", nargs="*", default=[], metavar="ENDPOINT",
                   help="endpoints to connect to (the plant, the recorder)")
    p.add_argument("--listen", metavar="ENDPOINT", help=LISTEN_HELP)
    p.add_argument("--gain-scale", type=float, default=1.0, metavar="K",
                   help="scale the controller output (a deliberately changed controller, for testing)")
    p.add_argument("--rung", choices=("rigid", "modal", "full", "ancf"),
                   help="the plant's model rung (default: [model] rung); under [model] gravity the ancf "
                        "rung's operating currents carry the weight")
    p.set_defaults(func=_controller)

    def record_file(args):  # --out is a folder; the file in it is named for the run
        Path(args.out).mkdir(parents=True, exist_ok=True)
        args.out = str(Path(args.out) / f"{args.run_id}.mcap")
    p = command(sub, "record", "record all traffic of a run to <out>/<run-id>.mcap")
    common(p, scene=False)
    add_out(p, "recordings", "the recording <run-id>.mcap")
    p.add_argument("--listen", metavar="ENDPOINT", help=LISTEN_HELP)
    p.add_argument("--connect", nargs="*", default=[], metavar="ENDPOINT", help="endpoints to connect to")
    p.add_argument("--owner-pid", type=int, metavar="PID",
                   help="the `ambhil run` that started this recorder: if it dies, the recording is finished "
                        "(status stopped), renamed <run-id>.failed.mcap and its .failed.rrd written")
    p.add_argument("--source", choices=("plant", "wire"), default="plant",
                   help="plant: sensor samples and currents from the plant's RecordBatch messages, off "
                        "the loop's path (ambhil plant); wire: subscribe to them directly (a plant "
                        "of your own that sends no RecordBatch; the loop then pays for the recorder)")
    p.set_defaults(func=_record, _finalize=record_file)

    p = command(sub, "run", "plant + controller + recorder as separate processes; summary; .mcap and .rrd")
    common(p)
    plant_flags(p)
    p.add_argument("--reply-timeout", type=arg_type(_positive_ms, "ms"), metavar="MS",
                   help="plant: controller dead after MS without any reply (real time, default 10 "
                        "periods); lockstep: last-resort cap (default 5 min)")
    p.add_argument("--max-overruns", type=arg_type(overrun_limit, "limit"), default="1%", metavar="LIMIT",
                   help="realtime: P%% = the run FAILED (exit 1, .failed files) when more than P %% of the periods "
                        "after the warm-up overran (its results are then not the scene's: the summary compares "
                        "its orbits with the in-process loop's); N = the plant halts after N overruns; off = "
                        "neither.  Before the run a calibration says whether this machine can hold the rate")
    p.add_argument("--placement", choices=PLACEMENTS, default="auto",
                   help="CPU placement: auto = plant and controller share the last CPU, the recorder "
                        "gets the others (needs >= 2 CPUs, else none); none = leave it to the OS")
    p.add_argument("--transport", choices=("auto", "unix", "tcp"), default="auto",
                   help="the link between the run's processes: auto = Unix-domain sockets where they "
                        "work, else TCP loopback (the summary says which); unix; tcp")
    p.add_argument("--no-record", action="store_true",
                   help="no recorder process, no .mcap/.rrd (the summary's orbit lines need the recording)")
    p.add_argument("--record-source", choices=("plant", "wire"), default="plant",
                   help="plant: the recorder gets the loop's messages in the plant's batches, off the "
                        "loop's path; wire: it subscribes to them directly (the loop pays; for comparison)")
    add_out(p, "recordings", "<run-id>.mcap and <run-id>.rrd")
    p.add_argument("--strict", action="store_true",
                   help="refuse to run when the sampled loop at the scene's rate and latency is unstable, "
                        "and fail a run in which the plant or controller rejected messages (another "
                        "process published into the run, or malformed traffic)")
    p.add_argument("--endpoint", metavar="ENDPOINT",
                   help="the plant's listen endpoint (default: a free port on 127.0.0.1)")
    p.add_argument("--controller", metavar="CMD",
                   help="run this command as the controller instead of `ambhil controller` (placeholders {scene}, "
                        "{run_id}, {connect} = the plant's and recorder's endpoints), e.g. "
                        "\"ambhil controller {scene} --run-id {run_id} --connect {connect}\"; its exit code says "
                        "how it ended")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="show each process's start-up steps (model, kernels, waiting, pairing); "
                        "without it only a kernel compilation and the plant's start are shown")
    p.set_defaults(func=_run)

    p = command(sub, "replay", "MCAP -> rerun .rrd, or replay the sensor stream into a controller")
    p.add_argument("mcap", metavar="RUN.mcap", help="a recording (ambhil run / ambhil record)")
    add_out(p, None, "the .rrd, named like the recording (default: the recording's folder)")
    p.add_argument("--to-controller", action="store_true",
                   help="re-publish the sensors to a controller and compare its currents with the recorded ones")
    p.add_argument("--scene", metavar="SCENE",
                   help="with --to-controller: start `ambhil controller SCENE` as the controller under test")
    p.add_argument("--gain-scale", type=float, default=1.0, metavar="K", help="with --scene: scale that controller's output")
    p.add_argument("--listen", metavar="ENDPOINT", help="endpoint the replay listens on (default: a free loopback port)")
    p.add_argument("--run-id", help="run id for the replay traffic (default: replay-<pid>)")
    p.add_argument("--controller-cmd", metavar="CMD",
                   help="with --to-controller: launch CMD as the controller under test, any language "
                        "({run_id} and {connect} in CMD are replaced; also in $AMBHIL_RUN_ID, "
                        "$AMBHIL_CONNECT); docs/controllers.md")
    p.add_argument("--tolerance", type=float, default=0.0, metavar="A",
                   help="largest allowed current deviation per axis, A (0 = bit for bit)")
    p.add_argument("--start-timeout", type=float, default=30.0, metavar="S",
                   help="s a controller started by hand may be absent before giving up")
    add_json(p)
    p.set_defaults(func=_replay)

    p = command(sub, "certs", "make a CA and a certificate per role (plant, controller, recorder) for --secure")
    p.add_argument("dir", metavar="DIR", help="folder for ca.pem and <role>.pem/.key (created)")
    p.add_argument("--host", default="127.0.0.1", help="address or name the certificates are valid for")
    p.add_argument("--days", type=int, default=825, help="validity, days")
    p.add_argument("--force", action="store_true", help="replace existing certificates")
    add_json(p)
    p.set_defaults(func=_certs)

    p = command(sub, "recover", "restore the readable part of a truncated MCAP (e.g. a recorder killed with SIGKILL)")
    p.add_argument("src", metavar="SRC", help="the truncated recording (never modified)")
    p.add_argument("dst", nargs="?", metavar="DST", help="the new file (default: SRC with .recovered.mcap)")
    p.add_argument("--force", action="store_true", help="replace DST if it exists")
    add_json(p)
    p.set_defaults(func=_recover)
