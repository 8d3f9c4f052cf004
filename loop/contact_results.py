"""What a run with auxiliary (touchdown) bearings did at them: per bearing the contacts, peak
force, penetration, race speed, friction heat and the whirl of the shaft in the clearance
(:func:`analyse`), and how a controller lifted the rotor off them again (:func:`relevitation`).

Everything is read from ``SimResult.contact`` (spec: per record row the shaft centre ``x, y``
relative to the bearing centre, ``fn``, ``d``, ``race_speed``, the cumulative energies, and the
contact log's ``events``, which see every contact even between record rows).  Conventions as
docs/contact.md: ``d = r - c`` (contact when ``d > 0`` or ``fn > 0``), spin ``+Omega`` about
``+z``, the orbit angle ``atan2(y, x)`` grows counter-clockwise.

**Whirl.**  Bouncing and resting rotors also touch the bearing; what makes a whirl is an orbit
that goes *round* the clearance.  So: the trailing stretch of the window where the radius stays
``>= 0.9 c`` (a rotor bouncing at the bottom leaves it between bounces); whirl when the orbit
angle turns at least 2 full revolutions in it, the shaft touches the bearing in it, and it still
turns at the end (its last revolution took at most twice as long as the one before: a rotor
that whirled and came to rest on the bearing is resting).  The rate
is the least-squares slope of the unwrapped angle over the last 3 revolutions (noise averages
out; the two end points alone would carry it), its sign against the spin's gives the direction
(forward = with the spin).  Full-clearance whirl: in contact at every record row of those
revolutions.  A record too sparse to follow the orbit (median turn per row above a quarter
revolution: the angle may alias) gives no verdict.  Reference for a rolling backward whirl on a
held race: ``-R_s Omega / (R_i - R_s)`` (docs/contact.md)."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

WHIRL_RADIUS = 0.9      # the orbit whirls at the clearance: radius >= this x clearance
WHIRL_MIN_REVS = 2.0    # ... and turns at least this many revolutions there
WHIRL_REVS = 3.0        # the revolutions (the last ones) the rate is fitted over
RESTING = 0.95          # contact fraction of the window's last quarter: resting on the bearing above


@dataclass
class WhirlVerdict:
    """The whirl of the shaft in one bearing's clearance (module docstring)."""
    direction: int = 0                  # +1 forward (with the spin), -1 backward, 0 none
    name: str = "no whirl"
    frequency_hz: float = math.nan      # signed orbit-angle rate / 2 pi (+ counter-clockwise)
    ratio: float = math.nan             # orbit rate / spin speed at the end of the window
    full_clearance: bool = False        # in contact over the whole analysed revolutions
    revolutions: float = 0.0            # revolutions analysed
    t_from_s: float | None = None       # the analysed revolutions
    t_to_s: float | None = None

    def text(self) -> str:
        if not self.direction:
            return self.name
        ratio = f" = {self.ratio:+.3g} x spin" if math.isfinite(self.ratio) else " (spin 0)"
        return (f"{self.name} {self.frequency_hz:+.4g} Hz{ratio} over {self.revolutions:.1f} revolutions "
                f"from t={self.t_from_s:.4g} s")


