"""Progress of long sweeps on stderr, drawn by rich: a live bar on a terminal; when stderr is
piped or redirected, plain lines (no control characters) at every tenth of the work."""
from __future__ import annotations

import sys
import time

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress as _RichProgress, TextColumn,
                           TimeElapsedColumn, TimeRemainingColumn)


class Progress:
    """``Progress(label)(done, total[, detail])``: the progress callback of the sweeps
    (``support_sweep.sweep``, ``modal.campbell``, ``study.accuracy``).  The bar starts at the
    first call and ends when ``done >= total`` or on leaving a ``with`` block."""

    def __init__(self, label: str, stream=None):
        self.label = label
        self.console = Console(file=stream or sys.stderr, highlight=False)
        self._bar = self._task = None
        self._t0, self._next = time.perf_counter(), 0

    def __call__(self, done: int, total: int, detail: str | None = None):
        desc = f"{self.label}: {detail}" if detail else self.label
        if not self.console.is_terminal:           # piped: a line per tenth, none repeated
            if done >= self._next or done >= total:
                self.console.print(f"{desc} {done}/{total} ({time.perf_counter() - self._t0:.1f} s)",
                                   markup=False, soft_wrap=True)
                self._next = done + max(1, -(-total // 10))
            return
        if self._bar is None:
            self._bar = _RichProgress(TextColumn("{task.description}", markup=False), BarColumn(),
                                      MofNCompleteColumn(), TimeElapsedColumn(), TextColumn("eta"),
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
