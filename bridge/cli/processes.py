"""The zenoh processes of a HIL run as commands: `ambhil plant`, `ambhil controller`,
`ambhil record` (each started by `ambhil run`, bridge/cli/run.py, or by hand across hosts), and
`ambhil certs` (their certificates for ``--secure``).  Each builds its step object, declares
itself at once (bridge/process/startup.py), and hands a config object
(bridge/process/config.py) made from its parsed flags to the node.

zenoh is imported inside the handlers (with the nodes and the recorder), never at module level:
`ambhil --help` and the commands that are no process stay quick.
"""
from __future__ import annotations

import importlib
import json
import os
import signal
import threading
from pathlib import Path

import numpy as np

from ambhil.controller import hardware as hw
from ambhil.controller.law_runner import LawRunner
from ambhil.loop.scene import load_scene, with_fault_flags
from ambhil.loop.system import compile_system, controller_runner
from ambhil.bridge.cli.arguments import law_label
from ambhil.bridge.cli.convention import HARD_EXIT, INTERRUPTED, CliError, emit
from ambhil.bridge.cli.keyfile import auth_line, check_endpoints, process_secret
from ambhil.bridge.cli.run_setup import (check_currents_at, duration_steps, latency_s, plant_runner,
                                         run_meta)
from ambhil.bridge.cli.run_files import mark_failed
from ambhil.bridge.process.config import ControllerNodeConfig, PlantNodeConfig
from ambhil.bridge.process.security import SecurityError, configure, make_certs
from ambhil.bridge.process.timing import pin_cpus


def _json_out(summary: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(summary, default=str), flush=True)


def _kernel_text(module: str, fn: str, what: str) -> str:
    """Progress line for loading ``what``: says when numba compiles (no cache index yet)."""
    try:
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
        try:
            configure(args.secure, role, args.run_id)
        except SecurityError as e:
            raise CliError(str(e)) from None


def _key(args) -> bytes | None:
    """``--key-file`` (or ``$AMBHIL_KEY_FILE``) read and checked, and the safe default: no
    listening or connecting beyond this host without a key, ``--secure`` or ``--insecure``
    (bridge/cli/keyfile.py).  Before any session is opened: a refused process never appears on
    the network.  Sets ``args.key_path`` for the summary."""
    secret, args.key_path = process_secret(args)
    check_endpoints(args.listen, args.connect, secret=secret, secure=getattr(args, "secure", None),
                    insecure=args.insecure)
    return secret


def _presence(args, role: str, secret: bytes | None):
    """Declare this process at once (``starting/<role>``), before any heavy work.  CPU pinning
    (``--cpus``) comes later, once the model is built (:func:`_pin`)."""
    from ambhil.bridge.process import transport as tr                  # zenoh: see the docstring
    from ambhil.bridge.process.startup import Presence
    _secure(args, role)
    try:
        return Presence.open(args.run_id, role, listen=args.listen, connect=args.connect or None,
                             secret=secret, insecure=args.insecure)
    except (tr.TransportError, ValueError) as e:
        raise SystemExit(f"ambhil {role}: {e}")


def _auth_out(role: str, s: dict, args) -> str:
    """The single process's summary gains its key file (its node gives ``auth``, the mode, and
    ``strangers``); returns the human ``<role>: auth ...`` line."""
    s["key_file"] = args.key_path
    return auth_line(role, s, args.key_path, getattr(args, "secure", None))


def _pin(args) -> None:
    """``--cpus``: pin every thread of this process (zenoh's included), after the model was
    built: BLAS sizes its thread pool to the CPUs it sees at start, and the plan's rounding
    depends on that pool (a lockstep run must reproduce an unpinned in-process run bit for bit)."""
    pin_cpus(getattr(args, "cpus", None), all_threads=True)


def _term_as_interrupt() -> None:
    """SIGTERM (``kill``, `ambhil run` stopping its plant, the parent-death signal of a killed
    `ambhil run`) ends this process as Ctrl-C does: a clean stop with its summary, not a death
    without one."""
    if threading.current_thread() is threading.main_thread():
        def _term(signum, frame):
            raise KeyboardInterrupt
        signal.signal(signal.SIGTERM, _term)


