"""Fixed-layout codecs of the per-period messages (SensorSample, CurrentCommand).

Preallocated per axis count; ``pack_from``/``unpack_into`` move vectors between the wire and
preallocated arrays through memoryviews and are the validating slow path of the loops (they
name the reason of a rejection).  The per-message fast path is :mod:`ambhil.bridge.protocol.wire` (one C call
per message), which produces identical bytes.

Protocol version 3: both messages end with the sender's 16-byte peer id and a 16-byte MAC
(``uint8[16] peer, uint8[16] mac``, after the vector; mac = keyed BLAKE2b-128 of every byte
before it, docs/protocol.md 5.3).  A codec encodes with the seal ``me`` (48 bytes: id || topic
key, :meth:`ambhil.bridge.protocol.auth.RunAuth.seal`; a bare 16-byte id means the all-zero key;
default :data:`NO_PEER`).  When ``peer`` (a seal, or an id with the zero key) is given it
rejects, right after the header check, a message whose id is not ``peer``'s
(:class:`ForeignError`, reason ``peer``) and then one whose MAC is not valid under ``peer``'s
key (:class:`AuthError`, reason ``auth``); only then the rest (docs/protocol.md, section 4).
Without ``peer`` neither is checked (readers of recordings, tools)."""
from __future__ import annotations

import hashlib
import hmac
import math
import struct

import numpy as np

from ambhil.bridge.protocol.messages import (DEFAULT_MAX_AXES, ENCAP, ENCAP_LEN, MAC_LEN, NO_PEER, PEER_LEN,
                       PROTOCOL_VERSION, CurrentCommand, SensorSample, split_seal)
from ambhil.bridge.protocol.errors import (AuthError, AxisCountError, ForeignError, LengthError,
                              NonFiniteError, OversizeError, TruncatedError, check_header)

_TAIL = PEER_LEN + MAC_LEN       # peer id, mac: the last 32 bytes


def _hasher(key: bytes):
    """The keyed BLAKE2b-128 state of ``key`` before any data: ``copy()`` per message costs
    less than keying a new one."""
    return hashlib.blake2b(key=key, digest_size=MAC_LEN)


