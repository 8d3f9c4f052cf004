"""Generic CDR (XCDR1, little endian) writer and reader, and the codecs of the variable-length
messages built on them: Event, RunMeta, Timing (docs/protocol.md, section 3)."""
from __future__ import annotations

import json
import struct

import numpy as np

from ambhil.bridge.protocol.messages import (DEFAULT_MAX_BATCH, DEFAULT_MAX_TEXT, ENCAP, ENCAP_LEN, PROTOCOL_VERSION,
                       Event, RunMeta, Timing)
from ambhil.bridge.protocol.errors import LengthError, OversizeError, StringError, TruncatedError, check_header


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
    check_header(data, ENCAP_LEN + 40)
    r = _R(data)
    _, kind = r.get("HH")
    (seq,), (step,), (sim,), (wall,) = r.get("Q"), r.get("Q"), r.get("q"), r.get("q")
    src = r.string(max_text)
    text = r.string(max_text)
    r.end()
    return Event(kind, text, src, seq, step, sim, wall)


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
    check_header(data, ENCAP_LEN + 40)
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
    check_header(data, ENCAP_LEN + 48)
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
