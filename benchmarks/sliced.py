"""`ambhil run` against the transport floor and without its recorder, measured in the same
seconds: the contenders take turns on the machine in short time slices.

    .venv/bin/python -m benchmarks.sliced [--scene scenes/paper_3amb.toml] [--rungs modal,full]
        [--slice 0.25] [--cycles 60] [--instances 2]
        [--compare VAR=VALUE | --compare-cmd "OTHER_CHECKOUT/.venv/bin/ambhil"]

Why: on a shared VM the loop's rate moves by 1.5-2x between regimes a few seconds long (other
guests on the host), within a run as much as between runs, so two runs started a minute apart
(benchmarks.lockstep) compare regimes as much as loops: single-run "recorder costs" there range
from -30 to +30 %.  Here the contenders of a rung run side by side, stopped (SIGSTOP) except for
their own slice:

- ``floor``: the two-process zenoh ping-pong (benchmarks.floor) with the scene's SensorSample
  size, on the transport and CPU placement `ambhil run` uses;
- ``rec``: `ambhil run SCENE --rung R` with its recorder;
- ``norec``: the same with ``--no-record``;
- ``--instances N`` (default 2) of each run: two processes of the same command can differ by a
  few per cent for the whole of their lives (memory placement, which caches their hot data
  share), a difference that time slicing does not remove; rates are pooled over instances;
- with ``--compare VAR=VALUE``, ``norec`` is replaced by the same run *with* its recorder and
  ``VAR=VALUE`` in its environment (e.g. ``AMBHIL_PURE_WIRE=1``, the pure-Python codec and
  loops): a before/after of a setting in the same seconds, printed as the change of steps/s;
- with ``--compare-cmd CMD``, the same with another checkout's ``ambhil`` command (e.g.
  ``git worktree add ../old <commit>``, its own virtual environment and C extensions; its runs
  start in that checkout, found as the folder holding the command's ``.venv``): a before/after
  of a code change in the same seconds.

All are started (the runs first: their start-up is the longest) and run side by side until each
one's loop runs (a process stopped for longer than zenoh's 10 s lease finds its links closed
when continued); then all are stopped and, for ``--cycles`` rounds, each in turn is continued
for ``--slice`` seconds and stopped again.  A contender's rate is counted only between its own
progress marks that fall in one of its slices (the plant's Timing flushes every 200 steps,
``AMBHIL_RATE_MARKS=1``; the ping-pong every 200 round trips: both on CLOCK_MONOTONIC, as the
slices), so stopped time and the wake-up after a stop never count.  The recorder process is not
stopped (it only works when its plant publishes).

Printed per rung: each contender's rate, the bound 1 / (floor round trip + plant step +
controller step) and the runs as fractions of it (the two steps timed in process at the start
of every cycle, on the loop's CPU while the contenders are stopped: the median of those
batches), and the recorder's cost 1 - rec / norec; also a second bound with the plant step as
the loop runs it, timed right after a zenoh round trip to a pong process on the loop's CPU (on
the full rung about 20 % more than the warm step), and the runs against it; also per block of
``--cycles / 6`` cycles, to show how stable the ratios are.
"""
from __future__ import annotations

import atexit
import os
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import common, floor
from benchmarks.lockstep import steppers as _lockstep_steppers

ROOT = str(common.ROOT)

_now = time.perf_counter_ns


