"""Real-time checks of `ambhil run --mode realtime`: before the run, whether this machine can
hold the scene's rate (:func:`calibrate`); after it, the in-process reference a run that did not
keep its rate is compared with (:func:`reference_orbits`).

Calibration (a fraction of a second, nothing waited for): the plant's and controller's steps
timed in this process over a few hundred periods (the same step objects the run's processes
build), and a round trip between two processes over a Unix-domain socket pair, pinned like the
run's loop (``--placement``), paced like the real-time plant (sleep, then spin, to each period)
and with the run's CPU wake-up latency request (``--cpu-wake-us``) held.  That socket round trip is a floor of the run's zenoh round trip
(zenoh adds its own work on both sides: docs/performance.md), so "cannot hold" is certain and
"can hold" is a necessary condition.  One period of a real-time run needs the plant step, the
controller step and the round trip; the verdict compares their 99th percentiles (the default
``--max-overruns`` is 1 %) with the period.
"""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import numpy as np

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


def round_trip_us(n: int = 300, cpus: list[int] | None = None, period: float | None = None) -> np.ndarray:
    """Round trips (us) of 8 bytes between this process and a child over a Unix socket pair,
    both pinned to ``cpus`` (the run's loop CPU) when given; with ``period`` (s) one round trip
    a period, after sleeping to the period's start as the real-time plant does, its wake-up's
    lateness included.  Empty if it cannot be measured."""
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
        now = time.perf_counter_ns
        msg = b"\0" * 8
        out = np.empty(n)
        period_ns = int(period * 1e9) if period else 0
        spin_ns = int(min(150e-6, 0.2 * period) * 1e9) if period else 0
        if period_ns:
            from .timing import set_timer_slack
            set_timer_slack(1000)       # as the real-time plant (bridge/plant_node.py)
        t0 = now()
        for k in range(20 + n):         # the first replies wait for the child's start-up
            if period_ns:               # paced as the real-time plant: sleep, then spin, to the period
                due = t0 + k * period_ns
                rem = due - spin_ns - now()
                if rem > 0:
                    time.sleep(rem * 1e-9)
                while now() < due:
                    pass
            t = now()
            a.send(msg)
            if len(a.recv(64)) == 0:
                return np.empty(0)
            if k >= 20:
                out[k - 20] = now() - t
                if period_ns:           # the wake-up's lateness counts against the period too
                    out[k - 20] += max(0, t - (t0 + k * period_ns))
            elif k == 19:
                t0 = now() - 20 * period_ns
        return out * 1e-3
    except OSError:
        return np.empty(0)
    finally:
        if old is not None:
            os.sched_setaffinity(0, old)
        a.close()
        if p is not None:
            try:
                p.wait(5.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def _nice_rate(fs: float) -> float:
    """The largest 1-2-5 rate (Hz) <= fs."""
    if not fs > 0:
        return 0.0
    dec = 10.0 ** np.floor(np.log10(fs))
    return max(m * dec for m in (1, 2, 5) if m * dec <= fs)


def calibrate(scene, model, args, cpus: list[int] | None = None, n: int = 300) -> dict:
    """Can this machine hold the scene's rate in real time?  Times the run's own plant and
    controller steps (and those of the modal rung when the run's rung is heavier) and a process
    round trip; returns ``{"can_hold", "line", "period_us", "step_us", "round_trip_us", ...}``
    with ``line`` one sentence for the user (what was measured, and what would fit)."""
    from loop.system import compile_system, controller_runner
    from .commands_hil import plant_runner
    fs = scene.controller.sample_rate
    period_us = 1e6 / fs
    st = _step_times(plant_runner(scene, model, args), controller_runner(scene, rung=model.rung), n)
    from .timing import CpuWakeLatency
    qos = CpuWakeLatency(getattr(args, "cpu_wake_us", None))   # the run's request, held as in the run
    try:
        rt = round_trip_us(n, cpus, 1.0 / fs)
    finally:
        qos.release()
    s50, s99 = float(np.percentile(st, 50)), float(np.percentile(st, 99))
    r50, r99 = (float(np.percentile(rt, 50)), float(np.percentile(rt, 99))) if len(rt) else (0.0, 0.0)
    need = s99 + r99
    can = need <= BUDGET * period_us
    rt_text = (f"process round trip p50 {r50:.0f} / p99 {r99:.0f} us (a floor: zenoh adds to it)" if len(rt)
               else "round trip not measured")
    line = (f"this machine {'can' if can else 'cannot'} hold {fs:g} Hz in real time: plant + controller step "
            f"p50 {s50:.0f} / p99 {s99:.0f} us ({model.rung} rung) + {rt_text} = {need:.0f} us against "
            f"{BUDGET * period_us:.0f} us of the {period_us:g} us period")
    out = {"can_hold": can, "period_us": period_us, "step_us": {"p50": s50, "p99": s99},
           "round_trip_us": {"p50": r50, "p99": r99, "n": int(len(rt))}, "rung": model.rung,
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
                s2 = float(np.percentile(_step_times(plant_runner(scene, m2, args),
                                                     controller_runner(scene, rung="modal"), n), 99))
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
    in-process loop of the same scene, rung, integrator, step and latency (``loop.simulation.
    simulate``, which a lockstep run reproduces bit for bit): what a run that kept its rate would
    have recorded.  None if the scene has a run-up or the loop cannot be run in process."""
    from loop.simulation import simulate
    if scene.plant.simulation.run_up is not None:
        return None
    try:   # speed None: the plant's own default, as the run's plant (commands_hil.plant_runner)
        res = simulate(model, n_steps / scene.controller.sample_rate, None, integrator=args.integrator,
                       h=args.h, latency=latency)
    except Exception:
        return None
    y = res.y[:n_steps]
    return [float(np.max(np.hypot(y[:, 2 * k], y[:, 2 * k + 1]))) if len(y) else 0.0
            for k in range(len(scene.plant.ambs)) if y.shape[1] >= 2 * k + 2]
