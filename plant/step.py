"""The plant step: ``step(plan, state, currents) -> (state, sensor readings)`` and the
``PlantRunner`` the plant process runs (over zenoh, or in-process through
:func:`ambhil.loop.simulation.simulate`, which calls the very same numba kernels).

A :class:`PlantState` holds the flat integrator state vector ``s = [q, v, h1, h2, k]``, the
scalar workspace (speed of the current factorisation, first fault, Newton statistics) and, on a
speed run-up, the factorisation itself.  ``step`` is pure: it modifies neither its input state
nor the plan (nor the model), so the same inputs give the same outputs; pass ``out=`` to reuse a
preallocated state and avoid any allocation.  A run-up refactorises as the speed drifts: in the
state's own factorisation (``step``) or the runner's (``PlantRunner``), never in the plan, which
stays shared and as built (``plant/plan.py``).

Timing: the controller samples ``y_k`` at ``t_k``, returns ``i_k``; the plant holds ``i_k`` over
``[t_k, t_k + T_c)`` in ``ratio = T_c / h`` plant steps (``T_c`` the controller period) and
returns ``y_{k+1}``.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from . import integrator as ig
from . import plan as pl
from .model import Model
from .latency import advance_late, new_ring, split_latency
from .params import ParameterError
from .run_options import RunOptions

__all__ = ["PlantState", "PlantRunner", "step", "initial", "make_plan", "fault_report"]


@dataclass
class PlantState:
    s: np.ndarray  # flat integrator state (see plant.integrator.plant_step)
    ws: np.ndarray  # scalar workspace
    # the factorisation the workspace's W_OMEGA_F speaks of, on a run-up (the state's own, which
    # step() refactorises); None: the plan's, at its nominal speed
    LU: np.ndarray | None = None

    def copy(self) -> "PlantState":
        return PlantState(self.s.copy(), self.ws.copy(), None if self.LU is None else self.LU.copy())

    def time(self, plan: ig.PlantArrays) -> float:
        """Simulated time (s): the step count times the plan's step."""
        return float(self.s[4 * int(plan.ip[ig.I_N])]) * float(plan.fp[ig.F_H])


def input_period(model: Model) -> float:
    """The period over which the plant holds its inputs (``Model.period``: the controller's)."""
    T = model.period
    if T is None:
        raise ParameterError(f"{model.spec.path}: the plant's input period (the controller's sample period) is not set")
    return float(T)


def make_plan(model: Model, integrator: str | None = None, h: float | None = None, *, speed=None,
              run_up=None, nonlinear: bool | None = None, rho_inf: float | None = None,
              newton_iterations: int | None = None, newton_tol: float | None = None, ratio: int = 1,
              contact: bool = True) -> ig.PlantArrays:
    """Plan from a model with its [simulation] defaults for anything not given."""
    sim = model.spec.simulation
    get = lambda v, key, default: v if v is not None else getattr(sim, key, default)
    integrator = get(integrator, "integrator", "bdf1")
    h = get(h, "step", None) or input_period(model)
    if speed is None:
        speed = get(None, "speed", None)
        if speed is None:
            speed = model.spec.speed.value if model.spec.speed.value is not None else 0.0
    if run_up is None and sim is not None and getattr(sim, "run_up", None) is not None:
        run_up = tuple(sim.run_up) + tuple(sim.run_up_time)
    return pl.build_plan(model, integrator, h, speed=speed, run_up=run_up,
                         nonlinear=(get(nonlinear, "force_law", "linear") in (True, "nonlinear")),
                         rho_inf=get(rho_inf, "rho_inf", 0.8),
                         newton_iterations=get(newton_iterations, "newton_iterations", 10),
                         newton_tol=get(newton_tol, "newton_tol", 1e-10), ratio=ratio, contact=contact)


def initial(plan_or_model) -> PlantState:
    """Plant state at the operating point for a plan (or a model, with its scene defaults)."""
    plan = plan_for(plan_or_model)
    return PlantState(pl.initial_state(plan), pl.new_workspace(plan)[1])


#: each model's default plan, built once; keyed on the model's identity (a Model is immutable and
#: hashed by identity), held no longer than the model
_default_plans: "weakref.WeakKeyDictionary[Model, ig.PlantArrays]" = weakref.WeakKeyDictionary()


def plan_for(plan_or_model) -> ig.PlantArrays:
    """A plan as given, or the model's default plan (scene [simulation] settings; built once and
    kept in a cache beside the model, never modified: see :func:`step`)."""
    if isinstance(plan_or_model, ig.PlantArrays):
        return plan_or_model
    m = plan_or_model
    if m not in _default_plans:
        _default_plans[m] = make_plan(m)
    return _default_plans[m]