def _ping_marks(endpoint: str, size: int, cpus, out_path: str) -> None:
    """The ping side (partner: benchmarks.floor's pong): round trips until SIGTERM, a
    (count, t) mark every 200; marks to out_path."""
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge.process.timing import pin_cpus
    stop = []
    signal.signal(signal.SIGTERM, lambda *a: stop.append(1))
    pin_cpus(cpus)
    s = tr.open_session(listen=endpoint)
    sub = tr.declare_subscriber(s, "bench/pong")
    pub = tr.declare_publisher(s, "bench/ping")
    w = tr.LivelinessWatch(s, "bench/alive/*")
    w.wait_for(["bench/alive/pong"], 60)
    tr.wait_matching(pub, 60, "pong")
    payload = bytes(size)
    put, recv = pub.put, sub.recv

    def rounds(n):
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
    """benchmarks.lockstep's steppers, warmed: ``(advance, currents, step, output, axes)``."""
    adv, u, stp, y, n = _lockstep_steppers(scene_path, rung)
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
        from ambhil.bridge.process import transport as tr
        self.tr = tr
        self.ep = floor.endpoint_for("unix", "sliced-step")
        self.p = common.popen(f"from benchmarks import floor as b; b._pong({self.ep!r}, {size}, [{cpu}], 'unix')",
                              common.child_env(ZENOH_RUNTIME=tr.RUNTIME))
        atexit.register(lambda p=self.p: p.poll() is None and p.kill())   # never left behind
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
    """The plant and controller processes of run ``run_id`` (by their command lines:
    ``... ambhil.bridge.cli plant|controller ... --run-id RUN_ID``)."""
    t_end = time.monotonic() + timeout
    while True:
        found = []
        for d in os.listdir("/proc"):
            if d.isdigit():
                w = _cmdline(int(d)).split()
                cli = [i for i, x in enumerate(w[:-1]) if x.endswith(".cli") or os.path.basename(x) == "ambhil"]
                if cli and w[cli[0] + 1] in ("plant", "controller") and "--run-id" in w[:-1] \
                        and w[w.index("--run-id") + 1] == run_id:
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


def _options(argv):
    ap = common.parser(__doc__, repeat=1)       # one invocation; its cycles are the repeats
    ap.add_argument("--scene", default=common.scene("paper_3amb"))
    ap.add_argument("--rungs", default="modal,full")
    ap.add_argument("--slice", type=float, default=0.25, help="s of each contender's turn")
    ap.add_argument("--cycles", type=int, default=60, help="turns of each contender")
    ap.add_argument("--instances", type=int, default=2,
                    help="`ambhil run` processes of each kind (with / without the recorder): two runs "
                         "of the same command differ by a few per cent for reasons of their own")
    ap.add_argument("--compare", metavar="VAR=VALUE",
                    help="instead of --no-record runs, recorded runs with VAR=VALUE in their environment")
    ap.add_argument("--compare-cmd", metavar="CMD",
                    help="instead of --no-record runs, recorded runs of another checkout's `ambhil` command")
    a = ap.parse_args(argv)
    if a.compare is not None and "=" not in a.compare:
        raise SystemExit(f"--compare {a.compare!r}: expected VAR=VALUE")
    if a.compare and a.compare_cmd:
        raise SystemExit("--compare and --compare-cmd: give one")
    a.ours = [sys.executable, "-m", "ambhil.bridge.cli"]
    a.alt_cmd, a.alt_cwd = a.ours, ROOT
    if a.compare_cmd:
        a.alt_cmd = shlex.split(a.compare_cmd)
        parts = Path(a.alt_cmd[0]).absolute().parts
        # started in the other checkout: `python -m` puts the working folder first on sys.path
        a.alt_cwd = str(Path(*parts[:parts.index(".venv")])) if ".venv" in parts else ROOT
    a.scene = common.scene(a.scene)
    a.alt_env = dict([a.compare.split("=", 1)]) if a.compare else {}
    a.lab_b = a.compare or (f"`{a.compare_cmd}`" if a.compare_cmd else "no recorder")
    a.comparing = bool(a.compare or a.compare_cmd)
    return a


def _start_runs(rung: str, a, env: dict, out: str) -> dict:
    """The `ambhil run` contenders of a rung, each running its loop: ``rec0``, ``norec0``, ..."""
    import threading
    runs = {}
    for name, extra in [(f"{kind}{i}", x) for i in range(a.instances)
                        for kind, x in (("rec", []), ("norec", [] if a.comparing else ["--no-record"]))]:
        alt = name.startswith("norec")
        c = Contender(name, (a.alt_cmd if alt else a.ours) + [
                          "run", a.scene, "--rung", rung, "--duration", "600", "--json", "--out", out,
                          "--run-id", f"sliced-{rung}-{name}"] + extra,   # long enough to outlast the cycles
                      {**env, **a.alt_env} if alt else env, "plant: running", cwd=a.alt_cwd if alt else ROOT)
        c.wait_ready(c.p.stderr)
        c.pids = _loop_pids(f"sliced-{rung}-{name}")
        # drain stderr so the pipe never blocks the run
        threading.Thread(target=lambda s=c.p.stderr: [None for _ in s], daemon=True).start()
        runs[name] = c
    return runs


