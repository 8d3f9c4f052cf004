"""A law between the hardware: the controller process's loop body for any law.

:class:`LawRunner` has the duck type of :class:`ambhil.controller.discrete.ControllerRunner`
(``n_axes``, ``period``, ``reset()``, ``step(d)``, ``step_shared(d)``, ``saturated``,
``step_index``), so the in-process loop, the controller process, campaigns and replays run it
unchanged.  Each sample::

    y = sensor(d)          u = law.step(t, y)          i = amplifier(u)      (controller/hardware.py)

``t`` is the simulation time of the sample: ``k T`` for the k-th sample answered (a controller
restart resets the law, not the clock).  What the law returns is checked before it reaches the
amplifier: an exception, a wrong shape or a non-finite value raises :class:`LawError` naming the
law and the step, and the run ends with that fault.
"""
from __future__ import annotations

import numpy as np

from . import discrete as dc
from . import hardware as hw
from .law import LawError, LawMeta
from .params import ControllerParams


class LawRunner:
    """``factory(meta) -> law``: a law class (or any callable making one); ``name``: how errors
    name it (e.g. ``controller.py:MyLaw``)."""

    def __init__(self, factory, config: ControllerParams, i_op, sample_rate: float | None = None,
                 method: str | None = None, axes=None, name: str = "law", base_dir: str = "."):
        import dataclasses
        self.config = config
        self.name = name
        self.i_op = np.array(i_op, dtype=float).reshape(-1)
        self.n_axes = len(self.i_op)
        self.sample_rate = float(sample_rate or config.sample_rate)
        self.period = 1.0 / self.sample_rate
        self.hw_params = hw.hardware_params(dc.discretise(config, self.sample_rate, method),
                                            config.amplifier.slew_rate, self.period)
        meta = LawMeta.of(dataclasses.replace(config, sample_rate=self.sample_rate,
                                              discretisation=method or config.discretisation),
                          self.i_op, axes, self.period, u_op=hw.input_at(self.hw_params, self.i_op),
                          base_dir=base_dir)
        self.meta = dataclasses.replace(meta, controller={**meta.controller, "sample_rate": self.sample_rate,
                                                          "discretisation": method or config.discretisation})
        try:
            self.law = factory(self.meta)
        except LawError:
            raise
        except Exception as e:
            raise LawError(f"law {name}: could not be made: {type(e).__name__}: {_line(e)}") from None
        self._reset_law = getattr(self.law, "reset", None)
        self.currents = np.zeros(self.n_axes)
        self._y = np.zeros(self.n_axes)
        self.saturated = 0
        self.k = 0                     # samples answered: the law's clock, t = k T
        self.reset()

    def reset(self) -> None:
        self.state = hw.initial_state(self.hw_params, self.i_op)
        self.step_index = 0
        self.saturated = 0
        if self._reset_law is not None:
            try:
                self._reset_law()
            except Exception as e:
                raise LawError(f"law {self.name}: reset() failed at step {self.k}: "
                               f"{type(e).__name__}: {_line(e)}") from None

    def step_shared(self, d: np.ndarray) -> np.ndarray:
        """One sample: displacements ``d`` (a writable float64 array of ``n_axes``) -> the runner's
        own current buffer (overwritten by the next call)."""
        p, h = self.hw_params, self.state
        hw.sensor_step(p, h, d, self._y)
        t = self.k * self.period
        try:
            u = self.law.step(t, self._y)
        except LawError as e:           # the law named its own fault (a C law's code): add the step
            msg = str(e).removeprefix(f"law {self.name}: ")
            raise LawError(f"law {self.name}: step {self.k}: {msg}" if msg != str(e) else
                           f"law {self.name}: step {self.k} (t = {t:.6g} s): {msg}") from None
        except Exception as e:
            raise LawError(f"law {self.name}: step {self.k} (t = {t:.6g} s) raised "
                           f"{type(e).__name__}: {_line(e)}") from None
        u = self._checked(u, t)
        self.saturated = hw.amplifier_step(p, h, u, self.currents)
        self.k += 1
        self.step_index += 1
        return self.currents

    def step(self, d: np.ndarray) -> np.ndarray:
        if np.shape(d) != (self.n_axes,):
            raise ValueError(f"controller expects {self.n_axes} displacements, got shape {np.shape(d)}")
        return self.step_shared(np.array(d, dtype=np.float64)).copy()

    def _checked(self, u, t) -> np.ndarray:
        if not (isinstance(u, np.ndarray) and u.dtype == np.float64 and u.shape == (self.n_axes,)
                and u.flags.c_contiguous):
            try:
                u = np.asarray(u, dtype=np.float64)
            except (TypeError, ValueError) as e:
                raise LawError(f"law {self.name}: step {self.k} (t = {t:.6g} s) returned "
                               f"{type(u).__name__}, not {self.n_axes} numbers: {_line(e)}") from None
            if u.shape != (self.n_axes,):
                raise LawError(f"law {self.name}: step {self.k} (t = {t:.6g} s) returned shape "
                               f"{u.shape}, expected ({self.n_axes},) (one amplifier input per axis)")
            u = np.ascontiguousarray(u)
        a = hw.first_nonfinite(u)
        if a >= 0:
            raise LawError(f"law {self.name}: step {self.k} (t = {t:.6g} s) returned a non-finite "
                           f"input for axis {self.meta.axes[a]}: {u[a]}")
        return u

    def close(self) -> None:
        close = getattr(self.law, "close", None)
        if close is not None:
            close()


def _line(e: BaseException) -> str:
    s = str(e).strip().splitlines()
    return s[0][:300] if s else ""
