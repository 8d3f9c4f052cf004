"""`ambhil run` against the transport floor and without its recorder, measured in the same
seconds: the contenders take turns on the machine in short time slices.

    .venv/bin/python benchmarks/bench_sliced.py [--scene scenes/paper_3amb.toml]
        [--rungs modal,full] [--slice 0.25] [--cycles 60] [--instances 2] [--attachment]
        [--compare VAR=VALUE | --compare-tree DIR]

Why: on the shared 2-vCPU VM the loop's rate moves by 1.5-2x between regimes a few seconds
long (other guests on the host; docs/performance.md), within a run as much as between runs, so
two runs started a minute apart (benchmarks/bench_run.py) compare regimes as much as loops:
single-run "recorder costs" there range from -30 to +30 %.  Here the three contenders of a rung
run side by side, stopped (SIGSTOP) except for their own slice:

- ``floor``: the two-process zenoh ping-pong (benchmarks/bench_pingpong.py) with the scene's
  SensorSample size, on the transport and CPU placement `ambhil run` uses;
- ``rec``: `ambhil run SCENE --rung R` with its recorder;
- ``norec``: the same with ``--no-record``;
- ``--instances N`` (default 2) of each run: two processes of the same command can differ by a
  few per cent for the whole of their lives (memory placement, which caches their hot data
  share), a difference that time slicing does not remove; rates are pooled over instances;
- with ``--attachment``, ``floor+att``: the ping-pong with the pairing attachment the loop's
  messages carried in protocol version 1 (put with it, read and compared on receipt, payload
  taken as bytes); version 2 carries the id in the payload instead (docs/protocol.md §5.1);
- with ``--compare VAR=VALUE``, ``norec`` is replaced by the same run *with* its recorder and
  ``VAR=VALUE`` in its environment (e.g. ``AMBHIL_RX_BUFFERS=1``, zenoh's one receive batch):
  a before/after of a setting in the same seconds, printed as the change of steps/s;
- with ``--compare-tree DIR``, the same with the code of another checkout (``git worktree add
  DIR <commit>``, its C extensions built in place): its runs start in ``DIR`` with
  ``PYTHONPATH=DIR``, so ``python -m ambhil.bridge.cli`` and every process it starts import ``DIR``'s
  ``bridge``: a before/after of a code change in the same seconds.

All are started (the runs first: their start-up is the longest) and run side by side until each one's loop runs (a process stopped for longer
than zenoh's 10 s lease finds its links closed when continued); then all are stopped and, for
``--cycles`` rounds, each in turn is continued for ``--slice`` seconds and stopped again.  A
contender's rate is counted only between its own progress marks that fall in one of its slices
(the plant's Timing flushes every 200 steps, the ping-pong every 200 round trips: both on
CLOCK_MONOTONIC, as the slices), so stopped time and the wake-up after a stop never count.
The recorder process is not stopped (it only works when its plant publishes).

Printed per rung: each contender's rate, the bound 1 / (floor round trip + plant step +
controller step) and the runs as fractions of it (the two steps timed in process at the start
of every cycle, on the loop's CPU while the contenders are stopped: the median of those
batches; a step's cost moves with the machine's regime too, 20-33 us on the full rung here), and the recorder's cost 1 - rec / norec;
also a second bound with the plant step as the loop runs it: timed right after a zenoh round
trip to a pong process on the loop's CPU (bench_cold_step.py: 23 % more than the warm step on
the full rung, +2.5 us on the modal one), and the runs against it;
also per block of ``--cycles / 6`` cycles, to show how stable the ratios are.
"""
from __future__ import annotations

import argparse
import atexit
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)
from ambhil.bridge import protocol as pr

_now = time.perf_counter_ns


