"""Scheduled faults on the plant side: a fault schedule (data) and :class:`FaultyPlant`, which
applies it around a :class:`ambhil.plant.step.PlantRunner` with the very same kernels.

The schedule is parsed from a scene's ``[[fault]]`` tables or ``--fault`` flags by
``loop/scene.py``; it is used by the in-process loop (``loop/simulation.py``) and by the plant
process (``ambhil plant`` / ``ambhil run``) alike, so a lockstep run with faults reproduces
``simulate`` with the same faults bit for bit.  Without faults nothing here runs.

Timing: a fault acts from the first sample instant ``t_k = k T`` at or after its ``at`` (``T``
the controller period) until the first one at or after its end.  Over the period ``[t_k,
t_k+1)`` a plant fault active at ``t_k`` holds; a sensor fault changes the reading ``y_k``.

Where each kind acts (docs/faults.md):

=================  ============================================================================
sensor_stuck       the reading of the axis freezes at its value at the fault start
sensor_zero        the reading is 0
sensor_noise       + ``sigma`` x N(0, 1) per sample (seeded generator, ``seed``)
sensor_bias        + ``value`` (m)
sensor_drift       + ``rate`` x (t - start) (m/s)
amp_limit          the coil control current is clipped to +- ``limit`` (A)
amp_slew           the coil current moves at most ``rate`` (A/s) per plant step towards the command
coil_loss          the axis' coils are off: no control force and no negative stiffness (bias gone)
amb_loss           coil_loss of every axis of a station
drop               coil_loss of every AMB axis (rotor drop onto the auxiliary bearings); with
                   ``coast_down`` (s) also a speed_trip to 0 over that time
unbalance_step     an unbalance ``magnitude`` (kg m) at ``phase`` (rad) is added at a node (blade loss)
speed_trip         the drive trips: the spin speed falls linearly to ``to`` (rad/s) over ``over`` (s)
message_loss       a message in ``direction`` (sensors | currents | both) is lost with ``probability``:
                   the receiver keeps the last one it got (zero-order hold)
message_delay      messages in ``direction`` arrive ``periods`` controller periods late
controller_restart the controller's state is reset (in-process; a HIL controller on the event)
=================  ============================================================================
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp

from . import integrator as ig
from . import plan as pl
from .model import _ro
from .params import ParameterError

SENSOR = ("sensor_stuck", "sensor_zero", "sensor_noise", "sensor_bias", "sensor_drift")
AMPLIFIER = ("amp_limit", "amp_slew")
LOSS = ("coil_loss", "amb_loss", "drop")
PLANT = ("unbalance_step", "speed_trip")
TRANSPORT = ("message_loss", "message_delay")
CONTROLLER = ("controller_restart",)
KINDS = SENSOR + AMPLIFIER + LOSS + PLANT + TRANSPORT + CONTROLLER
#: kinds that change the plant's matrices or forcing (a plan per combination, built up front)
PLAN_KINDS = LOSS + PLANT
#: kinds that last for ever once started (no duration / until)
PERMANENT = PLANT + CONTROLLER


@dataclass(frozen=True)
class Fault:
    """One scheduled fault.  ``start``/``end`` in s (``end = inf``: to the end of the run);
    ``axes``: 0-based axis indices (model.axes order) it acts on; ``axis``: as given (label);
    ``params``: sorted (key, value) pairs, SI units; ``index``: 1-based place in the schedule."""
    kind: str
    start: float
    end: float = math.inf
    axes: tuple[int, ...] = ()
    axis: str = ""
    params: tuple[tuple[str, object], ...] = ()
    index: int = 1
    source: str = ""

    def p(self, key: str, default=None):
        for k, v in self.params:
            if k == key:
                return v
        return default

    def start_step(self, T: float) -> int:
        return int(math.ceil(self.start / T - 1e-9))

    def end_step(self, T: float) -> float:
        return math.inf if math.isinf(self.end) else int(math.ceil(self.end / T - 1e-9))

    def describe(self) -> dict:
        return {"kind": self.kind, "axis": self.axis or None, "params": dict(self.params),
                "at_s": self.start, "end_s": None if math.isinf(self.end) else self.end}


@dataclass(frozen=True)
class FaultSchedule:
    faults: tuple[Fault, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.faults)

    def __len__(self) -> int:
        return len(self.faults)

    def __add__(self, other: "FaultSchedule") -> "FaultSchedule":
        fs = tuple(self.faults) + tuple(other.faults)
        return FaultSchedule(tuple(replace(f, index=i + 1) for i, f in enumerate(fs)))

    def of(self, kinds) -> tuple[Fault, ...]:
        return tuple(f for f in self.faults if f.kind in kinds)

    def controller_restart_steps(self, T: float) -> set[int]:
        return {f.start_step(T) for f in self.of(CONTROLLER)}


NO_FAULTS = FaultSchedule()


def _name(f: Fault) -> str:
    """How a message names a plan part: a drop's coast-down is a speed trip the user wrote as a drop."""
    return "drop coast_down" if f.kind == "speed_trip" and f.p("coast_down") is not None else f.kind


