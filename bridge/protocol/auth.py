"""Message authentication of a run (docs/protocol.md, section 5.3).

Every message of a run carries a MAC: keyed BLAKE2b (RFC 7693) with a 16-byte digest, under a
key derived from the run's 32-byte secret, the run id, the pairing (both peer ids and both
nonces of the challenge-response) and the message's topic (its key expression below
``ambhil/<run>/``, which names the direction and the sending role).  The sequence number and
everything else of the message are inside the MAC'd bytes.

- ``secret``: 32 random bytes per run, in a key file (64 hex digits, mode 0600,
  :func:`write_key_file` / ``ambhil key``); ``ambhil run`` makes one per run.  Without a key a
  run is *unauthenticated*: the same MACs are computed with the all-zero secret
  (:data:`NO_SECRET`), so anyone can compute them; the run says so.
- ``K_run = H32(secret, "ambhil/3/run" 0 run_id)``: before pairing (start-up Events) and for the
  pairing proofs.
- ``K_s = H32(secret, "ambhil/3/session" 0 run_id 0 plant_id controller_id nonce_p nonce_c)``:
  every message after pairing.
- ``K_topic = H32(K, "ambhil/3/topic" 0 topic)`` with K = K_s (or K_run before pairing).
- SensorSample / CurrentCommand end with ``peer[16] mac[16]``,
  ``mac = H16(K_topic, every byte before the mac)``.
- Every other message carries the zenoh attachment ``peer[16] mac[16]``,
  ``mac = H16(K_topic, payload peer)``.
- Pairing proof (reply to a challenge on ``ambhil/<run>/pair/<role>/<id>``):
  ``H16(K_run, "ambhil/3/pair" 0 role 0 responder_id challenger_id nonce_q nonce_r)``.

``H32(k, m)`` / ``H16(k, m)``: BLAKE2b with key k, digest size 32 / 16, over m (Python:
``hashlib.blake2b(m, key=k, digest_size=n)``).  The fast path has its own C implementation
(bridge/protocol/_blake2b.h), checked against hashlib (tests/test_mac.py).
"""
from __future__ import annotations

import hashlib
import hmac
import os
import stat

KEY_LEN = 32          # bytes of the run secret and of every derived key
MAC_LEN = 16          # bytes of a MAC
NONCE_LEN = 16        # bytes of a pairing nonce
ID_LEN = 16           # bytes of a peer id
SEAL_LEN = ID_LEN + KEY_LEN   # a codec's seal: the peer id and the topic key (wire.py, _wire.c)
ATTACH_LEN = ID_LEN + MAC_LEN
NO_SECRET = bytes(KEY_LEN)    # the secret of an unauthenticated run
MAC_NAME = "blake2b-128"      # named in RunMeta auth.mac

MODES = ("key", "none", "insecure")
# rejection reasons of a loop message that no sender of this run sealed (checked before the
# MAC, or the MAC itself): kept out of the run's channels (foreign/), never recorded as received
UNSEALED = ("truncated", "encapsulation", "version", "peer", "auth")   # key file / none on loopback / --insecure off loopback


class AuthError(ValueError):
    """A key file that cannot be used (one line naming the file and what is wrong)."""


def mac(key: bytes, data) -> bytes:
    """``H16(key, data)``: keyed BLAKE2b, 16-byte digest."""
    return hashlib.blake2b(bytes(data), key=key, digest_size=MAC_LEN).digest()


def derive(key: bytes, label: bytes) -> bytes:
    """``H32(key, label)``: a 32-byte key derived from ``key``."""
    return hashlib.blake2b(label, key=key, digest_size=KEY_LEN).digest()


def run_key(secret: bytes, run_id: str) -> bytes:
    return derive(secret, b"ambhil/3/run\0" + run_id.encode())


