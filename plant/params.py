"""The plant's parameters: the scene tables that describe the rotor, its bearings and how it is
integrated, as frozen dataclasses.  The scene loader (``loop/scene.py``) fills them from a TOML
file; anything else (a test, a study, another front end) may build them directly.

Units are SI throughout (m, kg, s, A, N, Pa, rad, rad/s), except ``pole_angle`` in degrees.
Node indices here are 0-based (the scene file is 1-based).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the kernel module imports numba: not needed to describe a scene
    from .auxiliary_bearing import AuxiliaryBearing

MU0 = 4e-7 * math.pi
RUNGS = ("rigid", "modal", "full", "ancf")
SCHEMES = ("bdf1", "bdf2", "trapezoidal", "generalized-alpha", "zoh")


class ParameterError(ValueError):
    """A user error in the plant's parameters: the message is one line, fit to print."""


@dataclass(frozen=True)
class Section:
    length: float
    outer_diameter: float
    inner_diameter: float
    elements: int
    youngs_modulus: float
    shear_modulus: float
    density: float


@dataclass(frozen=True)
class Disc:
    name: str
    node: int  # 0-based
    mass: float
    polar_inertia: float
    diametral_inertia: float


@dataclass(frozen=True)
class RadialAMB:
    name: str
    node: int  # 0-based actuator node
    sensor_node: int  # 0-based; equals node when collocated (the sensor is a plant output)
    gap: float
    bias_current: float
    turns: float
    pole_area: float
    pole_angle: float  # degrees (half angle between the pole pair and the axis)
    misalignment: tuple[float, float]  # stator offset (x, y) in m
    # datasheet coefficients (k_s N/m, negative; k_i N/A) at the centred operating point, given
    # instead of the coil (turns, pole_area, pole_angle are then unused and bias_current is the
    # equivalent bias k_x s0 / k_i); None: the coil parameters define the bearing
    datasheet: tuple[float, float] | None = None
    # m, radial clearance of the auxiliary (touchdown) bearing beside this AMB: the rotor lands on
    # it before it reaches the stator, so it is smaller than ``gap``; orbits at this AMB (and the
    # ISO 14839-2 zones at its sensor node) are judged against it.  None: not given (``clearance``
    # then assumes half the magnetic gap)
    touchdown_clearance: float | None = None
    # the auxiliary bearing at this AMB's actuator node, concentric with its stator (scene
    # ``[amb.auxiliary]``): the contact law the rotor meets at ``touchdown_clearance`` (its
    # ``clearance`` is that same value).  None: no contact model (the run ends at the magnetic gap)
    auxiliary: AuxiliaryBearing | None = None

    @property
    def clearance(self) -> float:
        """The touchdown clearance (m) every orbit, zone and criterion is judged against:
        ``touchdown_clearance``, or half the magnetic gap when it is not given (an assumption)."""
        return float(self.touchdown_clearance) if self.touchdown_clearance is not None else 0.5 * self.gap

    @property
    def force_constant(self) -> float:
        """k = mu0 N^2 A cos(alpha), the constant of the force law (N m^2 / A^2); from datasheet
        coefficients the equivalent k = k_i^2 s0 / k_x (k_x = -k_s), which with the equivalent
        bias i0 = k_x s0 / k_i gives back k_x = k i0^2 / s0^3 and k_i = k i0 / s0^2."""
        if self.datasheet is not None:
            ks, ki = self.datasheet
            return ki * ki * self.gap / (-ks)
        return MU0 * self.turns**2 * self.pole_area * math.cos(math.radians(self.pole_angle))


@dataclass(frozen=True)
class AxialAMB:
    name: str
    node: int
    gap: float
    bias_current: float
    turns: float
    pole_area: float

    @property
    def force_constant(self) -> float:
        return MU0 * self.turns**2 * self.pole_area


@dataclass(frozen=True)
class Unbalance:
    node: int
    magnitude: float  # kg m
    phase: float  # rad


@dataclass(frozen=True)
class Speed:
    value: float | None = None  # rad/s, constant speed
    start: float | None = None  # rad/s, range for sweeps and run-ups
    stop: float | None = None
    points: int = 400

    @property
    def nominal(self) -> float:
        return self.value if self.value is not None else float(self.stop)

    @property
    def sweep(self) -> tuple[float, float, int]:
        if self.start is not None:
            return float(self.start), float(self.stop), int(self.points)
        return 0.0, 4000.0, int(self.points)


@dataclass(frozen=True)
class Damping:
    mass_proportional: float = 0.0  # alpha, 1/s
    stiffness_proportional: float = 0.0  # beta, s


@dataclass(frozen=True)
class ModelOptions:
    rung: str = "full"  # rigid | modal | full | ancf
    gravity: float = 0.0  # m/s^2 along -y (every rung: the AMBs carry the weight at the operating point)
    beam: str = "euler-bernoulli"  # euler-bernoulli | timoshenko
    # rotary inertia of the shaft sections (rho I per length) in the beam mass matrix; off gives
    # the plain Euler-Bernoulli beam of other codes (discs keep their diametral inertia)
    rotary_inertia: bool = True
    # Hz, highest fixed-interface mode kept by the modal rung; None: from the input rate
    # (reduction.default_cutoff: the loop's modes up to and beyond Nyquist stay right)
    modal_cutoff: float | None = None


@dataclass(frozen=True)
class Simulation:
    """Time-domain defaults (plant/step.py, loop/simulation.py); every key may be overridden."""
    integrator: str = "bdf1"  # bdf1 | bdf2 | trapezoidal | generalized-alpha | zoh
    step: float | None = None  # plant step h, s; None = the input period (Model.period)
    rho_inf: float = 0.8  # generalized-alpha spectral radius at infinity
    duration: float = 0.5  # s
    force_law: str = "linear"  # linear | nonlinear
    speed: float | None = None  # rad/s, constant speed (default: [speed] value, else 0)
    run_up: tuple[float, float] | None = None  # (start, stop) rad/s
    run_up_time: tuple[float, float] = (0.0, 1.0)  # (t0, t1) s of the linear ramp
    newton_iterations: int = 10
    newton_tol: float = 1e-10
    output_nodes: tuple[int, ...] = ()  # 1-based nodes whose orbits are recorded
    record_every: int = 1


@dataclass(frozen=True)
class PlantSpec:
    """Everything the plant needs: the rotor, its bearings and sensors, unbalance, damping, the
    speed and the time-domain settings."""
    name: str
    path: str
    model: ModelOptions
    sections: tuple[Section, ...]
    discs: tuple[Disc, ...]
    ambs: tuple[RadialAMB, ...]
    axial_amb: AxialAMB | None
    unbalances: tuple[Unbalance, ...]
    speed: Speed
    damping: Damping
    node_z: tuple[float, ...] = field(repr=False, default=())
    simulation: Simulation = field(default_factory=Simulation)

    @property
    def n_nodes(self) -> int:
        return len(self.node_z)

    @property
    def length(self) -> float:
        return self.node_z[-1]

    def amb(self, name: str) -> RadialAMB:
        for a in self.ambs:
            if a.name == name:
                return a
        raise ParameterError(f"{self.path}: no [[amb]] named {name!r} (have {', '.join(a.name for a in self.ambs)})")

    def with_changes(self, **changes: Any) -> "PlantSpec":
        """A copy with some fields replaced (for sweeps and studies)."""
        return replace(self, **changes)
