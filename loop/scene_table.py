"""One TOML table of a scene under validation, and the helpers every table's parser shares.

:class:`Table` remembers where it is (``[[amb]] #2 'B'``), reads each key with its type and range
checked, and at :meth:`Table.done` rejects the keys it did not read (suggesting the nearest allowed
one).  Every problem is a :class:`SceneError` of one line naming the file, the table, the key and
what was expected.  :func:`tables` reads an array of tables (``[[disc]]``), :func:`station` a
station given by ``node`` (1-based) or ``position`` (m, on a node of the mesh).
"""
from __future__ import annotations

import difflib
import math
import reprlib
from typing import Any

from . import units


class SceneError(ValueError):
    """A user error in a scene: the message is one line, fit to print without a traceback."""


class Table:
    """A TOML table under validation: remembers where it is, rejects unknown keys."""

    #: largest |number| (and 1/LIMIT the smallest non-zero one) a scene may give, in SI units: beyond
    #: it a value is a unit slip, and powers of it (d^4, N^2, s0^3, Omega^2) overflow the model
    LIMIT = 1e18

    @staticmethod
    def short(v: Any) -> str:
        """repr of a value for a one-line message (long strings, big lists and deep nesting cut)."""
        if isinstance(v, str) and len(v) > 60:
            return repr(v[:57]) + f"... ({len(v)} characters)"
        r = reprlib.Repr()
        r.maxstring, r.maxother, r.maxlong, r.maxlist, r.maxdict, r.maxlevel = 60, 60, 40, 6, 4, 2
        return r.repr(v)

    def __init__(self, path: str, where: str, data: Any):
        self.path, self.where = path, where
        if not isinstance(data, dict):
            self.fail(None, f"must be a table, got {type(data).__name__}")
        self.data = data
        self.used: set[str] = set()

    def fail(self, key: str | None, problem: str):
        loc = f"{self.where} key '{key if len(key) <= 60 else key[:57] + '...'}'" if key else self.where
        raise SceneError(f"{self.path}: {loc}: {problem}")

    def has(self, key: str) -> bool:
        self.used.add(key)  # an allowed key (for the list of allowed keys in done())
        return key in self.data

    def raw(self, key: str, default: Any = ...):
        self.used.add(key)
        if key not in self.data:
            if default is ...:
                near = difflib.get_close_matches(key, [k for k in self.data if k not in self.used], 1, 0.6)
                self.fail(key, "is required" + (f" (found '{near[0]}': misspelled?)" if near else ""))
            return default
        return self.data[key]

    def num(self, key: str, default: Any = ..., *, positive=False, nonneg=False, finite=True) -> float:
        v = self.raw(key, default)
        if v is default and default is not ...:
            return v
        return self.number(key, v, positive=positive, nonneg=nonneg, finite=finite)

    def number(self, key: str, v: Any, *, positive=False, nonneg=False, finite=True, what="") -> float:
        """Validate one number (of key, or of an element ``what`` of it) and return it as a float."""
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.fail(key, f"{what}must be a number, got {type(v).__name__} {self.short(v)}")
        big = isinstance(v, int) and abs(v) > self.LIMIT  # an integer perhaps beyond the float range
        f = (math.inf if v > 0 else -math.inf) if big and abs(v) > 1e308 else float(v)
        shown = self.short(v) if big else f"{f:g}"
        if math.isnan(f) or (finite and math.isinf(f) and not big):
            self.fail(key, f"{what}must be finite, got {f}")
        if positive and not f > 0:
            self.fail(key, f"{what}must be > 0, got {shown}")
        if nonneg and f < 0:
            self.fail(key, f"{what}must be >= 0, got {shown}")
        if big or (math.isfinite(f) and f != 0 and not 1 / self.LIMIT <= abs(f) <= self.LIMIT):
            self.fail(key, f"{what}{shown} is out of range (|value| from {1 / self.LIMIT:g} to {self.LIMIT:g} "
                           f"in SI units, or 0 where allowed)")
        return f

    def integer(self, key: str, default: Any = ..., *, minimum: int | None = None,
                maximum: int | None = None) -> int:
        v = self.raw(key, default)
        if v is default and default is not ...:
            return v
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(key, f"must be an integer, got {type(v).__name__} {self.short(v)}")
        if minimum is not None and v < minimum:
            self.fail(key, f"must be >= {minimum}, got {self.short(v)}")
        if maximum is not None and v > maximum:
            self.fail(key, f"must be <= {maximum}, got {self.short(v)}")
        return v

    def string(self, key: str, default: Any = ..., *, choices: tuple[str, ...] | None = None) -> str:
        v = self.raw(key, default)
        if v is default and default is not ...:
            return v
        if not isinstance(v, str):
            self.fail(key, f"must be a string, got {type(v).__name__} {self.short(v)}")
        if choices and v not in choices:
            self.fail(key, f"must be one of {', '.join(choices)}; got {self.short(v)}")
        return v

    def boolean(self, key: str, default: Any = ...) -> bool:
        v = self.raw(key, default)
        if not isinstance(v, bool):
            self.fail(key, f"must be true or false, got {self.short(v)}")
        return v

    def pair(self, key: str, default: Any = ...) -> tuple[float, float]:
        v = self.raw(key, default)
        if v is default and default is not ...:
            return v
        if (not isinstance(v, list) or len(v) != 2
                or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in v)):
            self.fail(key, f"must be a list of two numbers, got {self.short(v)}")
        return tuple(self.number(key, x, what=f"[{i}] ") for i, x in enumerate(v))

    def nodes(self, key: str, n: int) -> list[int]:
        """A list of distinct 1-based node numbers (default empty)."""
        v = self.raw(key, [])
        if not isinstance(v, list) or any(isinstance(k, bool) or not isinstance(k, int) for k in v):
            self.fail(key, f"must be a list of node numbers, got {self.short(v)}")
        for k in v:
            if not 1 <= k <= n:
                self.fail(key, f"node {self.short(k)} is outside the shaft (nodes 1..{n})")
        if len(set(v)) < len(v):
            self.fail(key, f"node {next(k for k in v if v.count(k) > 1)} is listed twice")
        return v

    def quantity(self, key: str, v: Any, kind: str = "number") -> float:
        """A number, or a string: with units (``kind`` time or speed, :mod:`ambhil.loop.units`) or
        a plain number; checked as :meth:`number`."""
        if isinstance(v, str):
            try:
                v = units.quantity(v, kind, key) if kind in units.UNITS else float(v)
            except ValueError:
                hint = f" such as {units.EXAMPLES[kind]}" if kind in ("time", "speed") else ""
                self.fail(key, f"must be a {kind if hint else 'number'}{hint}, got {self.short(v)}")
        return self.number(key, v)

    def done(self):
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            near = difflib.get_close_matches(unknown[0].lower(), sorted(self.used), 1, 0.6)
            # a near match is the answer; the whole list only when there is none (one line stays short)
            self.fail(unknown[0], "unknown key" + (f" (did you mean '{near[0]}'?)" if near else
                                                   (f" (allowed: {', '.join(sorted(self.used))})" if self.used else "")))


