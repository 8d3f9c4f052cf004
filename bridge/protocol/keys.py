"""Key expressions of a run (docs/protocol.md, section 2) and the message type of each."""
from __future__ import annotations

import re
from typing import NamedTuple

_RUN_ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


class Keys(NamedTuple):
    root: str
    sensors: str
    currents: str
    events: str        # every role's events: ambhil/<run>/events/* (subscribe); publish on event_key()
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
    return Keys(r, f"{r}/plant/sensors", f"{r}/controller/currents", f"{r}/events/*", f"{r}/meta",
                f"{r}/timing", f"{r}/alive/plant", f"{r}/alive/controller", f"{r}/alive/recorder",
                f"{r}/alive/*", f"{r}/**", f"{r}/local/wake", f"{r}/record")


EVENT_ROLES = ("plant", "controller")   # the roles that put events (protocol 3); the recorder puts none


def event_key(run_id: str, role: str) -> str:
    """Where ``role`` puts its events (protocol 3): ``ambhil/<run>/events/<role>``; the replay
    tool posing as plant puts on the plant's key."""
    if role not in EVENT_ROLES:
        raise ValueError(f"no event key for role {role!r}: one of {', '.join(EVENT_ROLES)}")
    return f"{keys(run_id).root}/events/{role}"


def pair_key(run_id: str, role: str, pid: bytes | None = None) -> str:
    """The pairing queryable of ``role``'s peer ``pid`` (``*``: all), docs/protocol.md 5.3."""
    return f"{keys(run_id).root}/pair/{role}/{pid.hex() if pid is not None else '*'}"


def topic_of(key: str) -> str | None:
    """The topic of a run's key expression: what follows ``ambhil/<run>/``."""
    parts = str(key).split("/", 2)
    if len(parts) < 3 or parts[0] != "ambhil":
        return None
    return parts[2]


# key suffix (after ambhil/<run>/) -> message type
TOPIC_TYPES = {"plant/sensors": "SensorSample", "controller/currents": "CurrentCommand",
               "events": "Event", "events/plant": "Event", "events/controller": "Event",
               "meta": "RunMeta", "timing": "Timing"}


def message_type_for_key(key: str) -> str | None:
    t = topic_of(key)
    return None if t is None else TOPIC_TYPES.get(t)
