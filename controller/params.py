"""The controller's parameters: the per-axis signal chain of the paper's eq. 7, sensor ->
PID -> amplifier, and how it is sampled.  The scene loader (``loop/scene.py``) fills them from
the ``[controller]``, ``[sensor]`` and ``[amplifier]`` tables; a controller is given these, never
a plant or a scene.

The sensor and amplifier lags are part of the controller process (emulated in its discrete
state), the sensor *position* is a plant output.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

DISCRETISATIONS = ("tustin", "zoh")
KINDS = ("pid", "statespace", "transfer")   # [controller] kind: the built-in PID, or an LTI law


@dataclass(frozen=True)
class Sensor:
    gain: float = 1.0  # A_s, V/m (or any unit the controller gains are written in)
    time_constant: float = 0.0  # T_s, s; 0 = no lag


@dataclass(frozen=True)
class Amplifier:
    gain: float = 1.0  # alpha_a, A/V
    time_constant: float = 0.0  # T_a, s; 0 = no lag
    current_limit: float = math.inf  # |i| limit on the control current, A
    slew_rate: float = math.inf  # |di/dt| limit on the coil current, A/s (inf = none)


@dataclass(frozen=True)
class ControllerParams:
    kp: float
    ki: float = 0.0
    kd: float = 0.0
    derivative_filter: float = 0.0  # T_d, s
    sample_rate: float = 10_000.0  # Hz, the loop's one sample rate (its period is also the plant's input period)
    discretisation: str = "tustin"  # tustin | zoh
    delay_samples: int = 0
    anti_windup: bool = True
    sensor: Sensor = field(default_factory=Sensor)
    amplifier: Amplifier = field(default_factory=Amplifier)
    kind: str = "pid"            # pid | statespace | transfer (controller/law_lti.py)
    law: str | None = None       # a black-box law: "FILE.py:CLASS", "FILE.so", "FILE.fmu" (absolute)
    # the scene's [controller] table as written, and its [controller.params] sub-table (the
    # law's own parameters, controller/law.py LawMeta); not compared
    table: dict = field(default_factory=dict, compare=False)
    law_params: dict = field(default_factory=dict, compare=False)
    lti: dict = field(default_factory=dict, compare=False)   # kind statespace / transfer: its tables

    @property
    def period(self) -> float:
        """The sample period (s), derived: ``1 / sample_rate``."""
        return 1.0 / self.sample_rate
