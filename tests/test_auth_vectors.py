"""Shared test vectors of protocol 3's authentication (docs/protocol.md 5.3):
tests/fixtures/auth_vectors.json holds fixed inputs (secret, run id, peer ids, nonces, one message
of each kind) and what they give: K_run, K_s, the topic keys, a pairing proof, a sealed
SensorSample and CurrentCommand, an Event and a RunMeta with their attachments.

- the file equals what ambhil.bridge.protocol.auth (the reference primitives) computes, so it
  cannot drift from the implementation (and another language can test against the file alone);
- the Python example (examples/python_controller/controller.py, imported as a module) computes
  the same bytes with its own functions, and accepts / rejects the sealed sample as it must;
- the Rust example computes the same (``rust_controller --selftest-vectors FILE``; skipped when
  cargo is missing);
- the example's key file rules are those of ``auth.read_key_file``.

Regenerate the file (only when the protocol changes, with a new label or version):
``.venv/bin/python tests/test_auth_vectors.py > tests/fixtures/auth_vectors.json``.
"""
import importlib.util
import json
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from ambhil.bridge.protocol import auth

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "auth_vectors.json"
EXAMPLE = ROOT / "examples" / "python_controller" / "controller.py"
HEADER = b"\x00\x01\x00\x00"

INPUTS = {
    "secret": bytes(range(0x00, 0x20)).hex(),
    "run_id": "vec-run.1",
    "plant_id": bytes(range(0x40, 0x50)).hex(),
    "controller_id": bytes(range(0x80, 0x90)).hex(),
    "nonce_plant": bytes(range(0xa0, 0xb0)).hex(),
    "nonce_controller": bytes(range(0xc0, 0xd0)).hex(),
    "topics": ["plant/sensors", "controller/currents", "meta", "events/plant", "events/controller",
               "timing", "record"],
    "sensor_sample": {"seq": 5, "step": 6, "sim_time_ns": 600000, "publish_wall_ns": 1700000000123456789,
                      "displacement": [1e-06, -2.5e-05, 0.00030000000000000003]},
    "current_command": {"seq": 5, "step": 6, "sim_time_ns": 600000, "recv_wall_ns": 1700000000123460000,
                        "publish_wall_ns": 1700000000123461500, "current": [0.5, -1.25, 1.3333333333333335]},
    "event": {"kind": 2, "seq": 7, "step": 300, "sim_time_ns": 30000000, "wall_ns": 1700000000200000000,
              "source": "controller", "text": "{\"reason\": \"vectors\"}"},
    "run_meta": {"seq": 0, "step": 0, "sim_time_ns": 0, "wall_ns": 1700000000000000000,
                 "json": "{\"auth\":{\"mac\":\"blake2b-128\",\"mode\":\"key\",\"nonce_controller\":"
                         "\"c0c1c2c3c4c5c6c7c8c9cacbcccdcecf\",\"nonce_plant\":\"a0a1a2a3a4a5a6a7a8a9aaabacadaeaf\"},"
                         "\"n_axes\":3,\"run_id\":\"vec-run.1\"}"},
}


# ------------------------------------------------------------------ the reference (auth.py)
def _cdr_string(out: bytearray, s: str) -> None:
    while (len(out) - 4) % 4:
        out.append(0)
    raw = s.encode() + b"\0"
    out += struct.pack("<I", len(raw)) + raw


