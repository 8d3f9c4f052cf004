"""Every path takes a law (`--law FILE.py:CLASS`, `[controller] law`): `simulate` equals the
in-process loop of the same law; a lockstep `ambhil run` over zenoh equals `simulate` bit for
bit; a law that fails at a step ends a run with one line naming the law and the step and the
recording is kept; `test-controller` runs its cases with the law; `replay --to-controller`
checks the law against a recording; the frequency-domain analyses give the one-line reason for
a black box.  The law of these tests is the built-in PID as a user's Python class
(controller/pid_law.py), so every figure is also checked against the built-in law."""
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENE = str(ROOT / "scenes" / "paper_3amb.toml")

LAWS = textwrap.dedent('''
    import numpy as np
    from ambhil.controller.pid_law import PIDLaw


    class MyPID(PIDLaw):
        """The built-in PID, as a user's law."""


    class Louder(PIDLaw):
        """The PID with 5 % more output: another law."""
        def step(self, t, y):
            return 1.05 * super().step(t, y)


    class Breaks(PIDLaw):
        """The PID until step 37, then it raises."""
        def __init__(self, meta):
            self.period = meta.period
            super().__init__(meta)

        def step(self, t, y):
            if round(t / self.period) >= 37:
                raise RuntimeError("boom")
            return super().step(t, y)
''')


def cli(*args, cwd=ROOT, timeout=300):
    return subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd)


def last_json(out: str) -> dict:
    return json.loads([ln for ln in out.splitlines() if ln.startswith("{")][-1])


@pytest.fixture(scope="module")
def laws(tmp_path_factory) -> Path:
    f = tmp_path_factory.mktemp("laws") / "laws.py"
    f.write_text(LAWS)
    return f


@pytest.fixture(scope="module")
def modal():
    from ambhil.loop.system import compile_system
    return compile_system(SCENE, rung="modal")


@pytest.fixture(scope="module")
def law_run(laws, tmp_path_factory):
    """`ambhil run --law laws.py:MyPID`, lockstep, 0.02 s of the modal rung."""
    out = tmp_path_factory.mktemp("run")
    r = cli("run", SCENE, "--rung", "modal", "--duration", "0.02", "--run-id", "lawrun", "--out", str(out),
            "--law", f"{laws}:MyPID", "--json")
    assert r.returncode == 0, r.stdout + r.stderr
    return out / "lawrun.mcap", last_json(r.stdout), r


def test_simulate_with_a_law_equals_the_in_process_loop_and_names_it(laws, modal, tmp_path):
    from ambhil.loop.simulation import simulate
    r = cli("simulate", SCENE, "--rung", "modal", "--duration", "0.02", "--law", f"{laws}:MyPID",
            "--out", str(tmp_path), "--no-record", "--json")
    assert r.returncode == 0, r.stdout + r.stderr
    s = last_json(r.stdout)
    assert s["law"] == "laws.py:MyPID" and s["periods"] == 200
    assert "not computed (the law laws.py:MyPID is a black box" in r.stderr   # no PID precheck
    z = np.load(tmp_path / "simulation.npz")
    res = simulate(modal, 0.02, law=f"{laws}:MyPID")
    assert res.meta["law"] == "laws.py:MyPID"
    assert np.array_equal(z["y"], res.y) and np.array_equal(z["i"], res.i)
    builtin = simulate(modal, 0.02)                  # the PID as a user's law is the built-in law
    assert builtin.meta["law"] == "pid" and np.array_equal(builtin.y, res.y)


