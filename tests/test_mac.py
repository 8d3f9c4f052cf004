"""The MAC of the loop messages (docs/protocol.md 5.3): the C BLAKE2b of the fast path
(bridge/protocol/_blake2b.h) against RFC 7693 and hashlib, and the seals of both codec twins
(bridge/protocol/wire.py, _wire.c) and of the C lockstep loops: any changed bit is refused, a
message sealed under one topic key does not pass under another, a bare 16-byte id is the id
with the all-zero key."""
from __future__ import annotations

import hashlib
import os

import numpy as np
import pytest

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import auth, wire

try:
    from ambhil.bridge.protocol import _wire
except ImportError:
    _wire = None

needs_c = pytest.mark.skipif(_wire is None, reason="ambhil.bridge.protocol._wire not built")

PLANT, CTL = bytes(range(1, 17)), bytes(range(101, 117))
# the loop's seals as RunAuth makes them, after pairing under a keyed run
_NP, _NC = bytes(range(16)), bytes(range(16, 32))
PLANT_AUTH = auth.RunAuth(bytes(range(32)), "run-mac", "plant", PLANT)
CTL_AUTH = auth.RunAuth(bytes(range(32)), "run-mac", "controller", CTL)
for _a in (PLANT_AUTH, CTL_AUTH):
    _a.pair(PLANT, CTL, _NP, _NC)
SENSORS, CURRENTS = "plant/sensors", "controller/currents"

IMPLS = {"python": (wire.py_encode_sensor, wire.py_decode_sensor, wire.py_encode_current,
                    wire.py_decode_current)}
if _wire is not None:
    IMPLS["C"] = (_wire.encode_sensor, _wire.decode_sensor, _wire.encode_current,
                  _wire.decode_current)


@needs_c
def test_rfc7693_appendix_a_vector():
    """BLAKE2b-512("abc"), RFC 7693 Appendix A."""
    want = bytes.fromhex(
        "ba80a53f981c4d0d6a2797b69f12f6e94c212f14685ac4b74b12bb6fdbffa2d1"
        "7d87c5392aab792dc252d5de4533cc9518d38aa8dbf1925ab92386edd4009923")
    assert _wire.blake2b(b"abc", b"", 64) == want == hashlib.blake2b(b"abc").digest()


@needs_c
@pytest.mark.parametrize("key_len", [0, 16, 32, 64])
@pytest.mark.parametrize("digest", [16, 32, 64])
def test_c_blake2b_equals_hashlib(key_len, digest):
    """Every data length 0..300 (empty, within one block, the 128-byte boundaries of one and
    two blocks, three blocks), keyed and not."""
    rng = np.random.default_rng(key_len * 100 + digest)
    key = rng.bytes(key_len)
    for n in range(301):
        data = rng.bytes(n)
        assert _wire.blake2b(data, key, digest) == \
            hashlib.blake2b(data, key=key, digest_size=digest).digest(), n


@needs_c
def test_c_blake2b_odd_sizes_and_limits():
    data = os.urandom(1000)
    for digest in (1, 7, 20, 33, 63):
        for key in (b"", b"k", os.urandom(65 - digest)):
            assert _wire.blake2b(data, key, digest) == \
                hashlib.blake2b(data, key=key, digest_size=digest).digest()
    assert _wire.blake2b(memoryview(data)[3:200], b"", 16) == \
        hashlib.blake2b(data[3:200], digest_size=16).digest()
    for bad in ((data, b"", 0), (data, b"", 65), (data, bytes(65), 16)):
        with pytest.raises(ValueError, match="out of range"):
            _wire.blake2b(*bad)


def _msgs(enc_s, enc_c, n=4):
    y = np.linspace(-1e-4, 2e-4, n)
    mv = memoryview(y).cast("B")
    s = enc_s(mv, 11, 12, 13_000, 14, PLANT_AUTH.seal(SENSORS))
    c = enc_c(mv, 11, 12, 13_000, 15, 16, CTL_AUTH.seal(CURRENTS))
    return y, s, c


