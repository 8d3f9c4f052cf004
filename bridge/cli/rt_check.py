"""Real-time checks of `ambhil run --mode realtime`: before the run, whether this machine can
hold the scene's rate (:func:`calibrate`); after it, the in-process reference a run that did not
keep its rate is compared with (:func:`reference_orbits`).

Calibration (about a second, nothing waited for but a peer that lives): the plant's and
controller's steps timed in this process over a few hundred periods (the same step objects the
run's processes build), and a zenoh round trip between this process and a child with the run's
transport settings (a Unix socket, or TCP loopback with ``--transport tcp``), both pinned like the
run's loop (``--placement``), paced like the real-time plant (sleep, then spin, to each period) and
with the run's CPU wake-up latency request (``--cpu-wake-us``) held.  Where zenoh cannot be
measured (a secure run's TLS-only sessions), a round trip over a Unix socket pair stands in: a
floor, so its "can hold" is only a necessary condition.  One period of a real-time run needs the
plant step, the controller step and the round trip; the verdict compares their 99th percentiles
(the default ``--max-overruns`` is 1 %) with 90 % of the period.
"""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time

import numpy as np

from ambhil.loop.simulation import simulate
from ambhil.loop.system import compile_system, controller_runner
from ambhil.bridge.cli.run_setup import plant_runner
from ambhil.bridge.process.timing import CpuWakeLatency, set_timer_slack

#: fraction of the period a real-time period's work may take (the rest: wake-up, spin, guard)
BUDGET = 0.9

_ECHO = """
import os, socket, sys
s = socket.socket(fileno=int(sys.argv[1]))
cpus = [int(c) for c in sys.argv[2].split(",") if c]
if cpus:
    os.sched_setaffinity(0, cpus)
while True:
    b = s.recv(64)
    if not b:
        break
    s.send(b)
"""


def _step_times(runner, ctrl, n: int, warm: int = 20, cap_s: float = 1.0) -> np.ndarray:
    """Per-period cost (us) of controller step + plant advance, ``n`` periods after ``warm``
    (fewer, at least 20, where a heavy plant, e.g. the ancf rung, would take over ``cap_s``)."""
    y = runner.reset()
    ctrl.reset()
    now = time.perf_counter_ns
    out = np.empty(n)
    t_end = now() + int(cap_s * 1e9)
    k = 0
    for k in range(warm + n):
        t = now()
        y = runner.advance(ctrl.step(y))
        if k >= warm:
            out[k - warm] = now() - t
            if k - warm >= 19 and t > t_end:
                break
    return out[:max(0, k - warm + 1)] * 1e-3


def _paced(ping, n: int, period: float | None) -> np.ndarray:
    """``n`` round trips (us) of ``ping()`` after 20 untimed ones (the peer's start-up); with
    ``period`` (s) one a period: sleep, then spin, to the period's start as the real-time plant
    does (bridge/process/plant_node.py), the wake-up's lateness counted in.  A round trip that overran
    its period moves the next start to its end (the overrun is counted once, not carried into
    every later period).  Empty when ``ping()`` returns False (the peer is gone)."""
    now = time.perf_counter_ns
    out = np.empty(n)
    period_ns = int(period * 1e9) if period else 0
    spin_ns = int(min(150e-6, 0.2 * period) * 1e9) if period else 0
    if period_ns:
        set_timer_slack(1000)       # as the real-time plant
    due = now()
    for k in range(20 + n):
        if period_ns:
            rem = due - spin_ns - now()
            if rem > 0:
                time.sleep(rem * 1e-9)
            while now() < due:
                pass
        t = now()
        if not ping():
            return np.empty(0)
        end = now()
        if k >= 20:
            out[k - 20] = end - t + (max(0, t - due) if period_ns else 0)
        due = max(due + period_ns, end)
    return out * 1e-3


def _reap(p) -> None:
    """Wait for the calibration's child (told to stop, or its socket closed); kill it if it lingers."""
    if p is None:
        return
    try:
        p.wait(5.0)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()


