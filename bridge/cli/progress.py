"""Progress of long sweeps on stderr, drawn by rich: a live bar on a terminal; when stderr is
piped or redirected, a plain line (no control characters) at most every ``every_s`` seconds
(10 s), with the unit of the work and the share done, so a log of a short job stays empty and a
long one gets a line per ten seconds and one at the end."""
from __future__ import annotations

import sys
import time

from rich.console import Console
from rich.progress import (BarColumn, DownloadColumn, MofNCompleteColumn, Progress as _RichProgress,
                           TextColumn, TimeElapsedColumn, TimeRemainingColumn)

EVERY_S = 10.0          # s between two plain progress lines (stderr not a terminal)

# the unit of the work of the labels the sweeps and converters are given (the label's end)
_UNITS = (("support sweep", "positions"), ("Campbell", "speeds"), ("stability", "speeds"),
          ("over speed", "speeds"),
          ("timing study", "tasks"), ("accuracy study", "cases"), (".rrd", "bytes"))


def unit_for(label: str) -> str:
    """The unit counted by a progress of this label ("" if unknown)."""
    return next((u for k, u in _UNITS if label.endswith(k)), "")


def _amount(done: int, total: int, unit: str) -> str:
    if unit == "bytes":
        return f"{done / 1e6:.3g} of {total / 1e6:.3g} MB"
    return f"{done} of {total}" + (f" {unit}" if unit else "")


class Progress:
    """``Progress(label[, unit])(done, total[, detail])``: the progress callback of the sweeps
    (``support_sweep.sweep``, ``modal.campbell``, ``study.accuracy``) and of the .rrd writer.
    ``unit``: what ``done`` counts (default: from the label, :func:`unit_for`; ``"bytes"`` is
    shown in MB).  On a terminal the bar starts at the first call and ends when ``done >= total``
    or on leaving a ``with`` block.  Otherwise a line at most every ``every_s`` seconds and, if a
    line was printed, one when the work is done."""

    def __init__(self, label: str, stream=None, unit: str | None = None, every_s: float = EVERY_S,
                 clock=time.monotonic):
        self.label = label
        self.unit = unit_for(label) if unit is None else unit
        self.console = Console(file=stream or sys.stderr, highlight=False)
        self.every_s, self.clock = every_s, clock
        self._bar = self._task = None
        self._t0 = self._last = clock()
        self._printed = 0
        self._finished = False

    def _line(self, desc: str, done: int, total: int, now: float) -> None:
        el = now - self._t0
        share = f"{100.0 * done / total:.0f} % " if total else ""
        eta = (f", about {el * (total - done) / done:.0f} s left" if 0 < done < total and el > 0 else "")
        self.console.print(f"{desc}: {share}({_amount(done, total, self.unit)}, {el:.0f} s{eta})",
                           markup=False, soft_wrap=True)
        self._printed += 1
        self._last = now

    def __call__(self, done: int, total: int, detail: str | None = None):
        desc = f"{self.label}: {detail}" if detail else self.label
        if not self.console.is_terminal:           # piped: one line per every_s, then the end
            if self._finished:
                return
            now = self.clock()
            if done >= total:
                self._finished = True
                if self._printed:
                    self._line(desc, done, total, now)
            elif now - self._last >= self.every_s:
                self._line(desc, done, total, now)
            return
        if self._bar is None:
            count = DownloadColumn() if self.unit == "bytes" else MofNCompleteColumn()
            cols = [TextColumn("{task.description}", markup=False), BarColumn(), count]
            if self.unit and self.unit != "bytes":
                cols.append(TextColumn(self.unit))
            self._bar = _RichProgress(*cols, TimeElapsedColumn(), TextColumn("eta"),
                                      TimeRemainingColumn(), console=self.console)
            self._task = self._bar.add_task(desc, total=total)
            self._bar.start()
        self._bar.update(self._task, completed=done, total=total, description=desc)
        if done >= total:
            self.close()

    def close(self):
        if self._bar is not None:
            self._bar.stop()
            self._bar = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
