"""The values of the commands' flags, converted once, at the boundary: each is an argparse
``type`` (wrapped by :func:`ambhil.bridge.cli.convention.arg_type` where it raises a plain
``ValueError``), so a bad value is a one-line usage error naming the flag and a handler only
ever sees typed values.  Quantities with units go through :mod:`ambhil.loop.units`, the one
parser of them; what is passed on (to a child process, into a config) is the parsed value,
never the user's text again.
"""
from __future__ import annotations

import argparse
import math
import os

from ambhil.loop import units

MODES = ("lockstep", "realtime")
RUNGS = ("rigid", "modal", "full", "ancf")
INTEGRATORS = ("bdf1", "bdf2", "trapezoidal", "generalized-alpha", "zoh")


# --------------------------------------------------------------------------- quantities with units
def speed(text: str) -> float:
    """A spin speed in rad/s from ``314``, ``314rad/s``, ``3000rpm`` or ``50Hz`` (units
    case-insensitive, optional space before them; :func:`ambhil.loop.units.speed`)."""
    try:
        v = units.speed(str(text).strip().lower())
    except units.UnitError:
        raise argparse.ArgumentTypeError(f"expected a speed such as 314, 314rad/s, 3000rpm or 50Hz, "
                                         f"got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"speed must be finite, got {text!r}")
    return v


def speed_text(w: float) -> str:
    return f"{w:.2f} rad/s ({w * 60 / (2 * math.pi):.0f} rpm)"


def seconds(text: str) -> float:
    """A time in s: ``0.05``, ``50ms``, ``150us`` (:func:`ambhil.loop.units.time`; a plain number
    is s)."""
    try:
        v = units.time(text)
    except units.UnitError:
        raise ValueError(f"expected a time such as 0.05, 50ms or 150us (s), got {text!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"a time must be finite, got {text!r}")
    return v


def delay(text: str) -> units.Time:
    """``--delay``: ``2`` or ``1.5`` (controller periods: a bare number is periods here),
    ``1.5T``, ``150us``, ``0.2ms`` -> :class:`ambhil.loop.units.Time` (>= 0), in seconds once the
    scene's rate is known (``.seconds(period)``)."""
    t = str(text).strip()
    try:
        v = (units.Time(float(t), True) if t.replace(".", "", 1).isdigit()
             else units.time_spec(t, "--delay"))
    except ValueError:
        v = units.Time(float("nan"))
    if not v.value >= 0:
        raise ValueError(f"--delay: expected a latency such as 2, 1.5T, 150us or 0.2ms, got {text!r}")
    return v


def delay_text(latency_s: float) -> str:
    """A latency in s as the text of ``--delay`` that converts back to exactly that float (for a
    child process)."""
    return f"{latency_s!r}s"


# --------------------------------------------------------------------------- counts, lists, limits
def cpu_list(text: str) -> list[int]:
    """``--cpus``: CPU numbers this process may use, comma-separated."""
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


def positive_ms(text: str) -> float:
    """``--reply-timeout``: a positive number of ms."""
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not v > 0:
        raise SystemExit(f"--reply-timeout: expected a positive number of ms, got {text!r}")
    return v


def cpu_wake_us(text: str) -> int | None:
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


def add_fault_flag(p) -> None:
    """``--fault KIND:key=value,...`` (repeatable), of `simulate`, `plant` and `run`."""
    p.add_argument("--fault", action="append", default=[], metavar="KIND:key=value,...",
                   help="schedule a fault (repeatable; after the scene's [[fault]] tables; 'none' leaves those "
                        "out), e.g. sensor_noise:at=0.2s,axis=A.x,sigma=2e-6 or amb_loss:at=0.1s,axis=B "
                        "(docs/faults.md)")


# --------------------------------------------------------------------------- control laws
def law(text: str) -> str:
    """``--law``: a law of its own (``FILE.py:CLASS``, ``FILE.so``, ``FILE.fmu``;
    controller/law_loader.py), its file made absolute from the working directory, once, here:
    what is passed on (to a child process, a runner) is this resolved name."""
    from ambhil.controller.law import LawError
    from ambhil.controller.law_loader import resolve
    try:
        return resolve(text, os.getcwd())
    except LawError as e:
        raise ValueError(str(e)) from None


def law_label(spec: str | None, scene=None) -> str:
    """What a run's summary and RunMeta call its law, without loading it: ``FILE.py:CLASS`` or
    the library's / FMU's file name for a law of its own (``spec``, else the scene's
    ``[controller] law``), ``pid`` for the built-in, the kind for ``[controller] kind``."""
    from pathlib import Path
    c = getattr(scene, "controller", None)
    spec = spec or getattr(c, "law", None)
    if spec:
        path, sep, cls = spec.rpartition(":") if ".py:" in spec else (spec, "", "")
        return f"{Path(path).name}:{cls}" if sep else Path(spec).name
    kind = getattr(c, "kind", "pid")
    return "pid" if kind == "pid" else f"[controller] kind = {kind!r}"


def add_law_flag(p, what: str = "the controller") -> None:
    """``--law SPEC`` of `simulate`, `run`, `controller`, `test-controller`, `replay`, `study timing`."""
    from ambhil.bridge.cli.convention import arg_type
    p.add_argument("--law", type=arg_type(law, "law"), metavar="SPEC",
                   help=f"run {what} with this law instead of the scene's: FILE.py:CLASS, a shared library "
                        f"FILE.so (include/ambhil_law.h) or an FMU FILE.fmu, relative to the working "
                        f"directory (default: the scene's [controller] law, kind, or the built-in PID)")
