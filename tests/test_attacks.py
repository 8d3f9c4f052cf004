"""The attacks of issue 31, replayed against real runs by an outsider's raw zenoh script
(tests/attacks/rogue.py: zenoh, struct, hashlib, written from docs/protocol.md, no ambhil code).

Each test starts a real run (lockstep unless said, TCP loopback, a key from ``ambhil key`` or
the one ``ambhil run`` makes), lets the rogue join before the real controller (the run cannot be
over before it is there), and checks what an operator of the rig relies on: the trajectory is
bit-identical to an unattacked run of the same scene, the rejection is counted by reason in the
summaries and in the recording's ``ambhil.run_end``, ``--strict`` fails, and the recording holds
the forged traffic only under foreign topics.  Wall times are marked per test (busy 2-core
machine); the whole file takes about 4 minutes.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections import Counter

import numpy as np
import pytest

TESTS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(TESTS)
sys.path.insert(0, TESTS)

from test_nodes import endpoint, wait_listening  # noqa: E402

ROGUE = os.path.join(TESTS, "attacks", "rogue.py")
CLI = [sys.executable, "-m", "ambhil.bridge.cli"]
SCENE = os.path.join(ROOT, "scenes", "paper_2amb.toml")
DURATION, N = "0.2", 2000          # lockstep steps of the scene at 10 kHz
ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1")


# ------------------------------------------------------------------------- helpers
def _json_line(text: str) -> dict:
    lines = [ln for ln in (text or "").splitlines() if ln.startswith("{")]
    assert lines, f"no JSON summary in {text[-1500:]!r}"
    return json.loads(lines[-1])


def _wait(p, timeout=240):
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
        raise AssertionError(f"{p.args[:4]} still running after {timeout} s: {err[-2000:]}")
    return p.returncode, out, err


_BRIEF = ("steps", "fault", "rejected", "duplicates", "gaps", "strangers", "foreign_events", "restarts",
          "wall_s", "auth", "status", "steps_recorded", "foreign_copied")


def _brief(s):
    return {k: s[k] for k in _BRIEF if s and k in s}


def _log(run_id, **facts):
    """What the attack did and what the run said (shown with pytest -s)."""
    sys.stderr.write(f"[attack {run_id}] {json.dumps(facts)}\n")


def key_file(tmp_path) -> str:
    path = str(tmp_path / "run.key")
    subprocess.run(CLI + ["key", path], check=True, capture_output=True, timeout=60, env=ENV)
    return path


def start_rogue(tmp_path, attack, run_id, **cfg):
    stats = str(tmp_path / f"rogue-{attack}.json")
    cfg = {"attack": attack, "run": run_id, "stats": stats, "max_s": 240, "stop": stats + ".stop", **cfg}
    p = subprocess.Popen([sys.executable, ROGUE, json.dumps(cfg)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=ENV)
    return p, stats


def rogue_stats(p, stats) -> dict:
    """The rogue's counts, once the run is over (it is told to stop: it may not see the plant
    go if a token reached it over more than one link)."""
    open(stats + ".stop", "w").close()
    _, _, err = _wait(p, 60)
    assert os.path.exists(stats), f"the rogue wrote no stats: {err[-2000:]}"
    with open(stats) as fh:
        st = json.load(fh)
    assert "error" not in st, st
    return st


def _kill(*procs):
    for p in procs:
        if p is not None and p.poll() is None:
            p.kill()
            p.communicate()


def wait_file(path, procs, timeout=180):
    t_end = time.monotonic() + timeout
    while not os.path.exists(path):
        for q in procs:
            assert q.poll() is None, f"{q.args[:4]} ended early: {q.communicate()}"
        assert time.monotonic() < t_end, f"{path} never appeared"
        time.sleep(0.02)


def recording(path) -> dict:
    """Topics (message counts), run_end, events of the run's channel, vectors."""
    from mcap.reader import make_reader
    from ambhil.bridge.recording.load import load_run
    with open(path, "rb") as f:
        r = make_reader(f)
        ends = [dict(m.metadata) for m in r.iter_metadata() if m.name == "ambhil.run_end"]
        topics = Counter(ch.topic for _, ch, _ in r.iter_messages())
    run = load_run(path)
    return {"topics": topics, "run_end": ends[-1] if ends else {}, "run": run,
            "rejected": json.loads((ends[-1] if ends else {}).get("rejected") or "{}")}


