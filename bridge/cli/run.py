"""`ambhil run SCENE`: recorder, controller and plant as separate OS processes on an explicit
loopback mesh (the recorder listens; the plant listens and connects to the recorder; the
controller connects to both).  It checks the scene's sampled loop first, shows the peers'
start-up progress, waits for the plant, shuts everything down cleanly (also on Ctrl-C), prints a
summary that says first what failed, and leaves `<run-id>.mcap` and `<run-id>.rrd` (renamed
`.failed.*` for a failed run) in the output folder.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ambhil.loop.scene import SceneError, load_scene, touchdown_note, with_fault_flags
from ambhil.bridge.cli.hil import _duration_steps, check_currents_at, latency_of, placement_cpus, plant_runner


def _die_with_parent() -> None:
    """In the child, before exec: the kernel sends it SIGTERM when the process that started it
    dies (Linux ``PR_SET_PDEATHSIG``), so `ambhil run` killed from outside (SIGKILL, a
    ``timeout`` wrapper) does not leave its plant, controller and recorder running; SIGTERM
    lets each end as on Ctrl-C (the recorder closes its file).  And SIGINT is not ignored in
    the child (below).  No-op elsewhere."""
    if sys.platform.startswith("linux"):
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        # `ambhil run` stops its plant with SIGINT (Ctrl-C's path: summary, RUN_END, file
        # closed).  Started with SIGINT ignored (a background job of a script, nohup), the
        # children would inherit the ignore and never stop that way: give them the default
        # disposition (Python then installs its KeyboardInterrupt handler).  libc's signal():
        # Python's signal.signal refuses to run outside the main thread.
        libc.signal.argtypes, libc.signal.restype = [ctypes.c_int, ctypes.c_void_p], ctypes.c_void_p
        libc.signal(signal.SIGINT, None)        # SIG_DFL


def spawn_cli(argv: list[str]) -> subprocess.Popen:
    # the children inherit the caller's environment unchanged (BLAS threads included): the plan
    # matrices are built with BLAS, whose rounding depends on its thread count, and a lockstep
    # run must reproduce an in-process run of the same environment bit for bit
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "ambhil.bridge.cli"] + argv, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, start_new_session=True,
                            preexec_fn=_die_with_parent)


def last_json(p: subprocess.Popen, timeout: float) -> tuple[dict | None, str]:
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
    lines = [ln for ln in (out or "").splitlines() if ln.startswith("{")]
    return (json.loads(lines[-1]) if lines else None), (err or "")


def stop_process(p: subprocess.Popen, sig=signal.SIGTERM):
    if p.poll() is None:
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass


def orbit_report(mcap: str, clearances: list[float], stations: list[str]) -> list[tuple[str, float, float]]:
    """(station, largest orbit radius (m), radius / touchdown clearance) from the recorded sensor stream."""
    from ambhil.bridge.recording.replay import load_run
    v = load_run(mcap, raw=False)["sensors"]["v"]
    out = []
    for k, (name, c) in enumerate(zip(stations, clearances)):
        if v.shape[1] >= 2 * k + 2:
            r = float(np.max(np.hypot(v[:, 2 * k], v[:, 2 * k + 1]))) if len(v) else 0.0
            out.append((name, r, r / c))
    return out


def foreign_report(sp: dict | None, sc: dict | None) -> str | None:
    """One line on the messages the plant and controller rejected (None if none): a run that
    saw another process publish into it, or malformed traffic, says so."""
    parts = []
    for role, s in (("plant", sp), ("controller", sc)):
        if s and s.get("rejected_total"):
            why = ", ".join(f"{k} {v}" for k, v in sorted(s["rejected"].items()))
            parts.append(f"{role} rejected {s['rejected_total']} messages ({why})")
    extra = (sp or {}).get("foreign_peers") or 0
    if extra:
        parts.append(f"{extra} further controller(s) announced themselves")
    if sc and sc.get("foreign_run_ends"):
        parts.append(f"controller ignored {sc['foreign_run_ends']} RUN_END events not from its plant")
    if not parts:
        return None
    peer = sum((s.get("rejected", {}).get("peer") or 0) for s in (sp, sc) if s)
    # plant and controller put what they reject as foreign again for the recorder (bridge/process/events.py,
    # ForeignCopies: at most 1000 each); an external controller's summary may not say
    copied = sum((s.get("foreign_copied") or 0) for s in (sp, sc) if s)
    kept = ("its messages are in the recording under foreign/" if copied >= peer else
            f"{copied} of its {peer} messages are in the recording under foreign/" if copied else
            "its messages are not in the recording")
    return ("; ".join(parts) + (f": another process published into this run (ignored; {kept})"
                                if peer else ""))


def _fmt(st: dict) -> str:
    return (f"p50 {st.get('p50', float('nan')):.1f} / p99 {st.get('p99', float('nan')):.1f} / "
            f"max {st.get('max', float('nan')):.1f} us" if st.get("n") else "n/a")


def startup_step(line: str) -> bool:
    """A peer's start-up progress line (``<role>: <step>``, bridge/process/startup.py) that only ``-v``
    shows: all but a kernel compilation (minutes, first run only) and the plant's start."""
    role, sep, text = line.partition(": ")
    return (bool(sep) and role in ("plant", "controller", "recorder") and not text.startswith("compiling")
            and not line.startswith("plant: running"))