def round_trip_us(n: int = 300, cpus: list[int] | None = None, period: float | None = None) -> np.ndarray:
    """Round trips (us) of 8 bytes between this process and a child over a Unix socket pair,
    both pinned to ``cpus`` (the run's loop CPU) when given, paced by :func:`_paced`: the floor
    under any transport.  Empty if it cannot be measured."""
    try:
        a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    except OSError:
        return np.empty(0)
    old = os.sched_getaffinity(0) if cpus and hasattr(os, "sched_getaffinity") else None
    p = None
    try:
        p = subprocess.Popen([sys.executable, "-S", "-c", _ECHO, str(b.fileno()),
                              ",".join(map(str, cpus or []))], pass_fds=(b.fileno(),),
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        b.close()
        if old is not None:
            os.sched_setaffinity(0, cpus)
        msg = b"\0" * 8

        def ping() -> bool:
            a.send(msg)
            return len(a.recv(64)) > 0
        return _paced(ping, n, period)
    except OSError:
        return np.empty(0)
    finally:
        if old is not None:
            os.sched_setaffinity(0, old)
        a.close()
        _reap(p)


_ZPONG = """
import os, sys
from ambhil.bridge.process import transport as tr
ep, root, cpus = sys.argv[1], sys.argv[2], [int(c) for c in sys.argv[3].split(",") if c]
if cpus:
    os.sched_setaffinity(0, cpus)
s = tr.open_session(listen=ep, gossip=False)
sub = tr.declare_subscriber(s, root + "/ping")
pub = tr.declare_publisher(s, root + "/pong")
while True:
    d = sub.recv().payload.to_bytes()
    if d == b"stop":
        break
    pub.put(d)
os._exit(0)
"""


def zenoh_round_trip_us(n: int = 300, cpus: list[int] | None = None, period: float | None = None,
                        transport: str = "unix", start_timeout: float = 120.0) -> np.ndarray:
    """Round trips (us) of a sample-sized payload over zenoh with the run's transport settings
    (``ambhil.bridge.process.transport``, a Unix socket or TCP loopback) between this process and a child
    process, pinned and paced as :func:`round_trip_us`: what the run's loop pays per period for
    its messages.  The child's start-up is waited for while it lives (``start_timeout`` bounds
    a child that neither starts nor dies).  Empty if it cannot be measured (e.g. a secure
    session's TLS-only config): the caller falls back to the socket floor."""
    from ambhil.bridge.process import transport as tr     # zenoh: only when calibrating
    if tr.SECURE is not None:
        return np.empty(0)
    root = f"ambhil-calibration/{os.getpid()}"
    try:
        ep = tr.tcp_endpoint(tr.free_port()) if transport == "tcp" else tr.unix_endpoint(f"calibration-{os.getpid()}")
    except tr.TransportError:
        return np.empty(0)
    tr.remove_socket_files(ep)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                                      os.environ.get("PYTHONPATH", "")]))
    old = os.sched_getaffinity(0) if cpus and hasattr(os, "sched_getaffinity") else None
    p = s = None
    objs = []
    try:
        p = subprocess.Popen([sys.executable, "-c", _ZPONG, ep, root, ",".join(map(str, cpus or []))], env=env,
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        t_end = time.monotonic() + start_timeout
        while not os.path.exists(tr.endpoint_path(ep) or "") and transport != "tcp":
            if p.poll() is not None or time.monotonic() > t_end:
                return np.empty(0)
            time.sleep(0.005)
        s = tr.open_session(connect=ep, gossip=False)
        pub = tr.declare_publisher(s, root + "/ping")
        sub = tr.declare_subscriber(s, root + "/pong")
        waker = tr.Waker(s, root + "/pong")
        objs = [pub, sub]
        while not pub.matching_status.matching:     # the child's subscriber (its replies follow it)
            if p.poll() is not None or time.monotonic() > t_end:
                return np.empty(0)
            time.sleep(0.005)
        threading.Thread(target=lambda: (p.wait(), waker.wake()), daemon=True).start()
        if old is not None:
            os.sched_setaffinity(0, cpus)
        msg = bytes(84)                 # about a six-axis SensorSample

        def ping() -> bool:
            pub.put(msg)
            return len(sub.recv().payload.to_bytes()) > 0
        return _paced(ping, n, period)
    except Exception:                   # zenoh raises its own error types: no figure, not a failure
        return np.empty(0)
    finally:
        if old is not None:
            os.sched_setaffinity(0, old)
        if objs:
            try:
                objs[0].put(b"stop")
            except Exception:
                pass
        _reap(p)
        tr.close_quietly(*objs, s)
        tr.remove_socket_files(ep)


def _nice_rate(fs: float) -> float:
    """The largest 1-2-5 rate (Hz) <= fs."""
    if not fs > 0:
        return 0.0
    dec = 10.0 ** np.floor(np.log10(fs))
    return max(m * dec for m in (1, 2, 5) if m * dec <= fs)


def calibrate(scene, model, args, cpus: list[int] | None = None, n: int = 300, latency: float = 0.0) -> dict:
    """Can this machine hold the scene's rate in real time?  Times the run's own plant (its
    ``--integrator``, ``--h`` and ``latency``, s) and controller steps (its ``--law``; and those of the modal rung
    when the run's rung is heavier) and a process round trip; returns ``{"can_hold", "line",
    "period_us", "step_us", "round_trip_us", ...}`` with ``line`` one sentence for the user (what
    was measured, and what would fit)."""
    fs = scene.controller.sample_rate
    period_us = 1e6 / fs
    st = _step_times(plant_runner(scene, model, args.integrator, args.h, latency),
                     controller_runner(scene, rung=model.rung, law=getattr(args, "law", None)), n)
    qos = CpuWakeLatency(getattr(args, "cpu_wake_us", None))   # the run's request, held as in the run
    try:
        rt = zenoh_round_trip_us(n, cpus, 1.0 / fs, "tcp" if getattr(args, "transport", None) == "tcp" else "unix")
        floor = not len(rt)
        if floor:                       # zenoh not measurable here (e.g. a secure run): the socket floor
            rt = round_trip_us(n, cpus, 1.0 / fs)
    finally:
        qos.release()
    s50, s99 = float(np.percentile(st, 50)), float(np.percentile(st, 99))
    r50, r99 = (float(np.percentile(rt, 50)), float(np.percentile(rt, 99))) if len(rt) else (0.0, 0.0)
    need = s99 + r99
    can = need <= BUDGET * period_us
    rt_text = ("round trip not measured" if not len(rt) else
               f"process round trip p50 {r50:.0f} / p99 {r99:.0f} us (a socket floor: zenoh adds to it)" if floor
               else f"zenoh round trip p50 {r50:.0f} / p99 {r99:.0f} us")
    line = (f"this machine {'can' if can else 'cannot'} hold {fs:g} Hz in real time: plant + controller step "
            f"p50 {s50:.0f} / p99 {s99:.0f} us ({model.rung} rung) + {rt_text} = {need:.0f} us against "
            f"{BUDGET * period_us:.0f} us of the {period_us:g} us period")
    out = {"can_hold": can, "period_us": period_us, "step_us": {"p50": s50, "p99": s99},
           "round_trip_us": {"p50": r50, "p99": r99, "n": int(len(rt)), "over": "socket" if floor else "zenoh"},
           "rung": model.rung,
           "suggest_rate_hz": None, "suggest_rung": None}
    if not can:
        tips = []
        fit = _nice_rate(1e6 * BUDGET / need)
        if fit and fit < fs:
            out["suggest_rate_hz"] = fit
            tips.append(f"[controller] sample_rate = {fit:g} in the scene")
        if model.rung in ("full", "ancf"):
            try:
                m2 = compile_system(scene, rung="modal")
                s2 = float(np.percentile(_step_times(plant_runner(scene, m2, args.integrator, args.h, latency),
                                                     controller_runner(scene, rung="modal",
                                                                       law=getattr(args, "law", None)), n), 99))
                if s2 + r99 <= BUDGET * period_us:
                    out["suggest_rung"] = "modal"
                    tips.insert(0, f"--rung modal (step p99 {s2:.0f} us)")
            except Exception:       # a scene the modal rung does not take: no rung advice
                pass
        tips.append("--mode lockstep (any rate)")
        line += "; try " + ", or ".join(tips)
    out["line"] = line
    return out


def reference_orbits(scene, model, args, n_steps: int, latency: float) -> list[float] | None:
    """Largest orbit radius (m) per radial AMB station over the first ``n_steps`` samples of the
    in-process loop of the same scene, law, rung, integrator, step and latency (``ambhil.loop.simulation.
    simulate``, which a lockstep run reproduces bit for bit): what a run that kept its rate would
    have recorded.  None if the scene has a run-up or the loop cannot be run in process."""
    if scene.plant.simulation.run_up is not None:
        return None
    try:   # speed None: the plant's own default, as the run's plant (bridge/cli/run_setup.py plant_runner)
        res = simulate(model, n_steps / scene.controller.sample_rate, None, integrator=args.integrator,
                       h=args.h, latency=latency, law=getattr(args, "law", None))
    except Exception:
        return None
    y = res.y[:n_steps]
    return [float(np.max(np.hypot(y[:, 2 * k], y[:, 2 * k + 1]))) if len(y) else 0.0
            for k in range(len(scene.plant.ambs)) if y.shape[1] >= 2 * k + 2]