def session_key(secret: bytes, run_id: str, plant_id: bytes, controller_id: bytes,
                nonce_p: bytes, nonce_c: bytes) -> bytes:
    for what, v, n in (("plant_id", plant_id, ID_LEN), ("controller_id", controller_id, ID_LEN),
                       ("nonce_p", nonce_p, NONCE_LEN), ("nonce_c", nonce_c, NONCE_LEN)):
        if len(v) != n:
            raise ValueError(f"session_key: {what} is {len(v)} bytes, expected {n}")
    return derive(secret, b"ambhil/3/session\0" + run_id.encode() + b"\0" + plant_id
                  + controller_id + nonce_p + nonce_c)


def topic_key(base: bytes, topic: str) -> bytes:
    return derive(base, b"ambhil/3/topic\0" + topic.encode())


def pair_proof(k_run: bytes, role: str, responder_id: bytes, challenger_id: bytes,
               nonce_q: bytes, nonce_r: bytes) -> bytes:
    return mac(k_run, b"ambhil/3/pair\0" + role.encode() + b"\0" + responder_id + challenger_id
               + nonce_q + nonce_r)


def nonce() -> bytes:
    return os.urandom(NONCE_LEN)


def equal(a, b) -> bool:
    return hmac.compare_digest(bytes(a), bytes(b))


# ---- key files ---------------------------------------------------------------------------

def new_secret() -> bytes:
    return os.urandom(KEY_LEN)


def write_key_file(path: str, secret: bytes | None = None, force: bool = False) -> bytes:
    """Write a new secret (or ``secret``) to ``path`` as 64 hex digits, mode 0600, created with
    that mode (never readable by others, not even briefly).  Refuses to replace a file unless
    ``force``.  Returns the secret."""
    secret = new_secret() if secret is None else secret
    if len(secret) != KEY_LEN:
        raise AuthError(f"a run secret is {KEY_LEN} bytes, got {len(secret)}")
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if force else os.O_EXCL)
    try:
        fd = os.open(path, flags, 0o600)
    except FileExistsError:
        raise AuthError(f"key file {path} exists: use --force to replace it") from None
    except OSError as e:
        raise AuthError(f"key file {path}: {e.strerror}") from None
    with os.fdopen(fd, "w") as fh:
        os.fchmod(fh.fileno(), 0o600)
        fh.write(secret.hex() + "\n")
    return secret


