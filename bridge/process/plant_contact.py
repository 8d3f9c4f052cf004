"""The auxiliary bearings' contact events in the plant process (issue 32, docs/hil.md "Contact and
rotor drop over zenoh").

The plant step keeps each auxiliary bearing's contact state in its state vector; after every
controller period :class:`PlantContact` reads it with the very :class:`ambhil.plant.contact_log.
ContactLog` ``simulate`` uses (same periods, same step numbers, so a lockstep run records the events
``simulate`` lists in ``SimResult.contact["events"]``) and publishes each start and end as an INFO
event at that step, before the sample of that step goes out (as a fault's start and end are).

The hook is the plant's ``advance``: :meth:`PlantContact.fresh` returns an ``advance`` that reads the
contact state after the plant's own.  The C lockstep loop (bridge/protocol/_plant_lockstep.c) calls
whatever ``advance`` it is given once per period, so the contact log runs there too without a
Python loop of its own; the integration itself is untouched (bit for bit that of ``simulate``).

Every event is published (``force``: never rate-limited away), as a fault's are: a rotor chattering
on its bearing merges within a period (``merged``), so it costs at most a few events per bearing
and period.  The event text is the ContactLog dict as compact JSON, a figure that is not a number
(``restitution`` of an impact at zero speed, the end time of events merged into one period) as
``null``, so that any JSON parser reads it.  At the end of the run :meth:`PlantContact.emit_summary`
publishes ``{"contact_summary": {bearing: {...}}}`` (ContactLog.summary) as an INFO event before
RUN_END: the recorder's ``ambhil.run_end`` keeps it (bridge/recording/run_end.py), and the plant's
summary dict carries it as ``contact``."""
from __future__ import annotations

import json
import math

from ambhil.bridge import protocol as pr
from ambhil.plant.contact_log import ContactLog

SUMMARY_KEY = "contact_summary"


def _finite(x):
    """JSON-safe: a non-finite float as None (null), containers walked."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def event_text(event: dict) -> str:
    """A ContactLog event (or any dict) as the compact JSON an event carries (NaN -> null)."""
    return json.dumps(_finite(event), separators=(",", ":"))


def summary_text(summary: dict, events_logged: int) -> str:
    """The ``{"contact_summary": {"bearings": {...}, "events_logged": n}}`` event text of a run
    (``summary``: ContactLog.summary, per bearing)."""
    return json.dumps({SUMMARY_KEY: {"bearings": _finite(summary), "events_logged": int(events_logged)}},
                      separators=(",", ":"))


def of(plant, events, period_ns: int) -> "PlantContact | None":
    """The contact log of ``plant`` (a PlantRunner, or a FaultyPlant around one) publishing on
    ``events`` (an :class:`ambhil.bridge.process.events.EventSink`); None for a plant without
    auxiliary bearings (nothing changes for it)."""
    base = getattr(plant, "runner", plant)
    names = tuple(getattr(base, "contact_names", ()) or ())
    if not names or not hasattr(base, "contact"):
        return None
    return PlantContact(plant, base, names, events, period_ns)


class PlantContact:
    """The contact events of a plant process's run (see the module docstring)."""

    def __init__(self, plant, base, names, events, period_ns: int):
        self.plant, self.base, self.ev, self.period_ns = plant, base, events, int(period_ns)
        self.log = ContactLog(names, plant.period)
        self._s = self._c = None        # the plant's state vector and its contact rows (a view)
        # a state vector kept as an attribute (PlantRunner.s): its contact rows' view is made again
        # only when it is a new array (reset); a computed one (ANCFRunner): contact read every period
        self._cached = not isinstance(getattr(type(base), "s", None), property) and hasattr(base, "s")

    def reset(self) -> None:
        self.log.reset()

    def after_period(self) -> None:
        """After a controller period: its contact starts and ends, published at the plant's step
        (the step of the sample about to be published: sim time = step x period)."""
        k = self.plant.step_index
        if not self._cached:
            self._c = self.base.contact
        elif self.base.s is not self._s:    # a new state vector (reset): a new view of its contact rows
            self._s, self._c = self.base.s, self.base.contact
        new = self.log.update(k, self._c)
        if new:
            sim_ns = k * self.period_ns
            for e in new:
                self.ev.emit(pr.EventKind.INFO, event_text(e), k, sim_ns, force=True)

    def fresh(self, advance):
        """The log emptied (the plant was reset); returns ``advance`` (any signature) followed by
        :meth:`after_period`."""
        self.reset()
        after = self.after_period

        def advance_and_log(*args):
            y = advance(*args)
            after()
            return y
        return advance_and_log

    def summary(self) -> dict:
        """Per bearing: events, peak force, max penetration, energies, impulse, race speed
        (ContactLog.summary), JSON-safe; ``events_logged``: the start/end events published."""
        return json.loads(summary_text(self.log.summary(self.base.contact), len(self.log.events)))[SUMMARY_KEY]

    def emit_summary(self, step: int, sim_ns: int) -> None:
        """The summary as an INFO event ``{"contact_summary": ...}`` (before RUN_END)."""
        self.ev.emit(pr.EventKind.INFO, summary_text(self.log.summary(self.base.contact), len(self.log.events)),
                     step, sim_ns, force=True)