# --------------------------------------------------------------------------- plant
def plant_config(args, n_steps: int, meta: dict, secret: bytes | None = None) -> PlantNodeConfig:
    """The plant node's configuration from `ambhil plant`'s parsed flags."""
    return PlantNodeConfig(
        run_id=args.run_id, n_steps=n_steps, mode=args.mode, currents_at=args.currents_at,
        max_overruns=args.max_overruns, wait_recorder=args.wait_recorder, meta=meta,
        start_timeout=args.start_timeout, cpus=args.cpus,
        reply_timeout=None if args.reply_timeout is None else args.reply_timeout / 1e3,
        cpu_wake_us=args.cpu_wake_us, rt_receive=args.rt_receive,
        secret=secret, insecure=getattr(args, "insecure", False))


def cmd_plant(args) -> int:
    HARD_EXIT[0] = True                 # a zenoh process: end without interpreter shutdown (cli.entry)
    _term_as_interrupt()
    from ambhil.bridge.process.events import exit_code                    # zenoh: see the docstring
    from ambhil.bridge.process.plant_node import run_plant
    secret = _key(args)
    scene = with_fault_flags(load_scene(args.scene), args.fault)
    n = duration_steps(scene, args.duration)
    latency = latency_s(args, scene)
    check_currents_at(args, latency)
    presence = _presence(args, "plant", secret)
    try:
        presence.progress("building the model")
        model = compile_system(scene, rung=args.rung)
        runner = plant_runner(scene, model, args.integrator, args.h, latency)
        presence.progress(_kernel_text("ambhil.plant.integrator", "plant_advance", "the plant kernels"))
        runner.reset(); runner.advance(np.zeros(runner.n_axes))  # compile/load the kernels before going live
        _pin(args)
        cfg = plant_config(args, n, run_meta(scene, model, args.integrator, latency, law=args.law), secret)
        s = run_plant(runner, cfg, presence=presence)
    finally:
        presence.close(session_too=True)
    auth = _auth_out("plant", s, args)
    _json_out(s, args.json)
    if not args.json:
        print(f"plant: {s['steps']}/{s['n_steps']} steps, {s['mode']}, {s['steps_per_s']:.0f} steps/s, "
              f"overruns {s['overruns']}" + (f"; FAULT: {s['fault']}" if s["fault"] else ""))
        print(auth)
    return INTERRUPTED if s.get("end_reason") == "interrupted" else exit_code(s)


# --------------------------------------------------------------------------- controller
class _Scaled:
    """A controller whose output is scaled: the 'changed gain' of a regression test."""

    def __init__(self, inner, k):
        self.inner, self.k, self.n_axes = inner, k, inner.n_axes

    def reset(self):
        return self.inner.reset()

    def step(self, y):
        return self.k * self.inner.step(y)


def cmd_controller(args) -> int:
    HARD_EXIT[0] = True                 # a zenoh process: end without interpreter shutdown (cli.entry)
    from ambhil.bridge.process.controller_node import run_controller      # zenoh: see the docstring
    from ambhil.bridge.process.events import exit_code
    secret = _key(args)
    scene = load_scene(args.scene)
    presence = _presence(args, "controller", secret)
    try:
        presence.progress("building the controller")
        runner = controller_runner(scene, rung=args.rung, law=args.law)
        presence.progress(_kernel_text("ambhil.controller.discrete", "controller_step", "the controller kernel"))
        _warm(runner)
        if args.gain_scale != 1.0:  # a deliberately changed controller (regression-test demo)
            runner = _Scaled(runner, args.gain_scale)
        _pin(args)
        cfg = ControllerNodeConfig(run_id=args.run_id, start_timeout=args.start_timeout, cpus=args.cpus,
                                   secret=secret, insecure=args.insecure)
        s = run_controller(runner, cfg, presence=presence)
    finally:
        presence.close(session_too=True)
    s["law"] = law_label(args.law, scene)
    auth = _auth_out("controller", s, args)
    _json_out(s, args.json)
    if not args.json:
        print(f"controller: {s.get('steps', s.get('answered', '?'))} samples answered (law {s['law']})"
              + (f"; FAULT: {s['fault']}" if s.get("fault") else ""))
        print(auth)
    return exit_code(s)


