"""Wire protocol: round trips, byte layout, and every rejection path."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from ambhil.bridge import protocol as pr


import hashlib

ME = bytes(range(1, 17))               # a sender's peer id
OTHER = bytes(range(101, 117))
KEY = bytes(range(200, 232))           # a topic key
ME_SEAL = ME + KEY                     # the seal of a sender (id + key, docs/protocol.md 5.3)


def h16(key, data):
    return hashlib.blake2b(data, key=key, digest_size=16).digest()


def test_sensor_layout_and_roundtrip():
    c = pr.SensorCodec(4, me=ME_SEAL)
    y = np.array([1.5, -2.0, 3e-6, 0.0])
    b = c.encode(7, 8, 9_000, 10_000, y)
    assert len(b) == 4 + 48 + 32 + 16 + 16 == c.size == 84 + 8 * 4
    assert b[:4] == b"\x00\x01\x00\x00"
    assert struct.unpack_from("<H", b, 4)[0] == 3 == pr.PROTOCOL_VERSION
    assert struct.unpack_from("<QQqqI", b, 12) == (7, 8, 9_000, 10_000, 4)
    assert b[48:52] == b"\0\0\0\0"                       # re-align to 8 before float64[]
    assert np.array_equal(np.frombuffer(b, "<f8", 4, 52), y)
    assert b[84:100] == ME                               # uint8[16] peer: the sender
    assert b[100:] == h16(KEY, b[:100])                  # uint8[16] mac: of every byte before it
    m = c.decode(b)
    assert (m.seq, m.step, m.sim_time_ns, m.publish_wall_ns) == (7, 8, 9_000, 10_000)
    assert np.array_equal(m.displacement, y) and m.peer == ME and m.mac == b[100:]
    assert pr.decode_sensor(b).seq == 7                 # axis count from the message
    assert pr.decode_sensor(b, peer=ME_SEAL).seq == 7
    assert pr.encode_sensor(7, 8, 9_000, 10_000, y, peer=ME_SEAL) == b
    assert c.me == ME and c.me_seal == ME_SEAL


def test_current_layout_and_roundtrip():
    c = pr.CurrentCodec(2, me=ME)                        # a bare id: the all-zero key
    b = c.encode(3, 4, 5, 6, 7, [0.25, -1.0])
    assert len(b) == 4 + 56 + 16 + 16 + 16 == 92 + 8 * 2 and b[-32:-16] == ME
    assert b[-16:] == h16(pr.NO_KEY, b[:-16])
    assert struct.unpack_from("<QQqqqI", b, 12) == (3, 4, 5, 6, 7, 2)
    m = pr.decode_current(b, peer=ME)
    assert (m.seq, m.step, m.sim_time_ns, m.recv_wall_ns, m.publish_wall_ns) == (3, 4, 5, 6, 7)
    assert list(m.current) == [0.25, -1.0] and m.peer == ME
    assert pr.decode_current(b, peer=ME + pr.NO_KEY).seq == 3   # the same seal, spelt out
    with pytest.raises(pr.AuthError):
        pr.decode_current(b, peer=ME_SEAL)                # same id, another key
    assert pr.encode_current(3, 4, 5, 6, 7, [0.25, -1.0])[-32:-16] == pr.NO_PEER


def _reseal(body: bytes, key: bytes = KEY) -> bytes:
    """``body`` (a message without its mac) with a valid mac under ``key``."""
    return body + h16(key, body)


def test_peer_and_mac_checks_follow_the_header_check():
    """A codec given ``peer`` (a seal) accepts only messages carrying that id at bytes
    [-32:-16] (reason ``peer`` otherwise) and then a mac valid under its key (reason ``auth``);
    the header (truncated, encapsulation, version) is checked before them, the rest (oversize,
    axes, length, finiteness) after them (docs/protocol.md, section 4)."""
    good = pr.SensorCodec(4, me=ME_SEAL).encode(1, 1, 1, 1, [0.0, 1.0, 2.0, 3.0])
    c = pr.SensorCodec(4, peer=ME_SEAL)
    assert c.decode(good).peer == ME and c.peer == ME and c.peer_seal == ME_SEAL
    foreign = pr.SensorCodec(4, me=OTHER + KEY).encode(1, 1, 1, 1, [0.0, 1.0, 2.0, 3.0])
    with pytest.raises(pr.ForeignError, match=OTHER.hex()):
        c.decode(foreign)
    with pytest.raises(pr.ForeignError):
        c.unpack_into(foreign, c.view(np.zeros(4)))
    forged = pr.SensorCodec(4, me=ME).encode(1, 1, 1, 1, [0.0, 1.0, 2.0, 3.0])   # the id, no key
    with pytest.raises(pr.AuthError, match="not valid"):
        c.decode(forged)
    with pytest.raises(pr.AuthError):
        c.unpack_into(forged, c.view(np.zeros(4)))
    with pytest.raises(pr.VersionError):                 # a version-2 message (no mac) is
        c.decode(good[:4] + b"\x02\x00" + good[6:-16])  # named by its version, not as foreign
    with pytest.raises(pr.VersionError):
        c.decode(good[:4] + b"\x02\x00" + good[6:])
    with pytest.raises(pr.TruncatedError):
        c.decode(good[:40])
    with pytest.raises(pr.ForeignError):                 # the id is at [-32:-16]
        c.decode(good + b"\0")
    with pytest.raises(pr.AuthError):                    # authenticity before the content
        c.decode(good[:52] + struct.pack("<d", np.nan) + good[60:])
    with pytest.raises(pr.NonFiniteError):               # the rest after the sender
        c.decode(_reseal(good[:52] + struct.pack("<d", np.nan) + good[60:-16]))
    with pytest.raises(pr.LengthError):
        c.decode(_reseal(good[:-32] + b"\0" * 8 + ME))
    with pytest.raises(pr.AuthError):                    # a stranger's malformed message: auth
        c.decode(good[:-32] + b"\0" * 8 + ME + bytes(16))
    with pytest.raises(pr.AxisCountError):
        c.decode(_reseal(good[:44] + struct.pack("<I", 5) + good[48:-32] + b"\0" * 8 + ME))
    with pytest.raises(ValueError, match="16 bytes"):
        pr.SensorCodec(4, peer=b"short")
    c.peer = None                                        # without peer: neither is checked
    assert c.decode(forged).peer == ME and c.decode(foreign).peer == OTHER


def test_common_prefix_offsets():
    msgs = [pr.encode_sensor(11, 12, 13, 0, [1.0]), pr.encode_current(11, 12, 13, 0, 0, [1.0]),
            pr.encode_event(pr.Event(2, "x", "plant", 11, 12, 13, 0)),
            pr.encode_meta(pr.RunMeta({"a": 1}, 11, 12, 13, 0)),
            pr.encode_timing(pr.Timing(12, 13, 100, 0, np.zeros(1), np.zeros(1), np.zeros(1),
                                       np.zeros(1, np.uint8), 11))]
    for b in msgs:
        assert struct.unpack_from("<QQq", b, pr.SEQ_OFFSET) == (11, 12, 13)
    assert msgs[2][pr.EVENT_KIND_OFFSET] == 2


def test_event_meta_timing_roundtrip():
    e = pr.Event(pr.EventKind.FAULT, "controller lost: ü", "plant", 1, 2, 3, 4)
    assert pr.decode_event(pr.encode_event(e)) == e
    m = pr.decode_meta(pr.encode_meta(pr.RunMeta({"scene": "x", "rate": 1e4}, 1, 2, 3, 4)))
    assert m.info == {"scene": "x", "rate": 1e4} and (m.seq, m.wall_ns) == (1, 4)
    t = pr.Timing(100, 5, 100_000, 3, np.arange(5), np.arange(5) * 2, np.arange(5) * 3,
                  np.array([0, 1, 2, 4, 0], np.uint8), 9)
    d = pr.decode_timing(pr.encode_timing(t))
    assert (d.step, d.sim_time_ns, d.period_ns, d.overruns, d.seq) == (100, 5, 100_000, 3, 9)
    assert list(d.tet_ns) == [0, 3, 6, 9, 12] and list(d.flags) == [0, 1, 2, 4, 0]


GOOD = pr.SensorCodec(4, me=ME).encode(1, 1, 1, 1, [0.0, 1.0, 2.0, 3.0])
BAD_MAC = GOOD[:-1] + bytes([GOOD[-1] ^ 1])


@pytest.mark.parametrize("data,exc", [
    (b"", pr.TruncatedError),
    (GOOD[:30], pr.TruncatedError),
    (b"\x01\x00\x00\x00" + GOOD[4:], pr.EncapsulationError),        # big-endian header
    (GOOD[:4] + b"\x01\x00" + GOOD[6:], pr.VersionError),          # version 1
    (GOOD[:4] + b"\x02\x00" + GOOD[6:], pr.VersionError),
    (GOOD[:4] + b"\x04\x00" + GOOD[6:], pr.VersionError),
    (GOOD + b"\0", pr.LengthError),
    (GOOD[:-8], pr.LengthError),
    (GOOD[:44] + struct.pack("<I", 3) + GOOD[48:-8], pr.AxisCountError),
    (GOOD[:44] + struct.pack("<I", 5) + GOOD[48:] + b"\0" * 8, pr.AxisCountError),
    (GOOD[:44] + struct.pack("<I", 10 ** 6) + GOOD[48:], pr.OversizeError),
    (GOOD[:52] + struct.pack("<d", float("nan")) + GOOD[60:], pr.NonFiniteError),
    (GOOD[:-40] + struct.pack("<d", float("-inf")) + GOOD[-32:], pr.NonFiniteError),
    (GOOD[:-32] + OTHER + GOOD[-16:], pr.ForeignError),
    (BAD_MAC, pr.AuthError),
])
def test_sensor_rejections(data, exc):
    with pytest.raises(exc) as ei:
        pr.SensorCodec(4, peer=ME if exc in (pr.ForeignError, pr.AuthError) else None).decode(data)
    assert isinstance(ei.value, pr.ProtocolError) and ei.value.reason in pr.REASONS


def test_decode_any_axis_count_limits():
    big = pr.SensorCodec(80, max_axes=100).encode(0, 0, 0, 0, np.zeros(80))
    with pytest.raises(pr.OversizeError):
        pr.decode_sensor(big, max_axes=64)
    assert pr.decode_sensor(big, max_axes=100).displacement.shape == (80,)
    assert pr.SensorCodec(80, max_axes=100).decode(big).seq == 0        # numpy finiteness path
    bad = bytearray(big)
    bad[-40:-32] = struct.pack("<d", float("inf"))
    with pytest.raises(pr.NonFiniteError):
        pr.SensorCodec(80, max_axes=100).decode(bytes(bad))


def test_encode_refuses_bad_values():
    with pytest.raises(pr.NonFiniteError):
        pr.CurrentCodec(2).encode(0, 0, 0, 0, 0, [1.0, float("nan")])
    with pytest.raises(pr.AxisCountError):
        pr.CurrentCodec(2).encode(0, 0, 0, 0, 0, [1.0])
    with pytest.raises(ValueError):
        pr.SensorCodec(0)


def test_string_and_trailing_rejections():
    b = pr.encode_event(pr.Event(1, "hello", "plant"))
    with pytest.raises(pr.LengthError):
        pr.decode_event(b + b"\0\0\0\0")
    with pytest.raises(pr.TruncatedError):
        pr.decode_event(b[:-3])
    i = b.index(b"hello")
    nonul = b[:i + 5] + b"x" + b[i + 6:]
    with pytest.raises(pr.StringError):
        pr.decode_event(nonul)
    with pytest.raises(pr.OversizeError):
        pr.decode_event(pr.encode_event(pr.Event(1, "x" * 100)), max_text=10)
    with pytest.raises(pr.OversizeError):
        pr.encode_event(pr.Event(1, "x" * 100), max_text=10)
    m = pr.encode_meta(pr.RunMeta({"a": 1}))
    with pytest.raises(pr.StringError):
        pr.decode_meta(m.replace(b'{"a":1}', b'{"a":1'[:6] + b"]"))
    t = pr.encode_timing(pr.Timing(0, 0, 1, 0, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3, np.uint8)))
    with pytest.raises(pr.OversizeError):
        pr.decode_timing(t, max_batch=2)
    with pytest.raises(pr.VersionError):
        pr.decode_timing(t[:4] + b"\x09\x00" + t[6:])


def test_keys():
    K = pr.keys("run-1")
    assert K.sensors == "ambhil/run-1/plant/sensors"
    assert K.currents == "ambhil/run-1/controller/currents"
    assert K.alive_recorder == "ambhil/run-1/alive/recorder"
    assert pr.message_type_for_key(K.timing) == "Timing"
    for bad in ("", "a/b", "x*", "a b", "$x"):
        with pytest.raises(ValueError):
            pr.keys(bad)


def test_hot_path_pack_from_unpack_into_match_encode_decode():
    """The lockstep hot path (memoryviews of preallocated arrays) produces and accepts exactly
    the bytes of the reference codec, and leaves the output untouched on a rejected message."""
    sc, cc = pr.SensorCodec(4), pr.CurrentCodec(4)
    y = np.array([1e-6, -2.5e-5, 3.0, -4.0])
    assert sc.pack_from(7, 8, 9, 10, sc.view(y)) == sc.encode(7, 8, 9, 10, y)
    assert cc.pack_from(1, 2, 3, 4, 5, cc.view(y)) == cc.encode(1, 2, 3, 4, 5, y)
    out = np.zeros(4)
    h = cc.unpack_into(cc.encode(1, 2, 3, 4, 5, y), cc.view(out))
    assert h[2:7] == (1, 2, 3, 4, 5) and np.array_equal(out, y)
    big = [1e308, 1e308, -1e308, 0.0]          # finite, but the sum overflows
    out2 = np.zeros(4)
    cc.unpack_into(cc.encode(0, 0, 0, 0, 0, big), cc.view(out2))
    assert np.array_equal(out2, big)
    bad = bytearray(cc.encode(0, 0, 0, 0, 0, y))
    bad[-40:-32] = struct.pack("<d", float("nan"))
    with pytest.raises(pr.NonFiniteError):
        cc.unpack_into(bytes(bad), cc.view(out))
    assert np.array_equal(out, y)              # untouched
    with pytest.raises(pr.NonFiniteError):
        sc.pack_from(0, 0, 0, 0, sc.view(np.array([0.0, np.inf, 0.0, 0.0])))
    with pytest.raises(pr.AxisCountError):
        sc.view(np.zeros(3))


# ------------------------------------------------------------- bridge.protocol.wire (hot-path codec)
from ambhil.bridge.protocol import wire

IMPLS = {"python": (wire.py_encode_sensor, wire.py_decode_sensor,
                    wire.py_encode_current, wire.py_decode_current)}
try:
    from ambhil.bridge.protocol import _wire
    IMPLS["C"] = (_wire.encode_sensor, _wire.decode_sensor, _wire.encode_current,
                  _wire.decode_current)
except ImportError:
    _wire = None


def test_wire_extension_is_built_and_used():
    """`pip install` builds ambhil.bridge.protocol._wire (gcc); the lockstep speed target depends on it."""
    assert _wire is not None, "ambhil.bridge.protocol._wire not built: the pure-Python twin is in use"
    assert wire.NATIVE and wire.decode_current is _wire.decode_current


def test_loop_codes_agree_with_the_c_enum():
    """The lockstep loops' hand-back codes are one enum on both sides: _lockstep.h's ``enum
    LoopCode`` (exported as LOOP_*) and ``wire.LoopCode``, same names, same values."""
    if _wire is None:
        pytest.skip("ambhil.bridge.protocol._wire not built")
    c = {name[len("LOOP_"):]: getattr(_wire, name) for name in dir(_wire) if name.startswith("LOOP_")}
    assert c == {m.name: m.value for m in wire.LoopCode}
    assert wire.PlantLockstep is _wire.PlantLockstep and wire.ControllerLockstep is _wire.ControllerLockstep


def test_lockstep_loops_are_set_by_field_name():
    """The C loops' state is named: a keyword sets the field of that name (a misspelt one
    fails), a field not set is named when run() needs it."""
    if _wire is None:
        pytest.skip("ambhil.bridge.protocol._wire not built")
    lp = _wire.PlantLockstep(k_end=7, next_flush=3, has_status=True)
    assert (lp.k_end, lp.next_flush, lp.has_status, lp.k, lp.steps_done) == (7, 3, 1, 0, 0)
    assert lp.data is None and lp.y is None and lp.exc is None
    with pytest.raises(AttributeError):
        _wire.PlantLockstep(k_ned=7)
    with pytest.raises(TypeError, match="field y_mv is not set"):
        lp.run()
    with pytest.raises(TypeError, match="keyword"):
        _wire.ControllerLockstep(1)
    with pytest.raises(TypeError, match="field recv is not set"):
        _wire.ControllerLockstep(steps=2).run()


def _vectors(rng, n):
    yield np.zeros(n)
    yield rng.normal(size=n) * 10.0 ** rng.integers(-9, 3, n)
    yield np.full(n, 1.7e308)                      # finite, but the sum overflows to inf
    yield np.array([5e-324, -0.0] * n)[:n]         # subnormal, negative zero


@pytest.mark.parametrize("impl", sorted(IMPLS))
@pytest.mark.parametrize("n", [1, 4, 6, 33])
def test_wire_encode_decode_match_reference_codec(impl, n):
    enc_s, dec_s, enc_c, dec_c = IMPLS[impl]
    other = OTHER + KEY[::-1]
    sc, cc = pr.SensorCodec(n, max_axes=64, me=ME_SEAL), pr.CurrentCodec(n, max_axes=64, me=other)
    rng = np.random.default_rng(n)
    for v in _vectors(rng, n):
        seq, step, sim, t1, t2 = 2**64 - 1 - n, 12345, -7, 2**63 - 1, -(2**63)
        b = enc_s(sc.view(v), seq, step, sim, t1, ME_SEAL)
        assert b == sc.encode(seq, step, sim, t1, v)
        out = np.full(n, np.nan)
        assert dec_s(b, seq, sc.view(out), other) is None and np.isnan(out).all()  # not the peer
        assert dec_s(b, seq, sc.view(out), ME + KEY[::-1]) is None                 # nor its key
        assert np.isnan(out).all()
        assert dec_s(b, seq, sc.view(out), ME_SEAL) == (seq, step, sim, t1)
        assert np.array_equal(out.view(np.uint64), v.view(np.uint64))   # bit for bit
        b = enc_c(cc.view(v), 3, 4, 5, t1, t2, other)
        assert b == cc.encode(3, 4, 5, t1, t2, v)
        out = np.zeros(n)
        assert dec_c(b, 3, cc.view(out), other) == (3, 4, 5, t1, t2)
        assert np.array_equal(out.view(np.uint64), v.view(np.uint64))
        b = enc_c(cc.view(v), 3, 4, 5, t1, t2, OTHER)              # a bare id: the zero key
        assert b == pr.CurrentCodec(n, max_axes=64, me=OTHER).encode(3, 4, 5, t1, t2, v)
        assert b == enc_c(cc.view(v), 3, 4, 5, t1, t2, OTHER + pr.NO_KEY)
        assert dec_c(b, 3, cc.view(out), OTHER) == (3, 4, 5, t1, t2)


@pytest.mark.parametrize("impl", sorted(IMPLS))
def test_wire_rejects_to_slow_path_and_leaves_output_untouched(impl):
    enc_s, dec_s, enc_c, dec_c = IMPLS[impl]
    n = 4
    sc, cc = pr.SensorCodec(n, me=ME_SEAL), pr.CurrentCodec(n, me=ME_SEAL, peer=ME_SEAL)
    good = cc.encode(9, 1, 2, 3, 4, [1.0, 2.0, 3.0, 4.0])
    nan = _reseal(good[:-40] + np.array([np.nan]).tobytes() + good[-32:-16])
    bad = {"empty": b"", "truncated": good[:30], "long": good + b"\0",
           "encapsulation": b"\x01\x00\x00\x00" + good[4:],
           "version": good[:4] + b"\x02" + good[5:-16],          # a version-2 message (no mac)
           "axes": pr.CurrentCodec(3, me=ME_SEAL).encode(9, 1, 2, 3, 4, [1, 2, 3]),
           "nonfinite": nan, "sensor-as-current": sc.encode(9, 1, 2, 3, [1, 2, 3, 4]),
           "peer": pr.CurrentCodec(n, me=OTHER + KEY).encode(9, 1, 2, 3, 4, [1.0, 2.0, 3.0, 4.0]),
           "auth": pr.CurrentCodec(n, me=ME).encode(9, 1, 2, 3, 4, [1.0, 2.0, 3.0, 4.0]),
           "no-mac": good[:-16]}
    out = np.full(n, -1.0)
    for name, b in bad.items():
        assert dec_c(b, 9, cc.view(out), ME_SEAL) is None, name
        assert np.all(out == -1.0), name
    assert dec_c(good, 8, cc.view(out), ME_SEAL) is None and np.all(out == -1.0)    # wrong seq
    assert dec_c(good, 9, cc.view(out), ME) is None and np.all(out == -1.0)     # the zero key
    # the slow path classifies what the fast path passed over
    for name in ("truncated", "encapsulation", "version", "axes", "nonfinite", "peer", "auth"):
        with pytest.raises(pr.ProtocolError) as e:
            cc.unpack_into(bad[name], cc.view(out))
        assert e.value.reason == name
    assert dec_c(good, 9, cc.view(out), ME_SEAL) == (9, 1, 2, 3, 4) and list(out) == [1, 2, 3, 4]
    # nothing non-finite is ever encoded
    for x in (np.nan, np.inf, -np.inf):
        v = np.array([0.0, x, 0.0, 0.0])
        assert enc_s(sc.view(v), 0, 0, 0, 0, ME_SEAL) is None
        assert enc_c(cc.view(v), 0, 0, 0, 0, 0, ME) is None
    with pytest.raises(TypeError):
        enc_s(sc.view(np.zeros(n)), 0, 0, 0, 0)                # missing field (the seal)
    for short in (b"short", ME + b"x", ME_SEAL + b"x", bytes(32)):   # 16 or 48 bytes only
        with pytest.raises((TypeError, ValueError)):
            enc_s(sc.view(np.zeros(n)), 0, 0, 0, 0, short)
        with pytest.raises((TypeError, ValueError)):
            dec_s(sc.encode(0, 0, 0, 0, np.zeros(n)), 0, sc.view(np.zeros(n)), short)
    with pytest.raises((OverflowError, TypeError, struct.error)):
        enc_s(sc.view(np.zeros(n)), -1, 0, 0, 0, ME)          # seq is unsigned


@pytest.mark.parametrize("n", [1, 4, 7, 8, 12])
def test_wire_twins_agree_on_every_flipped_bit(n):
    """C and Python fast paths take and refuse the same messages: every single-bit change of a
    sealed SensorSample / CurrentCommand is refused by both (and by the slow path), for axis
    counts around the one-compression limit of the C MAC (128 bytes before the mac)."""
    if "C" not in IMPLS:
        pytest.skip("ambhil.bridge.protocol._wire not built")
    rng = np.random.default_rng(n)
    v = rng.normal(size=n)
    for nt in (1, 2):
        codec = (pr.SensorCodec if nt == 1 else pr.CurrentCodec)(n, me=ME_SEAL, peer=ME_SEAL)
        times = (5,) * nt
        msg = codec.encode(9, 1, 2, *times, v)
        decs = [IMPLS[k][1 if nt == 1 else 3] for k in ("C", "python")]
        out = np.zeros(n)
        assert [d(msg, 9, codec.view(out), ME_SEAL) for d in decs] == [(9, 1, 2) + times] * 2
        for i in range(len(msg)):
            for bit in range(8):
                b = bytearray(msg)
                b[i] ^= 1 << bit
                b = bytes(b)
                out[:] = -1.0
                assert [d(b, 9, codec.view(out), ME_SEAL) for d in decs] == [None, None], (i, bit)
                assert np.all(out == -1.0)
                with pytest.raises(pr.ProtocolError):
                    codec.unpack_into(b, codec.view(out))


@pytest.mark.parametrize("packer", ["native", "numpy"])
def test_record_batch_roundtrip_and_vectorised_flush_equals_reference(packer, monkeypatch):
    """The plant's Batcher.flush (one C call, or its numpy twin) packs exactly what the
    reference encoder packs (log time of a sample = its publish_wall_ns), and decode returns
    every payload verbatim."""
    import struct
    from ambhil.bridge.protocol import record_batch as rb
    if packer == "numpy":
        monkeypatch.setattr(rb, "_native_pack", None)
    elif rb._native_pack is None:
        pytest.skip("ambhil.bridge.protocol._wire not built")
    rng = np.random.default_rng(3)

    class Pub:
        msg = None

        def put(self, m, attachment=None):
            self.msg = m
    pub = Pub()
    b = rb.Batcher(pub)
    sc, cc = pr.SensorCodec(6), pr.CurrentCodec(6)
    for ns, nc in ((0, 0), (0, 3), (5, 0), (7, 7), (40, 39)):
        S = [sc.encode(k, k + 3, k * 100000, int(rng.integers(1, 2**62)), rng.normal(size=6))
             for k in range(ns)]
        C = [(int(rng.integers(1, 2**62)), cc.encode(k, k, k, 1, 2, rng.normal(size=6))[:int(rng.integers(0, 108))])
             for k in range(nc)]          # replies of any length: malformed ones are recorded too
        for m in S:
            b.sent(m)
        for x in C:
            b.received(x)
        pub.msg = None
        b.flush(0)
        if not ns and not nc:
            assert pub.msg is None
            continue
        log = [struct.unpack_from("<q", m, 36)[0] for m in S] + [t for t, _ in C]
        ref = rb.encode(b.seq - 1, 3 if S else 0, 0, log, [0] * ns + [1] * nc, S + [d for _, d in C])
        assert pub.msg == ref
        seq, step, sim, msgs = rb.decode(ref)
        assert seq == b.seq - 1 and [m[2] for m in msgs] == S + [d for _, d in C]
        assert [m[1] for m in msgs] == log and [m[0] for m in msgs] == [0] * ns + [1] * nc
    with pytest.raises(pr.ProtocolError):
        rb.decode(ref[:-1])


def test_native_timing_packer_equals_the_reference_encoder():
    """The plant's Timing batches (ambhil.bridge.protocol._wire.pack_timing, one C call on the loop's thread)
    are byte for byte what bridge/protocol/cdr.py encode_timing makes, and decode back."""
    from ambhil.bridge.protocol import wire
    if not wire.NATIVE:
        pytest.skip("ambhil.bridge.protocol._wire not built")
    rng = np.random.default_rng(7)
    for n in (0, 1, 3, 200):
        lat, rtt, tet = (rng.integers(-2**62, 2**62, n) for _ in range(3))
        fl = rng.integers(0, 256, n).astype(np.uint8)
        ref = pr.encode_timing(pr.Timing(11, 1234, 100000, 5, lat, rtt, tet, fl, 3))
        got = wire._wire.pack_timing(3, 11, 1234, 100000, 5, lat, rtt, tet, fl)
        assert got == ref
        t = pr.decode_timing(got)
        assert (t.step, t.seq, t.overruns) == (11, 3, 5)
        assert np.array_equal(t.rtt_ns, rtt) and np.array_equal(t.flags, fl)
    with pytest.raises(ValueError, match="equal length"):
        wire._wire.pack_timing(0, 0, 0, 1, 0, np.zeros(2, np.int64), np.zeros(3, np.int64),
                               np.zeros(2, np.int64), np.zeros(2, np.uint8))


def test_vector_messages_are_what_an_independent_ros2_codec_makes_of_the_schemas():
    """Protocol version 3 as the schemas of bridge/protocol/messages.py define it (``uint8[16] peer,
    uint8[16] mac`` after the vector): the mcap ROS 2 serializer, built from the schema text
    alone, produces the same bytes as our codecs, and its decoder reads ours back."""
    mr = pytest.importorskip("mcap_ros2._dynamic")
    v = np.array([1e-5, -2.5e-6, 0.0, 3.0, -7.25])
    for t, codec, fields, args in (
            ("SensorSample", pr.SensorCodec(5, me=ME_SEAL), ["seq", "step", "sim_time_ns",
                                                        "publish_wall_ns"], (7, 8, 9000, 123)),
            ("CurrentCommand", pr.CurrentCodec(5, me=OTHER), ["seq", "step", "sim_time_ns",
                                                              "recv_wall_ns", "publish_wall_ns"],
             (7, 8, 9000, 123, 456))):
        name = pr.schema_name(t)
        enc = mr.serialize_dynamic(name, pr.MSG_DEFS[t])[name]
        dec = mr.generate_dynamic(name, pr.MSG_DEFS[t])[name]
        ours = codec.encode(*args, v)
        msg = {"version": pr.PROTOCOL_VERSION, **dict(zip(fields, args)),
               ("displacement" if t == "SensorSample" else "current"): v.tolist(),
               "peer": list(codec.me), "mac": list(ours[-16:])}
        assert enc(msg) == ours, t
        d = dec(ours)
        assert bytes(d.peer) == codec.me and [getattr(d, f) for f in fields] == list(args)
        assert bytes(d.mac) == ours[-16:]
