"""Network namespaces for tests and benchmarks: plant and controller on two hosts of a private link.

    with NetPair("lock", delay_us=100, jitter_us=50) as net:
        net.popen("plant", [..., "--listen", net.endpoint("plant", 7447)])
        net.popen("controller", [..., "--connect", net.endpoint("plant", 7447)])

Two namespaces, ``plant`` (10.231.N.1/30) and ``controller`` (10.231.N.2/30), each with
loopback up and one interface ``eth0`` on the link.  The link is made in one of two ways:

- ``netem``: one veth pair between the two namespaces, and ``tc qdisc ... netem delay D J`` on
  each end (D +- J uniform per packet, each direction; a round trip adds 2 D on average).
- ``relay``: for a kernel without ``sch_netem`` (CONFIG_NET_SCH_NETEM is not set on this
  project's development VM): a third namespace ``link`` sits between two veth pairs and a
  small Python process in it forwards the Ethernet frames both ways through packet sockets,
  holding each one D +- J (uniform) in FIFO order (a frame never overtakes an earlier one of the
  same direction, as on a real link).  The relay adds its own forwarding time (tens of us on a
  loaded 2-core VM), so the delay it gives is at least D: the measured round trip is what counts,
  and it is what the benchmarks and the timing study read from the recordings.

``link="auto"`` takes netem when the kernel has it and a delay is asked for, else the relay
(also without delay the relay is used only when asked: a bare veth pair otherwise).

Names start with ``ambhil-<pid>-`` so parallel runs (pytest-xdist, other checkouts) never clash;
:func:`cleanup_stale` deletes the namespaces of processes that no longer exist (a killed run).
Everything is torn down on exit, also when the body raises.  Needs root and ``ip netns``;
:func:`unavailable` says why not (tests skip with that reason).
"""
from __future__ import annotations

import itertools
import json
import os
import random
import re
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

PREFIX = "ambhil-"
ROOT = Path(__file__).resolve().parents[1]
_counter = itertools.count()


def _ip(*args, check=True, ns: str | None = None) -> subprocess.CompletedProcess:
    cmd = ["ip"] + (["-n", ns] if ns else []) + list(args)
    r = subprocess.run(cmd, capture_output=True, text=True)
    if check and r.returncode != 0:
        raise NetnsError(f"{' '.join(cmd)}: {r.stderr.strip() or r.returncode}")
    return r


def _in(ns: str, *cmd, check=True) -> subprocess.CompletedProcess:
    r = subprocess.run(["ip", "netns", "exec", ns, *cmd], capture_output=True, text=True)
    if check and r.returncode != 0:
        raise NetnsError(f"ip netns exec {ns} {' '.join(cmd)}: {r.stderr.strip() or r.returncode}")
    return r


class NetnsError(RuntimeError):
    pass


def _namespaces() -> list[str]:
    r = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True)
    return [ln.split()[0] for ln in r.stdout.splitlines() if ln.strip()]


def cleanup_stale() -> list[str]:
    """Delete ``ambhil-<pid>-*`` namespaces whose creating process is gone; returns their names."""
    gone = []
    for ns in _namespaces():
        m = re.match(rf"{PREFIX}(\d+)-", ns)
        if m and not Path(f"/proc/{m.group(1)}").exists():
            _kill_inside(ns)
            _ip("netns", "del", ns, check=False)
            gone.append(ns)
    return gone


def _kill_inside(ns: str) -> None:
    r = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True)
    for pid in r.stdout.split():
        try:
            os.kill(int(pid), signal.SIGKILL)
        except (ProcessLookupError, ValueError):
            pass


_netem: bool | None = None


def netem_available() -> bool:
    """Whether this kernel has the netem qdisc (tried once on a throwaway veth)."""
    global _netem
    if _netem is None:
        ns = f"{PREFIX}{os.getpid()}-probe{next(_counter)}"
        try:
            _ip("netns", "add", ns)
            _ip("link", "add", "p0", "type", "veth", "peer", "name", "p1", ns=ns)
            _netem = subprocess.run(["ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", "p0", "root",
                                     "netem", "delay", "1ms"], capture_output=True).returncode == 0
        except NetnsError:
            _netem = False
        finally:
            _ip("netns", "del", ns, check=False)
    return _netem