def same_trajectory(rec, clean):
    a, b = clean["run"], rec["run"]
    assert len(b["currents"]["v"]) == len(b["sensors"]["v"]) == N, rec["topics"]
    assert rec["topics"]["/ambhil/controller/currents"] == N, rec["topics"]
    assert np.array_equal(a["sensors"]["v"], b["sensors"]["v"]), "the attack changed the orbit"
    assert np.array_equal(a["currents"]["v"], b["currents"]["v"]), "a forged current reached the coils"


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """The unattacked run every lockstep attack is compared with (about 15 s)."""
    d = tmp_path_factory.mktemp("clean")
    r = subprocess.run(CLI + ["run", SCENE, "--duration", DURATION, "--json", "--placement", "none",
                              "--run-id", "clean", "--out", str(d), "--transport", "tcp"],
                       capture_output=True, text=True, timeout=600, env=ENV)
    assert r.returncode == 0, r.stderr[-2000:]
    return recording(str(d / "clean.mcap"))


def attacked_run(tmp_path, run_id, attack, *, key="file", strict=True, mode="lockstep",
                 scene=SCENE, duration=DURATION, wait=("plant", "recorder"), extra=(), **cfg):
    """`ambhil run` with the rogue: it connects to the plant's endpoint (and by gossip to the
    recorder) and listens on an endpoint the controller connects to; the controller is started
    only once the rogue is armed (it has seen the tokens of ``wait``: the plant's link is all
    that attacks on the loop need; a link to the recorder, by gossip, only the forged events).
    Returns (rc, summary, rogue stats, recording)."""
    ep, ep_r = endpoint(), endpoint()
    ready = str(tmp_path / f"{run_id}.ready")
    ctl = (f"sh -c 'while [ ! -e {ready} ]; do sleep 0.02; done; exec {sys.executable} -m "
           f"ambhil.bridge.cli controller {{scene}} --run-id {{run_id}} --connect {{connect}} {ep_r} --json'")
    argv = CLI + ["run", scene, "--duration", duration, "--json", "--placement", "none",
                  "--run-id", run_id, "--out", str(tmp_path), "--transport", "tcp", "--endpoint", ep,
                  "--mode", mode, "--controller", ctl, "--start-timeout", "180", *extra] \
        + (["--strict"] if strict else [])
    # (the controller starts only once the rogue is armed: on a loaded machine the rogue's own
    # start took longer than the default 30 s the plant waits for an absent controller)
    argv += {"file": ["--key-file", key_file(tmp_path)], "run": [], "insecure": ["--insecure"]}[key]
    run = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    rogue = None
    try:
        wait_listening(ep, 180)
        rogue, stats = start_rogue(tmp_path, attack, run_id, connect=[ep], listen=[ep_r],
                                   ready=ready, wait=list(wait), **cfg)
        rc, out, err = _wait(run, 300)
    except BaseException:
        _kill(run, rogue)
        raise
    st = rogue_stats(rogue, stats)
    summ = _json_line(out)
    _log(run_id, rc=rc, rogue=st, plant=_brief(summ.get("plant")), controller=_brief(summ.get("controller")),
         recorder=_brief(summ.get("recorder")))
    mcap = next((p for p in (tmp_path / f"{run_id}.mcap", tmp_path / f"{run_id}.failed.mcap")
                 if p.exists()), None)
    assert mcap is not None, err[-2000:]
    return rc, summ, st, recording(str(mcap)), err


