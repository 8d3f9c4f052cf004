"""The `ambhil` command line: analyses, simulation and the HIL processes.

One convention for every command (bridge/cli/convention.py; ``tests/test_cli.py`` walks the
parser and checks it):

* ``--help`` shows every flag's help and its default; ``ambhil --version``.
* ``--out DIR`` is always a folder (created if missing); file names inside it are derived
  (from the scene, the run id or the input file).
* ``--json``: the summary as exactly one JSON line on stdout, nothing else on stdout
  (:func:`~ambhil.bridge.cli.convention.emit`); progress and notes go to stderr.
* quantities take units, parsed once by the flag's type (bridge/cli/arguments.py, through
  ambhil.loop.units): speeds ``3000rpm``, ``50Hz``, ``314rad/s`` (a bare number is rad/s), times
  ``50ms``, ``150us`` (a bare number is s), ``--delay 1.5T`` (a bare number is periods).
* errors: one line ``ambhil <command>: error: <what>`` on stderr; exit 2 for a user error
  (bad scene, flag value or file), 1 for a run that failed, 130 when interrupted.  No traceback
  reaches the user unless ``AMBHIL_DEBUG=1``.

This module is the top of the CLI room: it builds the parser from the command modules
(simulate.py, hil.py, campaign.py), runs the chosen handler with that convention, and has the two
small commands `analyze` and `view`.
"""
from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
import traceback
from pathlib import Path

from ambhil.controller.law import LawError
from ambhil.loop.scene import INPUT_ERRORS
from ambhil.bridge.cli import campaign, hil, simulate
from ambhil.bridge.cli.convention import (HARD_EXIT, INTERRUPTED, PROG, RUN_FAILED, USER_ERROR, CliError,
                                          HelpFormatter, Parser, add_json, add_out, command, emit, error_line)
from ambhil.bridge.recording.recover import RecordingError


def package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("ambhil")
    except PackageNotFoundError:
        return "unknown (not installed)"


# --------------------------------------------------------------------------- commands here
def _analyze(args) -> int:
    from ambhil.loop import report              # matplotlib: only for the analysis
    from ambhil.bridge.cli.progress import Progress    # rich: slow to import, only when drawing
    reports, text = report.analyze(args.scenes, args.out, sweep=not args.no_sweep, progress=Progress)
    emit(args, {"command": "analyze", "scenes": report.figures(reports)}, text)
    if args.out:
        print(f"plots and report written to {args.out}/", file=sys.stderr)
    return 0


def _view(args) -> int:
    path = Path(args.run)
    if not path.exists() and not path.suffix:          # a run id
        path = Path(args.recordings) / f"{args.run}.rrd"
        if not path.exists() and path.with_suffix(".mcap").exists():
            path = path.with_suffix(".mcap")
    if not path.exists():
        raise CliError(f"{args.run}: no such .rrd, .mcap or run id in {args.recordings}/")
    if path.suffix == ".mcap":                           # convert (again, if the .rrd is older)
        rrd = path.with_suffix(".rrd")
        if not rrd.exists() or rrd.stat().st_mtime < path.stat().st_mtime:
            from ambhil.bridge.recording.replay import to_rerun     # zenoh, rerun: only when converting
            try:
                from ambhil.bridge.cli.progress import Progress
                with Progress(f"writing {rrd.name}") as bar:
                    to_rerun(str(path), str(rrd), progress=bar)
            except RecordingError as e:
                raise CliError(str(e)) from None
            print(f"wrote {rrd}", file=sys.stderr)
        path = rrd
    elif path.suffix != ".rrd":
        raise CliError(f"{path}: expected a .rrd or .mcap file or a run id")
    # the viewer binary ships inside rerun-sdk (package rerun_cli); `rerun` itself is only on
    # the PATH of the virtual environment
    argv = [sys.executable, "-m", "rerun_cli", str(path)]
    if args.print_command:
        print(shlex.join(argv))
        return 0
    web = shlex.join([sys.executable, "-m", "rerun_cli", "--web-viewer", str(path)])
    if no_display():
        raise CliError(f"no display to open the viewer on ({no_display()}): open {path} where there "
                       f"is one (`ambhil view {path}`), or serve it to a browser with `{web}` "
                       f"(it prints the address to open)", RUN_FAILED)
    env = dict(os.environ)
    env.setdefault("RUST_LOG", "warn")        # the viewer's warnings and errors, not its banner
    tty = sys.stderr.isatty()
    if not tty:
        env["NO_COLOR"] = "1"                  # plain text in a log
    p = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True, errors="replace", env=env)
    error = None
    for line in p.stderr:                      # passed on; its error line kept for ours
        if not tty:
            line = _ANSI.sub("", line)
        if line.startswith("Error:") and error is None:
            error = line[len("Error:"):].strip()
            continue
        sys.stderr.write(line)
    code = p.wait()
    if code or error:    # the viewer can report an error and still exit 0 (rerun 0.41)
        raise CliError(f"the rerun viewer failed" + (f" (exit code {code})" if code else "")
                       + (f": {error}" if error else "") + f"; `{web}` serves it to a browser instead",
                       RUN_FAILED)
    return 0


