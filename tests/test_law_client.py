"""The thin client (bridge/process/law_client.py, examples/thin_client/my_controller.py): a law in
a process of its own, made from the plant's RunMeta alone, answers as ``ambhil controller`` does.

- in process: the runner made from a RunMeta (through JSON, as it travels) steps bit for bit like
  the scene's own controller (the fused kernel; a slew-limited amplifier and [controller.params]
  come through); the example's numpy PID is the built-in law bit for bit in ``simulate``;
- over zenoh (lockstep, modal rung, scenes/paper_3amb_misaligned.toml: one axis preloaded): the
  docs' walk-through (``ambhil plant`` + the example + ``ambhil record`` over TCP) and ``ambhil run
  --controller`` (Unix sockets, two endpoints) both with a scheduled controller restart, give the
  currents and displacements of ``ambhil run`` with the built-in controller bit for bit; the
  conformance command passes the example on a saturating recording with a 2-sample delay; a law
  that raises ends the run with the one line naming it and the step.

No wall-clock assertions: lockstep runs are deterministic however busy the machine is.
"""
import json
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ambhil.bridge.cli.run_setup import run_meta
from ambhil.bridge.process.law_client import runner_from_meta
from ambhil.controller.law import LawError
from ambhil.controller.law_loader import resolve
from ambhil.controller.pid_law import PIDLaw
from ambhil.loop.scene import load_scene
from ambhil.loop.simulation import simulate
from ambhil.loop.system import compile_system, controller_runner
from test_controllers import cli, spawn

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "paper_3amb_misaligned.toml"
EXAMPLE = ROOT / "examples" / "thin_client" / "my_controller.py"
DURATION, STEPS = "0.03", 300
RESTART = ["--fault", "controller_restart:at=0.01s"]       # a controller reset before step 100


def _meta_of(scene_path):
    """RunMeta's JSON object for ``scene_path`` at the modal rung, as a controller receives it."""
    scene = load_scene(str(scene_path))
    model = compile_system(scene, rung="modal")
    return scene, model, json.loads(json.dumps(run_meta(scene, model), allow_nan=False))


def _displacements(n_axes, n=3000):
    rng = np.random.default_rng(3)          # up to 300 um: into the 4 A limit and back
    return np.clip(np.cumsum(rng.normal(0, 2e-5, (n, n_axes)), axis=0), -3e-4, 3e-4)


# --------------------------------------------------------------------------- in process
def test_the_runner_made_from_runmeta_is_the_scenes_controller():
    scene, model, info = _meta_of(SCENE)
    mine, ref = runner_from_meta(PIDLaw, info, "pid"), controller_runner(model)
    assert type(ref).__name__ == "ControllerRunner"                    # the fused kernel
    assert mine.meta.axes == ("A-x", "A-y", "B-x", "B-y", "C-x", "C-y") and mine.meta.period == 1e-4
    assert mine.meta.i_op[3] == info["controller"]["i_op"][3] > 1.0
    sat = 0
    for y in _displacements(6):
        assert np.array_equal(mine.step(y), ref.step(y))               # bit for bit, every sample
        sat += ref.saturated
    assert sat > 100


def test_slew_limit_and_law_params_come_through_runmeta(tmp_path):
    text = SCENE.read_text().replace("current_limit = 4.0", "current_limit = 4.0\nslew_rate = 2000.0")
    text += "\n[controller.params]\nnotch_hz = 212.0\n"
    (tmp_path / "s.toml").write_text(text)
    scene, model, info = _meta_of(tmp_path / "s.toml")
    mine, ref = runner_from_meta(PIDLaw, info, "pid"), controller_runner(model)
    assert type(ref).__name__ == "LawRunner"                           # slew: the law path
    assert mine.config.amplifier.slew_rate == 2000.0 and mine.meta.params == {"notch_hz": 212.0}
    assert mine.meta.controller == ref.meta.controller
    assert all(np.array_equal(mine.step(y), ref.step(y)) for y in _displacements(6, 1000))


def test_a_runmeta_without_the_controller_is_named():
    _, _, info = _meta_of(SCENE)
    del info["controller"]["continuous"]
    with pytest.raises(LawError, match=r"^law pid: RunMeta has no controller.continuous"):
        runner_from_meta(PIDLaw, info, "pid")
    info = _meta_of(SCENE)[2]
    info["axis_names"] = info["axis_names"][:4]
    with pytest.raises(LawError, match="do not match controller.i_op"):
        runner_from_meta(PIDLaw, info, "pid")


def test_the_example_law_is_the_builtin_pid():
    model = compile_system(SCENE, rung="modal")
    a = simulate(model, 0.1)
    b = simulate(model, 0.1, law=resolve(f"{EXAMPLE}:MyLaw"))
    assert a.fault is None and b.fault is None and b.steps == 1000
    assert np.array_equal(a.i, b.i) and np.array_equal(a.y, b.y)      # bit for bit


# --------------------------------------------------------------------------- over zenoh
def _load(path):
    from ambhil.bridge.recording.load import load_run
    return load_run(str(path))


def _assert_same_run(ref, mine):
    assert ref["currents"]["v"].shape == mine["currents"]["v"].shape == (STEPS, 6)
    assert np.array_equal(ref["currents"]["seq"], mine["currents"]["seq"])
    assert np.array_equal(ref["currents"]["v"], mine["currents"]["v"])         # bit for bit
    assert np.array_equal(ref["sensors"]["v"], mine["sensors"]["v"])
    restarts = [(e.source, e.step) for e in mine["events"] if "controller restarted" in e.text]
    assert restarts == [("controller", 100)]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """`ambhil run` with the built-in controller and a controller restart."""
    d = tmp_path_factory.mktemp("ref")
    r = cli("run", str(SCENE), "--duration", DURATION, "--rung", "modal", "--run-id", "ref",
            "--out", str(d), *RESTART)
    assert r.returncode == 0, r.stdout + r.stderr
    return _load(d / "ref.mcap")


