"""Fault schedules: ``[[fault]]`` tables of a scene and ``--fault KIND:key=value,...`` flags ->
:class:`ambhil.plant.faults.Fault`, checked against the scene's plant (its AMB axes, stations and
nodes).

A fault is a kind (:data:`ambhil.plant.faults.KINDS`), a time window (``at``, then ``duration``
or ``until``; none for a permanent kind) and the kind's parameters (:data:`FAULT_PARAMS`).  Times
and speeds take units (``0.2s``, ``200ms``, ``3000rpm``: :mod:`ambhil.loop.units`).
"""
from __future__ import annotations

import math
from typing import Any

from ambhil.plant.faults import KINDS as FAULT_KINDS, PERMANENT, Fault
from ambhil.plant.params import PlantSpec
from .scene_table import SceneError, Table, station

#: parameters of each fault kind (besides kind, at, duration/until): key -> (quantity, default)
#: with quantity "time" (s, or "0.2s", "200ms", "150us"; "span": a time > 0), "speed" (rad/s, or "3000rpm", "50Hz"),
#: "number", "positive", "probability", "int", "direction", "axis", "axes" (optional axis, default
#: every axis), "station"; default ... = required
FAULT_PARAMS: dict[str, dict[str, tuple[str, Any]]] = {
    "sensor_stuck": {"axis": ("axis", ...)},
    "sensor_zero": {"axis": ("axis", ...)},
    "sensor_noise": {"axis": ("axis", ...), "sigma": ("positive", ...), "seed": ("int", None)},
    "sensor_bias": {"axis": ("axis", ...), "value": ("number", ...)},
    "sensor_drift": {"axis": ("axis", ...), "rate": ("number", ...)},
    "amp_limit": {"axis": ("axes", None), "limit": ("positive", ...)},
    "amp_slew": {"axis": ("axes", None), "rate": ("positive", ...)},
    "coil_loss": {"axis": ("axis", ...)},
    "amb_loss": {"axis": ("station", ...)},
    "drop": {"coast_down": ("span", None)},   # every AMB axis: no axis key (parse_fault)
    "unbalance_step": {"node": ("node", None), "position": ("position", None), "magnitude": ("positive", ...),
                       "phase": ("number", 0.0)},
    "speed_trip": {"to": ("speed", 0.0), "over": ("time", 1.0)},
    "message_loss": {"direction": ("direction", "both"), "probability": ("probability", 1.0), "seed": ("int", None)},
    "message_delay": {"direction": ("direction", "both"), "periods": ("periods", ...)},
    "controller_restart": {},
}
assert set(FAULT_PARAMS) == set(FAULT_KINDS)


def fault_axes(plant: PlantSpec) -> list[str]:
    """The names of the plant's AMB axes, in the order of every per-axis vector (``A.x``, ``A.y``, ...)."""
    return ([f"{a.name}.{x}" for a in plant.ambs for x in "xy"]
            + ([f"{plant.axial_amb.name}.z"] if plant.axial_amb is not None else []))


def parse_fault(raw: Any, path: str, where: str, plant: PlantSpec, index: int) -> Fault:
    """One ``[[fault]]`` table (or a ``--fault`` spec made into a table) -> :class:`Fault`."""
    t = Table(path, where, raw)
    kind = t.string("kind", choices=FAULT_KINDS)
    t.where = f"{where} {kind}"
    start, end = _window(t, kind)
    if kind == "drop" and "axis" in t.data:
        t.fail("axis", f"a drop switches off every AMB axis ({', '.join(fault_axes(plant))}): give no axis "
                       f"(amb_loss or coil_loss lose one AMB or one axis)")
    axes, label, params = _parameters(t, kind, fault_axes(plant))
    if kind == "drop":
        axes, label = tuple(range(len(fault_axes(plant)))), "all"
    if kind == "unbalance_step":
        node = station(t, plant.node_z)
        params["node"] = node + 1   # 1-based, as in the scene
        params.pop("position", None)
        label = ""   # the node is a parameter
    t.done()
    return Fault(kind=kind, start=start, end=end, axes=axes, axis=label, params=tuple(sorted(params.items())),
                 index=index, source=where)


def _window(t: Table, kind: str) -> tuple[float, float]:
    """(start, end) in s: ``at``, then ``duration`` or ``until`` (end inf when neither)."""
    start = t.quantity("at", t.raw("at"), "time")
    if start < 0:
        t.fail("at", f"must be >= 0 s, got {start:g}")
    end = math.inf
    if t.has("duration") and t.has("until"):
        t.fail("duration", "give either 'duration' or 'until', not both")
    for key in ("duration", "until"):
        if t.has(key):
            if kind in PERMANENT:
                t.fail(key, f"{kind} is permanent (no duration or until)")
            v = t.quantity(key, t.raw(key), "time")
            end = start + v if key == "duration" else v
            if not end > start:
                t.fail(key, f"the fault must end after it starts (at {start:g} s), got {key} {v:g} s")
    return start, end