@dataclass
class BearingContact:
    """One auxiliary bearing over the analysed window."""
    name: str
    clearance: float                    # m
    events: int = 0                     # contacts that started in the window
    first_contact_s: float | None = None
    last_contact_end_s: float | None = None
    in_contact_at_end: bool = False
    peak_force_N: float = 0.0           # normal force (record rows and the contact log's event peaks)
    t_peak_s: float | None = None
    max_penetration_m: float = 0.0
    max_radius_m: float = 0.0           # largest radius of the orbit (recorded rows)
    contact_fraction: float = 0.0       # of the window's record rows
    race_speed_end: float = 0.0         # rad/s
    friction_energy_J: float = 0.0      # in the window
    damping_energy_J: float = 0.0
    mean_friction_power_W: float = 0.0  # friction energy / window length (the heat a race takes on average)
    peak_friction_power_W: float = 0.0
    whirl: WhirlVerdict = field(default_factory=WhirlVerdict)
    whirl_episodes: list = field(default_factory=list)  # every stretch of the window that whirled (with the last)

    def lines(self) -> list[str]:
        c_um = self.clearance * 1e6
        head = f"{self.name:4s} clearance {c_um:g} um: "
        if not self.events and not self.contact_fraction:
            return [head + f"no contact (largest radius {self.max_radius_m * 1e6:.4g} um = "
                    f"{100 * self.max_radius_m / self.clearance:.1f} % of the clearance)"]
        end = ("in contact at the end" if self.in_contact_at_end
               else f"last left t={self.last_contact_end_s:.4g} s" if self.last_contact_end_s is not None else "")
        out = [head + f"{self.events} contact{'s' if self.events != 1 else ''}"
               + (f", first t={self.first_contact_s:.4g} s" if self.first_contact_s is not None else "")
               + (f", {end}" if end else "") + f"; in contact {100 * self.contact_fraction:.1f} % of the time",
               f"     peak force {force_text(self.peak_force_N)}"
               + (f" at t={self.t_peak_s:.4g} s" if self.t_peak_s is not None else "")
               + f", max penetration {self.max_penetration_m * 1e6:.3g} um; race {self.race_speed_end:.4g} rad/s "
                 f"at the end",
               f"     friction {self.friction_energy_J:.4g} J (mean {self.mean_friction_power_W:.4g} W, peak "
               f"{self.peak_friction_power_W:.4g} W), contact damping {self.damping_energy_J:.4g} J",
               f"     whirl: {self.whirl.text()}"]
        for e in self.whirl_episodes:
            if e.direction < 0 and not (self.whirl.direction and e.t_to_s >= self.whirl.t_from_s):  # not this one
                out.append(f"     earlier: {e.text()} (to t={e.t_to_s:.4g} s)")
        return out


@dataclass
class ContactReport:
    """Every auxiliary bearing of a run over ``t_from_s .. t_to_s``."""
    bearings: list
    t_from_s: float
    t_to_s: float

    @property
    def any_contact(self) -> bool:
        return any(b.events or b.contact_fraction for b in self.bearings)

    @property
    def backward_whirl(self) -> bool:
        return any(e.direction < 0 for b in self.bearings for e in [b.whirl, *b.whirl_episodes])

    def headline(self) -> str:
        """One line for a run's first block: did the rotor touch down, where, how hard."""
        hit = [b for b in self.bearings if b.events or b.contact_fraction]
        if not hit:
            return "no contact with the auxiliary bearings"
        first = min((b.first_contact_s for b in hit if b.first_contact_s is not None), default=None)
        peak = max(hit, key=lambda b: b.peak_force_N)
        return (f"TOUCHDOWN on the auxiliary bearing{'s' if len(hit) > 1 else ''} {', '.join(b.name for b in hit)}"
                + (f" from t={first:.4g} s" if first is not None else "")
                + f": peak {force_text(peak.peak_force_N)} ({peak.name})"
                + ("; BACKWARD WHIRL" if self.backward_whirl else ""))

    def lines(self) -> list[str]:
        out = [f"auxiliary bearings, t {self.t_from_s:.4g}-{self.t_to_s:.4g} s:"]
        for b in self.bearings:
            out += ["  " + s for s in b.lines()]
        return out

    def as_dict(self) -> dict:
        return {"t_from_s": self.t_from_s, "t_to_s": self.t_to_s, "any_contact": self.any_contact,
                "backward_whirl": self.backward_whirl, "bearings": [asdict(b) for b in self.bearings]}


@dataclass
class Relevitation:
    """How the rotor came off the auxiliary bearings after the AMBs came back at ``t_return_s``."""
    t_return_s: float
    time_s: float | None                # to off every bearing for good and settled (None: never)
    peak_force_N: float                 # after t_return
    backward_whirl: bool                # any bearing whirled backward after t_return
    settle_fraction: float
    held_s: float | None = None         # how long it then stayed so, to the end of the run
    last_contact_s: float | None = None

    @property
    def ok(self) -> bool:
        return self.time_s is not None and not self.backward_whirl

    def lines(self) -> list[str]:
        if self.time_s is None:
            what = "NOT re-levitated by the end of the run"
        else:
            what = (f"re-levitated in {self.time_s:.4g} s (off every auxiliary bearing, radius < "
                    f"{100 * self.settle_fraction:g} % of the clearance; held {self.held_s:.4g} s to the end)")
        return [f"re-levitation after the AMBs came back at t={self.t_return_s:.4g} s: {what}",
                f"  peak contact force after it {force_text(self.peak_force_N)}"
                + (f", last contact t={self.last_contact_s:.4g} s" if self.last_contact_s is not None else "")
                + ("; BACKWARD WHIRL after it" if self.backward_whirl else "; no backward whirl")]


