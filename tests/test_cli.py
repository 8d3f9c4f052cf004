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

from ambhil.bridge.cli import main as cli
from ambhil.bridge.cli.arguments import speed
from ambhil.bridge.cli.convention import folder
from ambhil.bridge.cli.simulate import sig3
from ambhil.bridge.cli.progress import Progress

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
                assert a.metavar == "DIR" and a.type is folder, f"ambhil {name} --out is not a folder"
        if name in SUMMARY_COMMANDS:
            assert any("--json" in a.option_strings for a in _flags(p)), f"ambhil {name} has no --json"


def test_out_refuses_a_file_name(tmp_path):
    f = tmp_path / "x.dat"
    f.write_text("")
    for bad in (str(tmp_path / "run.mcap"), str(tmp_path / "a.rrd"), str(f)):
        with pytest.raises(argparse.ArgumentTypeError, match="--out takes a folder"):
            folder(bad)
    assert folder(str(tmp_path / "new" / "dir")) == str(tmp_path / "new" / "dir")


def test_record_out_is_a_folder_and_the_file_is_named_for_the_run(tmp_path):
    args = cli.build_parser().parse_args(["record", "--run-id", "r1", "--out", str(tmp_path / "rec")])
    args._finalize(args)
    assert args.out == str(tmp_path / "rec" / "r1.mcap") and (tmp_path / "rec").is_dir()


@pytest.mark.parametrize("text,rad_s", [("314", 314.0), ("314rad/s", 314.0), ("314 rad/s", 314.0),
                                        ("3000rpm", 100 * math.pi), ("3000 RPM", 100 * math.pi),
                                        ("50Hz", 100 * math.pi), ("50hz", 100 * math.pi), ("1.5e2", 150.0)])
def test_speed_units(text, rad_s):
    assert speed(text) == pytest.approx(rad_s, rel=1e-12)


@pytest.mark.parametrize("text", ["fast", "3000rpx", "nan", "inf", "50 Hz Hz", ""])
def test_bad_speed_is_a_usage_error(text):
    with pytest.raises(argparse.ArgumentTypeError):
        speed(text)


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
    return subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env=e)


