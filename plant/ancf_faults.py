"""Scheduled faults on the ancf rung: the loss of AMB coils (``coil_loss``, ``amb_loss``, ``drop``)
around an :class:`ambhil.plant.ancf_step.ANCFRunner`, with the events of
:class:`ambhil.plant.faults.FaultyPlant` (same timing, same event dicts), so a rotor drop runs on the
nonlinear multibody rotor as on the linear rungs.

A lost axis gets zero AMB coefficients (``k_x``, ``k_i`` and the force constant): its force is zero,
linearised or nonlinear law alike (on the ancf rung the AMBs' share of the weight is part of the force
law, ``plant/ancf_model.from_model``, so the weight drops with the coils; the linear rungs need
``f_const = -load`` for the same).  The arrays of every segment between fault boundaries are built up
front; the DAE integrator swaps them at the segment's first step (:meth:`DAEIntegrator.set_arrays`).

A drop's ``coast_down`` (s) is the prescribed spin's ramp from the speed at the drop to 0 over that
time: the ancf spin profile is one ramp (``speed_profile``), so it is refused on a run that has a
run-up of its own.  Other fault kinds are refused (the message names the kind).
"""
from __future__ import annotations

import json
import math

import numpy as np

from . import dae_integrator as di
from .faults import LOSS, FaultSchedule, check_schedule, plan_parts


class ANCFFaultyPlant:
    """An ANCFRunner with a fault schedule of coil losses and drops; the runner's interface (what
    is not here is the runner's), ``events`` and ``on_event`` as :class:`FaultyPlant`'s."""
    FATAL = (di.NONFINITE, di.TOUCHDOWN)

    def __init__(self, runner, schedule: FaultSchedule, on_event=None):
        self.runner = runner
        self.schedule = schedule
        self.on_event = on_event
        model = runner.model
        path = model.spec.path
        for f in schedule.faults:
            if f.kind not in LOSS:
                raise ValueError(f"{path}: scheduled faults are not supported on the ancf rung yet "
                                 f"(fault #{f.index} {f.kind}; the ancf rung takes {', '.join(LOSS)})")
            if any(a >= runner.n_axes for a in f.axes):
                raise ValueError(f"fault #{f.index} {f.kind}: axis {f.axis!r} is not an axis of this plant")
        check_schedule(schedule)
        T = self.period = runner.period
        S = runner.S
        for f in schedule.of(("drop",)):
            cd = f.p("coast_down")
            if cd is None:
                continue
            if runner.run_up is not None:
                raise ValueError(f"{path}: fault #{f.index} drop coast_down: the ancf rung's spin profile is one "
                                 f"ramp and this run has a run-up; leave coast_down or the run-up out")
            ts = f.start_step(T) * T
            spin = S.spin.copy()
            spin[1:] = (runner.speed, 0.0, ts, ts + float(cd))
            S = S._replace(spin=spin)
        parts = [(g, g.start_step(T), g.end_step(T)) for f in schedule.faults
                 for g in plan_parts(f, runner.n_axes) if g.kind in LOSS]
        bounds = sorted({0} | {a for _, a, _ in parts} | {b for _, _, b in parts if not math.isinf(b)})
        self._segments = []
        cache = {}
        for b in bounds:
            lost = tuple(sorted({a for g, s, e in parts if s <= b < e for a in g.axes}))
            if lost not in cache:
                cache[lost] = without_axes(S, lost)
            self._segments.append((b, cache[lost]))
        self.marks: dict[int, list] = {}
        for f in schedule.faults:
            a, b = f.start_step(T), f.end_step(T)
            self.marks.setdefault(a, []).append((f, "start"))
            if not math.isinf(b):
                self.marks.setdefault(b, []).append((f, "end"))
        self.events: list[dict] = []
        self.reset()

    def __getattr__(self, name):
        if name == "runner":
            raise AttributeError(name)
        return getattr(self.runner, name)

    def reset(self) -> np.ndarray:
        r = self.runner
        r.S = self._segments[0][1]
        y = r.reset()
        self._seg = 0
        self.events = []
        self._emit(0)
        return y

    def advance(self, currents) -> np.ndarray:
        cur = np.ascontiguousarray(currents, dtype=np.float64)
        if cur.shape != (self.runner.n_axes,):
            raise ValueError(f"plant expects {self.runner.n_axes} currents, got shape {cur.shape}")
        return self.advance_shared(cur.copy()).copy()

    def advance_shared(self, currents: np.ndarray) -> np.ndarray:
        r = self.runner
        k = r.step_index
        segs = self._segments
        if self._seg + 1 < len(segs) and segs[self._seg + 1][0] <= k:
            while self._seg + 1 < len(segs) and segs[self._seg + 1][0] <= k:
                self._seg += 1
            r.S = segs[self._seg][1]
            r.dae.set_arrays(r.S)
        y = r.advance_shared(currents)
        self._emit(k + 1)
        return y

    def _emit(self, k):
        for f, phase in self.marks.get(k, ()):
            d = f.describe()
            ev = {"kind": f.kind, "axis": d["axis"], "params": d["params"], "phase": phase, "step": k,
                  "t_s": k * self.period, "index": f.index}
            self.events.append(ev)
            if self.on_event is not None:
                self.on_event(k, int(round(k * self.period * 1e9)),
                              json.dumps({x: ev[x] for x in ("kind", "axis", "params", "phase")}))


def without_axes(S, lost):
    """The ANCF arrays with the coils of AMB axes ``lost`` off: zero ``k_x``, ``k_i``, force constant."""
    if not lost:
        return S
    keep = ~np.isin(np.arange(S.amb_kx.shape[0]), lost)
    return S._replace(amb_kx=np.where(keep, S.amb_kx, 0.0), amb_ki=np.where(keep, S.amb_ki, 0.0),
                      amb_kc=np.where(keep, S.amb_kc, 0.0))
