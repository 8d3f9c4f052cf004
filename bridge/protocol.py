"""ambhil wire protocol: CDR (XCDR1, little endian) encodings of ros2msg types.

The payload on the wire is exactly the serialised message, so the recorder
stores it verbatim in MCAP (message_encoding "cdr", schema encoding "ros2msg")
and tools such as Rerun or Foxglove decode it natively.  See docs/protocol.md
for the byte layouts, key expressions and the behaviour on bad input.

Every message starts with the same 32-byte prefix (offsets relative to the
start of the CDR body, i.e. after the 4-byte encapsulation header
``00 01 00 00``)::

    0  uint16 version      (Event: offset 2 holds uint16 kind)
    8  uint64 seq
    16 uint64 step
    24 int64  sim_time_ns

Codecs (:class:`SensorCodec`, :class:`CurrentCodec`) are preallocated per axis count;
``pack_from``/``unpack_into`` move vectors between the wire and preallocated arrays through
memoryviews and are the validating slow path of the loops.  The per-message fast path is
:mod:`bridge.wire` (one C call per message), which produces identical bytes.
"""
from __future__ import annotations

import json
import math
import re
import struct
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

PROTOCOL_VERSION = 1
ENCAP = b"\x00\x01\x00\x00"          # CDR_LE encapsulation, options 0
ENCAP_LEN = 4
DEFAULT_MAX_AXES = 64                # largest accepted axis count
DEFAULT_MAX_TEXT = 64 * 1024         # largest accepted string (bytes, without NUL)
DEFAULT_MAX_BATCH = 100_000          # largest accepted Timing batch
SIM_TIME_OFFSET = ENCAP_LEN + 24     # absolute offset of int64 sim_time_ns in every message
SEQ_OFFSET = ENCAP_LEN + 8           # absolute offset of uint64 seq in every message
STEP_OFFSET = ENCAP_LEN + 16
EVENT_KIND_OFFSET = ENCAP_LEN + 2    # absolute offset of uint16 kind in Event

PACKAGE = "ambhil_msgs"

# --------------------------------------------------------------------------- schemas
MSG_DEFS: dict[str, str] = {
    "SensorSample": (
        "# plant -> controller, one per controller period\n"
        "uint16 version\nuint64 seq\nuint64 step\nint64 sim_time_ns\nint64 publish_wall_ns\n"
        "float64[] displacement\n"),
    "CurrentCommand": (
        "# controller -> plant, answers the SensorSample with the same seq\n"
        "uint16 version\nuint64 seq\nuint64 step\nint64 sim_time_ns\n"
        "int64 recv_wall_ns\nint64 publish_wall_ns\nfloat64[] current\n"),
    "Event": (
        "uint16 version\nuint16 kind\nuint64 seq\nuint64 step\nint64 sim_time_ns\n"
        "int64 wall_ns\nstring source\nstring text\n"),
    "RunMeta": (
        "uint16 version\nuint64 seq\nuint64 step\nint64 sim_time_ns\nint64 wall_ns\n"
        "string json\n"),
    "Timing": (
        "# plant-side timing for steps step..step+n-1 (one batch)\n"
        "uint16 version\nuint64 seq\nuint64 step\nint64 sim_time_ns\nint64 period_ns\n"
        "uint64 overruns\nint64[] wake_lateness_ns\nint64[] rtt_ns\nint64[] tet_ns\n"
        "uint8[] flags\n"),
}


def schema_name(msg_type: str) -> str:
    return f"{PACKAGE}/msg/{msg_type}"


# Timing.flags bits
FLAG_HELD = 1          # no valid reply at the deadline: last currents held (overrun)
FLAG_LATE_WAKE = 2     # plant woke after the next deadline (overrun)
FLAG_WARMUP = 4        # step belongs to the warm-up, excluded from statistics


