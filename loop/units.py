"""Quantities with units: the one parser of every number a user writes with a unit, in a scene
(``speed = "3000rpm"``, ``latency = "150us"``) or on the command line (``--delay 1.5T``,
``--rates 2k:50k:20``, ``--run-up 0,50Hz,0,1``).  Each returns SI (s, Hz, rad/s, A); a plain
number is taken as SI.  Errors are :class:`UnitError` (a ``ValueError``) naming what was expected.

| kind | units (case as written) | SI |
|---|---|---|
| time | ``ns``, ``us``, ``µs``, ``ms``, ``s``; ``T`` = controller periods (``1.5T``, ``T``) | s |
| rate | ``Hz``, ``kHz``, ``MHz``; ``k``, ``M`` (any case: ``5khz``, ``1m`` = 1 MHz) | Hz |
| speed | ``rpm``, ``Hz`` (revolutions per second), ``rad/s`` (any case: ``3000RPM``) | rad/s |
| current | ``A``, ``mA`` | A |

A time in periods needs the period: :func:`time` takes it, or :func:`time_spec` keeps the value
in periods (:class:`Time`) until the period is known.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


class UnitError(ValueError):
    """A quantity that does not parse: the message names what was expected and what was given."""


TIME = {"ns": 1e-9, "us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0}
RATE = {"MHz": 1e6, "kHz": 1e3, "Hz": 1.0, "hz": 1.0, "M": 1e6, "k": 1e3}
SPEED = {"rpm": 2 * math.pi / 60, "rad/s": 1.0, "Hz": 2 * math.pi, "hz": 2 * math.pi}
CURRENT = {"mA": 1e-3, "A": 1.0}
EXAMPLES = {"time": "0.2s, 200ms or 150us", "rate": "10kHz, 10k or 10000",
            "speed": "3000rpm, 50Hz or 314rad/s", "current": "2.5A or 300mA"}
UNITS = {"time": TIME, "rate": RATE, "speed": SPEED, "current": CURRENT}
#: kinds whose units are read in any case (no two of their units differ only in case; the rate
#: flags always took ``5khz`` and ``1m``, the speed flags ``3000RPM``)
ANY_CASE = frozenset({"rate", "speed"})


def _split(text: str, units: dict[str, float], any_case: bool = False) -> tuple[str, float]:
    t = text.strip()
    key = t.lower() if any_case else t
    for u in sorted(units, key=len, reverse=True):
        if key.endswith(u.lower() if any_case else u):
            return t[: -len(u)].strip(), units[u]
    return t, 1.0


def quantity(value, kind: str, what: str = "") -> float:
    """A number (SI) or a string with one of ``kind``'s units -> SI float.  ``what`` names the
    quantity in the error (``--delay``, ``[speed] value``)."""
    if isinstance(value, bool):
        raise UnitError(f"{what or kind}: expected a {kind} such as {EXAMPLES[kind]}, got {value!r}")
    if isinstance(value, (int, float, np.integer, np.floating)):
        return float(value)
    if not isinstance(value, str):
        raise UnitError(f"{what or kind}: expected a {kind} such as {EXAMPLES[kind]}, got {value!r}")
    num, f = _split(value, UNITS[kind], kind in ANY_CASE)
    try:
        return float(num) * f
    except ValueError:
        raise UnitError(f"{what or kind}: expected a {kind} such as {EXAMPLES[kind]}, got {value!r}") from None


@dataclass(frozen=True)
class Time:
    """A time as written: seconds, or a number of controller periods (``1.5T``)."""
    value: float
    in_periods: bool = False

    def seconds(self, period: float | None) -> float:
        if not self.in_periods:
            return self.value
        if period is None:
            raise UnitError(f"{self}: a time in periods needs a sample rate")
        return self.value * period

    def __str__(self) -> str:
        return f"{self.value:g}T" if self.in_periods else f"{self.value:g}s"


def time_spec(value, what: str = "time") -> Time:
    """``150us``, ``0.2ms``, ``3e-5`` (s), ``1.5T`` or ``T`` (periods) -> :class:`Time`."""
    if isinstance(value, str) and value.strip().endswith("T"):
        num = value.strip()[:-1].strip()
        try:
            return Time(float(num) if num else 1.0, True)
        except ValueError:
            raise UnitError(f"{what}: expected a time such as {EXAMPLES['time']} or 1.5T (periods), "
                            f"got {value!r}") from None
    return Time(quantity(value, "time", what))


def time(value, period: float | None = None, what: str = "time") -> float:
    """A time in s; ``1.5T`` is 1.5 periods (``period`` in s)."""
    return time_spec(value, what).seconds(period)


def rate(value, what: str = "rate") -> float:
    """A sample rate in Hz (``10k``, ``10kHz``, ``10000``); must be > 0."""
    v = quantity(value, "rate", what)
    if not v > 0:
        raise UnitError(f"{what}: a rate must be > 0, got {value!r}")
    return v


def speed(value, what: str = "speed") -> float:
    """A spin speed in rad/s (``3000rpm``, ``50Hz``, ``314rad/s``, a plain number is rad/s)."""
    return quantity(value, "speed", what)


def current(value, what: str = "current") -> float:
    """A current in A (``2.5A``, ``300mA``)."""
    return quantity(value, "current", what)


def span(text: str, conv, what: str, log: bool = False) -> np.ndarray:
    """``START:STOP:COUNT`` (linear, or geometric with ``log``) or a comma list, each item through
    ``conv``; the list is returned as written (not sorted)."""
    try:
        if ":" in text:
            a, b, n = text.split(":")
            lo, hi, k = conv(a), conv(b), int(n)
            if k < 1:
                raise ValueError
            return np.geomspace(lo, hi, k) if log else np.linspace(lo, hi, k)
        return np.array([conv(t) for t in text.split(",") if t.strip()], float)
    except (ValueError, ZeroDivisionError) as e:
        detail = f" ({e})" if isinstance(e, UnitError) else ""
        raise UnitError(f"{what}: expected START:STOP:COUNT or a comma list, got {text!r}{detail}") from None
