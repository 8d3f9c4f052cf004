"""Where `ambhil run`'s step goes beyond the transport floor (docs/performance.md, issue 16).

    .venv/bin/python benchmarks/bench_loop_costs.py [--runs 5] [--rung modal] [--only 1,2,3,4,5]

Five measurements, each a ratio within one invocation:
1. the pairing attachment: a two-process ping-pong on a Unix socket (both on the last CPU, as
   `ambhil run` places plant and controller), its pieces on both sides (put with the 16-byte
   attachment, read it, compare it: what bridge/process/pairing.py adds to every message; and a put
   with ``attachment=None``, the keyword path alone), in 500-round blocks interleaved with bare
   blocks in one process pair, each paired with the bare block next to it;
2. the plant's share of recording: `ambhil.bridge.protocol.record_batch.Batcher.flush` of 100/250/500 steps'
   messages (6-axis SensorSample + CurrentCommand sizes) to a subscriber process on the other
   CPU, thread CPU time per flush;
3. the other vCPU: `ambhil run SCENE --rung R --no-record` with CPU 0 idle against CPU 0 kept
   busy by a pinned busy loop (the recorder's CPU; shows whether the vCPUs are independent);
4. the recorder: `ambhil run SCENE --rung R` with and without `--no-record`, alternating;
5. one ``put``, warm: thread CPU of a put to a subscriber on CPU 0, bare, with the attachment
   and with ``attachment=None``, interleaved.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import struct
import subprocess
import sys
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)
LAST = os.cpu_count() - 1


def _pong_setup(ep: str):
    """The pong side's session on the last CPU, ready: (closeables, recv, put, me, peer)."""
    import zenoh
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge.process.timing import pin_cpus
    pin_cpus([LAST])
    s = tr.open_session(connect=ep)
    sub, pub = tr.declare_subscriber(s, "b/ping"), tr.declare_publisher(s, "b/pong")
    tok = tr.declare_token(s, "b/alive/pong")
    tr.wait_matching(pub, 30, "ping")
    return (tok, sub, pub, s), sub.recv, pub.put, zenoh.ZBytes(b"c" * 16), zenoh.ZBytes(b"p" * 16)


def _pong(ep: str, att: bool) -> None:
    from ambhil.bridge.process import transport as tr
    closeables, recv, put, me, peer = _pong_setup(ep)
    while True:
        smp = recv()
        d = smp.payload.to_bytes()
        if d == b"stop":
            break
        if att:
            if smp.attachment != peer:
                raise SystemExit("attachment mismatch")
            put(d, attachment=me)
        else:
            put(d)
    tr.close_quietly(*closeables)


# the pieces of the pairing attachment, interleaved in blocks within one process pair: the
# first payload byte tells the pong which mode a round is in
PARTS = ("bare", "put", "put+read", "put+read+compare", "put(attachment=None)")


def _pong_parts(ep: str) -> None:
    from ambhil.bridge.process import transport as tr
    closeables, recv, put, me, peer = _pong_setup(ep)
    while True:
        smp = recv()
        d = smp.payload.to_bytes()
        m = d[0]
        if m == 0:
            put(d)
        elif m == 1:
            put(d, attachment=me)
        elif m == 2:
            smp.attachment
            put(d, attachment=me)
        elif m == 3:
            if smp.attachment != peer:
                raise SystemExit("attachment mismatch")
            put(d, attachment=me)
        elif m == 4:
            put(d, attachment=None)
        else:
            break
    tr.close_quietly(*closeables)


def _ping_parts(ep: str, blocks: int, rounds: int) -> None:
    import zenoh
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge.process.timing import pin_cpus
    pin_cpus([LAST])
    s = tr.open_session(listen=ep)
    sub, pub = tr.declare_subscriber(s, "b/pong"), tr.declare_publisher(s, "b/ping")
    w = tr.LivelinessWatch(s, "b/alive/*")
    w.wait_for(["b/alive/pong"], 30)
    tr.wait_matching(pub, 30, "pong")
    me, peer = zenoh.ZBytes(b"p" * 16), zenoh.ZBytes(b"c" * 16)
    put, recv = pub.put, sub.recv
    payloads = [bytes([m]) + bytes(99) for m in range(len(PARTS))]
    us = {m: [] for m in range(len(PARTS))}
    pc = time.perf_counter
    for b in range(blocks):
        order = range(len(PARTS)) if b % 2 == 0 else range(len(PARTS) - 1, -1, -1)
        for m in order:
            p = payloads[m]
            t = pc()
            if m == 0:
                for _ in range(rounds):
                    put(p)
                    recv().payload.to_bytes()
            elif m == 1:
                for _ in range(rounds):
                    put(p, attachment=me)
                    recv().payload.to_bytes()
            elif m == 2:
                for _ in range(rounds):
                    put(p, attachment=me)
                    smp = recv()
                    smp.payload.to_bytes()
                    smp.attachment
            elif m == 3:
                for _ in range(rounds):
                    put(p, attachment=me)
                    smp = recv()
                    smp.payload.to_bytes()
                    if smp.attachment != peer:
                        raise SystemExit("attachment mismatch")
            else:
                for _ in range(rounds):
                    put(p, attachment=None)
                    recv().payload.to_bytes()
            us[m].append((pc() - t) / rounds * 1e6)
    put(bytes([255]))
    time.sleep(0.05)
    tr.close_quietly(w, sub, pub, s)
    print(json.dumps(us))