class EventKind:
    """Event.kind codes (uint16).  Names are stable; codes never reused."""
    INFO = 0
    RUN_START = 1
    RUN_END = 2
    FAULT = 3
    REJECTED = 4        # malformed message dropped (text = reason code + detail)
    DUPLICATE = 5       # seq already seen / stale reply
    GAP = 6             # seq jumped (missing messages)
    OVERRUN = 7         # deadline missed, last currents held
    PEER_LOST = 8       # liveliness DELETE of a peer
    TIMEOUT = 9         # no message within the watchdog timeout
    WARNING = 10        # non-fatal condition (e.g. plant Newton iteration not converged)
    NAMES = {0: "INFO", 1: "RUN_START", 2: "RUN_END", 3: "FAULT", 4: "REJECTED",
             5: "DUPLICATE", 6: "GAP", 7: "OVERRUN", 8: "PEER_LOST", 9: "TIMEOUT",
             10: "WARNING"}


# --------------------------------------------------------------------------- errors
class ProtocolError(ValueError):
    """A message failed validation.  ``reason`` is a short stable code."""
    reason = "protocol"

    def __init__(self, detail: str = ""):
        super().__init__(f"{self.reason}: {detail}" if detail else self.reason)
        self.detail = detail


class TruncatedError(ProtocolError):
    reason = "truncated"


class EncapsulationError(ProtocolError):
    reason = "encapsulation"


class VersionError(ProtocolError):
    reason = "version"


class LengthError(ProtocolError):
    reason = "length"


class OversizeError(ProtocolError):
    reason = "oversize"


class AxisCountError(ProtocolError):
    reason = "axes"


class NonFiniteError(ProtocolError):
    reason = "nonfinite"


class StringError(ProtocolError):
    reason = "string"


class SequenceError(ProtocolError):
    reason = "sequence"


REASONS = tuple(c.reason for c in (TruncatedError, EncapsulationError, VersionError, LengthError,
                                   OversizeError, AxisCountError, NonFiniteError, StringError,
                                   SequenceError))


# --------------------------------------------------------------------------- keys
_RUN_ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


class Keys(NamedTuple):
    root: str
    sensors: str
    currents: str
    events: str
    meta: str
    timing: str
    alive_plant: str
    alive_controller: str
    alive_recorder: str
    alive_all: str
    all: str
    wake: str          # session-local key used to wake a blocked receiver (never leaves a process)


def keys(run_id: str) -> Keys:
    """Key expressions of one run.  ``run_id`` must match ``[A-Za-z0-9_.-]{1,64}``."""
    if not isinstance(run_id, str) or not _RUN_ID_RE.match(run_id):
        raise ValueError(f"invalid run id {run_id!r}: use 1-64 characters of [A-Za-z0-9_.-]")
    r = f"ambhil/{run_id}"
    return Keys(r, f"{r}/plant/sensors", f"{r}/controller/currents", f"{r}/events", f"{r}/meta",
                f"{r}/timing", f"{r}/alive/plant", f"{r}/alive/controller", f"{r}/alive/recorder",
                f"{r}/alive/*", f"{r}/**", f"{r}/local/wake")


# key suffix (after ambhil/<run>/) -> message type
TOPIC_TYPES = {"plant/sensors": "SensorSample", "controller/currents": "CurrentCommand",
               "events": "Event", "meta": "RunMeta", "timing": "Timing"}


def message_type_for_key(key: str) -> str | None:
    parts = key.split("/", 2)
    if len(parts) < 3 or parts[0] != "ambhil":
        return None
    return TOPIC_TYPES.get(parts[2])


# --------------------------------------------------------------------------- helpers
def _check_header(data, min_len: int) -> None:
    if len(data) < min_len:
        raise TruncatedError(f"{len(data)} bytes < minimum {min_len}")
    if data[:4] != ENCAP:
        raise EncapsulationError(f"header {bytes(data[:4]).hex()} != 00010000 (CDR little endian)")
    v = data[4] | (data[5] << 8)
    if v != PROTOCOL_VERSION:
        raise VersionError(f"version {v} != {PROTOCOL_VERSION}")


class SensorSample(NamedTuple):
    seq: int
    step: int
    sim_time_ns: int
    publish_wall_ns: int
    displacement: np.ndarray


class CurrentCommand(NamedTuple):
    seq: int
    step: int
    sim_time_ns: int
    recv_wall_ns: int
    publish_wall_ns: int
    current: np.ndarray