def plan_parts(f: Fault, n_axes: int) -> tuple[Fault, ...]:
    """The plan-changing faults ``f`` stands for.  A ``drop`` is the existing machinery: the loss of
    every axis (all stations, axial too) over its window and, with ``coast_down``, a speed trip to 0
    over that time from its start.  The trip is permanent like every speed trip (the drive is off: the
    speed stays where the coast-down left it when the AMBs come back)."""
    if f.kind != "drop":
        return (f,)
    parts = [replace(f, axes=tuple(range(n_axes)))]
    cd = f.p("coast_down")
    if cd is not None:
        parts.append(replace(f, kind="speed_trip", end=math.inf, axes=(), axis="",
                             params=(("coast_down", cd), ("over", float(cd)), ("to", 0.0))))
    return tuple(parts)


def check_schedule(schedule: FaultSchedule) -> None:
    """Refuse (one line, ParameterError) a schedule that trips the drive twice: more than one
    ``speed_trip``, or a ``drop`` with ``coast_down`` (itself a trip to 0) beside another trip."""
    trips = [f for f in schedule.faults if f.kind == "speed_trip" or (f.kind == "drop" and f.p("coast_down") is not None)]
    if len(trips) < 2:
        return
    if all(f.kind == "speed_trip" for f in trips):
        raise ParameterError("more than one speed_trip in the fault schedule (the first one already trips)")
    a, b = trips[:2]
    raise ParameterError(f"fault #{a.index} {_name(plan_parts(a, 0)[-1])} and fault #{b.index} "
                         f"{_name(plan_parts(b, 0)[-1])} both trip the drive (a drop's coast_down is a speed_trip "
                         f"to 0): give one")


# --------------------------------------------------------------------------- plant variants
def _plan_settings(runner) -> dict:
    p = runner.plan
    scheme = ig.SCHEMES[int(p.ip[ig.I_SCHEME])]
    return dict(scheme=scheme, h=float(p.fp[ig.F_H]), nonlinear=bool(p.ip[ig.I_NL]),
                rho_inf=(1.0 / float(p.fp[ig.F_AF]) - 1.0) if scheme == "generalized-alpha" else 0.8,
                newton_iterations=int(p.ip[ig.I_MAXIT]), newton_tol=float(p.fp[ig.F_TOL]), ratio=runner.ratio)


def model_without_axes(model, lost):
    """The model with the coils of the axes ``lost`` switched off: no control force (k_i = 0) and
    no negative stiffness (k_x = 0; its -k_x term leaves K_eff), force constant 0.  The weight
    share those axes carried at the operating point (``load``) is no longer carried: it becomes a
    constant force ``f_const = -load`` on the rotor (the deviation coordinates stay those of the
    sagged equilibrium), and ``load`` on them is 0, so the nonlinear force law's remainder
    ``F - load - ...`` (0 - 0 on a lost axis) does not count it a second time."""
    lost = sorted(set(lost))
    if not lost:
        return model
    kx_l = np.zeros(model.n_axes)
    kx_l[lost] = model.kx[lost]
    if sp.issparse(model.K_eff):
        K_eff = (model.K_eff + model.Ba @ sp.diags(kx_l) @ model.Ca).tocsc()
    else:
        K_eff = np.asarray(model.K_eff) + np.asarray(model.Ba) @ np.diag(kx_l) @ np.asarray(model.Ca)
    def z(a):  # read-only like the model's own arrays: the plan keeps the kernels' numba types
        out = np.where(np.isin(np.arange(model.n_axes), lost), 0.0, a)
        out.setflags(write=False)
        return out
    load = model.loads
    f_const = np.array(model.constant_forces, dtype=np.float64)
    f_const[lost] = 0.0 - load[lost]          # (0.0 - : no -0.0 where an axis carried nothing)
    f_const.setflags(write=False)
    return replace(model, K_eff=_ro(K_eff), ki=z(model.ki), kx=z(model.kx), force_constant=z(model.force_constant),
                   load=z(load), f_const=f_const)


