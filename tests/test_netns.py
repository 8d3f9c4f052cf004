"""Plant and controller on two hosts: two network namespaces joined by a veth link with a
delay and jitter on it (tests/netns.py: netem where the kernel has it, else a relay namespace),
zenoh peer to peer (the plant listens on its address, controller and recorder connect to it).

- the ephemeral listener of a connecting session follows the route to the plant (a loopback
  one is unreachable from the other host: the recorder then missed every controller message);
- lockstep across the delayed link records the very currents and displacements of a loopback
  lockstep run of the same scene and steps (bit for bit);
- real time across the delayed link completes and its recorded round trips are at least the
  two one-way delays (an inequality on the link's delay, never on the machine's speed).

Skipped, with the reason, where namespaces cannot be made (not root, no `ip netns`)."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import netns

ROOT = Path(__file__).resolve().parents[1]
PAPER = str(ROOT / "scenes" / "paper_3amb.toml")
LIGHT = str(ROOT / "scenes" / "net_rigid_1khz.toml")
DELAY_US, JITTER_US = 100.0, 50.0

_why = netns.unavailable()
needs_netns = pytest.mark.skipif(_why is not None, reason=f"network namespaces: {_why}")


def test_ephemeral_listener_on_loopback_for_a_loopback_plant():
    from ambhil.bridge.process.transport import ephemeral_endpoints
    assert ephemeral_endpoints("tcp/127.0.0.1:7447") == ["tcp/127.0.0.1:0"]
    assert ephemeral_endpoints(None) == ["tcp/127.0.0.1:0"]
    assert ephemeral_endpoints("tls/10.0.0.1:7447") == ["tcp/127.0.0.1:0"]   # tls: explicit --listen


@needs_netns
def test_ephemeral_listener_follows_the_route_to_the_plant():
    code = "from ambhil.bridge.process.transport import ephemeral_endpoints as e; import sys; print(e(sys.argv[1:]))"
    with netns.NetPair("route") as net:
        p = net.popen("controller", [sys.executable, "-c", code, net.endpoint("plant", 7447),
                                     "tcp/127.0.0.1:7448"], text=True)
        out, err = p.communicate(timeout=60)
    assert out.strip() == str([net.endpoint("controller", 0), "tcp/127.0.0.1:0"]), out + err


def _check_ok(res):
    for role in ("plant", "controller", "recorder"):
        s, err, code = res[role]
        assert code == 0 and s is not None, f"{role} exit {code}: {(s or {}).get('fault')}; {err[-2000:]}"
        assert not s.get("fault"), f"{role}: {s['fault']}"
    assert res["recorder"][0]["status"] == "completed", res["recorder"][0]


@needs_netns
def test_lockstep_across_a_delayed_link_equals_loopback(tmp_path):
    from ambhil.bridge.recording.load import load_run
    n = 500
    lo = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "run", PAPER, "--rung", "modal", "--duration", "0.05",
                         "--run-id", "loop", "--out", str(tmp_path)], capture_output=True, text=True, cwd=ROOT,
                        timeout=600)
    assert lo.returncode == 0, lo.stdout + lo.stderr
    with netns.NetPair("lock", DELAY_US, JITTER_US) as net:
        res = net.run(PAPER, "net", str(tmp_path), plant_args=["--rung", "modal", "--duration", "0.05"])
    _check_ok(res)
    a, b = load_run(str(tmp_path / "loop.mcap")), load_run(str(tmp_path / "net.mcap"))
    assert b["sensors"]["v"].shape == (n, 6) and b["currents"]["v"].shape == (n, 6)   # 3 AMBs x (x, y)
    assert np.array_equal(a["sensors"]["v"], b["sensors"]["v"])      # bit for bit
    assert np.array_equal(a["currents"]["v"], b["currents"]["v"])
    assert np.abs(b["sensors"]["v"]).max() > 1e-7                       # the rotor moved
    # and the link was the slow one: every round trip crossed it twice
    rtt = b["timing"]["rtt_ns"]
    assert np.median(rtt[rtt > 0]) >= 2 * DELAY_US * 1e3, np.median(rtt)


@needs_netns
def test_realtime_across_a_delayed_link_sees_the_delay(tmp_path):
    from ambhil.bridge.protocol import FLAG_HELD, FLAG_WARMUP
    from ambhil.bridge.recording.load import load_run
    from ambhil.bridge.cli.study_timing import measured_latency
    # 500 Hz: the round trip over the relay link (several hundred us on a loaded 2-core machine)
    # fits the 2 ms period.  Gap 1 mm instead of 0.5: an 8x weaker negative stiffness, so the
    # rotor survives the held periods of a stalled machine (open loop it diverges 2.8x slower,
    # and has twice the room: touchdown from its 1.3 um orbit takes > 100 ms of holding);
    # still stable with 2.2 ms of latency margin at this rate (study timing)
    scene = tmp_path / "net_500hz.toml"
    scene.write_text(Path(LIGHT).read_text().replace("sample_rate = 1000.0", "sample_rate = 500.0")
                     .replace("gap = 5e-4", "gap = 1e-3"))
    with netns.NetPair("rt", DELAY_US, JITTER_US) as net:
        # reply timeout: a stall of the loaded test machine is counted (held), not fatal
        res = net.run(str(scene), "rt", str(tmp_path), mode="realtime",
                      plant_args=["--duration", "0.5", "--reply-timeout", "5000"])
    sp = res["plant"][0]
    tim = load_run(str(tmp_path / "rt.mcap"))["timing"]
    if sp is not None and "reached the stator" in (sp.get("fault") or ""):
        # once in a full-suite run on the shared VM (load ~6) the plant faulted at step 208 of 250:
        # a touchdown is what a stall of the controller side does to this open-loop-unstable
        # rotor while the plant runs on, holding the last currents.  Allowed only as that: held
        # periods just before it; the transport and the link are still checked below.
        k = sp["steps"]
        held = int(((tim["flags"][max(0, k - 100):k] & FLAG_HELD) != 0).sum())
        assert held >= 10, f"touchdown without a stall (held {held} of the last 100 periods): {sp['fault']}"
        for role in ("controller", "recorder"):
            assert res[role][2] == 0 and res[role][0] is not None, f"{role}: {res[role][1][-2000:]}"
    else:
        _check_ok(res)
        assert sp["steps"] == 250
    assert sp["mode"] == "realtime"
    ok = ((tim["flags"] & (FLAG_WARMUP | FLAG_HELD)) == 0) & (tim["rtt_ns"] > 0)
    assert ok.sum() > 50, f"only {ok.sum()} answered periods"
    assert np.median(tim["rtt_ns"][ok]) >= 2 * DELAY_US * 1e3
    lat = measured_latency(str(tmp_path / "rt.mcap"))        # what `study timing --jitter-from` reads
    assert np.median(lat.samples) >= 2 * DELAY_US * 1e-6


@needs_netns
def test_namespaces_are_removed_also_on_failure():
    names = None
    with pytest.raises(RuntimeError, match="boom"):
        with netns.NetPair("fail", DELAY_US, JITTER_US) as net:
            names = set(net.ns.values())
            raise RuntimeError("boom")
    left = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert names and not any(n in left for n in names), left


@needs_netns
def test_study_fed_the_measured_latency_predicts_the_divergence_it_shows(tmp_path):
    """250 Hz: the loop tolerates 1.07 ms of latency (study timing).  Over a link of 1 ms +- 0.2 ms
    each way, with the currents taking effect at their arrival, the run measures a round trip
    above 2 ms; the study, fed that recording, says mean-square unstable and growing, and the
    run ends in a touchdown.  (Load only lengthens the latency: the verdict cannot flip.)"""
    import json
    scene = tmp_path / "net_250hz.toml"
    scene.write_text(Path(LIGHT).read_text().replace("sample_rate = 1000.0", "sample_rate = 250.0"))
    with netns.NetPair("pred", 1000.0, 200.0) as net:
        res = net.run(str(scene), "far", str(tmp_path), mode="realtime",
                      plant_args=["--duration", "4", "--currents-at", "arrival", "--integrator", "zoh",
                                  "--h", "5e-5", "--reply-timeout", "5000"])
    sp, err, code = res["plant"]
    assert code == 1 and sp is not None and "reached the stator" in (sp["fault"] or ""), err[-2000:]
    assert sp["currents_at"] == "arrival"
    mcap = tmp_path / "far.mcap"
    assert mcap.exists()
    st = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "study", "timing", str(scene), "--rates", "250",
                         "--delays", "0", "--jitter-from", str(mcap), "--no-sensitivity", "--json"],
                        capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert st.returncode == 0, st.stderr
    study = json.loads(st.stdout.strip().splitlines()[-1])
    assert study["scene_point"]["stable"] and study["scene_point"]["margin_s"] < 2e-3   # stable without latency
    measured = [j for j in study["jitter"] if j["jitter"] != "none"]
    assert measured and not measured[0]["ms_stable"], measured


def test_currents_at_arrival_needs_real_time_and_no_fixed_delay():
    r = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "plant", LIGHT, "--run-id", "x", "--listen",
                        "tcp/127.0.0.1:1", "--currents-at", "arrival"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and r.stderr.strip() == ("ambhil plant: error: --currents-at arrival: only with "
                                                      "--mode realtime and without --delay (the measured arrival "
                                                      "is the latency)"), r.stderr