def test_walkthrough_plant_example_and_recorder_equal_the_builtin_run(reference, tmp_path):
    """docs/controllers.md, "A controller in its own process": three terminals over TCP."""
    from ambhil.bridge.process.transport import free_port, tcp_endpoint
    ep, ep_r = tcp_endpoint(free_port()), tcp_endpoint(free_port())
    py = [sys.executable, "-m", "ambhil.bridge.cli"]
    procs = {"plant": spawn(py + ["plant", str(SCENE), "--run-id", "thin", "--listen", ep, "--connect", ep_r,
                                  "--duration", DURATION, "--rung", "modal", "--wait-recorder", *RESTART]),
             "controller": spawn([sys.executable, str(EXAMPLE), "--run-id", "thin", "--connect", ep, ep_r]),
             "recorder": spawn(py + ["record", "--run-id", "thin", "--listen", ep_r, "--out", str(tmp_path)])}
    outs = {}
    try:
        for name, p in procs.items():
            outs[name] = p.communicate(timeout=600) + (p.returncode,)
    finally:
        for p in procs.values():
            p.kill()
    for name, (o, e, code) in outs.items():
        assert code == 0, f"{name}: {o}\n{e}"
    assert f"my_controller: {STEPS} samples answered; fault: None" in outs["controller"][0]
    assert "controller: RunMeta: 6 axes at 10000 Hz" in outs["controller"][1]
    _assert_same_run(reference, _load(tmp_path / "thin.mcap"))


def test_ambhil_run_with_the_example_as_controller_equals_the_builtin_run(reference, tmp_path):
    cmd = f"{shlex.quote(sys.executable)} {shlex.quote(str(EXAMPLE))} --run-id {{run_id}} --connect {{connect}}"
    r = cli("run", str(SCENE), "--duration", DURATION, "--rung", "modal", "--run-id", "thin-run",
            "--out", str(tmp_path), *RESTART, "--controller", cmd)
    assert r.returncode == 0, r.stdout + r.stderr
    _assert_same_run(reference, _load(tmp_path / "thin-run.mcap"))


def test_conformance_passes_the_example_bit_for_bit_through_saturation_and_delay(hard_recording):
    mcap, _ = hard_recording
    rec = _load(mcap)
    assert rec["meta"]["controller"]["delay_samples"] == 2
    assert (np.abs(rec["currents"]["v"]) == 1.4).sum() > 10            # the run saturated
    cmd = f"{shlex.quote(sys.executable)} {shlex.quote(str(EXAMPLE))} --run-id {{run_id}} --connect {{connect}}"
    r = cli("replay", str(mcap), "--to-controller", "--controller-cmd", cmd, "--run-id", "conf-thin", "--json")
    assert r.returncode == 0, r.stdout + r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["passed"] and res["compared"] == len(rec["currents"]["seq"]) > 0
    assert all(a["max_abs_dev"] == 0.0 for a in res["axes"])
    assert res["controller_exit"]["exit_code"] == 0


BAD = """
import numpy as np

class Bad:
    def __init__(self, meta):
        self.u_op = np.array(meta.u_op)
    def step(self, t, y):
        if t > 4e-4:
            raise RuntimeError("boom")
        return self.u_op - 2.0 * y
"""
SERVE = """
import sys
from ambhil.bridge.process.law_client import serve
s = serve(sys.argv[2], run_id="bad", connect=sys.argv[1])
print("FAULT:", s["fault"])
sys.exit(1 if s["fault"] else 0)
"""


def test_a_law_that_raises_ends_the_run_with_its_one_line(tmp_path):
    """The law named as FILE.py:CLASS (serve's other form); it raises at step 5."""
    from ambhil.bridge.process.transport import free_port, tcp_endpoint
    (tmp_path / "bad.py").write_text(BAD)
    (tmp_path / "serve.py").write_text(SERVE)
    ep = tcp_endpoint(free_port())
    plant = spawn([sys.executable, "-m", "ambhil.bridge.cli", "plant", str(SCENE), "--run-id", "bad", "--listen",
                   ep, "--duration", DURATION, "--rung", "modal", "--json"])
    ctl = subprocess.run([sys.executable, str(tmp_path / "serve.py"), ep, "bad.py:Bad"], capture_output=True,
                         text=True, timeout=600, cwd=tmp_path)
    p_out, p_err = plant.communicate(timeout=600)
    line = "law bad.py:Bad: step 5 (t = 0.0005 s) raised RuntimeError: boom"
    assert ctl.returncode == 1 and f"FAULT: {line}\n" in ctl.stdout, ctl.stdout + ctl.stderr
    s = json.loads(p_out.strip().splitlines()[-1])
    assert plant.returncode == 1 and s["steps"] == 5 and s["fault"], p_out + p_err


def test_the_docs_show_the_example_as_it_is():
    """docs/controllers.md's block of the thin client is the example's own lines."""
    doc = (ROOT / "docs" / "controllers.md").read_text()
    block = doc.split("## A controller in its own process", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    example = EXAMPLE.read_text()
    assert all(line in example for line in block.splitlines() if line.strip())
