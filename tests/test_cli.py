"""The command-line convention (issue 9), checked on the parser itself so it cannot drift:
help and shown defaults on every flag, --out a folder everywhere, --json one line, --version,
speeds with units, one error line `ambhil <command>: error: ...` with exit 2 / 1 / 130 and no
traceback unless AMBHIL_DEBUG=1; simulate's summary of a faulted run (issue 10 item 6)."""
import argparse
import io
import json
import math
import os
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

from bridge import cli
from bridge.commands_time import sig3
from bridge.progress import Progress

ROOT = Path(__file__).resolve().parents[1]
SUMMARY_COMMANDS = ("analyze", "simulate", "study accuracy", "plant", "controller", "record", "run",
                    "replay", "recover")


def _commands(parser=None, path=()):
    """(name, parser) of every leaf command, e.g. ('study accuracy', <parser>)."""
    parser = parser or cli.build_parser()
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, p in a.choices.items():
                subs = [x for x in p._actions if isinstance(x, argparse._SubParsersAction)]
                if subs:
                    yield from _commands(p, path + (name,))
                else:
                    yield " ".join(path + (name,)), p


def _flags(p):
    return [a for a in p._actions if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]


def test_every_command_follows_the_convention():
    cmds = dict(_commands())
    assert set(SUMMARY_COMMANDS) | {"view"} <= set(cmds), sorted(cmds)
    for name, p in cmds.items():
        assert p.formatter_class is cli.HelpFormatter and isinstance(p, cli.Parser), name
        assert p.get_default("_prog") == f"ambhil {name}" and p.get_default("func"), name
        text = " ".join(p.format_help().split())
        for a in _flags(p):
            assert a.help, f"ambhil {name}: {a.option_strings or a.dest} has no help"
            if a.option_strings and a.default not in (None, False, []):
                assert f"(default: {a.default})" in text, f"ambhil {name} {a.option_strings[0]}: default not shown"
            if a.dest == "out":
                assert a.metavar == "DIR" and a.type is cli.folder, f"ambhil {name} --out is not a folder"
        if name in SUMMARY_COMMANDS:
            assert any("--json" in a.option_strings for a in _flags(p)), f"ambhil {name} has no --json"


def test_out_refuses_a_file_name(tmp_path):
    f = tmp_path / "x.dat"
    f.write_text("")
    for bad in (str(tmp_path / "run.mcap"), str(tmp_path / "a.rrd"), str(f)):
        with pytest.raises(argparse.ArgumentTypeError, match="--out takes a folder"):
            cli.folder(bad)
    assert cli.folder(str(tmp_path / "new" / "dir")) == str(tmp_path / "new" / "dir")


def test_record_out_is_a_folder_and_the_file_is_named_for_the_run(tmp_path):
    args = cli.build_parser().parse_args(["record", "--run-id", "r1", "--out", str(tmp_path / "rec")])
    args._finalize(args)
    assert args.out == str(tmp_path / "rec" / "r1.mcap") and (tmp_path / "rec").is_dir()


@pytest.mark.parametrize("text,rad_s", [("314", 314.0), ("314rad/s", 314.0), ("314 rad/s", 314.0),
                                        ("3000rpm", 100 * math.pi), ("3000 RPM", 100 * math.pi),
                                        ("50Hz", 100 * math.pi), ("50hz", 100 * math.pi), ("1.5e2", 150.0)])
def test_speed_units(text, rad_s):
    assert cli.speed(text) == pytest.approx(rad_s, rel=1e-12)


@pytest.mark.parametrize("text", ["fast", "3000rpx", "nan", "inf", "50 Hz Hz", ""])
def test_bad_speed_is_a_usage_error(text):
    with pytest.raises(argparse.ArgumentTypeError):
        cli.speed(text)


def test_sig3():
    assert sig3(0.000949123) == "0.000949" and sig3(9.5612) == "9.56" and sig3(0.0791) == "0.0791"
    assert sig3(12.64) == "12.6" and sig3(105324.2) == "105324" and sig3(0.0) == "n/a"
    assert sig3(float("nan")) == "n/a"