@pytest.mark.parametrize("impl", sorted(IMPLS))
def test_sealed_messages_are_what_the_reference_codec_and_hashlib_make(impl):
    enc_s, dec_s, enc_c, dec_c = IMPLS[impl]
    y, s, c = _msgs(enc_s, enc_c)
    ks, kc = PLANT_AUTH.key(SENSORS), CTL_AUTH.key(CURRENTS)
    assert len(s) == 84 + 8 * 4 and len(c) == 92 + 8 * 4
    assert s[-32:-16] == PLANT and s[-16:] == auth.mac(ks, s[:-16])
    assert c[-32:-16] == CTL and c[-16:] == auth.mac(kc, c[:-16])
    assert s == pr.SensorCodec(4, me=PLANT_AUTH.seal(SENSORS)).encode(11, 12, 13_000, 14, y)
    # the receivers' view: peer_seal of the paired id, same keys on both sides
    assert CTL_AUTH.peer_seal(PLANT, SENSORS) == PLANT_AUTH.seal(SENSORS)
    out = np.zeros(4)
    assert dec_s(s, 11, memoryview(out).cast("B"), CTL_AUTH.peer_seal(PLANT, SENSORS)) == \
        (11, 12, 13_000, 14)
    assert dec_c(c, 11, memoryview(out).cast("B"), PLANT_AUTH.peer_seal(CTL, CURRENTS)) == \
        (11, 12, 13_000, 15, 16)
    assert np.array_equal(out, y)


@pytest.mark.parametrize("impl", sorted(IMPLS))
def test_any_flipped_bit_is_refused_by_both_twins_and_the_slow_path(impl):
    enc_s, dec_s, enc_c, dec_c = IMPLS[impl]
    _, s, c = _msgs(enc_s, enc_c)
    for msg, dec, codec in (
            (s, dec_s, pr.SensorCodec(4, peer=CTL_AUTH.peer_seal(PLANT, SENSORS))),
            (c, dec_c, pr.CurrentCodec(4, peer=PLANT_AUTH.peer_seal(CTL, CURRENTS)))):
        seal = codec.peer_seal
        out = np.full(4, -1.0)
        for i in range(len(msg)):
            for bit in range(8):
                b = bytearray(msg)
                b[i] ^= 1 << bit
                b = bytes(b)
                for d in IMPLS.values():
                    assert d[1 if dec is dec_s else 3](b, 11, codec.view(out), seal) is None, (i, bit)
                with pytest.raises(pr.ProtocolError) as e:
                    codec.unpack_into(b, codec.view(out))
                # the layout's fields are named; a change to an authentic field is a bad mac
                assert e.value.reason in ("encapsulation", "version", "peer", "auth"), (i, bit)
                if i >= 12 and not len(msg) - 32 <= i < len(msg) - 16:
                    assert e.value.reason == "auth", (i, bit)
                assert np.all(out == -1.0)


@pytest.mark.parametrize("impl", sorted(IMPLS))
def test_sealed_under_one_key_does_not_pass_under_another(impl):
    """A sample sealed under the sensors key is no CurrentCommand key's, nor the pre-pairing
    (K_run) key's, nor another run's: each is refused (reason ``auth``, the id being right)."""
    enc_s, dec_s, enc_c, dec_c = IMPLS[impl]
    y = np.arange(4.0)
    mv = memoryview(y).cast("B")
    out = np.zeros(4)
    omv = memoryview(out).cast("B")
    under_sensors = enc_c(mv, 1, 1, 1, 1, 1, PLANT_AUTH.seal(SENSORS))   # wrong topic's key
    assert dec_c(under_sensors, 1, omv, PLANT + PLANT_AUTH.key(CURRENTS)) is None
    assert dec_c(under_sensors, 1, omv, PLANT + PLANT_AUTH.key(SENSORS)) == (1, 1, 1, 1, 1)
    other_run = auth.RunAuth(bytes(range(32)), "run-other", "plant", PLANT)
    other_run.pair(PLANT, CTL, _NP, _NC)
    unpaired = auth.RunAuth(bytes(range(32)), "run-mac", "plant", PLANT)
    stranger = auth.RunAuth(None, "run-mac", "plant", PLANT)   # no secret: the all-zero one
    stranger.pair(PLANT, CTL, _NP, _NC)
    peer = CTL_AUTH.peer_seal(PLANT, SENSORS)
    codec = pr.SensorCodec(4, peer=peer)
    for ra in (other_run, unpaired, stranger):
        msg = enc_s(mv, 1, 1, 1, 1, ra.seal(SENSORS))
        assert msg[-32:-16] == PLANT
        assert dec_s(msg, 1, omv, peer) is None
        with pytest.raises(pr.AuthError):
            codec.decode(msg)
    assert np.all(out == y)           # untouched since the one accepted


