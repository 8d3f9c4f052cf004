"""The ANCF rung behind the plant step interface: :class:`ANCFRunner` has the duck type of
:class:`ambhil.plant.step.PlantRunner` (``reset``, ``advance``, ``advance_shared``,
``advance_arriving``, ``safe_state``, ``fault``, ``n_axes``, ``period``, ``h``, ``ratio``,
``step_index``, ``sim_time``, ``status``, ``currents``), so ``ambhil simulate`` and the plant
process of ``ambhil run`` drive it like any rung.  :func:`plant_runner` picks the runner of a
model's rung.
"""
from __future__ import annotations

import numpy as np

from . import ancf_contact as ac
from . import ancf_model as am
from . import dae_integrator as di
from .params import ParameterError
from .run_options import RunOptions
from .step import PlantRunner, input_period

STATUS_TEXT = {di.OK: "ok", di.NEWTON_FAIL: "Newton did not converge", di.NONFINITE: "state is not finite (blow-up)",
               di.TOUCHDOWN: "rotor reached the stator (|x| >= gap)"}


def plant_runner(model, options: RunOptions = RunOptions(), *, period=None, plan=None):
    """PlantRunner for the linear rungs, ANCFRunner for rung 'ancf' (same arguments)."""
    if getattr(model, "rung", None) == "ancf":
        return ANCFRunner(model, options, period=period, plan=plan)
    return PlantRunner(model, options, period=period, plan=plan)


def default_scheme(scene_integrator: str) -> str:
    """The DAE scheme of an ANCFRunner given no integrator: the scene's ``[simulation] integrator``
    when the DAE integrates with it, else bdf1 (the paper's; the scene's scheme is then one of the
    linear rungs', e.g. trapezoidal or zoh)."""
    return scene_integrator if scene_integrator in di.SCHEMES else "bdf1"


