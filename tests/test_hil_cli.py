"""End to end through the CLI on loopback: `ambhil run` (three OS processes over zenoh, lockstep)
reproduces the in-process loop of the same step functions bit for bit; the recording replays
into a controller (pass on the same controller, fail on a changed gain)."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENE = str(ROOT / "scenes" / "paper_3amb.toml")


def cli(*args, timeout=240):
    return subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    r = cli("run", SCENE, "--duration", "0.05", "--rung", "modal", "--run-id", "e2e", "--out", str(out), "-v")
    assert r.returncode == 0, r.stdout + r.stderr
    return out / "e2e.mcap", r


def test_run_leaves_mcap_and_rrd_and_summary(recorded):
    mcap, r = recorded
    assert mcap.exists() and mcap.with_suffix(".rrd").exists()
    for key in ("steps      500/500", "overruns", "latency", "orbit A", "% of the touchdown clearance 75 um",
                "transport  unix socket"):        # same host: Unix-domain sockets by default
        assert key in r.stdout, r.stdout
    from ambhil.bridge.recording.load import load_run
    meta = load_run(str(mcap))["meta"]           # the scene's touchdown clearances travel with the run
    assert meta["touchdown_clearances_m"] == [7.5e-5] * 3 and meta["gaps_m"] == [1.5e-4] * 3


def test_run_over_tcp_without_recorder(tmp_path):
    """--transport tcp is said in the summary; --no-record runs the loop alone and leaves no file."""
    import json
    r = cli("run", SCENE, "--duration", "0.02", "--rung", "rigid", "--run-id", "norec", "--out", str(tmp_path),
            "--transport", "tcp", "--no-record", "--json")
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert s["transport"]["kind"] == "tcp" and s["plant"]["steps"] == 200 and s["recorder"] is None
    assert s["files"] == [] and not list(tmp_path.iterdir())


def test_transport_falls_back_to_tcp_and_says_why(tmp_path, monkeypatch, capsys):
    """auto: a socket folder whose paths exceed a socket address -> TCP on loopback, with the
    reason on stderr and in the summary text; --transport unix refuses instead."""
    from ambhil.bridge.cli.run_transport import choose_transport
    from ambhil.loop.scene import SceneError
    deep = tmp_path / ("d" * 60) / ("e" * 60)
    deep.mkdir(parents=True)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(deep))
    t, ep_p, ep_r = choose_transport("auto", "fallback")
    assert t["kind"] == "tcp" and "fallback" in t["text"] and ep_p.startswith("tcp/127.0.0.1:")
    assert "using TCP on loopback" in capsys.readouterr().err
    with pytest.raises(SceneError, match="--transport unix: Unix socket path too long"):
        choose_transport("unix", "fallback")
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    t, ep_p, _ = choose_transport("auto", "ok")
    assert t["kind"] == "unix" and ep_p.startswith(f"unixsock-stream/{tmp_path}/ambhil/")


def test_lockstep_over_zenoh_equals_in_process(recorded):
    from ambhil.bridge.process.reference import run_inprocess
    from ambhil.bridge.recording.load import load_run
    from ambhil.loop.system import compile_system, controller_runner
    from ambhil.plant.step import PlantRunner
    mcap, _ = recorded
    run = load_run(str(mcap))
    model = compile_system(SCENE, rung="modal")
    Y, U = run_inprocess(PlantRunner(model), controller_runner(model.scene), 500)
    assert run["sensors"]["v"].shape == (500, model.n_axes)
    assert np.array_equal(run["sensors"]["v"], Y[:500])  # bit for bit
    assert np.array_equal(run["currents"]["v"], U)
    assert np.abs(Y).max() > 1e-7  # the rotor actually moved (unbalance at the critical speed)


def test_replay_to_controller_pass_and_fail(recorded):
    mcap, _ = recorded
    ok = cli("replay", str(mcap), "--to-controller", "--scene", SCENE, "--run-id", "rpok")
    assert ok.returncode == 0 and "PASS" in ok.stdout, ok.stdout + ok.stderr
    bad = cli("replay", str(mcap), "--to-controller", "--scene", SCENE, "--gain-scale", "1.05", "--run-id", "rpbad")
    assert bad.returncode == 1 and "FAIL" in bad.stdout and "largest deviation" in bad.stdout, bad.stdout + bad.stderr


def test_replay_to_rrd_and_recover(recorded, tmp_path):
    mcap, _ = recorded
    rrd = tmp_path / "rrd" / "e2e.rrd"                 # --out is a folder; the .rrd is named like the .mcap
    r = cli("replay", str(mcap), "--out", str(rrd.parent))
    assert r.returncode == 0 and rrd.exists() and "rerun" in r.stdout
    data = mcap.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    r = cli("recover", str(cut), str(tmp_path / "fixed.mcap"))
    assert r.returncode == 0 and "recovered" in r.stdout, r.stdout + r.stderr


def test_bad_scene_is_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(Path(SCENE).read_text().replace("turns = 100", "turns = -1", 1))
    r = cli("run", str(bad), "--duration", "0.01")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "'turns'" in r.stderr


def test_run_shows_startup_progress(recorded):
    """With -v, each process's start-up progress is shown until the plant runs (which lines a peer gets to
    print before that depends on the scheduler: under load the controller may still be loading
    its kernel when the plant starts, so only its first line is certain)."""
    _, r = recorded
    for line in ("plant: building the model", "controller: building the controller", "recorder: waiting for",
                 "plant: running (lockstep, 500 steps)"):
        assert line in r.stderr, r.stderr


def test_failed_run_files_are_marked(tmp_path):
    """A run that fails (a scene whose controller gain cannot hold the rotor: it touches down)
    leaves <run-id>.failed.mcap / .failed.rrd, the MCAP says why, and the summary says so."""
    from mcap.reader import make_reader
    bad = tmp_path / "weak.toml"
    text = Path(SCENE).read_text()
    assert "kp = 5.98869" in text
    bad.write_text(text.replace("kp = 5.98869", "kp = 0.5", 1))
    out = tmp_path / "rec"
    r = cli("run", str(bad), "--duration", "0.1", "--rung", "modal", "--run-id", "weak", "--out", str(out))
    assert r.returncode == 1 and "run failed: plant: rotor reached the stator" in r.stderr, r.stdout + r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["weak.failed.mcap", "weak.failed.rrd"]
    assert "marked .failed" in r.stdout, r.stdout
    with open(out / "weak.failed.mcap", "rb") as f:
        meta = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    end = meta["ambhil.run_end"]
    assert end["status"] == "failed" and "rotor reached the stator" in end["fault"], end
    assert int(end["steps_run"]) < int(end["steps_planned"]) == 1000


def test_fractional_latency_over_zenoh_equals_in_process(tmp_path):
    """`run --delay 1.5T` with plant steps of T/2 (the coil gets the new current half-way through
    the period after next) reproduces the in-process loop of the same runners bit for bit."""
    from ambhil.bridge.process.reference import run_inprocess
    from ambhil.bridge.recording.load import load_run
    from ambhil.loop.system import compile_system, controller_runner
    from ambhil.plant.run_options import RunOptions
    from ambhil.plant.step import PlantRunner
    r = cli("run", SCENE, "--duration", "0.03", "--rung", "modal", "--delay", "1.5T", "--h", "5e-5",
            "--run-id", "frac", "--out", str(tmp_path))
    # 150 us is beyond this loop's latency margin (an ~848 Hz mode grows at ~26 1/s): the run is
    # failed as `simulate` fails it (not steady), and its recording is still the exact loop
    assert r.returncode == 1 and "FAILED     not steady:" in r.stdout, r.stdout + r.stderr
    assert "latency 150 us (1.5 periods)" in r.stdout, r.stdout
    run = load_run(str(tmp_path / "frac.failed.mcap"))
    assert run["meta"]["latency_s"] == pytest.approx(1.5e-4)
    model = compile_system(SCENE, rung="modal")
    Y, U = run_inprocess(PlantRunner(model, RunOptions(h=5e-5, latency=1.5e-4)), controller_runner(model.scene), 300)
    assert np.array_equal(run["sensors"]["v"], Y[:300])
    assert np.array_equal(run["currents"]["v"], U)


def test_predicted_unstable_latency_diverges_over_zenoh_and_its_stable_neighbour_completes(tmp_path):
    """Full rung at 10 kHz: the timing model puts the boundary near 52 us.  With 40 us (0.4 T)
    the run completes; with 200 us (2 T) it is predicted unstable (a ~846 Hz mode growing at
    ~34 1/s), warned before the start, and the run (exact zoh plant: BDF1 at 100 us would damp
    the mode numerically, issue 15) ends in a touchdown fault; --strict refuses it."""
    ok = cli("run", SCENE, "--duration", "0.3", "--rung", "full", "--delay", "0.4T", "--h", "2e-5",
             "--run-id", "near", "--out", str(tmp_path))
    assert ok.returncode == 0 and "FAILED" not in ok.stdout, ok.stdout + ok.stderr
    bad = cli("run", SCENE, "--duration", "1.0", "--rung", "full", "--delay", "2T", "--integrator", "zoh",
              "--run-id", "far", "--out", str(tmp_path))
    assert "sampled loop is not" in bad.stderr and "grows at" in bad.stderr, bad.stderr
    assert bad.returncode == 1 and "FAILED" in bad.stdout and "reached the stator" in bad.stdout, bad.stdout
    assert (tmp_path / "far.failed.mcap").exists()
    strict = cli("run", SCENE, "--duration", "0.1", "--rung", "full", "--delay", "2T", "--strict",
                 "--run-id", "refused", "--out", str(tmp_path))
    assert strict.returncode == 1 and "error:" in strict.stderr and not (tmp_path / "refused.mcap").exists()


def _pids_with(marker: str) -> set[int]:
    """PIDs of live processes whose command line contains ``marker``."""
    out = set()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                state = next((ln for ln in (d / "status").read_text().splitlines() if ln.startswith("State:")), "")
            except OSError:
                continue
            if marker in cmd and "Z (zombie)" not in state:
                out.add(int(d.name))
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal is Linux-only")
def test_killed_run_takes_its_processes_with_it(tmp_path):
    """SIGKILL of `ambhil run` (no chance to clean up) still ends its plant, controller and
    recorder: each gets SIGTERM from the kernel when its parent dies.  Waits on the processes'
    presence and progress, not on a fixed time."""
    import os
    import time
    rid = f"orphan{os.getpid()}"
    p = subprocess.Popen([sys.executable, "-m", "ambhil.bridge.cli", "run", SCENE, "--rung", "modal", "--duration", "600",
                          "--run-id", rid, "--out", str(tmp_path)], cwd=ROOT, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True)
    for line in p.stderr:   # the start-up progress; the plant's 'running' means all three are up
        if line.startswith("plant: running"):
            break
    else:
        pytest.fail(f"ambhil run ended before running (exit {p.wait()})")
    children = _pids_with(f"--run-id {rid}") - {p.pid}
    assert len(children) == 3, children
    p.kill()
    p.wait()
    deadline = time.monotonic() + 120   # last resort only: they end as soon as SIGTERM is handled
    while (left := children & _pids_with(f"--run-id {rid}")) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not left, f"still running after the parent was killed: {left}"
    # the recorder finished what the run could not: the file kept, marked, its .rrd written, and
    # ambhil.run_end says the run was stopped because `ambhil run` died
    from mcap.reader import make_reader
    assert sorted(f.name for f in tmp_path.iterdir()) == [f"{rid}.failed.mcap", f"{rid}.failed.rrd"]
    with open(tmp_path / f"{rid}.failed.mcap", "rb") as f:
        end = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}["ambhil.run_end"]
    assert end["status"] == "stopped" and end["end_reason"] == f"ambhil run (pid {p.pid}) died", end
    # its socket files, if any are left, go at the next start (their owner is dead).  A process
    # leaves /proc's command lines (its memory released) a moment before the kernel closes its
    # files: until then its socket still accepts, and remove_stale_sockets rightly keeps it
    from ambhil.bridge.process import transport as tr

    def left_files():
        tr.remove_stale_sockets()
        return [f for f in os.listdir(tr.socket_dir()) if f.startswith(f"{rid}-{p.pid}-")]
    while (files := left_files()) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not files


def test_simulate_writes_the_recording_of_a_run_with_the_same_data(recorded, tmp_path):
    """Issue 14: `ambhil simulate` writes simulation.mcap + .rrd in the layout of a HIL run's
    recording (same topics but the run id, same schemas, stamps in simulation time), and for the
    same scene its displacements and currents are those of the lockstep run, bit for bit."""
    from ambhil.bridge.recording import layout as rc
    from ambhil.bridge.recording.load import load_run
    from mcap.reader import make_reader
    mcap, _ = recorded
    r = cli("simulate", SCENE, "--duration", "0.05", "--rung", "modal", "--record-every", "1", "--out", str(tmp_path))
    assert r.returncode == 0, r.stdout + r.stderr
    sim = tmp_path / "simulation.mcap"
    assert sim.exists() and (tmp_path / "simulation.rrd").exists() and "simulation.mcap" in r.stdout
    a, b = load_run(str(mcap)), load_run(str(sim))
    for k in ("sensors", "currents"):
        assert b[k]["v"].shape == (500, 6) and b[k]["v"].shape == a[k]["v"].shape
        assert np.array_equal(a[k]["v"], b[k]["v"]), k                      # bit for bit
        assert np.array_equal(a[k]["t_ns"], b[k]["t_ns"]) and np.array_equal(a[k]["seq"], b[k]["seq"])
        assert a[k]["raw"][7][:4] == b[k]["raw"][7][:4]
    assert b["meta"]["axis_names"] == a["meta"]["axis_names"] and b["meta"]["mode"] == "in-process"

    def layout(path):
        with open(path, "rb") as f:
            rd = make_reader(f)
            prof = rd.get_header().profile
            s = rd.get_summary()
            return prof, {rc.channel_key(c).split("/", 2)[2]: (s.schemas[c.schema_id].name, s.schemas[c.schema_id].data)
                          for c in s.channels.values()}
    pa, la = layout(mcap)
    pb, lb = layout(sim)
    assert pa == pb == "ros2"
    for topic in ("plant/sensors", "controller/currents", "events", "meta"):
        assert la[topic] == lb[topic], topic                                # same schema, same field names


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="libc signal() in the children's pre-exec")
def test_sigterm_stops_a_run_started_with_sigint_ignored_as_ctrl_c_does(tmp_path):
    """A run started as a script's background job (SIGINT ignored, inherited by every child)
    and ended with SIGTERM (kill, `timeout`): the plant is still stopped with SIGINT, so the
    run ends with the plant's own summary (interrupted, its steps), the recording kept and
    marked failed.  Waits on the run's progress, not on a fixed time."""
    import json
    import signal
    import time
    rid = f"term{__import__('os').getpid()}"
    p = subprocess.Popen([sys.executable, "-m", "ambhil.bridge.cli", "run", SCENE, "--rung", "modal", "--duration", "600",
                          "--run-id", rid, "--out", str(tmp_path), "--json"], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    for line in p.stderr:
        if line.startswith("plant: running"):
            break
    else:
        pytest.fail(f"ambhil run ended before running (exit {p.wait()})")
    mcap = tmp_path / f"{rid}.mcap"         # steps made: the recording grows past its first chunks
    while p.poll() is None and not (mcap.exists() and mcap.stat().st_size > 300_000):
        time.sleep(0.05)
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=300)   # last resort only: before the fix it never ended
    s = json.loads([ln for ln in out.splitlines() if ln.startswith("{")][-1])
    assert s["failed"] == ["interrupted by the user (SIGTERM)"], s["failed"]   # nothing else: a stop, not a fault
    assert p.returncode == 130, (p.returncode, err)                          # the README's code for it
    assert s["plant"]["end_reason"] == "interrupted" and s["plant"]["fault"] is None and s["plant"]["steps"] > 0
    assert s["plant"]["wall_s"] > 0 and s["plant"]["steps_per_s"] > 0     # the steps it made, timed
    assert s["recorder"]["status"] == "stopped"
    # everything the plant sent is in the file (the sample of the step it was stopped in too)
    assert s["plant"]["steps"] <= s["recorder"]["steps_recorded"] <= s["plant"]["steps"] + 1
    assert all(".failed." in f and Path(f).exists() for f in s["files"]), s["files"]


