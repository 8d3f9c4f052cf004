"""Scene loading: every validation error path gives one line naming file, key and problem."""
import copy
import subprocess
import sys

import pytest
from loop.scene import SceneError, load_scene, parse_scene
from tests.helpers import BASE, raw


def err(doc):
    with pytest.raises(SceneError) as e:
        parse_scene(doc, "bad.toml")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("bad.toml: ")
    return msg


def amb(**kw):
    d = copy.deepcopy(BASE)
    d["amb"][0].update(kw)
    return d


CASES = [
    (raw(bogus=1), "unknown top-level key 'bogus'"),
    (raw(shaft=[{"length": -1.0, "outer_diameter": 0.05}]), "[[shaft]] #1 key 'length': must be > 0"),
    (raw(shaft=[{"length": 1.0, "outer_diameter": "big"}]), "key 'outer_diameter': must be a number"),
    (raw(shaft=[{"length": 1.0, "outer_diameter": 0.05, "inner_diameter": 0.06}]), "must be < outer_diameter"),
    (raw(shaft=[{"length": 1.0, "outer_diameter": 0.05, "elements": 0}]), "key 'elements': must be >= 1"),
    (raw(shaft=[{"length": 1.0, "outer_diameter": 0.05, "elements": 2.5}]), "key 'elements': must be an integer"),
    (raw(shaft=[{"length": 1.0, "outer_diameter": 0.05, "colour": "red"}]), "key 'colour': unknown key"),
    (raw(shaft=[]), "at least one shaft section"),
    (amb(node=99), "[[amb]] #1 'A' key 'node': node 99 is outside the shaft (nodes 1..21)"),
    (amb(gap=0.0), "'A' key 'gap': must be > 0"),
    (amb(misalignment=[6e-4, 0.0]), "key 'misalignment': offset 0.0006 m must be smaller than the gap"),
    (amb(misalignment=[1e-4]), "key 'misalignment': must be a list of two numbers"),
    (amb(position=0.5), "give either 'node' or 'position'"),
    (amb(pole_angle=95.0), "key 'pole_angle': must be in [0, 90)"),
    (amb(turns=float("nan")), "key 'turns': must be finite"),
    (amb(node=19), "another AMB already sits at node 19"),
    (amb(name="B"), "duplicate AMB name 'B'"),
    (raw(amb=[BASE["amb"][0]]), "at least two radial AMBs"),
    (raw(disc=[{"position": 0.33, "mass": 1.0, "polar_inertia": 0.1, "diametral_inertia": 0.1}]),
     "0.33 m is not at a node (nearest: node 8 at 0.35 m)"),
    (raw(disc=[{"position": 2.0, "mass": 1.0, "polar_inertia": 0.1, "diametral_inertia": 0.1}]),
     "2 m is outside the shaft"),
    (raw(disc=[{"node": 5, "mass": 0.0, "polar_inertia": 0.1, "diametral_inertia": 0.1}]), "key 'mass': must be > 0"),
    (raw(controller={"kp": 1.0, "kd": 1e-3}), "key 'derivative_filter': must be > 0 when kd > 0"),
    (raw(controller={"kp": 1.0, "discretisation": "euler"}), "must be one of tustin, zoh"),
    (raw(controller={"ki": 1.0}), "[controller] key 'kp': is required"),
    ({k: v for k, v in BASE.items() if k != "controller"}, "[controller]: table is required"),
    (raw(speed={"value": 10.0, "range": [0, 100]}), "give either 'value'"),
    (raw(speed={"range": [100.0, 50.0]}), "0 <= start < stop"),
    (raw(model={"rung": "ancf-magic"}), "must be one of rigid, modal, full"),
    (raw(amplifier={"current_limit": 0.1}, amb=[dict(BASE["amb"][0], misalignment=[2e-4, 0.0]), BASE["amb"][1]]),
     "cannot hold AMB 'A' at its misalignment"),
    (raw(analysis={"output_nodes": [0]}), "node 0 is outside the shaft"),
    (raw(analysis={"sweep_amb": "Q"}), "no [[amb]] named 'Q'"),
    (raw(analysis={"sweep_amb": "A"}), "needs at least three"),
    (raw(analysis={"reference_criticals": [10, -1]}), "positive frequencies"),
    (raw(unbalance=[{"node": 3, "magnitude": -1.0}]), "key 'magnitude': must be >= 0"),
    (raw(unbalance={"node": 3}), "must be an array of tables [[unbalance]]"),
    (raw(sensor={"time_constant": -1e-5}), "[sensor] key 'time_constant': must be >= 0"),
    (raw(damping={"stiffness_proportional": True}), "must be a number, got bool"),
]


@pytest.mark.parametrize("doc,fragment", CASES, ids=[c[1][:40] for c in CASES])
def test_validation_errors(doc, fragment):
    assert fragment in err(doc)


def test_file_errors(tmp_path):
    with pytest.raises(SceneError, match="no such scene file"):
        load_scene(tmp_path / "missing.toml")
    p = tmp_path / "broken.toml"
    p.write_text("[scene\nname = 1")
    with pytest.raises(SceneError, match="broken.toml: not valid TOML"):
        load_scene(p)


def test_paper_scenes_load():
    for name in ("paper_2amb", "paper_3amb", "paper_3amb_misaligned"):
        s = load_scene(f"scenes/{name}.toml")
        assert s.plant.n_nodes == 63 and sum(x.elements for x in s.plant.sections) == 62
        assert [a.node + 1 for a in s.plant.ambs] == ([21, 57] if name == "paper_2amb" else [21, 39, 57])
        assert s.plant.unbalances[0].node + 1 == 30 and s.plant.unbalances[0].magnitude == 1e-3
        assert all(a.gap == 1.5e-4 for a in s.plant.ambs)


def test_position_resolves_to_node():
    d = raw(disc=[{"position": 0.35, "mass": 1.0, "polar_inertia": 0.1, "diametral_inertia": 0.1}])
    assert parse_scene(d).plant.discs[0].node == 7


def test_cli_reports_one_line_without_traceback(tmp_path):
    p = tmp_path / "bad.toml"
    text = open("scenes/paper_2amb.toml").read()
    p.write_text(text.replace("gap = 1.5e-4", "gap = 0.0", 1))
    r = subprocess.run([sys.executable, "-m", "bridge.cli", "analyze", str(p)], capture_output=True, text=True)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert "bad.toml" in lines[0] and "'gap'" in lines[0] and "must be > 0" in lines[0]
