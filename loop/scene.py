"""Scene files: a TOML description of one test situation, loaded and validated.

A scene says only what a situation needs.  Loading checks every key: unknown keys, wrong
types and non-physical values raise :class:`SceneError`, whose message is one line naming the
file, the key and the problem.  The result is a tree of frozen dataclasses; nothing downstream
re-reads the TOML.

Units are SI throughout (m, kg, s, A, N, Pa, rad, rad/s), except ``pole_angle`` in degrees.
Stations (discs, bearings, sensors, unbalances, outputs) are given either by ``node`` (1-based,
as in the paper: node 1 is the left end of the shaft) or by ``position`` (m from the left end),
which must coincide with a node of the mesh.
"""
from __future__ import annotations

import difflib
import math
import reprlib
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ambhil.controller.params import DISCRETISATIONS, Amplifier, ControllerParams, Sensor
from ambhil.plant.params import (RUNGS, SCHEMES, AxialAMB, Damping, Disc, ModelOptions, PlantSpec, RadialAMB, Section,
                          Simulation, Speed, Unbalance)
from ambhil.plant.params import ParameterError as _PlantParameterError
from ambhil.plant.faults import KINDS as FAULT_KINDS, PERMANENT as _PERMANENT, Fault, FaultSchedule


class SceneError(ValueError):
    """A user error in a scene: the message is one line, fit to print without a traceback."""


#: every exception that means "the user's input is wrong" (one line, print it, exit 2)
INPUT_ERRORS = (SceneError, _PlantParameterError)


@dataclass(frozen=True)
class Analysis:
    output_nodes: tuple[int, ...] = ()
    sweep_amb: str | None = None
    frequency_max: float = 4000.0  # rad/s: upper end of the critical-speed search and Campbell plot
    reference_criticals: tuple[float, ...] = ()  # Hz, published values to compare against
    reference: str = ""  # where the reference values come from
    # m, the touchdown clearance of every [[amb]] that does not give its own ``touchdown_clearance``
    # (the loader copies it into those AMBs: RadialAMB.touchdown_clearance); None: no default, such
    # an AMB assumes half its magnetic gap (stated wherever the clearance is printed)
    touchdown_clearance: float | None = None


@dataclass(frozen=True)
class Scene:
    """One test situation: the plant's parameters, the controller's, and what to analyse."""
    name: str
    description: str
    path: str
    plant: PlantSpec
    controller: ControllerParams
    analysis: Analysis = field(default_factory=Analysis)
    faults: FaultSchedule = field(default_factory=FaultSchedule)  # [[fault]] tables (plant/faults.py)

    def with_faults(self, extra: FaultSchedule) -> "Scene":
        """A copy with more faults scheduled (e.g. from ``--fault`` flags), after the scene's own."""
        return replace(self, faults=self.faults + extra)

    def with_plant(self, **changes: Any) -> "Scene":
        """A copy whose plant has some fields replaced (for sweeps and studies)."""
        return replace(self, plant=replace(self.plant, **changes))

    def with_controller(self, **changes: Any) -> "Scene":
        """A copy with controller parameters replaced; a new sample rate is also the plant's new
        input period."""
        c = replace(self.controller, **changes)
        plant = self.plant
        if c.sample_rate != self.controller.sample_rate:
            plant = replace(plant, simulation=replace(plant.simulation, period=1.0 / c.sample_rate))
        return replace(self, controller=c, plant=plant)


def touchdown_note(ambs) -> str:
    """The assumption to print beside touchdown clearances: '' when every AMB's is given in the
    scene, else which AMBs assume half their magnetic gap."""
    assumed = [a.name for a in ambs if a.touchdown_clearance is None]
    if not assumed:
        return ""
    return (f"touchdown clearance of {', '.join(assumed)} assumed: half the magnetic gap "
            f"(not in the scene; set [[amb]] touchdown_clearance)")


# --------------------------------------------------------------------------- validation helpers
class _Table:
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

    def done(self):
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            near = difflib.get_close_matches(unknown[0].lower(), sorted(self.used), 1, 0.6)
            self.fail(unknown[0], "unknown key" + (f" (did you mean '{near[0]}'?)" if near else "")
                      + (f" (allowed: {', '.join(sorted(self.used))})" if self.used else ""))


