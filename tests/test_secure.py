"""Secure runs (bridge/process/security.py): mutual TLS on loopback with certificates made for the test,
and zenoh access control that lets each role put only its own keys of the run (its own event key;
the recorder nothing)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

TESTS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(TESTS)

from ambhil.bridge import protocol as pr
from ambhil.bridge.process import transport as tr
from ambhil.bridge.process import security

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None,
                                reason="openssl not on PATH: certificates cannot be made")


def _open(folder, role, run_id, listen=None, connect=None):
    c = tr.make_config([listen] if listen else [], [connect] if connect else [], gossip=False,
                       extra=security.session_extra(folder, role, run_id))
    import zenoh
    return zenoh.open(c)


def _until(cond, what, timeout=120.0):
    t_end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < t_end, what
        time.sleep(0.01)


def test_mutual_tls_and_acl_let_only_the_controller_drive_the_currents(tmp_path):
    good, other = str(tmp_path / "certs"), str(tmp_path / "other-ca")
    security.make_certs(good)
    security.make_certs(other)                 # same names, another CA
    run = "secure1"
    K = pr.keys(run)
    ep = f"tls/127.0.0.1:{tr.free_port()}"
    plant = _open(good, "plant", run, listen=ep)
    got = []
    subs = [plant.declare_subscriber(K.currents, lambda s: got.append(("cur", s.payload.to_bytes()))),
            plant.declare_subscriber(K.events, lambda s: got.append(("ev", s.payload.to_bytes())))]
    ctl = _open(good, "controller", run, connect=ep)
    rec = _open(good, "recorder", run, connect=ep)
    rogue = _open(other, "controller", run, connect=ep)    # a controller cert of another CA
    try:
        seen = []
        rsub = rec.declare_subscriber(f"{K.root}/**", lambda s: seen.append(str(s.key_expr)))
        pub_c = ctl.declare_publisher(K.currents)
        _until(lambda: pub_c.matching_status.matching, "the controller never linked to the plant")
        pub_c.put(b"from-controller")
        _until(lambda: ("cur", b"from-controller") in got, "the controller's currents never arrived")
        # each role puts only its own event key: the controller's events arrive
        ctl.put(pr.event_key(run, "controller"), b"controller-event")
        _until(lambda: ("ev", b"controller-event") in got, "the controller's event never arrived")
        # the recorder's certificate may put nothing at all (protocol 3), the controller's not the
        # plant's events; a query on the same link afterwards (allowed: the pairing challenges are
        # queries on pair/**), answered by the plant, proves the puts were dropped, not delayed
        probe = pr.pair_key(run, "plant", bytes(16))
        queried = []

        def _answer(q):
            queried.append(1)
            q.reply(probe, b"ok")
        qa = plant.declare_queryable(probe, _answer)
        rec.put(K.currents, b"from-recorder")
        rec.put(pr.event_key(run, "controller"), b"recorder-event")
        ctl.put(pr.event_key(run, "plant"), b"controller-as-plant")
        for who in (rec, ctl):
            n = len(queried)
            _until(lambda: [r for r in who.get(probe, timeout=10.0) if r.ok] and len(queried) > n,
                   "the plant's pairing queryable never answered")
        assert ("cur", b"from-recorder") not in got, "ACL let the recorder's certificate drive the coils"
        assert ("ev", b"recorder-event") not in got, "ACL let the recorder's certificate put an event"
        assert ("ev", b"controller-as-plant") not in got, "ACL let the controller put the plant's events"
        tr.close_quietly(qa)
        # nobody may put outside the run's keys
        ctl.put("ambhil/another-run/controller/currents", b"x")
        # the plant's sensors reach the recorder (declarations within the run are allowed)
        plant.put(K.sensors, b"sample")
        _until(lambda: K.sensors in seen, "the recorder did not get the plant's sample")
        # a certificate of another CA never gets a link: nothing it sends arrives
        rogue.put(K.currents, b"from-other-ca")
        pub_c.put(b"marker")
        _until(lambda: ("cur", b"marker") in got, "marker")
        assert ("cur", b"from-other-ca") not in got
        assert not list(rogue.info.peers_zid()), "a peer with a foreign CA's certificate connected"
        assert str(rogue.zid()) not in {str(z) for z in plant.info.peers_zid()}
        # plaintext TCP to a TLS endpoint: no link either
        plain = tr.open_session(connect=ep.replace("tls/", "tcp/"), gossip=False)
        try:
            assert not list(plain.info.peers_zid())
        finally:
            plain.close()
        tr.close_quietly(rsub)
    finally:
        for o in subs:
            tr.close_quietly(o)
        for s in (rogue, rec, ctl, plant):
            tr.close_quietly(s)


def test_secure_run_equals_the_plain_run_bit_for_bit(tmp_path):
    """`ambhil run --secure DIR`: TLS + access control change the transport, not one number."""
    from ambhil.bridge.recording.load import load_run
    certs = str(tmp_path / "certs")
    ambhil = os.path.join(os.path.dirname(sys.executable), "ambhil")
    subprocess.run([ambhil, "certs", certs], check=True, capture_output=True, timeout=120)
    scene = os.path.join(ROOT, "scenes", "paper_2amb.toml")
    base = [ambhil, "run", scene, "--duration", "0.02", "--json", "--placement", "none",
            "--out", str(tmp_path)]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    for rid, extra in (("plain", []), ("secure", ["--secure", certs])):
        r = subprocess.run(base + ["--run-id", rid] + extra, env=env, capture_output=True,
                           text=True, timeout=900)
        assert r.returncode == 0, r.stderr[-2000:]
    a, b = load_run(str(tmp_path / "plain.mcap")), load_run(str(tmp_path / "secure.mcap"))
    assert len(a["currents"]["v"]) == 200
    assert np.array_equal(a["currents"]["v"], b["currents"]["v"])
    assert np.array_equal(a["sensors"]["v"], b["sensors"]["v"])
    bad = subprocess.run(base + ["--run-id", "nocerts", "--secure", str(tmp_path / "none")],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "missing" in bad.stderr and "ambhil certs" in bad.stderr, bad.stderr
