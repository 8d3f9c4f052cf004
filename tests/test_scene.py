"""Scene loading: every validation error path gives one line naming file, key and problem."""
import copy
import subprocess
import sys

import pytest
from ambhil.loop.scene import SceneError, load_scene, parse_scene
from helpers import BASE, raw


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
    (amb(touchdown_clearance=5e-4), "[[amb]] #1 'A' key 'touchdown_clearance': 0.0005 m must be smaller than "
                                    "this AMB's magnetic gap 0.0005 m"),
    (amb(touchdown_clearance=-1e-5), "[[amb]] #1 'A' key 'touchdown_clearance': must be > 0"),
    (amb(touchdown_clearance="75um"), "[[amb]] #1 'A' key 'touchdown_clearance': must be a number"),
    (raw(analysis={"touchdown_clearance": 6e-4}), "[analysis] key 'touchdown_clearance': 0.0006 m (the default of "
                                                  "every [[amb]] without its own) must be smaller than the magnetic gap "
                                                  "0.0005 m of AMB 'A'"),
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


def test_touchdown_clearance_per_amb_with_the_scene_default():
    """Each AMB's own touchdown_clearance wins; [analysis] touchdown_clearance is the default of
    the others; with neither, half the magnetic gap, marked as not given."""
    plain = parse_scene(raw())
    assert [(a.touchdown_clearance, a.clearance) for a in plain.plant.ambs] == [(None, 2.5e-4)] * 2
    d = amb(touchdown_clearance=1e-4)
    s = parse_scene(d)
    assert [(a.touchdown_clearance, a.clearance) for a in s.plant.ambs] == [(1e-4, 1e-4), (None, 2.5e-4)]
    d["analysis"] = {"touchdown_clearance": 2e-4}
    s = parse_scene(d)
    assert [(a.touchdown_clearance, a.clearance) for a in s.plant.ambs] == [(1e-4, 1e-4), (2e-4, 2e-4)]
    d["amb"][0]["touchdown_clearance"] = 4.9e-4          # A's own may exceed the default, below its gap
    d["analysis"] = {"touchdown_clearance": 4.99e-4}
    assert [a.clearance for a in parse_scene(d).plant.ambs] == [4.9e-4, 4.99e-4]
    for name in ("paper_2amb", "paper_3amb", "paper_3amb_misaligned", "paper_3amb_fast_runup"):
        assert all(a.touchdown_clearance == 7.5e-5 for a in load_scene(f"scenes/{name}.toml").plant.ambs), name


def test_position_resolves_to_node():
    d = raw(disc=[{"position": 0.35, "mass": 1.0, "polar_inertia": 0.1, "diametral_inertia": 0.1}])
    assert parse_scene(d).plant.discs[0].node == 7


def test_cli_reports_one_line_without_traceback(tmp_path):
    p = tmp_path / "bad.toml"
    text = open("scenes/paper_2amb.toml").read()
    p.write_text(text.replace("gap = 1.5e-4", "gap = 0.0", 1))
    r = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "analyze", str(p)], capture_output=True, text=True)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert "bad.toml" in lines[0] and "'gap'" in lines[0] and "must be > 0" in lines[0]


# --------------------------------------------------------------------------- bad files (issue 10 item 5)
PAPER = open("scenes/paper_2amb.toml", encoding="utf-8").read()


def load_err(tmp_path, data: bytes, name="bad.toml"):
    p = tmp_path / name
    p.write_bytes(data)
    with pytest.raises(SceneError) as e:
        load_scene(p)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{p}: ") and len(msg) < 400, msg
    return msg


def test_non_utf8_names_the_byte_and_where(tmp_path):
    text = PAPER.replace("# Su et al.", "# Su et al. caf\xe9", 1)
    msg = load_err(tmp_path, text.encode("latin-1"))
    off = text.index("\xe9")
    assert f"not UTF-8 text: byte 0xE9 at line 1, column {off + 1} (byte offset {off})" in msg
    lines = PAPER.splitlines(keepends=True)
    data = "".join(lines[:40]).encode() + b"x = \xff\n" + "".join(lines[40:]).encode()
    assert "byte 0xFF at line 41, column 5 (byte offset" in load_err(tmp_path, data)


def test_byte_order_marks(tmp_path):
    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf" + PAPER.encode())  # UTF-8 with a BOM (Notepad): accepted
    assert load_scene(p).name == "paper_2amb"
    assert "is UTF-16 text (byte order mark at byte 0); save it as UTF-8" in load_err(tmp_path, PAPER.encode("utf-16"))
    assert "is UTF-32 text" in load_err(tmp_path, PAPER.encode("utf-32"))


def test_absurd_nesting_and_size(tmp_path):
    deep = PAPER.replace("output_nodes = [21, 30, 57]\n", "output_nodes = " + "[" * 5000 + "]" * 5000 + "\n", 1)
    msg = load_err(tmp_path, deep.encode())  # was a RecursionError
    assert "nested too deeply (line " in msg
    assert "larger than 16 KiB" in load_err(tmp_path, PAPER.encode() + b"#" * (16 << 10))
    shallow = PAPER.replace("output_nodes = [21, 30, 57]", "output_nodes = " + "[" * 300 + "]" * 300, 1)
    assert "must be a list of node numbers, got [[[...]]]" in load_err(tmp_path, shallow.encode())