def _tables(path: str, doc: dict, key: str) -> list[tuple[str, Any]]:
    v = doc.get(key, [])
    if not isinstance(v, list):
        raise SceneError(f"{path}: '{key}' must be an array of tables [[{key}]], got a {type(v).__name__}")
    return [(f"[[{key}]] #{i + 1}", t) for i, t in enumerate(v)]


_TOP_KEYS = ("scene", "model", "shaft", "disc", "amb", "axial_amb", "sensor", "amplifier",
             "controller", "unbalance", "speed", "damping", "analysis", "simulation", "fault")


def _station(t: _Table, node_z: tuple[float, ...], key_node="node", key_pos="position",
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


def load_scene(path: str | Path) -> Scene:
    """Load and validate a scene file; raise SceneError with a one-line message on any problem."""
    p = str(path)
    # a scene is a few kB of TOML, and every run's metadata carries it (a 64 KiB string, JSON-escaped:
    # up to 3 bytes per byte); reading stops at the limit (a huge file, /dev/zero)
    limit = 16 << 10
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)
    except FileNotFoundError:
        raise SceneError(f"{p}: no such scene file") from None
    except OSError as e:
        raise SceneError(f"{p}: cannot read: {e.strerror}") from None
    if len(data) > limit:
        raise SceneError(f"{p}: larger than {limit >> 10} KiB: not a scene (a scene is a few kB of TOML text)")
    for bom, enc in ((b"\xff\xfe\x00\x00", "UTF-32"), (b"\x00\x00\xfe\xff", "UTF-32"), (b"\xff\xfe", "UTF-16"),
                     (b"\xfe\xff", "UTF-16")):
        if data.startswith(bom):
            raise SceneError(f"{p}: the file is {enc} text (byte order mark at byte 0); save it as UTF-8")
    skip = 3 if data.startswith(b"\xef\xbb\xbf") else 0  # a UTF-8 byte order mark (some editors write one)
    try:
        text = data[skip:].decode("utf-8")
    except UnicodeDecodeError as e:
        at = skip + e.start
        line, col = data.count(b"\n", 0, at) + 1, at - data.rfind(b"\n", 0, at)
        raise SceneError(f"{p}: not UTF-8 text: byte 0x{data[at]:02X} at line {line}, column {col} (byte offset "
                         f"{at}): {e.reason}; save the file as UTF-8") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{p}: not valid TOML: {e}") from None
    except RecursionError:
        lines = text.splitlines() or [""]
        k = max(range(len(lines)), key=lambda i: lines[i].count("[") + lines[i].count("{"))
        raise SceneError(f"{p}: cannot read this TOML: arrays or inline tables nested too deeply "
                         f"(line {k + 1})") from None
    try:
        return parse_scene(doc, p)
    except RecursionError:  # a deeply nested value in a message
        raise SceneError(f"{p}: a value is nested too deeply") from None


