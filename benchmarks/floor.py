"""The transport floor: a two-process zenoh ping-pong with ambhil's session settings, the
fastest any lockstep loop over zenoh can go on this machine.

    .venv/bin/python -m benchmarks.floor [--repeat 3] [--rounds 20000] [--size 100]
        [--placement shared|split|none] [--transports unix,tcp,tcp-default,unix-default,shm]

``--placement shared`` (the default, as `ambhil run` places plant and controller) pins both
processes to the last CPU: cross-core wake-ups cost more than sharing one core on a VM;
``split`` gives each its own CPU, ``none`` leaves them to the scheduler.  ``--size 100`` is the
six-axis SensorSample of protocol version 2.  Several ``--transports`` are measured interleaved
run by run.  Prints per run the round-trip percentiles (us) and round trips per second, then
the medians.  :func:`measure_floor` is what benchmarks.lockstep and benchmarks.sliced measure
their bound with.
"""
from __future__ import annotations

import json
import os
import subprocess
import time

from benchmarks import common


def _pong(endpoint: str, size: int, cpus, transport: str = "tcp") -> None:
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge.process.timing import pin_cpus
    pin_cpus(cpus)
    s = tr.open_session(connect=endpoint, **_session_kw(transport))
    sub = tr.declare_subscriber(s, "bench/ping")
    pub = tr.declare_publisher(s, "bench/pong")
    tok = tr.declare_token(s, "bench/alive/pong")
    tr.wait_matching(pub, 30, "ping")
    recv, put = sub.recv, pub.put
    shm = _shm_alloc(transport, size)
    while True:
        d = recv().payload.to_bytes()
        if d == b"stop":
            break
        put(shm(d) if shm else d)
    tr.close_quietly(tok, sub, pub, s)


def _session_kw(transport: str) -> dict:
    """Session options of a transport variant: ``tcp``/``unix`` with the ambhil low-latency
    settings, ``tcp-default``/``unix-default`` with zenoh's defaults (QoS on, batching),
    ``shm`` = unix socket + payloads in zenoh shared memory."""
    if transport.endswith("-default"):
        return {"lowlatency": False}
    if transport == "shm":
        return {"lowlatency": False, "extra": {"transport/shared_memory/enabled": True}}
    return {}


def _shm_alloc(transport: str, size: int):
    """For ``shm``: a function copying a payload into a fresh zenoh shared-memory buffer."""
    if transport != "shm":
        return None
    from zenoh import shm
    provider = shm.ShmProvider.default_backend(1 << 20)

    def alloc(d):
        buf = provider.alloc(len(d), shm.BlockOn(shm.GarbageCollect()))
        buf[:] = bytes(d)
        return buf
    return alloc


def endpoint_for(transport: str, tag: str = "") -> str:
    from ambhil.bridge.process.transport import free_port, tcp_endpoint, unix_endpoint
    if transport.startswith("tcp"):
        return tcp_endpoint(free_port())
    return unix_endpoint(f"bench{tag}-{os.getpid()}-{time.monotonic_ns()}")


TRANSPORTS = ("tcp", "unix", "tcp-default", "unix-default", "shm")


def _ping(endpoint: str, rounds: int, warmup: int, size: int, cpus, transport: str = "tcp") -> dict:
    import numpy as np
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge.process.timing import pin_cpus, stats_us, window_rates
    pin_cpus(cpus)
    s = tr.open_session(listen=endpoint, **_session_kw(transport))
    sub = tr.declare_subscriber(s, "bench/pong")
    pub = tr.declare_publisher(s, "bench/ping")
    w = tr.LivelinessWatch(s, "bench/alive/*")
    w.wait_for(["bench/alive/pong"], 30)
    tr.wait_matching(pub, 30, "pong")
    payload = bytearray(size)
    shm = _shm_alloc(transport, size)
    rtt = np.zeros(rounds, np.int64)
    now, put, recv = time.perf_counter_ns, pub.put, sub.recv
    for _ in range(warmup):
        put(shm(payload) if shm else payload)
        recv()
    marks = []                      # (round trips done, t) every 200: windowed rates
    t_start = time.perf_counter()
    for i in range(rounds):
        t0 = now()
        if i % 200 == 0:
            marks.append((i, t0))
        put(shm(payload) if shm else payload)
        recv()
        rtt[i] = now() - t0
    marks.append((rounds, now()))
    wall = time.perf_counter() - t_start
    put(b"stop")
    time.sleep(0.05)
    tr.close_quietly(w, sub, pub, s)
    st = stats_us(rtt)
    st["rate_hz"] = round(rounds / wall, 1)
    # the same 0.1 s window estimator as the plant's summary (steps_per_s_windows)
    st["rate_windows"] = window_rates(marks)
    return st


