"""The convention every `ambhil` command keeps (every command is made with :func:`command`;
``tests/test_cli.py`` walks the parser and checks it):

* ``--help`` shows every flag's help and its default (:class:`HelpFormatter`).
* ``--out DIR`` is always a folder (created if missing); file names inside it are derived
  (from the scene, the run id or the input file) (:func:`add_out`, :func:`folder`).
* ``--json``: the summary as exactly one JSON line on stdout, nothing else on stdout
  (:func:`add_json`, :func:`emit`); progress and notes go to stderr.
* errors: one line ``ambhil <command>: error: <what>`` on stderr (:class:`Parser`,
  :class:`CliError`, :func:`fail`); exit 2 for a user error (bad scene, flag value or file), 1
  for a run that failed, 130 when interrupted.
* a flag's value is converted once, by its argparse ``type`` (:func:`arg_type` turns a
  converter's ``ValueError`` into the one-line usage error naming the flag).
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

PROG = "ambhil"
USER_ERROR, RUN_FAILED, INTERRUPTED = 2, 1, 130

#: set by the commands that are zenoh processes (plant, controller, record) once they are done:
#: the process then ends without the interpreter's shutdown, which can meet a zenoh thread still
#: running a callback and abort ("FATAL: exception not rethrown", exit 134) after every file
#: was written and the summary printed (bridge/cli/main.py, entry)
HARD_EXIT = [False]


class CliError(Exception):
    """An error for the user, printed as ``ambhil <command>: error: <message>``; exit ``code``
    (2 = user error: bad scene, flag value or file; 1 = the run failed)."""

    def __init__(self, message: str, code: int = USER_ERROR):
        super().__init__(message)
        self.code = code


def one_line(msg: str) -> str:
    return "; ".join(s.strip() for s in str(msg).strip().splitlines() if s.strip()) or "unknown error"


def error_line(prog: str, msg: str) -> str:
    return f"{prog}: error: {one_line(msg)}"


def fail(args, msg: str, code: int = USER_ERROR) -> int:
    """Print the one-line error of ``args``' command and return ``code`` (for handlers that
    return their exit code instead of raising :class:`CliError`)."""
    print(error_line(getattr(args, "_prog", PROG), msg), file=sys.stderr)
    return code


# --------------------------------------------------------------------------- parser helpers
class Parser(argparse.ArgumentParser):
    """argparse with the one-line error convention (usage errors exit 2)."""

    def error(self, message):
        self.exit(USER_ERROR, error_line(self.prog, f"{message} (see {self.prog} --help)") + "\n")


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Appends ``(default: X)`` to every flag that has a default worth showing."""

    def _get_help_string(self, action):
        h = action.help or ""
        d = action.default
        if ("%(default)" in h or d is None or d is False or d is argparse.SUPPRESS
                or (isinstance(d, (list, tuple)) and not d)
                or isinstance(action, (argparse._HelpAction, argparse._VersionAction))):
            return h
        if not action.option_strings and action.nargs not in ("?", "*"):
            return h
        return f"{h} (default: %(default)s)"


def command(sub, name: str, help: str, description: str | None = None) -> argparse.ArgumentParser:
    """A subcommand parser following the convention (defaults shown, one-line errors)."""
    p = sub.add_parser(name, help=help, description=description or help, formatter_class=HelpFormatter)
    p.set_defaults(_prog=p.prog)
    return p


def add_json(p) -> None:
    p.add_argument("--json", action="store_true",
                   help="print the summary as exactly one JSON line on stdout (nothing else on stdout)")


_FILE_SUFFIXES = (".mcap", ".rrd", ".npz", ".png", ".txt", ".csv", ".json", ".toml")


def folder(text: str) -> str:
    """``--out``: a folder (it may not exist yet), never a file."""
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file; --out takes a folder (file names in it are derived)")
    if p.suffix.lower() in _FILE_SUFFIXES:
        raise argparse.ArgumentTypeError(f"{text} looks like a file name; --out takes a folder "
                                         f"(file names in it are derived)")
    return text


def add_out(p, default: str | None, what: str, required: bool = False) -> None:
    """``--out DIR``: always a folder, created if missing."""
    p.add_argument("--out", metavar="DIR", type=folder, default=default, required=required,
                   help=f"folder for {what} (created if missing)")


def arg_type(fn, name: str | None = None):
    """Wrap a converter that raises SystemExit/ValueError with a message so argparse reports it
    as a one-line usage error (exit 2)."""
    def conv(text):
        try:
            return fn(text)
        except (SystemExit, ValueError) as e:
            msg = str(e.code if isinstance(e, SystemExit) else e)
            msg = re.sub(r"^--[\w-]+( \S+)?: ", "", msg)  # argparse names the flag already
            raise argparse.ArgumentTypeError(msg) from None
    conv.__name__ = name or getattr(fn, "__name__", "value")
    return conv


# --------------------------------------------------------------------------- the summary
def json_safe(x):
    """JSON-safe: non-finite floats become null, numpy scalars/arrays plain Python."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if hasattr(x, "tolist") and not isinstance(x, (str, bytes)):
        return json_safe(x.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return str(x)


def emit(args, summary: dict, human=None) -> None:
    """With ``--json``: ``summary`` as exactly one JSON line on stdout.  Otherwise print
    ``human`` (a string, a list of lines, or a callable printing them)."""
    if getattr(args, "json", False):
        sys.stdout.write(json.dumps(json_safe(summary), allow_nan=False) + "\n")
        sys.stdout.flush()
        return
    if callable(human):
        human()
    elif isinstance(human, str):
        print(human)
    elif human is not None:
        for line in human:
            print(line)
