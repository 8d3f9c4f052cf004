"""Zenoh session factory and pub/sub/liveliness helpers (shared/reference/tooling.md §1.1, §1.6).

Import this module before anything else imports ``zenoh``: it sets ``ZENOH_RUNTIME`` to
:data:`RUNTIME` (unless already set), which only takes effect if done before the first
``import zenoh`` in the process: one receive worker thread, and zenoh's acceptor and network
runtimes handed over to it, so a link's socket is registered with the reactor of the thread that
reads it.  Without the hand-over every message woke the ``acc`` (listening side) or ``net``
(connecting side) thread first, which then woke the ``rx`` thread: one more context switch per
message in each process, 11-18 % of the same-host round trip (docs/performance.md).

Every session's receive buffer pool holds :func:`rx_buffers` batches (4)
(``transport/link/rx/buffer_size``; zenoh's default holds one).  A received sample keeps the
buffer it was read into until the application drops it, and the receive thread takes the buffer
for the next message as soon as it has handed one over, so with one buffer every message made
zenoh allocate and zero a fresh 64 KiB batch buffer (glibc ``memset`` on the ``rx`` thread: 4 us
of the full rung's step, and 64 KiB of cache written over each message; docs/performance.md).

Topology: the plant *listens* on the run endpoint (``tcp/127.0.0.1:<port>``, or its host's
address across a network); controller, recorder and replay tools *connect* to it.  Every
session without a listen endpoint of its own listens on an ephemeral port of each local address
its tcp connect endpoints are reached from (loopback for a loopback endpoint, the interface
towards the plant across a network: :func:`ephemeral_endpoints`), and gossip scouting (never
multicast) is on, so peers that only know the plant still reach each other directly (zenoh
peers do not forward data for others; a loopback-only listener is unreachable from another
host, and the recorder would then miss the controller's traffic).  Nothing binds beyond
127.0.0.1 unless an endpoint says so.
"""
from __future__ import annotations

import json
import os
import socket
import threading
import time
from typing import Callable, Iterable

RUNTIME = "(rx: (worker_threads: 1), acc: (handover: rx), net: (handover: rx))"
os.environ.setdefault("ZENOH_RUNTIME", RUNTIME)
import zenoh  # noqa: E402

EPHEMERAL = "tcp/127.0.0.1:0"
SECURE: dict | None = None   # config entries every session gets (bridge.process.security.configure)


class TransportError(RuntimeError):
    pass


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's range for automatically chosen local ports (Linux: ip_local_port_range)."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            lo, hi = (int(v) for v in f.read().split())
        return lo, hi
    except (OSError, ValueError):
        return 32768, 60999          # Linux's default; other systems use 49152-65535


def free_port(host: str = "127.0.0.1") -> int:
    """A currently free TCP port on ``host``, chosen *below* the kernel's ephemeral range.

    A port the kernel handed out for ``bind(0)`` lies inside that range, where every outgoing
    connection and every zenoh ephemeral listener also takes its port: between choosing the
    port and the plant binding it, another socket could take it, and a peer that connects to
    it before the plant listens can be given that very port as its source port and connect to
    itself (TCP simultaneous open), so the plant then cannot bind.  Below the range neither
    happens; only another program binding the same port explicitly still races.  A port once
    handed out is never handed out again by this process: two calls in a row (the plant's and
    the recorder's endpoint) cannot both get a port that neither has bound yet."""
    import random
    lo, _ = _ephemeral_range()
    top = min(lo, 32768)
    rng = random.Random()
    for _ in range(200 if top > 2048 else 0):   # no room below the range: let the kernel choose
        port = rng.randrange(20000, top) if top > 20000 else rng.randrange(1024, top)
        if port in _HANDED_OUT:
            continue
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
        _HANDED_OUT.add(port)
        return port
    while True:                      # everything below the range taken: let the kernel choose
        with socket.socket() as s:
            s.bind((host, 0))
            port = s.getsockname()[1]
        if port not in _HANDED_OUT:
            _HANDED_OUT.add(port)
            return port


_HANDED_OUT: set[int] = set()   # ports free_port() returned in this process


def tcp_endpoint(port: int, host: str = "127.0.0.1") -> str:
    return f"tcp/{host}:{port}"


UNIX_PATH_MAX = 107          # sun_path holds 108 bytes with the NUL


