"""The result of a simulated run (:class:`SimResult`, what ``ambhil.loop.simulation.simulate``
returns) and its time-series file.

Time-series file (``simulation.npz``, numpy ``savez``; all SI):

===============  ==================  ===================================================
array            shape               meaning
===============  ==================  ===================================================
``t``            (N,)                time, s (record every ``record_every`` controller periods)
``y``            (N, n_axes)         sensor displacements, m (model.axes order)
``i``            (N, n_axes)         control currents applied from that instant, A
``orbit``        (N, n_nodes, 2)     x, y displacement of each output node, m
``nodes``        (n_nodes,)          1-based node numbers of ``orbit``
``speed``        (N,)                spin speed, rad/s
``axes``         (n_axes,)           "AMB:axis" labels
``meta``         ()                  JSON string: scene, rung, integrator, h, period, ...
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: the contact time series of a run with auxiliary bearings (SimResult.contact), and the plant
#: state's field each one is read from (plant.integrator.C_*)
CONTACT_SERIES = ("x", "y", "fn", "ft", "d", "race_speed", "friction_power", "e_friction", "e_damping")


@dataclass
class SimResult:
    t: np.ndarray
    y: np.ndarray
    i: np.ndarray
    orbit: np.ndarray
    nodes: tuple[int, ...]  # 1-based
    speed: np.ndarray
    axes: tuple[str, ...]
    meta: dict
    fault: str | None
    steps: int  # controller periods done
    wall: float  # s, loop only
    instability: str | None = None  # report when the run diverged
    numerics: str | None = None  # numerical damping hides / overstates a mode (stability_check)
    events: list | None = None  # scheduled faults' start/end (plant/faults.py), None without faults
    # auxiliary-bearing contact (None without auxiliary bearings): arrays of CONTACT_SERIES (N, m),
    # "names", "clearance" (m,), "events" (plant/contact_log.py), "summary" per bearing
    contact: dict | None = None

    @property
    def us_per_period(self) -> float:
        return 1e6 * self.wall / max(self.steps, 1)

    @property
    def real_time_factor(self) -> float:
        return self.steps * self.meta["period"] / max(self.wall, 1e-12)

    def save(self, out_dir) -> Path:
        d = Path(out_dir)
        d.mkdir(parents=True, exist_ok=True)
        f = d / "simulation.npz"
        extra, meta = {}, dict(self.meta)
        if self.contact is not None:
            extra = {f"contact_{k}": self.contact[k] for k in CONTACT_SERIES}
            meta["contact"] = {k: self.contact[k] for k in ("names", "events", "summary")}
            for k in ("clearance", "shaft_radius", "race_radius"):
                meta["contact"][k] = [float(c) for c in self.contact[k]]
        np.savez(f, t=self.t, y=self.y, i=self.i, orbit=self.orbit, nodes=np.array(self.nodes),
                 speed=self.speed, axes=np.array(self.axes), meta=np.array(json.dumps(meta)), **extra)
        return f


def load(path) -> SimResult:
    z = np.load(Path(path) / "simulation.npz" if Path(path).is_dir() else path, allow_pickle=False)
    meta = json.loads(str(z["meta"]))
    contact = None
    if "contact" in meta:
        c = meta.pop("contact")
        contact = {k: z[f"contact_{k}"] for k in CONTACT_SERIES}
        contact.update(names=tuple(c["names"]), events=list(c["events"] or []), summary=c["summary"],
                       **{k: np.array(c[k]) for k in ("clearance", "shaft_radius", "race_radius")})
    return SimResult(t=z["t"], y=z["y"], i=z["i"], orbit=z["orbit"], nodes=tuple(int(k) for k in z["nodes"]),
                     speed=z["speed"], axes=tuple(str(a) for a in z["axes"]), meta=meta,
                     fault=meta.get("fault"), steps=meta.get("steps", 0), wall=meta.get("wall", 0.0), contact=contact)
