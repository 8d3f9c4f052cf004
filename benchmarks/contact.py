"""What auxiliary-bearing contact costs the plant step (issue 32): the same scene's plant step with
its rotor in contact, out of contact, and without auxiliary bearings, in one run so that the ratios
compare; and what the plant process adds per period to publish the contact events.

    .venv/bin/python -m benchmarks.contact [SCENE] [--repeat 7] [--periods 2000]

SCENE (default: scenes/rotor_drop.toml) needs auxiliary bearings and a ``drop`` (or any fault that
puts the rotor on them).  The states are taken from the scene's own closed loop, in process with
the kernels of a HIL plant (plant/faults.py FaultyPlant, the scene's built-in controller):

- ``without auxiliary bearings``: the scene with its ``[amb.auxiliary]`` tables and faults left
  out, levitated (the state 10 ms before the first fault);
- ``out of contact``: the scene with its auxiliary bearings, no faults, the same state;
- ``in contact``: the scene as it is, at the first controller period after the drop that stays in
  contact at every station from start to end (the rotor resting, rolling or whirling on its
  bearings: the contact force, its Jacobian's Woodbury correction and the race speed every step);
- ``in contact, no coast-down`` (a drop with ``coast_down``): the same with the drop's coast-down
  left out (the speed constant, as in the two levitated cases: what the contact costs alone).

Each figure: the state of that period restored and the period integrated again (the compiled
kernel, ``plant.step.bound_kernel(plant_advance)``, currents held) ``--periods`` times; per plant
step, the restore's own cost (timed alone) subtracted; median [min, max] of ``--repeat`` runs, the
cases timed in turn within each repeat (a busy machine's slow seconds fall on all of them).
``kernel``: the plan's path, ``dense`` (a linear step pre-multiplied out, plant/plan.py) or
``banded`` (the implicit step; always with auxiliary bearings).
``contact log``: the plant process's per-period read of the contact state and its events
(bridge/process/plant_contact.py PlantContact.after_period, no events to publish).
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from ambhil.loop.scene import load_scene, with_fault_flags
from ambhil.loop.system import compile_system, controller_runner
from ambhil.plant import integrator as ig
from ambhil.plant import plan as pl
from ambhil.plant.faults import FaultSchedule, FaultyPlant
from ambhil.plant.step import PlantRunner, bound_kernel
from benchmarks import common


def _loop_states(scene, at_steps, find_contact=False, limit_s=1.0):
    """Run the scene's closed loop (FaultyPlant, built-in controller); returns {step: (plan, s, ws,
    currents)} at ``at_steps`` and, with ``find_contact``, under ``"contact"`` the first period (after
    the first fault) that is in contact at every station from its start to its end."""
    m = compile_system(scene)
    fp = FaultyPlant(PlantRunner(m), scene.faults)
    ctrl = controller_runner(m)
    y = np.array(fp.reset())
    ctrl.reset()
    r = fp.runner
    out = {}
    n = int(round(limit_s / fp.period))
    for k in range(n):
        cur = np.array(ctrl.step_shared(y))
        before = (r.plan, r.s.copy(), r.ws.copy(), cur.copy())
        in_before = bool(len(r.contact_names)) and bool(np.all(r.contact[:, ig.C_V0] > 0))
        nev = r.contact[:, ig.C_NEV].copy() if len(r.contact_names) else None
        y = np.array(fp.advance_shared(cur))
        if k in at_steps:
            out[k] = before
        stayed = in_before and np.all(r.contact[:, ig.C_V0] > 0) and np.array_equal(nev, r.contact[:, ig.C_NEV])
        if find_contact and stayed:
            out["contact"] = before
            return out, m, fp
        if fp.status in fp.FATAL:
            raise RuntimeError(f"{scene.path}: the closed loop ended at step {k}: {fp.fault}")
        if not find_contact and k >= max(at_steps):
            return out, m, fp
    if find_contact:
        raise RuntimeError(f"{scene.path}: no period in contact at every station within {limit_s:g} s")
    return out, m, fp


def _period_runner(state, ratio, periods):
    """``(run, restore_only)``: ``periods`` periods integrated from ``state`` = (plan, s, ws,
    currents), the state restored before each (all of ``ws`` but the speed of the factorisation,
    ``W_OMEGA_F``: the plan's ``LU`` stays that of the speed it was last factorised at, as in a run,
    which refactorises a coasting rotor's every 0.2 % of speed, not every period); and the restores
    alone."""
    plan, s0, ws0, cur = state
    s, ws = s0.copy(), ws0.copy()
    keep = np.ones(len(ws), bool)
    keep[ig.W_OMEGA_F] = False
    wk = pl.new_workspace(plan)[0]
    y = np.zeros(int(plan.ip[ig.I_NA]))
    adv = bound_kernel(ig.plant_advance, plan, s, cur, ratio, wk, ws, y)

    def restore_only():
        for _ in range(periods):
            s[:] = s0
            ws[keep] = ws0[keep]

    def run():
        for _ in range(periods):
            s[:] = s0
            ws[keep] = ws0[keep]
            adv(plan, s, cur, ratio, wk, ws, y)
    run()                                   # warm: the first refactorisation, caches
    return run, restore_only


def _per_step(cases, ratio, periods, repeat):
    """Seconds per plant step of each case's state, the cases timed in turn within each repeat (so
    that a busy machine's slow seconds fall on all of them), the restores' own time subtracted."""
    runners = [_period_runner(st, ratio, periods) for _, st, _ in cases]
    out = [[] for _ in cases]
    for _ in range(repeat):
        for i, (run, restore_only) in enumerate(runners):
            base = common.timed(restore_only, 1, warmup=False)[0]
            out[i].append((common.timed(run, 1, warmup=False)[0] - base) / (periods * ratio))
    return out


def _contact_log_cost(fp, periods, repeat):
    """Seconds per period of PlantContact.after_period (no events) on the plant in contact."""
    from ambhil.bridge.process.plant_contact import of

    class _Quiet:
        def emit(self, *a, **k):
            pass
    pc = of(fp, _Quiet(), int(round(fp.period * 1e9)))
    pc.reset()
    pc.after_period()                 # the events of the run so far, once

    def run():
        for _ in range(periods):
            pc.after_period()
    return [t / periods for t in common.timed(run, repeat)]


def main(argv=None) -> int:
    ap = common.parser(__doc__, repeat=7)
    ap.add_argument("scene", nargs="?", default="rotor_drop")
    ap.add_argument("--periods", type=int, default=2000, help="periods integrated per run (default 2000)")
    a = ap.parse_args(argv)
    path = common.scene(a.scene)
    common.header("contact", "the plant step in contact, out of contact, without auxiliary bearings")
    scene = load_scene(path)
    faults = scene.faults.faults
    if not faults:
        raise SystemExit(f"{path}: no fault puts the rotor on its auxiliary bearings")
    T = 1.0 / scene.controller.sample_rate
    k_lev = max(1, faults[0].start_step(T) - int(round(0.01 / T)))
    clean = dataclasses.replace(scene, faults=FaultSchedule())
    bare = clean.with_plant(ambs=tuple(dataclasses.replace(x, auxiliary=None) for x in scene.plant.ambs))
    st_bare, _, fp_bare = _loop_states(bare, {k_lev})
    st_aux, m_aux, _ = _loop_states(clean, {k_lev})
    st_c, _, fp_c = _loop_states(scene, set(), find_contact=True)
    cases = [("without auxiliary bearings", st_bare[k_lev], fp_bare),
             ("auxiliary bearings, out of contact", st_aux[k_lev], fp_bare),
             ("auxiliary bearings, in contact", st_c["contact"], fp_c)]
    drop = [f for f in faults if f.kind == "drop" and f.p("coast_down") is not None]
    if drop:
        f = drop[0]
        spec = f"drop:at={f.start_step(T) * T!r}" + ("" if f.end_step(T) == float("inf") else
                                                      f",until={f.end_step(T) * T!r}")
        still = with_fault_flags(clean, [spec])
        st_n, _, fp_n = _loop_states(still, set(), find_contact=True)
        cases.append(("in contact, no coast-down", st_n["contact"], fp_n))
    ratio = fp_c.ratio
    print(f"# scene {path}: rung {m_aux.rung}, {m_aux.n} coordinates, {fp_c.runner.integrator} h = "
          f"{fp_c.h * 1e6:g} us, {ratio} plant steps per {T * 1e6:g} us period; {a.periods} periods per run, "
          f"median [min, max] of {a.repeat}")
    print(f"# in contact from t = {fp_c.runner.sim_time:g} s (the period measured ends there)")
    rows, ref = [], None
    for (name, state, _), v in zip(cases, _per_step(cases, ratio, a.periods, a.repeat)):
        med = float(np.median(v))
        ref = med if ref is None else ref
        common.report(f"{name}", v, "us per plant step", scale=1e6)
        rows.append([name, common.figure(v, "", scale=1e6), f"{med * ratio * 1e6:.3g}", f"{med / ref:.2f}",
                     "dense" if state[0].ip[ig.I_DENSE] else "banded"])
    lc = _contact_log_cost(fp_c, a.periods, a.repeat)
    common.report("contact log per period (plant process)", lc, "us", scale=1e6)
    common.table(["plant step", "us per plant step", "us per period", "x without auxiliary bearings", "kernel"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
