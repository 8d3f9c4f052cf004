"""Re-levitation criteria of a fault campaign (loop/campaign.py, bridge/cli/campaign.py): a case with
a ``drop`` that ends is judged on the time to lift the rotor off the auxiliary bearings after the
AMBs come back, the peak contact force after the return and backward whirl, all three figures from
``loop.contact_results.relevitation(res, t_return)``.  Here that function is a stub with its exact
signature, so the verdicts are checked on synthetic results whatever the contact model computes;
the campaign's parsing and the CLI's flags and refusals are checked for real."""
from __future__ import annotations

import json
import subprocess
import sys
import types
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from ambhil.loop import campaign as cp
from ambhil.loop.scene import SceneError, load_scene

ROOT = Path(__file__).resolve().parents[1]
SCENE = str(ROOT / "scenes" / "paper_3amb.toml")
SHIPPED = ROOT / "scenes" / "campaigns" / "rotor_drop_relevitation.toml"


@pytest.fixture(scope="module")
def scene():
    return load_scene(SCENE)


@dataclass
class Relev:
    """What ``relevitation(res, t_return)`` returns (helper C's object, same attributes)."""
    time_s: float | None
    peak_force_N: float
    backward_whirl: bool

    def lines(self):
        return [f"lifted off after {self.time_s} s", f"peak {self.peak_force_N} N"]


def campaign(tmp_path, text, scene):
    f = tmp_path / "c.toml"
    f.write_text(text)
    return cp.load_campaign(f, scene)


DROP = '[[case]]\nname = "drop"\nfaults = ["drop:at=0.1s,until=0.2s"]\n'


def synthetic(case, relev, why=""):
    """evaluate() on a calm synthetic orbit (1 um at 50 Hz at every station) and ``relev``."""
    t = np.arange(0, case.duration, 1e-4)
    r = 1e-6 * np.stack([np.cos(2 * np.pi * 50 * t), np.sin(2 * np.pi * 50 * t)], -1)
    xy = np.repeat(r[:, None, :], 3, axis=1)
    return cp.evaluate(case, t, xy, [7.5e-5] * 3, 2 * np.pi * 50, True, None, relev, why)


# --------------------------------------------------------------------------- parsing
def test_a_drop_that_ends_is_judged_with_the_default_limits_and_others_are_not(tmp_path, scene):
    cases = campaign(tmp_path, '[campaign]\nduration = "0.5s"\n\n' + DROP
                     + '\n[[case]]\nname = "for good"\nfaults = ["drop:at=0.1s"]\n'
                     + '\n[[case]]\nname = "loss B"\nfaults = ["amb_loss:at=0.1s,axis=B,until=0.2s"]\n', scene)
    drop, forever, loss = cases
    assert drop.judges_relevitation and drop.t_return == pytest.approx(0.2)
    assert (drop.relevitation_time, drop.max_relevitation_force, drop.no_backward_whirl) == (0.2, None, True)
    assert cp.RELEVITATION_TIME == 0.2
    assert not forever.judges_relevitation and not loss.judges_relevitation   # the AMBs never come back / no drop


def test_campaign_defaults_and_case_keys_set_the_limits(tmp_path, scene):
    text = ('[campaign]\nduration = "0.5s"\nrelevitation_time = "80ms"\nmax_relevitation_force = 500\n\n' + DROP
            + '\n[[case]]\nname = "own"\nfaults = ["drop:at=0.1s,duration=20ms", "drop:at=0.15s,until=0.25s"]\n'
              'relevitation_time = 0.15\nmax_relevitation_force = 900.0\nno_backward_whirl = false\n')
    a, b = campaign(tmp_path, text, scene)
    assert (a.relevitation_time, a.max_relevitation_force, a.no_backward_whirl) == (pytest.approx(0.08), 500, True)
    assert (b.relevitation_time, b.max_relevitation_force, b.no_backward_whirl) == (0.15, 900.0, False)
    assert b.t_return == pytest.approx(0.25)          # the latest drop end: when the AMBs are all back


