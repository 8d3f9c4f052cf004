"""RecordBatch: the loop's SensorSample / CurrentCommand traffic handed to the recorder in
batches by the plant, off the loop's critical path (docs/protocol.md, section 3; docs/hil.md).

A recorder subscribed to ``plant/sensors`` and ``controller/currents`` makes every put of the
loop go out twice (zenoh writes one copy per matching peer, in the publishing thread) and wakes
a third process twice per period.  Instead the plant keeps the bytes it published and received,
verbatim, and publishes them every ``max_age_s`` (10 ms) of wall time on
``ambhil/<run>/record``; the recorder unpacks each batch into the ``plant/sensors`` and
``controller/currents`` channels, byte for byte what went over the wire.

Message (CDR, the common prefix of docs/protocol.md §3)::

    uint16 version
    uint64 seq            # batch counter
    uint64 step           # plant step of the first sample in the batch (0 if none)
    int64 sim_time_ns     # its sim time
    int64[] log_time_ns   # per message: wall time the plant published it (SensorSample, its
                          # publish_wall_ns) or received it (CurrentCommand)
    uint8[] topics        # per message: 0 = plant/sensors, 1 = controller/currents
    uint32[] sizes        # per message: payload length
    uint8[] data          # the payloads, concatenated, verbatim
"""
from __future__ import annotations

import struct

import numpy as np

from ambhil.bridge.protocol import wire
from ambhil.bridge.protocol.cdr import _R, _W
from ambhil.bridge.protocol.messages import DEFAULT_MAX_BATCH, ENCAP_LEN, PROTOCOL_VERSION
from ambhil.bridge.protocol.errors import LengthError, OversizeError, check_header

# one C call per flush (bridge/protocol/_wire.c) where the codec is native (bridge/protocol/wire.py), else numpy
_native_pack = wire._wire.pack_record_batch if wire.NATIVE else None

SENSORS, CURRENTS = 0, 1
TOPIC_SUFFIX = {SENSORS: "plant/sensors", CURRENTS: "controller/currents"}
MSG_DEF = (
    "# plant -> recorder: the loop's SensorSample (topic 0) and CurrentCommand (topic 1)\n"
    "# payloads of a stretch of the run, verbatim, with the plant's publish/receive wall times\n"
    "uint16 version\nuint64 seq\nuint64 step\nint64 sim_time_ns\nint64[] log_time_ns\n"
    "uint8[] topics\nuint32[] sizes\nuint8[] data\n")
MAX_AGE_S = 0.01               # a batch is published at the latest this long after the previous one
_PUB_WALL = struct.Struct("<q")
_PUB_WALL_OFFSET = ENCAP_LEN + 32      # SensorSample.publish_wall_ns


def encode(seq: int, step: int, sim_ns: int, log_ns, topics, payloads) -> bytes:
    n = len(payloads)
    if not len(log_ns) == len(topics) == n:
        raise LengthError("RecordBatch arrays must have equal length")
    w = _W()
    w.put("H", PROTOCOL_VERSION)
    w.put("Q", seq)
    w.put("Q", step)
    w.put("q", sim_ns)
    w.array(np.asarray(log_ns, np.int64), "<i8")
    w.array(np.asarray(topics, np.uint8), "u1")
    w.array(np.fromiter(map(len, payloads), np.uint32, n), "<u4")
    data = b"".join(payloads)
    w.put("I", len(data))
    w.b += data
    return bytes(w.b)


def decode_arrays(data, max_msgs: int = DEFAULT_MAX_BATCH):
    """-> ``(seq, step, sim_ns, log_ns, topics, sizes, offsets)``: the per-message arrays in the
    plant's order, ``offsets`` the payloads' byte offsets in ``data``; raises
    :class:`ambhil.bridge.protocol.errors.ProtocolError` on a malformed batch."""
    check_header(data, ENCAP_LEN + 48)
    r = _R(data)
    r.get("H")
    (seq,), (step,), (sim,) = r.get("Q"), r.get("Q"), r.get("q")
    log = r.array("<i8", max_msgs)
    topics = r.array("u1", max_msgs)
    sizes = r.array("<u4", max_msgs)
    (nb,) = r.get("I")
    if not len(log) == len(topics) == len(sizes):
        raise LengthError("RecordBatch arrays of unequal length")
    ends = np.cumsum(sizes, dtype=np.int64)
    if (int(ends[-1]) if len(ends) else 0) != nb or r.p + nb != len(data):
        raise LengthError(f"RecordBatch data of {len(data) - r.p} bytes, sizes say {int(sizes.sum())}")
    if topics.size and int(topics.max()) > CURRENTS:
        raise OversizeError(f"RecordBatch topic {int(topics.max())} unknown")
    return seq, step, sim, log, topics, sizes, r.p + ends - sizes


def decode(data, max_msgs: int = DEFAULT_MAX_BATCH):
    """-> ``(seq, step, sim_ns, [(topic, log_ns, payload bytes), ...])`` in the plant's order;
    raises :class:`ambhil.bridge.protocol.errors.ProtocolError` on a malformed batch."""
    seq, step, sim, log, topics, sizes, offs = decode_arrays(data, max_msgs)
    mv = memoryview(data)
    return seq, step, sim, [(t, lg, bytes(mv[p:p + s])) for t, lg, p, s in
                            zip(topics.tolist(), log.tolist(), offs.tolist(), sizes.tolist())]


