"""The bearings' scene tables: ``[[amb]]`` (radial AMBs, by their coil or by datasheet
coefficients, with their sensor station, misalignment, touchdown clearance and auxiliary bearing
``[amb.auxiliary]``) and ``[axial_amb]`` -> :class:`ambhil.plant.params.RadialAMB` and
:class:`~ambhil.plant.params.AxialAMB`.
"""
from __future__ import annotations

import math
import re
from dataclasses import fields, replace

from ambhil.plant.auxiliary_bearing import AuxiliaryBearing
from ambhil.plant.params import AxialAMB, RadialAMB, Section
from .scene_table import SceneError, Table, station, tables

#: the keys that describe a radial AMB by its coil (the alternative: datasheet coefficients)
COIL_KEYS = ("bias_current", "turns", "pole_area", "pole_angle")


def radial_ambs(doc: dict, p: str, node_z: tuple[float, ...],
                sections: list[Section] | None = None) -> list[RadialAMB]:
    """Every ``[[amb]]`` (named A, B, ... unless named): at least two, distinct names and nodes.
    ``sections``: the shaft's (the default journal radius of an auxiliary bearing); None: read
    again from ``doc`` (already validated by :func:`ambhil.loop.scene_plant.shaft`)."""
    if sections is None and any(isinstance(r, dict) and "auxiliary" in r for _, r in tables(p, doc, "amb")):
        from .scene_plant import shaft
        sections = shaft(doc, p)[0]
    ambs: list[RadialAMB] = []
    for where, raw in tables(p, doc, "amb"):
        t = Table(p, where, raw)
        a = radial_amb(t, node_z, chr(ord("A") + len(ambs)), sections)
        if any(b.name == a.name for b in ambs):
            t.fail("name", f"duplicate AMB name {a.name!r}")
        if any(b.node == a.node for b in ambs):
            t.fail("node", f"another AMB already sits at node {a.node + 1}")
        ambs.append(a)
    if len(ambs) < 2:
        raise SceneError(f"{p}: [[amb]]: at least two radial AMBs are needed to levitate the rotor, got {len(ambs)}")
    return ambs