def step(plan: ig.PlantArrays | Model, state: PlantState, currents, out: PlantState | None = None,
         work: np.ndarray | None = None) -> tuple[PlantState, np.ndarray]:
    """One plant step of size h with the currents held: (new state, sensor displacements).
    ``plan`` may be a Model (its default plan from the scene's [simulation]).  Pure: neither
    ``state`` nor the plan is modified (a run-up refactorises in ``out``'s own factorisation);
    with ``out`` and ``work`` preallocated nothing is allocated except the returned readings."""
    plan = plan_for(plan)
    if out is None:
        out = PlantState(state.s.copy(), state.ws.copy())
    else:
        out.s[:] = state.s
        out.ws[:] = state.ws
    if pl.refactorises(plan):
        lu = plan.LU if state.LU is None else state.LU
        if out.LU is None:
            out.LU = lu.copy()
        else:
            out.LU[:] = lu
        plan = plan._replace(LU=out.LU)
    if work is None:
        work = pl.new_workspace(plan)[0]
    cur = np.ascontiguousarray(currents, dtype=np.float64)
    y = np.zeros(int(plan.ip[ig.I_NA]))
    ig.plant_advance(plan, out.s, cur, 1, work, out.ws, y)  # one substep: a controller update
    return out, y


def contact_view(plan: ig.PlantArrays, s: np.ndarray) -> np.ndarray:
    """The auxiliary bearings' part of a state vector as an (m, NC) view."""
    n, m = int(plan.ip[ig.I_N]), int(plan.ip[ig.I_AUX])
    return s[4 * n + 1: 4 * n + 1 + m * ig.NC].reshape(m, ig.NC)


def bound_kernel(dispatcher, *args):
    """The compiled code a numba ``dispatcher`` runs for these arguments' types, as a callable
    that skips the dispatcher's per-call type resolution: the same machine code, so the same
    bits, without re-typing the plan's 28 arrays on every call (about 2 us a call, more than the
    whole rigid-rung step; docs/performance.md).  Call it only with arguments of the same types
    (dtype, dimensions, layout, read-only flag) as ``args``."""
    return dispatcher.compile(tuple(dispatcher.typeof_pyval(a) for a in args))


def fault_report(plan: ig.PlantArrays, ws: np.ndarray, model: Model | None = None) -> str | None:
    """One-line description of the first fault recorded in a workspace (None if healthy)."""
    st = int(ws[ig.W_STATUS])
    if st == ig.OK:
        return None
    t = ws[ig.W_FAIL_T]
    if st == ig.NEWTON_FAIL:
        return (f"Newton did not converge at t={t:.6g} s after {int(ws[ig.W_FAIL_IT])} iterations "
                f"(residual {ws[ig.W_FAIL_RES]:.3g}; {int(ws[ig.W_NFAIL])} failing steps)")
    where = ""
    if st == ig.TOUCHDOWN and model is not None:
        amb, ax = model.axes[int(ws[ig.W_FAIL_AX])]
        where = f" at AMB {amb} axis {ax}"
        aux = next((a.auxiliary for a in model.spec.ambs if a.name == amb and getattr(a, "auxiliary", None)), None)
        if aux is not None:     # through its auxiliary bearing: the contact let the shaft penetrate that far
            where += (f", through its auxiliary bearing (a penetration of {(model.spec.amb(amb).gap - aux.clearance) * 1e6:.4g}"
                      f" um: its contact stiffness {aux.stiffness:.3g} cannot carry the load)")
    return f"{ig.STATUS_TEXT[st]}{where} at t={t:.6g} s"


