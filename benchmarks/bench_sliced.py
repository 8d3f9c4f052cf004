"""`ambhil run` against the transport floor and without its recorder, measured in the same
seconds: the contenders take turns on the machine in short time slices.

    .venv/bin/python benchmarks/bench_sliced.py [--scene scenes/paper_3amb.toml]
        [--rungs modal,full] [--slice 0.25] [--cycles 60]

Why: on the shared 2-vCPU VM the loop's rate moves by 1.5-2x between regimes a few seconds
long (other guests on the host; docs/performance.md), within a run as much as between runs, so
two runs started a minute apart (benchmarks/bench_run.py) compare regimes as much as loops:
single-run "recorder costs" there range from -30 to +30 %.  Here the three contenders of a rung
run side by side, stopped (SIGSTOP) except for their own slice:

- ``floor``: the two-process zenoh ping-pong (benchmarks/bench_pingpong.py) with the scene's
  SensorSample size, on the transport and CPU placement `ambhil run` uses;
- ``rec``: `ambhil run SCENE --rung R` with its recorder;
- ``norec``: the same with ``--no-record``.

Each is started while the others are stopped and stopped itself once its loop runs; then, for
``--cycles`` rounds, each in turn is continued for ``--slice`` seconds and stopped again.  A
contender's rate is counted only between its own progress marks that fall in one of its slices
(the plant's Timing flushes every 200 steps, the ping-pong every 200 round trips: both on
CLOCK_MONOTONIC, as the slices), so stopped time and the wake-up after a stop never count.
The recorder process is not stopped (it only works when its plant publishes).

Printed per rung: each contender's rate, the bound 1 / (floor round trip + plant step +
controller step) and the runs as fractions of it, and the recorder's cost 1 - rec / norec;
also per block of ``--cycles / 6`` cycles, to show how stable the ratios are.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

_now = time.perf_counter_ns


def _ping_marks(endpoint: str, size: int, cpus, out_path: str) -> None:
    """The ping side: round trips until SIGTERM, a (count, t) mark every 200; marks to out_path."""
    import bench_pingpong as pp
    from bridge import transport as tr
    from bridge.timing import pin_cpus
    stop = []
    signal.signal(signal.SIGTERM, lambda *a: stop.append(1))
    pin_cpus(cpus)
    s = tr.open_session(listen=endpoint, **pp._session_kw("unix"))
    sub = tr.declare_subscriber(s, "bench/pong")
    pub = tr.declare_publisher(s, "bench/ping")
    w = tr.LivelinessWatch(s, "bench/alive/*")
    w.wait_for(["bench/alive/pong"], 60)
    tr.wait_matching(pub, 60, "pong")
    payload = bytearray(size)
    put, recv = pub.put, sub.recv
    for _ in range(2000):
        put(payload)
        recv()
    print("running", flush=True)
    marks, i = [], 0
    while not stop:
        marks.append((i, _now()))
        for _ in range(200):
            put(payload)
            recv()
        i += 200
    put(b"stop")
    with open(out_path, "w") as f:
        json.dump(marks, f)
    tr.close_quietly(w, sub, pub, s)


def in_slices(marks, slices) -> tuple[int, int]:
    """(count, ns) summed over consecutive marks that lie in one and the same slice."""
    n = t = 0
    j = 0
    for (c0, t0), (c1, t1) in zip(marks, marks[1:]):
        while j < len(slices) and slices[j][1] < t0:
            j += 1
        if j < len(slices) and slices[j][0] <= t0 and t1 <= slices[j][1]:
            n += c1 - c0
            t += t1 - t0
    return n, t


def _loop_pids(run_id: str, timeout: float = 30.0) -> list[int]:
    """The plant and controller processes of run ``run_id`` (by their command lines)."""
    t_end = time.monotonic() + timeout
    while True:
        found = []
        for d in os.listdir("/proc"):
            if d.isdigit():
                c = _cmdline(int(d))
                if f"--run-id {run_id} " in c + " " and ("bridge.cli plant " in c or "bridge.cli controller " in c):
                    found.append(int(d))
        if len(found) == 2 or time.monotonic() > t_end:
            break
        time.sleep(0.1)
    if len(found) != 2:
        raise RuntimeError(f"{run_id}: plant and controller processes not found ({found})")
    return found


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


class Contender:
    def __init__(self, name: str, argv: list[str], env: dict, ready: str):
        self.name, self.slices = name, []
        self.p = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
        self.ready = ready
        self.pids: list[int] = []

    def wait_ready(self, stream, timeout: float = 300.0) -> None:
        t_end = time.monotonic() + timeout
        for line in stream:
            if self.ready in line:
                return
            if time.monotonic() > t_end:
                break
        raise RuntimeError(f"{self.name}: never reached {self.ready!r} (exit {self.p.poll()})")

    def signal(self, sig) -> None:
        for pid in self.pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass


def main(argv=None):
    import statistics
    import threading
    import bench_pingpong as pp
    from bench_run import step_costs
    from bridge.run import choose_transport
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=os.path.join(ROOT, "scenes", "paper_3amb.toml"))
    ap.add_argument("--rungs", default="modal,full")
    ap.add_argument("--slice", type=float, default=0.25, help="s of each contender's turn")
    ap.add_argument("--cycles", type=int, default=60, help="turns of each contender")
    a = ap.parse_args(argv)
    kind = choose_transport("auto", "probe")[0]["kind"]
    if kind != "unix":
        raise SystemExit(f"bench_sliced measures the same-host default, Unix sockets; this host gives {kind}")
    env = dict(os.environ, AMBHIL_RATE_MARKS="1",
               OPENBLAS_NUM_THREADS=os.environ.get("OPENBLAS_NUM_THREADS", "1"))
    last = os.cpu_count() - 1
    out = tempfile.mkdtemp(prefix="ambhil-bench-sliced-")
    print(f"load {os.getloadavg()[0]:.1f}; slices of {a.slice} s, {a.cycles} cycles; "
          f"transport {kind}; plant + controller + ping-pong on CPU {last}", flush=True)
    for rung in a.rungs.split(","):
        tp, tc, n_axes = step_costs(a.scene, rung)
        size = 52 + 8 * n_axes
        # -- the floor pair
        ep = pp.endpoint_for("unix", "sliced")
        marks_path = os.path.join(out, f"floor-{rung}.json")
        pong = subprocess.Popen([sys.executable, "-c",
                                 f"import sys; sys.path.insert(0, {ROOT!r}); sys.path.insert(0, {HERE!r}); "
                                 f"import bench_pingpong as b; b._pong({ep!r}, {size}, {[last]!r}, 'unix')"],
                                env=env)
        floor = Contender("floor", [sys.executable, "-c",
                                    f"import sys; sys.path.insert(0, {ROOT!r}); sys.path.insert(0, {HERE!r}); "
                                    f"import bench_sliced as b; b._ping_marks({ep!r}, {size}, {[last]!r}, {marks_path!r})"],
                          env, "running")
        floor.wait_ready(floor.p.stdout)
        floor.pids = [floor.p.pid, pong.pid]
        floor.signal(signal.SIGSTOP)
        # -- the two runs: long enough to outlast the cycles
        runs = {}
        for name, extra in (("rec", []), ("norec", ["--no-record"])):
            c = Contender(name, [sys.executable, "-m", "bridge.cli", "run", a.scene, "--rung", rung,
                                 "--duration", "600", "--json", "--out", out, "--run-id", f"sliced-{rung}-{name}"]
                          + extra, env, "plant: running")
            c.wait_ready(c.p.stderr)
            c.pids = _loop_pids(f"sliced-{rung}-{name}")
            c.signal(signal.SIGSTOP)
            # drain stderr so the pipe never blocks the run
            threading.Thread(target=lambda s=c.p.stderr: [None for _ in s], daemon=True).start()
            runs[name] = c
        order = [floor, runs["rec"], runs["norec"]]
        for k in range(a.cycles):
            for c in (order if k % 2 == 0 else order[::-1]):
                t0 = _now()
                c.signal(signal.SIGCONT)
                time.sleep(a.slice)
                c.signal(signal.SIGSTOP)
                c.slices.append((t0, _now()))
        # -- end: continue everyone, stop the runs (SIGINT: the plant's summary), the ping
        for c in order:
            c.signal(signal.SIGCONT)
        floor.p.send_signal(signal.SIGTERM)
        floor.p.wait(timeout=60)
        pong.wait(timeout=60)
        pp_marks = json.load(open(marks_path))
        summaries = {}
        for name, c in runs.items():
            c.p.send_signal(signal.SIGINT)
            so, _ = c.p.communicate(timeout=300)
            lines = [ln for ln in so.splitlines() if ln.startswith("{")]
            if not lines:
                raise RuntimeError(f"{name}: no summary (exit {c.p.returncode})")
            summaries[name] = json.loads(lines[-1])["plant"]
        from bridge.transport import remove_socket_files
        remove_socket_files(ep)
        marks = {"floor": pp_marks, "rec": summaries["rec"]["rate_marks"],
                 "norec": summaries["norec"]["rate_marks"]}
        slices = {"floor": floor.slices, "rec": runs["rec"].slices, "norec": runs["norec"].slices}

        def rates(lo, hi):
            r = {}
            for name in marks:
                n, t = in_slices(marks[name], slices[name][lo:hi])
                r[name] = n * 1e9 / t if t else float("nan")
            return r
        R = rates(0, a.cycles)
        bound = 1.0 / (1.0 / R["floor"] + tp + tc)
        print(f"{rung}: plant step {tp * 1e6:.2f} us, controller step {tc * 1e6:.2f} us; "
              f"floor {R['floor']:.0f} round trips/s -> bound {bound:.0f} steps/s", flush=True)
        print(f"  run+recorder {R['rec']:.0f} steps/s = {R['rec'] / bound:.3f} of the bound; "
              f"no recorder {R['norec']:.0f} = {R['norec'] / bound:.3f}; "
              f"recorder costs {100 * (1 - R['rec'] / R['norec']):+.1f} %", flush=True)
        nb = 6
        per = max(1, a.cycles // nb)
        blocks = []
        for b in range(nb):
            r = rates(b * per, (b + 1) * per)
            bb = 1.0 / (1.0 / r["floor"] + tp + tc)
            blocks.append((r["rec"] / bb, r["norec"] / bb, 100 * (1 - r["rec"] / r["norec"]), r["floor"]))
        print("  per block of " + f"{per} cycles: run+rec of bound "
              + ", ".join(f"{x[0]:.2f}" for x in blocks) + "; recorder cost "
              + ", ".join(f"{x[2]:+.1f}" for x in blocks) + " %; floor "
              + ", ".join(f"{x[3]:.0f}" for x in blocks), flush=True)
        print(f"  median of blocks: run+rec {statistics.median(x[0] for x in blocks):.3f} of bound, "
              f"no-rec {statistics.median(x[1] for x in blocks):.3f}, "
              f"recorder cost {statistics.median(x[2] for x in blocks):+.1f} %", flush=True)


if __name__ == "__main__":
    main()