def socket_dir() -> str:
    """Folder for the run's Unix-domain sockets: ``$XDG_RUNTIME_DIR/ambhil`` if set, else
    ``<tmp>/ambhil-<uid>`` (mode 0700: other users can neither connect nor squat the names)."""
    import tempfile
    base = os.environ.get("XDG_RUNTIME_DIR")
    d = os.path.join(base, "ambhil") if base and os.path.isdir(base) else \
        os.path.join(tempfile.gettempdir(), f"ambhil-{os.getuid()}")
    os.makedirs(d, mode=0o700, exist_ok=True)
    return d


def unix_endpoint(name: str, folder: str | None = None) -> str:
    """A zenoh Unix-domain stream socket endpoint ``unixsock-stream/<folder>/<name>.sock``.
    Raises :class:`TransportError` when the path is too long for a socket address."""
    path = os.path.join(folder or socket_dir(), f"{name}.sock")
    if len(path.encode()) > UNIX_PATH_MAX:
        raise TransportError(f"Unix socket path too long ({len(path.encode())} > {UNIX_PATH_MAX} "
                             f"bytes): {path}")
    return f"unixsock-stream/{path}"


def endpoint_path(endpoint: str) -> str | None:
    """The socket file of a ``unixsock-stream/...`` endpoint, else None."""
    return endpoint.split("/", 1)[1] if endpoint.startswith("unixsock-stream/") else None


def remove_socket_files(*endpoints: str) -> None:
    """Remove the socket (and zenoh's ``.lock``) files of Unix endpoints left after a run."""
    for ep in endpoints:
        path = endpoint_path(ep)
        for f in ((path, path + ".lock") if path else ()):
            try:
                os.unlink(f)
            except OSError:
                pass


def remove_stale_sockets(folder: str | None = None) -> list[str]:
    """Remove the socket files (and their ``.lock``) that an ``ambhil run`` killed before it
    could clean up left in ``folder`` (default :func:`socket_dir`): files named
    ``<run>-<pid>-plant|rec.sock[.lock]`` whose ``pid`` no longer runs and on whose socket
    nobody listens; likewise its per-run key file ``<run>-<pid>.key`` (bridge/cli/keyfile.py).
    A live run's files are never touched.  Returns the removed paths."""
    import re
    folder = folder or socket_dir()
    pat = re.compile(r"-(\d+)(?:-(?:plant|rec)\.sock(?:\.lock)?|\.key)$")
    removed = []
    try:
        names = sorted(os.listdir(folder))
    except OSError:
        return removed
    dead: dict[int, bool] = {}
    for name in names:
        m = pat.search(name)
        if not m:
            continue
        pid = int(m.group(1))
        if pid not in dead:
            try:
                os.kill(pid, 0)
                dead[pid] = False
            except ProcessLookupError:
                dead[pid] = True
            except OSError:             # exists, another user's: alive
                dead[pid] = False
        if not dead[pid]:
            continue
        path = os.path.join(folder, name)
        sock = path.removesuffix(".lock")
        if os.path.exists(sock):        # somebody listens on it (a pid reused?): keep both files
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sk:
                try:
                    sk.connect(sock)
                    continue
                except OSError:
                    pass
        try:
            os.unlink(path)
            removed.append(path)
        except OSError:
            pass
    return removed


def _host_port(endpoint: str) -> tuple[str, str, int] | None:
    """``tcp/10.0.0.1:7447`` -> ("tcp", "10.0.0.1", 7447); ``tcp/[::1]:7447`` -> ("tcp", "::1",
    7447); None for anything else (unix sockets, no port)."""
    proto, sep, rest = endpoint.partition("/")
    if not sep:
        return None
    addr = rest.split("?", 1)[0].split("#", 1)[0]
    host, sep, port = addr.rpartition(":")
    if not sep or not port.isdigit() or not host:
        return None
    return proto, host.strip("[]"), int(port)


def is_loopback(endpoint: str) -> bool:
    """Whether ``endpoint`` only reaches this host: a Unix-domain socket, or an IP endpoint on
    127.0.0.0/8, ::1 or ``localhost``.  Anything else is not: another address, a wildcard
    (``tcp/0.0.0.0``, ``tcp/[::]``: every interface), a host name (it may resolve anywhere), an
    endpoint that cannot be parsed.  The safe default of docs/hil.md ("Keys and
    authentication") refuses to listen beyond this host without a key."""
    import ipaddress
    if endpoint_path(endpoint) is not None or endpoint.startswith("unixsock-"):
        return True
    hp = _host_port(endpoint)
    if hp is None:
        return False
    host = hp[1].lower()
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.split("%", 1)[0]).is_loopback
    except ValueError:
        return False


