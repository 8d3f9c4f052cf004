"""The recording of an in-process run (``ambhil simulate``) in the layout of a HIL run
(:mod:`ambhil.bridge.recording.layout`), so that both are viewed and compared with the same tools."""
from __future__ import annotations

import json
import math

import numpy as np

from ambhil.bridge import protocol as pr
from ambhil.bridge.process.plant_contact import event_text, summary_text
from ambhil.bridge.protocol.messages import PROTOCOL_VERSION
from ambhil.bridge.recording.layout import PROFILE
from ambhil.bridge.recording.writer import Writer


def write_simulation(path, run_id: str, res, meta: dict) -> dict:
    """The recording of an in-process run (``ambhil simulate``): the topics, schemas and stamps
    of a HIL run's (RunMeta, RUN_START, the scheduled faults' FAULT_INJECTED, the auxiliary bearings'
    contact events and summary as INFO (bridge/process/plant_contact.py; each at the step after its
    time, where the plant process publishes it), one SensorSample and one CurrentCommand per
    recorded period, RUN_END), so both are viewed and compared with the same tools.  ``res``: a
    :class:`ambhil.loop.simulation.SimResult`; sample k is ``res.y[k]`` (the
    sensors at step k x record_every), its answer ``res.i[k]``; sim time = step x period (ns,
    rounded as the plant does).  No wall times exist in process: wall-time fields are 0 and the
    MCAP publish_time equals the log time.  No Timing (there is no transport to time)."""
    from mcap.writer import CompressionType, Writer as McapWriter
    K = pr.keys(run_id)
    period_ns = int(round(res.meta["period"] * 1e9))
    every = int(res.meta.get("record_every", 1))
    n_rows = min(res.steps // every, len(res.i))          # answered samples
    steps = np.arange(n_rows, dtype=np.int64) * every
    sim = steps * period_ns
    info = dict(meta, run_id=run_id, mode="in-process", n_axes=int(res.y.shape[1]),
                period_s=res.meta["period"], rate_hz=1.0 / res.meta["period"], n_steps=int(n_rows),
                record_every=every)
    with open(path, "wb") as f:
        w = McapWriter(f, compression=CompressionType.ZSTD, chunk_size=1024 * 1024)
        w.start(profile=PROFILE, library="ambhil-simulate")
        w.add_metadata("ambhil.recorder", {"run_id": run_id, "key_prefix": K.root, "source": "ambhil simulate",
                                           "protocol_version": str(PROTOCOL_VERSION)})
        w.add_metadata("ambhil.run_meta", {"json": json.dumps(info)})
        rw = Writer(w, run_id, axis_names=info.get("axis_names"))
        rw.put(K.meta, pr.encode_meta(pr.RunMeta(info)), 0)
        evs = [pr.Event(pr.EventKind.RUN_START, json.dumps({"mode": "in-process", "n_steps": int(n_rows)}),
                        "simulate")]
        for e in res.events or []:
            evs.append(pr.Event(pr.EventKind.FAULT_INJECTED,
                                json.dumps({x: e[x] for x in ("kind", "axis", "params", "phase")}),
                                "plant", step=int(e["step"]), sim_time_ns=int(e["step"]) * period_ns))
        contact, contact_end = getattr(res, "contact", None), {}
        evs += _contact_events(contact, res.meta["period"], period_ns)
        evs[1:] = sorted(evs[1:], key=lambda e: e.step)         # stable: faults first within a step
        if contact:             # the summary before RUN_END, as the plant process sends it
            evs.append(pr.Event(pr.EventKind.INFO, summary_text(contact["summary"], len(contact["events"])),
                                "plant", step=int(res.steps), sim_time_ns=int(res.steps) * period_ns))
            contact_end = {"contact": json.dumps(json.loads(evs[-1].text)["contact_summary"], separators=(",", ":"))}
        bad = res.instability or res.fault
        end = pr.Event(pr.EventKind.RUN_END, json.dumps({"reason": "fault" if bad else "completed",
                                                         "steps": int(res.steps), "fault": bad}),
                       "simulate", step=int(res.steps), sim_time_ns=int(res.steps) * period_ns)
        ev_key = pr.event_key(run_id, "plant")    # recorded on /ambhil/events, as a HIL run's
        for k, ev in enumerate(evs):
            ev.seq = k
            rw.put(ev_key, pr.encode_event(ev), ev.sim_time_ns)
        rw.put_vectors(K.sensors, "SensorSample", steps, steps, sim, res.y[:n_rows], sim, pub=0)
        rw.put_vectors(K.currents, "CurrentCommand", steps, steps, sim, res.i[:n_rows], sim, pub=0, recv=0)
        end.seq = len(evs)
        rw.put(ev_key, pr.encode_event(end), end.sim_time_ns)
        w.add_metadata("ambhil.run_end", {"status": "failed" if bad else "completed", "fault": bad or "",
                                          "steps_planned": str(int(round(res.meta.get("duration", 0) / res.meta["period"]))),
                                          "steps_run": str(res.steps), "steps_recorded": str(n_rows),
                                          "rejected": "{}", "auth": "none", **contact_end})
        w.finish()
    return {"path": str(path), "samples": int(n_rows), "run_id": run_id}


def _contact_events(contact, period: float, period_ns: int) -> list:
    """``SimResult.contact["events"]`` as the plant process publishes them: INFO at the step that
    ends the period the event happened in (an end merged into a period without its own time: the
    step of the event before it)."""
    out, k = [], 0
    for e in (contact or {}).get("events", ()):
        t = e.get("t_s")
        if t is not None and math.isfinite(t):
            k = max(0, int(math.ceil(t / period - 1e-9)))
        out.append(pr.Event(pr.EventKind.INFO, event_text(e), "plant", step=k, sim_time_ns=k * period_ns))
    return out