def model_with_unbalance(model, added):
    """The model with unbalances ``added`` = [(0-based node, kg m, rad), ...] besides its own."""
    if not added:
        return model
    dpn = model.rotor.dpn
    return replace(model, unb_dof=_ro(np.concatenate([model.unb_dof, [n * dpn for n, _, _ in added]]).astype(int)),
                   unb_me=_ro(np.concatenate([model.unb_me, [m for _, m, _ in added]])),
                   unb_phase=_ro(np.concatenate([model.unb_phase, [ph for _, _, ph in added]])))


def _variant_plan(runner, active: tuple[Fault, ...], T: float):
    """The plan of the plant with the plan-changing faults ``active``."""
    base = runner.plan
    model = runner.model
    lost = sorted({a for f in active if f.kind in LOSS for a in f.axes})
    model = model_without_axes(model, lost)
    model = model_with_unbalance(model, [(f.p("node") - 1, f.p("magnitude"), f.p("phase", 0.0))
                                         for f in active if f.kind == "unbalance_step"])
    st = _plan_settings(runner)
    fp = base.fp
    trips = [f for f in active if f.kind == "speed_trip"]
    speed, run_up, th0 = float(fp[ig.F_W0]), None, None
    if base.ip[ig.I_RUNUP]:
        run_up = tuple(float(x) for x in fp[ig.F_W0:ig.F_T1 + 1])
        speed = None
    if trips:
        f = trips[0]
        name = _name(f)
        ts = f.start_step(T) * T
        th_s, W_s, _ = ig.speed_at(fp, ts)
        W1, over = float(f.p("to", 0.0)), float(f.p("over", 0.0))
        if over > 0 and W1 != W_s:
            if st["scheme"] == "zoh":
                raise ParameterError(f"fault #{f.index} {name}: a coast-down (over > 0) needs a time-stepping "
                                     f"integrator, not zoh (exact for constant speed only); "
                                     + ("leave coast_down out" if name != "speed_trip" else "use over = 0")
                                     + " or another integrator")
            speed, run_up = None, (W_s, W1, ts, ts + over)
            th0 = th_s - W_s * ts
        else:
            speed, run_up = W1, None
            th0 = th_s - W1 * ts
    p = pl.build_plan(model, st["scheme"], st["h"], speed=speed if speed is not None else 0.0, run_up=run_up,
                      nonlinear=st["nonlinear"], rho_inf=st["rho_inf"], newton_iterations=st["newton_iterations"],
                      newton_tol=st["newton_tol"], ratio=st["ratio"])
    if th0 is not None:
        p.fp[ig.F_TH0] = th0
    return p


