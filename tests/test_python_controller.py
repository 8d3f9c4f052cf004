"""The example Python controller (examples/python_controller/controller.py): written from
docs/protocol.md and docs/controllers.md alone, standalone (zenoh only, nothing imported from
this project), it must reproduce the built-in controller bit for bit.

- the walk-through of docs/controllers.md (`ambhil plant` + the controller + `ambhil record`,
  lockstep, 300 steps, modal rung): the very currents and displacements of a built-in run;
- `ambhil run --controller CMD` with a scheduled controller restart (Unix-domain sockets, the
  `{connect}` placeholder expanding to two endpoints): same currents as the built-in run;
- the conformance command on a run that saturates through a 2-sample controller delay;
- protocol 3 (docs/protocol.md 5.3): two strangers posing as plants are refused; against a plant
  played by hand (with and without a key) it pairs by the challenge and the RunMeta MAC, answers
  bit for bit and rejects what a stranger forges.

No wall-clock assertions: lockstep runs are deterministic however busy the machine is.
"""
import json
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# the process helpers of the Rust example's tests (no cargo here); the saturating recording both
# use, hard_recording, is a session fixture in conftest.py
from test_controllers import SCENE, check_scripted_run, cli, run_three, scripted_plant, strangers_refused

ROOT = Path(__file__).resolve().parents[1]
CTL = ROOT / "examples" / "python_controller" / "controller.py"
STEPS = 300
DURATION = "0.03"                                       # 300 steps at 10 kHz


def _load(path):
    from ambhil.bridge.recording.load import load_run
    return load_run(str(path))


def _assert_same_run(ref, mine):
    assert mine["meta"]["controller"] == ref["meta"]["controller"]
    assert ref["currents"]["v"].shape == mine["currents"]["v"].shape == (STEPS, 6)
    assert np.array_equal(ref["currents"]["seq"], mine["currents"]["seq"])
    assert np.array_equal(ref["currents"]["v"], mine["currents"]["v"])          # bit for bit
    assert np.array_equal(ref["sensors"]["v"], mine["sensors"]["v"])


def test_controller_imports_nothing_from_the_project():
    import ast
    tree = ast.parse(CTL.read_text())
    mods = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    mods |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert not mods & {"plant", "controller", "loop", "bridge", "tests"}, mods
    assert "zenoh" in mods


def test_python_controller_run_equals_builtin_run(tmp_path):
    ref = cli("run", str(SCENE), "--duration", DURATION, "--rung", "modal", "--run-id", "ref",
              "--out", str(tmp_path))
    assert ref.returncode == 0, ref.stdout + ref.stderr
    mcap, outs = run_three(SCENE, "py", tmp_path,
                           [sys.executable, str(CTL), "--run-id", "py", "--connect", "{connect}",
                            "--connect", "{recorder}"], duration=DURATION)
    for name in ("plant", "controller", "recorder"):
        o, e, code = outs[name]
        assert code == 0, f"{name}: {o}\n{e}"
    assert "run completed" in outs["recorder"][0], outs["recorder"]
    assert f"{STEPS} samples answered, 0 duplicates, 0 missing, 0 rejected" in outs["controller"][1]
    a, b = _load(tmp_path / "ref.mcap"), _load(mcap)
    _assert_same_run(a, b)
    i_op = a["meta"]["controller"]["i_op"]
    assert abs(i_op[3]) > 1.0                                      # the preload path is taken
    assert np.abs(a["currents"]["v"][:, 3] - i_op[3]).max() > 1e-3  # and the loop moved


def test_python_controller_restart_via_ambhil_run(tmp_path):
    """`ambhil run --controller`: placeholders, the run's own transport, FAULT_INJECTED
    controller_restart (state reset as at start-up before step 100)."""
    fault = ["--fault", "controller_restart:at=0.01s"]
    common = [str(SCENE), "--duration", DURATION, "--rung", "modal", "--out", str(tmp_path)] + fault
    ref = cli("run", *common, "--run-id", "ref-r")
    assert ref.returncode == 0, ref.stdout + ref.stderr
    cmd = f"{shlex.quote(sys.executable)} {shlex.quote(str(CTL))} --run-id {{run_id}} --connect {{connect}}"
    mine = cli("run", *common, "--run-id", "py-r", "--controller", cmd)
    assert mine.returncode == 0, mine.stdout + mine.stderr
    a, b = _load(tmp_path / "ref-r.mcap"), _load(tmp_path / "py-r.mcap")
    _assert_same_run(a, b)
    restarts = [(e.source, e.step) for e in b["events"] if "controller restarted" in e.text]
    assert restarts == [("controller", 100)], [e for e in b["events"] if e.source == "controller"]