def parse_scene(doc: dict, p: str = "<scene>") -> Scene:
    for k in doc:
        if k not in _TOP_KEYS:
            near = difflib.get_close_matches(k, _TOP_KEYS, 1, 0.6)
            raise SceneError(f"{p}: unknown top-level key '{k if len(k) <= 60 else k[:57] + '...'}'"
                             + (f" (did you mean '{near[0]}'?)" if near else "")
                             + f" (allowed: {', '.join(_TOP_KEYS)})")

    t = _Table(p, "[scene]", doc.get("scene", {}))
    # the name makes run ids (zenoh key expressions, ambhil/<run-id>/..., with a 16-character time
    # stamp: at most 64 characters) and file names; the default, the file stem, is made to fit
    name_ok = lambda s: 1 <= len(s) <= 48 and all(c.isascii() and (c.isalnum() or c in "_.-") for c in s)
    name = t.string("name", "".join(c if name_ok(c) else "_" for c in Path(p).stem)[:48] or "scene")
    if not name_ok(name):
        t.fail("name", f"must be 1 to 48 characters of A-Z a-z 0-9 _ . - (it names runs and files), "
                       f"got {t.short(name)}")
    description = t.string("description", "")
    t.done()

    t = _Table(p, "[model]", doc.get("model", {}))
    model = ModelOptions(
        rung=t.string("rung", "full", choices=RUNGS),
        beam=t.string("beam", "euler-bernoulli", choices=("euler-bernoulli", "timoshenko")),
        modal_cutoff=t.num("modal_cutoff", None, positive=True),
        rotary_inertia=t.boolean("rotary_inertia", True),
        gravity=t.num("gravity", 0.0, nonneg=True),
    )
    t.done()

    # ---- shaft
    sections = []
    shaft = _tables(p, doc, "shaft")
    if not shaft:
        raise SceneError(f"{p}: [[shaft]]: at least one shaft section is required")
    for where, raw in shaft:
        t = _Table(p, where, raw)
        s = Section(
            length=t.num("length", positive=True),
            outer_diameter=t.num("outer_diameter", positive=True),
            inner_diameter=t.num("inner_diameter", 0.0, nonneg=True),
            elements=t.integer("elements", 1, minimum=1, maximum=1000),
            youngs_modulus=t.num("youngs_modulus", 2.11e11, positive=True),
            shear_modulus=t.num("shear_modulus", 8.12e10, positive=True),
            density=t.num("density", 7810.0, positive=True),
        )
        if s.inner_diameter >= s.outer_diameter:
            t.fail("inner_diameter", f"must be < outer_diameter ({s.outer_diameter:g} m), got {s.inner_diameter:g}")
        t.done()
        sections.append(s)
        if sum(x.elements for x in sections) > 1000:
            t.fail("elements", f"the shaft has {sum(x.elements for x in sections)} elements in all; the model "
                               f"takes at most 1000")
    z = [0.0]
    for s in sections:
        le = s.length / s.elements
        for k in range(s.elements):
            z.append(z[-1] + le)
    node_z = tuple(z)

    # ---- discs
    discs = []
    for where, raw in _tables(p, doc, "disc"):
        t = _Table(p, where, raw)
        d = Disc(
            name=t.string("name", f"disc{len(discs) + 1}"),
            node=_station(t, node_z),
            mass=t.num("mass", positive=True),
            polar_inertia=t.num("polar_inertia", nonneg=True),
            diametral_inertia=t.num("diametral_inertia", nonneg=True),
        )
        t.done()
        discs.append(d)

    # ---- radial AMBs
    ambs: list[RadialAMB] = []
    for where, raw in _tables(p, doc, "amb"):
        t = _Table(p, where, raw)
        nm = t.string("name", chr(ord("A") + len(ambs)))
        where = f"{where} {t.short(nm)}"
        t.where = where
        node = _station(t, node_z)
        sensor_node = _station(t, node_z, "sensor_node", "sensor_position", required=False)
        gap = t.num("gap", positive=True)
        mis = t.pair("misalignment", (0.0, 0.0))
        if math.hypot(*mis) >= gap:
            t.fail("misalignment", f"offset {math.hypot(*mis):g} m must be smaller than the gap {gap:g} m")
        coil = ("bias_current", "turns", "pole_area", "pole_angle")
        if t.has("position_stiffness") or t.has("current_stiffness"):
            # datasheet coefficients: k_s < 0 (N/m) and k_i > 0 (N/A) at the centred operating point
            ks, ki = t.num("position_stiffness"), t.num("current_stiffness", positive=True)
            if not ks < 0:
                t.fail("position_stiffness", f"is the bearing's negative position stiffness k_s (N/m): must be < 0, "
                                             f"got {ks:g}")
            both = [k for k in coil if k in t.data]
            if both:
                t.fail(both[0], "give either the coil (bias_current, turns, pole_area, pole_angle) or the datasheet "
                                "coefficients (position_stiffness, current_stiffness), not both")
            a = RadialAMB(name=nm, node=node, sensor_node=node if sensor_node is None else sensor_node, gap=gap,
                          bias_current=-ks * gap / ki, turns=0.0, pole_area=0.0, pole_angle=0.0,
                          misalignment=mis, datasheet=(ks, ki))
        else:
            a = RadialAMB(
                name=nm, node=node, sensor_node=node if sensor_node is None else sensor_node,
                gap=gap,
                bias_current=t.num("bias_current", positive=True),
                turns=t.num("turns", positive=True),
                pole_area=t.num("pole_area", positive=True),
                pole_angle=t.num("pole_angle", 22.5),
                misalignment=mis,
            )
        if not 0 <= a.pole_angle < 90:
            t.fail("pole_angle", f"must be in [0, 90) degrees, got {a.pole_angle:g}")
        td = t.num("touchdown_clearance", None, positive=True)
        if td is not None:
            if td >= gap:
                t.fail("touchdown_clearance", f"{td:g} m must be smaller than this AMB's magnetic gap {gap:g} m "
                                              f"(the touchdown bearing catches the rotor before the stator)")
            a = replace(a, touchdown_clearance=td)
        t.done()
        if any(b.name == nm for b in ambs):
            t.fail("name", f"duplicate AMB name {nm!r}")
        if any(b.node == node for b in ambs):
            t.fail("node", f"another AMB already sits at node {node + 1}")
        ambs.append(a)
    if len(ambs) < 2:
        raise SceneError(f"{p}: [[amb]]: at least two radial AMBs are needed to levitate the rotor, got {len(ambs)}")

    axial = None
    if "axial_amb" in doc:
        t = _Table(p, "[axial_amb]", doc["axial_amb"])
        axial = AxialAMB(
            name=t.string("name", "Z"), node=_station(t, node_z),
            gap=t.num("gap", positive=True), bias_current=t.num("bias_current", positive=True),
            turns=t.num("turns", positive=True), pole_area=t.num("pole_area", positive=True),
        )
        t.done()

    t = _Table(p, "[sensor]", doc.get("sensor", {}))
    sensor = Sensor(gain=t.num("gain", 1.0, positive=True), time_constant=t.num("time_constant", 0.0, nonneg=True))
    t.done()
    t = _Table(p, "[amplifier]", doc.get("amplifier", {}))
    amplifier = Amplifier(gain=t.num("gain", 1.0, positive=True),
                          time_constant=t.num("time_constant", 0.0, nonneg=True),
                          current_limit=t.num("current_limit", math.inf, positive=True, finite=False))
    t.done()
    for a in ambs:
        need = a.bias_current * math.hypot(*a.misalignment) / a.gap
        if need >= amplifier.current_limit:
            raise SceneError(f"{p}: [amplifier] key 'current_limit': {amplifier.current_limit:g} A cannot hold "
                             f"AMB {a.name!r} at its misalignment (needs {need:g} A)")

    if "controller" not in doc:
        raise SceneError(f"{p}: [controller]: table is required (kp, ki, kd, derivative_filter, sample_rate)")
    t = _Table(p, "[controller]", doc["controller"])
    ctrl = ControllerParams(
        kp=t.num("kp", positive=True),
        ki=t.num("ki", 0.0, nonneg=True),
        kd=t.num("kd", 0.0, nonneg=True),
        derivative_filter=t.num("derivative_filter", 0.0, nonneg=True),
        sample_rate=t.num("sample_rate", 10_000.0, positive=True),
        discretisation=t.string("discretisation", "tustin", choices=DISCRETISATIONS),
        delay_samples=t.integer("delay_samples", 0, minimum=0, maximum=10_000),
        anti_windup=t.boolean("anti_windup", True),
        sensor=sensor, amplifier=amplifier,
    )
    if ctrl.sample_rate > 1e6:
        t.fail("sample_rate", f"must be <= 1e+06 Hz, got {ctrl.sample_rate:g}")
    if ctrl.kd > 0 and ctrl.derivative_filter <= 0:
        t.fail("derivative_filter", "must be > 0 when kd > 0 (a pure derivative is not realisable)")
    t.done()

    unb = []
    for where, raw in _tables(p, doc, "unbalance"):
        t = _Table(p, where, raw)
        unb.append(Unbalance(node=_station(t, node_z), magnitude=t.num("magnitude", nonneg=True),
                             phase=t.num("phase", 0.0)))
        t.done()

    t = _Table(p, "[speed]", doc.get("speed", {}))
    if t.has("value") and t.has("range"):
        t.fail("value", "give either 'value' (constant speed) or 'range' (sweep), not both")
    if t.has("range"):
        lo, hi = t.pair("range")
        if lo < 0 or hi <= lo:
            t.fail("range", f"must be [start, stop] with 0 <= start < stop rad/s, got [{lo:g}, {hi:g}]")
        speed = Speed(start=lo, stop=hi, points=t.integer("points", 400, minimum=2, maximum=10_000))
    else:
        speed = Speed(value=t.num("value", 0.0, nonneg=True), points=t.integer("points", 400, minimum=2,
                                                                                 maximum=10_000))
    t.done()

    t = _Table(p, "[damping]", doc.get("damping", {}))
    damping = Damping(mass_proportional=t.num("mass_proportional", 0.0, nonneg=True),
                      stiffness_proportional=t.num("stiffness_proportional", 0.0, nonneg=True))
    if damping.stiffness_proportional > 1.0:  # beyond it the step matrix ~ beta K (singular: rigid modes)
        t.fail("stiffness_proportional", f"must be <= 1 s (beta = 1 s already overdamps every flexible mode), "
                                         f"got {damping.stiffness_proportional:g}")
    t.done()

    t = _Table(p, "[analysis]", doc.get("analysis", {}))
    outs = t.nodes("output_nodes", len(node_z))
    sweep_amb = t.string("sweep_amb", None)
    if sweep_amb is not None and sweep_amb not in [a.name for a in ambs]:
        t.fail("sweep_amb", f"no [[amb]] named {t.short(sweep_amb)}")
    if sweep_amb is not None and len(ambs) < 3:
        t.fail("sweep_amb", "the support sweep moves a third AMB: the scene needs at least three")
    refs = t.raw("reference_criticals", [])
    if not isinstance(refs, list) or any(isinstance(v, bool) or not isinstance(v, (int, float))
                                         or not 1 / t.LIMIT <= v <= t.LIMIT for v in refs):
        t.fail("reference_criticals", f"must be a list of positive frequencies in Hz, got {t.short(refs)}")
    analysis = Analysis(output_nodes=tuple(k - 1 for k in outs), sweep_amb=sweep_amb,
                        frequency_max=t.num("frequency_max", 4000.0, positive=True),
                        reference_criticals=tuple(float(v) for v in refs), reference=t.string("reference", ""),
                        touchdown_clearance=t.num("touchdown_clearance", None, positive=True))
    if analysis.touchdown_clearance is not None:  # the default of every AMB that gives none of its own
        c = analysis.touchdown_clearance
        for k, a in enumerate(ambs):
            if a.touchdown_clearance is None:
                if c >= a.gap:
                    t.fail("touchdown_clearance", f"{c:g} m (the default of every [[amb]] without its own) must be "
                                                  f"smaller than the magnetic gap {a.gap:g} m of AMB {a.name!r} (the "
                                                  f"touchdown bearing catches the rotor before the stator)")
                ambs[k] = replace(a, touchdown_clearance=c)
    t.done()

    t = _Table(p, "[simulation]", doc.get("simulation", {}))
    # whether the controller period is a whole number of steps is checked where the step is used
    # (plant.step.PlantRunner), so that `simulate --h` can override an inconsistent step
    step = t.num("step", None, positive=True)
    run_up = t.pair("run_up", None)
    if run_up is not None and (run_up[0] < 0 or run_up[1] < 0):
        t.fail("run_up", f"speeds must be >= 0 rad/s, got {list(run_up)!r}")
    run_up_time = t.pair("run_up_time", (0.0, 1.0))
    if not 0 <= run_up_time[0] < run_up_time[1]:
        t.fail("run_up_time", f"must be [t0, t1] with 0 <= t0 < t1 s, got {list(run_up_time)!r}")
    sim_nodes = t.nodes("output_nodes", len(node_z))
    rho = t.num("rho_inf", 0.8, nonneg=True)
    if rho > 1:
        t.fail("rho_inf", f"must be in [0, 1], got {rho:g}")
    simulation = Simulation(
        integrator=t.string("integrator", "bdf1", choices=SCHEMES),
        step=step, rho_inf=rho, duration=t.num("duration", 0.5, positive=True),
        force_law=t.string("force_law", "linear", choices=("linear", "nonlinear")),
        speed=t.num("speed", None, nonneg=True), run_up=run_up, run_up_time=run_up_time,
        newton_iterations=t.integer("newton_iterations", 10, minimum=1, maximum=1000),
        newton_tol=t.num("newton_tol", 1e-10, positive=True),
        output_nodes=tuple(sim_nodes), record_every=t.integer("record_every", 1, minimum=1),
    )
    if simulation.integrator == "zoh" and (simulation.force_law == "nonlinear" or run_up is not None):
        t.fail("integrator", "zoh (exact) needs a linear time-invariant scene: no nonlinear force law, no run_up")
    t.done()

    simulation = replace(simulation, period=1.0 / ctrl.sample_rate)
    plant = PlantSpec(name=name, path=p, model=model, sections=tuple(sections), discs=tuple(discs),
                      ambs=tuple(ambs), axial_amb=axial, unbalances=tuple(unb), speed=speed, damping=damping,
                      node_z=node_z, simulation=simulation)
    faults = FaultSchedule(tuple(parse_fault(raw, p, where, plant, i + 1)
                                 for i, (where, raw) in enumerate(_tables(p, doc, "fault"))))
    return Scene(name=name, description=description, path=p, plant=plant, controller=ctrl, analysis=analysis,
                 faults=faults)


