"""The ambhil wire, protocol 3, as an outsider writes it from docs/protocol.md and the design of
issue 31 (no ``ambhil`` import: only ``struct`` and ``hashlib``).

What a stranger on the run's links can do with it: read every message, copy the peer ids
(tokens ``ambhil/<run>/peer/<role>/<id hex>``, the ``peer`` field, attachments), re-put captured
bytes, and build well-formed messages with any id.  What it cannot do without the run secret:
compute a MAC (``mac_for``), unless the run is unauthenticated (the all-zero secret, which
anyone can use, ``NO_SECRET``).

Layouts (CDR little-endian, alignment measured from byte 4, offsets absolute):
- SensorSample: version@4 seq@12 step@20 sim@28 publish_wall@36 count@44 data@52,
  then peer[16], mac[16]: 84 + 8n bytes.
- CurrentCommand: seq@12 step@20 sim@28 recv_wall@36 publish_wall@44 count@52 data@60,
  then peer[16], mac[16]: 92 + 8n bytes.
- Event: version@4 kind@6 seq@12 step@20 sim@28 wall@36 string source@44, string text;
  attachment peer[16] mac[16].
- RunMeta: seq@12 step@20 sim@28 wall@36 string json@44.
- RecordBatch: seq, step, sim, int64[] log_time_ns, uint8[] topics, uint32[] sizes, uint8[] data.
"""
from __future__ import annotations

import hashlib
import json
import struct

VERSION = 3
HEADER = b"\x00\x01\x00\x00"
NO_SECRET = bytes(32)
INFO, RUN_START, RUN_END, FAULT, REJECTED = 0, 1, 2, 3, 4
WARNING, FAULT_INJECTED = 10, 11


# ---- MACs (keyed BLAKE2b) ------------------------------------------------------------------
def h16(key: bytes, data: bytes) -> bytes:
    return hashlib.blake2b(data, key=key, digest_size=16).digest()


def h32(key: bytes, data: bytes) -> bytes:
    return hashlib.blake2b(data, key=key, digest_size=32).digest()


def session_key(secret: bytes, run: str, plant_id: bytes, controller_id: bytes,
                nonce_p: bytes, nonce_c: bytes) -> bytes:
    return h32(secret, b"ambhil/3/session\0" + run.encode() + b"\0" + plant_id + controller_id
               + nonce_p + nonce_c)


def topic_key(base: bytes, topic: str) -> bytes:
    return h32(base, b"ambhil/3/topic\0" + topic.encode())


def session_from_meta(meta_json: dict, run: str, secret: bytes = NO_SECRET) -> bytes | None:
    """The session key of a run from its RunMeta: computable by anyone only when the secret is
    the public all-zero one (an unauthenticated run)."""
    a = meta_json.get("auth") or {}
    try:
        return session_key(secret, run, bytes.fromhex(meta_json["plant_peer_id"]),
                           bytes.fromhex(meta_json["controller_peer_id"]),
                           bytes.fromhex(a["nonce_plant"]), bytes.fromhex(a["nonce_controller"]))
    except (KeyError, ValueError):
        return None


# ---- CDR ------------------------------------------------------------------------------------
class Writer:
    def __init__(self):
        self.b = bytearray(HEADER)

    def align(self, n):
        while (len(self.b) - 4) % n:
            self.b.append(0)

    def put(self, fmt, *v):
        self.align(struct.calcsize(fmt))
        self.b += struct.pack("<" + fmt, *v)

    def string(self, s: str):
        data = s.encode() + b"\0"
        self.put("I", len(data))
        self.b += data


