"""The wire codecs: ambhil's CDR codecs against mcap-ros2-support's generic ROS 2 CDR codec.

    .venv/bin/pip install mcap-ros2-support      # in the test extra; only for this comparison
    .venv/bin/python -m benchmarks.codec [--axes 4,7] [--repeat 7] [--number 20000]

For SensorSample and CurrentCommand, sealed as in a keyed run (protocol 3: the sender's id and a
keyed BLAKE2b-128 MAC end each message; the decoders check both), and, for the generic part of
bridge/protocol/cdr.py, Event and Timing, it first checks that both codecs agree byte for byte (our bytes decode to the same
values with mcap_ros2, and mcap_ros2's encoding of the same values equals ours), then prints
the median time per call (us) over ``--repeat`` timings of ``--number`` calls:

- ``wire C``: ambhil.bridge.protocol.wire (the loops' fast path, one C call per message);
- ``wire py``: its pure-Python twin (used when the extension is not built);
- ``ours slow``: ambhil.bridge.protocol.vector_codec pack_from/unpack_into (the loops' validating slow path)
  and encode/decode (tools);
- ``mcap_ros2``: mcap_ros2._dynamic serialize_dynamic / generate_dynamic (no validation:
  no axis count, finiteness, version or trailing-byte checks, no MAC: it is given ours).

A last block times the MAC alone over a SensorSample's bytes: the C BLAKE2b with the key's
state precomputed (what the fast path does per message), keyed from scratch (one compression
more), and hashlib (a keyed state copied, as the Python twin and the slow path do).
"""
from __future__ import annotations

import statistics
import timeit

from benchmarks import common


def _t(fn, number, repeat) -> float:
    return statistics.median(timeit.repeat(fn, number=number, repeat=repeat)) / number * 1e6