class PlantRunner:
    """Plant process loop body (duck-typed interface used by the bridge).

    ``reset() -> y0``; ``advance(currents) -> y`` integrates one controller period holding the
    currents; ``safe_state()`` puts the plant in its defined safe state.  Attributes: ``n_axes``,
    ``period`` (controller period, s), ``h`` (plant step), ``ratio`` (plant steps per period),
    ``step_index`` (controller periods done), ``sim_time`` (s), ``fault`` (None or a one-line
    report of the first numerical fault / touchdown).

    ``options`` (:class:`ambhil.plant.run_options.RunOptions`, kept as ``self.options``): how to
    integrate (scheme, step, speed or run-up, force law, start state; ``None`` fields: the scene's
    ``[simulation]``).  Its ``latency`` (s): the currents passed to ``advance`` reach the coils
    that much later (``plant/latency.py``: whole periods plus a whole number of plant steps).
    ``period``: the input period (default: the model's); ``plan``: integrate with this plan
    (its scheme, step, speed and force law) instead of one built from the options."""

    def __init__(self, model: Model, options: RunOptions = RunOptions(), *, period: float | None = None,
                 plan: ig.PlantArrays | None = None):
        self.model = model
        self.options = o = options
        self.period = float(period or input_period(model))
        step_from_scene = o.h is None and plan is None and model.spec.simulation.step
        if plan is None:
            hh = o.h or model.spec.simulation.step or self.period
            plan = make_plan(model, o.integrator, hh, speed=o.speed, run_up=o.run_up, nonlinear=o.nonlinear,
                             rho_inf=o.rho_inf, newton_iterations=o.newton_iterations, newton_tol=o.newton_tol,
                             ratio=max(1, int(round(self.period / hh))))
        # the runner integrates with a factorisation of its own (a run-up refactorises it);
        # the plan given or built stays as it is
        self.plan = pl.own_factorisation(plan)
        self._lu0 = plan.LU.copy()  # the factorisation at the plan's nominal speed, for reset()
        self.h = float(self.plan.fp[ig.F_H])
        ratio = self.period / self.h
        self.ratio = int(round(ratio))
        if self.ratio < 1 or abs(ratio - self.ratio) > 1e-9 * ratio:
            raise ParameterError((f"{model.spec.path}: [simulation] key 'step': " if step_from_scene else "")
                                 + f"controller period {self.period:g} s is not an integer multiple of the plant step "
                             f"{self.h:g} s")
        self.n_axes = model.n_axes
        self.latency = float(o.latency)
        self.late = split_latency(self.latency, self.period, self.h) if self.latency else (0, 0)
        self.integrator = ig.SCHEMES[int(self.plan.ip[ig.I_SCHEME])]
        self.work, _ = pl.new_workspace(self.plan)
        self.y = np.zeros(self.n_axes)
        self.currents = np.zeros(self.n_axes)
        self.reset()
        # the kernels bound to this runner's argument types (reset() keeps the types)
        self._advance = bound_kernel(ig.plant_advance, self.plan, self.s, self.currents, self.ratio, self.work,
                                     self.ws, self.y)
        self._advance_late = (bound_kernel(advance_late, self.plan, self.s, self.currents, self.ring, 0, *self.late,
                                           self.ratio, self.work, self.ws, self.y) if self.ring is not None else None)

    def reset(self) -> np.ndarray:
        self.plan.LU[:] = self._lu0
        self.s = pl.initial_state(self.plan, self.options.q0, self.options.v0)
        _, self.ws = pl.new_workspace(self.plan)
        self.step_index = 0
        self.status = ig.OK
        self.currents = np.array(self.model.i_op, dtype=np.float64)
        self.ring = new_ring(*self.late, self.model.i_op) if self.latency else None
        ig.sense(self.plan, self.s, self.y)
        return self.y.copy()

    @property
    def sim_time(self) -> float:
        return self.step_index * self.period

    @property
    def fault(self) -> str | None:
        return fault_report(self.plan, self.ws, self.model)

    def advance(self, currents: np.ndarray) -> np.ndarray:
        cur = np.ascontiguousarray(currents, dtype=np.float64)
        if cur.shape != (self.n_axes,):
            raise ValueError(f"plant expects {self.n_axes} currents, got shape {cur.shape}")
        self.advance_shared(cur.copy())
        return self.y.copy()

    def advance_shared(self, currents: np.ndarray) -> np.ndarray:
        """Bridge hot path of :meth:`advance`: ``currents`` must be a C-contiguous float64
        array of ``n_axes`` values (not checked), and the returned array is the runner's own
        output buffer, overwritten by the next call.  Same arithmetic as :meth:`advance`."""
        self.currents = currents
        if self.ring is None:
            self.status = self._advance(self.plan, self.s, currents, self.ratio, self.work, self.ws, self.y)
        else:
            self.status = self._advance_late(self.plan, self.s, currents, self.ring, self.step_index, *self.late,
                                             self.ratio, self.work, self.ws, self.y)
        self.step_index += 1
        return self.y

    def advance_arriving(self, old: np.ndarray, new: np.ndarray, m: int) -> np.ndarray:
        """One period in which the coils hold ``old`` for the first ``m`` plant steps and ``new``
        for the remaining ``ratio - m`` (a command that reached the coils ``m h`` into the
        period: real time with the currents applied at their measured arrival).  Same buffers
        and arithmetic as :meth:`advance_shared` (``m = 0`` is exactly ``advance_shared(new)``);
        refused with a fixed ``latency`` (which already delays every command)."""
        if self.ring is not None:
            raise ValueError("advance_arriving: the plant already has a fixed latency")
        m = min(max(int(m), 0), self.ratio)
        st = ig.OK
        if m > 0:
            st = self._advance(self.plan, self.s, old, m, self.work, self.ws, self.y)
        if m < self.ratio and st not in self.FATAL:
            st2 = self._advance(self.plan, self.s, new, self.ratio - m, self.work, self.ws, self.y)
            st = st2 if st2 != ig.OK else st
        self.currents = new
        self.status = st
        self.step_index += 1
        return self.y

    #: statuses after which integrating on is meaningless (the bridge ends the run)
    FATAL = (ig.NONFINITE, ig.TOUCHDOWN)

    def safe_state(self) -> np.ndarray:
        """Safe state on a fault: the control currents are set to zero (coils at bias current
        only, the amplifiers' power-up state), and further ``advance`` calls integrate with them
        until the bridge resumes; returns the currents now applied."""
        self.currents = np.zeros(self.n_axes)
        return self.currents.copy()

    # convenient views
    @property
    def contact(self) -> np.ndarray:
        """(m, NC) view of the auxiliary bearings' contact state (``plant.integrator.C_*``; m = 0
        without auxiliary bearings)."""
        return contact_view(self.plan, self.s)

    @property
    def contact_names(self) -> tuple[str, ...]:
        return pl.auxiliary_stations(self.model)[2]

    @property
    def q(self) -> np.ndarray:
        return self.s[: self.model.n]

    @property
    def v(self) -> np.ndarray:
        n = self.model.n
        return self.s[n: 2 * n]
