"""Commands on a run's recording: `ambhil replay` (MCAP -> rerun .rrd, or the sensor stream into a
controller under test with the currents compared, bridge/recording/conform.py) and `ambhil
recover` (the readable part of a truncated MCAP).  zenoh and rerun are imported inside the
handlers (`ambhil --help` stays quick)."""
from __future__ import annotations

import os
import sys
from pathlib import Path

from ambhil.bridge.cli.arguments import law_label
from ambhil.bridge.cli.convention import RUN_FAILED, CliError, emit
from ambhil.bridge.cli.keyfile import ENV, auth_mode, auth_text, check_endpoints, process_secret
from ambhil.bridge.recording.recover import RecordingError, check, recover, same_file, truncated_message


def cmd_replay(args) -> int:
    if args.to_controller:
        return _conform(args)
    from ambhil.bridge.recording import replay                 # zenoh, rerun: see the docstring
    from ambhil.bridge.cli.progress import Progress    # rich: slow to import, only when drawing
    src = Path(args.mcap)
    outdir = Path(args.out) if args.out else src.parent
    rrd = outdir / (src.stem + ".rrd")
    try:
        if check(str(src)) == "truncated":
            raise RecordingError(truncated_message(str(src)))
        outdir.mkdir(parents=True, exist_ok=True)
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


def _conform(args) -> int:
    """``replay --to-controller``: the sensor stream into a controller process (``--scene``:
    `ambhil controller SCENE`, the scene's law or ``--law``; ``--controller-cmd``: any; neither:
    one started by hand), currents compared per axis (bridge/recording/conform.py)."""
    from ambhil.bridge.process import transport as tr          # zenoh: see the docstring
    from ambhil.bridge.recording.conform import ConformanceError, conform, controller_command, table
    if args.scene and args.controller_cmd:
        raise CliError("--scene and --controller-cmd both name the controller under test; give one")
    if args.gain_scale != 1.0 and not args.scene:
        raise CliError("--gain-scale scales the built-in controller: it needs --scene")
    if args.law and not args.scene:
        raise CliError("--law runs `ambhil controller SCENE --law SPEC` as the controller under test: it needs --scene")
    if not args.tolerance >= 0:
        raise CliError(f"--tolerance: expected a current >= 0 A, got {args.tolerance}")
    secret, key = process_secret(args)
    run_id = args.run_id or f"replay-{os.getpid()}"
    if args.secure:                     # the replay poses as the plant: the plant's certificate
        from ambhil.bridge.process.security import SecurityError, configure
        try:
            configure(args.secure, "plant", run_id)
        except SecurityError as e:
            raise CliError(str(e)) from None
    ep = args.listen or (f"tls/127.0.0.1:{tr.free_port()}" if args.secure else tr.tcp_endpoint(tr.free_port()))
    check_endpoints(ep, None, secret=secret, secure=args.secure, insecure=args.insecure)
    # the controller under test gets the same key: ours as --key-file PATH, a command of the
    # user's in $AMBHIL_KEY_FILE (conform starts it with this environment); never the secret
    auth = ((["--key-file", os.path.abspath(key)] if key else []) + (["--insecure"] if args.insecure else [])
            + (["--secure", os.path.abspath(args.secure)] if args.secure else []))
    if key:
        os.environ[ENV] = os.path.abspath(key)
    else:
        os.environ.pop(ENV, None)
    argv = None
    if args.scene:
        argv = [sys.executable, "-m", "ambhil.bridge.cli", "controller", args.scene, "--run-id", run_id,
                "--connect", ep] + (["--gain-scale", str(args.gain_scale)] if args.gain_scale != 1.0 else []) \
            + (["--law", args.law] if args.law else []) + auth
    elif args.controller_cmd:
        argv = controller_command(args.controller_cmd, run_id, ep)
    else:
        extra = "".join(f" {a}" for a in auth)
        print(f"waiting for a controller: run it with --run-id {run_id} --connect {ep}{extra} "
              f"(e.g. ambhil controller SCENE --run-id {run_id} --connect {ep}{extra})", file=sys.stderr)
    try:
        res = conform(args.mcap, run_id, listen=ep, argv=argv, tolerance=args.tolerance,
                      start_timeout=args.start_timeout, secret=secret, insecure=args.insecure)
    except (RecordingError, ValueError) as e:
        raise CliError(str(e)) from None
    except (ConformanceError, tr.TransportError) as e:
        raise CliError(str(e), 1) from None
    res.setdefault("auth", auth_mode(secret, args.insecure))
    res["key_file"] = key
    head = [f"auth: {auth_text(auth_mode(secret, args.insecure), key, secure=args.secure)}"]
    if args.scene:
        from ambhil.loop.scene import load_scene
        res["law"] = law_label(args.law, load_scene(args.scene))
        head += [f"controller under test: ambhil controller {args.scene} (law {res['law']})"]
    emit(args, {"command": "replay --to-controller", **res}, head + table(res))
    return 0 if res["passed"] else 1


def cmd_recover(args) -> int:
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