# --------------------------------------------------------------------------- the faulty plant
class FaultyPlant:
    """A :class:`ambhil.plant.step.PlantRunner` with a fault schedule applied (same duck-typed interface:
    ``reset``, ``advance``, ``advance_shared``, ``safe_state``, ``status``, ``FATAL``, ``fault``,
    ``n_axes``, ``period``, ``step_index``, ``sim_time``).

    ``on_event(step, sim_time_ns, text)``: called at every fault start and end (text: JSON
    ``{kind, axis, params, phase}``), also kept in ``events``.  A start or end at sample k is
    reported before ``y_k`` is returned (so a HIL plant publishes it before sample k)."""

    FATAL = (ig.NONFINITE, ig.TOUCHDOWN)

    def __init__(self, runner, schedule: FaultSchedule, on_event=None):
        self.runner = runner
        self.model = runner.model
        self.schedule = schedule
        self.on_event = on_event
        self.n_axes, self.period, self.h, self.ratio = runner.n_axes, runner.period, runner.h, runner.ratio
        T = self.period
        for f in schedule.faults:
            if any(a >= self.n_axes for a in f.axes):
                raise ParameterError(f"fault #{f.index} {f.kind}: axis {f.axis!r} is not an axis of this plant")
        check_schedule(schedule)
        if schedule.of(("amp_slew",)) and runner.ring is not None:
            raise ParameterError("amp_slew with a loop latency (--delay) is not supported: the slew acts on the "
                                 "current at the coil, plant step by plant step")
        self.win = [(f, f.start_step(T), f.end_step(T)) for f in schedule.faults]
        # plan per segment between the boundaries of the plan-changing faults, built up front
        pf = [(g, g.start_step(T), g.end_step(T)) for f in schedule.faults if f.kind in PLAN_KINDS
              for g in plan_parts(f, self.n_axes)]
        bounds = sorted({0} | {a for _, a, _ in pf} | {b for _, _, b in pf if not math.isinf(b)})
        self._segments = []      # (first step, plan)
        cache = {}
        for b in bounds:
            act = tuple(f for f, s, e in pf if s <= b < e)
            key = tuple((f.index, f.kind) for f in act)
            if key not in cache:
                cache[key] = runner.plan if not act else _variant_plan(runner, act, T)
            self._segments.append((b, cache[key]))
        self._lu0 = {id(p): p.LU.copy() for _, p in self._segments}
        self.sensor = [(f, a, b) for f, a, b in self.win if f.kind in SENSOR]
        self.amp = [(f, a, b) for f, a, b in self.win if f.kind in AMPLIFIER]
        self.sloss = [(f, a, b) for f, a, b in self.win if f.kind == "message_loss" and f.p("direction") in ("sensors", "both")]
        self.closs = [(f, a, b) for f, a, b in self.win if f.kind == "message_loss" and f.p("direction") in ("currents", "both")]
        self.sdelay = [(f, a, b) for f, a, b in self.win if f.kind == "message_delay" and f.p("direction") in ("sensors", "both")]
        self.cdelay = [(f, a, b) for f, a, b in self.win if f.kind == "message_delay" and f.p("direction") in ("currents", "both")]
        self.dmax = max([int(f.p("periods")) for f, _, _ in self.sdelay + self.cdelay] + [0])
        self.marks: dict[int, list[tuple[Fault, str]]] = {}
        for f, a, b in self.win:
            self.marks.setdefault(a, []).append((f, "start"))
            if not math.isinf(b):
                self.marks.setdefault(b, []).append((f, "end"))
        self.events: list[dict] = []
        self.y = np.zeros(self.n_axes)
        self.reset()

    def speed_at(self, t: float) -> float:
        """The spin speed (rad/s) at time t: that of the plan in force at the controller step of t
        (a speed trip or a drop's coast-down swaps the plan)."""
        k = int(math.floor(t / self.period + 1e-9))
        p = self._segments[0][1]
        for b, plan in self._segments:
            if b <= k:
                p = plan
        return float(ig.speed_at(p.fp, t)[1])

    # -- the interface
    @property
    def step_index(self) -> int:
        return self.runner.step_index

    @property
    def sim_time(self) -> float:
        return self.runner.sim_time

    @property
    def status(self) -> int:
        return self.runner.status

    @property
    def fault(self):
        return self.runner.fault

    @property
    def plan(self):
        return self.runner.plan

    @property
    def s(self):
        return self.runner.s

    @property
    def ws(self):
        return self.runner.ws

    @property
    def currents(self):
        return self.runner.currents

    def safe_state(self):
        return self.runner.safe_state()

    def reset(self) -> np.ndarray:
        r = self.runner
        r.plan = self._segments[0][1]
        y = r.reset()
        # after the runner's reset, which writes its own (healthy) factorisation into r.plan: a
        # plan-changing fault active from step 0 must keep the factorisation of its own plan
        for _, p in self._segments:
            p.LU[:] = self._lu0[id(p)]
        self._seg = 0
        self.i_op = np.array(self.model.i_op, dtype=np.float64)
        self.coil = self.i_op.copy()                 # current at the coils (amp_slew state)
        self.u_used = self.i_op.copy()               # last command the plant applied (message_loss)
        self.rx = [self.i_op.copy() for _ in range(self.dmax + 1)]     # commands received, newest last
        self.cur = np.zeros(self.n_axes)
        self.rng_noise = {f.index: np.random.default_rng(int(f.p("seed", f.index))) for f, _, _ in self.sensor
                          if f.kind == "sensor_noise"}
        self.rng_loss = {f.index: np.random.default_rng(int(f.p("seed", f.index))) for f, _, _ in self.sloss + self.closs}
        self.stuck: dict[tuple[int, int], float] = {}
        self.events = []
        self._emit(0)
        self.true_y = [y.copy() for _ in range(self.dmax + 1)]  # sensor readings, newest last
        self._sent = y.copy()                                    # last sample sent (message_loss)
        self.y[:] = self._sensed(0, y)
        return self.y.copy()

    def advance(self, currents) -> np.ndarray:
        cur = np.ascontiguousarray(currents, dtype=np.float64)
        if cur.shape != (self.n_axes,):
            raise ValueError(f"plant expects {self.n_axes} currents, got shape {cur.shape}")
        return self.advance_shared(cur.copy()).copy()

    def advance_shared(self, currents: np.ndarray) -> np.ndarray:
        r = self.runner
        k = r.step_index
        segs = self._segments
        if self._seg + 1 < len(segs) and segs[self._seg + 1][0] <= k:
            while self._seg + 1 < len(segs) and segs[self._seg + 1][0] <= k:
                self._seg += 1
            r.plan = segs[self._seg][1]
            r.ws[ig.W_OMEGA_F] = r.plan.fp[ig.F_WNOM]
        u = self._received(k, currents)
        u = self._amplifier(k, u)
        if self._slewing(k) and r.ratio > 1:
            self._advance_slewed(k, u)
        else:
            self.cur[:] = u
            r.advance_shared(self.cur)
            self.coil[:] = u
        y = self._sensed(k + 1, r.y)
        self._emit(k + 1)
        self.y[:] = y
        return self.y

    # -- currents: transport, then amplifier
    def _received(self, k, u):
        if self.cdelay:
            self.rx.append(np.array(u, dtype=np.float64))
            del self.rx[0]
            d = max([int(f.p("periods")) for f, a, b in self.cdelay if a <= k < b] + [0])
            u = self.rx[-1 - d]
        for f, a, b in self.closs:
            if a <= k < b and self.rng_loss[f.index].random() < f.p("probability", 1.0):
                u = self.u_used
                break
        self.u_used = np.array(u, dtype=np.float64)
        return self.u_used

    def _amplifier(self, k, u):
        out = None
        for f, a, b in self.amp:
            if f.kind == "amp_limit" and a <= k < b:
                out = u.copy() if out is None else out
                lim = float(f.p("limit"))
                for ax in f.axes:
                    out[ax] = min(max(out[ax], -lim), lim)
        if self._slewing(k) and self.ratio == 1:
            out = u.copy() if out is None else out
            self._slew(k, out, self.period)
        return u if out is None else out

    def _slewing(self, k):
        return any(f.kind == "amp_slew" and a <= k < b for f, a, b in self.amp)

    def _slew(self, k, target, dt):
        """target <- the coil current after dt moving towards target at the active slew rates."""
        for f, a, b in self.amp:
            if f.kind == "amp_slew" and a <= k < b:
                d = float(f.p("rate")) * dt
                for ax in f.axes:
                    target[ax] = self.coil[ax] + min(max(target[ax] - self.coil[ax], -d), d)
        self.coil[:] = target

    def _advance_slewed(self, k, u):
        """One period, the coil current ramping towards the command plant step by plant step."""
        r = self.runner
        st = ig.OK
        for j in range(r.ratio):
            self.cur[:] = u
            self._slew(k, self.cur, r.h)
            s = ig.plant_advance(r.plan, r.s, self.cur, 1, r.work, r.ws, r.y)
            if s != ig.OK:
                st = s
                if s in self.FATAL:
                    break
        r.currents = self.cur
        r.status = st
        r.step_index += 1

    # -- sensors: faults at the sensor, then transport
    def _sensed(self, k, y_true):
        y = np.array(y_true, dtype=np.float64)
        t = k * self.period
        for f, a, b in self.sensor:
            if not a <= k < b:
                continue
            for ax in f.axes:
                if f.kind == "sensor_stuck":
                    y[ax] = self.stuck.setdefault((f.index, ax), y[ax])
                elif f.kind == "sensor_zero":
                    y[ax] = 0.0
                elif f.kind == "sensor_bias":
                    y[ax] += float(f.p("value"))
                elif f.kind == "sensor_drift":
                    y[ax] += float(f.p("rate")) * (t - a * self.period)
            if f.kind == "sensor_noise":
                y[list(f.axes)] += float(f.p("sigma")) * self.rng_noise[f.index].standard_normal(len(f.axes))
        if not (self.sdelay or self.sloss):
            return y
        if self.sdelay:
            self.true_y.append(y)
            del self.true_y[0]
            d = max([int(f.p("periods")) for f, a, b in self.sdelay if a <= k < b] + [0])
            y = self.true_y[-1 - d].copy()
        for f, a, b in self.sloss:
            if a <= k < b and self.rng_loss[f.index].random() < f.p("probability", 1.0):
                y = self._sent.copy()
                break
        self._sent = y.copy()
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