def reference_vectors(inp=INPUTS) -> dict:
    """Everything the fixture's outputs hold, from auth.py and the layouts of docs/protocol.md 3."""
    b = bytes.fromhex
    secret, run = b(inp["secret"]), inp["run_id"]
    pid, cid, n_p, n_c = (b(inp[k]) for k in ("plant_id", "controller_id", "nonce_plant", "nonce_controller"))
    k_run = auth.run_key(secret, run)
    k_s = auth.session_key(secret, run, pid, cid, n_p, n_c)
    s = inp["sensor_sample"]
    y = s["displacement"]
    body = (HEADER + struct.pack("<H6xQQqqI4x", 3, s["seq"], s["step"], s["sim_time_ns"], s["publish_wall_ns"],
                                 len(y)) + struct.pack(f"<{len(y)}d", *y) + pid)
    sample = body + auth.mac(auth.topic_key(k_s, "plant/sensors"), body)
    c = inp["current_command"]
    i = c["current"]
    body = (HEADER + struct.pack("<H6xQQqqqI4x", 3, c["seq"], c["step"], c["sim_time_ns"], c["recv_wall_ns"],
                                 c["publish_wall_ns"], len(i)) + struct.pack(f"<{len(i)}d", *i) + cid)
    current = body + auth.mac(auth.topic_key(k_s, "controller/currents"), body)
    e = inp["event"]
    ev = bytearray(HEADER + struct.pack("<HHxxxxQQqq", 3, e["kind"], e["seq"], e["step"], e["sim_time_ns"],
                                        e["wall_ns"]))
    _cdr_string(ev, e["source"])
    _cdr_string(ev, e["text"])
    m = inp["run_meta"]
    meta = bytearray(HEADER + struct.pack("<H6xQQqq", 3, m["seq"], m["step"], m["sim_time_ns"], m["wall_ns"]))
    _cdr_string(meta, m["json"])
    ev, meta = bytes(ev), bytes(meta)
    # the attachment, as RunAuth makes it (id + H16(K_topic, payload id))
    ctl = auth.RunAuth(secret, run, "controller", cid)
    att_ev_run = ctl.attach("events/controller", ev)            # before pairing: under K_run
    ctl.pair(pid, cid, n_p, n_c)
    plant = auth.RunAuth(secret, run, "plant", pid)
    plant.pair(pid, cid, n_p, n_c)
    return {
        "k_run": k_run.hex(),
        "k_run_unauthenticated": auth.run_key(auth.NO_SECRET, run).hex(),
        "k_session": k_s.hex(),
        "topic_keys": {t: auth.topic_key(k_s, t).hex() for t in inp["topics"]},
        "run_topic_keys": {t: auth.topic_key(k_run, t).hex() for t in inp["topics"]},
        # the controller answers the plant's challenge (nonce_q = nonce_plant, nonce_r = nonce_controller)
        "proof_controller": auth.pair_proof(k_run, "controller", cid, pid, n_p, n_c).hex(),
        # the plant answers the controller-side challenger (e.g. the recorder) likewise
        "proof_plant": auth.pair_proof(k_run, "plant", pid, cid, n_c, n_p).hex(),
        "sensor_sample": sample.hex(),
        "current_command": current.hex(),
        "event_payload": ev.hex(),
        "event_attachment": ctl.attach("events/controller", ev).hex(),
        "event_attachment_run": att_ev_run.hex(),
        "run_meta_payload": meta.hex(),
        "run_meta_attachment": plant.attach("meta", meta).hex(),
    }