def _ping_marks(endpoint: str, size: int, cpus, out_path: str, att: bool = False) -> None:
    """The ping side: round trips until SIGTERM, a (count, t) mark every 200; marks to out_path.
    ``att``: as the loop does, each message carries a 16-byte attachment that the receiver
    reads, compares and whose payload it takes as bytes (bridge/process/pairing.py)."""
    import zenoh
    import bench_pingpong as pp
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge.process.timing import pin_cpus
    stop = []
    signal.signal(signal.SIGTERM, lambda *a: stop.append(1))
    pin_cpus(cpus)
    s = tr.open_session(listen=endpoint, **pp._session_kw("unix"))
    # the pong side is benchmarks/bench_loop_costs._pong (its keys; same attachment handling)
    sub = tr.declare_subscriber(s, "b/pong")
    pub = tr.declare_publisher(s, "b/ping")
    w = tr.LivelinessWatch(s, "b/alive/*")
    w.wait_for(["b/alive/pong"], 60)
    tr.wait_matching(pub, 60, "pong")
    payload = bytes(size)
    put, recv = pub.put, sub.recv
    me, peer = zenoh.ZBytes(b"p" * 16), zenoh.ZBytes(b"c" * 16)

    def rounds(n):
        if att:
            for _ in range(n):
                put(payload, attachment=me)
                smp = recv()
                smp.payload.to_bytes()
                if smp.attachment != peer:
                    raise SystemExit("attachment mismatch")
        else:
            for _ in range(n):
                put(payload)
                recv()
    rounds(2000)
    print("running", flush=True)
    i = 0
    with open(out_path, "w") as f:      # one "count t_ns" line per mark, flushed: readable after a kill
        while not stop:
            f.write(f"{i} {_now()}\n")
            f.flush()
            rounds(200)
            i += 200
    put(b"stop")
    tr.close_quietly(w, sub, pub, s)


def read_marks(path: str) -> list[tuple[int, int]]:
    """The marks :func:`_ping_marks` wrote (a last, partly written line is dropped)."""
    out = []
    with open(path) as f:
        for ln in f:
            parts = ln.split()
            if len(parts) == 2 and ln.endswith("\n"):
                out.append((int(parts[0]), int(parts[1])))
    return out


def _steppers(scene_path: str, rung: str):
    """bench_run's steppers, warmed: ``(advance, currents, step, output, axes)``."""
    from bench_run import steppers
    adv, u, stp, y, n = steppers(scene_path, rung)
    for _ in range(200):
        y = adv(u)
        stp(y)
    return adv, u, stp, y, n


def _step_costs_now(steppers, cpu: int, calls: int = 20, rt=None) -> tuple[float, float, float | None]:
    """Seconds per plant step and per controller step, one batch of ``calls`` each, timed on
    ``cpu`` (the affinity is restored after: `ambhil run` places its processes by the CPUs
    its parent may use); with ``rt`` (a zenoh round trip, see :class:`_Pong`) also the plant
    step as the loop runs it: each of ``calls`` steps timed right after a round trip (the
    round trip not counted), else None."""
    adv, u, stp, y, _ = steppers
    mask = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {cpu})
    t0 = _now()
    for _ in range(calls):
        adv(u)
    t1 = _now()
    for _ in range(calls):
        stp(y)
    t2 = _now()
    after = None
    if rt is not None:
        ts = []
        for _ in range(calls):
            rt()
            a = _now()
            adv(u)
            ts.append(_now() - a)
        after = statistics.median(ts) * 1e-9
    os.sched_setaffinity(0, mask)
    return (t1 - t0) * 1e-9 / calls, (t2 - t1) * 1e-9 / calls, after


