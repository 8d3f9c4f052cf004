"""What the HIL commands (`plant`, `controller`, `run`, and `simulate`'s recording) derive from a
scene and their parsed flags, shared so that each is derived one way: the number of periods, the
loop latency in s, the plant step object, the RunMeta, the CPU placement of `ambhil run`."""
from __future__ import annotations

import os
from pathlib import Path

from ambhil.controller.discrete import describe, discretise
from ambhil.loop.scene import SceneError
from ambhil.plant.model import operating_currents
from ambhil.plant.ancf_faults import ANCFFaultyPlant
from ambhil.plant.ancf_step import plant_runner as runner_of
from ambhil.plant.run_options import RunOptions
from ambhil.plant.faults import FaultyPlant
from ambhil.bridge.cli.arguments import law_label
from ambhil.bridge.cli.convention import CliError


def duration_steps(scene, duration: float | None) -> int:
    """Controller periods of a run of ``duration`` s (default: [simulation] duration or 1 s)."""
    d = duration if duration is not None else (scene.plant.simulation.duration or 1.0)
    if not d > 0:
        raise SceneError(f"{scene.path}: --duration must be > 0 s, got {d}")
    return max(1, int(round(d * scene.controller.sample_rate)))


def latency_s(args, scene) -> float:
    """``--delay`` (an :class:`ambhil.loop.units.Time`, bridge/cli/arguments.py) in s at the
    scene's rate; 0 for a command without it."""
    d = getattr(args, "delay", None)
    return d.seconds(1.0 / scene.controller.sample_rate) if d is not None else 0.0


def check_currents_at(args, latency: float) -> None:
    """``--currents-at arrival`` needs real time and no fixed ``--delay`` (the arrival is the latency)."""
    if args.currents_at == "arrival" and (args.mode != "realtime" or latency):
        raise CliError("--currents-at arrival: only with --mode realtime and without --delay "
                       "(the measured arrival is the latency)")


def plant_runner(scene, model, integrator: str | None, h: float | None, latency: float):
    """The plant step object of a HIL run: a PlantRunner, wrapped in a FaultyPlant when the scene or
    ``--fault`` schedules faults (plant/faults.py; the same code as ``simulate`` with faults).  The
    loop latency (s) lives in the plant (currents reach the coils late), as in simulate()."""
    runner = runner_of(model, RunOptions(integrator=integrator, h=h, latency=latency))
    if not scene.faults:
        return runner
    return (ANCFFaultyPlant if model.rung == "ancf" else FaultyPlant)(runner, scene.faults)


def run_meta(scene, model, integrator: str | None = None, latency: float = 0.0, law: str | None = None) -> dict:
    """Metadata carried by the RunMeta message and the MCAP file.  ``law``: the controller's law
    (``--law``; named, never loaded here): ``law`` is its label (:func:`law_label`), ``law_spec``
    the name it was given (None for the scene's built-in or LTI law)."""
    plant = scene.plant
    stations = [a.name for a in plant.ambs] + ([plant.axial_amb.name] if plant.axial_amb else [])
    return {
        "scene": scene.name, "scene_path": str(Path(scene.path).resolve()),
        "scene_toml": Path(scene.path).read_text() if Path(scene.path).exists() else "",
        "rung": model.rung, "integrator": integrator or plant.simulation.integrator,
        "latency_s": latency,
        "controller_rate_hz": scene.controller.sample_rate,
        "axis_names": [f"{a}-{x}" for a, x in model.axes],
        "station_names": stations,
        "gaps_m": [a.gap for a in plant.ambs],
        "touchdown_clearances_m": [a.clearance for a in plant.ambs],
        "touchdown_clearances_given": [a.touchdown_clearance is not None for a in plant.ambs],
        "speed_rad_s": plant.simulation.speed or plant.speed.nominal,
        "faults": [f.describe() for f in scene.faults.faults],
        "controller": controller_meta(scene, model.rung),
        "law": law_label(law, scene), "law_spec": law or scene.controller.law,
    }


def controller_meta(scene, rung: str | None = None) -> dict:
    """RunMeta ``controller``: the scene's discrete law as the built-in controller computes it
    (docs/protocol.md §5.2), so that a controller in any language needs no scene parser.  ``rung``:
    the plant's rung (under [model] gravity the ancf rung's operating currents carry the weight).
    It describes the built-in law of the scene's gains, also when another law runs (RunMeta
    ``law`` names that one): what a port of the built-in law reads."""
    c = scene.controller
    i_op = operating_currents(scene.plant, rung)   # what `ambhil controller SCENE [--rung R]` starts at
    return describe(discretise(c), i_op, c)


PLACEMENTS = ("auto", "none")


def placement_cpus(placement: str) -> dict:
    """``--cpus`` per role for ``ambhil run``.  Lockstep and real-time loops are fastest with
    plant and controller on one core (shared/reference/tooling.md §1.5c: cross-core wake-ups dominate); the
    recorder then gets the remaining cores so it never delays the loop."""
    avail = sorted(os.sched_getaffinity(0))
    if placement == "none" or len(avail) < 2:
        return {}
    loop, rest = avail[-1], avail[:-1]
    return {"plant": [loop], "controller": [loop], "recorder": rest}