class _VectorCodec:
    """Fixed-axis-count codec for SensorSample / CurrentCommand (hot path).

    ``encode`` returns ``bytes``; ``decode`` returns a NamedTuple whose vector is a
    read-only ``numpy`` view of the received bytes (no copy)."""
    _n_times = 2
    _SMALL = 32          # up to this many axes, finiteness is checked with math.isfinite

    def __init__(self, n_axes: int, max_axes: int = DEFAULT_MAX_AXES):
        if not 1 <= n_axes <= max_axes:
            raise ValueError(f"n_axes must be in 1..{max_axes}, got {n_axes}")
        self.n = n_axes
        self.max_axes = max_axes
        q = "q" * self._n_times
        self._hdr = struct.Struct(f"<4sH6xQQq{q}I4x")
        self._full = struct.Struct(f"<4sH6xQQq{q}I4x{n_axes}d")
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
        return self._full.pack(ENCAP, PROTOCOL_VERSION, seq, step, sim_ns, *times, self.n, *vals)

    def _slow_error(self, data):
        n = len(data)
        _check_header(data, self.data_offset)     # truncated / encapsulation / version
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
        if h[0] != ENCAP or h[1] != PROTOCOL_VERSION or h[self._cnt_idx] != self.n:
            self._slow_error(data)
        v = np.frombuffer(data, "<f8", self.n, self.data_offset)
        if self.n <= self._SMALL:
            ok = all(map(math.isfinite, h[self._cnt_idx + 1:]))
        else:
            ok = bool(np.isfinite(v).all())
        if not ok:
            bad = int(np.flatnonzero(~np.isfinite(v))[0])
            raise NonFiniteError(f"axis {bad} = {v[bad]}")
        return h, v


    # ---- memoryview path: no numpy calls and no objects beyond the struct tuple per message.
    # The loops' fast path is bridge.wire (same semantics, one C call); these are its
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
        sim_time_ns, <times>, count, v0, v1, ...)``.  ``out`` is untouched on error."""
        if len(data) != self.size:
            self._slow_error(data)
        h = self._full.unpack(data)
        ci = self._cnt_idx
        if h[0] != ENCAP or h[1] != PROTOCOL_VERSION or h[ci] != self.n:
            self._slow_error(data)
        v = h[ci + 1:]
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
                               publish_wall_ns, self.n, *v)

    def encode(self, seq: int, step: int, sim_time_ns: int, publish_wall_ns: int,
               displacement) -> bytes:
        return self._encode(seq, step, sim_time_ns, (publish_wall_ns,), displacement)

    def decode(self, data) -> SensorSample:
        h, v = self._decode(data)
        return SensorSample(h[2], h[3], h[4], h[5], v)


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
                               publish_wall_ns, self.n, *v)

    def encode(self, seq: int, step: int, sim_time_ns: int, recv_wall_ns: int,
               publish_wall_ns: int, current) -> bytes:
        return self._encode(seq, step, sim_time_ns, (recv_wall_ns, publish_wall_ns), current)

    def decode(self, data) -> CurrentCommand:
        h, v = self._decode(data)
        return CurrentCommand(h[2], h[3], h[4], h[5], h[6], v)


def encode_sensor(seq, step, sim_time_ns, publish_wall_ns, displacement) -> bytes:
    return SensorCodec(len(displacement)).encode(seq, step, sim_time_ns, publish_wall_ns,
                                                 displacement)


def encode_current(seq, step, sim_time_ns, recv_wall_ns, publish_wall_ns, current) -> bytes:
    return CurrentCodec(len(current)).encode(seq, step, sim_time_ns, recv_wall_ns,
                                             publish_wall_ns, current)


def _peek_count(data, off: int, max_axes: int) -> int:
    if len(data) < off + 4:
        _check_header(data, off + 4)
        raise TruncatedError(f"{len(data)} bytes")
    _check_header(data, off + 4)
    cnt = int.from_bytes(data[off:off + 4], "little")
    if cnt > max_axes:
        raise OversizeError(f"{cnt} axes > maximum {max_axes}")
    if cnt == 0:
        raise AxisCountError("0 axes")
    return cnt


def decode_sensor(data, n_axes: int | None = None, max_axes: int = DEFAULT_MAX_AXES) -> SensorSample:
    """Decode a SensorSample; ``n_axes`` None accepts any count in 1..max_axes."""
    if n_axes is None:
        n_axes = _peek_count(data, ENCAP_LEN + 40, max_axes)
    return SensorCodec(n_axes, max(max_axes, n_axes)).decode(data)


def decode_current(data, n_axes: int | None = None, max_axes: int = DEFAULT_MAX_AXES) -> CurrentCommand:
    if n_axes is None:
        n_axes = _peek_count(data, ENCAP_LEN + 48, max_axes)
    return CurrentCodec(n_axes, max(max_axes, n_axes)).decode(data)


# --------------------------------------------------------------------------- generic CDR
class _W:
    __slots__ = ("b",)

    def __init__(self):
        self.b = bytearray(ENCAP)

    def align(self, a):
        pad = (-(len(self.b) - ENCAP_LEN)) % a
        self.b += b"\0" * pad

    def put(self, fmt, *v):
        s = struct.calcsize(fmt)
        self.align(s if s in (2, 4, 8) else 1)
        self.b += struct.pack("<" + fmt, *v)

    def string(self, s: str, max_text: int):
        raw = s.encode("utf-8")
        if len(raw) > max_text:
            raise OversizeError(f"string of {len(raw)} bytes > maximum {max_text}")
        self.put("I", len(raw) + 1)
        self.b += raw + b"\0"

    def array(self, arr: np.ndarray, dtype: str):
        a = np.ascontiguousarray(arr, dtype=dtype)
        self.put("I", a.size)
        if a.size:
            self.align(a.itemsize)
            self.b += a.tobytes()


class _R:
    __slots__ = ("d", "p")

    def __init__(self, data):
        self.d = data
        self.p = ENCAP_LEN

    def align(self, a):
        self.p += (-(self.p - ENCAP_LEN)) % a

    def get(self, fmt):
        s = struct.calcsize(fmt)
        self.align(s if s in (2, 4, 8) else 1)
        if self.p + s > len(self.d):
            raise TruncatedError(f"need {self.p + s} bytes, have {len(self.d)}")
        v = struct.unpack_from("<" + fmt, self.d, self.p)
        self.p += s
        return v

    def string(self, max_text: int) -> str:
        (n,) = self.get("I")
        if n == 0:
            raise StringError("string length 0 (must include the NUL terminator)")
        if n - 1 > max_text:
            raise OversizeError(f"string of {n - 1} bytes > maximum {max_text}")
        if self.p + n > len(self.d):
            raise TruncatedError(f"string runs past the end ({self.p + n} > {len(self.d)})")
        raw = bytes(self.d[self.p:self.p + n])
        self.p += n
        if raw[-1] != 0:
            raise StringError("string not NUL-terminated")
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError as e:
            raise StringError(f"invalid UTF-8: {e}") from None

    def array(self, dtype: str, max_n: int) -> np.ndarray:
        (n,) = self.get("I")
        if n > max_n:
            raise OversizeError(f"array of {n} > maximum {max_n}")
        it = np.dtype(dtype).itemsize
        if n:
            self.align(it)
        if self.p + n * it > len(self.d):
            raise TruncatedError(f"array runs past the end ({self.p + n * it} > {len(self.d)})")
        a = np.frombuffer(self.d, dtype, n, self.p).copy()
        self.p += n * it
        return a

    def end(self):
        if self.p != len(self.d):
            raise LengthError(f"{len(self.d) - self.p} trailing bytes")


@dataclass
class Event:
    kind: int
    text: str = ""
    source: str = ""
    seq: int = 0
    step: int = 0
    sim_time_ns: int = 0
    wall_ns: int = 0

    @property
    def kind_name(self) -> str:
        return EventKind.NAMES.get(self.kind, f"KIND{self.kind}")


def encode_event(ev: Event, max_text: int = DEFAULT_MAX_TEXT) -> bytes:
    w = _W()
    w.put("HH", PROTOCOL_VERSION, ev.kind)
    w.put("Q", ev.seq)
    w.put("Q", ev.step)
    w.put("q", ev.sim_time_ns)
    w.put("q", ev.wall_ns)
    w.string(ev.source, max_text)
    w.string(ev.text, max_text)
    return bytes(w.b)


def decode_event(data, max_text: int = DEFAULT_MAX_TEXT) -> Event:
    _check_header(data, ENCAP_LEN + 40)
    r = _R(data)
    _, kind = r.get("HH")
    (seq,), (step,), (sim,), (wall,) = r.get("Q"), r.get("Q"), r.get("q"), r.get("q")
    src = r.string(max_text)
    text = r.string(max_text)
    r.end()
    return Event(kind, text, src, seq, step, sim, wall)


@dataclass
class RunMeta:
    info: dict
    seq: int = 0
    step: int = 0
    sim_time_ns: int = 0
    wall_ns: int = 0


def encode_meta(m: RunMeta, max_text: int = DEFAULT_MAX_TEXT) -> bytes:
    w = _W()
    w.put("H", PROTOCOL_VERSION)
    w.put("Q", m.seq)
    w.put("Q", m.step)
    w.put("q", m.sim_time_ns)
    w.put("q", m.wall_ns)
    w.string(json.dumps(m.info, sort_keys=True, separators=(",", ":")), max_text)
    return bytes(w.b)


def decode_meta(data, max_text: int = DEFAULT_MAX_TEXT) -> RunMeta:
    _check_header(data, ENCAP_LEN + 40)
    r = _R(data)
    r.get("H")
    (seq,), (step,), (sim,), (wall,) = r.get("Q"), r.get("Q"), r.get("q"), r.get("q")
    text = r.string(max_text)
    r.end()
    try:
        info = json.loads(text)
    except json.JSONDecodeError as e:
        raise StringError(f"RunMeta json invalid: {e}") from None
    if not isinstance(info, dict):
        raise StringError("RunMeta json is not an object")
    return RunMeta(info, seq, step, sim, wall)


@dataclass
class Timing:
    step: int
    sim_time_ns: int
    period_ns: int
    overruns: int
    wake_lateness_ns: np.ndarray
    rtt_ns: np.ndarray
    tet_ns: np.ndarray
    flags: np.ndarray
    seq: int = 0


def encode_timing(t: Timing) -> bytes:
    n = len(t.rtt_ns)
    if not (len(t.wake_lateness_ns) == len(t.tet_ns) == len(t.flags) == n):
        raise LengthError("Timing arrays must have equal length")
    w = _W()
    w.put("H", PROTOCOL_VERSION)
    w.put("Q", t.seq)
    w.put("Q", t.step)
    w.put("q", t.sim_time_ns)
    w.put("q", t.period_ns)
    w.put("Q", t.overruns)
    w.array(t.wake_lateness_ns, "<i8")
    w.array(t.rtt_ns, "<i8")
    w.array(t.tet_ns, "<i8")
    w.array(t.flags, "u1")
    return bytes(w.b)


def decode_timing(data, max_batch: int = DEFAULT_MAX_BATCH) -> Timing:
    _check_header(data, ENCAP_LEN + 48)
    r = _R(data)
    r.get("H")
    (seq,), (step,), (sim,), (per,), (ovr,) = (r.get("Q"), r.get("Q"), r.get("q"), r.get("q"),
                                               r.get("Q"))
    lat = r.array("<i8", max_batch)
    rtt = r.array("<i8", max_batch)
    tet = r.array("<i8", max_batch)
    flags = r.array("u1", max_batch)
    r.end()
    if not (len(lat) == len(rtt) == len(tet) == len(flags)):
        raise LengthError("Timing arrays of unequal length")
    return Timing(step, sim, per, ovr, lat, rtt, tet, flags, seq)


def decode_any(key_or_type: str, data):
    """Decode by key expression (``ambhil/<run>/plant/sensors``) or type name."""
    t = key_or_type if key_or_type in MSG_DEFS else message_type_for_key(key_or_type)
    if t == "SensorSample":
        return decode_sensor(data)
    if t == "CurrentCommand":
        return decode_current(data)
    if t == "Event":
        return decode_event(data)
    if t == "RunMeta":
        return decode_meta(data)
    if t == "Timing":
        return decode_timing(data)
    raise ValueError(f"no message type for {key_or_type!r}")
