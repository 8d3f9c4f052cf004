"""A one-line progress bar on stderr for long sweeps (silent when stderr is not a terminal
unless forced)."""
from __future__ import annotations

import sys
import time


class Progress:
    def __init__(self, label: str, stream=None, force: bool = False):
        self.label, self.stream = label, stream or sys.stderr
        self.enabled = force or getattr(self.stream, "isatty", lambda: False)()
        self.t0 = time.perf_counter()

    def __call__(self, done: int, total: int):
        if not self.enabled:
            return
        w = 30
        k = int(w * done / max(total, 1))
        el = time.perf_counter() - self.t0
        eta = el / done * (total - done) if done else 0.0
        self.stream.write(f"\r{self.label} [{'#' * k}{'.' * (w - k)}] {done}/{total} {el:5.1f}s eta {eta:4.1f}s")
        if done >= total:
            self.stream.write("\n")
        self.stream.flush()
