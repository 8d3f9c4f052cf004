"""Key expressions of a run (docs/protocol.md, section 2) and the message type of each."""
from __future__ import annotations

import re
from typing import NamedTuple

_RUN_ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


class Keys(NamedTuple):
    root: str
    sensors: str
    currents: str
    events: str
    meta: str
    timing: str
    alive_plant: str
    alive_controller: str
    alive_recorder: str
    alive_all: str
    all: str
    wake: str          # session-local key used to wake a blocked receiver (never leaves a process)
    record: str        # plant -> recorder: RecordBatch (bridge/protocol/record_batch.py)


def keys(run_id: str) -> Keys:
    """Key expressions of one run.  ``run_id`` must match ``[A-Za-z0-9_.-]{1,64}``."""
    if not isinstance(run_id, str) or not _RUN_ID_RE.match(run_id):
        raise ValueError(f"invalid run id {run_id!r}: use 1-64 characters of [A-Za-z0-9_.-]")
    r = f"ambhil/{run_id}"
    return Keys(r, f"{r}/plant/sensors", f"{r}/controller/currents", f"{r}/events", f"{r}/meta",
                f"{r}/timing", f"{r}/alive/plant", f"{r}/alive/controller", f"{r}/alive/recorder",
                f"{r}/alive/*", f"{r}/**", f"{r}/local/wake", f"{r}/record")


# key suffix (after ambhil/<run>/) -> message type
TOPIC_TYPES = {"plant/sensors": "SensorSample", "controller/currents": "CurrentCommand",
               "events": "Event", "meta": "RunMeta", "timing": "Timing"}


def message_type_for_key(key: str) -> str | None:
    parts = key.split("/", 2)
    if len(parts) < 3 or parts[0] != "ambhil":
        return None
    return TOPIC_TYPES.get(parts[2])