@pytest.mark.parametrize("extra, needle", [
    ('faults = ["amb_loss:at=0.1s,axis=B,until=0.2s"]\nrelevitation_time = "0.1s"\n',
     "key 'relevitation_time': re-levitation is judged after a drop that ends"),
    ('faults = ["drop:at=0.1s"]\nno_backward_whirl = true\n', "key 'no_backward_whirl': re-levitation is judged"),
    ('faults = ["drop:at=0.1s,until=0.2s"]\nrelevitation_time = 0\n', "key 'relevitation_time': must be > 0 s"),
    ('faults = ["drop:at=0.1s,until=0.2s"]\nmax_relevitation_force = -3\n', "key 'max_relevitation_force': must be > 0"),
    ('faults = ["drop:at=0.1s,until=0.2s"]\nno_backward_whirl = "yes"\n', "must be true or false"),
    ('faults = ["drop:at=0.1s,until=0.6s"]\n', "ends before the AMBs come back at 0.6 s"),
    ('faults = ["drop:at=0.1s,until=0.2s,coast_down=1s", "speed_trip:at=0.3s"]\n',
     "key 'faults': fault #1 drop coast_down and fault #2 speed_trip both trip the drive"),
])
def test_bad_relevitation_keys_are_one_line_errors_naming_case_and_key(tmp_path, scene, extra, needle):
    with pytest.raises(SceneError) as e:
        campaign(tmp_path, '[campaign]\nduration = "0.5s"\n\n[[case]]\nname = "x"\n' + extra, scene)
    msg = str(e.value)
    assert needle in msg and "[[case]] #1 'x'" in msg and "\n" not in msg, msg


def test_the_shipped_campaign_loads_and_judges_every_case_on_relevitation(scene):
    """The drop faults name no axis, so the file loads against any scene; here the paper rotor (the
    drop scene is checked end to end where the contact model runs)."""
    cases = cp.load_campaign(SHIPPED, scene)
    assert len(cases) >= 1 and all(c.judges_relevitation and c.relevitation_time == 0.2 for c in cases)


# --------------------------------------------------------------------------- verdicts
@pytest.mark.parametrize("relev, limits, failed", [
    (Relev(0.05, 800.0, False), {}, []),
    (Relev(0.25, 800.0, False), {}, ["re-levitated after 0.25 s > 0.2 s"]),
    (Relev(None, 800.0, False), {}, ["never lifted off the auxiliary bearings after the AMBs came back at 0.2 s"]),
    (Relev(0.05, 800.0, False), {"max_relevitation_force": 500.0},
     ["peak contact force after the return 800 N > 500 N"]),
    (Relev(0.05, 400.0, False), {"max_relevitation_force": 500.0}, []),
    (Relev(0.05, 800.0, True), {}, ["backward whirl on the auxiliary bearings"]),
    (Relev(0.05, 800.0, True), {"no_backward_whirl": False}, []),
    (Relev(0.3, 900.0, True), {"max_relevitation_force": 500.0},
     ["re-levitated after 0.3 s > 0.2 s", "peak contact force after the return 900 N > 500 N",
      "backward whirl on the auxiliary bearings"]),
])
def test_relevitation_criteria_pass_and_fail_on_synthetic_results(tmp_path, scene, relev, limits, failed):
    case = replace(campaign(tmp_path, '[campaign]\nduration = "0.5s"\n\n' + DROP, scene)[0], **limits)
    r = synthetic(case, relev)
    assert r.failures == failed and r.passed == (not failed)
    m = r.metrics["relevitation"]
    assert m["measured"] and m["time_s"] == relev.time_s and m["peak_force_N"] == relev.peak_force_N
    assert m["backward_whirl"] == relev.backward_whirl and m["lines"] == relev.lines() and m["t_return_s"] == 0.2


def test_an_unmeasured_relevitation_fails_the_case(tmp_path, scene):
    """A criterion that could not be checked never passes (a scene without auxiliary bearings)."""
    case = campaign(tmp_path, '[campaign]\nduration = "0.5s"\n\n' + DROP, scene)[0]
    r = synthetic(case, None, "the scene has no auxiliary bearings")
    assert not r.passed and r.failures == ["re-levitation not measured (the scene has no auxiliary bearings)"]
    assert r.metrics["relevitation"]["measured"] is False
    other = replace(case, t_return=None)            # a case without a returning drop: nothing of this
    r = synthetic(other, None)
    assert r.passed and "relevitation" not in r.metrics


def test_run_case_calls_relevitation_with_the_drop_end(tmp_path, scene, monkeypatch):
    """run_case hands simulate's result and the AMBs' return time to contact_results.relevitation."""
    case = campaign(tmp_path, '[campaign]\nduration = "0.3s"\n\n' + DROP, scene)[0]
    seen = {}
    stub = types.ModuleType("ambhil.loop.contact_results")

    def relevitation(res, t_return):
        seen["args"] = (res, t_return)
        return Relev(0.31, 123.0, False)
    stub.relevitation = relevitation
    monkeypatch.setitem(sys.modules, "ambhil.loop.contact_results", stub)
    import ambhil.loop as loop_pkg
    monkeypatch.setattr(loop_pkg, "contact_results", stub, raising=False)
    t = np.arange(0, 0.3, 1e-4)
    res = types.SimpleNamespace(t=t, orbit=np.full((len(t), 3, 2), 1e-6), meta={"period": 1e-4, "speed": 300.0},
                                steps=len(t), fault=None, instability=None, events=[], contact={"names": ["A"]})
    monkeypatch.setattr("ambhil.loop.simulation.simulate", lambda *a, **k: res)
    system = types.SimpleNamespace(spec=types.SimpleNamespace(
        ambs=[types.SimpleNamespace(node=k, clearance=7.5e-5) for k in range(3)]))
    r = cp.run_case(system, case)
    assert seen["args"] == (res, 0.2)
    assert not r.passed and r.failures == ["re-levitated after 0.31 s > 0.2 s"]
    res.contact = None                              # no auxiliary bearings: not measured, fails
    seen.clear()
    r = cp.run_case(system, case)
    assert not seen and not r.passed and "no auxiliary bearings" in r.failures[0]