# ---------------------------------------------------------------- how a run ends, and whether it kept its rate
def test_max_overruns_takes_a_share_a_count_or_off():
    from ambhil.bridge.cli.arguments import overrun_limit
    assert overrun_limit("1%") == ("percent", 1.0) and overrun_limit(" 0.5 % ".replace(" ", "")) == ("percent", 0.5)
    assert overrun_limit("20") == ("count", 20) and overrun_limit("off") is None
    for bad in ("-1%", "101%", "x", "1.5"):
        with pytest.raises(SystemExit, match="--max-overruns"):
            overrun_limit(bad)
    r = cli("run", SCENE, "--max-overruns", "lots", "--duration", "0.01")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "--max-overruns" in r.stderr


def _modal():
    import types
    from ambhil.loop.scene import load_scene
    from ambhil.loop.system import compile_system
    scene = load_scene(SCENE)
    return scene, compile_system(scene, rung="modal"), types.SimpleNamespace(
        integrator=None, h=None, delay="0", mode="realtime", max_overruns=("percent", 1.0))


def test_a_realtime_run_that_overran_is_failed_and_compared_with_the_in_process_loop():
    """--max-overruns 1 %: 30 of 1000 counted periods overran -> not kept, and the reason says by
    how much the run's orbit differs from the in-process loop's, which is `simulate`'s (an
    independent path: the fused numba loop) over the same steps."""
    from ambhil.bridge.cli.run_verdict import rate_check
    from ambhil.loop.simulation import simulate
    scene, model, args = _modal()
    sp = {"steps": 1100, "warmup_steps": 100, "overruns": 30}
    ref = simulate(model, 0.11).y[:1100]
    ra = float(np.max(np.hypot(ref[:, 0], ref[:, 1])))
    orbits = [("A", 2.0 * ra, 0.1), ("B", 1e-6, 0.1), ("C", 1e-6, 0.1)]
    r = rate_check(args, scene, model, sp, orbits, 0.0)
    assert not r["kept"] and r["overrun_percent"] == pytest.approx(3.0)
    assert r["reference_orbits_m"][0] == pytest.approx(ra, rel=1e-12)
    assert r["reason"].startswith("the loop did not keep 10000 Hz: 30 of 1000 periods overran (3.00 % > "
                                  "--max-overruns 1 %), so its results are not the scene's: orbit A")
    assert "(+100 %)" in r["reason"], r["reason"]
    assert rate_check(args, scene, model, dict(sp, overruns=10), orbits, 0.0)["kept"]          # 1.00 %: kept
    args.max_overruns = None
    assert rate_check(args, scene, model, sp, orbits, 0.0) is None                             # off
    args.max_overruns, args.mode = ("percent", 1.0), "lockstep"
    assert rate_check(args, scene, model, sp, orbits, 0.0) is None                             # no clock to keep