class _VectorCodec:
    """Fixed-axis-count codec for SensorSample / CurrentCommand (hot path).

    ``encode`` returns ``bytes``; ``decode`` returns a NamedTuple whose vector is a
    read-only ``numpy`` view of the received bytes (no copy).  ``me`` / ``peer`` are set from
    seals (or ids, the zero key) and read back as the ids; ``me_seal`` / ``peer_seal`` are the
    48-byte seals."""
    _n_times = 2
    _SMALL = 32          # up to this many axes, finiteness is checked with math.isfinite

    def __init__(self, n_axes: int, max_axes: int = DEFAULT_MAX_AXES, me: bytes = NO_PEER,
                 peer: bytes | None = None):
        if not 1 <= n_axes <= max_axes:
            raise ValueError(f"n_axes must be in 1..{max_axes}, got {n_axes}")
        self.n = n_axes
        self.max_axes = max_axes
        self.me = me                                   # the seal this codec's messages carry
        self.peer = peer                               # the only sender accepted (None: any)
        q = "q" * self._n_times
        self._hdr = struct.Struct(f"<4sH6xQQq{q}I4x")
        self._body = struct.Struct(f"<4sH6xQQq{q}I4x{n_axes}d{PEER_LEN}s")   # all but the mac
        self._full = struct.Struct(f"<4sH6xQQq{q}I4x{n_axes}d{PEER_LEN}s{MAC_LEN}s")
        self._vec = struct.Struct(f"={n_axes}d")     # native: the in-memory numpy layout
        self.data_offset = self._hdr.size
        self.size = self._full.size
        self._cnt_idx = 5 + self._n_times
        self._count_off = self.data_offset - 8

    # ---- seals
    @property
    def me(self) -> bytes:
        """The id this codec's messages carry (set: a seal or an id)."""
        return self._me

    @me.setter
    def me(self, seal) -> None:
        self._me, key = split_seal(seal, "me")
        self.me_seal = self._me + key
        self._me_h = _hasher(key)

    @property
    def peer(self) -> bytes | None:
        """The id of the only sender accepted, None: any (set: a seal, an id or None)."""
        return self._peer

    @peer.setter
    def peer(self, seal) -> None:
        if seal is None:
            self._peer = self.peer_seal = self._peer_h = None
            return
        self._peer, key = split_seal(seal, "peer")
        self.peer_seal = self._peer + key
        self._peer_h = _hasher(key)

    def _seal(self, body: bytes) -> bytes:
        h = self._me_h.copy()
        h.update(body)
        return body + h.digest()

    def _encode(self, seq, step, sim_ns, times, values) -> bytes:
        vals = values.tolist() if hasattr(values, "tolist") else list(values)
        if len(vals) != self.n:
            raise AxisCountError(f"{len(vals)} values, expected {self.n}")
        if not all(map(math.isfinite, vals)):
            raise NonFiniteError("refusing to send non-finite values")
        return self._seal(self._body.pack(ENCAP, PROTOCOL_VERSION, seq, step, sim_ns, *times,
                                          self.n, *vals, self._me))

    def check_peer(self, data) -> None:
        """Raise :class:`ForeignError` if ``data`` (a message with a valid header) does not
        carry the expected ``peer`` id (bytes [-32:-16]; nothing is checked without one)."""
        if self._peer is not None and data[-_TAIL:-MAC_LEN] != self._peer:
            raise ForeignError(f"peer id {bytes(data[-_TAIL:-MAC_LEN]).hex()}, not the paired "
                               f"{self._peer.hex()}")

    def mac_ok(self, data) -> bool:
        """Whether the last 16 bytes of ``data`` are the MAC of the rest under ``peer``'s key
        (True without ``peer``)."""
        if self._peer_h is None:
            return True
        h = self._peer_h.copy()
        h.update(data[:-MAC_LEN])
        return hmac.compare_digest(h.digest(), bytes(data[-MAC_LEN:]))

    def check_mac(self, data) -> None:
        """Raise :class:`AuthError` if ``data``'s MAC is not valid under ``peer``'s key."""
        if not self.mac_ok(data):
            raise AuthError(f"mac {bytes(data[-MAC_LEN:]).hex()} is not valid under the key of "
                            f"peer {self._peer.hex()}")

    def _slow_error(self, data):
        n = len(data)
        check_header(data, self.data_offset)     # truncated / encapsulation / version
        self.check_peer(data)                    # then: who sent it
        self.check_mac(data)                     # and whether it holds the key
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
                or (self._peer is not None and (h[-2] != self._peer or not self.mac_ok(data)))):
            self._slow_error(data)
        v = np.frombuffer(data, "<f8", self.n, self.data_offset)
        if self.n <= self._SMALL:
            ok = all(map(math.isfinite, h[self._cnt_idx + 1:-2]))
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
        sim_time_ns, <times>, count, v0, v1, ..., peer, mac)``.  ``out`` is untouched on
        error."""
        if len(data) != self.size:
            self._slow_error(data)
        h = self._full.unpack(data)
        ci = self._cnt_idx
        if (h[0] != ENCAP or h[1] != PROTOCOL_VERSION or h[ci] != self.n
                or (self._peer is not None and (h[-2] != self._peer or not self.mac_ok(data)))):
            self._slow_error(data)
        v = h[ci + 1:-2]
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
        return self._seal(self._body.pack(ENCAP, PROTOCOL_VERSION, seq, step, sim_time_ns,
                                          publish_wall_ns, self.n, *v, self._me))

    def encode(self, seq: int, step: int, sim_time_ns: int, publish_wall_ns: int,
               displacement) -> bytes:
        return self._encode(seq, step, sim_time_ns, (publish_wall_ns,), displacement)

    def decode(self, data) -> SensorSample:
        h, v = self._decode(data)
        return SensorSample(h[2], h[3], h[4], h[5], v, h[-2], h[-1])


class CurrentCodec(_VectorCodec):
    """CurrentCommand codec for a fixed axis count."""
    _n_times = 2

    def pack_from(self, seq: int, step: int, sim_time_ns: int, recv_wall_ns: int,
                  publish_wall_ns: int, current: memoryview) -> bytes:
        """Hot-path :meth:`encode` from a :meth:`view` (raises NonFiniteError)."""
        v = self._vec.unpack(current)
        if not all(map(math.isfinite, v)):
            self._check_vec(v)
        return self._seal(self._body.pack(ENCAP, PROTOCOL_VERSION, seq, step, sim_time_ns,
                                          recv_wall_ns, publish_wall_ns, self.n, *v, self._me))

    def encode(self, seq: int, step: int, sim_time_ns: int, recv_wall_ns: int,
               publish_wall_ns: int, current) -> bytes:
        return self._encode(seq, step, sim_time_ns, (recv_wall_ns, publish_wall_ns), current)

    def decode(self, data) -> CurrentCommand:
        h, v = self._decode(data)
        return CurrentCommand(h[2], h[3], h[4], h[5], h[6], v, h[-2], h[-1])


def encode_sensor(seq, step, sim_time_ns, publish_wall_ns, displacement,
                  peer: bytes = NO_PEER) -> bytes:
    """A SensorSample sent by the plant sealed with ``peer`` (a seal, or an id: zero key)."""
    return SensorCodec(len(displacement), me=peer).encode(seq, step, sim_time_ns,
                                                          publish_wall_ns, displacement)


def encode_current(seq, step, sim_time_ns, recv_wall_ns, publish_wall_ns, current,
                   peer: bytes = NO_PEER) -> bytes:
    """A CurrentCommand sent by the controller sealed with ``peer`` (a seal, or an id)."""
    return CurrentCodec(len(current), me=peer).encode(seq, step, sim_time_ns, recv_wall_ns,
                                                      publish_wall_ns, current)


def reseal(data, seal) -> bytes:
    """``data`` (a SensorSample or CurrentCommand of any axis count, assumed well formed) as
    sent by ``seal`` (48 bytes, or an id: the zero key): its id replaced by the seal's and
    its MAC recomputed under the seal's key.  For a sender that forwards recorded samples as its
    own (the replay tool posing as the plant) or copies them (foreign copies)."""
    b = bytes(data)
    if len(b) < ENCAP_LEN + 48 + _TAIL:
        raise TruncatedError(f"{len(b)} bytes: no SensorSample / CurrentCommand to reseal")
    pid, key = split_seal(seal, "reseal")
    h = _hasher(key)
    body = b[:-_TAIL] + pid
    h.update(body)
    return body + h.digest()


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
    seal (or id, zero key) of the only sender accepted, its MAC checked (None: any, unchecked)."""
    if n_axes is None:
        n_axes = _peek_count(data, ENCAP_LEN + 40, max_axes)
    return SensorCodec(n_axes, max(max_axes, n_axes), peer=peer).decode(data)


def decode_current(data, n_axes: int | None = None, max_axes: int = DEFAULT_MAX_AXES,
                   peer: bytes | None = None) -> CurrentCommand:
    if n_axes is None:
        n_axes = _peek_count(data, ENCAP_LEN + 48, max_axes)
    return CurrentCodec(n_axes, max(max_axes, n_axes), peer=peer).decode(data)