def read_key_file(path: str) -> bytes:
    """The secret in key file ``path``; :class:`AuthError` (one line) if it is missing, readable
    or writable by group or others, or not 64 hex digits."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise AuthError(f"--key-file {path}: no such file (make one with `ambhil key {path}`)") from None
    except OSError as e:
        raise AuthError(f"--key-file {path}: {e.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise AuthError(f"--key-file {path}: not a regular file")
    if st.st_mode & 0o077:
        raise AuthError(f"--key-file {path}: mode {stat.S_IMODE(st.st_mode):04o} lets group or "
                        f"others read it; run `chmod 600 {path}`")
    try:
        with open(path) as fh:
            text = fh.read().strip()
    except (OSError, UnicodeDecodeError) as e:
        raise AuthError(f"--key-file {path}: cannot read it ({e})") from None
    try:
        secret = bytes.fromhex(text)
    except ValueError:
        secret = b""
    if len(secret) != KEY_LEN:
        raise AuthError(f"--key-file {path}: expected {2 * KEY_LEN} hex digits (a secret of "
                        f"{KEY_LEN} bytes), found {len(text)} characters")
    if secret == NO_SECRET:
        raise AuthError(f"--key-file {path}: the all-zero secret is the unauthenticated one")
    return secret


# ---- one process's view of a run ---------------------------------------------------------

class RunAuth:
    """The keys of one process (``role``, peer id ``me``) in run ``run_id``.

    Before :meth:`pair` every key derives from ``K_run``; after it from the session key.
    ``seal(topic)`` / ``peer_seal(id, topic)`` are the 48-byte seals of the loop codecs
    (bridge/protocol/wire.py); ``attach`` / ``check`` the attachment of every other message."""

    def __init__(self, secret: bytes | None, run_id: str, role: str, me: bytes,
                 mode: str | None = None):
        if len(me) != ID_LEN:
            raise ValueError(f"RunAuth: a peer id is {ID_LEN} bytes, got {len(me)}")
        self.keyed = secret is not None
        self.secret = secret if secret is not None else NO_SECRET
        self.mode = mode or ("key" if self.keyed else "none")
        if self.mode not in MODES:
            raise ValueError(f"RunAuth: mode {self.mode!r}, expected one of {MODES}")
        self.run_id, self.role, self.me = run_id, role, bytes(me)
        self.k_run = run_key(self.secret, run_id)
        self.k_session: bytes | None = None
        self.pairing: dict | None = None     # plant_id, controller_id, nonce_p, nonce_c
        self._cache: dict = {}

    # keys
    def pair(self, plant_id: bytes, controller_id: bytes, nonce_p: bytes, nonce_c: bytes) -> bytes:
        """Derive the session key of this pairing; every key from now on derives from it."""
        self.k_session = session_key(self.secret, self.run_id, plant_id, controller_id,
                                     nonce_p, nonce_c)
        self.pairing = {"plant_id": bytes(plant_id), "controller_id": bytes(controller_id),
                        "nonce_p": bytes(nonce_p), "nonce_c": bytes(nonce_c)}
        return self.k_session

    @property
    def paired(self) -> bool:
        return self.k_session is not None

    def key(self, topic: str, session: bool | None = None) -> bytes:
        """The topic key under the session key (or, before pairing / ``session=False``, K_run)."""
        use_s = self.k_session is not None if session is None else session
        base = self.k_session if use_s else self.k_run
        if base is None:
            raise ValueError("RunAuth.key: not paired")
        k = self._cache.get((base, topic))
        if k is None:
            k = self._cache[(base, topic)] = topic_key(base, topic)
        return k

    def seal(self, topic: str) -> bytes:
        """This process's seal for the loop messages it sends on ``topic``."""
        return self.me + self.key(topic)

    def peer_seal(self, peer_id: bytes, topic: str) -> bytes:
        """The seal a loop message from ``peer_id`` on ``topic`` must carry."""
        return bytes(peer_id) + self.key(topic)

    # attachments (Event, RunMeta, Timing, RecordBatch, foreign copies)
    def attach(self, topic: str, payload) -> bytes:
        return self.me + mac(self.key(topic), bytes(payload) + self.me)

    def check(self, topic: str, payload, attachment, peer: bytes | None = None) -> str:
        """How ``payload`` with ``attachment`` on ``topic`` authenticates: ``"session"`` (under
        the session key), ``"run"`` (under K_run: sent before pairing, replayable, never to be
        obeyed) or ``""`` (it does not: reject, reason ``auth``).  With ``peer``, the attached
        id must be it (else ``""`` too)."""
        if attachment is None:
            return ""
        att = bytes(attachment)
        if len(att) != ATTACH_LEN:
            return ""
        pid, tag = att[:ID_LEN], att[ID_LEN:]
        if peer is not None and pid != peer:
            return ""
        data = bytes(payload) + pid
        if self.k_session is not None and equal(mac(self.key(topic, True), data), tag):
            return "session"
        if equal(mac(self.key(topic, False), data), tag):
            return "run"
        return ""

    # pairing proofs
    def proof(self, challenger_id: bytes, nonce_q: bytes, nonce_r: bytes) -> bytes:
        """This process's answer to a challenge (docs/protocol.md 5.3)."""
        return pair_proof(self.k_run, self.role, self.me, challenger_id, nonce_q, nonce_r)

    def check_proof(self, role: str, responder_id: bytes, nonce_q: bytes, nonce_r: bytes,
                    tag: bytes) -> bool:
        return equal(pair_proof(self.k_run, role, responder_id, self.me, nonce_q, nonce_r), tag)

    def describe(self) -> dict:
        """RunMeta ``auth``: how this run authenticates (nonces once paired)."""
        out = {"mode": self.mode, "mac": MAC_NAME}
        if self.pairing is not None:
            out["nonce_plant"] = self.pairing["nonce_p"].hex()
            out["nonce_controller"] = self.pairing["nonce_c"].hex()
        return out