def _start_floor(size: int, cpu: int, env: dict, marks_path: str) -> tuple[Contender, subprocess.Popen, str]:
    """The floor contender (its ping and pong processes), running; and its endpoint."""
    ep = floor.endpoint_for("unix", "sliced")
    pong = common.popen(f"from benchmarks import floor as f; f._pong({ep!r}, {size}, {[cpu]!r}, 'unix')", env)
    fl = Contender("floor", [sys.executable, "-c", f"from benchmarks import sliced as b; b._ping_marks("
                                                  f"{ep!r}, {size}, {[cpu]!r}, {marks_path!r})"], env, "running")
    fl.wait_ready(fl.p.stdout)
    fl.pids = [fl.p.pid, pong.pid]
    return fl, pong, ep


def _take_turns(order: list[Contender], steppers, cpu: int, step_pong: _Pong, a) -> dict:
    """All stopped, then ``a.cycles`` rounds of turns; the two steps timed at the start of each
    cycle, in the same seconds, on the loop's CPU (while all are stopped)."""
    step_t = {"plant": [], "controller": [], "plant after a round trip": []}
    for c in order:
        c.signal(signal.SIGSTOP)
    for k in range(a.cycles):
        tpk, tck, tpr = _step_costs_now(steppers, cpu, rt=step_pong.rt)
        step_t["plant"].append(tpk)
        step_t["controller"].append(tck)
        step_t["plant after a round trip"].append(tpr)
        for c in (order if k % 2 == 0 else order[::-1]):
            t0 = _now()
            c.signal(signal.SIGCONT)
            time.sleep(a.slice)
            c.signal(signal.SIGSTOP)
            c.slices.append((t0, _now()))
    return step_t


def _stop(order: list[Contender], fl: Contender, pong: subprocess.Popen, runs: dict) -> dict:
    """Continue everyone, stop the ping-pong (SIGTERM) and the runs (SIGINT); the plants' summaries."""
    for c in order:
        c.signal(signal.SIGCONT)
    fl.p.send_signal(signal.SIGTERM)
    for p in (fl.p, pong):
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:   # the marks are on disk already
            p.kill()
            p.wait()
    summaries = {}
    for name, c in runs.items():
        c.p.send_signal(signal.SIGINT)
        so, _ = c.p.communicate(timeout=300)
        try:
            summaries[name] = common.last_json(so)["plant"]
        except RuntimeError:
            raise RuntimeError(f"{name}: no summary (exit {c.p.returncode})")
    return summaries


def rates(marks: dict, slices: dict, lo: int, hi: int) -> dict:
    """Rate per contender over cycles ``lo:hi``; ``rec`` / ``norec`` pool their instances
    (counts and times summed)."""
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