class ANCFRunner:
    """The ancf rung's plant runner: ``ANCFRunner(model, options, *, period=None, plan=None)`` as
    :class:`ambhil.plant.step.PlantRunner` (``options`` kept as ``self.options``; ``plan`` is
    accepted for the shared signature and unused: the rung has no linear plan).  The resolved
    choices are attributes: ``integrator``, ``h``, ``speed``, ``run_up``, ``nonlinear``,
    ``rho_inf``, ``newton_iterations``, ``newton_tol``."""
    FATAL = (di.NONFINITE, di.TOUCHDOWN)

    def __init__(self, model, options: RunOptions = RunOptions(), *, period=None, plan=None):
        o = options
        if o.latency:
            raise ParameterError(f"{model.spec.path}: the ancf rung does not model a loop latency yet")
        sim = model.spec.simulation
        self.model = model
        self.options = options
        self.period = float(period or input_period(model))
        self.integrator = o.integrator or default_scheme(sim.integrator)
        if self.integrator not in di.SCHEMES:
            raise ParameterError(f"{model.spec.path}: [simulation] integrator {self.integrator!r}: the ancf rung "
                                 f"integrates with {' or '.join(di.SCHEMES)}")
        hh = float(o.h or sim.step or self.period)
        ratio = self.period / hh
        self.ratio = int(round(ratio))
        if self.ratio < 1 or abs(ratio - self.ratio) > 1e-9 * ratio:
            raise ParameterError(f"{model.spec.path}: controller period {self.period:g} s is not an integer multiple "
                                 f"of the plant step {hh:g} s")
        self.h = hh
        speed, run_up = o.speed, o.run_up
        if speed is None:
            speed = sim.speed if sim.speed is not None else (model.spec.speed.value or 0.0)
        if run_up is None and sim.run_up is not None:
            run_up = tuple(sim.run_up) + tuple(sim.run_up_time)
        self.speed, self.run_up = float(speed), run_up
        self.nonlinear = (o.nonlinear if o.nonlinear is not None else sim.force_law) in (True, "nonlinear")
        self.rho_inf = float(o.rho_inf if o.rho_inf is not None else sim.rho_inf)
        self.newton_iterations = int(o.newton_iterations or sim.newton_iterations)
        self.newton_tol = float(o.newton_tol or sim.newton_tol)
        self.S, self._q0 = am.from_model(model, self.speed, run_up, self.nonlinear)
        self.C, self._contact_names = ac.stations(model, self.S)  # auxiliary bearings (m may be 0)
        if self._contact_names:  # a step too coarse for an impact is refused as on the linear rungs
            from . import contact_step
            try:
                contact_step.check(model, self.h)
            except ValueError as e:
                raise ParameterError(f"{model.spec.path}: {e}") from None
        n = self._q0.shape[0]
        for name, v in (("q0", o.q0), ("v0", o.v0)):
            if v is not None and np.shape(v) != (n,):
                raise ParameterError(f"{model.spec.path}: the ancf rung's {name} has 8 coordinates per node "
                                     f"({n}), got shape {np.shape(v)}")
        if o.q0 is not None:
            self._q0 = np.asarray(o.q0, float)
        self._v0 = np.zeros_like(self._q0) if o.v0 is None else np.asarray(o.v0, float)
        self.n_axes = model.n_axes
        self.sens = 8 * self.S.sens_node + self.S.sens_axis
        self.y = np.zeros(self.n_axes)
        self.reset()

    def reset(self) -> np.ndarray:
        self.dae = di.DAEIntegrator(self.S, self._q0, self._v0, self.h, self.integrator, rho_inf=self.rho_inf,
                                    tol=self.newton_tol, maxit=self.newton_iterations,
                                    cur0=np.array(self.model.i_op, dtype=np.float64),
                                    contact=self.C if self.C.aux_p.shape[0] else None)
        self.step_index = 0
        self.status = di.OK
        self.currents = np.array(self.model.i_op, dtype=np.float64)
        self.y[:] = self.dae.q[self.sens]
        return self.y.copy()

    @property
    def sim_time(self) -> float:
        return self.step_index * self.period

    @property
    def fault(self) -> str | None:
        f = self.dae.fail
        if f is None:
            return None
        code, t, it, res = f
        if code == di.NEWTON_FAIL:
            return (f"Newton did not converge at t={t:.6g} s after {it} iterations (last increment {res:.3g}; "
                    f"{self.dae.nfail} failing steps)")
        return f"{STATUS_TEXT[code]} at t={t:.6g} s"

    def _run(self, cur, k):
        st = di.OK
        for _ in range(k):
            r = self.dae.step(cur)
            if r != di.OK:
                st = r
                if r in self.FATAL:
                    break
        return st

    def advance(self, currents) -> np.ndarray:
        cur = np.ascontiguousarray(currents, dtype=np.float64)
        if cur.shape != (self.n_axes,):
            raise ValueError(f"plant expects {self.n_axes} currents, got shape {cur.shape}")
        return self.advance_shared(cur.copy()).copy()

    def advance_shared(self, currents: np.ndarray) -> np.ndarray:
        self.currents = currents
        self.status = self._run(currents, self.ratio)
        self.y[:] = self.dae.q[self.sens]
        self.step_index += 1
        return self.y

    def advance_arriving(self, old, new, m) -> np.ndarray:
        m = min(max(int(m), 0), self.ratio)
        st = self._run(old, m) if m > 0 else di.OK
        if m < self.ratio and st not in self.FATAL:
            st2 = self._run(new, self.ratio - m)
            st = st2 if st2 != di.OK else st
        self.currents = new
        self.status = st
        self.y[:] = self.dae.q[self.sens]
        self.step_index += 1
        return self.y

    def safe_state(self) -> np.ndarray:
        self.currents = np.zeros(self.n_axes)
        return self.currents.copy()

    @property
    def contact(self) -> np.ndarray:
        """(m, NC) auxiliary-bearing contact state (``plant.integrator.C_*``), as PlantRunner's."""
        return self.dae.c

    @property
    def contact_names(self) -> tuple[str, ...]:
        return self._contact_names

    @property
    def s(self) -> np.ndarray:
        """FE-equivalent displacement vector [x, y, phi_x, phi_y per node] (orbit recording)."""
        return am.fe_view(self.S, self.dae.q)

    @property
    def stats(self) -> dict:
        d = self.dae
        return dict(newton_mean=d.newton_total / max(d.steps, 1), max_newton_iterations=d.newton_max,
                    refactorisations=d.refactorisations, constraint_drift=d.max_drift,
                    drive_torque=float(d.multipliers[self.S.nJ.shape[0]]) if d.steps else 0.0)