def test_calibration_says_when_this_machine_cannot_hold_the_rate_and_what_would_fit():
    """No machine does a modal plant step and a process round trip in 1 us: at 1 MHz the
    calibration must say 'cannot' and suggest a lower rate and lockstep (no timing asserted)."""
    import dataclasses
    from ambhil.bridge.cli.rt_check import calibrate
    scene, model, args = _modal()
    fast = dataclasses.replace(scene, controller=dataclasses.replace(scene.controller, sample_rate=1e6))
    c = calibrate(fast, model, args, n=50)
    assert c["can_hold"] is False and c["period_us"] == pytest.approx(1.0)
    assert c["step_us"]["p50"] > 0 and c["round_trip_us"]["n"] in (0, 50)
    assert c["suggest_rate_hz"] and c["suggest_rate_hz"] < 1e6
    assert c["line"].startswith("this machine cannot hold 1e+06 Hz in real time") and "--mode lockstep" in c["line"]


def test_run_fails_like_simulate_on_a_loop_predicted_to_grow(tmp_path):
    """`simulate` and `run` share one rule (ambhil.bridge.cli.simulate.not_steady): a scene whose
    sampled loop is predicted unstable (2 samples of delay: an ~846 Hz mode grows at ~34 1/s)
    has no steady orbit even before it diverges: both exit 1."""
    scene = tmp_path / "delay2.toml"
    text = Path(SCENE).read_text()
    assert "sample_rate = 10000.0\n" in text
    scene.write_text(text.replace("sample_rate = 10000.0\n", "sample_rate = 10000.0\ndelay_samples = 2\n", 1))
    sim = cli("simulate", str(scene), "--rung", "modal", "--duration", "0.02", "--out", str(tmp_path / "sim"))
    assert sim.returncode == 1 and "NOT STEADY" in sim.stdout, sim.stdout + sim.stderr
    r = cli("run", str(scene), "--rung", "modal", "--duration", "0.02", "--run-id", "grows", "--out", str(tmp_path / "run"))
    assert r.returncode == 1, r.stdout + r.stderr
    assert "FAILED     not steady: the continuous loop is stable but the sampled loop is not" in r.stdout, r.stdout
    assert sorted(f.name for f in (tmp_path / "run").iterdir()) == ["grows.failed.mcap", "grows.failed.rrd"]