class _Pong:
    """A ping-pong partner for :func:`_step_costs_now`: a pong process on ``cpu`` and this
    process's session, opened while pinned to ``cpu`` (zenoh's threads stay there), as the
    loop's plant and controller are placed.  ``rt()`` is one round trip of ``size`` bytes."""

    def __init__(self, cpu: int, size: int):
        import bench_pingpong as pp
        from ambhil.bridge.process import transport as tr
        self.tr = tr
        self.ep = pp.endpoint_for("unix", "sliced-step")
        code = (f"import sys; sys.path.insert(0, {ROOT!r}); sys.path.insert(0, {HERE!r}); "
                f"import bench_pingpong as b; b._pong({self.ep!r}, {size}, [{cpu}], 'unix')")
        self.p = subprocess.Popen([sys.executable, "-c", code], env=dict(os.environ, ZENOH_RUNTIME=tr.RUNTIME))
        mask = os.sched_getaffinity(0)
        os.sched_setaffinity(0, {cpu})
        try:
            self.s = tr.open_session(listen=self.ep)
        finally:
            os.sched_setaffinity(0, mask)
        self.sub = tr.declare_subscriber(self.s, "bench/pong")
        self.pub = tr.declare_publisher(self.s, "bench/ping")
        w = tr.LivelinessWatch(self.s, "bench/alive/*")
        w.wait_for(["bench/alive/pong"], 60)
        w.undeclare()
        tr.wait_matching(self.pub, 60, "pong")
        payload, put, recv = bytes(size), self.pub.put, self.sub.recv

        def rt():
            put(payload)
            recv()
        self.rt = rt
        for _ in range(500):
            rt()

    def close(self):
        try:
            self.pub.put(b"stop")
            self.p.wait(timeout=10)
        except Exception:
            self.p.kill()
        self.tr.close_quietly(self.sub, self.pub, self.s)
        self.tr.remove_socket_files(self.ep)


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
                if f"--run-id {run_id} " in c + " " and ("ambhil.bridge.cli.main plant " in c or "ambhil.bridge.cli.main controller " in c):
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


_STARTED: list = []        # every Contender, for the clean-up at exit


@atexit.register
def _cleanup() -> None:
    """On any exit (an error included): continue what was stopped and kill what still runs,
    so no stopped run or ping-pong is left behind."""
    for c in _STARTED:
        if c.p.poll() is None:
            c.signal(signal.SIGCONT)
            c.p.kill()


