"""Point-mass (Jeffcott) rotor dropped into one auxiliary bearing: the validation case of the contact law.

A mass ``m`` in the plane of one bearing station, its centre at ``(x, y)`` from the bearing centre,
gravity ``g`` along ``-y``, the AMBs off (their force is zero: a drop; ``external`` may add a force,
e.g. AMBs coming back), optionally held by a shaft stiffness ``k_shaft`` and damping ``c_shaft``
towards the centre (the Jeffcott shaft).  Spin ``Omega`` about ``+z``: prescribed (constant, a
drive holds it and its work is booked) or a state with polar inertia ``J_p``, braked by the
friction torque and ``spin_drag``.  The race is held (``race_inertia`` None) or a body that the
friction spins up and its drag brakes:

    m x'' = f_x - k_shaft x - c_shaft x' + f_ext,x          J_p Omega' = R_s F_t - spin_drag Omega
    m y'' = f_y - k_shaft y - c_shaft y' + f_ext,y - m g     J_i w'     = -R_i F_t - race_drag w

with ``(f_x, f_y, F_t)`` from :func:`ambhil.plant.auxiliary_bearing.contact`.

Integration: scipy ``solve_ivp`` (LSODA by default, or Radau/BDF), in segments split at contact
start and end located as events of ``d = r - c = 0``: the linear law's dashpot makes the force jump
at contact start, so no step may straddle it.  Inside a contact the step is limited to the
undamped contact duration over ``steps_per_contact`` (20: the solver cannot step over a contact;
the error control sets the step below that).  Each event keeps its impact normal speed ``v0``
(the Hertz law's damping needs it).  The works of every non-conservative force are integrated as
states with the same tolerances, so ``energy + dissipated - drive/external input = initial``
checks the whole integration (:meth:`DropResult.energy_error`).  Potential energy is counted from
the bottom of the clearance (``y = -c``), so a drop from the centre starts with ``m g c``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.integrate import solve_ivp

from .auxiliary_bearing import AuxiliaryBearing, _elastic_energy, contact, race_drag_torque

# state layout
X, Y, VX, VY, OM, WR, W_CD, W_F, W_SD, W_RD, W_SP, W_IN = range(12)
N_STATE = 12
WORKS = {"contact_damping": W_CD, "friction": W_F, "shaft_damping": W_SD, "race_drag": W_RD,
         "spin_drag": W_SP}


@dataclass(frozen=True)
class PointRotor:
    mass: float  # kg
    bearing: AuxiliaryBearing
    gravity: float = 9.81  # m/s^2, along -y
    k_shaft: float = 0.0  # N/m, Jeffcott shaft stiffness to the centre
    c_shaft: float = 0.0  # N s/m
    spin: float = 0.0  # rad/s, initial (or prescribed) Omega
    polar_inertia: float | None = None  # kg m^2, J_p; None = spin prescribed (constant)
    spin_drag: float = 0.0  # N m s
    external: Callable | None = None  # (t, x, y, vx, vy) -> (fx, fy): e.g. AMB force; None = AMBs off


@dataclass
class ContactEvent:
    start: float  # s
    v0: float  # m/s, normal speed at contact start (>= 0)
    end: float = math.nan  # s (nan: still in contact at the end of the run)
    v_out: float = math.nan  # m/s, normal speed at separation (>= 0 when leaving)
    peak_force: float = 0.0  # N
    max_penetration: float = 0.0  # m
    energy_lost: float = 0.0  # J, work of contact damping and friction during the event

    @property
    def restitution(self) -> float:
        return self.v_out / self.v0 if self.v0 > 0 else math.nan


@dataclass
class DropResult:
    rotor: PointRotor
    t: np.ndarray  # solver steps (s)
    y: np.ndarray  # (N_STATE, len(t))
    events: list[ContactEvent]
    segments: list = field(repr=False, default_factory=list)  # (t0, t1, dense OdeSolution, v0)

    def sample(self, t) -> np.ndarray:
        """State at the times t (dense output of the segment that holds each time)."""
        t = np.atleast_1d(np.asarray(t, float))
        out = np.empty((N_STATE, t.size))
        starts = np.array([s[0] for s in self.segments])
        k = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(starts) - 1)
        for j in np.unique(k):
            m = k == j
            out[:, m] = self.segments[j][2](t[m])
        return out

    def energy(self, y=None) -> np.ndarray:
        """Mechanical energy (J) at each column of y (default: the solver steps)."""
        r = self.rotor
        y = self.y if y is None else y
        p = r.bearing.array()
        c = r.bearing.clearance
        rr = np.hypot(y[X], y[Y])
        E = 0.5 * r.mass * (y[VX] ** 2 + y[VY] ** 2) + r.mass * r.gravity * (y[Y] + c) \
            + 0.5 * r.k_shaft * rr ** 2 + np.array([_elastic_energy(d, p) for d in rr - c])
        if r.polar_inertia is not None:
            E = E + 0.5 * r.polar_inertia * y[OM] ** 2
        if r.bearing.race_inertia is not None:
            E = E + 0.5 * r.bearing.race_inertia * y[WR] ** 2
        return E

    def dissipated(self, y=None) -> np.ndarray:
        y = self.y if y is None else y
        return sum(y[i] for i in WORKS.values())

    def energy_error(self) -> float:
        """max |E + dissipated - input - E0| / E0 over the solver steps (input: the drive of a
        prescribed spin and the external force)."""
        bal = self.energy() + self.dissipated() - self.y[W_IN]
        e0 = bal[0]
        return float(np.max(np.abs(bal - e0)) / abs(e0))

    def penetration(self, y=None) -> np.ndarray:
        y = self.y if y is None else y
        return np.hypot(y[X], y[Y]) - self.rotor.bearing.clearance


def _rhs_factory(rotor: PointRotor, p: np.ndarray, v0_box: list):
    m, g, ks, cs = rotor.mass, rotor.gravity, rotor.k_shaft, rotor.c_shaft
    jp, js = rotor.polar_inertia, rotor.spin_drag
    ji = rotor.bearing.race_inertia
    ext = rotor.external

    def rhs(t, s):
        x, y, vx, vy, om, wr = s[X], s[Y], s[VX], s[VY], s[OM], s[WR]
        fx, fy, fn, ft, d, tsh, tra, pf, pd = contact(x, y, vx, vy, om, wr, v0_box[0], p)
        ex, ey = ext(t, x, y, vx, vy) if ext is not None else (0.0, 0.0)
        ds = np.zeros(N_STATE)
        ds[X], ds[Y] = vx, vy
        ds[VX] = (fx - ks * x - cs * vx + ex) / m
        ds[VY] = (fy - ks * y - cs * vy + ey) / m - g
        if jp is None:
            ds[W_IN] = -tsh * om  # the drive holds Omega against the friction torque
        else:
            ds[OM] = (tsh - js * om) / jp
            ds[W_SP] = js * om * om
        if ji is not None:
            tdrag = race_drag_torque(wr, p)
            ds[WR] = (tra + tdrag) / ji
            ds[W_RD] = -tdrag * wr
        ds[W_CD], ds[W_F], ds[W_SD] = pd, pf, cs * (vx * vx + vy * vy)
        ds[W_IN] += ex * vx + ey * vy
        return ds
    return rhs


def drop(rotor: PointRotor, t_end: float, x0=(0.0, 0.0, 0.0, 0.0), race_speed: float = 0.0,
         rtol: float = 1e-8, method: str = "LSODA", steps_per_contact: int = 20,
         max_segments: int = 200_000) -> DropResult:
    """Integrate the rotor from ``x0 = (x, y, vx, vy)`` (AMBs off at t = 0) to ``t_end``."""
    b = rotor.bearing.validate("bearing")
    p = b.array()
    c = b.clearance
    s = np.zeros(N_STATE)
    s[:4], s[OM], s[WR] = x0, rotor.spin, race_speed if b.race_inertia is not None else 0.0
    v_ref = max(math.sqrt(2 * rotor.gravity * c), math.hypot(x0[2], x0[3]), 1e-3)
    om_ref = max(abs(rotor.spin), 1.0)
    e_ref = rotor.mass * (rotor.gravity * c + 0.5 * v_ref ** 2)
    atol = rtol * np.array([c, c, v_ref, v_ref, om_ref, om_ref] + [e_ref] * 6)
    v0_box = [0.0]
    rhs = _rhs_factory(rotor, p, v0_box)

    def gap(t, st):
        return math.hypot(st[X], st[Y]) - c

    def normal_speed(st):
        r = math.hypot(st[X], st[Y])
        return (st[X] * st[VX] + st[Y] * st[VY]) / r if r > 0 else 0.0

    in_contact = gap(0.0, s) > 0 or (gap(0.0, s) == 0 and normal_speed(s) > 0)
    events: list[ContactEvent] = []
    if in_contact:
        v0_box[0] = max(normal_speed(s), 0.0)
        events.append(ContactEvent(start=0.0, v0=v0_box[0]))
    t, ts, ys, segs = 0.0, [np.array([0.0])], [s[:, None]], []
    for _ in range(max_segments):
        if t >= t_end:
            break
        gap.terminal = True
        gap.direction = -1.0 if in_contact else 1.0
        max_step = b.contact_time(rotor.mass, v0_box[0]) / steps_per_contact if in_contact else np.inf
        sol = solve_ivp(rhs, (t, t_end), s, method=method, rtol=rtol, atol=atol, events=gap,
                        dense_output=True, max_step=max_step)
        if sol.status < 0:
            raise RuntimeError(f"integration failed at t = {t:g} s: {sol.message}")
        t1 = float(sol.t[-1])
        segs.append((t, t1, sol.sol, v0_box[0]))
        ts.append(sol.t[1:])
        ys.append(sol.y[:, 1:])
        if in_contact:
            _close(events[-1], sol, p, v0_box[0], t, t1)
        if sol.status != 1:
            break
        t, s = t1, sol.y[:, -1].copy()
        in_contact = not in_contact
        if in_contact:
            v0_box[0] = max(normal_speed(s), 0.0)
            events.append(ContactEvent(start=t, v0=v0_box[0]))
        else:
            events[-1].end, events[-1].v_out = t, max(-normal_speed(s), 0.0)
    else:
        raise RuntimeError(f"more than {max_segments} contact segments before t = {t_end:g} s (chatter)")
    return DropResult(rotor, np.concatenate(ts), np.concatenate(ys, axis=1), events, segs)


def _close(ev: ContactEvent, sol, p, v0, t0, t1):
    """Peak force, max penetration and lost energy of a contact segment (dense output sampled at
    the solver steps and 8 points between each)."""
    tt = np.unique(np.concatenate([sol.t, np.linspace(t0, t1, 8 * len(sol.t) + 1)]))
    yy = sol.sol(tt)
    for j in range(tt.size):
        out = contact(yy[X, j], yy[Y, j], yy[VX, j], yy[VY, j], yy[OM, j], yy[WR, j], v0, p)
        ev.peak_force = max(ev.peak_force, out[2])
        ev.max_penetration = max(ev.max_penetration, out[4])
    ev.energy_lost += float(sol.y[W_CD, -1] - sol.y[W_CD, 0] + sol.y[W_F, -1] - sol.y[W_F, 0])


@dataclass(frozen=True)
class Whirl:
    direction: int  # +1 forward (with the spin), -1 backward, 0 none
    frequency: float  # rad/s of the orbit angle (signed: + counter-clockwise)
    ratio: float  # frequency / Omega at the end
    full_clearance: bool  # r >= c for the whole last whirl period
    name: str  # "backward whirl", "forward whirl" (full clearance) or "no full-clearance whirl"


def whirl(res: DropResult, revolutions: int = 3, samples: int = 20000) -> Whirl:
    """Whirl of the last ``revolutions`` orbit revolutions: frequency from the unwrapped orbit
    angle, direction from its sign against the spin, full-clearance when the penetration stays
    >= 0 over the last whirl period."""
    t_end = float(res.t[-1])
    tt = np.linspace(0.0, t_end, samples)
    yy = res.sample(tt)
    phi = np.unwrap(np.arctan2(yy[Y], yy[X]))
    target = 2 * math.pi * revolutions
    i0 = np.nonzero(np.abs(phi[-1] - phi) >= target)[0]
    i0 = int(i0[-1]) if i0.size else 0
    freq = float((phi[-1] - phi[i0]) / (t_end - tt[i0]))
    om = float(yy[OM, -1])
    ratio = freq / om if om != 0 else math.nan
    turned = abs(phi[-1] - phi[i0]) >= 2 * math.pi
    full = False
    if turned and freq != 0:
        tp = np.linspace(t_end - 2 * math.pi / abs(freq), t_end, 2000)
        full = bool(np.all(res.penetration(res.sample(tp)) >= 0.0))
    direction = 0 if not turned else (1 if freq * om > 0 else -1)
    name = "no full-clearance whirl" if not full else ("backward whirl" if direction < 0 else "forward whirl")
    return Whirl(direction, freq, ratio, full, name)
