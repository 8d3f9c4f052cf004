"""The real-time plant's receive deadline (bridge/process/deadline.py, bridge/process/_deadline.c).

The timer must call ``fire(seq)`` once for a window whose reply was not marked received, never
for one that was, and never before the window's end.  Under load the fire may come late (the
timer thread waits for its CPU and for the GIL), so the checks wait for the fires that must
come and bound only the early side."""
from __future__ import annotations

import os
import threading
import time

import pytest

from ambhil.bridge.process import deadline

pytestmark = pytest.mark.skipif(deadline.DeadlineTimer is None,
                                reason="ambhil.bridge.process._deadline not built (pip install -e .)")

P = 1_000_000          # 1 ms windows: a test about semantics, not speed


def _timer():
    fired, lock, ev = [], threading.Lock(), threading.Event()

    def fire(seq):
        with lock:
            fired.append((seq, time.perf_counter_ns()))
        ev.set()
    return deadline.DeadlineTimer(fire, P, -1), fired, ev


def _wait(cond, what, limit=60.0):
    t_end = time.monotonic() + limit
    while not cond():
        if time.monotonic() > t_end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.001)


def test_fires_once_for_a_missed_window_and_never_early():
    t, fired, _ = _timer()
    try:
        w = time.perf_counter_ns() + 5 * P
        t.arm(1, w)
        _wait(lambda: fired, "the fire of window 1")
        time.sleep(0.02)                       # a second fire for the same window would come now
        assert [s for s, _ in fired] == [1]
        assert fired[0][1] >= w                 # not before the window's end
        assert t.stats()["timer_fires"] == 1
    finally:
        t.close()


def test_no_fire_for_windows_whose_reply_came():
    t, fired, _ = _timer()
    try:
        t0 = time.perf_counter_ns()
        for k in range(1, 21):                  # 20 windows answered in time
            w = t0 + (k + 2) * P
            t.arm(k, w)
            t.done(k)
            time.sleep(P * 1e-9)
        time.sleep(0.02)
        assert fired == [] and t.stats()["timer_fires"] == 0
        # then one missed window among answered ones: exactly that one fires
        k, w = 21, time.perf_counter_ns() + 3 * P
        t.arm(k, w)
        _wait(lambda: fired, "the fire of window 21")
        t.arm(22, time.perf_counter_ns() + 3 * P)
        t.done(22)
        time.sleep(0.02)
        assert [s for s, _ in fired] == [21]
    finally:
        t.close()


def test_a_window_already_over_when_armed_fires_at_once():
    t, fired, _ = _timer()
    try:
        t.arm(1, time.perf_counter_ns() - P)
        _wait(lambda: fired, "the fire of a past window")
        assert [s for s, _ in fired] == [1]
    finally:
        t.close()


def test_close_stops_the_thread_and_is_idempotent():
    t, fired, _ = _timer()
    t.arm(1, time.perf_counter_ns() + 50 * P)
    t.close()
    t.close()
    time.sleep(0.08)                           # past the armed window: a live thread would fire
    assert fired == [] and t.stats()["timer_fires"] == 0


def test_bad_arguments_are_one_line_errors():
    with pytest.raises(TypeError, match="fire must be callable"):
        deadline.DeadlineTimer(3, P)
    with pytest.raises(ValueError, match="period_ns must be > 0"):
        deadline.DeadlineTimer(lambda s: None, 0)


def test_choice_of_receive_path():
    # the timer goes to a CPU that is not the loop's; none left: callback (auto) or an error
    assert deadline.choose("auto", [1], allowed={0, 1})[:2] == ("deadline", 0)
    assert deadline.choose("auto", [1], allowed={1})[:2] == ("callback", None)
    assert deadline.choose("auto", None)[:2] == ("deadline", -1)      # unpinned loop, unpinned timer
    assert deadline.choose("callback", [1], allowed={0, 1})[:2] == ("callback", None)
    with pytest.raises(ValueError, match=r"no CPU besides the loop's \[1\]"):
        deadline.choose("deadline", [1], allowed={1})
    with pytest.raises(ValueError, match="rt_receive must be one of"):
        deadline.choose("fast", None)


def test_the_timer_thread_runs_on_the_cpu_it_was_given():
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        pytest.skip("one CPU")
    cpu = cpus[-1]
    seen = []         # fire() runs on the timer thread: its affinity mask is the thread's
    t = deadline.DeadlineTimer(lambda s: seen.append(os.sched_getaffinity(0)), P, cpu)
    try:
        t.arm(1, time.perf_counter_ns())
        _wait(lambda: seen, "the fire")
        assert seen[0] == {cpu}
    finally:
        t.close()
