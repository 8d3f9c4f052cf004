"""A law from a shared library of the C ABI (``include/ambhil_law.h``), loaded with ctypes.

The library exports ``ambhil_law_new``, ``ambhil_law_step``, ``ambhil_law_reset`` and
``ambhil_law_free`` (and optionally ``ambhil_law_fault_name``); :class:`CLaw` is the law object
of controller/law.py around them: ``step(t, y)`` calls ``ambhil_law_step`` on the caller's ``y``
and a buffer of its own for ``u``, ``reset()`` calls ``ambhil_law_reset``, ``close()`` (or the
garbage collector) ``ambhil_law_free``, once.  The example is ``examples/c_law/pid_law.c``, the
built-in PID bit for bit.

Per step the cost is one ctypes call: the argument types are set once, the state and the ``u``
buffer are passed as addresses, and the address of ``y`` is looked up only when a different
array comes (:class:`ambhil.controller.law_runner.LawRunner` passes the same one every period).
"""
from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np

from .law import LawError, LawMeta

#: what every law library exports (include/ambhil_law.h)
SYMBOLS = ("ambhil_law_new", "ambhil_law_step", "ambhil_law_reset", "ambhil_law_free")
FAULT_NAME = "ambhil_law_fault_name"


class CLaw:
    """The law of the shared library ``path`` for ``meta`` (``CLaw(path, meta)``)."""

    def __init__(self, path: str, meta: LawMeta):
        self.name = Path(path).name
        self._state = None
        try:
            lib = ctypes.CDLL(str(path))
        except OSError as e:
            raise LawError(f"law {self.name}: cannot load the library: {str(e).strip()[:300]}") from None
        for sym in SYMBOLS:
            if not hasattr(lib, sym):
                raise LawError(f"law {self.name}: missing symbol {sym} (the C ABI of include/ambhil_law.h)")
        vp, dbl = ctypes.c_void_p, ctypes.c_double
        lib.ambhil_law_new.argtypes = (ctypes.c_int, dbl, ctypes.c_char_p, ctypes.c_char_p)
        lib.ambhil_law_new.restype = vp
        lib.ambhil_law_step.argtypes = (vp, dbl, vp, vp)
        lib.ambhil_law_step.restype = ctypes.c_int
        lib.ambhil_law_reset.argtypes = (vp,)
        lib.ambhil_law_reset.restype = None
        lib.ambhil_law_free.argtypes = (vp,)
        lib.ambhil_law_free.restype = None
        self._fault_name = getattr(lib, FAULT_NAME, None)
        if self._fault_name is not None:
            self._fault_name.argtypes = (ctypes.c_int,)
            self._fault_name.restype = ctypes.c_char_p
        self._lib = lib
        self._step, self._reset, self._free = lib.ambhil_law_step, lib.ambhil_law_reset, lib.ambhil_law_free
        self.n_axes = meta.n_axes
        state = lib.ambhil_law_new(meta.n_axes, meta.period, ",".join(meta.axes).encode(),
                                   meta.params_json().encode())
        if not state:
            raise LawError(f"law {self.name}: ambhil_law_new returned NULL (the law refused "
                           f"{meta.n_axes} axes at {meta.period:.6g} s with these parameters)")
        self._state = state
        self.u = np.zeros(meta.n_axes)
        self._u_addr = self.u.ctypes.data
        self._y = self._y_addr = None

    def step(self, t: float, y: np.ndarray) -> np.ndarray:
        """``ambhil_law_step`` on ``y`` (float64, ``n_axes``) -> the law's own ``u`` buffer."""
        if y is not self._y:
            self._y_addr = self._address(y)
            self._y = y
        rc = self._step(self._state, t, self._y_addr, self._u_addr)
        if rc:
            raise LawError(f"law {self.name}: ambhil_law_step returned fault code {rc}"
                           f"{self._fault_text(rc)} at t = {t:.6g} s")
        return self.u

    def reset(self) -> None:
        self._reset(self._live())

    def close(self) -> None:
        """``ambhil_law_free``, once (later calls do nothing)."""
        state, self._state = self._state, None
        self._y = self._y_addr = None       # the next step() checks the state again
        if state:
            self._free(state)

    def __del__(self):
        if getattr(self, "_state", None):
            self.close()

    def _live(self):
        if not self._state:
            raise LawError(f"law {self.name}: used after close()")
        return self._state

    def _address(self, y) -> int:
        self._live()
        if not (isinstance(y, np.ndarray) and y.dtype == np.float64 and y.flags.c_contiguous
                and y.shape == (self.n_axes,)):
            raise LawError(f"law {self.name}: step needs {self.n_axes} contiguous float64 sensor "
                           f"outputs, got {getattr(y, 'dtype', type(y).__name__)} of shape {np.shape(y)}")
        return y.ctypes.data

    def _fault_text(self, rc: int) -> str:
        if self._fault_name is None:
            return ""
        try:
            name = self._fault_name(rc)
        except Exception:   # noqa: BLE001 -- a broken name function must not hide the fault itself
            return ""
        return f" ({name.decode(errors='replace')})" if name else ""
