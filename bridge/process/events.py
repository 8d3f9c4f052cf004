"""The one event and summary mechanism the HIL processes share.

Every process (plant, controller) reports through an :class:`EventSink` on its own key
``ambhil/<run>/events/<role>`` (each attached ``peer id || MAC``, docs/protocol.md 5.3; the
recorder keeps its events to itself): rate-limited Event messages, with FAULT / RUN_START / RUN_END kept
for the summary.  A run ends with a summary dict whose ``fault`` is None or a one-line
reason (:func:`exit_code`); a :class:`Fault` raised anywhere in a process carries that
reason, a :class:`Stop` a clean end on request.  :class:`Phase` names the states of the
process state machines (bridge/process/plant_node.py, bridge/process/controller_node.py)."""
from __future__ import annotations

import enum
import platform
import threading
import time

import numpy as np

from ambhil.bridge.process import transport as tr
from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import auth as au
from ambhil.bridge.protocol import wire


class Phase(enum.Enum):
    """States of a HIL process: STARTING -> READY -> RUNNING -> STOPPING, or -> FAULTED ->
    STOPPING from any of the first three."""
    STARTING = "starting"      # session, subscriptions, liveliness; waiting for the peers
    READY = "ready"            # peers present, run announced, first sample not yet sent
    RUNNING = "running"        # the loop
    STOPPING = "stopping"      # timing flushed, RUN_END, tokens undeclared
    FAULTED = "faulted"        # a fault ended the run (Event FAULT, plant safe state)


class Fault(Exception):
    """Ends a run with a one-line reason (``summary["fault"]``)."""


class Stop(Exception):
    """A stop request seen by a loop (the watchdog wakes it): a clean end."""


def exit_code(summary: dict) -> int:
    """0 for a clean run, 1 if the run ended with a fault."""
    return 1 if summary.get("fault") else 0


def versions() -> dict:
    """Versions of everything that shapes a run's numbers (carried in RunMeta)."""
    import zenoh  # noqa
    out = {"python": platform.python_version(), "numpy": np.__version__,
           "protocol": pr.PROTOCOL_VERSION, "wire_codec": "C" if wire.NATIVE else "python"}
    try:
        from importlib.metadata import version
        out["eclipse-zenoh"] = version("eclipse-zenoh")
        out["ambhil"] = version("ambhil")
    except Exception:
        pass
    return out


class EventSink:
    """Publishes Event messages of ``source`` on ``ambhil/<run>/events/<role>`` (``role`` =
    ``source``, the replay tool's ``replay`` on the plant's key), each attached under ``auth``
    (:class:`ambhil.bridge.protocol.auth.RunAuth`: the session key once paired, the run key
    before); a source without an event key (the recorder) publishes nothing and only keeps its
    log.  At most ``max_per_s`` per second (excess counted)."""

    def __init__(self, session, run_id: str, source: str, auth: au.RunAuth | None = None,
                 max_per_s: int = 200):
        role = "plant" if source == "replay" else source
        self.auth = auth if auth is not None else au.RunAuth(None, run_id, role, tr.peer_id(session))
        self.topic = f"events/{role}"
        self.pub = (tr.declare_publisher(session, pr.event_key(run_id, role))
                    if role in pr.EVENT_ROLES else None)
        self.source = source
        self.seq = 0
        self.max_per_s = max_per_s
        self._win = 0
        self._n_in_win = 0
        self.suppressed = 0
        self.log: list[pr.Event] = []      # FAULT / RUN_* kept for the summary
        self._lock = threading.Lock()

    def emit(self, kind: int, text: str, step: int = 0, sim_time_ns: int = 0, force=False):
        now = time.monotonic_ns()
        win = now // 1_000_000_000
        if win != self._win:
            self._win, self._n_in_win = win, 0
        if not force and self._n_in_win >= self.max_per_s:
            self.suppressed += 1
            return
        self._n_in_win += 1
        if self.suppressed and not force:
            text = f"{text} (+{self.suppressed} events suppressed)"
            self.suppressed = 0
        # seq and put under one lock: events come from the loop's thread and from zenoh's
        # (REJECTED, WARNING), and receivers reject an event whose seq is not above the last
        with self._lock:
            ev = pr.Event(kind, text[:4096], self.source, self.seq, step, sim_time_ns,
                          time.time_ns())
            self.seq += 1
            if kind in (pr.EventKind.FAULT, pr.EventKind.RUN_END, pr.EventKind.RUN_START):
                self.log.append(ev)
            if self.pub is None:
                return
            try:
                data = pr.encode_event(ev)
                self.pub.put(data, attachment=self.auth.attach(self.topic, data))
            except Exception:
                pass


class ForeignCopies:
    """The messages a process rejects as not from its paired peer (protocol §5.1), put again on
    ``ambhil/<run>/foreign/<topic>`` (e.g. ``foreign/controller/currents`` from the plant), where
    the recorder keeps them apart from the run's own stream: a hijack attempt stays visible in
    the recording.  At most ``limit`` per process and run (a flood costs the loop nothing more);
    ``copied`` / ``dropped`` count them."""

    def __init__(self, session, root: str, topic: str, limit: int = 1000,
                 auth: au.RunAuth | None = None):
        self.session, self.key, self.limit = session, f"{root}/foreign/{topic}", limit
        self.topic, self.auth = f"foreign/{topic}", auth
        self.copied = self.dropped = 0

    def __call__(self, data) -> None:
        if self.copied >= self.limit:
            self.dropped += 1
            return
        try:
            data = bytes(data)
            self.session.put(self.key, data, attachment=None if self.auth is None
                             else self.auth.attach(self.topic, data))
            self.copied += 1
        except Exception:
            self.dropped += 1
