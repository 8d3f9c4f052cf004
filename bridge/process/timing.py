"""Loop-timing helpers: pacing with absolute deadlines (sleep then spin,
shared/reference/tooling.md §2a), timer slack, CPU pinning, and latency statistics."""
from __future__ import annotations

import ctypes
import os
import sys
import time

import numpy as np

_now = time.perf_counter_ns
HIST_EDGES_US = (0, 10, 25, 50, 75, 100, 150, 200, 300, 500, 1000, 2000, 5000, 10000, float("inf"))


def set_timer_slack(ns: int = 1000) -> bool:
    """prctl(PR_SET_TIMERSLACK): sleeps overshoot by ~slack instead of the 50 µs default."""
    try:
        return ctypes.CDLL(None, use_errno=True).prctl(29, int(ns), 0, 0, 0) == 0
    except Exception:
        return False


CPU_LATENCY_DEV = "/dev/cpu_dma_latency"
CPUIDLE_DRIVER = "/sys/devices/system/cpu/cpuidle/current_driver"


def cpuidle_driver() -> str | None:
    """The kernel's cpuidle driver (e.g. ``haltpoll``, ``intel_idle``, ``acpi_idle``); ``"none"``
    where the kernel has none (then an idle CPU always runs the architecture's default idle,
    HLT on x86, whatever the PM QoS requests say); None if it cannot be read."""
    try:
        with open(CPUIDLE_DRIVER) as f:
            return f.read().strip() or None
    except OSError:
        return None


class CpuWakeLatency:
    """A Linux PM QoS request on the CPUs' wake-up latency, held while the object lives.

    A real-time loop sleeps between periods; an idle CPU then enters an idle state (on a VM:
    HLT, a VM exit) and its next wake-up adds tens of microseconds to every hand-over between
    plant, zenoh and controller.  Writing ``us`` to ``/dev/cpu_dma_latency`` and keeping the
    file open asks the kernel's cpuidle governor for no idle state whose exit latency exceeds
    ``us`` (0: poll only) on every CPU, as cyclictest does; the request ends when the file is
    closed (also when the process dies).  It costs power, not correctness; root or write
    access to that device is needed.  ``status`` says what was obtained, and that the request
    has no effect where the kernel has no cpuidle driver (``effective`` False: idle CPUs halt
    anyway; measured on such a VM, docs/performance.md)."""

    def __init__(self, us: int | None):
        self.fd, self.us = None, us
        self.effective = False
        if us is None:
            self.status = "not requested"
            return
        try:
            fd = os.open(CPU_LATENCY_DEV, os.O_WRONLY)
        except OSError as e:
            self.status = f"unavailable ({CPU_LATENCY_DEV}: {e.strerror})"
            return
        try:
            os.write(fd, int(us).to_bytes(4, sys.byteorder, signed=True))
        except OSError as e:
            os.close(fd)
            self.status = f"unavailable ({CPU_LATENCY_DEV}: {e.strerror})"
            return
        self.fd = fd
        self.status = f"held at {int(us)} us ({CPU_LATENCY_DEV})"
        drv = cpuidle_driver()
        self.effective = None if drv is None else drv != "none"
        if self.effective is False:
            self.status += ("; no effect here: the kernel has no cpuidle driver, idle CPUs halt "
                            f"({CPUIDLE_DRIVER}: none)")

    @property
    def held(self) -> bool:
        return self.fd is not None

    def release(self) -> None:
        if self.fd is not None:
            try:
                os.close(self.fd)
            finally:
                self.fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


_ORIGINAL_AFFINITY: set = set()     # the CPUs this process could use before pin_cpus


def original_affinity() -> set:
    """The CPUs this process was allowed before its first :func:`pin_cpus` (the current
    affinity if it never pinned itself)."""
    return set(_ORIGINAL_AFFINITY) or set(os.sched_getaffinity(0))


def pin_cpus(cpus, all_threads: bool = False) -> None:
    """Pin this thread (and threads created afterwards) to ``cpus`` (iterable of ints).
    Call before opening the zenoh session so its threads inherit the mask, or pass
    ``all_threads=True`` to pin every thread that exists already (zenoh's, BLAS's) too."""
    if cpus is None:
        return
    mask = set(int(c) for c in cpus)
    if not _ORIGINAL_AFFINITY:
        _ORIGINAL_AFFINITY.update(os.sched_getaffinity(0))
    os.sched_setaffinity(0, mask)
    if all_threads:
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setaffinity(int(tid), mask)
            except OSError:          # a thread that just ended
                pass


def wait_until(deadline_ns: int, spin_ns: int) -> int:
    """Sleep until ``spin_ns`` before the absolute ``perf_counter_ns`` deadline, then
    busy-wait.  Returns lateness in ns (>= 0 unless the clock is odd)."""
    t = _now()
    rem = deadline_ns - spin_ns - t
    if rem > 0:
        time.sleep(rem * 1e-9)
    t = _now()
    while t < deadline_ns:
        t = _now()
    return t - deadline_ns


def stats_us(arr_ns) -> dict:
    """Percentiles of a nanosecond array, reported in microseconds."""
    a = np.asarray(arr_ns, dtype=np.float64)
    if a.size == 0:
        return {"n": 0}
    p = np.percentile(a, [50, 90, 99, 99.9]) / 1e3
    return {"n": int(a.size), "p50": round(p[0], 2), "p90": round(p[1], 2), "p99": round(p[2], 2),
            "p999": round(p[3], 2), "max": round(float(a.max()) / 1e3, 2),
            "mean": round(float(a.mean()) / 1e3, 2)}


def histogram_us(arr_ns, edges_us=HIST_EDGES_US) -> dict:
    """Counts per bin; keys like ``"50-75"`` (µs), the last ``">=10000"``."""
    a = np.asarray(arr_ns, dtype=np.float64) / 1e3
    counts, _ = np.histogram(a, bins=np.asarray(edges_us, dtype=float))
    out = {}
    for lo, hi, c in zip(edges_us[:-1], edges_us[1:], counts):
        out[f">={lo:g}" if hi == float("inf") else f"{lo:g}-{hi:g}"] = int(c)
    return out


def window_rates(marks, window_s: float = 0.1) -> dict:
    """Throughput over consecutive wall-clock windows of a run: ``marks`` are ``(count, t_ns)``
    pairs taken as the run goes (monotonic clock, counts increasing); marks are grouped into
    windows of at least ``window_s`` and each window's rate is counted/elapsed.  Returns
    ``{"window_s", "n", "p10", "p50", "p90"}`` (per second), ``{"n": 0}`` without a full window.

    On a shared machine the rate moves by 1.5-2x from one second to the next (other guests on
    the host); ``p90`` is the rate of the run's quiet spells, which the same estimator applied
    to another measurement taken minutes apart can be compared with (python -m benchmarks.lockstep)."""
    rates = []
    if len(marks) >= 2:
        w_ns = int(window_s * 1e9)
        c0, t0 = marks[0]
        for c, t in marks[1:]:
            if t - t0 >= w_ns:
                rates.append((c - c0) * 1e9 / (t - t0))
                c0, t0 = c, t
    if not rates:
        return {"n": 0}
    p10, p50, p90 = np.percentile(rates, (10, 50, 90))
    return {"window_s": window_s, "n": len(rates), "p10": round(float(p10), 1),
            "p50": round(float(p50), 1), "p90": round(float(p90), 1)}
