"""Support-position sweep (paper Fig. 4): move one AMB along the shaft between its neighbours
and follow the critical speeds; compare with the rotor without that AMB."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..system import compile_system
from ..scene import Scene
from .modal import critical_speeds


@dataclass(frozen=True)
class SweepResult:
    amb: str
    positions: np.ndarray  # distance from the first AMB (m), as x in the paper's Fig. 4
    nodes: np.ndarray  # 0-based node of the moved AMB
    criticals: np.ndarray  # (n_pos, count) rad/s, nan where not found
    kinds: list[list[str]]
    baseline: np.ndarray  # criticals without the moved AMB
    baseline_kinds: list[str]

    def increase(self) -> np.ndarray:
        """Percent change of each critical against the baseline, (n_pos, count)."""
        return 100.0 * (self.criticals / self.baseline[None, :] - 1.0)


def sweep(scene: Scene, amb: str, count: int = 4, progress=None) -> SweepResult:
    plant = scene.plant
    moved = plant.amb(amb)
    others = [a for a in plant.ambs if a.name != amb]
    lo, hi = min(a.node for a in others), max(a.node for a in others)
    base_scene = replace(scene.with_plant(ambs=tuple(others)), analysis=replace(scene.analysis, sweep_amb=None))
    base = critical_speeds(compile_system(base_scene), count=count)
    bvals = np.full(count, np.nan)
    bvals[: len(base)] = [c.speed for c in base]
    nodes = np.array([k for k in range(lo + 1, hi) if all(k != a.node for a in others)])
    crit = np.full((len(nodes), count), np.nan)
    kinds = []
    for j, k in enumerate(nodes):
        d = moved.sensor_node - moved.node
        sn = int(np.clip(k + d, 0, plant.n_nodes - 1))
        ambs = tuple(replace(a, node=int(k), sensor_node=sn) if a.name == amb else a for a in plant.ambs)
        cs = critical_speeds(compile_system(scene.with_plant(ambs=ambs)), count=count)
        crit[j, : len(cs)] = [c.speed for c in cs]
        kinds.append([c.kind for c in cs])
        if progress:
            progress(j + 1, len(nodes))
    z = np.asarray(plant.node_z)
    return SweepResult(amb=amb, positions=z[nodes] - z[lo], nodes=nodes, criticals=crit, kinds=kinds,
                       baseline=bvals, baseline_kinds=[c.kind for c in base])