class Contender:
    def __init__(self, name: str, argv: list[str], env: dict, ready: str, cwd: str = ROOT):
        self.name, self.slices = name, []
        _STARTED.append(self)
        # the runs are stopped with SIGINT at the end: not ignored in them even if it is here
        # (this benchmark started in the background of a script)
        self.p = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True,
                                  preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
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
    import threading
    import bench_pingpong as pp
    from ambhil.bridge.cli.run import choose_transport
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=os.path.join(ROOT, "scenes", "paper_3amb.toml"))
    ap.add_argument("--rungs", default="modal,full")
    ap.add_argument("--slice", type=float, default=0.25, help="s of each contender's turn")
    ap.add_argument("--cycles", type=int, default=60, help="turns of each contender")
    ap.add_argument("--instances", type=int, default=2,
                    help="`ambhil run` processes of each kind (with / without the recorder): two runs "
                         "of the same command differ by a few per cent for reasons of their own")
    ap.add_argument("--attachment", action="store_true",
                    help="a fourth contender: the ping-pong with the 16-byte pairing attachment of "
                         "protocol version 1")
    ap.add_argument("--compare", metavar="VAR=VALUE",
                    help="instead of --no-record runs, recorded runs with VAR=VALUE in their environment")
    ap.add_argument("--compare-tree", metavar="DIR",
                    help="instead of --no-record runs, recorded runs of the checkout in DIR")
    a = ap.parse_args(argv)
    if a.compare is not None and "=" not in a.compare:
        raise SystemExit(f"--compare {a.compare!r}: expected VAR=VALUE")
    if a.compare_tree is not None:
        if a.compare is not None:
            raise SystemExit("--compare and --compare-tree: give one")
        a.compare_tree = os.path.abspath(a.compare_tree)
        if not os.path.isfile(os.path.join(a.compare_tree, "bridge", "cli.py")):
            raise SystemExit(f"--compare-tree {a.compare_tree}: not an ambhil checkout (no bridge/cli/main.py)")
        a.compare = f"PYTHONPATH={a.compare_tree}"
    a.scene = os.path.abspath(a.scene)
    alt_env = dict([a.compare.split("=", 1)]) if a.compare else {}
    alt_cwd = a.compare_tree or ROOT
    lab_b = (f"tree {a.compare_tree}" if a.compare_tree else a.compare) if a.compare else "no recorder"
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
        steppers = _steppers(a.scene, rung)
        n_axes = steppers[4]
        step_t = {"plant": [], "controller": [], "plant after a round trip": []}
        size = pr.SensorCodec(n_axes).size      # the scene's SensorSample (the sender id included)
        step_pong = _Pong(last, size)
        # -- the two runs: long enough to outlast the cycles
        runs = {}
        for name, extra in [(f"{kind}{i}", x) for i in range(a.instances)
                            for kind, x in (("rec", []), ("norec", [] if a.compare else ["--no-record"]))]:
            c = Contender(name, [sys.executable, "-m", "ambhil.bridge.cli", "run", a.scene, "--rung", rung,
                                 "--duration", "600", "--json", "--out", out, "--run-id", f"sliced-{rung}-{name}"]
                          + extra, {**env, **alt_env} if name.startswith("norec") else env, "plant: running",
                          cwd=alt_cwd if name.startswith("norec") else ROOT)
            c.wait_ready(c.p.stderr)
            c.pids = _loop_pids(f"sliced-{rung}-{name}")
            # drain stderr so the pipe never blocks the run
            threading.Thread(target=lambda s=c.p.stderr: [None for _ in s], daemon=True).start()
            runs[name] = c
        # -- the floor pairs: bare, and (--attachment) with the loop's pairing attachment
        floors, extra_procs, marks_paths, eps = {}, [], {}, []
        for fname, att in (("floor", False),) + ((("floor+att", True),) if a.attachment else ()):
            ep = pp.endpoint_for("unix", "sliced")
            eps.append(ep)
            marks_paths[fname] = os.path.join(out, f"{fname}-{rung}.json")
            head = f"import sys; sys.path.insert(0, {ROOT!r}); sys.path.insert(0, {HERE!r}); import bench_sliced as b; "
            pong = subprocess.Popen([sys.executable, "-c", head + f"import bench_loop_costs as c; c._pong({ep!r}, {att!r})"],
                                    env=env)
            fl = Contender(fname, [sys.executable, "-c", head + f"b._ping_marks({ep!r}, {size}, {[last]!r}, "
                                                               f"{marks_paths[fname]!r}, {att!r})"], env, "running")
            fl.wait_ready(fl.p.stdout)
            fl.pids = [fl.p.pid, pong.pid]
            floors[fname] = fl
            extra_procs.append(pong)
        order = list(floors.values()) + list(runs.values())
        # all started and running side by side (none is stopped longer than zenoh's 10 s lease:
        # a peer stopped through it finds its link closed when continued); now the turns
        for c in order:
            c.signal(signal.SIGSTOP)
        for k in range(a.cycles):
            # the two steps' costs in the same seconds, on the loop's CPU, while all are stopped
            tpk, tck, tpr = _step_costs_now(steppers, last, rt=step_pong.rt)
            step_t["plant"].append(tpk)
            step_t["controller"].append(tck)
            step_t["plant after a round trip"].append(tpr)
            for c in (order if k % 2 == 0 else order[::-1]):
                t0 = _now()
                c.signal(signal.SIGCONT)
                time.sleep(a.slice)
                c.signal(signal.SIGSTOP)
                c.slices.append((t0, _now()))
        # -- end: continue everyone, stop the runs (SIGINT: the plant's summary), the pings
        step_pong.close()
        for c in order:
            c.signal(signal.SIGCONT)
        for fl in floors.values():
            fl.p.send_signal(signal.SIGTERM)
        for p in [fl.p for fl in floors.values()] + extra_procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:   # the marks are on disk already
                p.kill()
                p.wait()
        summaries = {}
        for name, c in runs.items():
            c.p.send_signal(signal.SIGINT)
            so, _ = c.p.communicate(timeout=300)
            lines = [ln for ln in so.splitlines() if ln.startswith("{")]
            if not lines:
                raise RuntimeError(f"{name}: no summary (exit {c.p.returncode})")
            summaries[name] = json.loads(lines[-1])["plant"]
        from ambhil.bridge.process.transport import remove_socket_files
        remove_socket_files(*eps)
        marks = {fname: read_marks(marks_paths[fname]) for fname in floors}
        marks.update({name: sm["rate_marks"] for name, sm in summaries.items()})
        slices = {c.name: c.slices for c in order}

        def rates(lo, hi):
            """Per contender; ``rec`` / ``norec`` pool their instances (counts and times summed)."""
            r, pooled = {}, {"rec": [0, 0], "norec": [0, 0]}
            for name in marks:
                n, t = in_slices(marks[name], slices[name][lo:hi])
                r[name] = n * 1e9 / t if t else float("nan")
                kind = name.rstrip("0123456789")
                if kind in pooled and name != kind:
                    pooled[kind][0] += n
                    pooled[kind][1] += t
            for kind, (n, t) in pooled.items():
                r[kind] = n * 1e9 / t if t else float("nan")
            return r
        R = rates(0, a.cycles)
        tp, tc = statistics.median(step_t["plant"]), statistics.median(step_t["controller"])
        if a.instances > 1:
            print(f"  {rung}: per instance " + ", ".join(f"{k} {R[k]:.0f}" for k in runs) + " steps/s", flush=True)
        bound = 1.0 / (1.0 / R["floor"] + tp + tc)
        print(f"{rung}: plant step {tp * 1e6:.2f} us, controller step {tc * 1e6:.2f} us; "
              f"floor {R['floor']:.0f} round trips/s -> bound {bound:.0f} steps/s", flush=True)
        if "floor+att" in R:
            print(f"  floor with the pairing attachment {R['floor+att']:.0f} round trips/s "
                  f"({1e6 / R['floor+att'] - 1e6 / R['floor']:+.1f} us a round trip); the runs against it: "
                  f"run+recorder {R['rec'] / (1.0 / (1.0 / R['floor+att'] + tp + tc)):.3f}, "
                  f"{lab_b} {R['norec'] / (1.0 / (1.0 / R['floor+att'] + tp + tc)):.3f}", flush=True)
        tpr = statistics.median(step_t["plant after a round trip"])
        bound_rt = 1.0 / (1.0 / R["floor"] + tpr + tc)
        print(f"  the plant step as the loop runs it (right after a round trip): {tpr * 1e6:.2f} us "
              f"({100 * (tpr / tp - 1):+.0f} %) -> bound {bound_rt:.0f} steps/s; against it run+recorder "
              f"{R['rec'] / bound_rt:.3f}, {lab_b} {R['norec'] / bound_rt:.3f}", flush=True)
        print(f"  run+recorder {R['rec']:.0f} steps/s = {R['rec'] / bound:.3f} of the bound; "
              f"{lab_b} {R['norec']:.0f} = {R['norec'] / bound:.3f}; "
              + (f"with {lab_b} the run's steps/s change by {100 * (R['norec'] / R['rec'] - 1):+.1f} %" if a.compare
                 else f"recorder costs {100 * (1 - R['rec'] / R['norec']):+.1f} %"), flush=True)
        nb = min(6, a.cycles)             # blocks of whole cycles, none empty
        per = a.cycles // nb
        blocks = []
        for b in range(nb):
            r = rates(b * per, (b + 1) * per)
            bb = 1.0 / (1.0 / r["floor"] + tp + tc)
            blocks.append((r["rec"] / bb, r["norec"] / bb, 100 * ((r["norec"] / r["rec"] - 1) if a.compare else
                                                                   (1 - r["rec"] / r["norec"])), r["floor"]))
        what = f"change with {lab_b}" if a.compare else "recorder cost"
        print("  per block of " + f"{per} cycles: run+rec of bound "
              + ", ".join(f"{x[0]:.2f}" for x in blocks) + f"; {what} "
              + ", ".join(f"{x[2]:+.1f}" for x in blocks) + " %; floor "
              + ", ".join(f"{x[3]:.0f}" for x in blocks), flush=True)
        print(f"  median of blocks: run+rec {statistics.median(x[0] for x in blocks):.3f} of bound, "
              f"{lab_b} {statistics.median(x[1] for x in blocks):.3f}, "
              f"{what} {statistics.median(x[2] for x in blocks):+.1f} %", flush=True)


if __name__ == "__main__":
    main()
