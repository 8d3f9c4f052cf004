"""Fixed-layout codecs of the per-period messages (SensorSample, CurrentCommand).

Preallocated per axis count; ``pack_from``/``unpack_into`` move vectors between the wire and
preallocated arrays through memoryviews and are the validating slow path of the loops (they
name the reason of a rejection).  The per-message fast path is :mod:`ambhil.bridge.protocol.wire` (one C call
per message), which produces identical bytes.

Protocol version 2: both messages end with the sender's 16-byte peer id (``uint8[16] peer``,
after the vector).  A codec encodes with ``me`` (default :data:`NO_PEER`) and, when ``peer``
is given, rejects a message whose id is not ``peer`` with :class:`ForeignError` (reason
``peer``), right after the header check (docs/protocol.md, sections 4 and 5.1)."""
from __future__ import annotations

import math
import struct

import numpy as np

from ambhil.bridge.protocol.messages import (DEFAULT_MAX_AXES, ENCAP, ENCAP_LEN, NO_PEER, PEER_LEN, PROTOCOL_VERSION,
                       CurrentCommand, SensorSample)
from ambhil.bridge.protocol.errors import (AxisCountError, ForeignError, LengthError, NonFiniteError,
                              OversizeError, TruncatedError, check_header)


def _id(pid, what: str) -> bytes:
    b = bytes(pid)
    if len(b) != PEER_LEN:
        raise ValueError(f"{what}: a peer id is {PEER_LEN} bytes, got {len(b)}")
    return b


class _VectorCodec:
    """Fixed-axis-count codec for SensorSample / CurrentCommand (hot path).

    ``encode`` returns ``bytes``; ``decode`` returns a NamedTuple whose vector is a
    read-only ``numpy`` view of the received bytes (no copy)."""
    _n_times = 2
    _SMALL = 32          # up to this many axes, finiteness is checked with math.isfinite

    def __init__(self, n_axes: int, max_axes: int = DEFAULT_MAX_AXES, me: bytes = NO_PEER,
                 peer: bytes | None = None):
        if not 1 <= n_axes <= max_axes:
            raise ValueError(f"n_axes must be in 1..{max_axes}, got {n_axes}")
        self.n = n_axes
        self.max_axes = max_axes
        self.me = _id(me, "me")                        # the id this codec's messages carry
        self.peer = None if peer is None else _id(peer, "peer")   # the only sender accepted
        q = "q" * self._n_times
        self._hdr = struct.Struct(f"<4sH6xQQq{q}I4x")
        self._full = struct.Struct(f"<4sH6xQQq{q}I4x{n_axes}d{PEER_LEN}s")
        self._vec = struct.Struct(f"={n_axes}d")     # native: the in-memory numpy layout
        self.data_offset = self._hdr.size
        self.size = self._full.size
        self._cnt_idx = 5 + self._n_times
        self._count_off = self.data_offset - 8

    def _encode(self, seq, step, sim_ns, times, values) -> bytes:
        vals = values.tolist() if hasattr(values, "tolist") else list(values)
        if len(vals) != self.n:
            raise AxisCountError(f"{len(vals)} values, expected {self.n}")
        if not all(map(math.isfinite, vals)):
            raise NonFiniteError("refusing to send non-finite values")
        return self._full.pack(ENCAP, PROTOCOL_VERSION, seq, step, sim_ns, *times, self.n, *vals,
                               self.me)

    def check_peer(self, data) -> None:
        """Raise :class:`ForeignError` if ``data`` (a message with a valid header) does not end
        with the expected ``peer`` id (nothing is checked without one)."""
        if self.peer is not None and data[-PEER_LEN:] != self.peer:
            raise ForeignError(f"peer id {bytes(data[-PEER_LEN:]).hex()}, not the paired "
                               f"{self.peer.hex()}")

    def _slow_error(self, data):
        n = len(data)
        check_header(data, self.data_offset)     # truncated / encapsulation / version
        self.check_peer(data)                    # then: who sent it
        cnt = int.from_bytes(data[self._count_off:self._count_off + 4], "little")
        if cnt > self.max_axes:
            raise OversizeError(f"{cnt} axes > maximum {self.max_axes}")
        if cnt != self.n:
            raise AxisCountError(f"{cnt} axes, expected {self.n}")
        raise LengthError(f"{n} bytes, expected {self.size} for {self.n} axes")

    def _decode(self, data):
        if len(data) != self.size:
            self._slow_error(data)
        h = self._full.unpack(data)
        if (h[0] != ENCAP or h[1] != PROTOCOL_VERSION or h[self._cnt_idx] != self.n
                or (self.peer is not None and h[-1] != self.peer)):
            self._slow_error(data)
        v = np.frombuffer(data, "<f8", self.n, self.data_offset)
        if self.n <= self._SMALL:
            ok = all(map(math.isfinite, h[self._cnt_idx + 1:-1]))
        else:
            ok = bool(np.isfinite(v).all())
        if not ok:
            bad = int(np.flatnonzero(~np.isfinite(v))[0])
            raise NonFiniteError(f"axis {bad} = {v[bad]}")
        return h, v


    # ---- memoryview path: no numpy calls and no objects beyond the struct tuple per message.
    # The loops' fast path is bridge.protocol.wire (same semantics, one C call); these are its
    # validating slow path, which names the reason of a rejection (docs/hil.md).
    def view(self, arr) -> memoryview:
        """Writable byte view of a float64 vector of ``n`` values, for :meth:`unpack_into`
        (write) and ``pack_from`` (read).  Converts (copies) anything else; the view keeps
        the array alive.  Raises :class:`AxisCountError` on a wrong length."""
        a = np.ascontiguousarray(arr, dtype=np.float64)
        if a.shape != (self.n,):
            raise AxisCountError(f"{a.size} values in shape {a.shape}, expected ({self.n},)")
        return memoryview(a).cast("B")

    def _check_vec(self, vals):
        if not all(map(math.isfinite, vals)):
            bad = next(i for i, x in enumerate(vals) if not math.isfinite(x))
            raise NonFiniteError(f"axis {bad} = {vals[bad]}")

    def unpack_into(self, data, out: memoryview) -> tuple:
        """Validate ``data`` like :meth:`decode`; on success copy its vector into ``out``
        (a :meth:`view`) and return the raw field tuple ``(encap, version, seq, step,
        sim_time_ns, <times>, count, v0, v1, ..., peer)``.  ``out`` is untouched on error."""
        if len(data) != self.size:
            self._slow_error(data)
        h = self._full.unpack(data)
        ci = self._cnt_idx
        if (h[0] != ENCAP or h[1] != PROTOCOL_VERSION or h[ci] != self.n
                or (self.peer is not None and h[-1] != self.peer)):
            self._slow_error(data)
        v = h[ci + 1:-1]
        if not all(map(math.isfinite, v)):
            self._check_vec(v)
        self._vec.pack_into(out, 0, *v)
        return h


