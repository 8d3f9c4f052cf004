#!/usr/bin/env python3
"""An ambhil controller written from docs/protocol.md and docs/controllers.md only.

Standalone: needs eclipse-zenoh (1.x) and the standard library (hashlib for the MACs), imports
nothing from the project. It joins a run over zenoh, proves that it holds the run's secret,
pairs with the plant whose RunMeta proves the same, reads the law from RunMeta's `controller`
object (protocol §5.2) and answers every authenticated SensorSample with one sealed
CurrentCommand, bit for bit like the built-in controller (protocol 3, §5.3).

    python controller.py --run-id RUN --connect tcp/127.0.0.1:7447 [tcp/127.0.0.1:7448]
                         [--key-file FILE]

The run's secret: `--key-file FILE`, else the file named by $AMBHIL_KEY_FILE (`ambhil run
--controller` sets it), else none (an unauthenticated run: the all-zero secret, loopback only
unless --insecure).

Exit codes: 0 after the plant's RUN_END (whatever its reason), 1 on a fault (plant lost, bad
RunMeta, non-finite current, timeouts), 2 on bad command-line input or an unusable key file.
"""
from __future__ import annotations

import argparse
import collections
import hashlib
import hmac
import json
import math
import os
import queue
import re
import stat
import struct
import sys
import time

# protocol §1: one rx worker thread that also owns the sockets (set before zenoh starts its runtime)
os.environ.setdefault("ZENOH_RUNTIME", "(rx: (worker_threads: 1), acc: (handover: rx), net: (handover: rx))")

import zenoh  # noqa: E402

PROG = "python_controller"
ROLE = "controller"
VERSION = 3
MAX_AXES = 64
SEQ_WINDOW = 65536
ID_LEN = MAC_LEN = NONCE_LEN = 16
KEY_LEN = 32
NO_SECRET = bytes(KEY_LEN)              # the secret of an unauthenticated run
HEADER = b"\x00\x01\x00\x00"
CANDIDATES = 64                         # pairing challenges remembered (protocol §5.3)
EVENTS_PER_S = 200                      # rate limit of the events we send (protocol §3)

# Event kinds (protocol §3)
INFO, RUN_START, RUN_END, FAULT, REJECTED, DUPLICATE, GAP, OVERRUN, PEER_LOST, TIMEOUT, WARNING, \
    FAULT_INJECTED = range(12)

RUN_ID_RE = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def say(msg: str) -> None:
    print(f"{PROG}: {msg}", file=sys.stderr, flush=True)


class ProtocolError(Exception):
    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


class Fault(Exception):
    """The controller's own fault: Event FAULT, send nothing more, exit 1."""


class KeyFileError(Exception):
    """A key file that cannot be used: one line, exit 2."""


# ---------------------------------------------------------------- keys and MACs (protocol §5.3)
# H16 / H32: keyed BLAKE2b with a 16 / 32-byte digest. Every key derives from the run's secret.

def h16(key: bytes, data: bytes) -> bytes:
    return hashlib.blake2b(data, key=key, digest_size=MAC_LEN).digest()


def h32(key: bytes, data: bytes) -> bytes:
    return hashlib.blake2b(data, key=key, digest_size=KEY_LEN).digest()


def run_key(secret: bytes, run_id: str) -> bytes:
    """K_run: the pairing proofs and every message sent before pairing."""
    return h32(secret, b"ambhil/3/run\0" + run_id.encode())


def session_key(secret, run_id, plant_id, controller_id, nonce_p, nonce_c) -> bytes:
    """K_s: every message after pairing (both ids, both nonces of the challenge)."""
    return h32(secret, b"ambhil/3/session\0" + run_id.encode() + b"\0" + plant_id + controller_id
               + nonce_p + nonce_c)


def topic_key(base: bytes, topic: str) -> bytes:
    """K_topic under K_s (or K_run): topic = the key below ambhil/<run>/, e.g. "meta"."""
    return h32(base, b"ambhil/3/topic\0" + topic.encode())


def pair_proof(k_run, role, responder_id, challenger_id, nonce_q, nonce_r) -> bytes:
    """The answer to a challenge on ambhil/<run>/pair/<role>/<responder id>."""
    return h16(k_run, b"ambhil/3/pair\0" + role.encode() + b"\0" + responder_id + challenger_id
               + nonce_q + nonce_r)


def attachment(key: bytes, me: bytes, payload: bytes) -> bytes:
    """The zenoh attachment of every message but the two loop ones: id, then its MAC."""
    return me + h16(key, payload + me)