def force_text(f: float) -> str:
    return f"{f / 1e3:.3g} kN" if abs(f) >= 1e3 else f"{f:.3g} N"


def in_contact(d, fn) -> np.ndarray:
    """Rows in contact: penetration >= 0 or a normal force (docs/contact.md)."""
    return (np.asarray(d) > 0.0) | (np.asarray(fn) > 0.0)


def _window(t, t_from, t_to) -> tuple[int, int]:
    """Row range [a, b) of ``t_from <= t <= t_to``."""
    a = 0 if t_from is None else int(np.searchsorted(t, t_from - 1e-12, side="left"))
    b = len(t) if t_to is None else int(np.searchsorted(t, t_to + 1e-12, side="right"))
    return a, max(a, b)


def whirl(t, x, y, contact, spin, c) -> WhirlVerdict:
    """The whirl at the end of a stretch of record rows (module docstring): ``contact`` (bool per
    row), ``spin`` (rad/s per row), ``c`` the clearance."""
    t, x, y, spin = (np.asarray(a, float) for a in (t, x, y, spin))
    contact = np.asarray(contact, bool)
    low = np.nonzero(np.hypot(x, y) < WHIRL_RADIUS * c)[0]
    i0 = int(low[-1]) + 1 if low.size else 0
    if len(t) - i0 < 4 or not contact[i0:].any():
        return _resting(t, contact)
    phi = np.unwrap(np.arctan2(y[i0:], x[i0:]))
    if abs(phi[-1] - phi[0]) < 2 * math.pi * WHIRL_MIN_REVS:
        return _resting(t, contact)
    back = [np.flatnonzero(np.abs(phi[-1] - phi) >= 2 * math.pi * k) for k in (1, 2, WHIRL_REVS)]
    t1, t2 = (t[i0 + int(b[-1])] for b in back[:2])
    if t[-1] - t1 > 2 * (t1 - t2):          # its last revolution took over twice the one before: it stopped
        return _resting(t, contact)
    j = int(back[2][-1]) if back[2].size else 0
    tt, pp = t[i0 + j:], phi[j:]
    if np.median(np.abs(np.diff(pp))) > math.pi / 2:
        return WhirlVerdict(name="whirl not resolved (record too sparse)")
    rate = float(np.polyfit(tt - tt[0], pp, 1)[0])          # rad/s
    w_end = float(spin[-1])
    ref = np.sign(np.mean(spin[i0 + j:])) or np.sign(w_end) or 1.0   # at rest: the +z spin convention
    direction = 1 if rate * ref > 0 else -1
    full = bool(contact[i0 + j:].all())
    name = ("forward" if direction > 0 else "backward") + " whirl" + (" (full clearance)" if full else "")
    return WhirlVerdict(direction, name, rate / (2 * math.pi), rate / w_end if w_end else math.nan, full,
                        abs(pp[-1] - pp[0]) / (2 * math.pi), float(tt[0]), float(tt[-1]))


def _resting(t, contact) -> WhirlVerdict:
    """No whirl: named by the contact fraction of the stretch's last quarter."""
    if not len(t):
        return WhirlVerdict()
    tail = contact[t >= t[-1] - 0.25 * (t[-1] - t[0])]
    frac = float(tail.mean()) if tail.size else 0.0
    return WhirlVerdict(name="no whirl" if frac == 0 else "resting on the bearing" if frac >= RESTING else "bouncing")


def whirl_episodes(t, x, y, contact, spin, c) -> list[WhirlVerdict]:
    """Every whirl of the rows: each stretch with the radius >= 0.9 c, up to the end of its last
    whole orbit revolution (a whirl that stopped on the bearing), analysed as :func:`whirl`."""
    at = np.hypot(x, y) >= WHIRL_RADIUS * c
    edges = np.flatnonzero(np.diff(np.concatenate([[0], at.astype(np.int8), [0]])))
    out = []
    for a, b in zip(edges[::2], edges[1::2]):
        turn = np.abs(np.unwrap(np.arctan2(y[a:b], x[a:b])) - math.atan2(y[a], x[a]))
        if turn.max() < 2 * math.pi * WHIRL_MIN_REVS:
            continue
        whole = 2 * math.pi * math.floor(turn.max() / (2 * math.pi))
        b = a + int(np.argmax(turn >= whole)) + 1              # to the end of its last whole revolution
        v = whirl(t[a:b], x[a:b], y[a:b], contact[a:b], spin[a:b], c)
        if v.direction:
            out.append(v)
    return out