@pytest.mark.parametrize("impl", sorted(IMPLS))
def test_a_bare_id_is_the_id_with_the_zero_key(impl):
    enc_s, dec_s, enc_c, dec_c = IMPLS[impl]
    y = np.array([1.0, -2.0, 3.5])
    mv = memoryview(y).cast("B")
    a = enc_s(mv, 5, 6, 7, 8, PLANT)
    assert a == enc_s(mv, 5, 6, 7, 8, PLANT + pr.NO_KEY)
    assert a[-16:] == hashlib.blake2b(a[:-16], key=bytes(32), digest_size=16).digest()
    assert a == pr.SensorCodec(3, me=PLANT).encode(5, 6, 7, 8, y)
    assert a == pr.encode_sensor(5, 6, 7, 8, y, peer=PLANT)
    out = np.zeros(3)
    for seal in (PLANT, PLANT + pr.NO_KEY):
        assert dec_s(a, 5, memoryview(out).cast("B"), seal) == (5, 6, 7, 8)
        assert pr.decode_sensor(a, peer=seal).seq == 5
    c = enc_c(mv, 5, 6, 7, 8, 9, CTL)
    assert c == enc_c(mv, 5, 6, 7, 8, 9, CTL + pr.NO_KEY)
    assert pr.decode_current(c, peer=CTL + pr.NO_KEY).seq == 5


def test_reseal_makes_the_message_the_seal_holders():
    """pr.reseal: a recorded sample sent again as another sender's (the replay tool) decodes
    under that sender's seal only, its content unchanged."""
    y = np.array([0.5, -0.25, 1e-9])
    orig = pr.SensorCodec(3, me=PLANT_AUTH.seal(SENSORS)).encode(4, 5, 6, 7, y)
    replay = auth.RunAuth(None, "run-r", "plant", CTL)
    b = pr.reseal(orig, replay.seal(SENSORS))
    assert b[:-32] == orig[:-32] and len(b) == len(orig)
    m = pr.SensorCodec(3, peer=replay.seal(SENSORS)).decode(b)
    assert m.peer == CTL and np.array_equal(m.displacement, y) and m.seq == 4
    with pytest.raises(pr.ForeignError):
        pr.SensorCodec(3, peer=PLANT_AUTH.seal(SENSORS)).decode(b)
    assert pr.reseal(b, PLANT_AUTH.seal(SENSORS)) == orig
    c = pr.CurrentCodec(2, me=CTL).encode(1, 2, 3, 4, 5, [1.0, 2.0])
    assert pr.reseal(c, PLANT) == pr.CurrentCodec(2, me=PLANT).encode(1, 2, 3, 4, 5, [1.0, 2.0])
    with pytest.raises(pr.TruncatedError):
        pr.reseal(b"\0" * 40, PLANT)


def test_seal_arguments_are_checked():
    with pytest.raises(ValueError, match="48"):
        pr.SensorCodec(2, me=bytes(20))
    with pytest.raises(ValueError, match="48"):
        pr.CurrentCodec(2, peer=bytes(47))
    assert pr.split_seal(PLANT) == (PLANT, pr.NO_KEY)
    assert pr.split_seal(PLANT_AUTH.seal(SENSORS)) == (PLANT, PLANT_AUTH.key(SENSORS))
    c = pr.SensorCodec(2)
    c.peer = PLANT                       # set later, as the nodes do once paired
    assert (c.peer, c.peer_seal) == (PLANT, PLANT + pr.NO_KEY)
    c.peer = None
    assert c.peer is None and c.peer_seal is None


# ---------------------------------------------------------------- the C lockstep loops' seals
class _Sample:
    """What a zenoh subscriber's recv() returns, as far as the loops look at it."""

    def __init__(self, data):
        self.payload, self._d = self, data

    def to_bytes(self):
        return self._d


def _feeder(msgs):
    it = iter(msgs)
    return lambda: _Sample(next(it))


