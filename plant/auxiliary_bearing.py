"""Auxiliary (touchdown) bearing: the contact law between the shaft and the inner race.

The shaft centre sits at ``(x, y)`` relative to the bearing centre (the plane of one bearing
station; spin ``+omega`` about ``+z``).  With ``r = |(x, y)|`` and the radial clearance ``c``:

    penetration    d = r - c            (contact when d > 0)
    normal         n = (x, y) / r       (outward, from the bearing centre to the shaft centre)
    tangent        t = (-y, x) / r      (n turned by +90 deg: the direction of positive spin)
    normal rate    d' = (x vx + y vy) / r

Normal force (magnitude, acting on the shaft along ``-n``), never pulling: ``F_n = max(0, ...)``

    linear (exponent n = 1):  F_n = k_c d + c_c d'                                   (spring-dashpot)
    Hertz  (n != 1):          F_n = K d^n (1 + 3 (1 - e^2) d' / (4 v0))   (Hunt-Crossley damping with
                                                                           Lankarani-Nikravesh's factor)

``v0`` is the normal speed at the start of this contact event.  The kernel cannot know it (it sees one
instant), so the caller keeps it per contact event and passes it in; it is floored at
``impact_speed_floor`` so a grazing or resting contact (v0 -> 0) does not get an infinite damping
factor.  For the linear law it is unused.

Slip velocity of the shaft surface against the race at the contact point (derivation: the shaft's
material point there moves with ``v + omega z x (R_s n)``, whose tangential part is
``(x vy - y vx)/r + R_s omega``; the race's point ``R_i n`` moves with ``w_race R_i t``):

    v_rel = (x vy - y vx) / r + R_s omega - R_i w_race

Friction on the shaft along ``t`` (Coulomb, sign() regularised by ``tanh`` over the velocity scale
``v_s``: no stick-slip switch, so rolling is "slip below v_s"):

    F_t = -mu F_n tanh(v_rel / v_s)

Force on the shaft ``f = -F_n n + F_t t``; torque on the shaft about its axis ``R_s F_t`` (brakes a
shaft whose surface outruns the race); torque on the race ``-R_i F_t`` (the reaction at radius
R_i; the race's own drag ``-race_drag w_race`` acts whether or not there is contact, so
:func:`race_drag_torque` is separate).  Friction dissipates ``P_f = -F_t v_rel = mu F_n v_rel
tanh(v_rel/v_s) >= 0``: the power of the friction pair on shaft and race together.  The normal
dissipation is ``P_d = (F_n - F_el(d)) d'`` with ``F_el`` the spring part (``k_c d`` or ``K d^n``),
also >= 0 (the clamp only removes a pull, and then ``d' < 0``).

Left out (docs/contact.md): the support (housing) stiffness in series, the rolling elements (the race
is one rigid ring, its centre fixed), axial contact and tilt at the station, thermal growth.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numba as nb
import numpy as np

# layout of the parameter array of the kernel (AuxiliaryBearing.array())
A_C, A_K, A_N, A_CC, A_E, A_MU, A_VS, A_RS, A_RI, A_JI, A_DRAG, A_V0MIN = range(12)
A_LEN = 12


@dataclass(frozen=True)
class AuxiliaryBearing:
    """One auxiliary bearing station.  Field names are the scene keys (``auxiliary.friction``)."""
    clearance: float  # m, radial clearance c between shaft and inner race (< the magnetic gap)
    stiffness: float  # N/m (linear) or N/m^n (Hertz): k_c or K
    shaft_radius: float  # m, R_s: the journal at the station
    exponent: float = 1.0  # n: 1 = linear spring-dashpot, 1.5 = Hertz point contact, 10/9 = line contact
    damping: float | None = None  # N s/m, c_c of the linear law (None = 0); not for Hertz
    restitution: float | None = None  # e in (0, 1] of the Hertz law (None = 1, elastic); not for linear
    friction: float = 0.1  # mu, Coulomb coefficient
    slip_velocity: float = 1e-3  # m/s, v_s of the tanh regularisation of sign(v_rel)
    race_radius: float | None = None  # m, R_i (None = shaft_radius + clearance)
    race_inertia: float | None = None  # kg m^2, J_i (None = no race body: the race is held, pure sliding)
    race_drag: float = 0.0  # N m s, drag torque coefficient of the race: T = -race_drag w_race
    impact_speed_floor: float = 1e-3  # m/s, the least v0 of the Hertz damping factor (grazing contact)

    @property
    def linear(self) -> bool:
        return self.exponent == 1.0

    @property
    def race_r(self) -> float:
        return self.shaft_radius + self.clearance if self.race_radius is None else self.race_radius

    def validate(self, where: str = "auxiliary") -> "AuxiliaryBearing":
        """Raise a one-line ValueError naming ``where.key`` for the first bad value; return self.

        ``friction`` is in 0..1: measured Coulomb coefficients of steel or ceramic against a
        bearing race are about 0.05-0.6 even dry; a value above 1 is in no pairing's data and is
        nearly always a unit slip (percent), so it is refused rather than simulated."""
        def bad(key, why):
            raise ValueError(f"{where}.{key} = {getattr(self, key)!r}: {why}")

        for key, v in asdict(self).items():
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(v):
                bad(key, "must be a finite number")
        for key in ("clearance", "stiffness", "shaft_radius", "slip_velocity", "impact_speed_floor"):
            if getattr(self, key) <= 0:
                bad(key, "must be > 0")
        if not 1.0 <= self.exponent <= 2.0:
            bad("exponent", "must be in 1..2 (1 linear, 1.5 Hertz point contact, 10/9 line contact)")
        if self.damping is not None:
            if self.damping < 0:
                bad("damping", "must be >= 0 N s/m")
            if not self.linear:
                bad("damping", "is the linear law's c_c (exponent = 1); the Hertz law takes restitution")
        if self.restitution is not None:
            if not 0.0 < self.restitution <= 1.0:
                bad("restitution", "must be in (0, 1]")
            if self.linear:
                bad("restitution", "is the Hertz law's e (exponent != 1); the linear law takes damping")
        if not 0.0 <= self.friction <= 1.0:
            bad("friction", "must be in 0..1")
        if self.race_radius is not None and self.race_radius <= self.shaft_radius:
            bad("race_radius", f"must be > shaft_radius ({self.shaft_radius:g} m)")
        if self.race_inertia is not None and self.race_inertia <= 0:
            bad("race_inertia", "must be > 0 kg m^2 (leave it out for a held race)")
        if self.race_drag < 0:
            bad("race_drag", "must be >= 0 N m s")
        return self

    def array(self) -> np.ndarray:
        """The float64 parameter array of :func:`contact` (layout ``A_*``)."""
        p = np.zeros(A_LEN)
        p[A_C], p[A_K], p[A_N] = self.clearance, self.stiffness, self.exponent
        p[A_CC] = self.damping or 0.0
        p[A_E] = 1.0 if self.restitution is None else self.restitution
        p[A_MU], p[A_VS] = self.friction, self.slip_velocity
        p[A_RS], p[A_RI] = self.shaft_radius, self.race_r
        p[A_JI] = self.race_inertia or 0.0  # 0 = held race
        p[A_DRAG], p[A_V0MIN] = self.race_drag, self.impact_speed_floor
        return p

    def elastic_energy(self, d: float) -> float:
        """Energy stored in the contact spring at penetration d (J): k d^2/2 or K d^(n+1)/(n+1)."""
        return _elastic_energy(d, self.array())

    def contact_time(self, m: float, v0: float) -> float:
        """Duration (s) of an undamped impact of mass m at normal speed v0: pi sqrt(m/k) for the
        linear law; for F = K d^n, 2 (d_max/v0) I_n with d_max = ((n+1) m v0^2 / (2K))^(1/(n+1))
        and I_n = int_0^1 du / sqrt(1 - u^(n+1)) = B(1/(n+1), 1/2)/(n+1) (2.943 d_max/v0 at n = 1.5).
        The integrator's step limit inside a contact is a fraction of it."""
        if self.linear:
            return math.pi * math.sqrt(m / self.stiffness)
        from scipy.special import beta
        n = self.exponent
        v0 = max(v0, self.impact_speed_floor)
        dmax = ((n + 1) * m * v0 * v0 / (2 * self.stiffness)) ** (1 / (n + 1))
        return 2 * dmax / v0 * beta(1 / (n + 1), 0.5) / (n + 1)