def attachment(runs: int) -> None:
    """The pairing attachment's pieces, each paired with the bare block next to it in time."""
    from bench_pingpong import endpoint_for
    from ambhil.bridge.process.transport import remove_socket_files
    ep = endpoint_for("unix", "att")
    p = subprocess.Popen([sys.executable, __file__, "_pong_parts", ep])
    out = subprocess.run([sys.executable, __file__, "_ping_parts", ep, str(12 * runs), "500"],
                         capture_output=True, text=True, timeout=1800)
    p.wait(timeout=30)
    remove_socket_files(ep)
    if out.returncode != 0:
        raise SystemExit(f"attachment ping failed: {out.stderr[-500:]}")
    us = {int(k): v for k, v in json.loads(out.stdout.strip().splitlines()[-1]).items()}
    bare = us[0]
    rows = []
    for m in range(1, len(PARTS)):
        d = sorted(a - b for a, b in zip(us[m], bare))
        rows.append(f"{PARTS[m]} {statistics.median(d):+.1f} us (quartiles {d[len(d) // 4]:+.1f}, "
                    f"{d[3 * len(d) // 4]:+.1f})")
    print(f"1. ping-pong, Unix socket, both on CPU {LAST}, {len(bare)} blocks of 500 rounds per mode, "
          f"modes interleaved: bare {statistics.median(bare):.1f} us a round trip; on both sides, "
          f"against the bare block next to it: " + "; ".join(rows))


def _sink(ep: str) -> None:
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge.process.timing import pin_cpus
    pin_cpus([0])
    s = tr.open_session(connect=ep)
    done = threading.Event()

    def on(smp):
        if smp.payload.to_bytes() == b"stop":
            done.set()
    sub = s.declare_subscriber("b/rec", on)
    tok = tr.declare_token(s, "b/alive/sink")
    done.wait()
    tr.close_quietly(tok, sub, s)


def _to_sink(tag: str):
    """A publisher on the last CPU matched with a ``_sink`` process on CPU 0: (pub, close)."""
    from bench_pingpong import endpoint_for
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge.process.timing import pin_cpus
    from ambhil.bridge.process.transport import remove_socket_files
    ep = endpoint_for("unix", tag)
    p = subprocess.Popen([sys.executable, __file__, "_sink", ep])
    pin_cpus([LAST])
    s = tr.open_session(listen=ep)
    pub = tr.declare_publisher(s, "b/rec")
    w = tr.LivelinessWatch(s, "b/alive/*")
    w.wait_for(["b/alive/sink"], 30)
    tr.wait_matching(pub, 30, "sink")

    def close():
        pub.put(b"stop")
        p.wait(timeout=30)
        tr.close_quietly(w, pub, s)
        remove_socket_files(ep)
    return pub, close


def flush() -> None:
    from ambhil.bridge.protocol.record_batch import Batcher
    pub, close = _to_sink("flush")
    sample, cur = bytearray(100), bytes(84)
    rows = []
    for n in (100, 250, 500):
        b = Batcher(pub, attachment=b"x" * 16)
        cpu = []
        for _ in range(200):
            for _ in range(n):
                struct.pack_into("<q", sample, 36, time.time_ns())
                b.sent(bytes(sample))
                b.received((time.time_ns(), cur))
            c0 = time.thread_time_ns()
            b.flush(time.time_ns())
            cpu.append(time.thread_time_ns() - c0)
            time.sleep(0.002)
        m = statistics.median(cpu) / 1e3
        rows.append(f"{n} steps {m:.0f} us ({m / n:.2f} us/step)")
    close()
    print("2. Batcher.flush to a subscriber on CPU 0, thread CPU per flush (median of 200): " + "; ".join(rows))