# --------------------------------------------------------------------------- fault schedules
#: parameters of each fault kind (besides kind, at, duration/until): key -> (quantity, default)
#: with quantity "time" (s, or "0.2s", "200ms", "150us"), "speed" (rad/s, or "3000rpm", "50Hz"),
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
    "unbalance_step": {"node": ("node", None), "position": ("position", None), "magnitude": ("positive", ...),
                       "phase": ("number", 0.0)},
    "speed_trip": {"to": ("speed", 0.0), "over": ("time", 1.0)},
    "message_loss": {"direction": ("direction", "both"), "probability": ("probability", 1.0), "seed": ("int", None)},
    "message_delay": {"direction": ("direction", "both"), "periods": ("periods", ...)},
    "controller_restart": {},
}
assert set(FAULT_PARAMS) == set(FAULT_KINDS)


def _quantity(t: _Table, key: str, v: Any, what: str) -> float:
    """A number, or a string with units: time (s, ms, us, ns) or speed (rpm, Hz, rad/s)."""
    if isinstance(v, str):
        txt = v.strip()
        units = ({"ns": 1e-9, "us": 1e-6, "ms": 1e-3, "s": 1.0} if what == "time"
                 else {"rpm": 2 * math.pi / 60, "Hz": 2 * math.pi, "hz": 2 * math.pi, "rad/s": 1.0} if what == "speed"
                 else {})
        f = 1.0
        for u in sorted(units, key=len, reverse=True):
            if txt.endswith(u):
                txt, f = txt[: -len(u)].strip(), units[u]
                break
        try:
            x = float(txt) * f
        except ValueError:
            hint = {"time": " such as 0.2s, 200ms or 150us", "speed": " such as 3000rpm, 50Hz or 314rad/s"}.get(what, "")
            t.fail(key, f"must be a {what if what in ('time', 'speed') else 'number'}{hint}, got {t.short(v)}")
        return t.number(key, x)
    return t.number(key, v)


