"""The controller's scene tables: ``[sensor]``, ``[amplifier]`` and ``[controller]`` (the PID
gains, the derivative filter, the sample rate, the discretisation) -> the dataclasses of
:mod:`ambhil.controller.params`.

``[controller] sample_rate`` is the loop's one sample rate: the controller samples at it and the
plant holds each current over its period (:attr:`ambhil.loop.scene.Scene.period`).
"""
from __future__ import annotations

import math
from typing import Sequence

from ambhil.controller.params import DISCRETISATIONS, Amplifier, ControllerParams, Sensor
from ambhil.plant.params import RadialAMB
from .scene_table import SceneError, Table

#: highest sample rate a scene may give, Hz
MAX_SAMPLE_RATE = 1e6


def sensor_amplifier(doc: dict, p: str, ambs: Sequence[RadialAMB]) -> tuple[Sensor, Amplifier]:
    """``[sensor]`` and ``[amplifier]``; the amplifier's current limit must hold every AMB at its
    misalignment."""
    t = Table(p, "[sensor]", doc.get("sensor", {}))
    sensor = Sensor(gain=t.num("gain", 1.0, positive=True), time_constant=t.num("time_constant", 0.0, nonneg=True))
    t.done()
    t = Table(p, "[amplifier]", doc.get("amplifier", {}))
    amplifier = Amplifier(gain=t.num("gain", 1.0, positive=True),
                          time_constant=t.num("time_constant", 0.0, nonneg=True),
                          current_limit=t.num("current_limit", math.inf, positive=True, finite=False))
    t.done()
    for a in ambs:
        need = a.bias_current * math.hypot(*a.misalignment) / a.gap
        if need >= amplifier.current_limit:
            raise SceneError(f"{p}: [amplifier] key 'current_limit': {amplifier.current_limit:g} A cannot hold "
                             f"AMB {a.name!r} at its misalignment (needs {need:g} A)")
    return sensor, amplifier


def controller(doc: dict, p: str, sensor: Sensor, amplifier: Amplifier) -> ControllerParams:
    """``[controller]`` (required): kp, ki, kd, derivative_filter, sample_rate, discretisation,
    delay_samples, anti_windup."""
    if "controller" not in doc:
        raise SceneError(f"{p}: [controller]: table is required (kp, ki, kd, derivative_filter, sample_rate)")
    t = Table(p, "[controller]", doc["controller"])
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
    if ctrl.sample_rate > MAX_SAMPLE_RATE:
        t.fail("sample_rate", f"must be <= {MAX_SAMPLE_RATE:g} Hz, got {ctrl.sample_rate:g}")
    if ctrl.kd > 0 and ctrl.derivative_filter <= 0:
        t.fail("derivative_filter", "must be > 0 when kd > 0 (a pure derivative is not realisable)")
    t.done()
    return ctrl