def _warm(runner) -> None:
    """Compile/load the controller's kernels before going live.  The built-in fused kernel takes a
    step (its reset undoes it); a law runs between the hardware kernels, which are warmed on a
    copy of their state: the law itself is not stepped, so its first step is the run's step 0
    at t = 0, as in ``simulate`` (a law need not have a reset())."""
    if not isinstance(runner, LawRunner):
        runner.reset(); runner.step(np.zeros(runner.n_axes))
        return
    h, y, u = runner.state.copy(), np.zeros(runner.n_axes), np.zeros(runner.n_axes)
    hw.sensor_step(runner.hw_params, h, np.zeros(runner.n_axes), y)
    hw.amplifier_step(runner.hw_params, h, u, np.zeros(runner.n_axes))


# --------------------------------------------------------------------------- recorder
def record_file(args) -> None:
    """``record --out`` is a folder; the file in it is named for the run (parsed-args finaliser)."""
    Path(args.out).mkdir(parents=True, exist_ok=True)
    args.out = str(Path(args.out) / f"{args.run_id}.mcap")


def cmd_record(args) -> int:
    HARD_EXIT[0] = True                 # a zenoh process: end without interpreter shutdown (cli.entry)
    from ambhil.bridge.recording.recorder import RecorderConfig, record   # zenoh: see the docstring
    secret = _key(args)
    _secure(args, "recorder")
    pin_cpus(args.cpus)
    s = record(args.run_id, args.out, RecorderConfig(
        listen=args.listen, connect=args.connect or None, start_timeout=args.start_timeout, echo=True,
        source=args.source, owner_pid=args.owner_pid, secret=secret, insecure=args.insecure))
    if args.owner_pid and str(s.get("end_reason")).startswith("ambhil run") and os.path.exists(s["path"]):
        s["files"] = _orphaned(s["path"], args.run_id)
    auth = _auth_out("recorder", s, args)
    _json_out(s, args.json)
    if not args.json:
        print(f"recorder: {s['messages']} messages -> {s['path']} ({s['end_reason']}); run {s['status']}"
              + (f": {s['fault']}" if s.get("fault") else "")
              + (f"; {s['steps_recorded']} of {s['steps_run']} steps recorded"
                 if s.get("steps_run") is not None and s["steps_recorded"] < s["steps_run"] else ""))
        print(auth)
    return 0 if s.get("path") and not s.get("write_error") else 1


def _orphaned(path: str, run_id: str) -> list[str]:
    """The recorder of an `ambhil run` that died (killed, SIGKILL): nobody else will finish the
    run's files, so it does what the run would have: the recording renamed
    ``<run-id>.failed.mcap`` (its ``ambhil.run_end`` says stopped and why) and its
    ``.failed.rrd`` written.  Returns the files."""
    mcap = Path(path)
    files = mark_failed(mcap)
    out = [str(f) for f in files]
    if files:
        try:
            from ambhil.bridge.recording.replay import to_rerun             # rerun: only when writing
            rrd = files[0].with_suffix(".rrd")
            to_rerun(str(files[0]), str(rrd), recording_id=run_id)
            out.append(str(rrd))
        except Exception:           # nobody reads our stderr any more: the summary says what was written
            pass
    return out


# --------------------------------------------------------------------------- certificates
def cmd_certs(args) -> int:
    try:
        out = make_certs(args.dir, host=args.host, days=args.days, force=args.force)
    except SecurityError as e:
        raise CliError(str(e)) from None
    emit(args, {"command": "certs", "files": out},
         lambda: print(f"certificates for plant, controller, recorder (valid for {args.host}) in {args.dir}: "
                       f"{', '.join(os.path.basename(f) for f in out)}"))
    return 0