def put_cpu(runs: int) -> None:
    """Thread CPU of one ``put`` (warm, to a subscriber on CPU 0): bare, with the attachment,
    with ``attachment=None`` (the keyword path alone)."""
    import zenoh
    pub, close = _to_sink("put")
    me, payload, put = zenoh.ZBytes(b"p" * 16), bytes(100), pub.put
    names = ("bare", "attachment", "attachment=None")
    us = {k: [] for k in names}
    for b in range(6 * runs):
        for k in (names if b % 2 == 0 else names[::-1]):
            c0 = time.thread_time_ns()
            if k == "bare":
                for _ in range(2000):
                    put(payload)
            elif k == "attachment":
                for _ in range(2000):
                    put(payload, attachment=me)
            else:
                for _ in range(2000):
                    put(payload, attachment=None)
            us[k].append((time.thread_time_ns() - c0) / 2000 / 1e3)
            time.sleep(0.01)
    close()
    print(f"5. put to a subscriber on CPU 0, thread CPU per put (median of {6 * runs} blocks of 2000): "
          + ", ".join(f"{k} {statistics.median(v):.2f} us" for k, v in us.items()))


def sibling(runs: int, rung: str, scene: str) -> None:
    res = {"idle": [], "busy": []}
    amb = os.path.join(os.path.dirname(sys.executable), "ambhil")
    for _ in range(runs):
        for k in res:
            hog = (subprocess.Popen(["taskset", "-c", "0", "sh", "-c", "while :; do :; done"])
                   if k == "busy" else None)
            try:
                out = subprocess.run([amb, "run", scene, "--rung", rung, "--duration", "3", "--json", "--no-record"],
                                     cwd=ROOT, capture_output=True, text=True, timeout=600)
            finally:
                if hog is not None:
                    hog.kill()
                    hog.wait()
            res[k].append(json.loads(out.stdout.splitlines()[-1])["plant"]["steps_per_s"])
    a, b = statistics.median(res["idle"]), statistics.median(res["busy"])
    print(f"3. ambhil run --rung {rung} --no-record (plant + controller on CPU {LAST}), medians of {runs}: "
          f"CPU 0 idle {a:.0f} steps/s, CPU 0 busy {b:.0f} steps/s ({100 * (b / a - 1):+.1f} %)")


def recorder(runs: int, rung: str, scene: str) -> None:
    res = {"no-record": [], "record": []}
    amb = os.path.join(os.path.dirname(sys.executable), "ambhil")
    for _ in range(runs):
        for k in res:
            out = subprocess.run([amb, "run", scene, "--rung", rung, "--duration", "3", "--json"]
                                 + (["--no-record"] if k == "no-record" else []),
                                 cwd=ROOT, capture_output=True, text=True, timeout=600)
            res[k].append(json.loads(out.stdout.splitlines()[-1])["plant"]["steps_per_s"])
    a, b = statistics.median(res["no-record"]), statistics.median(res["record"])
    print(f"4. ambhil run --rung {rung}, medians of {runs} alternating 3 s runs: without the recorder {a:.0f} "
          f"steps/s, with it {b:.0f} (recorder cost {100 * (a / b - 1):+.1f} %; recorded runs "
          f"{min(res['record']):.0f}-{max(res['record']):.0f})")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--rung", default="modal")
    ap.add_argument("--scene", default=os.path.join(ROOT, "scenes", "paper_3amb.toml"))
    ap.add_argument("--only", default="1,2,3,4,5", help="which measurements, e.g. 1 or 2,5")
    a = ap.parse_args(argv)
    only = {int(x) for x in a.only.split(",")}
    print(f"load {os.getloadavg()[0]:.1f}")
    if 1 in only:
        attachment(a.runs)
    if 2 in only:
        flush()
    if 3 in only and LAST >= 1:
        sibling(a.runs, a.rung, a.scene)
    if 4 in only:
        recorder(a.runs, a.rung, a.scene)
    if 5 in only:
        put_cpu(a.runs)


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "_pong":
        _pong(sys.argv[2], sys.argv[3] == "1")
    elif len(sys.argv) > 2 and sys.argv[1] == "_pong_parts":
        _pong_parts(sys.argv[2])
    elif len(sys.argv) > 2 and sys.argv[1] == "_ping_parts":
        _ping_parts(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]))
    elif len(sys.argv) > 2 and sys.argv[1] == "_sink":
        _sink(sys.argv[2])
    else:
        main()