def test_stale_sockets_are_removed_only_when_their_owner_is_dead(tmp_path):
    import os
    import socket
    from ambhil.bridge.process import transport as tr
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()                                             # a pid that no longer runs
    names = [f"r-{dead.pid}-plant.sock", f"r-{dead.pid}-plant.sock.lock", f"r-{dead.pid}-rec.sock",
             f"r-{os.getpid()}-plant.sock", f"r-{os.getpid()}-rec.sock.lock", "other.sock"]
    for nm in names:
        (tmp_path / nm).write_text("")
    live = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)   # a socket someone listens on
    (tmp_path / names[2]).unlink()
    live.bind(str(tmp_path / names[2]))
    live.listen()
    try:
        gone = tr.remove_stale_sockets(str(tmp_path))
    finally:
        live.close()
    assert sorted(os.path.basename(g) for g in gone) == sorted(names[:2])
    assert sorted(f.name for f in tmp_path.iterdir()) == sorted(names[2:])


def _run_until_running(tmp_path, rid, *extra):
    p = subprocess.Popen([sys.executable, "-m", "ambhil.bridge.cli", "run", SCENE, "--rung", "modal", "--duration", "600",
                          "--run-id", rid, "--out", str(tmp_path), "--json", *extra], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in p.stderr:
        if line.startswith("plant: running"):
            return p
    pytest.fail(f"ambhil run ended before running (exit {p.wait()})")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc")
@pytest.mark.parametrize("victim", ["controller", "record"])
def test_a_peer_killed_during_the_run_is_named_and_the_plant_reports_its_steps(tmp_path, victim):
    """kill -9 of the controller: the plant sees it (liveliness) and ends the run with the
    reason; kill -9 of the recorder: the plant is stopped as on Ctrl-C.  Either way the summary
    names the peer and how it died first, has the plant's own summary (steps), exit 1, and the
    recording's readable part is kept and marked."""
    import json
    import os
    import time
    rid = f"kill{victim}{os.getpid()}"
    p = _run_until_running(tmp_path, rid)
    mcap = tmp_path / f"{rid}.mcap"
    while p.poll() is None and not (mcap.exists() and mcap.stat().st_size > 200_000):
        time.sleep(0.05)
    pids = [pid for pid in _pids_with(f"--run-id {rid}") - {p.pid}
            if f" {victim} ".encode() in (Path("/proc") / str(pid) / "cmdline").read_bytes().replace(b"\0", b" ")]
    assert len(pids) == 1, pids
    os.kill(pids[0], 9)
    out, err = p.communicate(timeout=300)
    s = json.loads([ln for ln in out.splitlines() if ln.startswith("{")][-1])
    role = "recorder" if victim == "record" else "controller"
    assert p.returncode == 1 and s["failed"][0] == f"{role} killed by SIGKILL during the run", s["failed"]
    assert not any("gave no summary" in f for f in s["failed"]), s["failed"]
    assert s["plant"]["steps"] > 0 and s["plant"]["wall_s"] > 0
    if role == "controller":
        assert "controller lost" in s["plant"]["fault"], s["plant"]
    else:
        assert s["plant"]["end_reason"] == "interrupted" and s["plant"]["fault"] is None
    assert [Path(f).name for f in s["files"]][:1] == [f"{rid}.failed.mcap"], s["files"]


@pytest.mark.skipif(not sys.platform.startswith("linux") or os.geteuid() != 0, reason="mounting a tmpfs needs root")
def test_a_full_disk_ends_the_run_with_the_file_named_and_marked(tmp_path):
    """--out on a 2 MB tmpfs: the recorder cannot write, says which file and why, the plant is
    stopped with its summary, the truncated recording is kept and marked .failed, exit 1."""
    import json
    full = tmp_path / "full"
    full.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(full)], capture_output=True).returncode:
        pytest.skip("mounting a tmpfs is not permitted here")
    try:
        r = cli("run", SCENE, "--rung", "modal", "--duration", "30", "--run-id", "full", "--out", str(full), "--json")
        s = json.loads(r.stdout.strip().splitlines()[-1])
        assert r.returncode == 1, r.stdout + r.stderr
        assert s["failed"][0] == f"recorder: cannot write {full}/full.mcap: No space left on device", s["failed"]
        assert s["plant"]["steps"] > 0 and s["plant"]["end_reason"] == "interrupted"
        assert [f.name for f in full.iterdir()] == ["full.failed.mcap"] and s["files"] == [str(full / "full.failed.mcap")]
        assert "Traceback" not in r.stderr
    finally:
        subprocess.run(["umount", str(full)])