def test_simulate_with_a_law_that_raises_is_one_fault_line_and_keeps_its_outputs(laws, tmp_path):
    r = cli("simulate", SCENE, "--rung", "modal", "--duration", "0.02", "--law", f"{laws}:Breaks",
            "--out", str(tmp_path))
    assert r.returncode == 1, r.stdout + r.stderr
    faults = [ln for ln in r.stdout.splitlines() if "FAULT" in ln]
    assert faults == ["  FAULT: law laws.py:Breaks: step 37 (t = 0.0037 s) raised RuntimeError: boom"], r.stdout
    z = np.load(tmp_path / "simulation.npz")
    assert len(z["y"]) == 38                          # the initial sample and the 37 steps done
    from ambhil.bridge.recording.load import load_run
    run = load_run(str(tmp_path / "simulation.mcap"))
    assert run["meta"]["law"] == "laws.py:Breaks" and len(run["sensors"]["v"]) >= 37


def test_lockstep_run_with_a_law_equals_simulate_bit_for_bit(law_run, laws, modal):
    from ambhil.bridge.recording.load import load_run
    from ambhil.loop.simulation import simulate
    mcap, s, r = law_run
    assert s["law"] == "laws.py:MyPID" and s["controller"]["law"] == "laws.py:MyPID"
    assert "(law laws.py:MyPID)" not in r.stdout      # --json: one line; the text says it too (below)
    run = load_run(str(mcap))
    assert run["meta"]["law"] == "laws.py:MyPID" and run["meta"]["law_spec"] == f"{laws}:MyPID"
    res = simulate(modal, 0.02, law=f"{laws}:MyPID")
    assert run["sensors"]["v"].shape == (200, modal.n_axes)
    assert np.array_equal(run["sensors"]["v"], res.y[:200])     # bit for bit
    assert np.array_equal(run["currents"]["v"], res.i[:200])
    assert np.abs(res.y).max() > 1e-7


def test_a_law_that_raises_in_a_run_ends_it_with_one_line_and_the_recording_is_kept(laws, tmp_path):
    from ambhil.bridge.recording.load import load_run
    r = cli("run", SCENE, "--rung", "modal", "--duration", "0.02", "--run-id", "breaks", "--out", str(tmp_path),
            "--law", f"{laws}:Breaks")
    assert r.returncode == 1, r.stdout + r.stderr
    err = [ln for ln in r.stderr.splitlines() if "error:" in ln]
    assert len(err) == 1 and err[0].startswith(
        "ambhil run: error: run failed: controller: law laws.py:Breaks: step 37 (t = 0.0037 s) raised "
        "RuntimeError: boom"), r.stderr
    assert "(law laws.py:Breaks)" in r.stdout
    mcap = tmp_path / "breaks.failed.mcap"
    run = load_run(str(mcap))
    assert len(run["currents"]["v"]) == 37 and len(run["sensors"]["v"]) == 38   # steps 0..36 answered
    assert any("law laws.py:Breaks: step 37" in e.text for e in run["events"] if e.kind_name == "FAULT")


def test_a_law_that_cannot_be_loaded_is_a_user_error_before_anything_starts(laws, tmp_path):
    for spec, what in ((f"{laws}:Nope", "has no 'Nope'"), (str(tmp_path / "none.py:X"), "no such file"),
                       (str(laws), "FILE.py:CLASS")):
        r = cli("run", SCENE, "--rung", "modal", "--duration", "0.01", "--law", spec, "--out", str(tmp_path))
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and what in lines[-1] and lines[-1].startswith("ambhil run: error:"), r.stderr
    assert not list(tmp_path.iterdir())