def _fault_axes(plant: PlantSpec) -> list[str]:
    return ([f"{a.name}.{x}" for a in plant.ambs for x in "xy"]
            + ([f"{plant.axial_amb.name}.z"] if plant.axial_amb is not None else []))


def parse_fault(raw: Any, path: str, where: str, plant: PlantSpec, index: int) -> Fault:
    """One ``[[fault]]`` table (or a ``--fault`` spec made into a table) -> :class:`Fault`."""
    t = _Table(path, where, raw)
    kind = t.string("kind", choices=FAULT_KINDS)
    t.where = f"{where} {kind}"
    start = _quantity(t, "at", t.raw("at"), "time")
    if start < 0:
        t.fail("at", f"must be >= 0 s, got {start:g}")
    end = math.inf
    if t.has("duration") and t.has("until"):
        t.fail("duration", "give either 'duration' or 'until', not both")
    for key in ("duration", "until"):
        if t.has(key):
            if kind in _PERMANENT:
                t.fail(key, f"{kind} is permanent (no duration or until)")
            v = _quantity(t, key, t.raw(key), "time")
            end = start + v if key == "duration" else v
            if not end > start:
                t.fail(key, f"the fault must end after it starts (at {start:g} s), got {'duration' if key == 'duration' else 'until'} {v:g} s")
    names = _fault_axes(plant)
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
            if not isinstance(v, str):
                t.fail(key, f"must be an axis name such as {names[0]!r} or a station such as "
                            f"{names[0].split('.')[0]!r}, got {t.short(v)}")
            stations = sorted({n.split(".")[0] for n in names})
            if v in names and q != "station":
                axes = (names.index(v),)
            elif v in stations:
                axes = tuple(i for i, n in enumerate(names) if n.split(".")[0] == v)
            elif v == "all" and q == "axes":
                axes = tuple(range(len(names)))
            else:
                t.fail(key, f"{t.short(v)} is not " + ("a station" if q == "station" else "an AMB axis or station")
                            + f" of this scene (have {', '.join(stations if q == 'station' else names + stations)})")
            label = v
        elif q in ("time", "speed"):
            params[key] = _quantity(t, key, v, q)
            if params[key] < 0:
                t.fail(key, f"must be >= 0, got {params[key]:g}")
        elif q in ("number", "positive", "probability"):
            params[key] = _quantity(t, key, v, "number")
            if q == "positive" and not params[key] > 0:
                t.fail(key, f"must be > 0, got {params[key]:g}")
            if q == "probability" and not 0 < params[key] <= 1:
                t.fail(key, f"must be a probability in (0, 1], got {params[key]:g}")
        elif q in ("int", "periods"):
            if isinstance(v, bool) or not isinstance(v, int):
                t.fail(key, f"must be an integer, got {t.short(v)}")
            lo, hi = (1, 100_000) if q == "periods" else (0, 2**63 - 1)
            if not lo <= v <= hi:
                t.fail(key, f"must be from {lo} to {hi}, got {v}")
            params[key] = v
        elif q == "direction":
            params[key] = t.string(key, choices=("sensors", "currents", "both"))
    if kind == "unbalance_step":
        node = _station(t, plant.node_z)
        params["node"] = node + 1   # 1-based, as in the scene
        params.pop("position", None)
        label = ""   # the node is a parameter
    t.done()
    return Fault(kind=kind, start=start, end=end, axes=axes, axis=label, params=tuple(sorted(params.items())),
                 index=index, source=where)


def parse_fault_spec(text: str, scene: Scene, index: int) -> Fault:
    """A ``--fault`` flag, ``KIND:key=value,key=value`` (e.g. ``sensor_noise:at=0.2s,axis=A.x,sigma=2e-6``),
    parsed by the rules of ``[[fault]]``; errors name the flag as ``--fault #index``."""
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
        val = val.strip()
        for conv in (int, float):
            try:
                val = conv(val)
                break
            except ValueError:
                pass
        table[key] = val
    return parse_fault(table, "command line", where, scene.plant, index)


def with_fault_flags(scene: Scene, specs) -> Scene:
    """The scene with ``--fault`` specs scheduled after its own ``[[fault]]`` tables."""
    if not specs:
        return scene
    n = len(scene.faults)
    return scene.with_faults(FaultSchedule(tuple(parse_fault_spec(s, scene, n + i + 1) for i, s in enumerate(specs))))