class Reader:
    def __init__(self, data: bytes):
        self.d, self.p = bytes(data), 4

    def align(self, n):
        self.p += (-(self.p - 4)) % n

    def get(self, fmt):
        self.align(struct.calcsize(fmt))
        v = struct.unpack_from("<" + fmt, self.d, self.p)
        self.p += struct.calcsize(fmt)
        return v[0] if len(v) == 1 else v

    def seq(self, code):
        n = self.get("I")
        if n == 0:
            return ()
        size = struct.calcsize(code)
        self.align(size)
        v = struct.unpack_from(f"<{n}{code}", self.d, self.p)
        self.p += n * size
        return v

    def blob(self):
        n = self.get("I")
        v = self.d[self.p:self.p + n]
        self.p += n
        return v

    def string(self):
        return self.blob()[:-1].decode()


# ---- loop messages --------------------------------------------------------------------------
def sample(seq, step, sim_ns, wall_ns, disp, peer: bytes, mac: bytes = b"") -> bytes:
    """A SensorSample; ``mac`` given (16 bytes) or the one of ``key`` via :func:`seal`."""
    body = (HEADER + struct.pack("<H6xQQqqI4x", VERSION, seq, step, sim_ns, wall_ns, len(disp))
            + struct.pack(f"<{len(disp)}d", *disp) + peer)
    return body + (mac or bytes(16))


def current(seq, step, sim_ns, recv_ns, pub_ns, amps, peer: bytes, mac: bytes = b"") -> bytes:
    body = (HEADER + struct.pack("<H6xQQqqqI4x", VERSION, seq, step, sim_ns, recv_ns, pub_ns,
                                 len(amps)) + struct.pack(f"<{len(amps)}d", *amps) + peer)
    return body + (mac or bytes(16))


def seal(msg: bytes, key: bytes) -> bytes:
    """``msg`` with its last 16 bytes replaced by the MAC under topic key ``key``."""
    return msg[:-16] + h16(key, msg[:-16])


def loop_header(data: bytes) -> dict:
    """seq, step, sim_time_ns and n of a SensorSample or CurrentCommand (either layout: the
    count sits at 44 in a sample, 52 in a current; told apart by the total length)."""
    seq, step, sim = struct.unpack_from("<QQq", data, 12)
    n = struct.unpack_from("<I", data, 44)[0]
    if len(data) == 84 + 8 * n:
        return {"seq": seq, "step": step, "sim": sim, "n": n, "kind": "sample",
                "v": struct.unpack_from(f"<{n}d", data, 52), "peer": data[-32:-16]}
    n = struct.unpack_from("<I", data, 52)[0]
    return {"seq": seq, "step": step, "sim": sim, "n": n, "kind": "current",
            "v": struct.unpack_from(f"<{n}d", data, 60), "peer": data[-32:-16]}


def patch_seq(data: bytes, seq: int, step: int, sim_ns: int) -> bytes:
    """A captured loop message with another seq/step/sim_time (its MAC no longer fits)."""
    return data[:12] + struct.pack("<QQq", seq, step, sim_ns) + data[36:]


# ---- other messages -------------------------------------------------------------------------
def event(kind, seq, step, sim_ns, wall_ns, source: str, text: str) -> bytes:
    w = Writer()
    w.put("H", VERSION)
    w.put("H", kind)
    w.put("Q", seq)
    w.put("Q", step)
    w.put("q", sim_ns)
    w.put("q", wall_ns)
    w.string(source)
    w.string(text)
    return bytes(w.b)


def attachment(peer: bytes, key: bytes | None, payload: bytes, mac: bytes = b"") -> bytes:
    """``peer || mac``, mac = H16(topic key, payload || peer) when ``key`` is known."""
    return peer + (h16(key, payload + peer) if key is not None else (mac or bytes(16)))


def read_meta(data: bytes) -> dict:
    r = Reader(data)
    r.p = 44
    return json.loads(r.string())


def read_record_batch(data: bytes) -> list:
    """[(topic 0 sensors | 1 currents, payload)] of a RecordBatch."""
    r = Reader(data)
    r.p = 36
    r.seq("q")
    topics, sizes = r.seq("B"), r.seq("I")
    n = r.get("I")
    blob = r.d[r.p:r.p + n]
    out, at = [], 0
    for t, s in zip(topics, sizes):
        out.append((t, blob[at:at + s]))
        at += s
    return out