def _main(capsys, *argv):
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _one_error_line(err, command):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"ambhil {command}: error: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("argv,command,needle", [
    (["simulate", "missing.toml"], "simulate", "missing.toml: no such scene file"),
    (["simulate", "scenes/paper_2amb.toml", "--speed", "3000rpx"], "simulate", "argument --speed"),
    (["simulate", "scenes/paper_2amb.toml", "--out", "o.npz"], "simulate", "--out takes a folder"),
    (["analyze", "missing.toml"], "analyze", "missing.toml: no such scene file"),
    (["run", "missing.toml"], "run", "missing.toml: no such scene file"),
    (["run"], "run", "required: SCENE"),
    (["study", "accuracy", "scenes/paper_2amb.toml", "--rungs", "rigid,bogus"], "study accuracy", "--rungs"),
    (["study", "accuracy", "scenes/paper_2amb.toml", "--ratios", "1,0"], "study accuracy", "--ratios"),
    (["plant", "scenes/paper_2amb.toml", "--run-id", "x", "--listen", "tcp/127.0.0.1:1", "--cpus", "9999"],
     "plant", "argument --cpus"),
    (["record", "--run-id", "x", "--out", "x.mcap"], "record", "--out takes a folder"),
    (["view", "no-such-run"], "view", "no-such-run: no such"),
    (["replay", "missing.mcap"], "replay", "missing.mcap: no such recording"),
    (["recover", "missing.mcap"], "recover", "missing.mcap: no such recording"),
])
def test_user_errors_are_one_line_exit_2(capsys, monkeypatch, argv, command, needle):
    monkeypatch.chdir(ROOT)
    code, out, err = _main(capsys, *argv)
    assert code == 2 and out == "", (code, out, err)
    assert needle in _one_error_line(err, command)


def _boom(exc):
    def handler(args):
        raise exc
    return handler


def test_failures_and_interrupts_are_one_line_without_traceback(capsys, monkeypatch):
    monkeypatch.delenv("AMBHIL_DEBUG", raising=False)
    parser = cli.build_parser()
    sim = dict(_commands(parser))["simulate"]
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    for exc, code, text in ((RuntimeError("boom"), 1, "RuntimeError: boom (AMBHIL_DEBUG=1 shows the traceback)"),
                            (KeyboardInterrupt(), 130, "interrupted"),
                            (cli.CliError("bad thing\nsecond line"), 2, "bad thing; second line"),
                            (cli.CliError("run failed", cli.RUN_FAILED), 1, "run failed"),
                            (PermissionError(13, "Permission denied", "/x/y"), 2, "/x/y: Permission denied"),
                            (UnicodeDecodeError("utf-8", b"\xff", 0, 1, "invalid start byte"), 2,
                             "input is not UTF-8 text (invalid start byte: byte b'\\xff' at offset 0)")):
        sim.set_defaults(func=_boom(exc))
        got, out, err = _main(capsys, "simulate", "s.toml")
        assert got == code and out == "" and _one_error_line(err, "simulate").endswith(text), (got, err)
    monkeypatch.setenv("AMBHIL_DEBUG", "1")
    sim.set_defaults(func=_boom(RuntimeError("boom")))
    with pytest.raises(RuntimeError, match="boom"):
        cli.main(["simulate", "s.toml"])


def _cli(*args, env=None, timeout=300):
    e = dict(os.environ, **(env or {}))
    e.pop("AMBHIL_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "bridge.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env=e)


