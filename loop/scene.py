"""Scene files: a TOML description of one test situation, loaded and validated.

A scene says only what a situation needs.  Loading checks every key: unknown keys, wrong
types and non-physical values raise :class:`SceneError`, whose message is one line naming the
file, the key and the problem.  The result is a tree of frozen dataclasses; nothing downstream
re-reads the TOML.

Units are SI throughout (m, kg, s, A, N, Pa, rad, rad/s), except ``pole_angle`` in degrees.
Stations (discs, bearings, sensors, unbalances, outputs) are given either by ``node`` (1-based,
as in the paper: node 1 is the left end of the shaft) or by ``position`` (m from the left end),
which must coincide with a node of the mesh.

The loop has one sample rate, ``[controller] sample_rate``: the controller samples at it and the
plant holds each coil current over its period, :attr:`Scene.period` (given to the plant model by
:func:`ambhil.loop.system.compile_system`).

:func:`parse_scene` reads the tables in the order of a scene file, one parser per table or group:
``scene_plant.py`` (the rotor's tables and ``[simulation]``), ``scene_bearings.py`` (the AMBs),
``scene_controller.py`` (sensor, amplifier, controller), ``scene_faults.py`` (``[[fault]]``), all
on the validation helpers of ``scene_table.py``.
"""
from __future__ import annotations

import difflib
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ambhil.controller.params import ControllerParams
from ambhil.plant.faults import FaultSchedule
from ambhil.plant.params import ParameterError as _PlantParameterError, PlantSpec, RadialAMB
from . import scene_bearings, scene_controller, scene_plant
from .scene_faults import FAULT_PARAMS, parse_fault, parse_fault_spec
from .scene_table import SceneError, Table, tables

__all__ = ["Analysis", "Scene", "SceneError", "INPUT_ERRORS", "touchdown_note", "load_scene", "parse_scene",
           "with_fault_flags", "parse_fault", "FAULT_PARAMS"]

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

    @property
    def period(self) -> float:
        """The loop's period (s): the controller's sample period, over which the plant holds each
        coil current (derived from ``[controller] sample_rate``, the one place it is stored)."""
        return self.controller.period

    def with_faults(self, extra: FaultSchedule) -> "Scene":
        """A copy with more faults scheduled (e.g. from ``--fault`` flags), after the scene's own."""
        return replace(self, faults=self.faults + extra)

    def with_plant(self, **changes: Any) -> "Scene":
        """A copy whose plant has some fields replaced (for sweeps and studies)."""
        return replace(self, plant=replace(self.plant, **changes))

    def with_controller(self, **changes: Any) -> "Scene":
        """A copy with controller parameters replaced (a new sample rate is also the plant's new
        input period: :attr:`period`)."""
        return replace(self, controller=replace(self.controller, **changes))


def touchdown_note(ambs) -> str:
    """The assumption to print beside touchdown clearances: '' when every AMB's is given in the
    scene, else which AMBs assume half their magnetic gap."""
    assumed = [a.name for a in ambs if a.touchdown_clearance is None]
    if not assumed:
        return ""
    return (f"touchdown clearance of {', '.join(assumed)} assumed: half the magnetic gap "
            f"(not in the scene; set [[amb]] touchdown_clearance)")


_TOP_KEYS = ("scene", "model", "shaft", "disc", "amb", "axial_amb", "sensor", "amplifier",
             "controller", "unbalance", "speed", "damping", "analysis", "simulation", "fault")


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
    """A scene's TOML document (``p`` names it in messages) -> :class:`Scene`; the tables are read
    in the order of a scene file, so the first problem reported is the first in the file."""
    _check_top_keys(doc, p)
    name, description = _header(doc, p)
    model = scene_plant.model_options(doc, p)
    sections, node_z = scene_plant.shaft(doc, p)
    discs = scene_plant.discs(doc, p, node_z)
    ambs = scene_bearings.radial_ambs(doc, p, node_z)
    axial = scene_bearings.axial_amb(doc, p, node_z)
    sensor, amplifier = scene_controller.sensor_amplifier(doc, p, ambs)
    ctrl = scene_controller.controller(doc, p, sensor, amplifier, ambs)
    unbalances = scene_plant.unbalances(doc, p, node_z)
    speed = scene_plant.speed(doc, p)
    damping = scene_plant.damping(doc, p)
    analysis, ambs = _analysis(doc, p, node_z, ambs)
    simulation = scene_plant.simulation(doc, p, node_z)
    plant = PlantSpec(name=name, path=p, model=model, sections=tuple(sections), discs=tuple(discs),
                      ambs=tuple(ambs), axial_amb=axial, unbalances=tuple(unbalances), speed=speed,
                      damping=damping, node_z=node_z, simulation=simulation)
    faults = FaultSchedule(tuple(parse_fault(raw, p, where, plant, i + 1)
                                 for i, (where, raw) in enumerate(tables(p, doc, "fault"))))
    return Scene(name=name, description=description, path=p, plant=plant, controller=ctrl, analysis=analysis,
                 faults=faults)


def _check_top_keys(doc: dict, p: str) -> None:
    for k in doc:
        if k not in _TOP_KEYS:
            near = difflib.get_close_matches(k, _TOP_KEYS, 1, 0.6)
            raise SceneError(f"{p}: unknown top-level key '{k if len(k) <= 60 else k[:57] + '...'}'"
                             + (f" (did you mean '{near[0]}'?)" if near else "")
                             + f" (allowed: {', '.join(_TOP_KEYS)})")


def _header(doc: dict, p: str) -> tuple[str, str]:
    """``[scene]``: (name, description); the name defaults to the file's stem, made to fit."""
    t = Table(p, "[scene]", doc.get("scene", {}))
    # the name makes run ids (zenoh key expressions, ambhil/<run-id>/..., with a 16-character time
    # stamp: at most 64 characters) and file names; the default, the file stem, is made to fit
    name_ok = lambda s: 1 <= len(s) <= 48 and all(c.isascii() and (c.isalnum() or c in "_.-") for c in s)
    name = t.string("name", "".join(c if name_ok(c) else "_" for c in Path(p).stem)[:48] or "scene")
    if not name_ok(name):
        t.fail("name", f"must be 1 to 48 characters of A-Z a-z 0-9 _ . - (it names runs and files), "
                       f"got {t.short(name)}")
    description = t.string("description", "")
    t.done()
    return name, description


def _analysis(doc: dict, p: str, node_z: tuple[float, ...],
              ambs: list[RadialAMB]) -> tuple[Analysis, list[RadialAMB]]:
    """``[analysis]`` -> (Analysis, the AMBs with its default touchdown clearance filled in)."""
    t = Table(p, "[analysis]", doc.get("analysis", {}))
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
    ambs = list(ambs)
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
    return analysis, ambs


def with_fault_flags(scene: Scene, specs) -> Scene:
    """The scene with ``--fault`` specs scheduled after its own ``[[fault]]`` tables; a spec ``none``
    leaves the scene's own tables out (a campaign's case runs with its faults alone)."""
    if not specs:
        return scene
    if "none" in specs:
        scene = replace(scene, faults=FaultSchedule())
        specs = [s for s in specs if s != "none"]
    n = len(scene.faults)
    return scene.with_faults(FaultSchedule(tuple(parse_fault_spec(s, scene.plant, n + i + 1)
                                                 for i, s in enumerate(specs))))
