"""The bearings' scene tables: ``[[amb]]`` (radial AMBs, by their coil or by datasheet
coefficients, with their sensor station, misalignment and touchdown clearance) and
``[axial_amb]`` -> :class:`ambhil.plant.params.RadialAMB` and :class:`~ambhil.plant.params.AxialAMB`.
"""
from __future__ import annotations

import math
from dataclasses import replace

from ambhil.plant.params import AxialAMB, RadialAMB
from .scene_table import SceneError, Table, station, tables

#: the keys that describe a radial AMB by its coil (the alternative: datasheet coefficients)
COIL_KEYS = ("bias_current", "turns", "pole_area", "pole_angle")


def radial_ambs(doc: dict, p: str, node_z: tuple[float, ...]) -> list[RadialAMB]:
    """Every ``[[amb]]`` (named A, B, ... unless named): at least two, distinct names and nodes."""
    ambs: list[RadialAMB] = []
    for where, raw in tables(p, doc, "amb"):
        t = Table(p, where, raw)
        a = radial_amb(t, node_z, chr(ord("A") + len(ambs)))
        if any(b.name == a.name for b in ambs):
            t.fail("name", f"duplicate AMB name {a.name!r}")
        if any(b.node == a.node for b in ambs):
            t.fail("node", f"another AMB already sits at node {a.node + 1}")
        ambs.append(a)
    if len(ambs) < 2:
        raise SceneError(f"{p}: [[amb]]: at least two radial AMBs are needed to levitate the rotor, got {len(ambs)}")
    return ambs


def radial_amb(t: Table, node_z: tuple[float, ...], default_name: str) -> RadialAMB:
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
    t.done()
    return a


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