@needs_c
def test_controller_lockstep_answers_only_sealed_samples():
    """ControllerLockstep with 48-byte seals: a sample sealed by the paired plant is answered
    with a reply sealed by the controller; one with the plant's id but a bad mac goes back to
    Python (LOOP_SLOW); me/peer of another size are refused by name; bare ids still work."""
    n = 3
    ps, cs = PLANT_AUTH.seal(SENSORS), CTL_AUTH.seal(CURRENTS)
    y_in, c = np.zeros(n), np.array([0.5, -0.5, 0.25])
    sc = pr.SensorCodec(n, me=ps)
    good = [sc.encode(k, k, 1000 * k, 7, np.full(n, float(k))) for k in range(3)]
    forged = pr.SensorCodec(n, me=PLANT).encode(3, 3, 3000, 7, np.ones(n))   # zero key
    sent = []
    loop = _wire.ControllerLockstep(
        recv=_feeder(good + [forged]), put=sent.append, y_mv=memoryview(y_in).cast("B"),
        y_in=y_in, step=lambda y: c, c_obj=c, c_mv=memoryview(c).cast("B"), me=cs,
        peer=CTL_AUTH.peer_seal(PLANT, SENSORS), wmark=[0], restarts=[], last_seq=-1)
    assert loop.run() == wire.LoopCode.SLOW and loop.data == forged
    assert loop.last_seq == 2 and loop.steps == 3 and len(sent) == 3
    assert np.array_equal(y_in, np.full(n, 2.0))           # the forged one not decoded
    pc = pr.CurrentCodec(n, peer=PLANT_AUTH.peer_seal(CTL, CURRENTS))
    assert [pc.decode(m).seq for m in sent] == [0, 1, 2]
    with pytest.raises(pr.AuthError):
        pr.CurrentCodec(n, peer=CTL).decode(sent[0])       # not under the zero key
    for field in ("me", "peer"):
        for bad in (b"", CTL + b"\0", cs + b"\0", bytes(32), "x" * 16):
            loop2 = _wire.ControllerLockstep(**{f: getattr(loop, f) for f in (
                "recv", "put", "y_mv", "y_in", "step", "c_obj", "c_mv", "me", "peer", "wmark",
                "restarts")})
            setattr(loop2, field, bad)
            with pytest.raises(TypeError, match=f"ControllerLockstep.{field} must be a 16-byte "
                                                "peer id or a 48-byte seal"):
                loop2.run()
    loop.me, loop.peer = CTL, PLANT                        # bare ids: the zero key
    loop.recv = _feeder([forged, b"end"])
    assert loop.run() == wire.LoopCode.SLOW and loop.data == b"end"
    assert loop.last_seq == 3 and pr.CurrentCodec(n, peer=CTL).decode(sent[-1]).seq == 3


@needs_c
def test_plant_lockstep_seals_its_samples_and_takes_only_sealed_replies():
    n = 2
    ps, cs = PLANT_AUTH.seal(SENSORS), CTL_AUTH.seal(CURRENTS)
    y, u = np.array([1e-5, -2e-5]), np.zeros(n)

    class Plant:
        step_index = 0

    def advance(uu):
        Plant.step_index += 1
        return y
    cc_good, cc_bad = pr.CurrentCodec(n, me=cs), pr.CurrentCodec(n, me=CTL + PLANT_AUTH.key(CURRENTS)[::-1])
    sent, received = [], []

    def recv():                                            # the reply to the last sample
        k = pr.decode_sensor(sent[-1]).seq
        cc = cc_bad if k == 4 else cc_good
        return _Sample(cc.encode(k, k, 0, 1, 2, np.full(n, 0.1 * k)))
    loop = _wire.PlantLockstep(
        y_mv=memoryview(y).cast("B"), y_obj=y, rx_mv=memoryview(u).cast("B"), u=u,
        advance=advance, plant=Plant, put=lambda m: None, recv=recv, sent=sent,
        received=received, rtt=np.zeros(10, np.int64), tet=np.zeros(10, np.int64), wmark=[0],
        me=ps, peer=PLANT_AUTH.peer_seal(CTL, CURRENTS), has_status=0, period_ns=1000,
        k_end=10, next_flush=100, rb_due=2 ** 62, k=0)
    assert loop.run() == wire.LoopCode.SLOW and loop.k == 4      # step 4's reply: a bad mac
    assert loop.steps_done == 4 and len(received) == 4 and len(sent) == 5
    assert np.allclose(u, 0.3)
    sc = pr.SensorCodec(n, peer=CTL_AUTH.peer_seal(PLANT, SENSORS))
    assert [sc.decode(m).seq for m in sent] == list(range(5))
    with pytest.raises(pr.AuthError):
        pr.CurrentCodec(n, peer=PLANT_AUTH.peer_seal(CTL, CURRENTS)).decode(loop.data)