# --------------------------------------------------------------------------- CLI
def cli(*a, timeout=300):
    return subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "test-controller", *a], capture_output=True,
                          text=True, cwd=ROOT, timeout=timeout)


def test_cli_refuses_bad_relevitation_flags(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('[campaign]\nduration = "0.3s"\n\n' + DROP)
    for flag, v in (("--relevitation-time", "soon"), ("--max-relevitation-force", "-1")):
        r = cli(SCENE, "--faults", str(f), flag, v)
        assert r.returncode == 2 and flag in r.stderr and r.stderr.strip().count("\n") <= 2, r.stderr


def test_relevitation_against_a_controller_command_agrees_with_in_process(tmp_path):
    """--controller: each case is an `ambhil run` (here with the reference controller as the command),
    and re-levitation is judged from its recording: the sensor orbit and the plant's contact events.
    Lockstep being bit-identical, the verdict, the time to re-levitate (to a sample) and the peak
    force after the return (the contact events' peaks) agree with the in-process case; the scene's own
    drop ([[fault]] in rotor_drop.toml) is left out of both (`--fault none`)."""
    f = tmp_path / "c.toml"
    f.write_text('[campaign]\nduration = "0.2s"\nrelevitation_time = "0.1s"\n\n[[case]]\nname = "drop"\n'
                 'faults = ["drop:at=0.02s,duration=80ms"]\n')      # back while the rotor rests on its bearings
    drop = str(ROOT / "scenes" / "rotor_drop.toml")
    inproc = cli(drop, "--faults", str(f), "--json")
    cmd = f"{sys.executable} -m ambhil.bridge.cli controller {{scene}} --run-id {{run_id}} --connect {{connect}}"
    ext = cli(drop, "--faults", str(f), "--json", "--controller", cmd, "--out", str(tmp_path / "o"), timeout=600)
    a, b = json.loads(inproc.stdout)["results"][0], json.loads(ext.stdout)["results"][0]
    assert a["passed"] and b["passed"] and ext.returncode == 0, ext.stdout + ext.stderr
    ra, rb = a["relevitation"], b["relevitation"]
    assert ra["time_s"] is not None and abs(ra["time_s"] - rb["time_s"]) <= 1e-4 + 1e-9, (ra, rb)
    assert ra["peak_force_N"] > 50.0 and rb["peak_force_N"] == pytest.approx(ra["peak_force_N"], rel=1e-9)
    assert ra["backward_whirl"] is rb["backward_whirl"] is False


def test_cli_flags_override_the_limits_and_an_unmeasured_case_fails_with_exit_1(tmp_path):
    """The paper rotor has no auxiliary bearings: the drop case runs and fails as not measured
    (exit 1), with the command line's limits in the JSON row and the table's column."""
    f = tmp_path / "c.toml"
    f.write_text('[campaign]\nduration = "0.12s"\nrelevitation_time = "0.1s"\n\n'
                 '[[case]]\nname = "drop"\nfaults = ["drop:at=0.05s,until=0.052s"]\nmust_stay_stable = false\n')
    human = cli(SCENE, "--faults", str(f), "--rung", "modal", "--relevitation-time", "30ms",
                "--max-relevitation-force", "750", "--out", str(tmp_path / "o"))
    assert human.returncode == 1, human.stdout + human.stderr
    assert "re-levitation" in human.stdout and "not measured" in human.stdout, human.stdout
    row = json.loads((tmp_path / "o" / "campaign.json").read_text())["results"][0]
    rl = row["relevitation"]
    assert rl["limit_time_s"] == pytest.approx(0.03) and rl["limit_peak_force_N"] == 750.0 and rl["no_backward_whirl"]
    assert rl["measured"] is False and rl["t_return_s"] == pytest.approx(0.052)
    assert not row["passed"] and row["failures"][-1].startswith("re-levitation not measured (the scene has no")
    assert [(e["kind"], e["phase"]) for e in row["events"]] == [("drop", "start"), ("drop", "end")]