class SensorCodec(_VectorCodec):
    """SensorSample codec for a fixed axis count."""
    _n_times = 1

    def pack_from(self, seq: int, step: int, sim_time_ns: int, publish_wall_ns: int,
                  displacement: memoryview) -> bytes:
        """Hot-path :meth:`encode` from a :meth:`view` (raises NonFiniteError)."""
        v = self._vec.unpack(displacement)
        if not all(map(math.isfinite, v)):
            self._check_vec(v)
        return self._full.pack(ENCAP, PROTOCOL_VERSION, seq, step, sim_time_ns,
                               publish_wall_ns, self.n, *v, self.me)

    def encode(self, seq: int, step: int, sim_time_ns: int, publish_wall_ns: int,
               displacement) -> bytes:
        return self._encode(seq, step, sim_time_ns, (publish_wall_ns,), displacement)

    def decode(self, data) -> SensorSample:
        h, v = self._decode(data)
        return SensorSample(h[2], h[3], h[4], h[5], v, h[-1])


class CurrentCodec(_VectorCodec):
    """CurrentCommand codec for a fixed axis count."""
    _n_times = 2

    def pack_from(self, seq: int, step: int, sim_time_ns: int, recv_wall_ns: int,
                  publish_wall_ns: int, current: memoryview) -> bytes:
        """Hot-path :meth:`encode` from a :meth:`view` (raises NonFiniteError)."""
        v = self._vec.unpack(current)
        if not all(map(math.isfinite, v)):
            self._check_vec(v)
        return self._full.pack(ENCAP, PROTOCOL_VERSION, seq, step, sim_time_ns, recv_wall_ns,
                               publish_wall_ns, self.n, *v, self.me)

    def encode(self, seq: int, step: int, sim_time_ns: int, recv_wall_ns: int,
               publish_wall_ns: int, current) -> bytes:
        return self._encode(seq, step, sim_time_ns, (recv_wall_ns, publish_wall_ns), current)

    def decode(self, data) -> CurrentCommand:
        h, v = self._decode(data)
        return CurrentCommand(h[2], h[3], h[4], h[5], h[6], v, h[-1])


def encode_sensor(seq, step, sim_time_ns, publish_wall_ns, displacement,
                  peer: bytes = NO_PEER) -> bytes:
    """A SensorSample sent by the plant with peer id ``peer``."""
    return SensorCodec(len(displacement), me=peer).encode(seq, step, sim_time_ns,
                                                          publish_wall_ns, displacement)


def encode_current(seq, step, sim_time_ns, recv_wall_ns, publish_wall_ns, current,
                   peer: bytes = NO_PEER) -> bytes:
    """A CurrentCommand sent by the controller with peer id ``peer``."""
    return CurrentCodec(len(current), me=peer).encode(seq, step, sim_time_ns, recv_wall_ns,
                                                      publish_wall_ns, current)


def _peek_count(data, off: int, max_axes: int) -> int:
    if len(data) < off + 4:
        check_header(data, off + 4)
        raise TruncatedError(f"{len(data)} bytes")
    check_header(data, off + 4)
    cnt = int.from_bytes(data[off:off + 4], "little")
    if cnt > max_axes:
        raise OversizeError(f"{cnt} axes > maximum {max_axes}")
    if cnt == 0:
        raise AxisCountError("0 axes")
    return cnt


def decode_sensor(data, n_axes: int | None = None, max_axes: int = DEFAULT_MAX_AXES,
                  peer: bytes | None = None) -> SensorSample:
    """Decode a SensorSample; ``n_axes`` None accepts any count in 1..max_axes; ``peer``: the
    only sender accepted (None: any)."""
    if n_axes is None:
        n_axes = _peek_count(data, ENCAP_LEN + 40, max_axes)
    return SensorCodec(n_axes, max(max_axes, n_axes), peer=peer).decode(data)


def decode_current(data, n_axes: int | None = None, max_axes: int = DEFAULT_MAX_AXES,
                   peer: bytes | None = None) -> CurrentCommand:
    if n_axes is None:
        n_axes = _peek_count(data, ENCAP_LEN + 48, max_axes)
    return CurrentCodec(n_axes, max(max_axes, n_axes), peer=peer).decode(data)
