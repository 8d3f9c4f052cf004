"""Contact events of the auxiliary bearings, read from the plant's state after every controller period.

The plant step keeps, per auxiliary-bearing station, the current or last contact event in its state
vector (``plant.integrator.C_*``: start and end time, impact and separation speed, peak force, the
energy lost).  :class:`ContactLog` turns those into a list of start / end events, the same in
``simulate`` and in the plant process (which publishes each as an event and the recorder keeps it):

    start: {"kind": "contact", "bearing": "A", "phase": "start", "t_s", "v0_m_s" (impact normal speed), "merged"}
    end:   {..., "phase": "end", "t_s", "start_s", "v0_m_s", "v_out_m_s" (separation speed),
            "restitution" (v_out / v0), "peak_force_N", "max_penetration_m", "impulse_N_s" (the normal
            force's impulse: the momentum the bearing took), "energy_J" (lost to friction and contact
            damping), "merged"}

Resolution: one controller period.  When more than one event started and ended within one period
(a rotor chattering on its bearing faster than the controller samples) the events are merged into
one start/end pair whose figures are the last event's and ``merged`` says how many there were.
"""
from __future__ import annotations

import numpy as np

from . import integrator as ig


class ContactLog:
    """The contact events of a run (``events``) and their summary per bearing (:meth:`summary`)."""

    def __init__(self, names, period: float):
        self.names = tuple(names)
        self.period = float(period)
        self.reset()

    def reset(self) -> None:
        m = len(self.names)
        self.events: list[dict] = []
        self._nev = np.zeros(m)
        self._open = [False] * m
        self._last = np.zeros((m, ig.NC))
        self._last[:, ig.C_TE] = -1.0
        self._imp0 = np.zeros(m)

    def update(self, step: int, c: np.ndarray) -> list[dict]:
        """The events that started or ended during the period that ended at controller step
        ``step`` (``c``: the plant's (m, NC) contact state now)."""
        new: list[dict] = []
        for j, name in enumerate(self.names):
            row = c[j]
            n = row[ig.C_NEV]
            started = int(round(n - self._nev[j]))
            in_contact = row[ig.C_V0] > 0.0
            if started > 0:
                if self._open[j]:       # the open event ended within this period, and others started
                    new.append(self._end(name, row, merged=started, closed_before=True,
                                         t_end=float(row[ig.C_TE]) if started == 1 and in_contact else float("nan")))
                new.append(self._start(name, row, merged=started))
                self._open[j] = True
                self._imp0[j] = self._last[j, ig.C_IMP]     # the normal impulse before this event
            if self._open[j] and not in_contact and (started > 0 or row[ig.C_TE] != self._last[j, ig.C_TE]):
                new.append(self._end(name, row, merged=max(started, 1)))
                self._open[j] = False
            self._nev[j] = n
            self._last[j] = row
        self.events.extend(new)
        return new

    def _start(self, name, row, merged) -> dict:
        return {"kind": "contact", "bearing": name, "phase": "start", "t_s": float(row[ig.C_TS]),
                "v0_m_s": float(row[ig.C_EV0]), "merged": int(merged)}

    def _end(self, name, row, merged, closed_before=False, t_end=float("nan")) -> dict:
        j = self.names.index(name)
        if closed_before:   # the event that was open: its figures were last seen a period ago
            row = self._last[j]
        else:
            t_end = float(row[ig.C_TE])
        v0, vout = float(row[ig.C_EV0]), float(row[ig.C_EVOUT])
        return {"kind": "contact", "bearing": name, "phase": "end", "t_s": t_end, "start_s": float(row[ig.C_TS]),
                "v0_m_s": v0, "v_out_m_s": vout, "restitution": vout / v0 if v0 > 0 else float("nan"),
                "peak_force_N": float(row[ig.C_EPEAK]), "max_penetration_m": float(row[ig.C_EDMAX]),
                "impulse_N_s": float(row[ig.C_IMP] - self._imp0[j]),
                "energy_J": float(row[ig.C_EE]), "merged": int(merged)}

    def summary(self, c: np.ndarray) -> dict:
        """Per bearing: events, peak force, max penetration, friction and damping energy, normal
        impulse and the race speed, from the plant's contact state ``c`` at the end of a run."""
        return {name: {"events": int(c[j, ig.C_NEV]), "peak_force_N": float(c[j, ig.C_PEAK]),
                       "max_penetration_m": float(c[j, ig.C_DMAX]), "friction_energy_J": float(c[j, ig.C_EF]),
                       "damping_energy_J": float(c[j, ig.C_ED]), "impulse_N_s": float(c[j, ig.C_IMP]),
                       "race_speed_end": float(c[j, ig.C_W]), "in_contact_at_end": bool(c[j, ig.C_V0] > 0)}
                for j, name in enumerate(self.names)}