def fixture() -> dict:
    return json.loads(FIXTURE.read_text())


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("ambhil_example_python_controller", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_fixture_is_what_the_reference_computes():
    f = fixture()
    assert f["inputs"] == INPUTS
    assert f["outputs"] == reference_vectors()
    assert len(bytes.fromhex(f["outputs"]["sensor_sample"])) == 84 + 8 * 3
    assert len(bytes.fromhex(f["outputs"]["current_command"])) == 92 + 8 * 3
    assert len(bytes.fromhex(f["outputs"]["event_attachment"])) == auth.ATTACH_LEN


def test_project_codecs_seal_as_the_vectors():
    """The wire codecs (bridge/protocol) with 48-byte seals give the fixture's bytes (skipped
    until they speak protocol 3 with seals)."""
    import ambhil.bridge.protocol as pr
    out, inp = fixture()["outputs"], INPUTS
    k_s = bytes.fromhex(out["k_session"])
    pid, cid = bytes.fromhex(inp["plant_id"]), bytes.fromhex(inp["controller_id"])
    seal_p = pid + auth.topic_key(k_s, "plant/sensors")
    seal_c = cid + auth.topic_key(k_s, "controller/currents")
    s, c = inp["sensor_sample"], inp["current_command"]
    try:
        sample = pr.encode_sensor(s["seq"], s["step"], s["sim_time_ns"], s["publish_wall_ns"],
                                  s["displacement"], peer=seal_p)
        current = pr.encode_current(c["seq"], c["step"], c["sim_time_ns"], c["recv_wall_ns"],
                                    c["publish_wall_ns"], c["current"], peer=seal_c)
    except (TypeError, ValueError) as e:
        pytest.skip(f"the project's codecs take no 48-byte seal yet: {e}")
    if len(sample) != 84 + 24:
        pytest.skip(f"the project's codecs are not protocol 3 yet ({len(sample)}-byte sample)")
    assert sample.hex() == out["sensor_sample"]
    assert current.hex() == out["current_command"]
    import numpy as np
    from ambhil.bridge.protocol import wire           # the hot-path twins (C where built, Python)
    for enc_s, enc_c in ((wire.encode_sensor, wire.encode_current),
                         (wire.py_encode_sensor, wire.py_encode_current)):
        got = enc_s(np.array(s["displacement"]), s["seq"], s["step"], s["sim_time_ns"], s["publish_wall_ns"],
                    seal_p)
        assert bytes(got).hex() == out["sensor_sample"]
        got = enc_c(np.array(c["current"]), c["seq"], c["step"], c["sim_time_ns"], c["recv_wall_ns"],
                    c["publish_wall_ns"], seal_c)
        assert bytes(got).hex() == out["current_command"]


def test_python_example_computes_the_vectors(example):
    m, out, inp = example, fixture()["outputs"], INPUTS
    b = bytes.fromhex
    secret, run = b(inp["secret"]), inp["run_id"]
    pid, cid, n_p, n_c = (b(inp[k]) for k in ("plant_id", "controller_id", "nonce_plant", "nonce_controller"))
    k_run, k_s = m.run_key(secret, run), m.session_key(secret, run, pid, cid, n_p, n_c)
    assert k_run.hex() == out["k_run"] and k_s.hex() == out["k_session"]
    assert m.run_key(m.NO_SECRET, run).hex() == out["k_run_unauthenticated"]
    assert {t: m.topic_key(k_s, t).hex() for t in inp["topics"]} == out["topic_keys"]
    assert {t: m.topic_key(k_run, t).hex() for t in inp["topics"]} == out["run_topic_keys"]
    assert m.pair_proof(k_run, "controller", cid, pid, n_p, n_c).hex() == out["proof_controller"]
    assert m.pair_proof(k_run, "plant", pid, cid, n_c, n_p).hex() == out["proof_plant"]
    c = inp["current_command"]
    cur = m.encode_current_command(c["seq"], c["step"], c["sim_time_ns"], c["recv_wall_ns"], c["publish_wall_ns"],
                                   c["current"], cid, m.topic_key(k_s, "controller/currents"))
    assert cur.hex() == out["current_command"]
    e = inp["event"]
    ev = m.encode_event(e["kind"], e["seq"], e["step"], e["sim_time_ns"], e["wall_ns"], e["source"], e["text"])
    assert ev.hex() == out["event_payload"]
    assert m.attachment(m.topic_key(k_s, "events/controller"), cid, ev).hex() == out["event_attachment"]
    assert m.attachment(m.topic_key(k_run, "events/controller"), cid, ev).hex() == out["event_attachment_run"]
    # what it receives: the sealed sample and the RunMeta with its attachment
    s = inp["sensor_sample"]
    key_s = m.topic_key(k_s, "plant/sensors")
    got = m.decode_sensor_sample(b(out["sensor_sample"]), 3, pid, key_s)
    assert got == (s["seq"], s["step"], s["sim_time_ns"], tuple(s["displacement"]))
    meta, att = b(out["run_meta_payload"]), b(out["run_meta_attachment"])
    assert m.verify_attachment(m.topic_key(k_s, "meta"), meta, att, pid)
    assert m.decode_run_meta(meta) == json.loads(inp["run_meta"]["json"])
    assert not m.verify_attachment(m.topic_key(k_run, "meta"), meta, att, pid)     # K_run is not K_s
    assert not m.verify_attachment(m.topic_key(k_s, "meta"), meta, att, cid)       # another id


def test_python_example_rejects_a_flipped_bit_of_the_sealed_sample(example):
    m, out, inp = example, fixture()["outputs"], INPUTS
    pid = bytes.fromhex(inp["plant_id"])
    key = bytes.fromhex(out["topic_keys"]["plant/sensors"])
    good = bytes.fromhex(out["sensor_sample"])
    reasons = set()
    for i in range(4, len(good)):
        bad = bytearray(good)
        bad[i] ^= 0x01
        with pytest.raises(m.ProtocolError) as e:
            m.decode_sensor_sample(bytes(bad), 3, pid, key)
        reasons.add((e.value.reason, i >= len(good) - 32 and i < len(good) - 16))
    # a flipped id byte is `peer`, any other byte (header fields, vector, the mac itself) `auth`
    # (version: a flipped version byte)
    assert reasons <= {("peer", True), ("auth", False), ("version", False)}, reasons
    assert ("peer", True) in reasons and ("auth", False) in reasons
    wrong_topic = bytes.fromhex(out["topic_keys"]["controller/currents"])
    with pytest.raises(m.ProtocolError, match="auth"):
        m.decode_sensor_sample(good, 3, pid, wrong_topic)


def test_python_example_key_file_rules(example, tmp_path):
    m = example
    good = tmp_path / "run.key"
    secret = auth.write_key_file(str(good))
    assert m.read_key_file(str(good)) == secret == auth.read_key_file(str(good))
    cases = {"open.key": (0o644, secret.hex()), "short.key": (0o600, "abcd"),
             "zero.key": (0o600, "00" * 32), "garbage.key": (0o600, "zz" * 32)}
    for name, (mode, text) in cases.items():
        p = tmp_path / name
        p.write_text(text + "\n")
        p.chmod(mode)
        with pytest.raises(auth.AuthError) as ref:
            auth.read_key_file(str(p))
        with pytest.raises(m.KeyFileError) as mine:
            m.read_key_file(str(p))
        assert str(mine.value) == str(ref.value)
    for name in ("missing.key", "."):                  # no file; not a regular file
        with pytest.raises(auth.AuthError) as ref:
            auth.read_key_file(str(tmp_path / name))
        with pytest.raises(m.KeyFileError) as mine:
            m.read_key_file(str(tmp_path / name))
        assert str(mine.value) == str(ref.value)


def test_python_example_refuses_a_public_listen_without_key(tmp_path):
    r = subprocess.run([sys.executable, str(EXAMPLE), "--run-id", "x", "--connect", "tcp/127.0.0.1:9",
                        "--listen", "tcp/0.0.0.0:0"], capture_output=True, text=True, timeout=60,
                       env={"PATH": "/usr/bin:/bin"})
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "--listen tcp/0.0.0.0:0 is not loopback: give --key-file FILE" in r.stderr
    bad = tmp_path / "k"
    bad.write_text("11" * 32)
    bad.chmod(0o640)
    r = subprocess.run([sys.executable, str(EXAMPLE), "--run-id", "x", "--connect", "tcp/127.0.0.1:9"],
                       capture_output=True, text=True, timeout=60,
                       env={"PATH": "/usr/bin:/bin", "AMBHIL_KEY_FILE": str(bad)})
    assert r.returncode == 2 and f"--key-file {bad}: mode 0640" in r.stderr, r.stderr


def test_rust_example_computes_the_vectors():
    from test_controllers import _build_rust
    rust_bin = _build_rust()
    r = subprocess.run([rust_bin, "--selftest-vectors", str(FIXTURE)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    got = json.loads(r.stdout)
    out = fixture()["outputs"]
    assert got.pop("sensor_sample_decoded") == [5, 6, 600000] + INPUTS["sensor_sample"]["displacement"]
    assert got.pop("run_meta_verifies") is True
    assert got.pop("sensor_sample_flipped_rejected") == ["peer", "auth"]
    assert got == {k: out[k] for k in got}
    assert set(got) == set(out) - {"sensor_sample", "run_meta_payload", "run_meta_attachment"}


if __name__ == "__main__":
    print(json.dumps({"inputs": INPUTS, "outputs": reference_vectors()}, indent=1))
