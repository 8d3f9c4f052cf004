"""The ``drop`` fault (plant/faults.py, loop/scene_faults.py): every AMB axis loses its coils (the
existing loss machinery), the weight share each axis carried becomes a constant force on the rotor
(``f_const = -load``), an optional ``coast_down`` is a speed trip to 0, and the schedule's one-line
refusals.  The physics check: after a drop under gravity the rotor's centre of mass falls freely,
-g t^2/2, until it meets an auxiliary bearing."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ambhil.loop.scene import SceneError, load_scene, with_fault_flags
from ambhil.loop.simulation import simulate
from ambhil.loop.system import compile_system
from ambhil.plant import integrator as ig
from ambhil.plant.faults import FaultyPlant, model_without_axes, plan_parts
from ambhil.plant.params import ParameterError
from ambhil.plant.step import PlantRunner

ROOT = Path(__file__).resolve().parents[1]
SCENE = str(ROOT / "scenes" / "paper_3amb.toml")
DROP_SCENE = ROOT / "scenes" / "rotor_drop.toml"
LOAD = np.array([1.0, 100.0, -2.0, 200.0, 0.0, 50.0])   # N per axis: an operating point under some load


@pytest.fixture(scope="module")
def scene():
    return load_scene(SCENE)


@pytest.fixture(scope="module")
def model(scene):
    """The paper rotor (modal) as if it carried LOAD at its operating point."""
    return replace(compile_system(scene, rung="modal"), load=LOAD)


def plant(model, scene, *specs):
    sc = with_fault_flags(scene, list(specs))
    return FaultyPlant(PlantRunner(model), sc.faults)


# --------------------------------------------------------------------------- the plan
def test_drop_expands_to_the_loss_of_every_axis_and_the_lost_weight_share(model, scene):
    """Within the drop every axis has k_i = k_x = 0 and the force law's constant 0, the constant
    force is -load and the load 0 (so the nonlinear law's remainder does not count it twice); the
    plan is that of losing every AMB with amb_loss; after the drop's end the healthy plan again."""
    fp = plant(model, scene, "drop:at=0.05s,until=0.08s")
    (b0, healthy), (b1, dropped), (b2, back) = fp._segments
    assert (b0, b1, b2) == (0, 500, 800) and back is healthy
    n = model.n_axes
    assert np.array_equal(dropped.ki, np.zeros(n)) and np.array_equal(dropped.kx, np.zeros(n))
    assert np.array_equal(dropped.f0, -LOAD) and np.array_equal(dropped.load, np.zeros(n))
    assert np.array_equal(healthy.f0, np.zeros(n)) and np.array_equal(healthy.load, LOAD)
    assert not np.signbit(dropped.f0[LOAD == 0]).any()      # no -0.0 on an axis that carried nothing
    m = model_without_axes(model, range(n))
    assert np.array_equal(m.force_constant, np.zeros(n)) and np.array_equal(m.constant_forces, -LOAD)
    every = plant(model, scene, "amb_loss:at=0.05s,until=0.08s,axis=A", "amb_loss:at=0.05s,until=0.08s,axis=B",
                  "amb_loss:at=0.05s,until=0.08s,axis=C")._segments[1][1]
    for name in ("Kb", "Sb", "LU", "ki", "kx", "f0", "load", "fp"):
        assert np.array_equal(getattr(dropped, name), getattr(every, name)), name


def test_a_lost_axis_drops_only_its_own_weight_share(model, scene):
    """amb_loss and coil_loss too: f_const = -load on the lost axes only."""
    p = plant(model, scene, "amb_loss:at=0.05s,axis=B")._segments[1][1]
    assert np.array_equal(p.f0, [0, 0, 2.0, -200.0, 0, 0]) and np.array_equal(p.load, [1.0, 100.0, 0, 0, 0.0, 50.0])
    p = plant(model, scene, "coil_loss:at=0.05s,axis=C.y")._segments[1][1]
    assert np.array_equal(p.f0, [0, 0, 0, 0, 0, -50.0])


def test_plan_parts_of_a_drop(scene):
    f = with_fault_flags(scene, ["drop:at=0.1s,until=0.2s,coast_down=2s"]).faults.faults[-1]
    assert (f.kind, f.axes, f.axis, f.params) == ("drop", tuple(range(6)), "all", (("coast_down", 2.0),))
    loss, trip = plan_parts(f, 6)
    assert (loss.kind, loss.axes, loss.start, loss.end) == ("drop", tuple(range(6)), 0.1, 0.2)
    assert (trip.kind, trip.start, trip.end, trip.p("to"), trip.p("over")) == ("speed_trip", 0.1, np.inf, 0.0, 2.0)
    held = replace(f, params=())                   # no coast_down: the loss alone
    assert plan_parts(held, 6) == (held,)


def test_coast_down_is_a_speed_trip_to_zero_that_outlasts_the_drop(model, scene):
    """The spin speed falls linearly from its value at the drop to 0 over coast_down, with a
    continuous phase, and keeps falling after the AMBs come back (the drive stays off)."""
    fp = plant(model, scene, "drop:at=0.1s,until=0.2s,coast_down=0.5s")
    (b0, before), (b1, during), (b2, after) = fp._segments
    assert (b0, b1, b2) == (0, 1000, 2000)
    W = float(before.fp[ig.F_W0])
    th0, W0, _ = ig.speed_at(before.fp, 0.1)
    for p in (during, after):
        th1, W1, _ = ig.speed_at(p.fp, 0.1)
        assert W1 == W0 == W and abs(th1 - th0) < 1e-12 * th0
        assert ig.speed_at(p.fp, 0.35)[1:] == pytest.approx((0.5 * W, -W / 0.5)) and ig.speed_at(p.fp, 0.7)[1] == 0.0
    assert np.array_equal(during.f0, -LOAD) and np.array_equal(after.f0, np.zeros(6))
    still = plant(model, scene, "drop:at=0.1s,until=0.2s")._segments     # no coast_down: the drive holds the speed
    assert all(not p.ip[ig.I_RUNUP] and p.fp[ig.F_W0] == W for _, p in still)


# --------------------------------------------------------------------------- refusals
@pytest.mark.parametrize("spec, needle", [
    ("drop:at=0.1s,axis=A", "drop key 'axis': a drop switches off every AMB axis (A.x, A.y, B.x, B.y, C.x, C.y)"),
    ("drop:at=0.1s,axis=all", "give no axis"),
    ("drop:at=0.1s,coast_down=0", "key 'coast_down': must be > 0 s, got 0"),
    ("drop:at=0.1s,coast_down=-2s", "key 'coast_down': must be > 0 s, got -2"),
    ("drop:at=0.1s,coast_down=slow", "key 'coast_down': must be a time"),
    ("drop:at=0.1s,until=0.05s", "must end after it starts"),
    ("drop:at=0.1s,to=0", "key 'to': unknown key"),
])
def test_bad_drop_specs_are_one_line_errors(scene, spec, needle):
    with pytest.raises(SceneError) as e:
        with_fault_flags(scene, [spec])
    assert needle in str(e.value) and "--fault #1 drop" in str(e.value) and "\n" not in str(e.value), str(e.value)


@pytest.mark.parametrize("specs, needle", [
    (["drop:at=0.1s,coast_down=1s", "speed_trip:at=0.2s"],
     "fault #1 drop coast_down and fault #2 speed_trip both trip the drive"),
    (["speed_trip:at=0.05s,over=0", "drop:at=0.1s,until=0.2s,coast_down=1s"],
     "fault #1 speed_trip and fault #2 drop coast_down both trip the drive"),
    (["drop:at=0.1s,until=0.2s,coast_down=1s", "drop:at=0.3s,coast_down=1s"],
     "fault #1 drop coast_down and fault #2 drop coast_down both trip the drive"),
    (["speed_trip:at=0.1s", "speed_trip:at=0.2s"], "more than one speed_trip"),
])
def test_two_trips_of_the_drive_are_refused(model, scene, specs, needle):
    with pytest.raises(ParameterError) as e:
        plant(model, scene, *specs)
    assert needle in str(e.value) and "\n" not in str(e.value), str(e.value)
    plant(model, scene, "drop:at=0.1s,until=0.2s", "speed_trip:at=0.3s")    # a drop without coast_down: one trip
    plant(model, scene, "drop:at=0.1s,until=0.2s", "drop:at=0.3s,coast_down=1s")


def test_simulate_refuses_a_drop_with_a_speed_trip_in_one_line():
    r = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "simulate", SCENE, "--rung", "modal", "--duration",
                        "0.01", "--fault", "drop:at=0.005s,coast_down=1s", "--fault", "speed_trip:at=0.006s"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "both trip the drive" in r.stderr, r.stderr


# --------------------------------------------------------------------------- events
def test_drop_start_and_end_are_events(scene):
    seen = []
    m = compile_system(with_fault_flags(scene, ["drop:at=0.02s,until=0.0205s,coast_down=3s"]), rung="modal")
    fp = FaultyPlant(PlantRunner(m), m.scene.faults, on_event=lambda k, ns, text: seen.append((k, ns, json.loads(text))))
    for _ in range(220):
        fp.advance(np.asarray(m.i_op))
    start = {"kind": "drop", "axis": "all", "params": {"coast_down": 3.0}, "phase": "start"}
    assert seen == [(200, 20_000_000, start), (205, 20_500_000, {**start, "phase": "end"})]
    r = simulate(m, 0.03)
    assert [(e["kind"], e["phase"], e["step"], e["axis"]) for e in r.events] == \
        [("drop", "start", 200, "all"), ("drop", "end", 205, "all")]


# --------------------------------------------------------------------------- physics
@pytest.fixture(scope="module")
def drop_scene(tmp_path_factory):
    """scenes/rotor_drop.toml without its unbalance: the rotor rests at the operating point, so a
    drop from it is a free fall and nothing else."""
    if not DROP_SCENE.exists():
        pytest.skip("scenes/rotor_drop.toml not there")
    txt = re.sub(r"\[\[unbalance\]\]\n(?:[a-z_]+ = [^\n]*\n)+", "", DROP_SCENE.read_text())
    assert "[[unbalance]]" not in txt and "\ngravity = 9.81 " in txt
    p = tmp_path_factory.mktemp("drop") / "still.toml"
    p.write_text(txt)
    return load_scene(p)


@pytest.mark.parametrize("nonlinear", [False, True])
def test_after_a_drop_the_centre_of_mass_falls_freely(drop_scene, nonlinear):
    """Independent of how the weight is shared between the AMBs: the constant forces -load add up
    to the weight, so the centre of mass (nodal masses of the 21-node shaft, lumped, plus the disc)
    falls as -g t^2/2 until the shaft meets an auxiliary bearing (250 um; here 5 ms, 123 um); the
    force law's remainder (nonlinear) must not count the lost share a second time."""
    m = compile_system(with_fault_flags(drop_scene, ["drop:at=0.01s"]), rung="modal")
    g = 9.81
    assert float(np.sum(m.loads)) > 0
    r = simulate(m, 0.015, nodes=tuple(range(1, 22)), nonlinear=nonlinear)
    assert r.fault is None
    w = np.full(21, 1.0)
    w[0] = w[-1] = 0.5
    w *= 15.3155 / w.sum()                          # steel 1 m x 50 mm
    w[10] += 4.9                                    # the impeller at node 11
    com = r.orbit[:, :, 1] @ w / w.sum()
    i0 = np.searchsorted(r.t, 0.01 - 1e-9)
    assert np.abs(com[:i0 + 1]).max() < 1e-9       # at rest at the operating point before it
    for tt in (0.012, 0.013, 0.015):
        i = np.searchsorted(r.t, tt - 1e-9)
        fall = -0.5 * g * (r.t[i] - 0.01) ** 2
        assert com[i] == pytest.approx(fall, rel=0.01), (tt, com[i], fall)
    assert np.abs(r.orbit[:, :, 0]).max() < 0.01 * abs(com[-1])   # straight down (gyroscopic x: tiny)
