"""Watchdog thread of the HIL loops: wakes a loop blocked in ``recv()`` when no progress was
made for a timeout, on a tick (so signal handlers and stop requests run), and when a stop is
requested."""
from __future__ import annotations

import threading
import time
from typing import Callable

from ambhil.bridge.process import transport as tr


def stop_fn(stop) -> Callable[[], bool] | None:
    """``stop`` as a callable: None, a ``threading.Event`` (its ``is_set``) or a callable."""
    if stop is None:
        return None
    if hasattr(stop, "is_set"):
        return stop.is_set
    return stop


class Watchdog(threading.Thread):
    """Fires ``waker.wake()`` when ``progress[0]`` has not changed for ``timeout`` s while
    ``active``; also ticks every ``tick`` s while the owner is blocked, and when
    ``stop()`` becomes true, so signal handlers and stop requests get a chance to run."""

    def __init__(self, waker: tr.Waker, timeout: float, stop=None, tick: float = 0.1):
        super().__init__(daemon=True, name="ambhil-watchdog")
        self.waker = waker
        self.timeout = timeout
        self.stop = stop
        self.tick = tick
        self.progress = [-1]       # owner writes progress[0] (a list store: cheapest hot-path write)
        self.active = False
        self.fired_mark = None
        self.pending = 0
        self.done = False

    def wake(self):
        self.pending += 1
        self.waker.wake()

    def run(self):
        check = max(min(self.timeout / 5.0, self.tick), 0.0005)
        last, t_last, t_tick = None, time.monotonic(), time.monotonic()
        while not self.done:
            time.sleep(check)
            now = time.monotonic()
            if self.stop is not None and self.stop():
                self.wake()
                continue
            m = self.progress[0]
            if m != last:
                last, t_last, t_tick = m, now, now
                continue
            if self.active and now - t_last >= self.timeout and self.fired_mark != m:
                self.fired_mark = m
                self.wake()
            elif now - t_tick >= self.tick:
                t_tick = now
                self.wake()
