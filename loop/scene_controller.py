"""The controller's scene tables: ``[sensor]``, ``[amplifier]`` and ``[controller]`` (the PID
gains, the derivative filter, the sample rate, the discretisation) -> the dataclasses of
:mod:`ambhil.controller.params`.

``[controller] sample_rate`` is the loop's one sample rate: the controller samples at it and the
plant holds each current over its period (:attr:`ambhil.loop.scene.Scene.period`).
"""
from __future__ import annotations

import math
import os
from typing import Sequence

from ambhil.controller.law import LawError
from ambhil.controller.law_loader import resolve
from ambhil.controller.params import DISCRETISATIONS, KINDS, Amplifier, ControllerParams, Sensor
from ambhil.plant.params import RadialAMB
from .scene_table import SceneError, Table

#: highest sample rate a scene may give, Hz
MAX_SAMPLE_RATE = 1e6

#: sub-tables of [controller] a law reads: statespace / transfer (controller/law_lti.py), fmu (law_fmu.py)
LAW_TABLES = ("statespace", "transfer", "fmu")


def sensor_amplifier(doc: dict, p: str, ambs: Sequence[RadialAMB]) -> tuple[Sensor, Amplifier]:
    """``[sensor]`` and ``[amplifier]``; the amplifier's current limit must hold every AMB at its
    misalignment."""
    t = Table(p, "[sensor]", doc.get("sensor", {}))
    sensor = Sensor(gain=t.num("gain", 1.0, positive=True), time_constant=t.num("time_constant", 0.0, nonneg=True))
    t.done()
    t = Table(p, "[amplifier]", doc.get("amplifier", {}))
    amplifier = Amplifier(gain=t.num("gain", 1.0, positive=True),
                          time_constant=t.num("time_constant", 0.0, nonneg=True),
                          current_limit=t.num("current_limit", math.inf, positive=True, finite=False),
                          slew_rate=t.num("slew_rate", math.inf, positive=True, finite=False))
    t.done()
    for a in ambs:
        need = a.bias_current * math.hypot(*a.misalignment) / a.gap
        if need >= amplifier.current_limit:
            raise SceneError(f"{p}: [amplifier] key 'current_limit': {amplifier.current_limit:g} A cannot hold "
                             f"AMB {a.name!r} at its misalignment (needs {need:g} A)")
    return sensor, amplifier


def controller(doc: dict, p: str, sensor: Sensor, amplifier: Amplifier,
               ambs: Sequence[RadialAMB] = ()) -> ControllerParams:
    """``[controller]`` (required): kp, ki, kd, derivative_filter, sample_rate, discretisation,
    delay_samples, anti_windup; ``kind`` (pid | statespace | transfer, controller/law_lti.py),
    ``law`` (a law of its own, controller/law_loader.py, relative to the scene) and the law's
    parameters ``[controller.params]``.  The PID gains are required by the built-in law only.
    ``ambs``: the loop's bearings, whose axes an LTI kind's table is checked against."""
    if "controller" not in doc:
        raise SceneError(f"{p}: [controller]: table is required (kp, ki, kd, derivative_filter, sample_rate)")
    t = Table(p, "[controller]", doc["controller"])
    kind = t.string("kind", "pid", choices=KINDS)
    law = t.raw("law", None)
    if law is not None:
        if not isinstance(law, str) or not law.strip():
            t.fail("law", f"must be a file name (FILE.py:CLASS, FILE.so or FILE.fmu), got {t.short(law)}")
        if kind != "pid":
            t.fail("law", f"a law of its own and kind = {kind!r} exclude each other")
        try:
            law = resolve(law, os.path.dirname(os.path.abspath(p)))
        except LawError as e:
            t.fail("law", str(e))
    params = t.raw("params", {})
    if not isinstance(params, dict):
        t.fail("params", f"must be a table (the law's own parameters), got {t.short(params)}")
    lti = {k: t.raw(k) for k in LAW_TABLES if t.has(k)}
    builtin = kind == "pid" and law is None
    ctrl = ControllerParams(
        kp=t.num("kp", positive=True) if builtin else t.num("kp", 1.0, positive=True),
        ki=t.num("ki", 0.0, nonneg=True),
        kd=t.num("kd", 0.0, nonneg=True),
        derivative_filter=t.num("derivative_filter", 0.0, nonneg=True),
        sample_rate=t.num("sample_rate", 10_000.0, positive=True),
        discretisation=t.string("discretisation", "tustin", choices=DISCRETISATIONS),
        delay_samples=t.integer("delay_samples", 0, minimum=0, maximum=10_000),
        anti_windup=t.boolean("anti_windup", True),
        sensor=sensor, amplifier=amplifier, kind=kind, law=law,
        table={k: v for k, v in doc["controller"].items() if k != "params"}, law_params=params, lti=lti,
    )
    if ctrl.sample_rate > MAX_SAMPLE_RATE:
        t.fail("sample_rate", f"must be <= {MAX_SAMPLE_RATE:g} Hz, got {ctrl.sample_rate:g}")
    if ctrl.kd > 0 and ctrl.derivative_filter <= 0:
        t.fail("derivative_filter", "must be > 0 when kd > 0 (a pure derivative is not realisable)")
    t.done()
    _check_lti(ctrl, p, ambs)
    return ctrl


def _check_lti(ctrl: ControllerParams, p: str, ambs: Sequence[RadialAMB]) -> None:
    """An LTI kind needs its sub-table, valid for the loop's axes (controller/law_lti.py); the
    sub-table of another kind is refused rather than ignored."""
    for k in ("transfer", "statespace"):
        if k in ctrl.lti and ctrl.kind != k:
            raise SceneError(f"{p}: [controller.{k}]: given, but [controller] kind = {ctrl.kind!r} "
                             f"(set kind = {k!r} to use it)")
    if ctrl.kind == "pid":
        return
    if ctrl.kind not in ctrl.lti:
        raise SceneError(f"{p}: [controller.{ctrl.kind}]: table is required by [controller] kind = {ctrl.kind!r}")
    if not ambs:
        return
    from ambhil.controller.law_lti import check
    try:
        check(ctrl, tuple(f"{a.name}-{x}" for a in ambs for x in "xy"))
    except LawError as e:
        raise SceneError(f"{p}: {e}") from None
