"""In-process closed loop: plant + discrete controller in one fused numba loop.

:func:`simulate` runs exactly the kernels of the plant and controller processes
(:func:`ambhil.plant.integrator.plant_advance`, :func:`ambhil.controller.discrete.controller_step`) in the same
order as a lockstep run over zenoh (``y_k -> i_k = C(y_k) -> plant holds i_k for one controller
period -> y_{k+1}``), so both give bit-identical results.

``simulate(stability_check=True)`` reports the simulated loop's eigenvalues and the numerics
warning of :mod:`ambhil.loop.numerics`; a run that diverged gets an :func:`instability_report`.
The result and its time-series file: ``loop/sim_result.py``; what its orbits say:
``loop/orbits.py``; its plots: ``loop/orbit_plots.py``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numba as nb
import numpy as np

from ambhil.controller import discrete as dc
from ambhil.controller.law import LawError
from ambhil.plant import contact_step, integrator as ig
from ambhil.plant.contact_log import ContactLog
from ambhil.plant.faults import FaultSchedule, FaultyPlant
from ambhil.plant.latency import advance_late
from ambhil.plant.run_options import RunOptions
from ambhil.plant.step import PlantRunner, fault_report
from .numerics import numerics_warning, sampled_loop
from .sim_result import CONTACT_SERIES, SimResult
from .system import System, black_box_reason, controller_runner


@nb.njit(cache=True, _nrt=False)
def run_loop(p, s, wk, ws, cp, cx, nsteps, ratio, y, cur, R, every, out_y, out_i, out_o, ring, d, m):
    """Fused closed loop over nsteps controller periods; records every `every` periods
    (row 0 = initial).  With a latency (``ring`` non-empty, plant/latency.py) the currents reach
    the coils d periods + m plant steps after they are computed.  Returns the number of periods
    done (stops at a fatal fault)."""
    nrec = out_y.shape[0]
    n = R.shape[1]
    na = y.shape[0]
    for a in range(na):
        out_y[0, a] = y[a]
        out_i[0, a] = cur[a]
    for r in range(R.shape[0]):
        acc = 0.0
        for k in range(n):
            acc += R[r, k] * s[k]
        out_o[0, r] = acc
    for k in range(nsteps):
        dc.controller_step(cp, cx, y, cur)
        if ring.shape[0] == 0:
            st = ig.plant_advance(p, s, cur, ratio, wk, ws, y)
        else:
            st = advance_late(p, s, cur, ring, k, d, m, ratio, wk, ws, y)
        if (k + 1) % every == 0:
            j = (k + 1) // every
            if j < nrec:
                for a in range(na):
                    out_y[j, a] = y[a]
                    out_i[j - 1, a] = cur[a]
                for r in range(R.shape[0]):
                    acc = 0.0
                    for c in range(n):
                        acc += R[r, c] * s[c]
                    out_o[j, r] = acc
        if st == ig.NONFINITE or st == ig.TOUCHDOWN:
            return k + 1
    return nsteps


class ContactRecord:
    """The auxiliary bearings' contact series of a run (every recorded period) and its events
    (every period, plant/contact_log.py)."""
    FIELDS = {"x": ig.C_X, "y": ig.C_Y, "fn": ig.C_FN, "ft": ig.C_FT, "d": ig.C_D, "race_speed": ig.C_W,
              "friction_power": ig.C_PF, "e_friction": ig.C_EF, "e_damping": ig.C_ED}

    def __init__(self, plant, nrec: int):
        self.plant = plant
        self.names = plant.contact_names
        self.log = ContactLog(self.names, plant.period)
        self.series = {k: np.zeros((nrec, len(self.names))) for k in CONTACT_SERIES}

    def row(self, j: int) -> None:
        c = self.plant.contact
        for k, col in self.FIELDS.items():
            self.series[k][j] = c[:, col]

    def period(self, k: int) -> None:
        self.log.update(k, self.plant.contact)

    def finish(self, res: SimResult, model, h: float) -> None:
        """The run's contact record into ``res.contact``; how well the plant step ``h`` resolved a
        contact into its metadata (plant/contact_step.py)."""
        res.contact = self.result(len(res.t), model)
        res.meta["contact_resolution"] = {k: {"t_c_s": tc, "steps": st}
                                          for k, (tc, st) in contact_step.resolution(model, h).items()}
        res.meta["contact_notes"] = contact_step.check(model, h)

    def result(self, nvalid: int, model) -> dict:
        out = {k: v[:nvalid] for k, v in self.series.items()}
        by = {a.name: a for a in model.spec.ambs}
        out.update(names=self.names, clearance=np.array([by[n].auxiliary.clearance for n in self.names]),
                   shaft_radius=np.array([by[n].auxiliary.shaft_radius for n in self.names]),
                   race_radius=np.array([by[n].auxiliary.race_r for n in self.names]),
                   events=list(self.log.events), summary=self.log.summary(self.plant.contact))
        return out


def run_faulty(plant: FaultyPlant, ctrl, nsteps, R, every, out_y, out_i, out_o, contact=None) -> int:
    """The closed loop period by period with a fault schedule: the same kernels and order as
    :func:`run_loop` (``controller_step`` then the plant's period), the faulty plant of a HIL
    run, and the controller's state reset at a ``controller_restart``.  Same recording rules."""
    y = np.ascontiguousarray(plant.reset(), dtype=np.float64)
    ctrl.reset()
    restarts = plant.schedule.controller_restart_steps(plant.period)
    cur = np.array(plant.model.i_op, dtype=np.float64)
    out_y[0] = y
    out_i[0] = cur
    out_o[0] = R @ plant.s
    if contact is not None:
        contact.row(0)
    nrec = out_y.shape[0]
    fatal = plant.FATAL
    for k in range(nsteps):
        try:
            if k in restarts and k > 0:
                ctrl.reset()
            cur = ctrl.step_shared(y)
        except LawError as e:           # the law failed: the run ends here, its fault named
            ctrl.fault = str(e)
            return k
        y[:] = plant.advance_shared(cur)
        if contact is not None:
            contact.period(k + 1)
        if (k + 1) % every == 0:
            j = (k + 1) // every
            if j < nrec:
                out_y[j] = y
                out_i[j - 1] = cur
                out_o[j] = R @ plant.s
                if contact is not None:
                    contact.row(j)
        if plant.status in fatal:
            return k + 1
    return nsteps


def simulate(model: System, duration: float, speed=None, *, run_up=None, integrator: str | None = None,
             h: float | None = None, nodes=None, nonlinear=None, rho_inf=None, record_every: int = 1,
             sample_rate: float | None = None, method: str | None = None, q0=None, v0=None,
             plan: ig.PlantArrays | None = None, stability_check: bool = False, latency: float = 0.0,
             faults: FaultSchedule | None = None, law: str | None = None) -> SimResult:
    """Closed-loop transient from the operating point (or q0, v0) for ``duration`` s.

    ``speed``: constant spin speed (rad/s); ``run_up = (W0, W1, T0, T1)``.  ``nodes``: 1-based FE
    nodes whose x-y orbit is recorded (default: scene [simulation]/[analysis] output nodes, else
    the AMB nodes).  Defaults for integrator, h, force law come from the scene's [simulation].
    ``stability_check`` (linear time-invariant scenes): also compute the eigenvalues of the
    simulated discrete loop and report a growing mode even before the run visibly diverges.
    ``latency`` (s): the currents reach the coils that much after they are computed (whole
    periods plus whole plant steps; the same arithmetic as ``PlantRunner(model, RunOptions(latency=...))``).
    ``faults``: a fault schedule (default: the scene's ``[[fault]]`` tables); with faults the loop
    runs period by period in Python around the same kernels (:func:`run_faulty`), the very code
    of a HIL plant with faults, and ``SimResult.events`` lists each fault's start and end.
    ``law``: a law of its own (a resolved name, controller/law_loader.py) instead of the scene's;
    any law but the built-in PID runs period by period too (``meta["law"]`` names it)."""
    if not duration > 0:
        raise ValueError(f"duration must be > 0 s, got {duration!r}")
    if isinstance(speed, (tuple, list)):
        run_up, speed = tuple(speed), None
    ctrl = controller_runner(model, sample_rate=sample_rate, method=method, law=law)
    try:
        return _simulate(model, ctrl, duration, speed, run_up, integrator, h, nodes, nonlinear,
                         rho_inf, record_every, sample_rate, method, q0, v0, plan, stability_check,
                         latency, faults, law)
    finally:
        close = getattr(ctrl, "close", None)    # a law's own resources (a C library's state, an FMU)
        if close is not None:
            close()


def _simulate(model, ctrl, duration, speed, run_up, integrator, h, nodes, nonlinear, rho_inf,
              record_every, sample_rate, method, q0, v0, plan, stability_check, latency, faults,
              law) -> SimResult:
    options = RunOptions(integrator=integrator, h=h, speed=speed, run_up=run_up, nonlinear=nonlinear,
                         rho_inf=rho_inf, latency=latency, q0=q0, v0=v0)
    if model.rung == "ancf":
        return _simulate_ancf(model, ctrl, options, duration, nodes, record_every, method, faults)
    plant = PlantRunner(model, options, period=ctrl.period, plan=plan)
    rec = _Record.of(model, nodes, duration, ctrl.period, record_every)
    Rs = np.zeros((rec.R.shape[0], plant.s.shape[0]))
    Rs[:, :model.n] = rec.R
    if faults is None:
        faults = getattr(model.scene, "faults", None) or FaultSchedule()
    contact = ContactRecord(plant, rec.nrec) if plant.plan.ip[ig.I_AUX] else None
    p = plant.plan      # the scene's plan (a fault may swap the runner's for a while: a coast-down)
    done, wall, events, fplant = _run(model, plant, ctrl, faults, rec, Rs, contact)
    t = np.arange(rec.nrec) * rec.every * ctrl.period
    if fplant is not None and len(fplant._segments) > 1:
        sp_ = np.array([fplant.speed_at(tt) for tt in t])
    else:
        sp_ = np.array([ig.speed_at(p.fp, tt)[1] for tt in t]) if p.ip[ig.I_RUNUP] else np.full(rec.nrec, p.fp[ig.F_W0])
    fault = getattr(ctrl, "fault", None) or fault_report(p, plant.ws, model)
    meta = dict(scene=model.scene.name, scene_path=model.scene.path, rung=model.rung, n=model.n,
                integrator=plant.integrator, h=plant.h, period=ctrl.period, ratio=plant.ratio,
                discretisation=method or model.scene.controller.discretisation,
                delay_samples=model.scene.controller.delay_samples,
                nonlinear=bool(p.ip[ig.I_NL]), speed=float(p.fp[ig.F_W0]),
                run_up=None if not p.ip[ig.I_RUNUP] else [float(x) for x in p.fp[ig.F_W0:ig.F_T1 + 1]],
                rho_inf=rho_inf, duration=duration, record_every=rec.every, steps=int(done), wall=wall,
                latency=latency, fault=fault, max_newton_iterations=int(plant.ws[ig.W_MAXIT]),
                refactorisations=int(plant.ws[ig.W_NREFAC]), mode="in-process lockstep",
                amb_nodes={a.name: a.node + 1 for a in model.spec.ambs}, law=law_name(ctrl))
    res = rec.result(model, t, sp_, meta, fault, done, wall, events)
    if contact is not None:
        contact.finish(res, model, plant.h)
    if events is not None:
        meta["fault_events"] = events
    if getattr(ctrl, "fault", None):
        pass                            # the law's own fault, not the loop's numerics
    elif done < rec.nsteps or int(plant.ws[ig.W_STATUS]) in (ig.NONFINITE, ig.TOUCHDOWN):
        res.instability = instability_report(res, model)
    why = black_box_reason(model.scene, law) if stability_check else None
    if why:                             # the loop's eigenvalues need a linear law
        meta["stability_check"] = f"not computed ({why})"
    elif stability_check and not latency and not p.ip[ig.I_NL] and not p.ip[ig.I_RUNUP] and not faults:
        _check_stability(res, model, plant, ctrl, sample_rate, rho_inf, method)
    meta["instability"] = res.instability
    return res


@dataclass
class _Record:
    """What a run records: the output nodes, their rows of the state, and the arrays of every
    ``every``-th controller period (row 0: the initial state)."""
    nodes: tuple
    R: np.ndarray
    nsteps: int
    every: int
    nrec: int
    out_y: np.ndarray
    out_i: np.ndarray
    out_o: np.ndarray

    @classmethod
    def of(cls, model, nodes, duration, period, record_every) -> "_Record":
        nodes = _output_nodes(model, nodes)
        R = np.ascontiguousarray(model.node_rows([k - 1 for k in nodes]), dtype=np.float64)
        nsteps = int(round(duration / period))
        every = max(1, int(record_every))
        nrec = nsteps // every + 1
        return cls(nodes, R, nsteps, every, nrec, np.zeros((nrec, model.n_axes)), np.zeros((nrec, model.n_axes)),
                   np.zeros((nrec, R.shape[0])))

    def result(self, model, t, speed, meta, fault, done, wall, events=None) -> SimResult:
        """The recorded rows up to the last period done."""
        nvalid = done // self.every + 1
        orbit = self.out_o.reshape(self.nrec, len(self.nodes), 2)
        return SimResult(t=t[:nvalid], y=self.out_y[:nvalid], i=self.out_i[:nvalid], orbit=orbit[:nvalid],
                         nodes=self.nodes, speed=speed[:nvalid], axes=tuple(f"{a}:{x}" for a, x in model.axes),
                         meta=meta, fault=fault, steps=int(done), wall=wall, events=events)


def _run(model: System, plant: PlantRunner, ctrl, faults, rec: _Record, Rs, contact=None):
    """The loop itself, timed: the fused kernel (:func:`run_loop`), or period by period around a
    :class:`FaultyPlant` with a fault schedule, a law of its own or auxiliary bearings (whose
    contact events are read every period).  Returns (periods done, wall time, fault events, the
    FaultyPlant or None)."""
    y = plant.reset()
    ctrl.reset()
    cur = np.array(model.i_op, dtype=np.float64)
    if faults or not isinstance(ctrl, dc.ControllerRunner) or contact is not None:
        # a fault schedule, or a law run between the hardware kernels (LawRunner): period by
        # period around the same plant kernels
        fplant = FaultyPlant(plant, faults)
        t0 = time.perf_counter()
        done = run_faulty(fplant, ctrl, rec.nsteps, Rs, rec.every, rec.out_y, rec.out_i, rec.out_o, contact)
        return done, time.perf_counter() - t0, fplant.events, fplant
    ring = plant.ring if plant.ring is not None else np.zeros((0, model.n_axes))
    # zero periods first: the kernel is loaded (from numba's cache, or compiled) outside the
    # timing, so us/period is the loop's own cost however short the run
    run_loop(plant.plan, plant.s, plant.work, plant.ws, ctrl.params, ctrl.state, 0, plant.ratio,
             y, cur, Rs, rec.every, rec.out_y, rec.out_i, rec.out_o, ring, *plant.late)
    t0 = time.perf_counter()
    done = run_loop(plant.plan, plant.s, plant.work, plant.ws, ctrl.params, ctrl.state, rec.nsteps, plant.ratio,
                    y, cur, Rs, rec.every, rec.out_y, rec.out_i, rec.out_o, ring, *plant.late)
    return done, time.perf_counter() - t0, None, None


def _check_stability(res: SimResult, model: System, plant: PlantRunner, ctrl, sample_rate, rho_inf, method) -> None:
    """The simulated discrete loop's eigenvalues into ``res.meta``; a growing mode into
    ``res.instability``, the numerics warning into ``res.numerics``."""
    meta, p = res.meta, plant.plan
    lm = sampled_loop(model, plant.integrator, plant.h, ctrl=ctrl, plan=plant.plan, vectors=True, response=True)
    rho = lm.spectral_radius
    meta["loop_spectral_radius"] = rho
    meta["loop_growth_rate"], meta["loop_frequency"] = lm.growth_rate, lm.frequency_hz
    if not lm.stable:
        k = lm.dominant
        nd = _worst_node(model, lm.V[:model.n, k])
        txt = (f"discrete loop unstable: mode at {lm.frequency_hz:.4g} Hz grows at {lm.growth_rate:.3g} 1/s "
               f"(|mu| = {rho:.6f} per period; largest at node {nd})")
        res.instability = txt if res.instability is None else f"{res.instability}; {txt}"
    res.numerics = numerics_warning(model, plant.integrator, plant.h, speed=float(p.fp[ig.F_W0]),
                                    sample_rate=sample_rate, rho_inf=rho_inf, method=method, loop=lm)
    meta["numerics_warning"] = res.numerics


def _output_nodes(model, nodes):
    if nodes is None:
        sim = model.spec.simulation
        nodes = tuple(getattr(sim, "output_nodes", ()) or ()) or tuple(k + 1 for k in model.scene.analysis.output_nodes) \
            or tuple(sorted({a.node + 1 for a in model.spec.ambs}))
    nodes = tuple(int(k) for k in nodes)
    for k in nodes:
        if not 1 <= k <= model.spec.n_nodes:
            raise ValueError(f"output node {k} is outside the shaft (nodes 1..{model.spec.n_nodes})")
    return nodes

def _simulate_ancf(model, ctrl, options: RunOptions, duration, nodes, record_every, method, faults) -> SimResult:
    """simulate() for the ancf rung: the same loop order (controller step, then one period of the
    plant), period by period in Python around plant/ancf_step.ANCFRunner (its Newton steps); with a
    fault schedule (coil losses, drops) around plant/ancf_faults.ANCFFaultyPlant, with auxiliary
    bearings their contact series and events recorded as :func:`_simulate` does (ContactRecord)."""
    from ambhil.plant.ancf_faults import ANCFFaultyPlant
    from ambhil.plant.ancf_model import speed_profile
    from ambhil.plant.ancf_step import ANCFRunner
    if faults is None:
        faults = getattr(model.scene, "faults", None) or FaultSchedule()
    plant = ANCFRunner(model, options, period=ctrl.period)
    if faults:
        plant = ANCFFaultyPlant(plant, faults)
    rec = _Record.of(model, nodes, duration, ctrl.period, record_every)
    R, nsteps, every, nrec, out_y, out_i, out_o = rec.R, rec.nsteps, rec.every, rec.nrec, rec.out_y, rec.out_i, rec.out_o
    contact = ContactRecord(plant, nrec) if len(plant.contact_names) else None
    y = np.ascontiguousarray(plant.reset(), dtype=np.float64)
    ctrl.reset()
    cur = np.array(model.i_op, dtype=np.float64)
    out_y[0] = y; out_i[0] = cur; out_o[0] = R @ plant.s
    if contact is not None:
        contact.row(0)
    t0 = time.perf_counter()
    done = nsteps
    for k in range(nsteps):
        try:
            cur = ctrl.step_shared(y)
        except LawError as e:           # the law failed: the run ends here, its fault named
            ctrl.fault = str(e)
            done = k
            break
        y[:] = plant.advance_shared(cur)
        if contact is not None:
            contact.period(k + 1)
        if (k + 1) % every == 0:
            j = (k + 1) // every
            if j < nrec:
                out_y[j] = y; out_i[j - 1] = cur; out_o[j] = R @ plant.s
                if contact is not None:
                    contact.row(j)
        if plant.status in plant.FATAL:
            done = k + 1
            break
    wall = time.perf_counter() - t0
    t = np.arange(nrec) * every * ctrl.period
    sp_ = np.array([speed_profile(plant.S.spin, tt)[1] for tt in t])
    fault = getattr(ctrl, "fault", None) or plant.fault
    meta = dict(law=law_name(ctrl), scene=model.scene.name, scene_path=model.scene.path, rung="ancf", n=int(plant.dae.n),
                constraints=int(plant.dae.nc), integrator=plant.integrator, h=plant.h, period=ctrl.period,
                ratio=plant.ratio, discretisation=method or model.scene.controller.discretisation,
                delay_samples=model.scene.controller.delay_samples, nonlinear=plant.nonlinear, speed=plant.speed,
                run_up=None if plant.run_up is None else [float(x) for x in plant.run_up],
                rho_inf=options.rho_inf, duration=duration, record_every=every, steps=int(done), wall=wall,
                latency=options.latency, fault=fault, mode="in-process lockstep", **plant.stats)
    events = plant.events if faults else None
    res = rec.result(model, t, sp_, meta, fault, done, wall, events)
    if contact is not None:
        contact.finish(res, model, plant.h)
    if events is not None:
        meta["fault_events"] = events
    if done < nsteps and not getattr(ctrl, "fault", None):
        res.instability = instability_report(res, model)
    meta["instability"] = res.instability
    return res


def law_name(ctrl) -> str:
    """What a run's metadata calls its law: ``pid`` (the built-in, fused) or the law's name."""
    return "pid" if isinstance(ctrl, dc.ControllerRunner) else ctrl.name


def _worst_node(model: System, v_eta: np.ndarray) -> int:
    q = v_eta if model.T is None else model.T @ v_eta
    dpn = model.rotor.dpn
    amp = np.abs(q[0::dpn]) ** 2 + np.abs(q[1::dpn]) ** 2
    return int(np.argmax(amp)) + 1


def instability_report(res: SimResult, model: System) -> str:
    """When and where a run diverged: time, worst AMB axis / node, growth rate and frequency."""
    y = res.y
    ok = np.all(np.isfinite(y), axis=1)
    yy, tt = y[ok], res.t[ok]
    a = int(np.argmax(np.abs(yy[-1]))) if len(yy) else 0
    sig = yy[:, a]
    txt = f"numerically unstable: {res.fault or 'diverged'}; largest motion at AMB {model.axes[a][0]} axis {model.axes[a][1]}"
    if len(sig) > 20:
        seg = slice(max(0, len(sig) - max(64, len(sig) // 5)), len(sig))
        env = np.abs(sig[seg]) + 1e-300
        g = np.polyfit(tt[seg], np.log(np.maximum.accumulate(env)), 1)[0]
        x = sig[seg] * np.exp(-g * (tt[seg] - tt[seg][-1]))  # remove the growth before the FFT
        x = (x - x.mean()) * np.hanning(len(x))
        nfft = 16 * len(x)
        F = np.abs(np.fft.rfft(x, nfft))
        f = np.fft.rfftfreq(nfft, tt[1] - tt[0])[int(np.argmax(F))]
        txt += f"; growth rate ~{g:.3g} 1/s at ~{f:.4g} Hz"
    return txt