def _report(rung: str, a, marks: dict, slices: dict, step_t: dict, runs: dict) -> None:
    R = rates(marks, slices, 0, a.cycles)
    lab_b, comparing = a.lab_b, a.comparing
    tp, tc = statistics.median(step_t["plant"]), statistics.median(step_t["controller"])
    if a.instances > 1:
        print(f"  {rung}: per instance " + ", ".join(f"{k} {R[k]:.0f}" for k in runs) + " steps/s", flush=True)
    bound = 1.0 / (1.0 / R["floor"] + tp + tc)
    print(f"{rung}: plant step {tp * 1e6:.2f} us, controller step {tc * 1e6:.2f} us; "
          f"floor {R['floor']:.0f} round trips/s -> bound {bound:.0f} steps/s", flush=True)
    tpr = statistics.median(step_t["plant after a round trip"])
    bound_rt = 1.0 / (1.0 / R["floor"] + tpr + tc)
    print(f"  the plant step as the loop runs it (right after a round trip): {tpr * 1e6:.2f} us "
          f"({100 * (tpr / tp - 1):+.0f} %) -> bound {bound_rt:.0f} steps/s; against it run+recorder "
          f"{R['rec'] / bound_rt:.3f}, {lab_b} {R['norec'] / bound_rt:.3f}", flush=True)
    print(f"  run+recorder {R['rec']:.0f} steps/s = {R['rec'] / bound:.3f} of the bound; "
          f"{lab_b} {R['norec']:.0f} = {R['norec'] / bound:.3f}; "
          + (f"with {lab_b} the run's steps/s change by {100 * (R['norec'] / R['rec'] - 1):+.1f} %" if comparing
             else f"recorder costs {100 * (1 - R['rec'] / R['norec']):+.1f} %"), flush=True)
    nb = min(6, a.cycles)             # blocks of whole cycles, none empty
    per = a.cycles // nb
    blocks = []
    for b in range(nb):
        r = rates(marks, slices, b * per, (b + 1) * per)
        bb = 1.0 / (1.0 / r["floor"] + tp + tc)
        blocks.append((r["rec"] / bb, r["norec"] / bb, 100 * ((r["norec"] / r["rec"] - 1) if comparing else
                                                               (1 - r["rec"] / r["norec"])), r["floor"]))
    what = f"change with {lab_b}" if comparing else "recorder cost"
    print("  per block of " + f"{per} cycles: run+rec of bound "
          + ", ".join(f"{x[0]:.2f}" for x in blocks) + f"; {what} "
          + ", ".join(f"{x[2]:+.1f}" for x in blocks) + " %; floor "
          + ", ".join(f"{x[3]:.0f}" for x in blocks), flush=True)
    print(f"  median of blocks: run+rec {statistics.median(x[0] for x in blocks):.3f} of bound, "
          f"{lab_b} {statistics.median(x[1] for x in blocks):.3f}, "
          f"{what} {statistics.median(x[2] for x in blocks):+.1f} %", flush=True)


def main(argv=None):
    from ambhil.bridge import protocol as pr
    from ambhil.bridge.cli.run_transport import choose_transport
    from ambhil.bridge.process.transport import remove_socket_files
    a = _options(argv)
    kind = choose_transport("auto", "probe")[0]["kind"]
    if kind != "unix":
        raise SystemExit(f"benchmarks.sliced measures the same-host default, Unix sockets; this host gives {kind}")
    env = common.child_env(AMBHIL_RATE_MARKS="1")
    last = os.cpu_count() - 1
    out = tempfile.mkdtemp(prefix="ambhil-bench-sliced-")
    common.header("sliced", "`ambhil run` against the floor and without its recorder, in the same seconds")
    print(f"# slices of {a.slice} s, {a.cycles} cycles, {a.instances} instances; "
          f"transport {kind}; plant + controller + ping-pong on CPU {last}", flush=True)
    for rung in common.csv(a.rungs):
        steppers = _steppers(a.scene, rung)
        size = pr.SensorCodec(steppers[4]).size      # the scene's SensorSample (the sender id included)
        step_pong = _Pong(last, size)
        runs = _start_runs(rung, a, env, out)
        marks_path = os.path.join(out, f"floor-{rung}.json")
        fl, pong, ep = _start_floor(size, last, env, marks_path)
        # all started and running side by side (none is stopped longer than zenoh's 10 s lease:
        # a peer stopped through it finds its link closed when continued); now the turns
        order = [fl] + list(runs.values())
        step_t = _take_turns(order, steppers, last, step_pong, a)
        step_pong.close()
        summaries = _stop(order, fl, pong, runs)
        remove_socket_files(ep)
        marks = {"floor": read_marks(marks_path)}
        marks.update({name: sm["rate_marks"] for name, sm in summaries.items()})
        _report(rung, a, marks, {c.name: c.slices for c in order}, step_t, runs)


if __name__ == "__main__":
    main()