def _events(cd: dict, name: str, t0: float, t1: float) -> list[dict]:
    return [e for e in cd.get("events") or () if e.get("kind", "contact") == "contact"
            and e.get("bearing") == name and t0 - 1e-12 <= float(e["t_s"]) <= t1 + 1e-12]


def _bearing(res, k: int, a: int, b: int, t0: float, t1: float) -> BearingContact:
    cd = res.contact
    t = np.asarray(res.t, float)
    name, c = str(cd["names"][k]), float(cd["clearance"][k])
    sl = slice(a, b)
    x, y = np.asarray(cd["x"])[sl, k], np.asarray(cd["y"])[sl, k]
    fn, d = np.asarray(cd["fn"])[sl, k], np.asarray(cd["d"])[sl, k]
    tw, spin = t[sl], np.asarray(res.speed, float)[sl]
    on = in_contact(d, fn)
    out = BearingContact(name, c)
    if not len(tw):
        return out
    ev = _events(cd, name, t0, t1)
    starts = [e for e in ev if e["phase"] == "start"]
    ends = [e for e in ev if e["phase"] == "end"]
    if "events" in cd and cd["events"] is not None:                    # the log sees every contact
        out.events = sum(int(e.get("merged") or 1) for e in starts)
    else:                                                               # only the record: its rising edges
        out.events = int(np.count_nonzero(on[1:] & ~on[:-1]) + (on[0] and a == 0))
    first = [float(e["t_s"]) for e in starts] + ([float(tw[on][0])] if on.any() else [])
    out.first_contact_s = min(first) if first else None
    out.in_contact_at_end = bool(on[-1])
    out.last_contact_end_s = max((float(e["t_s"]) for e in ends), default=None)
    if out.last_contact_end_s is None and on.any() and not on[-1]:      # no log: the first free row after
        out.last_contact_end_s = float(tw[np.flatnonzero(on)[-1] + 1])
    i = int(np.argmax(fn))
    out.peak_force_N, out.t_peak_s = max(float(fn[i]), 0.0), (float(tw[i]) if fn[i] > 0 else None)
    for e in ev:
        if float(e.get("peak_force_N") or 0.0) > out.peak_force_N:     # a peak between record rows
            out.peak_force_N, out.t_peak_s = float(e["peak_force_N"]), float(e["t_s"])
    out.max_penetration_m = max([0.0, float(np.max(d))] + [float(e.get("max_penetration_m") or 0.0) for e in ev])
    out.max_radius_m = float(np.max(np.hypot(x, y)))
    out.contact_fraction = float(on.mean())
    out.race_speed_end = float(np.asarray(cd["race_speed"])[b - 1, k])
    out.friction_energy_J = _gained(cd["e_friction"], k, a, b)
    out.damping_energy_J = _gained(cd["e_damping"], k, a, b)
    span = float(tw[-1] - (t[a - 1] if a > 0 else tw[0]))
    out.mean_friction_power_W = out.friction_energy_J / span if span > 0 else 0.0
    out.peak_friction_power_W = float(np.max(np.asarray(cd["friction_power"])[sl, k]))
    out.whirl = whirl(tw, x, y, on, spin, c)
    out.whirl_episodes = whirl_episodes(tw, x, y, on, spin, c)
    return out


def _gained(e, k, a, b) -> float:
    """Energy a cumulative column gained over rows [a, b): from the row before the window."""
    e = np.asarray(e)
    return float(e[b - 1, k] - (e[a - 1, k] if a > 0 else 0.0))