@pytest.mark.parametrize("value,fragment", [
    ("1" + "0" * 400, "key 'kp': 100000000000000000...0000000000000000000 is out of range"),  # was OverflowError
    ("1e300", "key 'kp': 1e+300 is out of range (|value| from 1e-18 to 1e+18"),
    ("1e-300", "key 'kp': 1e-300 is out of range"),
    ("-" + "9" * 40, "key 'kp': must be > 0, got -99999"),
])
def test_numbers_out_of_range(tmp_path, value, fragment):
    assert fragment in load_err(tmp_path, PAPER.replace("kp = 5.98869", f"kp = {value}", 1).encode())


def test_size_limits():
    assert "'elements': must be <= 1000" in err(raw(shaft=[{"length": 1.0, "outer_diameter": 0.05, "elements": 10**7}]))
    two = [{"length": 1.0, "outer_diameter": 0.05, "elements": 600}] * 2
    assert "#2 key 'elements': the shaft has 1200 elements in all" in err(raw(shaft=two))
    assert "'points': must be <= 10000" in err(raw(speed={"value": 1.0, "points": 10**10}))
    assert "'delay_samples': must be <= 10000" in err(raw(controller={"kp": 1.0, "delay_samples": 10**12}))
    assert "'sample_rate': must be <= 1e+06 Hz" in err(raw(controller={"kp": 1.0, "sample_rate": 1e9}))
    assert "'stiffness_proportional': must be <= 1 s" in err(raw(damping={"stiffness_proportional": 1e12}))
    assert "[simulation] key 'output_nodes': node 5 is listed twice" in err(raw(simulation={"output_nodes": [5, 5]}))
    assert "'misalignment': [1] must be finite" in err(amb(misalignment=[0.0, float("inf")]))


def test_scene_names_fit_run_ids(tmp_path):
    for bad in ("a/b", "run*1", "", "two words", "x" * 49):
        assert "key 'name': must be 1 to 48 characters" in err(raw(scene={"name": bad}))
    p = tmp_path / "my scene#1.toml"  # the default, the file stem, is made to fit
    p.write_text(PAPER.replace('name = "paper_2amb"\n', "", 1))
    assert load_scene(p).name == "my_scene_1"


def test_misspelled_keys_are_named():
    assert "key 'gap': is required (found 'gpa': misspelled?)" in err(
        raw(amb=[{k if k != "gap" else "gpa": v for k, v in BASE["amb"][0].items()}, BASE["amb"][1]]))
    assert "key 'Kp': unknown key (did you mean 'kp'?)" in err(raw(controller={"kp": 1.0, "Kp": 2.0}))
    assert "unknown top-level key 'controler' (did you mean 'controller'?)" in err(raw(controler={}))


def test_step_is_checked_where_it_is_used(tmp_path):
    """A [simulation] step that does not divide the controller period loads (analyses do not use
    it); the time-domain plant refuses it naming the file and key, unless h is overridden."""
    from ambhil.loop.system import compile_system
    from ambhil.plant.params import ParameterError
    from ambhil.plant.run_options import RunOptions
    from ambhil.plant.step import PlantRunner
    p = tmp_path / "step.toml"
    p.write_text(PAPER.replace("step = 1.0e-4", "step = 3e-5", 1))
    scene = load_scene(p)
    assert scene.plant.simulation.step == 3e-5
    model = compile_system(scene, rung="rigid")
    with pytest.raises(ParameterError) as e:
        PlantRunner(model)
    assert str(e.value) == (f"{p}: [simulation] key 'step': controller period 0.0001 s is not an integer "
                            f"multiple of the plant step 3e-05 s")
    assert PlantRunner(model, RunOptions(h=5e-5)).ratio == 2  # the override makes the scene consistent
    with pytest.raises(ParameterError, match=r"^controller period 0.0001 s is not an integer multiple of the plant step"):
        PlantRunner(model, RunOptions(h=7e-5))  # a bad override is the option's fault, not the file's


def test_cli_step_override(tmp_path, capsys):
    """analyze ignores the step; simulate refuses it but takes --h; run refuses it before it
    starts any process (in-process CLI; run's processes are not reached)."""
    from ambhil.bridge.cli import main as cli
    p = tmp_path / "step.toml"
    p.write_text(PAPER.replace("step = 1.0e-4", "step = 3e-5", 1).replace('rung = "full"', 'rung = "rigid"', 1))
    out = str(tmp_path / "o")
    assert cli.main(["simulate", str(p), "--out", out, "--duration", "1e-3"]) == 2
    assert "[simulation] key 'step'" in capsys.readouterr().err
    assert cli.main(["simulate", str(p), "--out", out, "--duration", "1e-3", "--h", "5e-5"]) == 0
    assert "h=5e-05 s" in capsys.readouterr().out
    run_out = tmp_path / "run"            # simulate's own recording is in `out`
    assert cli.main(["run", str(p), "--duration", "1e-3", "--out", str(run_out)]) == 2
    assert "[simulation] key 'step'" in capsys.readouterr().err
    assert not list(run_out.glob("*.mcap")) and (tmp_path / "o" / "simulation.mcap").exists()
