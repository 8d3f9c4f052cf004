"""CLI of the HIL processes: `plant`, `controller`, `record`, `run`, `replay`, `recover`.

`ambhil run SCENE` starts recorder, controller and plant as separate OS processes on an explicit
loopback mesh (the recorder listens; the plant listens and connects to the recorder; the
controller connects to both), waits for the plant, shuts everything down cleanly (also on
Ctrl-C), prints a summary and leaves `<run-id>.mcap` and `<run-id>.rrd` in `recordings/`.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from plant.scene import SceneError, load_scene

MODES = ("lockstep", "realtime")
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
    sim = getattr(scene, "simulation", None)
    d = duration if duration is not None else (getattr(sim, "duration", None) or 1.0)
    if not d > 0:
        raise SceneError(f"{scene.path}: --duration must be > 0 s, got {d}")
    return max(1, int(round(d * scene.controller.sample_rate)))


def run_meta(scene, model, args) -> dict:
    """Metadata carried by the RunMeta message and the MCAP file."""
    stations = [a.name for a in scene.ambs] + ([scene.axial_amb.name] if scene.axial_amb else [])
    return {
        "scene": scene.name, "scene_path": str(Path(scene.path).resolve()),
        "scene_toml": Path(scene.path).read_text() if Path(scene.path).exists() else "",
        "rung": model.rung, "integrator": getattr(args, "integrator", None) or getattr(
            getattr(scene, "simulation", None), "integrator", "bdf1"),
        "controller_rate_hz": scene.controller.sample_rate,
        "axis_names": [f"{a}-{x}" for a, x in model.axes],
        "station_names": stations,
        "gaps_m": [a.gap for a in scene.ambs],
        "speed_rad_s": getattr(getattr(scene, "simulation", None), "speed", None) or scene.speed.nominal,
    }


# --------------------------------------------------------------------------- plant / controller
def _plant(args) -> int:
    from plant.model import compile_model
    from plant.step import PlantRunner
    from . import nodes
    scene = load_scene(args.scene)
    model = compile_model(scene, rung=args.rung)
    runner = PlantRunner(model, integrator=args.integrator)
    runner.reset(); runner.advance(np.zeros(runner.n_axes))  # compile/load the kernels before going live
    n = _duration_steps(scene, args.duration)
    s = nodes.run_plant(runner, args.run_id, listen=args.listen, connect=args.connect or None, mode=args.mode,
                        n_steps=n, delay_samples=args.delay, max_overruns=args.max_overruns,
                        wait_recorder=args.wait_recorder, meta=run_meta(scene, model, args),
                        start_timeout=args.start_timeout, cpus=args.cpus,
                        reply_timeout=None if args.reply_timeout is None else args.reply_timeout / 1e3)
    _json_out(s, args.json)
    if not args.json:
        print(f"plant: {s['steps']}/{s['n_steps']} steps, {s['mode']}, {s['steps_per_s']:.0f} steps/s, "
              f"overruns {s['overruns']}" + (f"; FAULT: {s['fault']}" if s["fault"] else ""))
    return nodes.exit_code(s)


def _controller(args) -> int:
    from controller.discrete import ControllerRunner
    from . import nodes
    scene = load_scene(args.scene)
    runner = ControllerRunner(scene)
    runner.reset(); runner.step(np.zeros(runner.n_axes))  # compile/load the kernel before going live
    if args.gain_scale != 1.0:  # a deliberately changed controller (regression-test demo)
        runner = _Scaled(runner, args.gain_scale)
    s = nodes.run_controller(runner, args.run_id, connect=args.connect or None, listen=args.listen,
                             start_timeout=args.start_timeout, cpus=args.cpus)
    _json_out(s, args.json)
    if not args.json:
        print(f"controller: {s.get('steps', s.get('answered', '?'))} samples answered"
              + (f"; FAULT: {s['fault']}" if s.get("fault") else ""))
    return nodes.exit_code(s)


class _Scaled:
    """A controller whose output is scaled: the 'changed gain' of a regression test."""

    def __init__(self, inner, k):
        self.inner, self.k, self.n_axes = inner, k, inner.n_axes

    def reset(self):
        return self.inner.reset()

    def step(self, y):
        return self.k * self.inner.step(y)


def _record(args) -> int:
    from .recorder import record
    from .timing import pin_cpus
    pin_cpus(args.cpus)
    s = record(args.run_id, args.out, listen=args.listen, connect=args.connect or None,
               start_timeout=args.start_timeout)
    _json_out(s, args.json)
    if not args.json:
        print(f"recorder: {s['messages']} messages -> {s['path']} ({s['end_reason']})")
    return 0 if s.get("path") else 1


# --------------------------------------------------------------------------- run
def _spawn(argv: list[str]) -> subprocess.Popen:
    # the children inherit the caller's environment unchanged (BLAS threads included): the plan
    # matrices are built with BLAS, whose rounding depends on its thread count, and a lockstep
    # run must reproduce an in-process run of the same environment bit for bit
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "bridge.cli"] + argv, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)


def _last_json(p: subprocess.Popen, timeout: float) -> tuple[dict | None, str]:
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
    lines = [ln for ln in (out or "").splitlines() if ln.startswith("{")]
    return (json.loads(lines[-1]) if lines else None), (err or "")


def _stop(p: subprocess.Popen, sig=signal.SIGTERM):
    if p.poll() is None:
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass


def orbit_report(mcap: str, gaps: list[float], stations: list[str]) -> list[tuple[str, float, float]]:
    """(station, largest orbit radius (m), radius / gap) from the recorded sensor stream."""
    from .replay import load_run
    v = load_run(mcap)["sensors"]["v"]
    out = []
    for k, (name, gap) in enumerate(zip(stations, gaps)):
        if v.shape[1] >= 2 * k + 2:
            r = float(np.max(np.hypot(v[:, 2 * k], v[:, 2 * k + 1]))) if len(v) else 0.0
            out.append((name, r, r / gap))
    return out


def _fmt(st: dict) -> str:
    return (f"p50 {st.get('p50', float('nan')):.1f} / p99 {st.get('p99', float('nan')):.1f} / "
            f"max {st.get('max', float('nan')):.1f} us" if st.get("n") else "n/a")


def _run(args) -> int:
    from plant.model import compile_model
    from plant.step import PlantRunner
    from . import transport as tr
    scene = load_scene(args.scene)
    model = compile_model(scene, rung=args.rung)
    PlantRunner(model, integrator=args.integrator)  # refuse now what the plant process would ([simulation] step)
    n = _duration_steps(scene, args.duration)
    run_id = args.run_id or f"{scene.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    mcap, rrd = outdir / f"{run_id}.mcap", outdir / f"{run_id}.rrd"
    ep_p, ep_r = tr.tcp_endpoint(tr.free_port()), tr.tcp_endpoint(tr.free_port())
    common = ["--run-id", run_id, "--json", "--start-timeout", str(args.start_timeout)]
    cpus = placement_cpus(args.placement)

    def pin(role):
        return ["--cpus", ",".join(map(str, cpus[role]))] if role in cpus else []
    rec = _spawn(["record", "--out", str(mcap), "--listen", ep_r] + common + pin("recorder"))
    ctl = _spawn(["controller", args.scene, "--connect", ep_p, ep_r] + common + pin("controller"))
    plant_argv = ["plant", args.scene, "--listen", ep_p, "--connect", ep_r, "--wait-recorder",
                  "--mode", args.mode, "--delay", str(args.delay), "--duration", str(n / scene.controller.sample_rate)]
    for flag, val in (("--rung", args.rung), ("--integrator", args.integrator), ("--max-overruns", args.max_overruns),
                      ("--reply-timeout", args.reply_timeout)):
        if val is not None:
            plant_argv += [flag, str(val)]
    pl = _spawn(plant_argv + common + pin("plant"))
    procs = {"plant": pl, "controller": ctl, "recorder": rec}
    interrupted = False
    try:
        while pl.poll() is None:
            for name, p in (("controller", ctl), ("recorder", rec)):
                if p.poll() is not None and p.returncode != 0:
                    raise RuntimeError(f"{name} exited early with code {p.returncode}")
            time.sleep(0.05)
    except KeyboardInterrupt:
        interrupted = True
        print("ambhil run: interrupted, stopping plant, controller and recorder ...", file=sys.stderr)
        _stop(pl, signal.SIGINT)
    except RuntimeError as e:
        print(f"ambhil run: {e}", file=sys.stderr)
        _stop(pl)
    results = {}
    for name in ("plant", "controller", "recorder"):
        p = procs[name]
        s, err = _last_json(p, timeout=10.0 if name != "recorder" else 20.0)
        if s is None:
            _stop(p)
            s, err2 = _last_json(p, timeout=5.0)
            err += err2
        results[name] = (s, err, p.returncode)
    sp, sc, sr = (results[k][0] for k in ("plant", "controller", "recorder"))
    if sr is None and mcap.exists():  # recorder died: restore what it wrote
        from .recover import recover
        fixed = mcap.with_suffix(".recovered.mcap")
        k = recover(str(mcap), str(fixed))
        fixed.replace(mcap)
        print(f"ambhil run: recorder did not finish; recovered {k} messages into {mcap}", file=sys.stderr)
    rrd_ok = False
    if mcap.exists():
        try:
            from .replay import to_rerun
            to_rerun(str(mcap), str(rrd), recording_id=run_id)
            rrd_ok = True
        except Exception as e:  # a replay problem must not lose the run's MCAP
            print(f"ambhil run: could not write {rrd}: {e}", file=sys.stderr)

    # ---- summary
    print(f"run {run_id}: scene {scene.name}, rung {model.rung}, mode {args.mode}, "
          f"controller {scene.controller.sample_rate:g} Hz" + (f", delay {args.delay} samples" if args.delay else ""))
    if sp:
        print(f"  steps      {sp['steps']}/{sp['n_steps']} ({sp['steps'] / scene.controller.sample_rate:.3f} s simulated) "
              f"in {sp['wall_s']:.2f} s wall, {sp['steps_per_s']:.0f} steps/s")
        if args.mode == "realtime":
            counted = max(sp["steps"] - sp.get("warmup_steps", 0), 0)
            frac = sp["overruns"] / counted if counted else 0.0
            print(f"  overruns   {sp['overruns']} of {counted} periods after the warm-up ({100 * frac:.2f} %; "
                  f"held currents {sp.get('held', 0)})")
            if frac > 0.01:
                print(f"  note       more than 1 % overruns: this machine does not sustain "
                      f"{scene.controller.sample_rate:g} Hz real time with this plant (docs/hil.md); "
                      f"lockstep runs at any rate")
        else:
            print(f"  overruns   {sp['overruns']}")
        print(f"  latency    round trip {_fmt(sp['latency_us'])}; controller TET {_fmt(sp['tet_us'])}")
        if args.mode == "realtime":
            print(f"  wake late  {_fmt(sp['lateness_us'])}")
        if sp.get("rejected_total"):
            print(f"  rejected   {sp['rejected_total']} messages {sp['rejected']}")
    if mcap.exists():
        try:
            for name, r, frac in orbit_report(str(mcap), [a.gap for a in scene.ambs], [a.name for a in scene.ambs]):
                print(f"  orbit {name:4s} largest radius {r * 1e6:8.2f} um = {100 * frac:5.1f}% of the clearance")
        except Exception as e:
            print(f"  orbit: could not read the recording: {e}")
    print(f"  files      {mcap}" + (f", {rrd}" if rrd_ok else ""))
    reasons = []
    if interrupted:
        reasons.append("interrupted by the user")
    for name in ("plant", "controller"):
        s, err, code = results[name]
        if s is None:
            tail = err.strip().splitlines()[-1] if err.strip() else f"exit code {code}"
            reasons.append(f"{name} gave no summary ({tail})")
        elif s.get("fault"):
            reasons.append(f"{name}: {s['fault']}")
    if sr is None:
        reasons.append("recorder gave no summary")
    if reasons:
        print(f"ambhil run: FAILED: {'; '.join(reasons)}", file=sys.stderr)
        return 130 if interrupted and len(reasons) == 1 else 1
    return 0


# --------------------------------------------------------------------------- replay / recover
def _replay(args) -> int:
    from . import replay
    if not Path(args.mcap).exists():
        raise SceneError(f"{args.mcap}: no such recording")
    if not args.to_controller:
        rrd = args.out or str(Path(args.mcap).with_suffix(".rrd"))
        info = replay.to_rerun(args.mcap, rrd)
        print(f"wrote {rrd}: {info['samples']} samples, stations {', '.join(info['stations'])}; "
              f"open it with: rerun {rrd}")
        return 0
    from . import transport as tr
    ep = args.listen or tr.tcp_endpoint(tr.free_port())
    run_id = args.run_id or f"replay-{os.getpid()}"
    ctl = None
    if args.scene:  # start the controller under test ourselves
        argv = ["controller", args.scene, "--run-id", run_id, "--connect", ep, "--json"]
        if args.gain_scale != 1.0:
            argv += ["--gain-scale", str(args.gain_scale)]
        ctl = _spawn(argv)
    else:
        print(f"waiting for a controller: ambhil controller SCENE --run-id {run_id} --connect {ep}", file=sys.stderr)
    try:
        res = replay.to_controller(args.mcap, run_id, listen=ep, tolerance=args.tolerance)
    finally:
        if ctl is not None:
            _last_json(ctl, timeout=10.0)
    w = res.get("worst") or {}
    verdict = "PASS" if res["passed"] else "FAIL"
    print(f"replay-to-controller {verdict}: {res.get('compared', 0)} samples compared, largest deviation "
          f"{res['max_abs_dev']:.3g} A" + (f" at step {w.get('step')} axis {w.get('axis')} "
                                           f"(recorded {w.get('recorded'):.6g}, replayed {w.get('replayed'):.6g})"
                                           if w else "") + f", tolerance {args.tolerance:g} A")
    return 0 if res["passed"] else 1


def _recover(args) -> int:
    from .recover import recover
    if not Path(args.src).exists():
        raise SceneError(f"{args.src}: no such recording")
    dst = args.dst or str(Path(args.src).with_suffix(".recovered.mcap"))
    n = recover(args.src, dst)
    print(f"recovered {n} messages from {args.src} into {dst}")
    return 0


def add_parsers(sub) -> None:
    def common(p, scene=True):
        if scene:
            p.add_argument("scene", help="scene TOML file")
        p.add_argument("--run-id", required=p.prog.split()[-1] in ("plant", "controller", "record"),
                       help="run identifier (key expressions ambhil/<run-id>/...)")
        p.add_argument("--json", action="store_true", help="print the summary as one JSON line")
        p.add_argument("--start-timeout", type=float, default=30.0, help="s to wait for peers")
        if p.prog.split()[-1] in ("plant", "controller", "record"):
            p.add_argument("--cpus", type=_cpu_list, help="pin this process (all its threads) to "
                           "these CPUs, e.g. 1 or 0,1 (set before zenoh starts its threads)")

    p = sub.add_parser("plant", help="the plant process: integrates the rotor, publishes sensor displacements")
    common(p)
    p.add_argument("--listen", required=True, help="zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--connect", nargs="*", default=[], help="endpoints to connect to (e.g. the recorder)")
    p.add_argument("--mode", choices=MODES, default="lockstep")
    p.add_argument("--duration", type=float, help="simulated s (default [simulation] duration or 1 s)")
    p.add_argument("--delay", type=int, default=0, help="emulated transport delay in samples (lockstep)")
    p.add_argument("--max-overruns", type=int, help="realtime: halt after N overruns")
    p.add_argument("--reply-timeout", type=_positive_ms, metavar="MS",
                   help="declare the controller dead after MS without any reply (default: 10 "
                        "controller periods in real time; max(10 periods, 100 ms) in lockstep)")
    p.add_argument("--wait-recorder", action="store_true", help="start only once a recorder is present")
    p.add_argument("--rung", choices=("rigid", "modal", "full"))
    p.add_argument("--integrator", choices=("bdf1", "bdf2", "trapezoidal", "generalized-alpha", "zoh"))
    p.set_defaults(func=_plant)

    p = sub.add_parser("controller", help="the discrete PID controller process: returns coil currents")
    common(p)
    p.add_argument("--connect", nargs="*", default=[], help="endpoints to connect to (the plant, the recorder)")
    p.add_argument("--listen", help="endpoint to listen on (optional)")
    p.add_argument("--gain-scale", type=float, default=1.0, help="scale the controller output (testing)")
    p.set_defaults(func=_controller)

    p = sub.add_parser("record", help="record all traffic of a run to MCAP")
    common(p, scene=False)
    p.add_argument("--out", required=True, help="MCAP file to write")
    p.add_argument("--listen", help="endpoint to listen on")
    p.add_argument("--connect", nargs="*", default=[], help="endpoints to connect to")
    p.set_defaults(func=_record)

    p = sub.add_parser("run", help="plant + controller + recorder as separate processes; summary; .mcap and .rrd")
    common(p)
    p.add_argument("--mode", choices=MODES, default="lockstep")
    p.add_argument("--duration", type=float, help="simulated s (default [simulation] duration or 1 s)")
    p.add_argument("--delay", type=int, default=0, help="emulated transport delay in samples (lockstep)")
    p.add_argument("--max-overruns", type=int, help="realtime: halt after N overruns")
    p.add_argument("--reply-timeout", type=_positive_ms, metavar="MS",
                   help="plant: controller dead after MS without any reply (default 10 periods)")
    p.add_argument("--rung", choices=("rigid", "modal", "full"))
    p.add_argument("--integrator", choices=("bdf1", "bdf2", "trapezoidal", "generalized-alpha", "zoh"))
    p.add_argument("--placement", choices=PLACEMENTS, default="auto",
                   help="CPU placement: auto = plant and controller share the last CPU, the recorder "
                        "gets the others (needs >= 2 CPUs, else none); none = leave it to the OS")
    p.add_argument("--out", default="recordings", help="folder for the .mcap and .rrd (default recordings/)")
    p.set_defaults(func=_run)

    p = sub.add_parser("replay", help="MCAP -> rerun .rrd, or replay the sensor stream into a controller")
    p.add_argument("mcap")
    p.add_argument("--out", help=".rrd to write (default: beside the .mcap)")
    p.add_argument("--to-controller", action="store_true", help="re-publish sensors to a controller and compare currents")
    p.add_argument("--scene", help="with --to-controller: start `ambhil controller SCENE` as the controller under test")
    p.add_argument("--gain-scale", type=float, default=1.0, help="with --scene: scale that controller's output")
    p.add_argument("--listen", help="endpoint the replay listens on (default: a free loopback port)")
    p.add_argument("--run-id", help="run id for the replay traffic")
    p.add_argument("--tolerance", type=float, default=1e-9, help="largest allowed current deviation (A)")
    p.set_defaults(func=_replay)

    p = sub.add_parser("recover", help="restore a truncated MCAP (e.g. a recorder killed with SIGKILL)")
    p.add_argument("src")
    p.add_argument("dst", nargs="?")
    p.set_defaults(func=_recover)