def test_version_and_help_in_a_real_process():
    r = _cli("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"ambhil {version('ambhil')}"
    r = _cli("simulate", "--help")
    assert r.returncode == 0 and "(default: out/simulate)" in r.stdout and "3000rpm" in r.stdout
    r = _cli("simulate", "scenes/nope.toml")         # the error class is the one main catches
    assert r.returncode == 2 and r.stderr.strip() == "ambhil simulate: error: scenes/nope.toml: no such scene file"


def test_progress_when_piped_is_plain_lines():
    buf = io.StringIO()
    p = Progress("Campbell", stream=buf)
    for k in range(1, 42):
        p(k, 41)
    lines = buf.getvalue().splitlines()
    assert "\x1b" not in buf.getvalue() and "\r" not in buf.getvalue()
    assert 2 <= len(lines) <= 11 and lines[-1].startswith("Campbell 41/41")


def _slow_scene(tmp_path):
    """paper_2amb with its controller at 1 kHz: the rigid rung's loop is unstable and the rotor
    reaches the stator at t ~ 0.35 s."""
    text = (ROOT / "scenes" / "paper_2amb.toml").read_text()
    assert "sample_rate = 10000.0" in text
    p = tmp_path / "slow1k.toml"
    p.write_text(text.replace("sample_rate = 10000.0", "sample_rate = 1000.0"))
    return p


def test_simulate_faulted_run_shows_the_fault_first_and_no_steady_state(tmp_path, capsys):
    sc = _slow_scene(tmp_path)
    argv = ["simulate", str(sc), "--rung", "rigid", "--duration", "0.5", "--out", str(tmp_path / "o")]
    code, out, err = _main(capsys, *argv)
    assert code == 1, out + err
    lines = out.splitlines()
    assert lines[1].startswith("  FAULT: ") and "rotor reached the stator" in lines[1], out
    assert "steady orbit" not in out and "settle" not in out and "nan" not in out, out
    assert "no steady-state figures" in out and "real-time factor 0.0" not in out
    code, out, err = _main(capsys, *argv, "--json")
    s = json.loads(out)
    assert code == 1 and len(out.splitlines()) == 1 and not s["ok"] and s["orbits"] == []
    assert "rotor reached the stator" in s["fault"] and s["periods"] < s["periods_planned"] == 500


def test_simulate_json_good_run_and_speed_units(tmp_path, capsys):
    from test_integrator import SCENE
    sc = tmp_path / "s.toml"
    sc.write_text(SCENE)
    code, out, err = _main(capsys, "simulate", str(sc), "--duration", "0.05", "--speed", "3000rpm",
                           "--out", str(tmp_path / "o"), "--json")
    assert code == 0 and len(out.splitlines()) == 1, out + err
    s = json.loads(out)                        # strict JSON: no NaN (a nan settle time is null)
    assert s["ok"] and s["speed_rad_s"] == pytest.approx(100 * math.pi) and len(s["orbits"]) == 2
    assert s["periods"] == s["periods_planned"] == 500 and s["real_time_factor"] > 0
    code, out, err = _main(capsys, "simulate", str(sc), "--duration", "0.05", "--speed", "50Hz",
                           "--out", str(tmp_path / "o"))
    assert code == 0 and "speed 314.16 rad/s (3000 rpm)" in out and "FAULT" not in out, out
    rtf = out.split("real-time factor ")[1].split()[0]
    assert rtf != "0.0" and len(rtf.replace(".", "").lstrip("0")) <= 6, rtf


def test_run_json_is_one_line(tmp_path):
    r = _cli("run", "scenes/paper_3amb.toml", "--duration", "0.01", "--rung", "modal", "--run-id", "j1",
             "--out", str(tmp_path), "--json")
    assert r.returncode == 0 and len(r.stdout.splitlines()) == 1, r.stdout + r.stderr
    json.loads(r.stdout)


def test_view_converts_a_recording_and_uses_the_installed_viewer(tmp_path, capsys):
    from test_replay import write_recording
    mcap = write_recording(tmp_path / "v1.mcap", 20)
    code, out, err = _main(capsys, "view", str(mcap), "--print-command")
    assert code == 0 and (tmp_path / "v1.rrd").exists(), err
    argv = out.split()
    assert argv[:3] == [sys.executable, "-m", "rerun_cli"] and argv[3] == str(tmp_path / "v1.rrd")
    # the viewer binary behind that command exists in this environment
    r = subprocess.run(argv[:3] + ["--version"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "rerun" in r.stdout.lower(), r.stdout + r.stderr
    code, out, err = _main(capsys, "view", "v1", "--recordings", str(tmp_path), "--print-command")
    assert code == 0 and out.split()[3] == str(tmp_path / "v1.rrd")