def test_conformance_command_passes_python_controller_bit_for_bit(hard_recording):
    mcap, _ = hard_recording
    rec = _load(mcap)
    assert rec["meta"]["controller"]["delay_samples"] == 2
    assert (np.abs(rec["currents"]["v"]) == 1.4).sum() > 10          # the run saturated
    cmd = f"{shlex.quote(sys.executable)} {shlex.quote(str(CTL))} --run-id {{run_id}} --connect {{connect}}"
    r = cli("replay", str(mcap), "--to-controller", "--controller-cmd", cmd, "--run-id", "conf-py", "--json")
    assert r.returncode == 0, r.stdout + r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["passed"] and res["compared"] == len(rec["currents"]["seq"]) > 0
    assert all(a["max_abs_dev"] == 0.0 for a in res["axes"])
    assert res["controller_exit"]["exit_code"] == 0


def test_python_controller_refuses_two_plants():
    """Two strangers' plant tokens and forged RunMeta: neither pairs (protocol 3, §5.3)."""
    code, out = strangers_refused([sys.executable, str(CTL), "--run-id", "two-py", "--connect", "{connect}"],
                                  "two-py")
    assert code == 1, out
    for i in ("11" * 16, "22" * 16):
        assert f"stranger {i} sent a RunMeta that fails the pairing proof (no key)" in out, out
    assert '{"auth": 2}' in out and "plant lost (liveliness) while starting" in out, out


@pytest.mark.parametrize("secret", [None, bytes(range(32, 64))], ids=["unauthenticated", "key"])
def test_python_controller_against_a_scripted_plant(tmp_path, secret):
    """The example against a plant played by hand (tests/test_controllers.py scripted_plant):
    the challenge, the RunMeta pairing, sealed samples and replies bit for bit, a stranger's
    RunMeta, a forged sample, a forged RUN_END and a replayed event rejected, a forged jump in
    an unauthenticated run answered once without stalling the genuine stream."""
    code, out, rejected = scripted_plant([sys.executable, str(CTL), "--run-id", "scr-py", "--connect", "{connect}"],
                                         "scr-py", tmp_path, secret)
    check_scripted_run(code, out, rejected, secret)


FAKE_DIES_AT_PAIRING = """
import sys, time, zenoh
run, ep = sys.argv[1], sys.argv[2]
c = zenoh.Config()
c.insert_json5("mode", '"peer"'); c.insert_json5("connect/endpoints", f'["{ep}"]')
c.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(c)
toks = [s.liveliness().declare_token(f"ambhil/{run}/{k}/controller") for k in ("starting", "alive")]
while not list(s.liveliness().get(f"ambhil/{run}/alive/plant", timeout=1.0)):
    time.sleep(0.05)
print("no peer id: bye")          # ready, never announced peer/controller/<id>, gone
sys.exit(3)
"""


def test_conformance_fails_fast_when_the_controller_dies_before_pairing(hard_recording):
    """A controller that was ready and died before announcing its peer id (the first mistake of
    examples/python_controller: it took the replay's peer/plant token for presence) fails the
    replay at once, saying so, instead of waiting start_timeout for a peer id."""
    mcap, _ = hard_recording
    cmd = f"{shlex.quote(sys.executable)} -c {shlex.quote(FAKE_DIES_AT_PAIRING)} {{run_id}} {{connect}}"
    r = cli("replay", str(mcap), "--to-controller", "--controller-cmd", cmd, "--run-id", "conf-gone",
            "--start-timeout", "600", "--json")
    assert r.returncode == 1, r.stdout + r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert "went away before it announced its peer id" in res["fault"], res
    assert res["controller_exit"]["exit_code"] == 3