@nb.njit(cache=True)
def _elastic_energy(d, p):
    if d <= 0.0:
        return 0.0
    n = p[A_N]
    return p[A_K] * d ** (n + 1.0) / (n + 1.0)


@nb.njit(cache=True)
def normal_force(x, y, vx, vy, v0, p):
    """The normal part of :func:`contact`: ``(fn, fel, d, dd, nx, ny, r)`` (normal force >= 0, its
    spring part, penetration, normal rate, outward normal, radius); fn = fel = 0 out of contact."""
    r = math.sqrt(x * x + y * y)
    d = r - p[A_C]
    if d <= 0.0 or r == 0.0:
        return 0.0, 0.0, d, 0.0, 0.0, 0.0, r
    nx, ny = x / r, y / r
    dd = nx * vx + ny * vy
    n = p[A_N]
    if n == 1.0:
        fel = p[A_K] * d
        fn = fel + p[A_CC] * dd
    else:
        fel = p[A_K] * d ** n
        e = p[A_E]
        fn = fel * (1.0 + 0.75 * (1.0 - e * e) * dd / max(v0, p[A_V0MIN]))
    if fn < 0.0:
        fn = 0.0
    return fn, fel, d, dd, nx, ny, r


@nb.njit(cache=True)
def contact(x, y, vx, vy, omega, w_race, v0, p):
    """Contact force and powers at one instant.  Returns
    ``(fx, fy, fn, ft, d, t_shaft, t_race, p_friction, p_damping)``: the force on the shaft (N),
    the normal magnitude (>= 0) and the friction along t (N), the penetration (m, may be < 0: then
    everything else is 0), the torques on shaft and race (N m), and the friction and normal
    dissipation powers (W, >= 0).  ``v0`` is this contact event's impact normal speed (Hertz law)."""
    fn, fel, d, dd, nx, ny, r = normal_force(x, y, vx, vy, v0, p)
    if d <= 0.0 or r == 0.0:
        return 0.0, 0.0, 0.0, 0.0, d, 0.0, 0.0, 0.0, 0.0
    v_rel = (x * vy - y * vx) / r + p[A_RS] * omega - p[A_RI] * w_race
    ft = -p[A_MU] * fn * math.tanh(v_rel / p[A_VS])
    fx = -fn * nx - ft * ny
    fy = -fn * ny + ft * nx
    return fx, fy, fn, ft, d, p[A_RS] * ft, -p[A_RI] * ft, -ft * v_rel, (fn - fel) * dd