PLACEMENTS = ("shared", "split", "none")


def placement_cpus(placement) -> tuple:
    """CPU sets (listener process, connecting process) for a placement: ``shared`` = both on
    the last CPU, ``split`` = one CPU each (last two CPUs), ``none``/False = unpinned."""
    if placement is True:
        placement = "shared"
    if not placement or placement == "none":
        return None, None
    last = os.cpu_count() - 1
    if placement == "shared":
        return [last], [last]
    if placement == "split":
        if last < 1:
            raise SystemExit("placement 'split' needs 2 CPUs")
        return [last - 1], [last]
    raise SystemExit(f"--placement must be one of {PLACEMENTS}, got {placement!r}")


def measure_floor(rounds=20000, warmup=2000, size=100, pin="shared", transport="unix") -> dict:
    """One ping-pong run in two fresh processes; returns RTT stats (µs) and rate_hz.
    ``pin``: a placement (see :func:`placement_cpus`) or a bool (True = shared);
    ``transport``: one of :data:`TRANSPORTS`."""
    ep = endpoint_for(transport)
    cpus_ping, cpus = placement_cpus(pin)
    from ambhil.bridge.process.transport import RUNTIME   # the runtime layout ambhil's processes use
    env = common.child_env(ZENOH_RUNTIME=os.environ.get("ZENOH_RUNTIME", RUNTIME))
    p = common.popen(f"from benchmarks import floor as b; b._pong({ep!r}, {size}, {cpus!r}, {transport!r})", env)
    try:
        out = common.run(f"import json; from benchmarks import floor as b; "
                         f"print(json.dumps(b._ping({ep!r}, {rounds}, {warmup}, {size}, {cpus_ping!r}, {transport!r})))",
                         env=env)
        if out.returncode != 0:
            raise RuntimeError(out.stderr.strip().splitlines()[-1] if out.stderr else "ping failed")
        return json.loads(out.stdout.strip().splitlines()[-1])
    finally:
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.kill()
        from ambhil.bridge.process.transport import remove_socket_files
        remove_socket_files(ep)


def main(argv=None):
    ap = common.parser(__doc__, repeat=3)
    ap.add_argument("--rounds", type=int, default=20000)
    ap.add_argument("--warmup", type=int, default=2000)
    ap.add_argument("--size", type=int, default=100, help="payload bytes (100 = a six-axis SensorSample)")
    ap.add_argument("--placement", choices=PLACEMENTS, default="shared")
    ap.add_argument("--transports", default="unix", metavar="LIST",
                    help=f"comma-separated, measured interleaved run by run: {', '.join(TRANSPORTS)}; "
                         f"'all' = every one")
    a = ap.parse_args(argv)
    ts = TRANSPORTS if a.transports == "all" else tuple(common.csv(a.transports))
    bad = [t for t in ts if t not in TRANSPORTS]
    if bad:
        raise SystemExit(f"benchmarks.floor: error: unknown transport(s) {bad}; choose from {TRANSPORTS}")
    common.header("floor", f"zenoh ping-pong, {a.size} B, placement {a.placement}, {a.rounds} round trips a run")
    runs = {t: [] for t in ts}
    for i in range(a.repeat):
        for t in ts:
            r = measure_floor(a.rounds, a.warmup, a.size, a.placement, t)
            runs[t].append(r)
            print(f"run {i + 1} {t:12s}: rtt p50 {r['p50']} p90 {r['p90']} p99 {r['p99']} p99.9 {r['p999']} "
                  f"max {r['max']} us, {r['rate_hz']:.0f} round trips/s", flush=True)
    for t in ts:
        common.report(f"{t} round trips/s", [r["rate_hz"] for r in runs[t]])
        common.report(f"{t} round trip p50", [r["p50"] for r in runs[t]], "us")
        common.report(f"{t} round trip p99", [r["p99"] for r in runs[t]], "us")


if __name__ == "__main__":
    main()