def runs(data, max_msgs: int = DEFAULT_MAX_BATCH):
    """The batch's payloads per topic, for the recorder: ``(topic, log_ns, offset, count, size)``
    where a topic's payloads are all ``size`` bytes and back to back from ``offset`` (the plant
    packs them so), else ``(topic, log_ns, [payload bytes, ...], count, None)``; plus the header
    ``(seq, step, sim_ns)``.  Raises :class:`ambhil.bridge.protocol.errors.ProtocolError` as
    :func:`decode`."""
    seq, step, sim, log, topics, sizes, offs = decode_arrays(data, max_msgs)
    out = []
    for topic in (SENSORS, CURRENTS):
        sel = np.flatnonzero(topics == topic)
        if not len(sel):
            continue
        o, sz = offs[sel], sizes[sel]
        if (sz == sz[0]).all() and int(o[-1] - o[0]) == (len(sel) - 1) * int(sz[0]):
            out.append((topic, log[sel], int(o[0]), len(sel), int(sz[0])))
        else:
            mv = memoryview(data)
            out.append((topic, log[sel], [bytes(mv[p:p + s]) for p, s in zip(o.tolist(), sz.tolist())],
                        len(sel), None))
    return (seq, step, sim), out


class Batcher:
    """The plant's side: ``sent(msg)`` after each SensorSample put, ``received((wall_ns,
    payload))`` for each CurrentCommand payload that arrived (both plain list appends on the
    hot path); ``due`` is the wall time (ns, ``time.time_ns``) by which :meth:`flush` must run."""

    def __init__(self, pub, max_age_s: float = MAX_AGE_S, attach=None):
        self.pub = pub
        self.attach = attach      # payload -> attachment (the plant's id + MAC, docs/protocol.md 5.3)
        self.age_ns = int(max_age_s * 1e9)
        self._s: list[bytes] = []
        self._c: list[tuple[int, bytes]] = []
        self.sent = self._s.append
        self.received = self._c.append
        self.lists = (self._s, self._c)       # the same, as lists (the C lockstep loop of bridge/protocol/_plant_lockstep.c appends)
        self.seq = 0
        self.due = 0
        self.messages = 0

    def flush(self, now_ns: int) -> None:
        """Publish what was kept since the last flush (nothing if empty); next due in max_age.
        One C call (``ambhil.bridge.protocol._wire.pack_record_batch``) where built, else :meth:`_pack_py`."""
        self.due = now_ns + self.age_ns
        s, c = self._s, self._c
        ns, nc = len(s), len(c)
        if not ns and not nc:
            return
        if _native_pack is not None:
            msg = _native_pack(self.seq, PROTOCOL_VERSION, s, c)
        else:
            msg = self._pack_py(s, c, ns, nc)
        self.seq += 1
        self.messages += ns + nc
        s.clear()
        c.clear()
        self.pub.put(msg, attachment=None if self.attach is None else self.attach(msg))

    def _pack_py(self, s, c, ns, nc) -> bytes:
        """The batch bytes with numpy (the twin of ``ambhil.bridge.protocol._wire.pack_record_batch``)."""
        S = b"".join(s)
        if ns and len(S) == ns * len(s[0]):          # equal sizes: read the stamps in place
            size = len(s[0])
            slog = np.ndarray((ns,), "<i8", S, _PUB_WALL_OFFSET, (size,))
            ssz = np.full(ns, size, np.uint32)
        else:
            slog = np.fromiter((_PUB_WALL.unpack_from(m, _PUB_WALL_OFFSET)[0] for m in s), np.int64, ns)
            ssz = np.fromiter(map(len, s), np.uint32, ns)
        ct, cd = zip(*c) if nc else ((), ())
        msg = _pack(self.seq, s[0] if ns else None,
                    np.concatenate((slog, np.asarray(ct, np.int64))),
                    np.concatenate((np.zeros(ns, np.uint8), np.ones(nc, np.uint8))),
                    np.concatenate((ssz, np.fromiter(map(len, cd), np.uint32, nc))), S + b"".join(cd))
        return msg


def _pack(seq, first, log, topics, sizes, data) -> bytes:
    """The RecordBatch bytes (same layout as :func:`encode`, built without per-message work)."""
    step, sim = (struct.unpack_from("<Qq", first, ENCAP_LEN + 16) if first is not None else (0, 0))
    n = len(log)
    head = struct.pack("<4sH6xQQqI", b"\x00\x01\x00\x00", PROTOCOL_VERSION, seq, step, sim, n)
    out = [head]
    if n:
        out += [b"\0" * 4, log.astype("<i8").tobytes()]          # body offset 36 -> align 8
    out += [struct.pack("<I", n), topics.tobytes()]
    pos = sum(map(len, out)) - ENCAP_LEN
    pad = (-pos) % 4
    out += [b"\0" * pad, struct.pack("<I", n)]
    pos += pad + 4
    if n:                                                          # uint32: already 4-aligned
        out.append(sizes.astype("<u4").tobytes())
        pos += 4 * n
    out += [struct.pack("<I", len(data)), data]
    return b"".join(out)