def unavailable() -> str | None:
    """None if namespaces can be made here, else the reason (for ``pytest.skip``)."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "no `ip` command (iproute2)"
    ns = f"{PREFIX}{os.getpid()}-check{next(_counter)}"
    r = subprocess.run(["ip", "netns", "add", ns], capture_output=True, text=True)
    if r.returncode != 0:
        return f"`ip netns add` failed: {r.stderr.strip()}"
    _ip("netns", "del", ns, check=False)
    return None


class NetPair:
    """Two namespaces ``plant`` and ``controller`` on one private /30 link (see the module doc)."""

    ROLES = ("plant", "controller")

    def __init__(self, tag: str = "t", delay_us: float = 0.0, jitter_us: float = 0.0, link: str = "auto",
                 seed: int = 0):
        if link not in ("auto", "netem", "relay", "veth"):
            raise ValueError(f"link must be auto, netem, relay or veth, got {link!r}")
        if jitter_us > delay_us:
            raise ValueError(f"jitter {jitter_us} us larger than the delay {delay_us} us")
        if link == "auto":
            link = "veth" if not delay_us else ("netem" if netem_available() else "relay")
        if link == "veth" and delay_us:
            raise ValueError("a bare veth link has no delay; use netem or relay")
        self.link, self.delay_us, self.jitter_us, self.seed = link, float(delay_us), float(jitter_us), seed
        n = next(_counter)
        base = f"{PREFIX}{os.getpid()}-{re.sub(r'[^A-Za-z0-9]', '', tag)[:12]}{n}"
        self.ns = {"plant": f"{base}-p", "controller": f"{base}-c", "link": f"{base}-l"}
        self.subnet = 1 + (os.getpid() * 7 + n) % 250      # 10.231.<subnet>.0/30
        self.addr = {"plant": f"10.231.{self.subnet}.1", "controller": f"10.231.{self.subnet}.2"}
        self._relay: subprocess.Popen | None = None
        self._procs: list[subprocess.Popen] = []

    # ------------------------------------------------------------------ set-up and tear-down
    def __enter__(self) -> "NetPair":
        cleanup_stale()
        try:
            self._build()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _build(self) -> None:
        made = ["plant", "controller"] + (["link"] if self.link == "relay" else [])
        for r in made:
            _ip("netns", "add", self.ns[r])
            _ip("link", "set", "lo", "up", ns=self.ns[r])
            _in(self.ns[r], "sysctl", "-q", "-w", "net.ipv6.conf.all.disable_ipv6=1", check=False)
        p, c = self.ns["plant"], self.ns["controller"]
        if self.link == "relay":
            lk = self.ns["link"]
            _ip("link", "add", "eth0", "netns", p, "type", "veth", "peer", "name", "lp", "netns", lk)
            _ip("link", "add", "eth0", "netns", c, "type", "veth", "peer", "name", "lc", "netns", lk)
            for dev in ("lp", "lc"):
                _ip("link", "set", dev, "up", ns=lk)
        else:
            _ip("link", "add", "eth0", "netns", p, "type", "veth", "peer", "name", "eth0", "netns", c)
        for r in ("plant", "controller"):
            _ip("addr", "add", f"{self.addr[r]}/30", "dev", "eth0", ns=self.ns[r])
            _ip("link", "set", "eth0", "up", ns=self.ns[r])
            if self.link == "netem":
                _in(self.ns[r], "tc", "qdisc", "add", "dev", "eth0", "root", "netem", "delay",
                    f"{self.delay_us:g}us", f"{self.jitter_us:g}us")
        if self.link == "relay":
            self._relay = subprocess.Popen(
                ["ip", "netns", "exec", self.ns["link"], sys.executable, str(Path(__file__).resolve()), "relay",
                 "lp", "lc", f"{self.delay_us:g}", f"{self.jitter_us:g}", str(self.seed)],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
            line = self._relay.stdout.readline()
            if not line.startswith("ready"):
                err = self._relay.stderr.read() if self._relay.poll() is not None else ""
                raise NetnsError(f"link relay did not start: {line.strip()} {err.strip()}")
        self.wait_reachable()

    def wait_reachable(self, timeout: float = 30.0) -> None:
        """Until a TCP connection from controller to plant gets through (ARP, relay up)."""
        code = ("import socket,sys,time\n"
                "s=socket.socket();s.bind((sys.argv[1],0));s.listen(1);print(s.getsockname()[1],flush=True)\n"
                "c,_=s.accept();c.sendall(b'ok')")
        srv = self.popen("plant", [sys.executable, "-c", code, self.addr["plant"]], text=True)
        port = int(srv.stdout.readline())
        probe = ("import socket,sys,time\nt=time.monotonic()+float(sys.argv[3])\n"
                 "while True:\n"
                 " try:\n  c=socket.create_connection((sys.argv[1],int(sys.argv[2])),1.0);print(c.recv(2).decode());break\n"
                 " except OSError as e:\n  if time.monotonic()>t: print('unreachable',e);break\n  time.sleep(0.05)")
        r = _in(self.ns["controller"], sys.executable, "-c", probe, self.addr["plant"], str(port), str(timeout),
                check=False)
        srv.kill()
        srv.wait()
        if r.stdout.strip() != "ok":
            raise NetnsError(f"controller namespace cannot reach {self.addr['plant']}: {r.stdout.strip()} "
                             f"{r.stderr.strip()}")

    def close(self) -> None:
        for pr in self._procs:
            if pr.poll() is None:
                try:
                    os.killpg(pr.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            try:
                pr.wait(5)
            except subprocess.TimeoutExpired:
                pass
        if self._relay is not None:
            if self._relay.poll() is None:
                os.killpg(self._relay.pid, signal.SIGKILL)
            self._relay.wait()
            self._relay.stdout.close()
            self._relay.stderr.close()
        existing = set(_namespaces())
        for ns in self.ns.values():
            if ns in existing:
                _kill_inside(ns)
                _ip("netns", "del", ns, check=False)

    # ------------------------------------------------------------------ use
    def endpoint(self, role: str, port: int = 0) -> str:
        """``tcp/<address of role>:<port>`` (port 0: any free port, for an ephemeral listener)."""
        return f"tcp/{self.addr[role]}:{port}"

    def popen(self, role: str, argv: list[str], **kw) -> subprocess.Popen:
        """Start ``argv`` in ``role``'s namespace (own process group; killed at close)."""
        kw.setdefault("stdout", subprocess.PIPE)
        kw.setdefault("stderr", subprocess.PIPE)
        kw.setdefault("start_new_session", True)
        kw.setdefault("cwd", ROOT)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.update(kw.pop("env", {}) or {})
        p = subprocess.Popen(["ip", "netns", "exec", self.ns[role], *argv], env=env, **kw)
        self._procs.append(p)
        return p

    def ambhil(self, role: str, args: list[str], **kw) -> subprocess.Popen:
        """``ambhil ARGS`` (this interpreter's ``ambhil.bridge.cli``) in ``role``'s namespace."""
        return self.popen(role, [sys.executable, "-m", "ambhil.bridge.cli", *args], text=True, **kw)

    def run(self, scene: str, run_id: str, out: str, mode: str = "lockstep", plant_args: list[str] = (),
            port: int = 7447, timeout: float = 600.0) -> dict:
        """One HIL run across the link, the explicit mesh of ``ambhil run``: ``ambhil record``
        (listening on ``plant``'s address, port + 1) and ``ambhil plant`` (listening on port,
        connecting to the recorder, waiting for it) in the plant namespace, ``ambhil
        controller`` in the controller namespace connecting to both.  (Gossip alone, with the
        controller and recorder connecting to the plant only, linked them in some runs and not in
        others: the recorder then misses the controller's currents.)  Returns {role: (summary or
        None, stderr, exit code)}; the recording is ``out/<run_id>.mcap``."""
        ep, ep_rec = self.endpoint("plant", port), self.endpoint("plant", port + 1)
        # one key for the run's three processes, as docs/hil.md deploys them across hosts (without
        # one they refuse to listen on or connect to a non-loopback address)
        from ambhil.bridge.protocol.auth import write_key_file
        os.makedirs(str(out), exist_ok=True)
        key = os.path.join(str(out), f".{run_id}.key")
        write_key_file(key, force=True)
        common = ["--run-id", run_id, "--json", "--key-file", key]
        procs = {
            "recorder": self.ambhil("plant", ["record", "--out", str(out), "--listen", ep_rec] + common),
            "controller": self.ambhil("controller", ["controller", scene, "--connect", ep, ep_rec] + common),
            "plant": self.ambhil("plant", ["plant", scene, "--listen", ep, "--connect", ep_rec, "--wait-recorder",
                                           "--mode", mode] + list(plant_args) + common),
        }
        res = {}
        t_end = time.monotonic() + timeout
        for role in ("plant", "controller", "recorder"):
            p = procs[role]
            try:
                o, e = p.communicate(timeout=max(1.0, t_end - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                o, e = p.communicate()
                e += f"\n(killed after {timeout:g} s)"
            lines = [ln for ln in o.splitlines() if ln.startswith("{")]
            res[role] = (json.loads(lines[-1]) if lines else None, e, p.returncode)
        return res

    def describe(self) -> str:
        what = {"veth": "veth pair", "netem": f"veth + netem delay {self.delay_us:g}us {self.jitter_us:g}us",
                "relay": f"veth + relay delay {self.delay_us:g}us +- {self.jitter_us:g}us"}[self.link]
        return f"{what} ({self.addr['plant']} <-> {self.addr['controller']})"


class Loopback(NetPair):
    """The same interface on one host's loopback, no namespaces (the baseline of the benchmarks)."""

    def __init__(self, tag: str = "lo"):
        self.link, self.delay_us, self.jitter_us = "loopback", 0.0, 0.0
        self.ns = {}
        self.addr = {"plant": "127.0.0.1", "controller": "127.0.0.1"}
        self._relay, self._procs = None, []

    def __enter__(self) -> "Loopback":
        return self

    def close(self) -> None:
        for pr in self._procs:
            if pr.poll() is None:
                os.killpg(pr.pid, signal.SIGKILL)
                pr.wait()

    def popen(self, role: str, argv: list[str], **kw) -> subprocess.Popen:
        kw.setdefault("stdout", subprocess.PIPE)
        kw.setdefault("stderr", subprocess.PIPE)
        kw.setdefault("start_new_session", True)
        kw.setdefault("cwd", ROOT)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.update(kw.pop("env", {}) or {})
        p = subprocess.Popen(argv, env=env, **kw)
        self._procs.append(p)
        return p

    def run(self, *a, **kw) -> dict:
        if "port" not in kw:
            with socket.socket() as s1, socket.socket() as s2:
                s1.bind(("127.0.0.1", 0))
                s2.bind(("127.0.0.1", s1.getsockname()[1] + 1))   # port and port + 1 both free
                kw["port"] = s1.getsockname()[1]
        return super().run(*a, **kw)

    def describe(self) -> str:
        return "loopback (one namespace)"


# ---------------------------------------------------------------------------------- the relay
SOL_PACKET, PACKET_VNET_HDR = 263, 15
ETH_P_ALL = 0x0003
PACKET_OUTGOING = 4


def _packet_socket(dev: str) -> socket.socket:
    s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    # virtio-net header in front of each frame: checksum-offload and GSO state pass through
    # unchanged (a veth frame's TCP checksum is left to be completed; a large TSO frame stays one)
    s.setsockopt(SOL_PACKET, PACKET_VNET_HDR, 1)
    s.bind((dev, 0))
    s.setblocking(False)
    return s


def relay(dev_a: str, dev_b: str, delay_us: float, jitter_us: float, seed: int = 0) -> None:
    """Forward frames between ``dev_a`` and ``dev_b``, each held ``delay +- jitter`` (uniform), FIFO
    per direction.  Runs until killed."""
    from collections import deque
    rng = random.Random(seed)
    socks = {dev_a: _packet_socket(dev_a), dev_b: _packet_socket(dev_b)}
    other = {dev_a: dev_b, dev_b: dev_a}
    queues = {dev_a: deque(), dev_b: deque()}   # frames to send out of that device: (due, bytes)
    last_due = {dev_a: 0.0, dev_b: 0.0}
    d, j = delay_us * 1e-6, jitter_us * 1e-6
    by_sock = {s: dev for dev, s in socks.items()}
    rlist = list(socks.values())
    print("ready", flush=True)
    now = time.monotonic
    while True:
        due = min((q[0][0] for q in queues.values() if q), default=None)
        # select(): microsecond timeouts (epoll's are whole milliseconds)
        ready, _, _ = select.select(rlist, [], [], None if due is None else max(0.0, due - now()))
        for s in ready:
            dev = by_sock[s]
            while True:
                try:
                    data, addr = s.recvfrom(70000)
                except BlockingIOError:
                    break
                if addr[2] == PACKET_OUTGOING:      # our own transmission seen on the way out
                    continue
                out = other[dev]
                t = max(now() + d + (rng.uniform(-j, j) if j else 0.0), last_due[out])
                last_due[out] = t
                queues[out].append((t, data))
        t = now()
        for dev, q in queues.items():
            while q and q[0][0] <= t:
                try:
                    socks[dev].send(q.popleft()[1])
                except OSError:
                    pass          # a frame the link cannot take is lost, as on a wire


if __name__ == "__main__":
    if len(sys.argv) >= 6 and sys.argv[1] == "relay":
        relay(sys.argv[2], sys.argv[3], float(sys.argv[4]), float(sys.argv[5]),
              int(sys.argv[6]) if len(sys.argv) > 6 else 0)
    else:
        print(__doc__)
        sys.exit(2)