def analyse(res, t_from: float | None = None, t_to: float | None = None) -> ContactReport:
    """Per auxiliary bearing of ``res`` (a SimResult with ``contact``), over ``t_from .. t_to``
    (default: the whole run): the figures of :class:`BearingContact`."""
    cd = res.contact
    if cd is None:
        raise ValueError("this run has no auxiliary bearings (SimResult.contact is None)")
    t = np.asarray(res.t, float)
    a, b = _window(t, t_from, t_to)
    t0 = float(t[a]) if b > a else float(t_from or 0.0)
    t1 = float(t[b - 1]) if b > a else float(t_to if t_to is not None else t0)
    t0 = t0 if t_from is None else min(t0, float(t_from))
    return ContactReport([_bearing(res, k, a, b, t0, t1) for k in range(len(cd["names"]))], t0, t1)


def relevitation(res, t_return: float, settle_fraction: float = 0.3) -> Relevitation:
    """After the AMBs came back at ``t_return``: the time until the shaft is off every auxiliary
    bearing for good (no contact in the record or the contact log afterwards) and its radius
    stays below ``settle_fraction`` x clearance at every bearing to the end of the run (None if
    that never happens, or the run ends in contact); the peak contact force after ``t_return``;
    whether any bearing whirled backward after it."""
    cd = res.contact
    t = np.asarray(res.t, float)
    a, b = _window(t, t_return, None)
    rep = analyse(res, t_return, None)
    peak = max((bc.peak_force_N for bc in rep.bearings), default=0.0)
    back = rep.backward_whirl
    if b <= a:
        return Relevitation(float(t_return), None, peak, back, settle_fraction)
    done, last = float(t_return), None
    for k, bc in enumerate(rep.bearings):
        x, y = np.asarray(cd["x"])[a:b, k], np.asarray(cd["y"])[a:b, k]
        on = in_contact(np.asarray(cd["d"])[a:b, k], np.asarray(cd["fn"])[a:b, k])
        out = on | (np.hypot(x, y) >= settle_fraction * bc.clearance)
        if out[-1]:
            return Relevitation(float(t_return), None, peak, back, settle_fraction,
                                last_contact_s=float(t[b - 1]) if on[-1] else None)
        if out.any():
            done = max(done, float(t[a + np.flatnonzero(out)[-1] + 1]))
        touched = [float(t[a + i]) for i in np.flatnonzero(on)[-1:]]
        touched += [float(e["t_s"]) for e in _events(cd, bc.name, float(t_return), float(t[b - 1]))]
        if touched:
            last = max(touched + ([last] if last is not None else []))
            done = max(done, last)
    return Relevitation(float(t_return), done - float(t_return), peak, back, settle_fraction,
                        held_s=float(t[b - 1]) - done, last_contact_s=last)


def whirl_ratio_series(res, k: int, rows: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(t, ratio) of bearing ``k``: the orbit-angle rate over a sliding window of ``rows`` record
    rows (default: 1/200 of the run, at least 3) over the spin speed; NaN where the radius is below
    0.9 x clearance (no whirl there), where the orbit turns over a quarter revolution per row (the
    record cannot follow it) or the spin is 0."""
    cd = res.contact
    t = np.asarray(res.t, float)
    x, y = np.asarray(cd["x"])[:, k], np.asarray(cd["y"])[:, k]
    c = float(cd["clearance"][k])
    n = len(t)
    w = rows or max(3, n // 200)
    ratio = np.full(n, np.nan)
    if n < 2 * w + 1:
        return t, ratio
    phi = np.unwrap(np.arctan2(y, x))
    rate = (phi[2 * w:] - phi[:-2 * w]) / (t[2 * w:] - t[:-2 * w])
    spin = np.asarray(res.speed, float)[w:n - w]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio[w:n - w] = np.where(spin != 0, rate / spin, np.nan)
    r = np.hypot(x, y)
    fine = np.concatenate([[True], np.abs(np.diff(phi)) <= math.pi / 2])   # else the angle may alias
    at = np.convolve(((r >= WHIRL_RADIUS * c) & fine).astype(float), np.ones(2 * w + 1), "same") > 2 * w + 0.5
    ratio[~at] = np.nan
    return t, ratio


def return_time(res) -> float | None:
    """When the AMBs came back after the run's ``drop`` faults (the latest end; what a campaign
    judges re-levitation from): None without a drop, or when one never ends."""
    from .orbits import fault_windows
    wins = [w for w in fault_windows(res.events or res.meta.get("fault_events")) if w["kind"] == "drop"]
    if not wins or any(w["end_s"] is None for w in wins):
        return None
    return max(w["end_s"] for w in wins)