def local_address_towards(host: str, port: int) -> str | None:
    """The local IP address the kernel would use to reach ``host`` (a routing lookup: a UDP
    socket's ``connect`` sends nothing), or None if there is no route or the name does not
    resolve."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
    except OSError:
        return None
    for family, _, _, _, sockaddr in infos:
        try:
            with socket.socket(family, socket.SOCK_DGRAM) as s:
                s.connect(sockaddr)
                return s.getsockname()[0]
        except OSError:
            continue
    return None


def ephemeral_endpoints(connect) -> list[str]:
    """Listen endpoints (port 0: any free port) for a session that connects to ``connect``: one
    per distinct local address that reaches a connect endpoint, so that every peer that reaches
    the same endpoints can reach this session back (gossip hands them these locators).
    Only ``tcp`` endpoints are followed (a ``tls``/``quic`` listener needs its own certificate
    configuration: give such a session an explicit ``listen``).  Loopback, ``tcp/127.0.0.1:0``,
    when there is nothing to follow or no route is known."""
    out = []
    for ep in _as_list(connect):
        hp = _host_port(ep)
        if hp is None or hp[0] != "tcp":
            continue
        _, host, port = hp
        local = local_address_towards(host, port)
        if local is None:
            continue
        e = f"tcp/{'[' + local + ']' if ':' in local else local}:0"
        if e not in out:
            out.append(e)
    return out or [EPHEMERAL]


def _as_list(x) -> list[str]:
    if x is None:
        return []
    if isinstance(x, str):
        return [x]
    return list(x)


def rx_buffers() -> int:
    """Receive batches pooled per link: 4, or ``AMBHIL_RX_BUFFERS`` (1 = zenoh's default; read
    when a session is configured, so a bad value fails that session with this message)."""
    v = os.environ.get("AMBHIL_RX_BUFFERS", "4")
    try:
        n = int(v)
    except ValueError:
        n = 0
    if n < 1:
        raise TransportError(f"AMBHIL_RX_BUFFERS={v!r}: expected a whole number of receive batches >= 1")
    return n


BATCH = 65535        # zenoh's batch size (transport/link/tx/batch_size default), bytes


def make_config(listen=None, connect=None, *, lowlatency: bool = True, gossip: bool = True,
                extra: dict | None = None) -> "zenoh.Config":
    """Peer-mode config: multicast scouting off, optional gossip over existing links only,
    ``lowlatency`` with QoS off (mandatory pairing), a receive pool of :func:`rx_buffers`
    batches.  ``listen``/``connect``: endpoint or list."""
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "true" if gossip else "false")
    c.insert_json5("listen/endpoints", json.dumps(_as_list(listen)))
    c.insert_json5("connect/endpoints", json.dumps(_as_list(connect)))
    if lowlatency:
        c.insert_json5("transport/unicast/lowlatency", "true")
        c.insert_json5("transport/unicast/qos/enabled", "false")
    c.insert_json5("transport/link/rx/buffer_size", str(rx_buffers() * BATCH))
    for k, v in (extra or {}).items():
        c.insert_json5(k, json.dumps(v))
    return c


def open_session(listen=None, connect=None, *, lowlatency: bool = True, gossip: bool = True,
                 extra: dict | None = None) -> "zenoh.Session":
    """Open a peer session.  With ``connect`` and no ``listen``, ephemeral listeners on the local
    addresses that reach the connect endpoints are added (:func:`ephemeral_endpoints`) so gossip
    can link third parties (recorder) directly, on one host or across a network."""
    if SECURE is not None:          # bridge/process/security.py: TLS + ACL, explicit links only
        extra = {**SECURE, **(extra or {})}
        gossip = False
    listen_l = _as_list(listen)
    if gossip and not listen_l:
        listen_l = ephemeral_endpoints(connect)
    try:
        return zenoh.open(make_config(listen_l, connect, lowlatency=lowlatency, gossip=gossip,
                                      extra=extra))
    except Exception as e:  # zenoh raises ZError
        raise TransportError(f"cannot open zenoh session (listen={listen_l}, "
                             f"connect={_as_list(connect)}): {e}") from None


ID_LEN = 16             # bytes of a peer id (bridge/process/pairing.py)


def peer_id(session) -> bytes:
    """The 16-byte peer id of a zenoh session: its zid, big-endian (bridge/process/pairing.py)."""
    return int(str(session.zid()), 16).to_bytes(ID_LEN, "big")


def declare_publisher(session, key: str, *, block: bool = True, express: bool = True,
                      encoding=None):
    """Reliable publisher; ``block=True`` back-pressures instead of dropping."""
    return session.declare_publisher(
        key,
        encoding=encoding if encoding is not None else zenoh.Encoding.APPLICATION_CDR,
        congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP,
        priority=zenoh.Priority.REAL_TIME, express=express,
        reliability=zenoh.Reliability.RELIABLE)


def declare_subscriber(session, key: str, capacity: int = 1024):
    """Subscriber with a bounded FifoChannel, read with blocking ``recv()``/``try_recv()``."""
    return session.declare_subscriber(key, zenoh.handlers.FifoChannel(capacity))


def declare_callback_subscriber(session, key: str, fn: Callable, *, direct: bool = False):
    """Subscriber whose ``fn(sample)`` runs on a zenoh thread (never block in it).

    zenoh-python hands a plain callable's samples to a Python thread of its own ("indirect"), so
    they may be seen after later messages of the same link that went to other subscribers.
    ``direct=True`` runs ``fn`` on zenoh's receive thread itself
    (``zenoh.handlers.Callback(fn, indirect=False)``), before that thread delivers the link's
    next message: for short callbacks whose effect must precede what follows on the link."""
    if direct:
        return session.declare_subscriber(key, zenoh.handlers.Callback(fn, indirect=False))
    return session.declare_subscriber(key, fn)


class Waker:
    """Wakes a thread blocked in ``sub.recv()`` by putting an empty payload on the
    subscribed key with ``allowed_destination=SESSION_LOCAL`` (never leaves the process).
    Receivers treat an empty payload as "check your flags"."""

    def __init__(self, session, key: str):
        self._pub = session.declare_publisher(key, allowed_destination=zenoh.Locality.SESSION_LOCAL)
        self._lock = threading.Lock()

    def wake(self):
        with self._lock:
            try:
                self._pub.put(b"")
            except Exception:
                pass          # session closing


def wait_matching(pub, timeout: float, what: str = "subscriber") -> None:
    """Block until ``pub`` has a matching remote subscriber (puts before that are lost)."""
    t_end = time.monotonic() + timeout
    while not pub.matching_status.matching:
        if time.monotonic() > t_end:
            raise TransportError(f"no {what} matched {pub.key_expr} within {timeout:g} s")
        time.sleep(0.002)


def declare_token(session, key: str):
    return session.liveliness().declare_token(key)


class LivelinessWatch:
    """Tracks liveliness tokens under ``key_expr`` (e.g. ``ambhil/<run>/alive/*``).

    ``on_change(key, alive)`` runs on a zenoh thread.  ``wait_for(keys, timeout)`` blocks
    until every key is alive.  ``lost`` holds keys that were seen alive and then deleted."""

    def __init__(self, session, key_expr: str, on_change: Callable[[str, bool], None] | None = None):
        self.alive: set[str] = set()
        self.lost: list[str] = []
        self._cond = threading.Condition()
        self._on_change = on_change
        self._sub = session.liveliness().declare_subscriber(key_expr, self._cb, history=True)

    def _cb(self, sample):
        key = str(sample.key_expr)
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            if alive:
                self.alive.add(key)
            else:
                self.alive.discard(key)
                self.lost.append(key)
            self._cond.notify_all()
        if self._on_change is not None:
            self._on_change(key, alive)

    def wait_for(self, keys: Iterable[str], timeout: float, stop: Callable[[], bool] | None = None) -> None:
        keys = set(keys)
        t_end = time.monotonic() + timeout
        with self._cond:
            while not keys <= self.alive:
                rem = t_end - time.monotonic()
                if rem <= 0 or (stop is not None and stop()):
                    missing = ", ".join(sorted(keys - self.alive))
                    raise TransportError(f"peer(s) not alive within {timeout:g} s: {missing}")
                self._cond.wait(min(rem, 0.05))

    def undeclare(self):
        try:
            self._sub.undeclare()
        except Exception:
            pass


def close_quietly(*objs) -> None:
    for o in objs:
        if o is None:
            continue
        try:
            (o.undeclare if hasattr(o, "undeclare") else o.close)()
        except Exception:
            pass
