"""The closed-loop system: a compiled plant model together with the controller's continuous
current law, what the closed-loop analyses (``loop/analysis``) and studies read.

    compile_system(scene) -> System        scene -> plant Model (ambhil.plant.model) + H(s) (ambhil.controller.transfer)
    controller_runner(scene | system)      the controller process's loop body for this scene

A :class:`System` *is* the plant model (every matrix and operator of :class:`ambhil.plant.model.Model`)
with two more fields: the whole ``scene`` and ``H``, the per-axis current law ``i = -H(s) y``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import scipy.signal as sig

from ambhil.controller.discrete import ControllerRunner
from ambhil.controller.law_loader import law_factory
from ambhil.controller.law_runner import LawRunner
from ambhil.controller.pid_law import PIDLaw
from ambhil.controller.transfer import current_law
from ambhil.plant.model import Model, compile_model, operating_currents
from ambhil.plant.params import ParameterError
from ambhil.plant.rotor import FERotor
from .scene import Scene, load_scene


@dataclass(frozen=True, eq=False)
class System(Model):
    scene: Scene | None = None
    H: sig.StateSpace | None = None  # current law i = -H(s) y: per axis (1 x 1), or na x na (MIMO)


def _scene(scene: Scene | str | Path) -> Scene:
    return scene if isinstance(scene, Scene) else load_scene(scene)


def compile_system(scene: Scene | str | Path, rung: str | None = None, rotor: FERotor | None = None) -> System:
    """Compile a scene (or a scene file) at its rung, or at ``rung``; ``rotor``: an FE rotor already
    assembled from this very scene (e.g. ``other.rotor``), reused as is."""
    scene = _scene(scene)
    model = compile_model(scene.plant, rung, rotor, period=scene.period)
    c = scene.controller
    if c.kind == "pid":
        H = current_law(c)
    else:  # an LTI kind: SISO for one chain on every axis, else na x na (controller/law_lti.py)
        from ambhil.controller.law_lti import current_law as lti_current_law
        H = lti_current_law(c, axis_names(scene), scene.period)
    return System(**{f.name: getattr(model, f.name) for f in fields(Model)}, scene=scene, H=H)


def controller_runner(scene: Scene | System | str | Path, sample_rate: float | None = None,
                      method: str | None = None, rung: str | None = None, law: str | None = None):
    """The scene's discrete controller, started in equilibrium at the operating point (of the
    scene's rung, or ``rung``: under gravity its currents carry the weight).

    The law is ``law`` (a resolved name, controller/law_loader.py: ``--law``), else the scene's
    ``[controller] law`` or ``kind``; the built-in PID runs fused with the sensor and amplifier
    (:class:`ControllerRunner`), unless the amplifier has a slew limit (the fused kernel has
    none); every other law runs between them in a :class:`LawRunner`."""
    if isinstance(scene, System):
        sc, i_op = scene.scene, scene.i_op
    else:
        sc = _scene(scene)
        i_op = operating_currents(sc.plant, rung)
    _check_limit(sc, i_op, sc.plant.model.gravity)
    return make_runner(sc, i_op, sample_rate, method, law)


def make_runner(scene: Scene, i_op, sample_rate=None, method=None, law: str | None = None):
    """The runner of ``scene``'s law (see :func:`controller_runner`) at the operating currents ``i_op``."""
    c = scene.controller
    law = law or c.law
    axes = axis_names(scene)
    if law is not None:
        factory, name = law_factory(law)
        return LawRunner(factory, c, i_op, sample_rate, method, axes=axes, name=name)
    if c.kind != "pid":
        from ambhil.controller.law_lti import LTILaw
        return LawRunner(LTILaw, c, i_op, sample_rate, method, axes=axes, name=f"[controller] kind = {c.kind!r}")
    if math.isfinite(c.amplifier.slew_rate):
        return LawRunner(PIDLaw, c, i_op, sample_rate, method, axes=axes, name="pid")
    return ControllerRunner(c, i_op, sample_rate, method)


def black_box_reason(scene: Scene, law: str | None = None) -> str | None:
    """Why the frequency-domain analyses cannot use the scene's law (``law``: a ``--law`` given
    instead), or None when they can (the built-in PID and the LTI kinds of ``[controller] kind``).
    One line, with the time-domain alternatives."""
    law = law or scene.controller.law
    if law is None:
        return None
    from pathlib import Path
    return (f"the law {Path(law).name} is a black box "
            f"(Python, C or FMU): the frequency-domain analyses need a linear law (the built-in PID, "
            f"or [controller] kind = \"statespace\" / \"transfer\"); use the time domain: "
            f"`ambhil simulate`, `ambhil run`, `ambhil test-controller`")


def axis_names(scene: Scene) -> tuple[str, ...]:
    """The sensor/coil axes in the order of every vector of the loop (RunMeta ``axis_names``)."""
    return tuple(f"{a.name}-{x}" for a in scene.plant.ambs for x in "xy")


def _check_limit(scene: Scene, i_op, gravity) -> None:
    """Under gravity (every rung) the operating currents carry the weight: refuse a scene whose
    amplifier cannot deliver them (the loop would start saturated and drop the rotor)."""
    if not gravity:
        return
    lim = scene.controller.amplifier.current_limit
    for (name, ax), i in zip(((a.name, x) for a in scene.plant.ambs for x in "xy"), i_op):
        if abs(i) > lim:
            raise ParameterError(f"{scene.path}: AMB {name} {ax}: carrying its share of the weight under [model] "
                                 f"gravity needs {i:.4g} A, beyond [amplifier] current_limit = {lim:g} A")