def verify_attachment(key: bytes, payload: bytes, att, peer: bytes) -> bool:
    return (att is not None and len(att) == ID_LEN + MAC_LEN and att[:ID_LEN] == peer
            and hmac.compare_digest(h16(key, payload + peer), att[ID_LEN:]))


def read_key_file(path: str) -> bytes:
    """The secret in a key file: 64 hex digits, readable by its owner only."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise KeyFileError(f"--key-file {path}: no such file (make one with `ambhil key {path}`)") from None
    except OSError as e:
        raise KeyFileError(f"--key-file {path}: {e.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise KeyFileError(f"--key-file {path}: not a regular file")
    if st.st_mode & 0o077:
        raise KeyFileError(f"--key-file {path}: mode {stat.S_IMODE(st.st_mode):04o} lets group or "
                           f"others read it; run `chmod 600 {path}`")
    try:
        with open(path) as fh:
            text = fh.read().strip()
    except (OSError, UnicodeDecodeError) as e:
        raise KeyFileError(f"--key-file {path}: cannot read it ({e})") from None
    try:
        secret = bytes.fromhex(text)
    except ValueError:
        secret = b""
    if len(secret) != KEY_LEN:
        raise KeyFileError(f"--key-file {path}: expected {2 * KEY_LEN} hex digits (a secret of "
                           f"{KEY_LEN} bytes), found {len(text)} characters")
    if secret == NO_SECRET:
        raise KeyFileError(f"--key-file {path}: the all-zero secret is the unauthenticated one")
    return secret


def is_loopback(endpoint: str) -> bool:
    """A listen endpoint that only this host can reach (protocol §5.3, safe defaults)."""
    proto, _, addr = endpoint.partition("/")
    if proto.startswith("unixsock"):
        return True
    host = addr.rsplit(":", 1)[0].strip("[]")
    return host in ("localhost", "::1") or host.startswith("127.")


# ---------------------------------------------------------------- CDR codecs (protocol §3)

def _check_head(buf: bytes, fixed: int, what: str) -> None:
    if len(buf) < fixed:
        raise ProtocolError("truncated", f"{what} of {len(buf)} bytes, fixed part {fixed}")
    if buf[:4] != HEADER:
        raise ProtocolError("encapsulation", f"{what} header {buf[:4].hex()}")
    (version,) = struct.unpack_from("<H", buf, 4)
    if version != VERSION:
        raise ProtocolError("version", f"{what} version {version}")


def decode_sensor_sample(buf: bytes, n_axes: int, plant_id: bytes, key: bytes):
    """-> (seq, step, sim_time_ns, displacement tuple of floats). The sample ends with the
    sender's peer id and the MAC under `key` (K_s, topic plant/sensors) of every byte before it:
    an id that is not `plant_id` is rejected (`peer`), then a wrong MAC (`auth`), before the
    rest is read."""
    _check_head(buf, 52, "SensorSample")
    peer = buf[-ID_LEN - MAC_LEN:-MAC_LEN]
    if peer != plant_id:
        raise ProtocolError("peer", f"not from the paired plant {plant_id.hex()} "
                            f"(peer id {peer.hex()})")
    if not hmac.compare_digest(h16(key, buf[:-MAC_LEN]), buf[-MAC_LEN:]):
        raise ProtocolError("auth", f"SensorSample from {peer.hex()} with a wrong MAC")
    seq, step, sim_ns, _pub = struct.unpack_from("<QQqq", buf, 12)
    (count,) = struct.unpack_from("<I", buf, 44)
    if count > MAX_AXES:
        raise ProtocolError("oversize", f"SensorSample count {count} > {MAX_AXES}")
    if count == 0 or count != n_axes:
        raise ProtocolError("axes", f"SensorSample with {count} axes, run has {n_axes}")
    if len(buf) != 52 + 8 * count + ID_LEN + MAC_LEN:
        raise ProtocolError("length", f"SensorSample of {len(buf)} bytes for {count} axes")
    y = struct.unpack_from(f"<{count}d", buf, 52)
    if not all(math.isfinite(v) for v in y):
        raise ProtocolError("nonfinite", f"SensorSample seq {seq}: non-finite displacement")
    return seq, step, sim_ns, y


def encode_current_command(seq, step, sim_ns, recv_ns, pub_ns, current, peer_id, key) -> bytes:
    """The current vector, then the sender's 16-byte peer id and the MAC under `key` (K_s,
    topic controller/currents) of every byte before it (no attachment)."""
    n = len(current)
    body = (HEADER + struct.pack("<H6xQQqqqI4x", VERSION, seq, step, sim_ns, recv_ns, pub_ns, n)
            + struct.pack(f"<{n}d", *current) + peer_id)
    return body + h16(key, body)


def _pack_string(out: bytearray, s: str) -> None:
    while (len(out) - 4) % 4:          # alignment measured from the body (payload byte 4)
        out.append(0)
    raw = s.encode("utf-8") + b"\x00"
    out += struct.pack("<I", len(raw)) + raw


def _read_string(buf: bytes, off: int, what: str):
    off += (-(off - 4)) % 4
    if off + 4 > len(buf):
        raise ProtocolError("truncated", f"{what}: string length beyond the end")
    (length,) = struct.unpack_from("<I", buf, off)
    if length > 64 * 1024:
        raise ProtocolError("oversize", f"{what}: string of {length} bytes")
    start, end = off + 4, off + 4 + length
    if length == 0 or end > len(buf) or buf[end - 1] != 0:
        raise ProtocolError("string", f"{what}: missing NUL")
    try:
        return buf[start:end - 1].decode("utf-8"), end
    except UnicodeDecodeError as e:
        raise ProtocolError("string", f"{what}: bad UTF-8 ({e})") from None


def encode_event(kind, seq, step, sim_ns, wall_ns, source, text) -> bytes:
    out = bytearray(HEADER + struct.pack("<HHxxxxQQqq", VERSION, kind, seq, step, sim_ns, wall_ns))
    _pack_string(out, source)
    _pack_string(out, text)
    return bytes(out)


def decode_event(buf: bytes):
    """-> (kind, seq, step, source, text)."""
    _check_head(buf, 48, "Event")
    (kind,) = struct.unpack_from("<H", buf, 6)
    seq, step, _sim, _wall = struct.unpack_from("<QQqq", buf, 12)
    source, off = _read_string(buf, 44, "Event source")
    text, off = _read_string(buf, off, "Event text")
    if off != len(buf):
        raise ProtocolError("length", f"Event with {len(buf) - off} trailing bytes")
    return kind, seq, step, source, text


def decode_run_meta(buf: bytes) -> dict:
    _check_head(buf, 48, "RunMeta")
    text, off = _read_string(buf, 44, "RunMeta json")
    if off != len(buf):
        raise ProtocolError("length", f"RunMeta with {len(buf) - off} trailing bytes")
    try:
        meta = json.loads(text)        # Python's float parser rounds correctly
    except ValueError as e:
        raise ProtocolError("string", f"RunMeta json: {e}") from None
    if not isinstance(meta, dict):
        raise ProtocolError("string", "RunMeta json is not an object")
    return meta


# ---------------------------------------------------------------- the law (protocol §5.2)

class Law:
    """sensor-pid-amplifier, per axis, IEEE double in the documented order (pure Python floats:
    no fused multiply-add)."""

    BLOCKS = ("sensor", "integral", "derivative", "amplifier")

    def __init__(self, ctl: dict, n_axes: int, rate_hz):
        def fail(msg):
            raise Fault(f"bad RunMeta controller: {msg}")

        if not isinstance(ctl, dict):
            fail("missing `controller` object")
        if ctl.get("law") != "sensor-pid-amplifier":
            fail(f"law {ctl.get('law')!r} is not sensor-pid-amplifier; refusing to run")
        if ctl.get("n_axes") != n_axes:
            fail(f"n_axes {ctl.get('n_axes')} != RunMeta n_axes {n_axes}")
        if rate_hz is not None and ctl.get("rate_hz") != rate_hz:
            fail(f"rate_hz {ctl.get('rate_hz')} != RunMeta rate_hz {rate_hz}")

        def num(v, key):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                fail(f"`{key}` = {v!r} is not a finite number")
            return float(v)

        self.blk = {}
        for name in self.BLOCKS:
            b = ctl.get(name)
            if not isinstance(b, dict):
                fail(f"block `{name}` missing")
            self.blk[name] = tuple(num(b.get(k), f"{name}.{k}") for k in "abcd")
        self.kp = num(ctl.get("kp"), "kp")
        lim = ctl.get("input_limit")
        self.input_limit = None if lim is None else num(lim, "input_limit")
        lim = ctl.get("current_limit")
        self.current_limit = None if lim is None else num(lim, "current_limit")
        aw = ctl.get("anti_windup")
        if not isinstance(aw, bool):
            fail(f"`anti_windup` = {aw!r} is not a bool")
        self.anti_windup = aw
        d = ctl.get("delay_samples")
        if isinstance(d, bool) or not isinstance(d, int) or d < 0:
            fail(f"`delay_samples` = {d!r} is not an integer >= 0")
        self.delay = d
        i_op = ctl.get("i_op")
        if not isinstance(i_op, list) or len(i_op) != n_axes:
            fail(f"`i_op` is not a list of {n_axes} numbers")
        self.i_op = [num(v, "i_op") for v in i_op]
        self.n = n_axes
        self.reset()

    def reset(self) -> None:
        """Start state: equilibrium at zero displacement with output i_op."""
        n = self.n
        self.xs, self.xi, self.xd, self.xa = [0.0] * n, [0.0] * n, [0.0] * n, [0.0] * n
        self.ring = [[0.0] * self.delay for _ in range(n)]
        self.k = 0
        aa, ab, ac, ad = self.blk["amplifier"]
        ic = self.blk["integral"][2]
        for a in range(n):
            i0 = self.i_op[a]
            if i0 == 0.0:
                continue
            amp_dc = ad + ((ac * ab) / (1.0 - aa) if aa != 1.0 else 0.0)
            u0 = i0 / amp_dc
            self.xi[a] = u0 / ic if ic != 0.0 else 0.0
            self.xa[a] = (ab * u0) / (1.0 - aa) if ab != 0.0 else 0.0
            self.ring[a] = [i0] * self.delay

    def step(self, y) -> list:
        sa, sb, sc, sd = self.blk["sensor"]
        ia, ib, ic, id_ = self.blk["integral"]
        da, db, dc, dd = self.blk["derivative"]
        aa, ab, ac, ad = self.blk["amplifier"]
        kp, ulim, ilim, aw = self.kp, self.input_limit, self.current_limit, self.anti_windup
        out = [0.0] * self.n
        for a in range(self.n):
            ya = y[a]
            xs, xi, xd, xa = self.xs[a], self.xi[a], self.xd[a], self.xa[a]
            ys = sc * xs + sd * ya
            self.xs[a] = sa * xs + sb * ya
            e = -ys
            ui = ic * xi + id_ * e
            ud = dc * xd + dd * e
            self.xd[a] = da * xd + db * e
            u = kp * e + ui + ud
            sat = False
            if ulim is not None and u > ulim:
                us, sat = ulim, True
            elif ulim is not None and u < -ulim:
                us, sat = -ulim, True
            else:
                us = u
            i = ac * xa + ad * us
            self.xa[a] = aa * xa + ab * us
            if ilim is not None and i > ilim:
                i, sat = ilim, True
            elif ilim is not None and i < -ilim:
                i, sat = -ilim, True
            if not (sat and aw and e * u > 0):
                self.xi[a] = ia * xi + ib * e
            if self.delay:
                out[a] = self.ring[a][self.k]
                self.ring[a][self.k] = i
            else:
                out[a] = i
        if self.delay:
            self.k = (self.k + 1) % self.delay
        return out


# ---------------------------------------------------------------- the node

class Controller:
    def __init__(self, args, secret: bytes | None):
        self.args = args
        self.run = args.run_id
        self.pre = f"ambhil/{self.run}"
        self.peer_id = os.urandom(ID_LEN)
        while self.peer_id == bytes(ID_LEN):
            self.peer_id = os.urandom(ID_LEN)
        self.peer_hex = self.peer_id.hex()
        # keys (protocol §5.3): K_run until a RunMeta pairs us, then the session key K_s
        self.secret = secret if secret is not None else NO_SECRET
        self.mode = "key" if secret is not None else ("insecure" if args.insecure else "none")
        self.k_run = run_key(self.secret, self.run)
        self.k_s: bytes | None = None
        self.topic_keys: dict = {}
        self.candidates = collections.deque(maxlen=CANDIDATES)   # (challenger, nonce_q, nonce_r)
        self.q: queue.Queue = queue.Queue()
        self.status = "starting"
        self.event_seq = 0
        self.ev_window = [0.0, 0, 0]   # start of the second, events sent in it, suppressed
        self.tokens = set()            # liveliness keys present (relative to ambhil/<run>/)
        self.seen = set()              # roles ever seen present (starting/ or alive/ token)
        self.plant_id: bytes | None = None
        self.strangers: list = []      # plant ids whose RunMeta failed the proof (hex)
        self.law: Law | None = None
        self.n_axes = 0
        self.pending: list = []        # samples received before pairing (checked once paired)
        self.early_events: list = []   # events received before pairing (judged once paired)
        self.last_seq = -1             # last answered seq of the confirmed stream
        self.jump: int | None = None   # a seq that jumped ahead, not yet confirmed (§5.3)
        self.last_event_seq = -1       # last accepted event seq of the plant
        self.restart_steps: set = set()
        self.answered = self.duplicates = self.missing = self.gaps = 0
        self.rejected_by: dict = {}    # reason -> count
        self.foreign_events = 0
        self.last_sample_t = None

    @property
    def rejected(self) -> int:
        return sum(self.rejected_by.values())

    def key(self, topic: str) -> bytes:
        """The key of `topic` under K_s once paired, K_run before."""
        base = self.k_s if self.k_s is not None else self.k_run
        k = self.topic_keys.get((base, topic))
        if k is None:
            k = self.topic_keys[(base, topic)] = topic_key(base, topic)
        return k

    # --- zenoh plumbing
    def open(self):
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps(self.args.connect))
        listen = self.args.listen if self.args.listen else ["tcp/127.0.0.1:0"]
        conf.insert_json5("listen/endpoints", json.dumps(listen))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("scouting/gossip/enabled", "true")
        conf.insert_json5("transport/unicast/lowlatency", "true")
        conf.insert_json5("transport/unicast/qos/enabled", "false")
        # a pool of 4 receive batches: with zenoh's one, each message allocates and zeroes 64 KiB
        conf.insert_json5("transport/link/rx/buffer_size", str(4 * 65535))
        self.session = zenoh.open(conf)
        s, p = self.session, self.pre
        self.tok_starting = s.liveliness().declare_token(f"{p}/starting/{ROLE}")
        self.queryable = s.declare_queryable(f"{p}/status/{ROLE}", self._on_query)
        self.live_sub = s.liveliness().declare_subscriber(f"{p}/**", self._on_live, history=True)
        # the callbacks run on zenoh's receive thread ("direct", not a Python thread per
        # subscriber), so the queue holds the messages in the order the link delivered them: a
        # controller_restart event the plant publishes before sample k is seen before sample k
        # (with a thread per subscriber it could come a step late under load)
        def direct(kind):
            return zenoh.handlers.Callback(lambda smp: self._push(kind, smp), indirect=False)
        self.sub_meta = s.declare_subscriber(f"{p}/meta", direct("meta"))
        # only the plant's events concern a controller (and our own are not echoed to us)
        self.sub_events = s.declare_subscriber(f"{p}/events/plant", direct("event"))
        self.sub_sensors = s.declare_subscriber(f"{p}/plant/sensors", direct("sample"))
        opts = dict(encoding=zenoh.Encoding.APPLICATION_CDR,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.REAL_TIME, express=True,
                    reliability=zenoh.Reliability.RELIABLE)
        self.pub_currents = s.declare_publisher(f"{p}/controller/currents", **opts)
        self.pub_events = s.declare_publisher(f"{p}/events/{ROLE}", **opts)
        # the pairing queryable before the peer token: whoever sees the token can challenge us
        self.pair_q = s.declare_queryable(f"{p}/pair/{ROLE}/{self.peer_hex}", self._on_challenge)
        self.tok_peer = s.liveliness().declare_token(f"{p}/peer/{ROLE}/{self.peer_hex}")
        self.tok_alive = s.liveliness().declare_token(f"{p}/alive/{ROLE}")
        self.progress(f"ready (peer id {self.peer_hex}, auth {self.mode}); waiting for plant")

    def _push(self, kind, smp):
        att = smp.attachment
        self.q.put((kind, time.time_ns(), smp.payload.to_bytes(),
                    att.to_bytes() if att is not None else None))

    def _on_live(self, smp):
        rel = str(smp.key_expr)[len(self.pre) + 1:]
        self.q.put(("live", rel, smp.kind == zenoh.SampleKind.PUT))

    def _on_query(self, query):
        query.reply(f"{self.pre}/status/{ROLE}", f"{ROLE}: {self.status}".encode())

    def _on_challenge(self, query):
        """A challenge `challenger_id nonce_q`: answer `nonce_r proof` (a fresh nonce_r each
        time) and remember the candidate session; a RunMeta pairs with one of them."""
        raw = query.payload.to_bytes() if query.payload is not None else b""
        if len(raw) != ID_LEN + NONCE_LEN:
            return
        challenger, nonce_q = raw[:ID_LEN], raw[ID_LEN:]
        nonce_r = os.urandom(NONCE_LEN)
        self.candidates.append((challenger, nonce_q, nonce_r))    # before the reply leaves
        proof = pair_proof(self.k_run, ROLE, self.peer_id, challenger, nonce_q, nonce_r)
        query.reply(query.key_expr, nonce_r + proof)

    def event(self, kind, text, step=0, sim_ns=0, force=False):
        """Event on events/controller, id and MAC attached; at most 200 a second (the excess is
        counted in the next one's text), FAULT and restarts always."""
        w, now = self.ev_window, time.monotonic()
        if now - w[0] >= 1.0:
            w[0], w[1] = now, 0
        if w[1] >= EVENTS_PER_S and not force:
            w[2] += 1
            return
        w[1] += 1
        if w[2]:
            text, w[2] = f"{text} ({w[2]} events suppressed)", 0
        payload = encode_event(kind, self.event_seq, step, sim_ns, time.time_ns(), ROLE, text)
        self.event_seq += 1
        self.pub_events.put(payload, attachment=attachment(self.key(f"events/{ROLE}"),
                                                           self.peer_id, payload))

    def progress(self, step):
        self.status = step
        say(step)
        self.event(INFO, step, force=True)

    def close(self):
        for name in ("tok_alive", "tok_peer", "tok_starting"):
            tok = getattr(self, name, None)
            if tok is not None:
                tok.undeclare()
        try:
            self.session.close()
        except Exception:
            pass

    # --- liveliness
    def _apply_live(self, rel, put):
        parts = rel.split("/")
        if put:
            self.tokens.add(rel)
            if len(parts) == 2 and parts[0] in ("starting", "alive"):
                self.seen.add(parts[1])
        else:
            self.tokens.discard(rel)

    def plant_present(self):
        return "starting/plant" in self.tokens or "alive/plant" in self.tokens

    # --- start-up: wait for the plant, pair by its RunMeta, publisher matched
    def wait_ready(self):
        absent = 0.0
        last = time.monotonic()
        while True:
            now = time.monotonic()
            if not self.plant_present():
                if "plant" in self.seen:
                    raise Fault("plant lost (liveliness) while starting")
                absent += now - last
                if absent > self.args.start_timeout:
                    raise Fault(f"plant absent for {self.args.start_timeout:g} s; giving up")
            last = now
            if self.law is not None and self.pub_currents.matching_status.matching:
                return
            self.pump(timeout=0.05)

    def take_meta(self, raw, att):
        """Pair with the first RunMeta that proves one of our candidate sessions: its attached
        id is the challenger, its MAC verifies under that session's K_s and its `auth` nonces
        are that challenge's. Anything else is rejected (`auth`); its sender is a stranger."""
        pid = att[:ID_LEN] if att is not None and len(att) == ID_LEN + MAC_LEN else None
        if pid is None:
            self.reject("RunMeta", "auth", "no peer id and MAC attached")
            return
        if self.k_s is not None:        # RunMeta is sent once: a repeat of the paired one is
            if not verify_attachment(self.key("meta"), raw, att, self.plant_id):   # ignored
                self.reject("RunMeta", "auth", f"from {pid.hex()}, after pairing")
            return
        for challenger, nonce_q, nonce_r in reversed(self.candidates):
            k_s = session_key(self.secret, self.run, pid, self.peer_id, nonce_q, nonce_r)
            if challenger == pid and verify_attachment(topic_key(k_s, "meta"), raw, att, pid):
                break
        else:
            self.stranger(pid)
            self.reject("RunMeta", "auth", f"from {pid.hex()}: matches no challenge we answered")
            return
        try:
            meta = decode_run_meta(raw)
        except ProtocolError as e:
            raise Fault(f"bad RunMeta: {e}") from None
        auth = meta.get("auth") if isinstance(meta.get("auth"), dict) else {}
        if (auth.get("nonce_plant"), auth.get("nonce_controller")) != (nonce_q.hex(), nonce_r.hex()):
            self.reject("RunMeta", "auth", f"from {pid.hex()}: its auth nonces are not the session's")
            return
        self.k_s, self.plant_id = k_s, pid
        say(f"paired with plant {pid.hex()} (auth {auth.get('mode')}, {auth.get('mac')})")
        n = meta.get("n_axes")
        if isinstance(n, bool) or not isinstance(n, int) or not 0 < n <= MAX_AXES:
            raise Fault(f"bad RunMeta: n_axes {n!r}")
        rate = meta.get("rate_hz")
        self.n_axes = n
        self.law = Law(meta.get("controller"), n, rate)
        ctl = meta["controller"]
        say(f"RunMeta: {n} axes at {ctl['rate_hz']:g} Hz ({ctl.get('discretisation')}), "
            f"mode {meta.get('mode')}, {meta.get('n_steps')} steps, "
            f"delay {self.law.delay} samples, i_op max {max(map(abs, self.law.i_op)):.4g} A, "
            f"input limit {self.law.input_limit}, current limit {self.law.current_limit} A, "
            f"anti-windup {'on' if self.law.anti_windup else 'off'}")
        early, self.early_events = self.early_events, []
        for raw_ev, att_ev in early:
            self.on_event(raw_ev, att_ev)

    def stranger(self, pid: bytes):
        if pid.hex() not in self.strangers:
            self.strangers.append(pid.hex())
            say(f"stranger {pid.hex()} sent a RunMeta that fails the pairing proof (no key)")

    # --- messages
    def pump(self, timeout):
        try:
            item = self.q.get(timeout=timeout)
        except queue.Empty:
            return False
        self.handle(item)
        return True

    def handle(self, item):
        kind = item[0]
        if kind == "live":
            _, rel, put = item
            self._apply_live(rel, put)
            if not put and rel == "alive/plant" and self.running:
                self.plant_lost()
        elif kind == "meta":
            self.take_meta(item[2], item[3])
        elif kind == "event":
            self.on_event(item[2], item[3])
        elif kind == "sample":
            if self.law is None:        # before pairing only a stranger's can come: keep 1024
                if len(self.pending) < 1024:
                    self.pending.append(item)
            else:
                self.on_sample(item[1], item[2])

    running = False
    ended = None

    def on_event(self, raw, att):
        """An event on events/plant. Obeyed (RUN_END, FAULT_INJECTED) only when it carries the
        paired plant's id and a MAC under K_s, and its seq is beyond the last accepted one."""
        if self.plant_id is None:
            if len(self.early_events) < 1024:
                self.early_events.append((raw, att))
            return
        if verify_attachment(self.key("events/plant"), raw, att, self.plant_id):
            session = True
        elif verify_attachment(topic_key(self.k_run, "events/plant"), raw, att, self.plant_id):
            session = False             # sent before pairing (start-up): never obeyed
        else:
            who = att[:ID_LEN].hex() if att is not None and len(att) == ID_LEN + MAC_LEN else "?"
            return self.reject_event("auth", f"from {who}: not the paired plant's, or a wrong MAC")
        try:
            kind, seq, step, source, text = decode_event(raw)
        except ProtocolError as e:
            return self.reject_event(e.reason, str(e).split(": ", 1)[1])
        if source not in ("plant", "replay"):
            return self.reject_event("auth", f"source {source!r} on events/plant")
        if not session:
            return
        if seq <= self.last_event_seq:
            return self.reject_event("sequence", f"seq {seq}, last {self.last_event_seq}")
        self.last_event_seq = seq
        if kind == RUN_END:
            self.ended = text
        elif kind == FAULT_INJECTED and source == "plant":
            try:
                info = json.loads(text)
            except ValueError:
                return
            if info.get("kind") == "controller_restart" and info.get("phase") == "start":
                self.restart_steps.add(step)

    def reject_event(self, reason, detail):
        self.foreign_events += 1
        self.reject("event", reason, detail)

    def plant_lost(self):
        """alive/plant went away: a RUN_END still in flight gets 20 ms, then Event FAULT."""
        t_end = time.monotonic() + 0.02
        while self.ended is None and time.monotonic() < t_end:
            try:
                item = self.q.get(timeout=max(t_end - time.monotonic(), 0.0))
            except queue.Empty:
                break
            if item[0] == "event":
                self.on_event(item[2], item[3])
        if self.ended is None:
            raise Fault(f"plant lost (liveliness) without RUN_END after {self.answered} samples")

    def reject(self, what, reason, detail, step=0, sim_ns=0):
        """Event REJECTED, text `<what> rejected: <reason>: <detail>` (as the reference)."""
        self.rejected_by[reason] = self.rejected_by.get(reason, 0) + 1
        self.event(REJECTED, f"{what} rejected: {reason}: {detail}", step, sim_ns)

    def on_sample(self, recv_ns, raw):
        try:
            seq, step, sim_ns, y = decode_sensor_sample(raw, self.n_axes, self.plant_id,
                                                        self.key("plant/sensors"))
        except ProtocolError as e:
            self.reject("sensor sample", e.reason, str(e).split(": ", 1)[1])
            return
        # protocol §5.3: a jump ahead is answered, but it moves `last` only once the next
        # sample confirms it, so one message cannot make the genuine stream stale
        last, jump = self.last_seq, self.jump
        if seq == last + 1 or (jump is not None and seq == jump + 1):
            self.last_seq, self.jump = seq, None
        elif seq <= last or seq == jump:
            self.duplicates += 1
            self.event(DUPLICATE, f"duplicate/stale sample seq {seq} (last {last}) ignored",
                       step, sim_ns)
            return
        elif seq > last + SEQ_WINDOW:
            self.reject("sensor sample", "sequence",
                        f"seq {seq} is more than {SEQ_WINDOW} ahead of the last ({last})", step, sim_ns)
            return
        else:
            self.jump = seq
            self.gaps += 1
            self.missing += seq - last - 1
            self.event(GAP, f"samples {last + 1}..{seq - 1} missing", step, sim_ns)
        due = [s for s in self.restart_steps if s <= step]
        if due:                         # reset before the first sample at or after that step
            self.restart_steps.difference_update(due)
            self.law.reset()
            self.event(INFO, f"controller restarted (state reset) before step {step}", step, sim_ns,
                       force=True)
        current = self.law.step(y)
        if not all(math.isfinite(v) for v in current):
            raise Fault(f"non-finite current at seq {seq}, step {step}")
        self.pub_currents.put(encode_current_command(seq, step, sim_ns, recv_ns, time.time_ns(),
                                                     current, self.peer_id,
                                                     self.key("controller/currents")))
        self.answered += 1
        self.last_sample_t = time.monotonic()

    def serve(self):
        self.running = True
        self.status = "running"
        for item in self.pending:
            self.on_sample(item[1], item[2])
        self.pending = []
        self.last_sample_t = time.monotonic()
        while self.ended is None:
            if not self.pump(timeout=1.0):
                if "alive/plant" not in self.tokens:
                    self.plant_lost()
                if time.monotonic() - self.last_sample_t > self.args.sample_timeout:
                    raise Fault(f"no sample for {self.args.sample_timeout:g} s from a live plant")
        say(f"{self.answered} samples answered, {self.duplicates} duplicates, {self.missing} "
            f"missing, {self.rejected} rejected; plant ended: {self.ended}")

    def report(self):
        """The authentication part of the summary (also after a fault)."""
        say(f"auth {self.mode}; rejected {json.dumps(self.rejected_by, sort_keys=True)}, "
            f"foreign events {self.foreign_events}, strangers {self.strangers}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    ap.add_argument("--run-id", required=True)
    ap.add_argument("--connect", nargs="+", action="extend", default=[],
                    help="endpoints to connect to (the plant, the recorder)")
    ap.add_argument("--listen", nargs="+", action="extend", default=[],
                    help="endpoints to listen on (default tcp/127.0.0.1:0)")
    ap.add_argument("--key-file", default=os.environ.get("AMBHIL_KEY_FILE") or None,
                    help="the run's secret (64 hex digits, mode 0600; default $AMBHIL_KEY_FILE)")
    ap.add_argument("--insecure", action="store_true",
                    help="allow an unauthenticated run to listen beyond loopback")
    ap.add_argument("--start-timeout", type=float, default=30.0)
    ap.add_argument("--sample-timeout", type=float, default=300.0)
    args = ap.parse_args(argv)
    # `{connect}` may expand to several endpoints in one argument
    args.connect = [e for c in args.connect for e in c.replace(",", " ").split()]
    if not RUN_ID_RE.fullmatch(args.run_id):
        print(f"{PROG}: error: --run-id {args.run_id!r} must match [A-Za-z0-9_.-]{{1,64}}",
              file=sys.stderr)
        return 2
    if not args.connect:
        print(f"{PROG}: error: --connect: give the plant's endpoint", file=sys.stderr)
        return 2
    try:
        secret = read_key_file(args.key_file) if args.key_file else None
    except KeyFileError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    for ep in args.listen:
        if secret is None and not args.insecure and not is_loopback(ep):
            print(f"{PROG}: error: --listen {ep} is not loopback: give --key-file FILE (ambhil key "
                  f"FILE), or --insecure to run unauthenticated", file=sys.stderr)
            return 2
    ctl = Controller(args, secret)
    try:
        ctl.open()
        ctl.wait_ready()
        ctl.serve()
        return 0
    except Fault as e:
        say(f"FAULT: {e}")
        try:
            ctl.event(FAULT, str(e), force=True)
        except Exception:
            pass
        return 1
    except KeyboardInterrupt:
        return 130
    finally:
        ctl.report()
        ctl.close()


if __name__ == "__main__":
    sys.exit(main())