@nb.njit(cache=True)
def race_speed_implicit(fn, vt, omega, w_old, h, p):
    """The race speed after a backward-Euler step h of ``J_i w' = -R_i F_t(w) - race_drag w`` with
    the normal force ``fn`` and the shaft's tangential surface speed ``vt + R_s omega`` held over
    the step (``vt = (x y' - y x')/r``); ``F_t(w) = -mu fn tanh((vt + R_s omega - R_i w)/v_s)``.
    The equation is monotone in w (one root), bracketed by the friction's bound mu fn; solved by
    Newton's method safeguarded by bisection.  A held race (race_inertia 0) stays at 0."""
    J = p[A_JI]
    if J <= 0.0:
        return 0.0
    a = J / h + p[A_DRAG]
    b = J / h * w_old
    if fn <= 0.0:
        return b / a
    tmax = p[A_RI] * p[A_MU] * fn
    lo, hi = (b - tmax) / a, (b + tmax) / a
    s0 = vt + p[A_RS] * omega
    ri, vs, mf = p[A_RI], p[A_VS], p[A_MU] * fn
    w = min(max(s0 / ri, lo), hi)
    for _ in range(60):
        th = math.tanh((s0 - ri * w) / vs)
        g = a * w - b - ri * mf * th
        if g > 0.0:
            hi = w
        else:
            lo = w
        dg = a + ri * mf * (1.0 - th * th) * ri / vs
        wn = w - g / dg
        if not lo < wn < hi:
            wn = 0.5 * (lo + hi)
        if abs(wn - w) <= 1e-14 * (abs(w) + abs(s0) / ri) or hi - lo <= 1e-15 * (abs(lo) + abs(hi)):
            return wn
        w = wn
    return w


@nb.njit(cache=True)
def race_drag_torque(w_race, p):
    """Drag torque on the race (N m), in or out of contact."""
    return -p[A_DRAG] * w_race
