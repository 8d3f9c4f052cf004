"""The closed-loop system: a compiled plant model together with the controller's continuous
current law, what the closed-loop analyses (``loop/analysis``) and studies read.

    compile_system(scene) -> System        scene -> plant Model (ambhil.plant.model) + H(s) (ambhil.controller.transfer)
    controller_runner(scene | system)      the controller process's loop body for this scene

A :class:`System` *is* the plant model (every matrix and operator of :class:`ambhil.plant.model.Model`)
with two more fields: the whole ``scene`` and ``H``, the per-axis current law ``i = -H(s) y``.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import scipy.signal as sig

from ambhil.controller.discrete import ControllerRunner
from ambhil.controller.transfer import current_law
from ambhil.plant.model import Model, compile_model, operating_currents
from ambhil.plant.params import ParameterError
from ambhil.plant.rotor import FERotor
from .scene import Scene, load_scene


@dataclass(frozen=True, eq=False)
class System(Model):
    scene: Scene | None = None
    H: sig.StateSpace | None = None  # per-axis current law i = -H(s) y


def _scene(scene: Scene | str | Path) -> Scene:
    return scene if isinstance(scene, Scene) else load_scene(scene)


def compile_system(scene: Scene | str | Path, rung: str | None = None, rotor: FERotor | None = None) -> System:
    """Compile a scene (or a scene file) at its rung, or at ``rung``; ``rotor``: an FE rotor already
    assembled from this very scene (e.g. ``other.rotor``), reused as is."""
    scene = _scene(scene)
    model = compile_model(scene.plant, rung, rotor, period=scene.period)
    return System(**{f.name: getattr(model, f.name) for f in fields(Model)}, scene=scene,
                  H=current_law(scene.controller))


def controller_runner(scene: Scene | System | str | Path, sample_rate: float | None = None,
                      method: str | None = None, rung: str | None = None) -> ControllerRunner:
    """The scene's discrete controller, started in equilibrium at the operating point (of the
    scene's rung, or ``rung``: under gravity the ancf rung's currents carry the weight)."""
    if isinstance(scene, System):
        _check_limit(scene.scene, scene.i_op, scene.gravity)
        return ControllerRunner(scene.scene.controller, scene.i_op, sample_rate, method)
    scene = _scene(scene)
    i_op = operating_currents(scene.plant, rung)
    _check_limit(scene, i_op, (rung or scene.plant.model.rung) == "ancf" and scene.plant.model.gravity)
    return ControllerRunner(scene.controller, i_op, sample_rate, method)


def _check_limit(scene: Scene, i_op, gravity) -> None:
    """Under gravity (ancf rung) the operating currents carry the weight: refuse a scene whose
    amplifier cannot deliver them (the loop would start saturated and drop the rotor)."""
    if not gravity:
        return
    lim = scene.controller.amplifier.current_limit
    for (name, ax), i in zip(((a.name, x) for a in scene.plant.ambs for x in "xy"), i_op):
        if abs(i) > lim:
            raise ParameterError(f"{scene.path}: AMB {name} {ax}: carrying its share of the weight under [model] "
                                 f"gravity needs {i:.4g} A, beyond [amplifier] current_limit = {lim:g} A")