class _Child:
    """A child process whose output is read by threads: stdout kept (its last JSON line is the
    summary), stderr kept and echoed to our stderr while ``echo`` is set (the start-up progress
    lines, ``<role>: <step>``; the plant's ``plant: running`` line ends the start-up)."""

    def __init__(self, name: str, argv: list[str], echo: threading.Event, external: bool = False):
        self.name, self.echo, self.external = name, echo, external
        self.verbose = getattr(echo, "verbose", False)     # -v: every start-up step
        if external:   # a command of the user's (e.g. a controller in another language)
            env = dict(os.environ, PYTHONUNBUFFERED="1")
            self.p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                      start_new_session=True, preexec_fn=_die_with_parent)
        else:
            self.p = spawn_cli(argv)
        self.out: list[str] = []
        self.err: list[str] = []
        self._threads = [threading.Thread(target=self._read, args=(self.p.stdout, self.out, False), daemon=True),
                         threading.Thread(target=self._read, args=(self.p.stderr, self.err, True), daemon=True)]
        for t in self._threads:
            t.start()

    def _read(self, stream, sink, is_err):
        for line in stream:
            sink.append(line)
            if is_err and self.echo.is_set() and (self.verbose or not startup_step(line)):
                sys.stderr.write(line)
                sys.stderr.flush()
                if self.name == "plant" and line.startswith("plant: running"):
                    self.echo.clear()

    def result(self, timeout: float) -> tuple[dict | None, str, int | None]:
        """(summary or None, stderr, exit code) once the process ended (stopped after
        ``timeout`` s: SIGTERM, then SIGKILL)."""
        for sig, wait in ((None, timeout), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if sig is not None:
                stop_process(self.p, sig)
            try:
                self.p.wait(wait)
                break
            except subprocess.TimeoutExpired:
                continue
        for t in self._threads:
            t.join(2.0)
        lines = [ln for ln in self.out if ln.startswith("{")]
        try:
            s = json.loads(lines[-1]) if lines else None
        except ValueError:
            s = None
        if self.external and (not isinstance(s, dict) or "fault" not in s) and self.p.returncode is not None:
            # a command of the user's need not print our summary: its exit code says how it ended
            s = {"role": self.name, "external": True, "exit_code": self.p.returncode,
                 "fault": None if self.p.returncode == 0 else f"exited with code {self.p.returncode}"}
        return s, "".join(self.err), self.p.returncode


PLANT_END_CAP_S = 30.0     # s; last resort: a plant still running this long after its controller died


def exit_text(code: int | None) -> str:
    """How a process ended, from its exit code: ``killed by SIGKILL`` / ``exited with code 1``."""
    if code is None:
        return "still running when stopped"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


def _overrun_count(args):
    """``--max-overruns N`` (a count) is the plant's: it halts after N overruns."""
    lim = getattr(args, "max_overruns", None)
    return lim[1] if lim and lim[0] == "count" else None


def rate_check(args, scene, model, sp: dict | None, orbits: list, latency: float) -> dict | None:
    """Did a real-time run keep its rate?  ``--max-overruns P%``: more than P % of the periods
    after the warm-up overran -> ``kept`` False, and ``reason`` says so in one line with how far
    the run's largest orbit is from the in-process loop's of the same scene (bridge/cli/rt_check.py;
    what a run that kept its rate records).  None for lockstep, no limit or no plant summary."""
    lim = getattr(args, "max_overruns", None)
    if args.mode != "realtime" or not sp or not lim or lim[0] != "percent":
        return None
    warm = min(sp.get("warmup_steps", 0), sp["steps"])
    counted = sp["steps"] - warm
    pct = 100.0 * sp["overruns"] / counted if counted else 0.0
    out = {"overrun_percent": pct, "limit_percent": lim[1], "kept": pct <= lim[1],
           "reference": "in-process loop (ambhil.loop.simulation.simulate), same scene, rung, integrator, step, latency",
           "reference_orbits_m": None, "reason": None}
    if out["kept"]:
        return out
    fs = scene.controller.sample_rate
    text = (f"the loop did not keep {fs:g} Hz: {sp['overruns']} of {counted} periods overran ({pct:.2f} % > "
            f"--max-overruns {lim[1]:g} %), so its results are not the scene's")
    from ambhil.bridge.cli.rt_check import reference_orbits
    ref = reference_orbits(scene, model, args, sp["steps"], latency) if sp["steps"] else None
    if ref and orbits:
        out["reference_orbits_m"] = ref
        pairs = [(nm, r, q) for (nm, r, _), q in zip(orbits, ref) if q > 0]
        if pairs:
            nm, r, q = max(pairs, key=lambda t: abs(t[1] - t[2]))   # the largest difference
            text += (f": orbit {nm} {r * 1e6:.2f} um against {q * 1e6:.2f} um in process "
                     f"({100 * (r / q - 1):+.0f} %)")
    out["reason"] = text
    return out


def mark_failed(*paths: Path, why: str | None = None) -> list[Path]:
    """Rename a failed run's files ``<run-id>.mcap`` -> ``<run-id>.failed.mcap`` (same for the
    .rrd): a failed run is recognisable from its file names; the MCAP's ``ambhil.run_end``
    metadata says why: ``why`` goes into it where the recorder saw the run end normally
    (bridge/recording/recover.py, mark_run_failed).  Returns the new paths of the files that existed."""
    out = []
    for p in paths:
        if p.exists():
            if why and p.suffix == ".mcap":
                from ambhil.bridge.recording.recover import mark_run_failed
                try:
                    mark_run_failed(str(p), why)
                except Exception as e:      # the file stays as the recorder wrote it
                    print(f"ambhil run: note: could not write the verdict into {p}'s run_end: {e}",
                          file=sys.stderr)
            q = p.with_name(f"{p.stem}.failed{p.suffix}")
            p.replace(q)
            out.append(q)
    return out


def _precheck(args, scene, model, latency: float):
    """Before anything starts: the sampled loop at the scene's rate and this latency
    (ambhil.loop.timing_study.precheck), and whether the plant's integrator at its step misreports the
    loop (ambhil.loop.numerics.numerics_note: a warning, or a note that the check was skipped); one line each on stderr."""
    from ambhil.loop.numerics import numerics_note
    from ambhil.loop.timing_study import precheck
    sim = scene.plant.simulation
    if sim.run_up is not None:
        return None
    speed = sim.speed if sim.speed is not None else scene.plant.speed.value or 0.0
    pre = precheck(model, speed, latency)
    if pre.line:
        print(f"{args._prog}: {'error' if args.strict and not pre.stable else 'warning'}: {pre.line}", file=sys.stderr)
    note = numerics_note(model, args.integrator, args.h, speed=speed, nonlinear=sim.force_law == "nonlinear",
                         latency=latency)
    if note:
        print(f"{args._prog}: {note[0]}: {note[1]}", file=sys.stderr)
    return pre


TRANSPORTS = ("auto", "unix", "tcp")


def choose_transport(kind: str, run_id: str) -> tuple[dict, str, str]:
    """The run's zenoh link between its processes on this host, and the plant's and recorder's
    listening endpoints.  ``auto`` (the default) = ``unix`` where Unix-domain sockets work,
    else ``tcp`` on loopback, saying why; ``unix`` refuses to fall back.  Multi-host runs
    start the processes themselves (``ambhil plant --listen tcp/HOST:PORT`` ...).  Returns
    (``{"kind", "auto", "text"}``, plant endpoint, recorder endpoint)."""
    import socket
    from ambhil.bridge.process import transport as tr
    why = None
    if kind in ("auto", "unix"):
        try:
            if not hasattr(socket, "AF_UNIX"):
                raise tr.TransportError("no Unix-domain sockets on this platform")
            tag = f"{run_id[:40]}-{os.getpid()}"
            ep_p, ep_r = tr.unix_endpoint(f"{tag}-plant"), tr.unix_endpoint(f"{tag}-rec")
            gone = tr.remove_stale_sockets(os.path.dirname(tr.endpoint_path(ep_p)))
            if gone:                        # left by a run killed before it could clean up
                print(f"ambhil run: note: removed {len(gone)} socket file(s) of runs whose process is gone: "
                      f"{', '.join(os.path.basename(g) for g in gone)}", file=sys.stderr)
            probe = tr.endpoint_path(ep_r) + ".probe"
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sk:   # the folder takes sockets
                sk.bind(probe)
            os.unlink(probe)
            return ({"kind": "unix", "auto": kind == "auto",
                     "text": f"unix socket {os.path.dirname(tr.endpoint_path(ep_p))} (same host"
                             f"{', auto' if kind == 'auto' else ''}; --transport tcp for TCP loopback)"},
                    ep_p, ep_r)
        except (OSError, tr.TransportError) as e:
            if kind == "unix":
                raise SceneError(f"--transport unix: {e}") from None
            why = str(e)
            print(f"ambhil run: note: Unix-domain sockets unusable ({why}); using TCP on loopback",
                  file=sys.stderr)
    ep_p, ep_r = tr.tcp_endpoint(tr.free_port()), tr.tcp_endpoint(tr.free_port())
    return ({"kind": "tcp", "auto": kind == "auto",
             "text": "tcp loopback 127.0.0.1" + (f" (auto: fallback, {why})" if why else "")},
            ep_p, ep_r)


def run(args) -> int:
    from ambhil.loop.system import compile_system
    from ambhil.bridge.process import transport as tr
    scene = with_fault_flags(load_scene(args.scene), args.fault)
    model = compile_system(scene, rung=args.rung)
    n = _duration_steps(scene, args.duration)
    latency = latency_of(args.delay, scene)
    plant_runner(scene, model, args)  # refuse now what the plant would (a step or a fault that does not fit)
    check_currents_at(args, scene)
    pre = _precheck(args, scene, model, latency)
    if pre is not None and not pre.stable and args.strict:
        return 1
    cal = None
    if args.mode == "realtime":             # can this machine hold the rate? (bridge/cli/rt_check.py)
        from ambhil.bridge.cli.rt_check import calibrate
        cal = calibrate(scene, model, args, placement_cpus(args.placement).get("plant"))
        print(f"{args._prog}: {'note' if cal['can_hold'] else 'warning'}: {cal['line']}", file=sys.stderr)
    run_id = args.run_id or f"{scene.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    mcap, rrd = outdir / f"{run_id}.mcap", outdir / f"{run_id}.rrd"
    for stale in (outdir / f"{run_id}.failed.mcap", outdir / f"{run_id}.failed.rrd"):
        stale.unlink(missing_ok=True)       # a rerun of the same id: no marker of an older run
    transport, ep_p, ep_r = choose_transport(args.transport, run_id)
    if args.secure:                         # mutual TLS + access control (bridge/process/security.py)
        from ambhil.bridge.process.security import SecurityError, files
        try:
            for role in ("plant", "controller", "recorder"):
                files(args.secure, role)
        except SecurityError as e:
            from ambhil.bridge.cli.main import CliError
            raise CliError(str(e)) from None
        ep_p, ep_r = (f"tls/127.0.0.1:{tr.free_port()}" for _ in range(2))
        transport = {"kind": "tls", "auto": False,
                     "text": f"TLS on loopback, mutual, certificates {args.secure}, access control on"}
    if args.endpoint:                       # the plant's endpoint, given (e.g. to attach a tool)
        ep_p = args.endpoint
        transport = dict(transport, kind=ep_p.split("/", 1)[0], text=f"{ep_p} (--endpoint)")
    record = not args.no_record
    common = ["--run-id", run_id, "--json", "--start-timeout", str(args.start_timeout)]
    if args.secure:
        common += ["--secure", str(Path(args.secure).resolve())]
    cpus = placement_cpus(args.placement)

    def pin(role):
        return ["--cpus", ",".join(map(str, cpus[role]))] if role in cpus else []
    echo = threading.Event()
    echo.set()                              # show the peers' start-up progress until the run runs
    echo.verbose = bool(getattr(args, "verbose", False))
    rec = (_Child("recorder", ["record", "--out", str(outdir), "--listen", ep_r, "--source", args.record_source,
                               "--owner-pid", str(os.getpid())]
                  + common + pin("recorder"), echo)
           if record else None)
    ctl_connect = [ep_p] + ([ep_r] if record else [])
    if getattr(args, "controller", None):
        import shlex
        try:
            argv = shlex.split(args.controller.format(scene=shlex.quote(str(Path(args.scene).resolve())),
                                                      run_id=run_id, connect=" ".join(ctl_connect)))
        except (KeyError, IndexError, ValueError) as e:
            if rec is not None:
                stop_process(rec.p)
            from ambhil.bridge.cli.main import CliError
            raise CliError(f"--controller {args.controller!r}: {e!r}; placeholders are {{scene}}, {{run_id}}, "
                           f"{{connect}}") from None
        ctl = _Child("controller", argv, echo, external=True)
    else:
        ctl = _Child("controller", ["controller", args.scene, "--connect"] + ctl_connect + common
                     + (["--rung", args.rung] if args.rung else []) + pin("controller"), echo)
    plant_argv = ["plant", args.scene, "--listen", ep_p] + (["--connect", ep_r, "--wait-recorder"] if record else []) + [
                  "--mode", args.mode, "--currents-at", args.currents_at, "--delay", str(args.delay), "--duration", str(n / scene.controller.sample_rate)]
    for spec in args.fault:
        plant_argv += ["--fault", spec]
    for flag, val in (("--rung", args.rung), ("--integrator", args.integrator), ("--max-overruns", _overrun_count(args)),
                      ("--reply-timeout", args.reply_timeout), ("--h", args.h)):
        if val is not None:
            plant_argv += [flag, str(val)]
    plant_argv += ["--cpu-wake-us", "off" if args.cpu_wake_us is None else str(args.cpu_wake_us),
                   "--rt-receive", args.rt_receive]
    pl = _Child("plant", plant_argv + common + pin("plant"), echo)
    children = {"plant": pl, "controller": ctl, "recorder": rec}
    interrupted = None                      # how the user stopped the run (Ctrl-C, SIGTERM)
    early: dict[str, str] = {}              # a peer that ended (not 0) while the plant ran: how
    # SIGTERM (kill, a `timeout` wrapper, a script whose background jobs ignore SIGINT) stops
    # the run as Ctrl-C does: the plant ends with RUN_END, the summary is printed, files kept
    on_term, how = None, ["Ctrl-C"]
    if threading.current_thread() is threading.main_thread():
        def _term(signum, frame):
            how[0] = "SIGTERM"
            raise KeyboardInterrupt
        on_term = signal.signal(signal.SIGTERM, _term)
    t_early = None
    try:
        while pl.p.poll() is None:
            for c in (ctl, rec) if record else (ctl,):
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
    echo.clear()
    results = {name: children[name].result(timeout=10.0 if name != "recorder" else 20.0)
               for name in ("plant", "controller", "recorder") if children[name] is not None}
    results.setdefault("recorder", (None, "", None))
    tr.remove_socket_files(ep_p, ep_r)
    sp, sc, sr = (results[k][0] for k in ("plant", "controller", "recorder"))
    if record and (sr is None or sr.get("write_error")) and mcap.exists():  # restore what it wrote
        from ambhil.bridge.recording.recover import RecordingError, recover
        fixed = mcap.with_suffix(".recovered.mcap")
        try:
            k = recover(str(mcap), str(fixed))
            fixed.replace(mcap)
            print(f"ambhil run: recorder did not finish {mcap}; recovered {k} messages into it", file=sys.stderr)
        except (OSError, RecordingError) as e:
            fixed.unlink(missing_ok=True)
            print(f"ambhil run: recorder did not finish {mcap}, and its readable part could not be copied "
                  f"({e}); the file is kept as it is (`ambhil recover` it where there is room)", file=sys.stderr)
    rrd_ok, conv = False, {}
    if mcap.exists():
        try:
            from ambhil.bridge.recording.replay import to_rerun
            from ambhil.bridge.cli.progress import Progress
            with Progress(f"writing {rrd.name}") as bar:
                conv = to_rerun(str(mcap), str(rrd), recording_id=run_id, progress=bar)
            rrd_ok = True
        except Exception as e:  # a replay problem must not lose the run's MCAP
            print(f"ambhil run: could not write {rrd}: {e}", file=sys.stderr)

    # ---- what went wrong, if anything
    reasons = []
    if interrupted:
        reasons.append(f"interrupted by the user ({interrupted})")
    def _said(name):            # a dying peer's own last words (its one-line error), if any
        lines = [ln for ln in results[name][1].strip().splitlines() if "error:" in ln]
        return f" ({lines[-1].strip()})" if lines else ""
    if "controller" in early and not (sc and sc.get("fault")):
        reasons.append(f"controller {early['controller']} during the run{_said('controller')}")
    if "recorder" in early:
        reasons.append(f"recorder: {sr['write_error']}" if sr and sr.get("write_error")
                       else f"recorder {early['recorder']} during the run{_said('recorder')}")
    for name in ("plant", "controller"):
        s, err, code = results[name]
        if s is None:
            if name in early:
                continue
            tail = err.strip().splitlines()[-1] if err.strip() else None
            reasons.append(f"{name} gave no summary ({exit_text(code)}" + (f": {tail})" if tail else ")"))
        elif s.get("fault"):
            reasons.append(f"{name}: {s['fault']}")
    if not interrupted and not (sp or {}).get("fault"):
        from ambhil.bridge.cli.simulate import not_steady   # the rule of `simulate`: a loop that grows has no steady orbit
        if (nst := not_steady(pre)):
            reasons.append(nst)
    recorded = None                       # sensor samples in the file
    if not record:
        pass
    elif sr is not None:
        recorded = sr.get("steps_recorded")
    else:
        if "recorder" not in early:
            reasons.append(f"recorder gave no summary ({exit_text(results['recorder'][2])})")
        if mcap.exists():
            try:
                from ambhil.bridge.recording.replay import load_run
                recorded = len(load_run(str(mcap))["sensors"]["v"])
            except Exception:
                recorded = None
    foreign = foreign_report(sp, sc)
    if foreign and args.strict:
        reasons.append(f"--strict: {foreign}")
    incomplete = sp is not None and recorded is not None and recorded < sp["steps"]
    if incomplete:
        reasons.append(f"recording incomplete: {recorded} of the plant's {sp['steps']} steps recorded")

    # ---- summary: what went wrong first, then the figures
    from ambhil.bridge.cli.main import emit
    orbits, orbit_err = [], None
    if mcap.exists():
        try:
            clr, names = [a.clearance for a in scene.plant.ambs], [a.name for a in scene.plant.ambs]
            if rrd_ok and len(conv.get("orbit_max_m", ())) == len(names):    # read once, while converting
                orbits = [(nm, r, r / c) for nm, r, c in zip(names, conv["orbit_max_m"], clr)]
            else:
                orbits = orbit_report(str(mcap), clr, names)
        except Exception as e:
            orbit_err = str(e)
    injected = []
    if mcap.exists() and scene.faults:
        try:
            from ambhil.bridge.recording.replay import load_run
            injected = [dict(json.loads(e.text), step=e.step, t_s=e.sim_time_ns * 1e-9)
                        for e in load_run(str(mcap))["events"] if e.kind_name == "FAULT_INJECTED"]
        except Exception as e:
            orbit_err = orbit_err or str(e)
    rate = rate_check(args, scene, model, sp, orbits, latency)
    if rate and not rate["kept"]:
        reasons.insert(0, rate["reason"])   # the first thing to know: these are not the scene's results
    files = ([mcap] if mcap.exists() else []) + ([rrd] if rrd_ok else [])
    if reasons:
        files = mark_failed(*files, why="; ".join(reasons))
    fs = scene.controller.sample_rate
    summary = {"command": "run", "ok": not reasons, "failed": reasons, "run_id": run_id, "scene": scene.name,
               "rung": model.rung, "mode": args.mode, "controller_rate_hz": fs, "latency_s": latency,
               "transport": transport, "recorded": record,
               "precheck": None if pre is None else {"stable": pre.stable, "note": pre.line},
               "rejected_note": foreign,
               "plant": sp, "controller": sc, "recorder": sr, "recorded_steps": recorded,
               "orbits": [{"station": nm, "largest_radius_m": r, "touchdown_clearance_m": scene.plant.amb(nm).clearance,
                           "fraction_of_touchdown_clearance": f} for nm, r, f in orbits],
               "touchdown_clearance_note": touchdown_note(scene.plant.ambs) or None,
               "fault_events": injected,
               "files": [str(f) for f in files],
               "calibration": cal, "rate": rate}

    def human():
        print(f"run {run_id}: scene {scene.name}, rung {model.rung}, mode {args.mode}, controller {fs:g} Hz"
              + (f", latency {latency * 1e6:g} us ({latency * fs:g} periods)" if latency else ""))
        if reasons:
            print(f"  {'STOPPED' if interrupted else 'FAILED':10s} {'; '.join(reasons)}")
        print(f"  transport  {transport['text']}")
        if cal:
            print(f"  machine    {cal['line']}")
        if pre is not None and not pre.stable:
            print(f"  predicted  {pre.line}")
        if sp:
            print(f"  steps      {sp['steps']}/{sp['n_steps']} ({sp['steps'] / fs:.3f} s simulated) "
                  f"in {sp['wall_s']:.2f} s wall, {sp['steps_per_s']:.0f} steps/s")
            if args.mode == "realtime":
                warm = min(sp.get("warmup_steps", 0), sp["steps"])
                counted = sp["steps"] - warm
                frac = sp["overruns"] / counted if counted else 0.0
                held = sp.get("held", 0)
                print(f"  overruns   {sp['overruns']} of {counted} periods after the {warm}-period warm-up "
                      f"({100 * frac:.2f} %); currents held in {held} of all {sp['steps']} periods "
                      f"({100 * held / max(sp['steps'], 1):.2f} %, warm-up included)")
                if frac > 0.01 and not (rate and not rate["kept"]):
                    print(f"  note       more than 1 % overruns: this machine does not sustain {fs:g} Hz real time "
                          f"with this plant (docs/hil.md); lockstep runs at any rate")
            else:
                print(f"  overruns   {sp['overruns']}")
            if sc:
                print(f"  loops      plant {sp.get('loop')}, controller {sc.get('loop')} (C: bridge/protocol/_wire.c runs "
                      f"the ordinary steps; {sp.get('loop_handbacks', 0)} / {sc.get('loop_handbacks', 0)} "
                      f"handed back to Python)")
            print(f"  latency    round trip {_fmt(sp['latency_us'])}; controller TET {_fmt(sp['tet_us'])}")
            if args.mode == "realtime":
                print(f"  wake late  {_fmt(sp['lateness_us'])}; CPU wake-up latency request: "
                      f"{sp.get('cpu_wake_latency')}")
                rr = sp.get("rt_receive") or {}
                print(f"  receive    {rr.get('mode')} ({rr.get('why')}"
                      + (f"; timer on CPU {rr['timer_cpu']}, fired {rr.get('timer_fires')} times"
                         if rr.get("mode") == "deadline" else "") + ")")
        if foreign:
            print(f"  REJECTED   {foreign}")
        for e in injected:
            params = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in e["params"].items())
            print(f"  fault      {e['phase']:5s} t={e['t_s']:.4g} s (step {e['step']}): {e['kind']}"
                  + (f" {e['axis']}" if e.get("axis") else "") + (f" {params}" if params else ""))
        if incomplete:
            print(f"  recording  INCOMPLETE: the .mcap stops after {recorded} of the plant's {sp['steps']} steps")
        for nm, r, frac in orbits:
            print(f"  orbit {nm:4s} largest radius {r * 1e6:8.2f} um = {100 * frac:5.1f}% of the touchdown clearance "
                  f"{scene.plant.amb(nm).clearance * 1e6:g} um" + (" (of a failed run)" if reasons else ""))
        if orbits and touchdown_note(scene.plant.ambs):
            print(f"  note       {touchdown_note(scene.plant.ambs)}")
        if rate and rate.get("reference_orbits_m"):
            print("  reference  in-process loop of the same scene (what a run that kept its rate records): "
                  + ", ".join(f"orbit {nm} {q * 1e6:.2f} um" for (nm, _, _), q in zip(orbits, rate["reference_orbits_m"])))
        if orbit_err:
            print(f"  orbit: could not read the recording: {orbit_err}")
        print(f"  files      {', '.join(map(str, files)) or 'none'}"
              + (f" (marked .failed: the run {'was stopped' if interrupted else 'failed'}; the MCAP's "
                 f"ambhil.run_end metadata says why)"
                 if reasons and files else ""))
    emit(args, summary, human)
    if reasons:
        print(f"ambhil run: error: run {'stopped' if interrupted else 'failed'}: {'; '.join(reasons)}", file=sys.stderr)
        return 130 if interrupted else 1
    return 0