def main(argv=None):
    import numpy as np
    from ambhil.bridge import protocol as pr
    from ambhil.bridge.protocol import wire
    try:
        from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic
    except ImportError:
        raise SystemExit("benchmarks.codec: needs mcap-ros2-support (.venv/bin/pip install mcap-ros2-support)")
    ap = common.parser(__doc__, repeat=7)
    ap.add_argument("--axes", default="4,7")
    ap.add_argument("--number", type=int, default=20000)
    a = ap.parse_args(argv)
    common.header("codec", "wire codecs, us per call")
    N, R = a.number, a.repeat

    def codecs(t):
        name = pr.schema_name(t)
        return generate_dynamic(name, pr.MSG_DEFS[t])[name], serialize_dynamic(name, pr.MSG_DEFS[t])[name]

    print(f"wire codec: {'C' if wire.NATIVE else 'pure Python (C extension not built)'}; "
          f"median us per call over {R} x {N} calls")
    print(f"{'message':26s} {'op':7s} {'wire C':>8s} {'wire py':>8s} {'ours slow':>10s} {'mcap_ros2':>10s}  ratio mcap/ours-slow")
    for n in (int(x) for x in a.axes.split(",")):
        v = np.linspace(-1e-4, 1e-4, n)
        out = np.zeros(n)
        out_mv = memoryview(out).cast("B")
        v_mv = memoryview(v).cast("B")
        me = bytes(range(16))                # the sender's peer id
        seal = me + bytes(range(100, 132))   # ... and its topic key (a 48-byte seal)
        for t, codec, args, enc_c, dec_c, enc_py, dec_py, field in (
                ("SensorSample", pr.SensorCodec(n, me=seal, peer=seal), (7, 7, 7000, 123), wire.encode_sensor,
                 wire.decode_sensor, wire.py_encode_sensor, wire.py_decode_sensor, "displacement"),
                ("CurrentCommand", pr.CurrentCodec(n, me=seal, peer=seal), (7, 7, 7000, 123, 456), wire.encode_current,
                 wire.decode_current, wire.py_encode_current, wire.py_decode_current, "current")):
            dec_m, enc_m = codecs(t)
            ours = codec.encode(*args, v)
            fields = ["seq", "step", "sim_time_ns"] + (["publish_wall_ns"] if t == "SensorSample"
                                                       else ["recv_wall_ns", "publish_wall_ns"])
            msg = {"version": pr.PROTOCOL_VERSION, **dict(zip(fields, args)), field: v.tolist(),
                   "peer": list(me), "mac": list(ours[-16:])}
            # agreement, both ways
            theirs = enc_m(msg)
            assert theirs == ours, f"{t}: mcap_ros2 bytes differ from ours"
            d = dec_m(ours)
            assert [getattr(d, f) for f in fields] == list(args) and list(getattr(d, field)) == v.tolist()
            assert bytes(d.peer) == me and bytes(d.mac) == ours[-16:]
            rows = {
                "encode": (lambda: enc_c(v_mv, *args, seal), lambda: enc_py(v_mv, *args, seal),
                           lambda: codec.pack_from(*args, v_mv), lambda: enc_m(msg)),
                "decode": (lambda: dec_c(ours, 7, out_mv, seal), lambda: dec_py(ours, 7, out_mv, seal),
                           lambda: codec.unpack_into(ours, out_mv), lambda: dec_m(ours)),
            }
            assert dec_c(ours, 7, out_mv, seal) is not None and dec_py(ours, 7, out_mv, seal) is not None
            for op, fns in rows.items():
                ts = [_t(f, N, R) for f in fns]
                print(f"{t + f' ({n} axes)':26s} {op:7s} {ts[0]:8.3f} {ts[1]:8.3f} {ts[2]:10.3f} "
                      f"{ts[3]:10.3f}  {ts[3] / ts[2]:.1f}x", flush=True)
    # the generic CDR part (bridge/protocol/cdr.py): Event and a 200-step Timing batch
    ev = pr.Event(pr.EventKind.WARNING, "plant: Newton did not converge (step 17)", "plant", 3, 17, 17000, 99)
    b = pr.encode_event(ev)
    dec_m, enc_m = codecs("Event")
    evd = {"version": pr.PROTOCOL_VERSION, "kind": ev.kind, "seq": ev.seq, "step": ev.step, "sim_time_ns": ev.sim_time_ns,
           "wall_ns": ev.wall_ns, "source": ev.source, "text": ev.text}
    assert enc_m(evd) == b and dec_m(b).text == ev.text
    import numpy as np
    z = np.arange(200, dtype=np.int64)
    tm = pr.Timing(0, 0, 100000, 0, z, z, z, (z % 3).astype(np.uint8), 0)
    tb = pr.encode_timing(tm)
    tdec, tenc = codecs("Timing")
    tmd = {"version": pr.PROTOCOL_VERSION, "seq": 0, "step": 0, "sim_time_ns": 0, "period_ns": 100000, "overruns": 0,
           "wake_lateness_ns": z.tolist(), "rtt_ns": z.tolist(), "tet_ns": z.tolist(),
           "flags": (z % 3).tolist()}
    assert tenc(tmd) == tb and list(tdec(tb).rtt_ns) == z.tolist()
    for name, ours_e, ours_d, their_e, their_d in (
            ("Event", lambda: pr.encode_event(ev), lambda: pr.decode_event(b), lambda: enc_m(evd), lambda: dec_m(b)),
            ("Timing (200 steps)", lambda: pr.encode_timing(tm), lambda: pr.decode_timing(tb),
             lambda: tenc(tmd), lambda: tdec(tb))):
        for op, f1, f2 in (("encode", ours_e, their_e), ("decode", ours_d, their_d)):
            t1, t2 = _t(f1, N // 10, R), _t(f2, N // 10, R)
            print(f"{name:26s} {op:7s} {'':8s} {'':8s} {t1:10.3f} {t2:10.3f}  {t2 / t1:.1f}x", flush=True)
    _mac_alone(pr, wire, N, R)
    print("bytes: identical in every case (checked both ways)")


def _mac_alone(pr, wire, N, R):
    import hashlib
    key, body = bytes(range(32)), pr.encode_sensor(1, 1, 1, 1, [0.0] * 4)[:-16]
    h0 = hashlib.blake2b(key=key, digest_size=16)

    def py_mac():
        h = h0.copy()
        h.update(body)
        return h.digest()
    rows = [("hashlib (keyed state copied)", py_mac)]
    if wire.NATIVE:
        b2b = wire._wire.blake2b
        assert b2b(body, key, 16) == py_mac()
        rows.append(("C blake2b keyed from scratch", lambda: b2b(body, key, 16)))
    print(f"MAC alone, {len(body)} bytes (SensorSample, 4 axes), us per call:")
    for name, f in rows:
        print(f"  {name:32s} {_t(f, N, R):8.3f}", flush=True)


if __name__ == "__main__":
    main()
