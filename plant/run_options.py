"""How to integrate a plant: :class:`RunOptions`, the choices a plant runner takes whole.

A runner (:class:`ambhil.plant.step.PlantRunner`, :class:`ambhil.plant.ancf_step.ANCFRunner`,
chosen by :func:`ambhil.plant.ancf_step.plant_runner`) integrates a model with a scheme, a step,
a spin speed or run-up, a force law, the schemes' numerical damping and Newton settings, a loop
latency and a start state.  They travel together, as one frozen :class:`RunOptions`, from the
user-facing boundary (:func:`ambhil.loop.simulation.simulate`'s keywords, the CLI's flags) to the
runner, which keeps it as ``runner.options``.

``None`` means "the scene's ``[simulation]`` default" (resolved by the runner, which knows the
model); what can be checked without the model is checked once, here: a step ``h > 0`` when given
and a latency ``>= 0`` s.  The start state ``q0``/``v0`` (arrays) is held as given: the options
compare by identity (``eq=False``), as arrays have no single truth value.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .params import ParameterError

__all__ = ["RunOptions"]


@dataclass(frozen=True, eq=False)
class RunOptions:
    """The how-to-integrate choices of a plant runner; ``None``: the scene's ``[simulation]`` default.

    ``integrator``: scheme name (``bdf1``, ``bdf2``, ``trapezoidal``, ``galpha``, ``zoh``; the
    ancf rung: its DAE schemes); ``h``: plant step (s); ``speed``: constant spin speed (rad/s);
    ``run_up = (W0, W1, T0, T1)``: speed W0 until T0, linear to W1 at T1; ``nonlinear``: the
    nonlinear force law (``True``/``"nonlinear"``) or the linearised one; ``rho_inf``:
    generalised-alpha's spectral radius at infinity; ``latency`` (s): the currents reach the coils
    that much later (``plant/latency.py``); ``q0``, ``v0``: start state (default: the operating
    point at rest); ``newton_iterations``, ``newton_tol``: the nonlinear steps' Newton limits."""

    integrator: str | None = None
    h: float | None = None
    speed: float | None = None
    run_up: tuple | None = None
    nonlinear: bool | str | None = None
    rho_inf: float | None = None
    latency: float = 0.0
    q0: np.ndarray | None = None
    v0: np.ndarray | None = None
    newton_iterations: int | None = None
    newton_tol: float | None = None

    def __post_init__(self):
        if self.h is not None and not self.h > 0:
            raise ParameterError(f"plant step h must be > 0, got {self.h!r}")
        if not self.latency >= 0:
            raise ParameterError(f"latency must be >= 0 s, got {float(self.latency)!r}")
        if self.run_up is not None:
            object.__setattr__(self, "run_up", tuple(self.run_up))