def test_a_neutral_mode_is_not_a_growing_loop():
    """The rigid rung's free mode sits at mu = 1 to the last bits ('grows at 4.44e-12 1/s'):
    within ambhil.loop.numerics.STABILITY_TOL that is not growth, so neither `simulate` nor `run` calls
    the loop NOT STEADY, and no latency-margin warning comes from it; a real growth still counts."""
    from ambhil.loop import sampled as sd
    from ambhil.loop.scene import load_scene
    from ambhil.loop.system import compile_system
    from ambhil.loop.timing_study import precheck
    assert sd.Stability(1.0 + 4.4e-16, 4.4e-12, 0.0, 1.0, 0.0).stable
    assert not sd.Stability(1.0 + 1e-6, 1e-2, 0.0, 1.0, 0.0).stable
    m = compile_system(load_scene(SCENE), rung="rigid")
    pre = precheck(m, 327.19)
    assert pre.stable and pre.line is None, pre


def test_calibration_round_trip_goes_over_zenoh_and_survives_a_dead_peer():
    """The calibration's round trip is the run's own transport (zenoh, Unix socket): n finite
    round trips, the calibration line says zenoh, no socket file left; a peer that dies at
    start-up (no CPU 9999 to pin to) gives no figure at once instead of a hang."""
    import glob
    import os
    from ambhil.bridge.cli import rt_check
    from ambhil.bridge.process import transport as tr
    x = rt_check.zenoh_round_trip_us(50, None, 1e-3)
    assert len(x) == 50 and np.all(np.isfinite(x)) and np.all(x > 0)
    assert not glob.glob(os.path.join(tr.socket_dir(), f"calibration-{os.getpid()}.sock*"))
    assert len(rt_check.zenoh_round_trip_us(10, [9999], 1e-3)) == 0
    scene, model, args = _modal()
    c = rt_check.calibrate(scene, model, args, n=30)
    assert c["round_trip_us"]["over"] == "zenoh" and "zenoh round trip p50" in c["line"]