_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def no_display() -> str | None:
    """Why no window can open here (None if one can): on Linux (X11 / Wayland) without
    ``DISPLAY``, ``WAYLAND_DISPLAY`` and ``WAYLAND_SOCKET``."""
    if sys.platform.startswith("linux") and not any(
            os.environ.get(k) for k in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")):
        return "DISPLAY, WAYLAND_DISPLAY and WAYLAND_SOCKET are unset"
    return None


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog=PROG, description="HIL testbench for flexible rotors on active magnetic bearings",
               formatter_class=HelpFormatter,
               epilog="Every command: --help for its flags; errors exit 2 (user error), 1 (run failed), "
                      "130 (interrupted); AMBHIL_DEBUG=1 shows tracebacks.")
    p.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    a = command(sub, "analyze", "critical speeds, stability, sensitivity, unbalance response, support sweep")
    a.add_argument("scenes", nargs="+", metavar="SCENE", help="scene TOML file(s); several are compared")
    add_out(a, None, "PNG plots and report.txt (default: print the report only)")
    a.add_argument("--no-sweep", action="store_true", help="skip the support-position sweep")
    add_json(a)
    a.set_defaults(func=_analyze)
    for m in (simulate, hil, campaign):
        m.add_parsers(sub)
    v = command(sub, "view", "open a run in the rerun viewer (the one installed with rerun-sdk)")
    v.add_argument("run", metavar="RUN", help="a .rrd, a .mcap (converted to the .rrd beside it if needed) "
                                              "or a run id in --recordings")
    v.add_argument("--recordings", metavar="DIR", default="recordings", help="folder where run ids are looked up")
    v.add_argument("--print-command", action="store_true",
                   help="print the viewer command instead of starting it (e.g. to run it elsewhere)")
    v.set_defaults(func=_view)
    return p


def _debug() -> bool:
    return os.environ.get("AMBHIL_DEBUG", "") not in ("", "0")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:             # --help/--version exit 0; usage errors were printed (2)
        if isinstance(e.code, str):     # a converter that raised SystemExit(message)
            print(error_line(PROG, e.code), file=sys.stderr)
            return USER_ERROR
        return int(e.code or 0)
    prog = getattr(args, "_prog", PROG)
    try:
        fin = getattr(args, "_finalize", None)
        if fin is not None:
            fin(args)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        msg, code = "interrupted", INTERRUPTED
    except CliError as e:
        msg, code = str(e), e.code
    except INPUT_ERRORS as e:
        msg, code = str(e), USER_ERROR
    except LawError as e:               # a law that cannot be loaded or made (its step's faults end a run)
        msg, code = str(e), USER_ERROR
    except SystemExit as e:
        if not isinstance(e.code, str):
            return int(e.code or 0)
        msg, code = e.code, USER_ERROR
    except UnicodeDecodeError as e:     # an input file that is not text (the loader should name it)
        bad = e.object[e.start:e.start + 1]
        msg, code = f"input is not UTF-8 text ({e.reason}: byte {bad!r} at offset {e.start})", USER_ERROR
    except BrokenPipeError:             # e.g. `ambhil ... | head`: nothing to tell
        try:
            sys.stdout = open(os.devnull, "w")
        except OSError:
            pass
        return RUN_FAILED
    except OSError as e:
        if e.filename is None:
            if _debug():
                raise
            msg, code = f"{type(e).__name__}: {e}", RUN_FAILED
        else:
            msg, code = f"{e.filename}: {e.strerror or e}", USER_ERROR
    except Exception as e:              # a bug or an unforeseen failure: still one line
        if _debug():
            raise
        msg, code = f"{type(e).__name__}: {e} (AMBHIL_DEBUG=1 shows the traceback)", RUN_FAILED
    if _debug():
        traceback.print_exc()
    print(error_line(prog, msg), file=sys.stderr)
    return code


def entry() -> None:
    """The `ambhil` executable: :func:`main`, then exit (at once for a zenoh process)."""
    try:
        code = main()
    except BaseException:   # e.g. its error line written to the pipe of an `ambhil run` that died
        if not HARD_EXIT[0]:
            raise
        code = RUN_FAILED   # a zenoh process still ends at once (no shutdown that waits on zenoh threads)
    if HARD_EXIT[0]:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    sys.exit(code)