def test_test_controller_runs_its_cases_with_the_law(laws, tmp_path):
    camp = tmp_path / "camp.toml"
    camp.write_text('[campaign]\nduration = "0.3s"\n\n[[case]]\nname = "blade loss"\n'
                    'faults = ["unbalance_step:at=0.1s,node=30,magnitude=0.0015"]\nmax_orbit_fraction = 0.5\n')
    runs = {}
    for law in (None, "MyPID", "Breaks"):
        r = cli("test-controller", SCENE, "--faults", str(camp), "--rung", "modal", "--json",
                *(["--law", f"{laws}:{law}"] if law else []))
        runs[law] = (r.returncode, last_json(r.stdout), r.stderr)
    (c0, s0, _), (c1, s1, _), (c2, s2, _) = runs[None], runs["MyPID"], runs["Breaks"]
    assert (c0, c1, c2) == (0, 0, 1), runs
    assert s0["law"] == "pid" and s1["law"] == "laws.py:MyPID"
    a, b = s0["results"][0], s1["results"][0]
    assert a["max_orbit_fraction"] == b["max_orbit_fraction"] and a["passed"] and b["passed"]
    fail = s2["results"][0]["failures"]
    assert fail and "law laws.py:Breaks: step 37" in fail[0], fail


def test_replay_to_controller_checks_a_law_against_its_recording(law_run, laws):
    mcap, _, _ = law_run
    ok = cli("replay", str(mcap), "--to-controller", "--scene", SCENE, "--law", f"{laws}:MyPID",
             "--run-id", "lawok")
    assert ok.returncode == 0 and "PASS" in ok.stdout and "(law laws.py:MyPID)" in ok.stdout, ok.stdout + ok.stderr
    assert "largest deviation 0 A" in ok.stdout
    bad = cli("replay", str(mcap), "--to-controller", "--scene", SCENE, "--law", f"{laws}:Louder",
              "--run-id", "lawbad", "--json")
    s = last_json(bad.stdout)
    assert bad.returncode == 1 and not s["passed"] and s["law"] == "laws.py:Louder" and s["max_abs_dev"] > 0
    r = cli("replay", str(mcap), "--to-controller", "--law", f"{laws}:MyPID")
    assert r.returncode == 2 and "needs --scene" in r.stderr


def _scene_with_law(tmp_path: Path, laws: Path) -> Path:
    """paper_3amb with ``[controller] law = "laws.py:MyPID"``, the law beside the scene, in its own folder."""
    d = tmp_path / "scenes"
    d.mkdir()
    (d / "laws.py").write_text(laws.read_text())
    text = Path(SCENE).read_text()
    assert text.count("[controller]") == 1
    f = d / "with_law.toml"
    f.write_text(text.replace("[controller]", '[controller]\nlaw = "laws.py:MyPID"', 1))
    return f


def test_black_box_law_gets_the_one_line_reason_in_the_frequency_domain(laws, tmp_path, modal):
    scene = _scene_with_law(tmp_path, laws)
    r = cli("analyze", str(scene))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and not r.stdout, r.stdout + r.stderr
    assert "analyses are not computed (the law laws.py:MyPID is a black box" in lines[0]
    assert "ambhil simulate" in lines[0]                      # the time-domain alternatives
    r = cli("study", "timing", SCENE, "--law", f"{laws}:MyPID", "--rates", "5k,10k", "--delays", "0,1T")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "timing study is not computed (the law" in lines[0], r.stderr
    from ambhil.loop.simulation import simulate
    res = simulate(modal, 0.01, law=f"{laws}:MyPID", stability_check=True)
    assert res.meta["stability_check"].startswith("not computed (the law laws.py:MyPID is a black box")


def test_a_scene_law_is_relative_to_the_scene_file(laws, tmp_path, modal):
    from ambhil.loop.scene import load_scene
    from ambhil.loop.simulation import simulate
    scene = _scene_with_law(tmp_path, laws)
    assert load_scene(scene).controller.law == f"{scene.parent / 'laws.py'}:MyPID"
    out = tmp_path / "out"
    r = cli("simulate", str(scene), "--rung", "modal", "--duration", "0.02", "--out", str(out), "--no-record",
            "--json")                                # run from the repository root, not the scene's folder
    assert r.returncode == 0, r.stdout + r.stderr
    assert last_json(r.stdout)["law"] == "laws.py:MyPID"
    assert np.array_equal(np.load(out / "simulation.npz")["y"], simulate(modal, 0.02).y)