def radial_amb(t: Table, node_z: tuple[float, ...], default_name: str,
               sections: list[Section] | None = None) -> RadialAMB:
    """One ``[[amb]]`` table (``t``; its keys all read and checked when this returns)."""
    nm = t.string("name", default_name)
    t.where = f"{t.where} {t.short(nm)}"
    node = station(t, node_z)
    sensor_node = station(t, node_z, "sensor_node", "sensor_position", required=False)
    sensor_node = node if sensor_node is None else sensor_node
    gap = t.num("gap", positive=True)
    mis = t.pair("misalignment", (0.0, 0.0))
    if math.hypot(*mis) >= gap:
        t.fail("misalignment", f"offset {math.hypot(*mis):g} m must be smaller than the gap {gap:g} m")
    if t.has("position_stiffness") or t.has("current_stiffness"):
        # datasheet coefficients: k_s < 0 (N/m) and k_i > 0 (N/A) at the centred operating point
        ks, ki = t.num("position_stiffness"), t.num("current_stiffness", positive=True)
        if not ks < 0:
            t.fail("position_stiffness", f"is the bearing's negative position stiffness k_s (N/m): must be < 0, "
                                         f"got {ks:g}")
        both = [k for k in COIL_KEYS if k in t.data]
        if both:
            t.fail(both[0], "give either the coil (bias_current, turns, pole_area, pole_angle) or the datasheet "
                            "coefficients (position_stiffness, current_stiffness), not both")
        a = RadialAMB(name=nm, node=node, sensor_node=sensor_node, gap=gap, bias_current=-ks * gap / ki, turns=0.0,
                      pole_area=0.0, pole_angle=0.0, misalignment=mis, datasheet=(ks, ki))
    else:
        a = RadialAMB(
            name=nm, node=node, sensor_node=sensor_node,
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
    if t.has("auxiliary"):
        aux = auxiliary(t, a, sections)
        a = replace(a, auxiliary=aux, touchdown_clearance=aux.clearance)
    t.done()
    return a


#: the keys of ``[amb.auxiliary]``: the fields of AuxiliaryBearing, in their order
AUX_KEYS = tuple(f.name for f in fields(AuxiliaryBearing))


def journal_radius(sections: list[Section], node: int) -> float:
    """Half the outer diameter of the shaft at ``node`` (0-based): the larger of the two sections
    meeting there (the journal a touchdown bearing sits on is the thicker one)."""
    first = 0  # index of the first element of each section
    d = 0.0
    for s in sections:
        if first <= node <= first + s.elements:  # the node is one of this section's
            d = max(d, s.outer_diameter)
        first += s.elements
    return 0.5 * d


def auxiliary(t: Table, a: RadialAMB, sections: list[Section] | None) -> AuxiliaryBearing:
    """``[amb.auxiliary]`` of the AMB ``a`` (its ``[[amb]]`` table ``t``, every other key of it
    already read): the auxiliary bearing, checked; each error names ``auxiliary.<key>``.

    One clearance: ``clearance`` defaults to the AMB's ``touchdown_clearance`` and must equal it
    when both are given (the orbits and zones are judged against the same circle the rotor lands
    on); it is below the magnetic gap (the rotor lands before it reaches the stator)."""
    raw = t.raw("auxiliary")
    if not isinstance(raw, dict):
        t.fail("auxiliary", f"must be a table ([amb.auxiliary] after its [[amb]], or auxiliary = {{ ... }}), "
                            f"got {type(raw).__name__} {t.short(raw)}")
    # the sub-table's keys prefixed, so that every message (unknown keys too) names 'auxiliary.<key>'
    s = Table(t.path, t.where, {f"auxiliary.{k}": v for k, v in raw.items()})
    got = {k: s.num(f"auxiliary.{k}", None) for k in AUX_KEYS}
    td = a.touchdown_clearance
    c = got["clearance"]
    if c is None:
        if td is None:
            s.fail("auxiliary.clearance", "is required (or this [[amb]]'s touchdown_clearance)")
        c = td
    elif td is not None and not math.isclose(c, td, rel_tol=1e-12):
        s.fail("auxiliary.clearance", f"{c:g} m differs from this AMB's touchdown_clearance {td:g} m: give one "
                                      f"(the rotor lands on the auxiliary bearing at the touchdown clearance)")
    if c >= a.gap:
        s.fail("auxiliary.clearance", f"{c:g} m must be smaller than this AMB's magnetic gap {a.gap:g} m (the "
                                      f"auxiliary bearing catches the rotor before the stator)")
    if got["stiffness"] is None:
        s.fail("auxiliary.stiffness", "is required (N/m for exponent 1, N/m^n for the Hertz law)")
    s.done()
    rs = got["shaft_radius"]
    if rs is None:
        rs = journal_radius(sections, a.node) if sections else None
        if not rs:
            s.fail("auxiliary.shaft_radius", "is required (the shaft's section at this node is not known)")
    kw = {k: v for k, v in got.items() if v is not None}
    kw.update(clearance=c, shaft_radius=rs)
    try:
        return AuxiliaryBearing(**kw).validate("auxiliary")
    except ValueError as e:  # "auxiliary.<key> = <value>: <why>" -> the scene's one-line style
        m = re.match(r"(auxiliary\.\w+) = (.*?): (.*)$", str(e))
        if m is None:
            raise
        s.fail(m[1], f"{_shown(m[2])}: {m[3]}")


def _shown(v: str) -> str:
    """A value of AuxiliaryBearing's message as the scene's messages show numbers (%g)."""
    try:
        return f"{float(v):g}"
    except ValueError:
        return v


def axial_amb(doc: dict, p: str, node_z: tuple[float, ...]) -> AxialAMB | None:
    """``[axial_amb]`` (named Z unless named), or None when the scene has none."""
    if "axial_amb" not in doc:
        return None
    t = Table(p, "[axial_amb]", doc["axial_amb"])
    axial = AxialAMB(
        name=t.string("name", "Z"), node=station(t, node_z),
        gap=t.num("gap", positive=True), bias_current=t.num("bias_current", positive=True),
        turns=t.num("turns", positive=True), pole_area=t.num("pole_area", positive=True),
    )
    t.done()
    return axial