def tables(path: str, doc: dict, key: str) -> list[tuple[str, Any]]:
    v = doc.get(key, [])
    if not isinstance(v, list):
        raise SceneError(f"{path}: '{key}' must be an array of tables [[{key}]], got a {type(v).__name__}")
    return [(f"[[{key}]] #{i + 1}", t) for i, t in enumerate(v)]


def station(t: Table, node_z: tuple[float, ...], key_node="node", key_pos="position",
             required=True) -> int | None:
    """Resolve a station given as 1-based ``node`` or ``position`` (m) to a 0-based node index."""
    has_n, has_p = t.has(key_node), t.has(key_pos)
    if has_n and has_p:
        t.fail(key_node, f"give either '{key_node}' or '{key_pos}', not both")
    if not (has_n or has_p):
        if required:
            t.fail(key_node, f"is required (or '{key_pos}' in m)")
        return None
    n = len(node_z)
    if has_n:
        k = t.integer(key_node)
        if not 1 <= k <= n:
            t.fail(key_node, f"node {k} is outside the shaft (nodes 1..{n})")
        return k - 1
    z = t.num(key_pos)
    L = node_z[-1]
    if not -1e-9 * L <= z <= L * (1 + 1e-9):
        t.fail(key_pos, f"{z:g} m is outside the shaft (0..{L:g} m)")
    k = min(range(n), key=lambda i: abs(node_z[i] - z))
    if abs(node_z[k] - z) > 1e-6 * max(L, 1.0):
        t.fail(key_pos, f"{z:g} m is not at a node (nearest: node {k + 1} at {node_z[k]:g} m)")
    return k