def standalone_run(tmp_path, run_id, attack, *, key=True, secure=None, **cfg):
    """Standalone processes in the deployment order of docs/hil.md: recorder, then
    `ambhil plant --listen` (waiting for the recorder), then the rogue joins (connects to plant
    and recorder, listens), then the real controller (connects to all three).  Returns
    (plant, controller, recorder summaries, rogue stats, recording)."""
    scheme = "tls" if secure else "tcp"
    ep_p, ep_rec, ep_r = (endpoint().replace("tcp/", f"{scheme}/") for _ in range(3))
    common = ["--run-id", run_id, "--json"]
    if key:
        common += ["--key-file", key_file(tmp_path)]
    procs = []      # every process started, the rogue too

    def start(role, *args):
        extra = ["--secure", secure] if secure else []
        procs.append(subprocess.Popen(CLI + [role, SCENE, *args, *common, *extra], stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True, env=ENV))
        return procs[-1]
    ready = str(tmp_path / f"{run_id}.ready")
    try:
        rec = subprocess.Popen(CLI + ["record", "--run-id", run_id, "--json", "--out", str(tmp_path),
                                      "--listen", ep_rec] + common[3:]
                               + (["--secure", secure] if secure else []),
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
        procs.append(rec)
        wait_listening(ep_rec, 180)
        plant = start("plant", "--listen", ep_p, "--connect", ep_rec, "--duration", DURATION,
                      "--wait-recorder")
        wait_listening(ep_p, 180)
        tls = None
        if secure:
            tls = {"root_ca_certificate": f"{secure}/ca.pem", "enable_mtls": True,
                   "listen_private_key": f"{secure}/recorder.key", "listen_certificate": f"{secure}/recorder.pem",
                   "connect_private_key": f"{secure}/recorder.key", "connect_certificate": f"{secure}/recorder.pem"}
        rogue, stats = start_rogue(tmp_path, attack, run_id, connect=[ep_p, ep_rec], listen=[ep_r],
                                   ready=ready, wait=["plant", "recorder"], tls=tls,
                                   gossip=not secure, **cfg)
        procs.append(rogue)
        wait_file(ready, [rogue, plant, rec])
        ctl = start("controller", "--connect", ep_p, ep_rec, ep_r)
        res = [_wait(p, 300) for p in (plant, ctl, rec)]
    except BaseException:
        _kill(*procs)
        raise
    st = rogue_stats(rogue, stats)
    sums = [_json_line(out) if out.strip() else {"rc": rc, "stderr": err[-2000:]} for rc, out, err in res]
    _log(run_id, rogue=st, plant=_brief(sums[0]), controller=_brief(sums[1]), recorder=_brief(sums[2]))
    return (*sums, st, recording(str(tmp_path / f"{run_id}.mcap")))


def says_rejected(rec, reason="auth"):
    """The recording says what was rejected: its run_end counts it by reason (issue 31, item 6:
    "rejected traffic counted by reason in the summary and in ambhil.run_end")."""
    assert rec["rejected"].get(reason, 0) >= 1, (f"the recording's run_end does not count the "
                                                 f"{reason!r} rejections: {rec['run_end']}")


def auth_rejections(rec) -> list:
    return [e for e in rec["run"]["events"] if e.kind_name == "REJECTED" and ": auth:" in e.text]


# ------------------------------------------------------------------------- the attacks
def test_forged_id_currents_are_rejected_auth_and_change_nothing(tmp_path, clean):
    """1 (about 20 s): replies under the controller's copied id, +-3.9 A, a MAC the rogue cannot
    compute: every one rejected ``auth``, the orbit bit-identical, --strict fails, the recording's
    currents are the genuine ones and its run_end says failed with the rejections counted."""
    rc, summ, st, rec, err = attacked_run(tmp_path, "forged", "forged_id", wait=("plant",))
    plant = summ["plant"]
    assert st["sent"] > 0, f"the rogue never answered a sample: {st}"
    assert set(plant["rejected"]) == {"auth"} and 1 <= plant["rejected"]["auth"] <= st["sent"], plant["rejected"]
    assert plant["fault"] is None and plant["steps"] == N, plant
    assert rc != 0, f"--strict passed a run with forged traffic: {err[-1500:]}"
    same_trajectory(rec, clean)
    assert rec["run_end"]["status"] == "failed" and rec["run_end"]["auth"] == "key", rec["run_end"]
    assert auth_rejections(rec), "the rejections are not in the recording"
    assert rec["topics"]["/ambhil/foreign/controller/currents"] >= 1, rec["topics"]
    says_rejected(rec)


def test_forged_id_in_real_time_at_2khz_is_rejected_and_the_run_completes(tmp_path):
    """1 in real time (about 15 s): the light rigid rotor of the network runs
    (scenes/net_rigid_1khz.toml) at 2 kHz, the rogue answering every sample under the copied id:
    the run completes, every forged reply is rejected ``auth``.  (The paper scene at 2 kHz is
    marginal, orbit A 37 um in process: with two busy CPUs its overruns grew it to touchdown;
    the rigid rotor keeps its orbit at 1.4 % of the clearance, so only the attack can move it.)"""
    text = open(os.path.join(ROOT, "scenes", "net_rigid_1khz.toml")).read()
    text = text.replace("sample_rate = 1000.0", "sample_rate = 2000.0")
    assert "sample_rate = 2000.0" in text
    scene = tmp_path / "rt2k.toml"
    scene.write_text(text)
    # the rogue is one more busy process on the machine: a 2 s reply timeout (not 10 periods)
    # keeps a scheduling stall of the controller on a loaded machine from ending the run; the
    # rogue needs only the plant's link (its forged replies go to the plant)
    rc, summ, st, rec, err = attacked_run(tmp_path, "forgedrt", "forged_id", mode="realtime",
                                          scene=str(scene), duration="0.25", wait=("plant",),
                                          extra=["--reply-timeout", "2000"])
    plant = summ["plant"]
    assert st["sent"] > 0, st
    assert plant["fault"] is None and plant["steps"] == 500, plant
    assert set(plant["rejected"]) == {"auth"} and plant["rejected"]["auth"] >= 1, plant["rejected"]
    assert rc != 0, err[-1500:]
    # the recording holds the controller's replies only, never a forged one: at most one per
    # sample (a reply still in flight when the run ended is missing, so possibly fewer)
    got = rec["topics"]["/ambhil/controller/currents"]
    assert 500 - 1 - plant["held"] <= got <= 500, (got, plant["held"], rec["topics"])
    says_rejected(rec)


def test_replayed_record_batches_are_rejected_and_stay_out_of_the_recording(tmp_path, clean):
    """2 (about 20 s; the run's own per-run key): CurrentCommands captured from the plant's
    RecordBatches, re-put with the live seq patched in (``auth``) and verbatim (stale: rejected
    or counted as duplicates, never applied); the recording holds exactly n currents."""
    rc, summ, st, rec, err = attacked_run(tmp_path, "replay", "replay", key="run", wait=("plant",))
    plant = summ["plant"]
    assert st["captured"] > 0 and st["patched"] > 0 and st["verbatim"] > 0, st
    assert plant["rejected"].get("auth", 0) >= 1, plant["rejected"]
    assert plant["rejected"].get("sequence", 0) >= 1, plant       # the verbatim ones: stale
    assert plant["fault"] is None and plant["steps"] == N, plant
    assert rc != 0, err[-1500:]
    same_trajectory(rec, clean)
    assert rec["run_end"]["currents_recorded"] == str(N), rec["run_end"]
    says_rejected(rec)


def test_plus_one_flood_is_rejected_and_strict_fails(tmp_path, clean):
    """3 (about 20 s): forged-id replies with seq = last + 1, zero MAC: ``auth``, orbit
    unchanged, --strict exits non-zero."""
    rc, summ, st, rec, err = attacked_run(tmp_path, "plus1", "plus1", mac="zeros", wait=("plant",))
    plant = summ["plant"]
    assert st["sent"] > 0, st
    assert set(plant["rejected"]) == {"auth"}, plant["rejected"]
    assert rc != 0, err[-1500:]
    same_trajectory(rec, clean)
    assert rec["run_end"]["status"] == "failed", rec["run_end"]
    says_rejected(rec)


def test_seq_stall_sample_is_rejected_auth_and_does_not_stall(tmp_path, clean):
    """4, keyed (about 20 s): one SensorSample under the plant's id with seq = live + 60000:
    rejected ``auth`` by the controller, no gap, no wait for the reply timeout."""
    rc, summ, st, rec, err = attacked_run(tmp_path, "stall", "seq_stall", after=20, wait=("plant",))
    ctl, plant = summ["controller"], summ["plant"]
    assert st["forged_seq"] is not None and st["sent"] == 1, st
    assert ctl["rejected"] == {"auth": 1}, ctl["rejected"]
    assert ctl["gaps"] == 0 and ctl["steps"] == N, ctl
    assert plant["fault"] is None and plant["steps"] == N and plant["wall_s"] < 30, plant
    assert rc != 0, err[-1500:]
    same_trajectory(rec, clean)
    says_rejected(rec)


def test_seq_stall_in_an_unauthenticated_run_does_not_stall_the_controller(tmp_path):
    """4, no key on loopback (about 20 s): the forger computes the MAC (the all-zero secret and
    the nonces of RunMeta): the controller answers it as a gap and resynchronises on the next
    genuine sample (spec 5): the run completes in normal time, not at the reply timeout."""
    sp, sc, sr, st, rec = standalone_run(tmp_path, "stallnone", "seq_stall", key=False, unauth=True,
                                         after=20)
    assert st["forged_seq"] is not None and st["mac"].startswith("valid"), st
    assert sp.get("fault") is None and sp.get("steps") == N, sp
    assert sp["wall_s"] < 30, sp
    assert sc.get("fault") is None and sc["steps"] >= N and sc["auth"] == "none", sc
    assert sc["gaps"] >= 1 or sc["rejected"], sc
    assert sr["status"] == "completed" and sr["steps_recorded"] == N, sr


def test_forged_events_are_not_obeyed_and_recorded_as_foreign(tmp_path, clean):
    """5 (about 20 s): FAULT_INJECTED controller_restart and RUN_END "completed" under the
    plant's copied id on events/plant: no restart, controller and recorder run to the end, the
    events are counted and recorded under /ambhil/foreign/events, never /ambhil/events."""
    rc, summ, st, rec, err = attacked_run(tmp_path, "events", "events", every=5, count=200,
                                          end_after=300)
    ctl = summ["controller"]
    assert st["restarts"] > 0 and st["run_ends"] == 1, st
    assert ctl["restarts"] == 0 and ctl["steps"] == N and ctl["fault"] is None, ctl
    assert ctl["foreign_events"] >= 1, ctl
    assert ctl["rejected"].get("auth", 0) >= 1, ctl["rejected"]
    assert rc != 0, err[-1500:]
    same_trajectory(rec, clean)
    assert rec["run_end"]["steps_recorded"] == str(N), rec["run_end"]
    assert rec["topics"]["/ambhil/foreign/events"] >= 1, rec["topics"]
    says_rejected(rec)
    evs = rec["run"]["events"]
    assert not [e for e in evs if e.kind_name == "FAULT_INJECTED"], "a forged fault is recorded as the plant's"
    ends = [e for e in evs if e.kind_name == "RUN_END"]
    assert len(ends) == 1 and json.loads(ends[0].text)["steps"] == N, [e.text for e in ends]


def test_first_joiner_is_a_stranger_and_the_real_controller_pairs(tmp_path, clean):
    """6 (about 25 s): `ambhil plant --listen --key-file` started first, a rogue joins first as
    controller (tokens, a pairing queryable answering garbage, replies under its own id), then
    the real controller: the plant pairs with the real one and names the stranger."""
    sp, sc, sr, st, rec = standalone_run(tmp_path, "joiner", "first_joiner")
    assert st["challenges"] >= 1, st
    assert sp.get("fault") is None and sp["steps"] == N, sp
    assert st["me"] in sp["strangers"], sp
    assert sp["paired_controller"] != st["me"], sp
    assert sc["steps"] == N and sc.get("fault") is None, sc
    assert sr["status"] == "completed", sr
    same_trajectory(rec, clean)


def test_early_announcer_does_not_deny_the_run(tmp_path, clean):
    """7 (about 20 s): two peer/controller tokens announced before the real controller: no
    "2 controllers announced" refusal, the run is normal, the strangers are named."""
    rc, summ, st, rec, err = attacked_run(tmp_path, "announce", "announcer", key="run",
                                          strict=False, count=2, wait=("plant",))
    plant = summ["plant"]
    assert plant["fault"] is None and plant["steps"] == N, plant
    assert len(plant["strangers"]) == 2, plant
    assert rc == 0, err[-1500:]
    same_trajectory(rec, clean)


def test_recorder_certificate_can_neither_end_nor_stall_a_secure_run(tmp_path, clean):
    """8 (about 30 s): `--secure` plus a key; a session with the recorder's certificate joins
    after the plant, poses as controller (tokens, garbage proofs) and puts RUN_END on
    events/plant and events/controller: not paired with (stranger), the run not stalled, the
    RUN_ENDs denied by the ACL or rejected by MAC, the recorder records every step."""
    certs = str(tmp_path / "certs")
    subprocess.run(CLI + ["certs", certs], check=True, capture_output=True, timeout=120, env=ENV)
    sp, sc, sr, st, rec = standalone_run(tmp_path, "certrec", "recorder_cert", secure=certs,
                                         end_after=200)
    assert st["run_ends"] >= 1, st
    assert sp.get("fault") is None and sp["steps"] == N and sp["wall_s"] < 30, sp
    assert sp["paired_controller"] != st["me"], sp
    # the ACL lets a recorder's certificate declare only recorder tokens and queryables
    # (bridge/process/security.py): its controller tokens never reach the plant, which never
    # challenges it, so there is no stranger to name either
    assert st["challenges"] == 0 and st["me"] not in sp["strangers"], (st, sp["strangers"])
    assert sc["steps"] == N and sc.get("fault") is None and sc["restarts"] == 0, sc
    assert sr["status"] == "completed" and sr["steps_recorded"] == N, sr
    same_trajectory(rec, clean)