def test_version_and_help_in_a_real_process():
    r = _cli("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"ambhil {version('ambhil')}"
    r = _cli("simulate", "--help")
    assert r.returncode == 0 and "(default: out/simulate)" in r.stdout and "3000rpm" in r.stdout
    r = _cli("simulate", "scenes/nope.toml")         # the error class is the one main catches
    assert r.returncode == 2 and r.stderr.strip() == "ambhil simulate: error: scenes/nope.toml: no such scene file"


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_progress_when_piped_is_a_line_per_ten_seconds_with_a_unit():
    """Piped (a log): plain lines, at most one per 10 s and one at the end, each with its unit
    (before: a line per tenth of the work, 9-11 lines in under a second, "853/439504" with no
    unit).  The clock is the test's, so the count does not depend on the machine's speed."""
    buf, clock = io.StringIO(), _Clock()
    p = Progress("writing run.rrd", stream=buf, clock=clock)       # bytes: shown in MB
    total = 439_504
    for done in range(0, total + 1, 853):       # 515 calls over 103 s of simulated time
        clock.t += 0.2
        p(min(done, total), total)
    p(total, total)
    text = buf.getvalue()
    lines = text.splitlines()
    assert "\x1b" not in text and "\r" not in text
    assert 10 <= len(lines) <= 11, lines                     # 103 s: 10 lines, then the end
    assert all(ln.startswith("writing run.rrd: ") and " MB, " in ln for ln in lines), lines
    assert lines[-1].startswith("writing run.rrd: 100 % (0.44 of 0.44 MB"), lines
    buf2, clock2 = io.StringIO(), _Clock()
    q = Progress("paper_3amb: support sweep", stream=buf2, clock=clock2)   # a 3.5 s sweep
    for k in range(1, 36):
        clock2.t += 0.1
        q(k, 35)
    assert buf2.getvalue() == ""                             # a short job leaves the log alone
    buf3, clock3 = io.StringIO(), _Clock()
    r = Progress("paper_3amb: support sweep", stream=buf3, clock=clock3)
    for k in range(1, 36):
        clock3.t += 1.0
        r(k, 35)
    assert [ln.split("(")[1].split(",")[0] for ln in buf3.getvalue().splitlines()] == [
        "10 of 35 positions", "20 of 35 positions", "30 of 35 positions", "35 of 35 positions"]


def test_view_without_a_display_fails_with_a_hint(tmp_path, capsys, monkeypatch):
    """No DISPLAY / WAYLAND_DISPLAY / WAYLAND_SOCKET on Linux: `ambhil view` does not start the
    viewer (before: rerun's winit error, ANSI colours, exit 0); one error line, exit 1, with
    what to do instead."""
    import subprocess as sp
    rrd = tmp_path / "run.rrd"
    rrd.write_bytes(b"")
    for k in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setattr(sys, "platform", "linux")

    def _no(*a, **k):
        raise AssertionError("the viewer was started without a display")
    monkeypatch.setattr(sp, "Popen", _no)
    monkeypatch.setattr(sp, "call", _no)
    code, out, err = _main(capsys, "view", str(rrd))
    line = _one_error_line(err, "view")
    assert code == 1 and "no display" in line and "DISPLAY" in line and "--web-viewer" in line, err


def test_view_reports_a_viewer_error_even_when_it_exits_0(tmp_path, capsys, monkeypatch):
    """The viewer prints `Error: ...` and exits 0 (rerun 0.41 without a usable display): `ambhil
    view` fails (exit 1) naming that error, and its other output is passed on without colours
    when stderr is not a terminal."""
    import subprocess as sp
    rrd = tmp_path / "run.rrd"
    rrd.write_bytes(b"")
    monkeypatch.setenv("DISPLAY", ":99")
    real = sp.Popen
    script = ("import sys; sys.stderr.write('\\x1b[33m WARN\\x1b[0m some warning\\n"
              "Error: winit EventLoopError: Failed to open connection to X server\\n')")
    monkeypatch.setattr(sp, "Popen", lambda argv, **kw: real([sys.executable, "-c", script], **kw))
    code, out, err = _main(capsys, "view", str(rrd))
    assert code == 1, err
    assert " WARN some warning" in err and "\x1b" not in err, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("ambhil view: error: the rerun viewer failed: winit EventLoopError"), err


def test_run_start_up_steps_only_with_verbose(capsys):
    """`ambhil run` passes its processes' start-up steps on only with -v; without it, a kernel
    compilation (minutes, first run), the plant's start and anything else (warnings, errors)."""
    import threading
    from ambhil.bridge.cli.children import Child as _Child
    lines = ["recorder: waiting for plant, controller", "plant: building the model",
             "plant: compiling the plant kernels (first run only) ...", "controller: ready; waiting for plant",
             "ambhil controller: warning: something to know", "plant: paired with controller 0b9d",
             "plant: running (lockstep, 500 steps)", "plant: after the start"]
    script = "import sys\n" + "".join(f"print({ln!r}, file=sys.stderr)\n" for ln in lines)
    for verbose, want in ((False, [lines[2], lines[4], lines[6]]), (True, lines[:7])):
        echo = threading.Event()
        echo.set()
        echo.verbose = verbose
        c = _Child("plant", [sys.executable, "-c", script], echo, external=True)
        c.result(60)
        assert capsys.readouterr().err.splitlines() == want, verbose


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


def _segment_rows(out: str) -> list[tuple[float, float, str, dict]]:
    """(start, end, what, {AMB: largest radius um}) of simulate's orbit rows per segment."""
    import re
    rows = []
    for ln in out.splitlines():
        m = re.match(r"\s+t ([\d.e+-]+)-([\d.e+-]+) s\s+(.*?)\s{2,}([A-Z].*)$", ln)
        if m:
            amb = {a: float(v) for a, v in re.findall(r"([A-Z]\w*)\s+([\d.]+) \(", m.group(4))}
            rows.append((float(m.group(1)), float(m.group(2)), m.group(3).strip(), amb))
    return rows


def _largest_um(res, node: int, t0: float, t1: float, last: bool) -> float:
    import numpy as np
    j = res.nodes.index(node)
    sel = (res.t >= t0 - 1e-12) & ((res.t <= t1) if last else (res.t < t1 - 1e-12))
    return float(np.max(np.hypot(res.orbit[sel, j, 0], res.orbit[sel, j, 1]))) * 1e6


def test_simulate_run_up_titles_its_speed_range_and_prints_orbits_per_phase(tmp_path, capsys, monkeypatch):
    """A run-up's plots are titled with its speed range and ramp times (not "at 1000.0 rad/s" or
    "at 0.0 rad/s"); its summary prints the largest orbit per AMB before, during and after the
    ramp, each the largest recorded radius over that window (recomputed from simulation.npz), and
    the steady orbit after the ramp."""
    import matplotlib.figure
    from ambhil.loop.sim_result import load
    titles, save = [], matplotlib.figure.Figure.savefig
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: (
        titles.append(fig._suptitle.get_text() if fig._suptitle else ""), save(fig, *a, **k))[1])
    o = tmp_path / "o"
    code, out, err = _main(capsys, "simulate", str(ROOT / "scenes" / "paper_3amb.toml"), "--rung", "modal",
                           "--run-up", "1000,2000,0.02,0.04", "--duration", "0.08", "--no-record", "--out", str(o))
    assert code == 0, out + err
    assert len(titles) == 5 and all("run-up 1000 -> 2000 rad/s (9549 -> 19099 rpm), t 0.02-0.04 s" in t
                                    for t in titles), titles
    assert "before, during and after the run-up:" in out, out
    rows = _segment_rows(out)
    assert [(r[0], r[1], r[2]) for r in rows] == [(0, 0.02, "at 1000 rad/s"), (0.02, 0.04, "run-up 1000 -> 2000 rad/s"),
                                                 (0.04, 0.08, "at 2000 rad/s")], out
    res = load(o)
    for k, (t0, t1, _, amb) in enumerate(rows):
        for name, node in (("A", 21), ("B", 39), ("C", 57)):
            assert amb[name] == pytest.approx(_largest_um(res, node, t0, t1, k == len(rows) - 1), abs=0.006)
    assert "steady orbit after t=0.04 s at 2000.00 rad/s" in out, out
