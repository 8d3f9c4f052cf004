"""The compiled model stays immutable and ``step`` stays pure, speed run-ups included.

A run-up refactorises the step matrix as the spin speed drifts; that factorisation belongs to
whoever integrates (a ``PlantState`` in ``step``, a ``PlantRunner``), never to the model nor to
a plan shared between them (issue 29: a run-up used to refactorise the model's default plan in
place, so ``step`` from the same state gave other bits after another run)."""
import tomllib

import numpy as np
import pytest
import scipy.sparse as sp

from ambhil.loop.period_map import physical_loop
from ambhil.loop.scene import parse_scene
from ambhil.loop.simulation import simulate
from ambhil.loop.system import compile_system
from ambhil.plant import integrator as ig
from ambhil.plant.step import PlantRunner, initial, make_plan, plan_for, step
from test_integrator import SCENE, model

RUN_UP = (250.0, 600.0, 0.0, 0.01)  # rad/s from 0 to 10 ms: a refactorisation every few periods


def runup_model(rung="rigid"):
    """The test scene with a [simulation] run-up: its model's default plan refactorises."""
    doc = tomllib.loads(SCENE)
    doc["model"]["rung"] = rung
    doc["simulation"] = {"integrator": "trapezoidal", "run_up": list(RUN_UP[:2]), "run_up_time": list(RUN_UP[2:])}
    return compile_system(parse_scene(doc, "<runup>"))


def arrays(m):
    """Every array a model holds: its fields (a sparse matrix's data, indices and pointers), its
    FE rotor's and its gravity operating point's."""
    out = {}

    def add(name, a):
        if isinstance(a, np.ndarray):
            out[name] = a
        elif sp.issparse(a):
            for part in ("data", "indices", "indptr"):
                if getattr(a, part, None) is not None:
                    out[f"{name}.{part}"] = getattr(a, part)

    for name, value in vars(m).items():
        if name in ("scene", "H", "dense"):
            continue
        add(name, value)
        if name in ("rotor", "gravity") and value is not None:
            for sub, a in vars(value).items():
                add(f"{name}.{sub}", a)
    return out


def snapshot(m) -> dict:
    return {k: (a.dtype.str, a.shape, a.tobytes()) for k, a in arrays(m).items()}


def plan_bytes(p) -> dict:
    return {f: getattr(p, f).tobytes() for f in p._fields}


def currents(m, k):
    return np.array(m.i_op) + 0.02 * np.sin(0.3 * k + np.arange(m.n_axes))


@pytest.mark.parametrize("rung", ["rigid", "full"])
def test_model_arrays_are_read_only_and_it_holds_no_cache(rung):
    m = model(rung)
    got = arrays(m)
    assert {"M.data" if rung == "full" else "M", "K_eff.data" if rung == "full" else "K_eff", "i_op", "ki",
            "rotor.M.data", "rotor.node_z"} <= set(got)
    writable = [k for k, a in got.items() if a.flags.writeable]
    assert writable == []
    with pytest.raises(ValueError):
        m.ki[0] = 1.0
    # nothing mutable besides: no dict or list field (the old model.extras cache)
    assert not [k for k, v in vars(m).items() if isinstance(v, (dict, list, set))]


def test_step_through_a_run_up_leaves_the_model_and_its_default_plan_unchanged():
    m = runup_model()
    before = snapshot(m)
    plan = plan_for(m)
    assert plan.ip[ig.I_RUNUP] == 1
    p0 = plan_bytes(plan)
    st = initial(m)
    for k in range(150):
        st, _ = step(m, st, currents(m, k))
    assert st.ws[ig.W_NREFAC] > 0  # the run-up did refactorise (in the state's own factorisation)
    assert plan_for(m) is plan and plan_bytes(plan) == p0
    assert snapshot(m) == before


def test_step_twice_from_the_same_state_gives_the_same_bits():
    m = runup_model()
    st0 = initial(m)
    cur = currents(m, 0)
    a, ya = step(m, st0, cur)
    st = st0
    for k in range(120):  # a run-up in between: refactorisations at higher speeds
        st, _ = step(m, st, currents(m, k))
    mid = st.copy()
    b, yb = step(m, st0, cur)
    assert np.array_equal(ya, yb) and np.array_equal(a.s, b.s) and np.array_equal(a.ws, b.ws)
    # from a state in the middle of the run-up, before and after other steps
    c, yc = step(m, mid, cur)
    for k in range(40):
        step(m, initial(m), currents(m, k))
        st, _ = step(m, st, currents(m, k))
    d, yd = step(m, mid, cur)
    assert np.array_equal(yc, yd) and np.array_equal(c.s, d.s) and np.array_equal(c.LU, d.LU)
    assert not np.array_equal(mid.s, st0.s) and mid.LU is not None


def test_step_with_out_reuses_the_state_and_matches_the_runner():
    m = runup_model()
    st = initial(m)
    out = st.copy()
    runner = PlantRunner(m)
    assert runner.ratio == 1  # step() is one plant step, the runner one period
    for k in range(60):
        cur = currents(m, k)
        st2, y = step(m, st, cur, out=out if k % 2 else None)
        assert np.array_equal(runner.advance(cur), y) and np.array_equal(runner.s, st2.s)
        st = st2.copy()


def test_a_runners_run_up_does_not_touch_the_shared_plan_or_another_runner():
    m = runup_model()
    plan = make_plan(m)
    p0 = plan_bytes(plan)
    before = snapshot(m)
    a, b = PlantRunner(m, plan=plan), PlantRunner(m, plan=plan)
    ref = [b.advance(currents(m, k)).copy() for k in range(80)]
    b.reset()
    for k in range(150):
        a.advance(currents(m, k))
    assert a.ws[ig.W_NREFAC] > 0
    got = [b.advance(currents(m, k)).copy() for k in range(80)]
    assert np.array_equal(np.array(ref), np.array(got))
    a.reset()
    again = [a.advance(currents(m, k)).copy() for k in range(80)]
    assert np.array_equal(np.array(ref), np.array(again))
    assert plan_bytes(plan) == p0 and snapshot(m) == before


def test_simulate_a_run_up_leaves_the_model_unchanged():
    m = runup_model()
    before = snapshot(m)
    st0 = initial(m)
    s1, y1 = step(m, st0, currents(m, 0))
    res = simulate(m, 0.02, None, run_up=RUN_UP, integrator="trapezoidal")
    assert res.meta["refactorisations"] > 0
    assert snapshot(m) == before
    s2, y2 = step(m, st0, currents(m, 0))
    assert np.array_equal(y1, y2) and np.array_equal(s1.s, s2.s)
    res2 = simulate(m, 0.02, None, run_up=RUN_UP, integrator="trapezoidal")
    assert np.array_equal(res.y, res2.y) and np.array_equal(res.i, res2.i)


def test_physical_loop_is_cached_beside_the_model_not_in_it():
    m = model("rigid")
    before, keys = snapshot(m), set(vars(m)) - {"dense"}
    ex = physical_loop(m, speed=300.0)
    assert physical_loop(m, speed=300.0) is ex
    assert physical_loop(m, speed=310.0) is not ex
    assert snapshot(m) == before and set(vars(m)) - {"dense"} == keys
