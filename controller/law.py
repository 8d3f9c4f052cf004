"""The control-law interface: what a law is given and what it must give back.

A law maps what an ADC would read to what a DAC would drive, once per controller period::

    law = CLASS(meta)            # meta: LawMeta (axes, period, operating point, the scene's table)
    u = law.step(t, y)           # y: sensor outputs (n_axes, float64), t: simulation time (s)
    law.reset()                  # optional: back to the state at t = 0 (a controller restart)

``y`` is the displacement of each sensor axis *through the scene's sensor model* (its gain and
lag: volts for the paper's scenes), in the order of :attr:`LawMeta.axes` (RunMeta's
``axis_names``); ``u`` is the amplifier input of each axis (the scene's amplifier model, its gain,
lag, limits, slew and the delay, turns it into coil currents).  A scene whose sensor and
amplifier are unity gain and lag-free hands the law metres and takes amperes.  ``step`` may
return a fresh array or write into one of its own; the testbench copies what it keeps.

The testbench keeps the hardware around every law (:mod:`ambhil.controller.hardware`,
:class:`ambhil.controller.law_runner.LawRunner`): the built-in PID
(:class:`ambhil.controller.pid_law.PIDLaw`) and a user's law meet the same plant.  Laws come as
a Python class (``FILE.py:CLASS``), a shared library of the C ABI (``include/ambhil_law.h``), an
FMU (FMI 2.0 / 3.0 co-simulation) or an LTI system of the scene (``[controller] kind``);
:func:`ambhil.controller.law_loader.law_factory` tells them apart.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np

from .params import Amplifier, ControllerParams, Sensor


class LawError(RuntimeError):
    """A law that could not be loaded, or that failed at a step; the message is one line that
    names the law (and the step)."""


@dataclass(frozen=True)
class LawMeta:
    """What a law is told when it is made.

    ``axes``: the sensor/coil axis names in the order of ``y`` and ``u`` (``"A-x"``, ...);
    ``period``: the controller period (s); ``i_op``: the operating-point coil current of each axis
    (A), what the loop must deliver at zero displacement; ``u_op``: the amplifier input that holds
    ``i_op`` in steady state (``i_op / amplifier gain``), where a law with an integrator starts;
    ``controller``: the scene's ``[controller]`` table as written (gains and all);
    ``params``: its ``[controller.params]`` sub-table, the law's own parameters;
    ``sensor`` and ``amplifier``: the hardware models around the law;
    ``base_dir``: the folder the law was named relative to (the scene's);
    ``discrete``: the built-in PID of the scene's gains discretised at this period
    (:func:`ambhil.controller.discrete.describe`: each block's ``a, b, c, d``, ``kp``, the limits,
    ``anti_windup``), what a port of the built-in law (examples/c_law) starts from."""
    axes: tuple[str, ...]
    period: float
    i_op: tuple[float, ...]
    u_op: tuple[float, ...]
    controller: dict = field(default_factory=dict)
    params: dict = field(default_factory=dict)
    sensor: Sensor = field(default_factory=Sensor)
    amplifier: Amplifier = field(default_factory=Amplifier)
    base_dir: str = "."
    discrete: dict = field(default_factory=dict)

    @property
    def n_axes(self) -> int:
        return len(self.axes)

    @property
    def sample_rate(self) -> float:
        return 1.0 / self.period

    def params_json(self) -> str:
        """The law's parameters for a C law (``ambhil_law_new``): one JSON object with the
        ``[controller]`` table (``controller``), its ``params`` sub-table, the operating point
        (``i_op``, ``u_op``) and the hardware's limits (``input_limit``: the amplifier input range,
        ``current_limit``), infinite limits as ``null``."""
        fin = lambda v: float(v) if math.isfinite(v) else None  # noqa: E731
        a = self.amplifier
        return json.dumps({"controller": _plain(self.controller), "params": _plain(self.params),
                           "axes": list(self.axes), "period_s": self.period,
                           "i_op": list(self.i_op), "u_op": list(self.u_op),
                           "input_limit": fin(a.current_limit / a.gain),
                           "current_limit": fin(a.current_limit),
                           "discrete": _plain(self.discrete)}, allow_nan=False)

    @classmethod
    def of(cls, config: ControllerParams, i_op, axes=None, period: float | None = None,
           u_op=None, base_dir: str = ".") -> "LawMeta":
        """The meta of a scene's controller: ``config`` with the operating currents ``i_op``
        (``u_op``: the amplifier inputs that hold them, default ``i_op / gain``).  ``controller``
        holds the PID keys of ``config`` under the table as written."""
        i_op = tuple(float(v) for v in np.atleast_1d(np.asarray(i_op, float)))
        axes = tuple(axes) if axes is not None else tuple(f"axis{k}" for k in range(len(i_op)))
        if len(axes) != len(i_op):
            raise ValueError(f"{len(axes)} axis names for {len(i_op)} operating currents")
        g = config.amplifier.gain
        u_op = tuple(v / g for v in i_op) if u_op is None else tuple(float(v) for v in u_op)
        table = {k: getattr(config, k) for k in PID_KEYS}
        table.update(config.table)
        from . import discrete as dc
        import dataclasses
        period = float(period or config.period)
        p = dc.discretise(dataclasses.replace(config, delay_samples=0), 1.0 / period)
        return cls(axes=axes, period=period, i_op=i_op, u_op=u_op,
                   controller=table, params=dict(config.law_params), sensor=config.sensor,
                   amplifier=config.amplifier, base_dir=base_dir, discrete=dc.describe(p, i_op))


#: the built-in law's keys of [controller], always in LawMeta.controller
PID_KEYS = ("kp", "ki", "kd", "derivative_filter", "sample_rate", "discretisation",
            "delay_samples", "anti_windup")


def _plain(d):
    """A TOML table as JSON-able data (infinite floats as None)."""
    if isinstance(d, dict):
        return {str(k): _plain(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_plain(v) for v in d]
    if isinstance(d, float) and not math.isfinite(d):
        return None
    return d
