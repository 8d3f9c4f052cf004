"""The real-time plant's receive path: a blocking FIFO ``recv()`` with a reply deadline.

zenoh-python's ``recv()`` has no timeout.  The real-time loop used a zenoh callback feeding a
``queue.SimpleQueue`` (``get(timeout=...)``): every reply then crosses zenoh's receive thread,
zenoh-python's callback thread and the queue, each hand-over needing the GIL, which is what
kept 10 kHz out of reach (docs/performance.md).  Here the loop blocks in the FIFO channel's
own ``recv()`` (one hand-over, no GIL) and the window's end is kept by
``ambhil.bridge.process._deadline.DeadlineTimer``: a C thread pinned to a CPU other than the loop's, which
sleeps to the end of each reply window and, only when the reply has not been marked received,
takes the GIL and wakes ``recv()`` with a session-local empty put (:class:`transport.Waker`).
The loop stores two integers per period and makes no system call for it.

``RECEIVE_MODES``: ``"deadline"`` (that), ``"callback"`` (the callback queue), ``"auto"``
(deadline when the C extension is built and the process may use a CPU besides the loop's,
else callback: on one CPU the timer's wake-ups would land on the loop's own CPU).
"""
from __future__ import annotations

from ambhil.bridge.process.timing import original_affinity

try:
    from ambhil.bridge.process._deadline import DeadlineTimer
except ImportError:          # not built (pip install builds it; the fallback is the callback queue)
    DeadlineTimer = None

RECEIVE_MODES = ("auto", "deadline", "callback")


def timer_cpu(loop_cpus, allowed=None) -> int | None:
    """A CPU for the timer thread: the lowest CPU the process was allowed (before it pinned
    itself) that is not one of ``loop_cpus``; None when there is none; -1 (no pinning) when
    the loop is not pinned either."""
    if loop_cpus is None:
        return -1
    allowed = set(original_affinity() if allowed is None else allowed)
    spare = sorted(allowed - {int(c) for c in loop_cpus})
    return spare[0] if spare else None


def choose(mode: str, loop_cpus, allowed=None) -> tuple[str, int | None, str]:
    """``(mode used, timer cpu, why)`` for the requested ``mode``; raises ValueError with a
    one-line reason when ``"deadline"`` is asked for and cannot be had."""
    if mode not in RECEIVE_MODES:
        raise ValueError(f"rt_receive must be one of {RECEIVE_MODES}, got {mode!r}")
    if mode == "callback":
        return "callback", None, "requested"
    if DeadlineTimer is None:
        if mode == "deadline":
            raise ValueError("rt_receive='deadline': the C extension ambhil.bridge.process._deadline is not built "
                             "(pip install -e . builds it)")
        return "callback", None, "ambhil.bridge.process._deadline not built"
    cpu = timer_cpu(loop_cpus, allowed)
    if cpu is None:
        if mode == "deadline":
            raise ValueError(f"rt_receive='deadline': no CPU besides the loop's {sorted(loop_cpus)} "
                             f"for the timer thread")
        return "callback", None, "no spare CPU for the deadline timer"
    return "deadline", cpu, "requested" if mode == "deadline" else "auto"