def _parameters(t: Table, kind: str, names: list[str]) -> tuple[tuple[int, ...], str, dict[str, Any]]:
    """The kind's parameters (:data:`FAULT_PARAMS`) -> (axes it acts on, their label as written,
    the other parameters with their defaults)."""
    axes: tuple[int, ...] = ()
    label = ""
    params: dict[str, Any] = {}
    for key, (q, default) in FAULT_PARAMS[kind].items():
        if not t.has(key):
            if default is ...:
                t.fail(key, f"is required for {kind}")
            if q == "axes":
                axes, label = tuple(range(len(names))), "all"
            elif default is not None and q not in ("node", "position"):
                params[key] = default
            continue
        v = t.raw(key)
        if q in ("axis", "axes", "station"):
            axes, label = _axes(t, key, q, v, names), v
        elif q not in ("node", "position"):  # node, position: the station, read by parse_fault
            params[key] = _value(t, key, q, v)
    return axes, label, params


def _axes(t: Table, key: str, q: str, v: Any, names: list[str]) -> tuple[int, ...]:
    """The axes an ``axis`` key names: one axis (``A.x``), a station's (``A``) or ``all`` (``axes``)."""
    if not isinstance(v, str):
        t.fail(key, f"must be an axis name such as {names[0]!r} or a station such as "
                    f"{names[0].split('.')[0]!r}, got {t.short(v)}")
    stations = sorted({n.split(".")[0] for n in names})
    if v in names and q != "station":
        return (names.index(v),)
    if v in stations:
        return tuple(i for i, n in enumerate(names) if n.split(".")[0] == v)
    if v == "all" and q == "axes":
        return tuple(range(len(names)))
    t.fail(key, f"{t.short(v)} is not " + ("a station" if q == "station" else "an AMB axis or station")
                + f" of this scene (have {', '.join(stations if q == 'station' else names + stations)})")


def _value(t: Table, key: str, q: str, v: Any):
    """One parameter of quantity ``q`` (see :data:`FAULT_PARAMS`), checked."""
    if q in ("time", "speed", "span"):
        x = t.quantity(key, v, "time" if q == "span" else q)
        if q == "span" and not x > 0:
            t.fail(key, f"must be > 0 s, got {x:g}")
        if x < 0:
            t.fail(key, f"must be >= 0, got {x:g}")
        return x
    if q in ("number", "positive", "probability"):
        x = t.quantity(key, v)
        if q == "positive" and not x > 0:
            t.fail(key, f"must be > 0, got {x:g}")
        if q == "probability" and not 0 < x <= 1:
            t.fail(key, f"must be a probability in (0, 1], got {x:g}")
        return x
    if q in ("int", "periods"):
        if isinstance(v, bool) or not isinstance(v, int):
            t.fail(key, f"must be an integer, got {t.short(v)}")
        lo, hi = (1, 100_000) if q == "periods" else (0, 2**63 - 1)
        if not lo <= v <= hi:
            t.fail(key, f"must be from {lo} to {hi}, got {v}")
        return v
    assert q == "direction", q
    return t.string(key, choices=("sensors", "currents", "both"))


def spec_value(text: str) -> int | float | str:
    """A value of a ``KIND:key=value`` spec as TOML would give it: an integer, else a float, else
    the text (a quantity with units, a name)."""
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def parse_fault_spec(text: str, plant: PlantSpec, index: int) -> Fault:
    """A ``--fault`` flag, ``KIND:key=value,key=value`` (e.g. ``sensor_noise:at=0.2s,axis=A.x,sigma=2e-6``),
    parsed by the rules of ``[[fault]]`` against ``plant``; errors name the flag as ``--fault #index``."""
    where = f"--fault #{index}"
    kind, _, rest = str(text).partition(":")
    table: dict[str, Any] = {"kind": kind.strip()}
    for item in (s for s in rest.split(",") if s.strip()):
        key, eq, val = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise SceneError(f"{where}: {text!r}: expected KIND:key=value,key=value,..., got {item.strip()!r}")
        if key in table:
            raise SceneError(f"{where}: key {key!r} given twice")
        table[key] = spec_value(val.strip())
    return parse_fault(table, "command line", where, plant, index)
