"""In-process closed loop: plant + discrete controller in one fused numba loop.

:func:`simulate` runs exactly the kernels of the plant and controller processes
(:func:`ambhil.plant.integrator.plant_advance`, :func:`ambhil.controller.discrete.controller_step`) in the same
order as a lockstep run over zenoh (``y_k -> i_k = C(y_k) -> plant holds i_k for one controller
period -> y_{k+1}``), so both give bit-identical results.

Also here: steady-state harmonic fits and orbit metrics (settle time, steady radius) and the
orbit plots.  ``simulate(stability_check=True)`` reports the simulated loop's eigenvalues and the
numerics warning of :mod:`ambhil.loop.numerics`.

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
===============  ==================  ===================================================
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np

from ambhil.controller import discrete as dc
from ambhil.plant import integrator as ig
from ambhil.plant.faults import FaultSchedule, FaultyPlant
from ambhil.plant.latency import advance_late
from ambhil.plant.step import PlantRunner, fault_report
from .numerics import numerics_warning, sampled_loop
from .system import System, controller_runner


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


def run_faulty(plant: FaultyPlant, ctrl, nsteps, R, every, out_y, out_i, out_o) -> int:
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
    nrec = out_y.shape[0]
    fatal = plant.FATAL
    for k in range(nsteps):
        if k in restarts and k > 0:
            ctrl.reset()
        cur = ctrl.step_shared(y)
        y[:] = plant.advance_shared(cur)
        if (k + 1) % every == 0:
            j = (k + 1) // every
            if j < nrec:
                out_y[j] = y
                out_i[j - 1] = cur
                out_o[j] = R @ plant.s
        if plant.status in fatal:
            return k + 1
    return nsteps


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
        np.savez(f, t=self.t, y=self.y, i=self.i, orbit=self.orbit, nodes=np.array(self.nodes),
                 speed=self.speed, axes=np.array(self.axes), meta=np.array(json.dumps(self.meta)))
        return f


def load(path) -> SimResult:
    z = np.load(Path(path) / "simulation.npz" if Path(path).is_dir() else path, allow_pickle=False)
    meta = json.loads(str(z["meta"]))
    return SimResult(t=z["t"], y=z["y"], i=z["i"], orbit=z["orbit"], nodes=tuple(int(k) for k in z["nodes"]),
                     speed=z["speed"], axes=tuple(str(a) for a in z["axes"]), meta=meta,
                     fault=meta.get("fault"), steps=meta.get("steps", 0), wall=meta.get("wall", 0.0))


def simulate(model: System, duration: float, speed=None, *, run_up=None, integrator: str | None = None,
             h: float | None = None, nodes=None, nonlinear=None, rho_inf=None, record_every: int = 1,
             sample_rate: float | None = None, method: str | None = None, q0=None, v0=None,
             plan: ig.PlantArrays | None = None, stability_check: bool = False, latency: float = 0.0,
             faults: FaultSchedule | None = None) -> SimResult:
    """Closed-loop transient from the operating point (or q0, v0) for ``duration`` s.

    ``speed``: constant spin speed (rad/s); ``run_up = (W0, W1, T0, T1)``.  ``nodes``: 1-based FE
    nodes whose x-y orbit is recorded (default: scene [simulation]/[analysis] output nodes, else
    the AMB nodes).  Defaults for integrator, h, force law come from the scene's [simulation].
    ``stability_check`` (linear time-invariant scenes): also compute the eigenvalues of the
    simulated discrete loop and report a growing mode even before the run visibly diverges.
    ``latency`` (s): the currents reach the coils that much after they are computed (whole
    periods plus whole plant steps; the same arithmetic as ``PlantRunner(latency=...)``).
    ``faults``: a fault schedule (default: the scene's ``[[fault]]`` tables); with faults the loop
    runs period by period in Python around the same kernels (:func:`run_faulty`), the very code
    of a HIL plant with faults, and ``SimResult.events`` lists each fault's start and end."""
    if not duration > 0:
        raise ValueError(f"duration must be > 0 s, got {duration!r}")
    if isinstance(speed, (tuple, list)):
        run_up, speed = tuple(speed), None
    ctrl = controller_runner(model, sample_rate=sample_rate, method=method)
    if model.rung == "ancf":
        return _simulate_ancf(model, ctrl, duration, speed, run_up, integrator, h, nodes, nonlinear, rho_inf,
                              record_every, method, q0, v0, latency, faults)
    plant = PlantRunner(model, integrator, h, period=ctrl.period, speed=speed, run_up=run_up,
                        nonlinear=nonlinear, rho_inf=rho_inf, q0=q0, v0=v0, plan=plan, latency=latency)
    nodes = _output_nodes(model, nodes)
    R = np.ascontiguousarray(model.node_rows([k - 1 for k in nodes]), dtype=np.float64)
    Rs = np.zeros((R.shape[0], plant.s.shape[0]))
    Rs[:, :model.n] = R
    nsteps = int(round(duration / ctrl.period))
    every = max(1, int(record_every))
    nrec = nsteps // every + 1
    out_y = np.zeros((nrec, model.n_axes)); out_i = np.zeros((nrec, model.n_axes)); out_o = np.zeros((nrec, R.shape[0]))
    y = plant.reset()
    ctrl.reset()
    cur = np.array(model.i_op, dtype=np.float64)
    t0 = time.perf_counter()
    if faults is None:
        faults = getattr(model.scene, "faults", None) or FaultSchedule()
    events = None
    if faults:
        fplant = FaultyPlant(plant, faults)
        t0 = time.perf_counter()
        done = run_faulty(fplant, ctrl, nsteps, Rs, every, out_y, out_i, out_o)
        events = fplant.events
    else:
        ring = plant.ring if plant.ring is not None else np.zeros((0, model.n_axes))
        # zero periods first: the kernel is loaded (from numba's cache, or compiled) outside the
        # timing, so us/period is the loop's own cost however short the run
        run_loop(plant.plan, plant.s, plant.work, plant.ws, ctrl.params, ctrl.state, 0, plant.ratio,
                 y, cur, Rs, every, out_y, out_i, out_o, ring, *plant.late)
        t0 = time.perf_counter()
        done = run_loop(plant.plan, plant.s, plant.work, plant.ws, ctrl.params, ctrl.state, nsteps, plant.ratio,
                        y, cur, Rs, every, out_y, out_i, out_o, ring, *plant.late)
    wall = time.perf_counter() - t0
    nvalid = done // every + 1
    t = np.arange(nrec) * every * ctrl.period
    p = plant.plan
    sp_ = np.array([ig.speed_at(p.fp, tt)[1] for tt in t]) if p.ip[ig.I_RUNUP] else np.full(nrec, p.fp[ig.F_W0])
    fault = fault_report(p, plant.ws, model)
    meta = dict(scene=model.scene.name, scene_path=model.scene.path, rung=model.rung, n=model.n,
                integrator=plant.integrator, h=plant.h, period=ctrl.period, ratio=plant.ratio,
                discretisation=method or model.scene.controller.discretisation,
                delay_samples=model.scene.controller.delay_samples,
                nonlinear=bool(p.ip[ig.I_NL]), speed=float(p.fp[ig.F_W0]),
                run_up=None if not p.ip[ig.I_RUNUP] else [float(x) for x in p.fp[ig.F_W0:ig.F_T1 + 1]],
                rho_inf=rho_inf, duration=duration, record_every=every, steps=int(done), wall=wall, latency=latency,
                fault=fault, max_newton_iterations=int(plant.ws[ig.W_MAXIT]),
                refactorisations=int(plant.ws[ig.W_NREFAC]), mode="in-process lockstep",
                amb_nodes={a.name: a.node + 1 for a in model.spec.ambs})
    orbit = out_o.reshape(nrec, len(nodes), 2)
    res = SimResult(t=t[:nvalid], y=out_y[:nvalid], i=out_i[:nvalid], orbit=orbit[:nvalid], nodes=nodes,
                    speed=sp_[:nvalid], axes=tuple(f"{a}:{x}" for a, x in model.axes), meta=meta, fault=fault,
                    steps=int(done), wall=wall, events=events)
    if events is not None:
        meta["fault_events"] = events
    if done < nsteps or int(plant.ws[ig.W_STATUS]) in (ig.NONFINITE, ig.TOUCHDOWN):
        res.instability = instability_report(res, model)
    if stability_check and not latency and not p.ip[ig.I_NL] and not p.ip[ig.I_RUNUP] and not faults:
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
    meta["instability"] = res.instability
    return res


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


def _simulate_ancf(model, ctrl, duration, speed, run_up, integrator, h, nodes, nonlinear, rho_inf, record_every,
                   method, q0, v0, latency, faults) -> SimResult:
    """simulate() for the ancf rung: the same loop order (controller step, then one period of the
    plant), period by period in Python around plant/ancf_step.ANCFRunner (its Newton steps)."""
    from ambhil.plant.ancf_step import ANCFRunner
    if faults is None:
        faults = getattr(model.scene, "faults", None) or FaultSchedule()
    if faults:
        raise ValueError(f"{model.spec.path}: scheduled faults are not supported on the ancf rung yet")
    plant = ANCFRunner(model, integrator, h, period=ctrl.period, speed=speed, run_up=run_up, nonlinear=nonlinear,
                       rho_inf=rho_inf, q0=q0, v0=v0, latency=latency)
    nodes = _output_nodes(model, nodes)
    R = np.ascontiguousarray(model.node_rows([k - 1 for k in nodes]), dtype=np.float64)
    nsteps = int(round(duration / ctrl.period))
    every = max(1, int(record_every))
    nrec = nsteps // every + 1
    out_y = np.zeros((nrec, model.n_axes)); out_i = np.zeros((nrec, model.n_axes)); out_o = np.zeros((nrec, R.shape[0]))
    y = np.ascontiguousarray(plant.reset(), dtype=np.float64)
    ctrl.reset()
    cur = np.array(model.i_op, dtype=np.float64)
    out_y[0] = y; out_i[0] = cur; out_o[0] = R @ plant.s
    t0 = time.perf_counter()
    done = nsteps
    for k in range(nsteps):
        cur = ctrl.step_shared(y)
        y[:] = plant.advance_shared(cur)
        if (k + 1) % every == 0:
            j = (k + 1) // every
            if j < nrec:
                out_y[j] = y; out_i[j - 1] = cur; out_o[j] = R @ plant.s
        if plant.status in plant.FATAL:
            done = k + 1
            break
    wall = time.perf_counter() - t0
    nvalid = done // every + 1
    t = np.arange(nrec) * every * ctrl.period
    from ambhil.plant.ancf_model import speed_profile
    sp_ = np.array([speed_profile(plant.S.spin, tt)[1] for tt in t])
    fault = plant.fault
    meta = dict(scene=model.scene.name, scene_path=model.scene.path, rung="ancf", n=int(plant.dae.n),
                constraints=int(plant.dae.nc), integrator=plant.integrator, h=plant.h, period=ctrl.period,
                ratio=plant.ratio, discretisation=method or model.scene.controller.discretisation,
                delay_samples=model.scene.controller.delay_samples, nonlinear=plant.nonlinear, speed=plant.speed,
                run_up=None if plant.run_up is None else [float(x) for x in plant.run_up],
                rho_inf=rho_inf, duration=duration, record_every=every, steps=int(done), wall=wall, latency=latency,
                fault=fault, mode="in-process lockstep", **plant.stats)
    orbit = out_o.reshape(nrec, len(nodes), 2)
    res = SimResult(t=t[:nvalid], y=out_y[:nvalid], i=out_i[:nvalid], orbit=orbit[:nvalid], nodes=nodes,
                    speed=sp_[:nvalid], axes=tuple(f"{a}:{x}" for a, x in model.axes), meta=meta, fault=fault,
                    steps=int(done), wall=wall)
    if done < nsteps:
        res.instability = instability_report(res, model)
    meta["instability"] = res.instability
    return res


def _worst_node(model: System, v_eta: np.ndarray) -> int:
    q = v_eta if model.T is None else model.T @ v_eta
    dpn = model.rotor.dpn
    amp = np.abs(q[0::dpn]) ** 2 + np.abs(q[1::dpn]) ** 2
    return int(np.argmax(amp)) + 1


# --------------------------------------------------------------------------- post-processing
def harmonic(t, x, w, t_from: float | None = None) -> complex:
    """Complex amplitude X of x(t) ~ Re(X e^{i w t}) + c, least squares over t >= t_from
    (default: the last half), trimmed to whole periods."""
    t = np.asarray(t); x = np.asarray(x)
    t_from = t[len(t) // 2] if t_from is None else t_from
    T = 2 * np.pi / w
    tend = t[-1]
    nper = math.floor((tend - t_from) / T)
    if nper >= 1:
        t_from = tend - nper * T
    m = t >= t_from - 1e-12
    A = np.column_stack([np.cos(w * t[m]), np.sin(w * t[m]), np.ones(m.sum())])
    a, b, _ = np.linalg.lstsq(A, x[m], rcond=None)[0]
    return complex(a, -b)


def orbit_metrics(t, x, y, w, band: float = 0.05, tail: float = 0.2) -> dict:
    """Steady orbit radius (mean radius over the last `tail` fraction, whole revolutions) and
    settle time: start of the first revolution after which every revolution's peak radius stays
    within +-band of the steady radius."""
    t = np.asarray(t); r = np.hypot(x, y)
    T = 2 * np.pi / w if w > 0 else (t[-1] - t[0]) / 50
    edges = np.arange(t[0], t[-1] + 1e-12, T)
    if len(edges) < 3:
        return dict(radius=float(np.mean(r)), settle_time=float("nan"), peak=float(np.max(r)))
    idx = np.searchsorted(t, edges)
    peaks = np.array([r[a:b].max() for a, b in zip(idx[:-1], idx[1:]) if b > a])
    starts = edges[:len(peaks)]
    ntail = max(2, int(len(peaks) * tail))
    steady = float(np.mean(peaks[-ntail:]))
    bad = np.where(np.abs(peaks - steady) > band * steady)[0]
    settle = float(starts[bad[-1] + 1]) if len(bad) and bad[-1] + 1 < len(starts) else (
        float(starts[0]) if not len(bad) else float("nan"))
    return dict(radius=steady, settle_time=settle, peak=float(np.max(r)))


def touchdown_orbits(res: SimResult, ambs) -> list[dict]:
    """The largest orbit radius over the run at each AMB whose node is an output node, against
    that AMB's touchdown clearance (``RadialAMB.clearance``): the figure a fault campaign judges
    (``ambhil.loop.campaign``) and ``ambhil run`` prints."""
    out = []
    for a in ambs:
        if a.node + 1 in res.nodes:
            j = res.nodes.index(a.node + 1)
            r = np.hypot(res.orbit[:, j, 0], res.orbit[:, j, 1])
            r = float(np.nanmax(r)) if np.isfinite(r).any() else float("nan")
            out.append({"amb": a.name, "node": a.node + 1, "largest_radius_m": r, "touchdown_clearance_m": a.clearance,
                        "touchdown_clearance_given": a.touchdown_clearance is not None,
                        "fraction_of_touchdown_clearance": r / a.clearance})
    return out


def orbit_segments(res: SimResult, stations) -> list[dict]:
    """The largest orbit per AMB between the instants where the run changes: each scheduled
    fault's start and end, and a run-up's ramp start and end (:func:`time_marks`).  ``stations``:
    ``(AMB name, 1-based node, touchdown clearance m)`` of the AMBs at output nodes.  Each segment:
    ``{start_s, end_s, faults (labels of the faults active), speed_rad_s (None on the ramp),
    run_up (W0, W1) on the ramp, orbits: [{amb, node, largest_radius_m, fraction_of_touchdown_clearance,
    at_s, speed_rad_s}]}``.  A run without faults or run-up is one segment."""
    t = np.asarray(res.t)
    if not len(t):
        return []
    t_end = float(t[-1])
    marks = time_marks(res)
    cuts = sorted({0.0, t_end} | {v for m in marks for v in (m["start_s"], m["end_s"])
                                  if v is not None and 0.0 < v < t_end})
    ru = res.meta.get("run_up")
    out = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        sel = (t >= a - 1e-12) & ((t < b - 1e-12) if b < t_end else (t <= b))
        if not sel.any():
            continue
        mid = 0.5 * (a + b)
        seg = {"start_s": a, "end_s": b,
               "faults": [m["label"] for m in marks if m["kind"] == "fault"
                          and m["start_s"] <= mid < (m["end_s"] if m["end_s"] is not None else np.inf)],
               "speed_rad_s": None, "run_up": None, "orbits": []}
        if ru and ru[2] <= mid < ru[3]:
            seg["run_up"] = [float(ru[0]), float(ru[1])]
        else:
            seg["speed_rad_s"] = float(np.asarray(res.speed)[sel][0]) if len(res.speed) else None
        idx = np.where(sel)[0]
        for name, nd, clr in stations:
            if nd not in res.nodes:
                continue
            j = res.nodes.index(nd)
            r = np.hypot(res.orbit[idx, j, 0], res.orbit[idx, j, 1])
            ok = np.isfinite(r)
            k = idx[ok][int(np.argmax(r[ok]))] if ok.any() else None
            big = float(np.max(r[ok])) if ok.any() else float("nan")
            seg["orbits"].append({"amb": name, "node": nd, "largest_radius_m": big,
                                  "fraction_of_touchdown_clearance": big / clr if clr else float("nan"),
                                  "at_s": float(t[k]) if k is not None else None,
                                  "speed_rad_s": float(res.speed[k]) if k is not None and len(res.speed) else None})
        out.append(seg)
    return out


def steady_at_end(res: SimResult, stations, start_s: float) -> list[dict]:
    """Steady orbit and settle time per AMB over ``[start_s, end]`` (:func:`orbit_metrics` at the
    final speed): how a run settles after its last fault event or its run-up.  Empty where the
    speed varies there or the stretch is shorter than three revolutions."""
    t = np.asarray(res.t)
    sel = t >= start_s - 1e-12
    w = float(res.speed[-1]) if len(res.speed) else 0.0
    if not w > 0 or sel.sum() < 3 or not np.allclose(res.speed[sel], w, rtol=1e-9) \
            or (t[-1] - start_s) < 3 * 2 * np.pi / w:
        return []
    out = []
    for name, nd, _ in stations:
        if nd not in res.nodes:
            continue
        j = res.nodes.index(nd)
        met = orbit_metrics(t[sel], res.orbit[sel, j, 0], res.orbit[sel, j, 1], w)
        out.append({"amb": name, "node": nd, "radius_m": met["radius"], "settle_time_s": met["settle_time"],
                    "from_s": float(start_s), "speed_rad_s": w})
    return out


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


# --------------------------------------------------------------------------- plots
def plot_orbits(res: SimResult, out_dir, nodes=None, gaps: dict | None = None,
                clearances: dict | None = None) -> list[Path]:
    """``orbit_node<k>.png`` per output node (whirl radius over time, the x-y orbit with +y up and
    the touchdown clearance circle of an AMB node, that AMB's coil currents) and ``currents.png``
    (every AMB's control currents over time).  ``clearances``: {1-based node: touchdown clearance
    (m)} of the AMB nodes, the circle the orbit is judged against; ``gaps``: {1-based node:
    magnetic gap (m)}, drawn apart (grey, dashed) where it is in view.  A clearance much larger
    than the orbit is drawn in an inset at its own scale, so the orbit stays readable.  Every
    time plot marks each scheduled fault's start and end and a run-up's ramp (:func:`time_marks`);
    the titles name the speed, or the run-up's range (:func:`speed_title`)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    out = []
    gaps, clearances = gaps or {}, clearances or {}
    nodes = nodes or res.nodes
    every = int(res.meta.get("record_every", 1))
    n_i = min(res.steps // every, len(res.i))            # answered samples (the last row has none)
    stations = _stations(res.axes)
    amb_at = {nd: name for name, nd in _amb_nodes(res, stations, clearances or gaps)}
    marks = time_marks(res)
    for nd in nodes:
        if nd not in res.nodes:
            continue
        j = res.nodes.index(nd)
        x, y = res.orbit[:, j, 0] * 1e6, res.orbit[:, j, 1] * 1e6
        st = amb_at.get(nd)
        fig, ax = plt.subplots(1, 3 if st else 2, figsize=(15 if st else 10, 4.4))
        ax[0].plot(res.t, np.hypot(x, y), lw=0.6)
        ax[0].set_xlabel("t (s)"); ax[0].set_ylabel("orbit radius (um)")
        ax[0].set_title(f"node {nd}: whirl radius"); ax[0].grid(alpha=0.3)
        _mark_times(ax[0], marks)
        ax[1].plot(x, y, lw=0.4)
        ax[1].plot(x[-1:], y[-1:], "o", ms=3, color="C0")
        ax[1].set_aspect("equal", adjustable="datalim"); ax[1].set_xlabel("x (um)"); ax[1].set_ylabel("y (um)")
        ax[1].axhline(0, color="0.7", lw=0.5); ax[1].axvline(0, color="0.7", lw=0.5); ax[1].grid(alpha=0.3)
        title = f"node {nd}" + (f" (AMB {st})" if st else "") + f": orbit ({res.meta['integrator']}, h={res.meta['h']:g} s)"
        g = clearances.get(nd)
        if g:
            g_um = g * 1e6
            mg_um = gaps[nd] * 1e6 if gaps.get(nd) else None        # the magnetic gap, apart
            r_max = float(np.nanmax(np.hypot(x, y))) if len(x) else 0.0
            circle = np.linspace(0, 2 * np.pi, 361)
            title += (f"\nlargest radius {r_max:.3g} um = {100 * r_max / g_um:.1f} % of the touchdown clearance "
                      f"{g_um:g} um")
            if r_max > 0.3 * g_um:                                   # same scale: draw it
                ax[1].plot(g_um * np.cos(circle), g_um * np.sin(circle), color="C3", lw=1.2,
                           label=f"touchdown clearance {g_um:g} um")
                if mg_um:
                    ax[1].plot(mg_um * np.cos(circle), mg_um * np.sin(circle), color="0.5", lw=1.0, ls="--",
                               label=f"magnetic gap {mg_um:g} um")
                ax[1].legend(loc="upper right", fontsize=8)
            else:                                                   # inset at the clearance's scale
                ins = ax[1].inset_axes([0.76, 0.7, 0.23, 0.23])     # in the corner the orbit leaves free
                if mg_um:
                    ins.plot(mg_um * np.cos(circle), mg_um * np.sin(circle), color="0.5", lw=0.8, ls="--")
                ins.plot(g_um * np.cos(circle), g_um * np.sin(circle), color="C3", lw=1.0)
                ins.plot(x, y, lw=0.6, color="C0")
                ins.set_aspect("equal"); ins.set_xticks([]); ins.set_yticks([])
                ins.set_xlabel(f"touchdown clearance {g_um:g} um" + (f"\n(dashed: magnetic gap {mg_um:g} um)"
                                                                     if mg_um else ""),
                               fontsize=7, color="C3", labelpad=1)
        ax[1].set_title(title, fontsize=10)
        if st:
            for k, (axn, col) in enumerate(stations[st]):
                ax[2].plot(res.t[:n_i], res.i[:n_i, col], lw=0.6, label=f"{st}-{axn}")
            ax[2].set_xlabel("t (s)"); ax[2].set_ylabel("control current (A)")
            ax[2].set_title(f"AMB {st}: coil currents"); ax[2].legend(fontsize=8, loc="upper right"); ax[2].grid(alpha=0.3)
            _mark_times(ax[2], marks)
        fig.suptitle(f"{res.meta['scene']} [{res.meta['rung']}] {speed_title(res.meta)}" + _faults_title(marks))
        fig.tight_layout()
        p = Path(out_dir) / f"orbit_node{nd}.png"
        fig.savefig(p, dpi=110); plt.close(fig)
        out.append(p)
    if stations and n_i:
        fig, ax = plt.subplots(len(stations), 1, figsize=(10, 2.2 + 1.8 * len(stations)), sharex=True, squeeze=False)
        for r, (st, cols) in enumerate(stations.items()):
            a = ax[r, 0]
            for axn, col in cols:
                a.plot(res.t[:n_i], res.i[:n_i, col], lw=0.6, label=f"{st}-{axn}")
            a.set_ylabel(f"AMB {st} (A)"); a.legend(fontsize=8, loc="upper right"); a.grid(alpha=0.3)
            _mark_times(a, marks, labels=r == 0)
        ax[-1, 0].set_xlabel("t (s)")
        fig.suptitle(f"{res.meta['scene']} [{res.meta['rung']}]: control currents per AMB axis\n{speed_title(res.meta)}"
                     + _faults_title(marks))
        fig.tight_layout()
        p = Path(out_dir) / "currents.png"
        fig.savefig(p, dpi=110); plt.close(fig)
        out.append(p)
    return out


def speed_title(meta: dict) -> str:
    """The spin speed of a run for a title: ``at 327.2 rad/s (3124 rpm)``, or for a run-up
    ``run-up 1000 -> 2000 rad/s (9549 -> 19099 rpm), t 0.02-0.04 s``."""
    rpm = 60 / (2 * np.pi)
    ru = meta.get("run_up")
    if ru:
        w0, w1, t0, t1 = (float(v) for v in ru[:4])
        return f"run-up {w0:.4g} -> {w1:.4g} rad/s ({w0 * rpm:.0f} -> {w1 * rpm:.0f} rpm), t {t0:g}-{t1:g} s"
    w = float(meta.get("speed", 0.0))
    return f"at {w:.1f} rad/s ({w * rpm:.0f} rpm)"


def fault_windows(events, t_end: float | None = None) -> list[dict]:
    """Each scheduled fault's window from ``SimResult.events`` (its start and end events paired
    by the fault's index): ``{index, kind, axis, label, start_s, end_s}``, ``end_s`` None for a
    fault still active at the end of the run (``t_end``, if given, is then its ``until_s``)."""
    out: dict = {}
    for e in events or ():
        k = e.get("index", (e["kind"], e.get("axis")))
        w = out.setdefault(k, {"index": k, "kind": e["kind"], "axis": e.get("axis"), "start_s": None, "end_s": None,
                               "label": e["kind"] + (f" {e['axis']}" if e.get("axis") else "")})
        w["start_s" if e["phase"] == "start" else "end_s"] = float(e["t_s"])
    wins = [w for w in out.values() if w["start_s"] is not None]
    for w in wins:
        w["until_s"] = w["end_s"] if w["end_s"] is not None else t_end
    return sorted(wins, key=lambda w: (w["start_s"], str(w["index"])))


def time_marks(res: SimResult) -> list[dict]:
    """What the time plots mark: every fault's window (from ``res.events`` or the saved meta's
    ``fault_events``) and a run-up's ramp, ``{label, start_s, end_s, kind}`` (end None: to the end)."""
    t_end = float(res.t[-1]) if len(res.t) else None
    marks = [dict(w, kind="fault") for w in fault_windows(res.events or res.meta.get("fault_events"), t_end)]
    ru = res.meta.get("run_up")
    if ru:
        marks.append({"label": "run-up", "start_s": float(ru[2]), "end_s": float(ru[3]), "kind": "run-up"})
    return marks


def _faults_title(marks) -> str:
    n = sum(m["kind"] == "fault" for m in marks)
    return f"\n{n} scheduled fault{'s' if n > 1 else ''}: shaded from start (dashed) to end (dotted)" if n else ""


def _mark_times(ax, marks, labels: bool = True) -> None:
    """Shade each fault's window (red, dashed start, dotted end; to the right edge if it does not
    end) and a run-up's ramp (grey), with its name at the top of the axes."""
    if not marks:
        return
    tr = ax.get_xaxis_transform()
    right = ax.get_xlim()[1]
    for k, m in enumerate(marks):
        fault = m["kind"] == "fault"
        col = "C3" if fault else "0.4"
        t0 = m["start_s"]
        t1 = m["end_s"] if m["end_s"] is not None else right
        ax.axvspan(t0, t1, color=col, alpha=0.08 if fault else 0.06, lw=0, zorder=0)
        ax.axvline(t0, color=col, ls="--", lw=0.9, zorder=1)
        if m["end_s"] is not None:
            ax.axvline(m["end_s"], color=col, ls=":", lw=0.9, zorder=1)
        if labels:
            ax.text(t0, 0.98 - 0.1 * (k % 4), f" {m['label']}" + ("" if m["end_s"] is not None else " (to the end)"),
                    transform=tr, fontsize=7, color="darkred" if fault else "0.3", va="top", ha="left", zorder=5,
                    bbox=dict(fc="white", alpha=0.75, lw=0, pad=0.5))
    ax.set_xlim(right=right)


def _stations(axes) -> dict:
    """{station: [(axis, column), ...]} from ``SimResult.axes`` labels ``"A:x"``."""
    out: dict = {}
    for col, lab in enumerate(axes):
        st, _, axn = str(lab).partition(":")
        out.setdefault(st, []).append((axn, col))
    return out


def _amb_nodes(res: SimResult, stations: dict, gaps: dict):
    """(station, 1-based node) pairs: the meta's AMB nodes when known, else the ``gaps`` (or
    clearances) order."""
    nodes = res.meta.get("amb_nodes")
    if isinstance(nodes, dict):
        return [(st, int(nodes[st])) for st in stations if st in nodes]
    return list(zip(stations, gaps))
