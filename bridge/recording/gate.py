"""What the recorder lets into a run's channels (protocol 3, docs/protocol.md 5.3): only what
authenticates under the run's secret, from the run's own plant and controller.

The recorder has no pairing of its own: it learns the run's session key from the plant.  It
challenges every announced ``peer/plant/<id>`` (:func:`ambhil.bridge.process.pairing.challenge`,
in a thread of its own, retried while the id stays announced); a plant that proves the secret
is *proven*.  The run's RunMeta is the first one whose ``plant_peer_id`` is a proven plant and
whose attachment verifies under the session key derived from the RunMeta's own ``auth`` nonces
and both ids; any other RunMeta is rejected (``auth``).  From then on, every message is judged
under that key:

- events: on ``events/plant`` (source ``plant`` or ``replay``) or ``events/controller`` (source
  ``controller``), attached by that role's id of the RunMeta, with a MAC under the session key
  (``session``: may be obeyed) or, for an event sent before pairing, under the run key
  (``run``: recorded as that role's, never obeyed); the event seq strictly above the last
  accepted one of that role (else ``sequence``: a replayed event).  Anything else is rejected
  and recorded apart, on ``ambhil/<run>/foreign/events`` (MCAP ``/ambhil/foreign/events``);
- Timing and RecordBatch: from the plant, under the session key; the foreign copies that plant
  and controller put (``foreign/<topic>``): from the copier, under the session key; rejected
  ones are counted only;
- ``--source wire``: each SensorSample / CurrentCommand must end with its sender's id and MAC
  (the seal :meth:`RunAuth.peer_seal`); the others go to the foreign topics, as the plant's and
  controller's own copies would.

Messages that arrive before the RunMeta is known are held (at most :data:`HOLD_MAX`, of
:data:`HOLD_BYTES` in all; beyond that rejected, ``auth``) and judged
once it is; at the end of a recording that never learnt it, held events are judged under the
run key alone (recorded, never obeyed) and the rest rejected.  ``rejected`` counts every
rejection by reason (``auth``, ``sequence``, ``peer``).
"""
from __future__ import annotations

import queue
import struct
import threading
from collections import Counter

import zenoh

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import auth as au
from ambhil.bridge.process.pairing import challenge

HOLD_MAX = 65536                 # messages held before the RunMeta is known (more: rejected) ...
HOLD_BYTES = 64 << 20            # ... and bytes (a recorder without the key must not fill memory)
RETRY_S = 0.2                    # pause between two challenges of a still unproven plant
SESSION, RUN, FOREIGN = "session", "run", "foreign"   # how a released message was judged
EVENT_SOURCES = {"plant": ("plant", "replay"), "controller": ("controller",)}
_SEQ = struct.Struct("<Q")


class Gate:
    """The recorder's judge of run ``auth.run_id``'s traffic.  :meth:`offer` takes one received
    message and returns what may be stored now: ``(key, data, t_log, how)`` tuples, ``how`` one of
    :data:`SESSION` / :data:`RUN` (accepted; RUN: never to be obeyed) / :data:`FOREIGN` (store on
    ``key``, a foreign topic); :meth:`poll` (on every wake-up) and :meth:`finish` (at the end)
    return what held messages became.  Not thread-safe except for the liveliness callback and the
    challenger thread, which only add to :attr:`proven`."""

    def __init__(self, session, auth: au.RunAuth, wire: bool):
        self.session, self.auth, self.wire = session, auth, wire
        self.K = K = pr.keys(auth.run_id)
        self.root = K.root + "/"
        self.rejected: Counter = Counter()
        self.rejected_topics: Counter = Counter()    # the same by topic (``record``: foreign batches)
        self.proven: set[bytes] = set()
        self.announced: set[bytes] = set()
        self.ids: dict[str, bytes] | None = None     # role -> id, from the run's RunMeta
        self.meta: dict | None = None
        self.mode: str | None = None                 # RunMeta auth.mode
        self.last_seq = {"plant": -1, "controller": -1}
        self.held: list[tuple] = []
        self.held_bytes = 0
        self.meta_at: list[int] = []                 # where in ``held`` the RunMeta candidates are
        self._closed = threading.Event()
        self._wake = threading.Event()
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._sub = session.liveliness().declare_subscriber(f"{K.root}/peer/plant/*", self._peer,
                                                            history=True)
        self._thread = threading.Thread(target=self._challenger, daemon=True,
                                        name="ambhil-recorder-challenge")
        self._thread.start()

    # ------------------------------------------------------------------ proving the plant
    def _peer(self, sample) -> None:
        try:
            pid = bytes.fromhex(str(sample.key_expr).rsplit("/", 1)[-1])
        except ValueError:
            return
        if len(pid) != au.ID_LEN:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self.announced.add(pid)
            self._q.put(pid)
        else:
            self.announced.discard(pid)

    def _challenger(self) -> None:
        """Challenge each announced plant until it proves the secret, it is no longer announced,
        the run's RunMeta is known, or the gate closes."""
        todo: set[bytes] = set()
        while not self._closed.is_set():
            try:
                todo.add(self._q.get(timeout=RETRY_S))
            except queue.Empty:
                pass
            if self.ids is not None:
                todo.clear()
                continue
            for pid in sorted(todo):
                if self._closed.is_set():
                    return
                if pid in self.proven or pid not in self.announced:
                    todo.discard(pid)
                elif challenge(self.session, self.auth, "plant", pid) is not None:
                    self.proven.add(pid)
                    todo.discard(pid)

    # ------------------------------------------------------------------ judging
    def offer(self, key: str, data: bytes, att: bytes | None, t_log: int) -> list[tuple]:
        """One received message (payload ``data``, attachment ``att``): what may be stored now."""
        if self.ids is None:
            if len(self.held) >= HOLD_MAX or self.held_bytes + len(data) > HOLD_BYTES:
                self._reject(key, data, t_log, "auth", out := [])
                return out
            self.held_bytes += len(data)
            if pr.topic_of(key) == "meta":
                self.meta_at.append(len(self.held))
            self.held.append((key, data, att, t_log))
            return self.poll() if self.meta_at[-1:] == [len(self.held) - 1] else []
        return self._judge(key, data, att, t_log)

    def poll(self) -> list[tuple]:
        """Once the run's RunMeta can be told (a plant was proven since), the held messages
        judged, in the order they arrived."""
        if self.ids is not None or not self.proven:
            return []
        later = []
        for i in self.meta_at:
            ok = self._pairs(self.held[i][1], self.held[i][2])
            if ok:
                held, self.held, self.meta_at, self.held_bytes = self.held, [], [], 0
                out: list[tuple] = []
                for j, (k, d, a, t) in enumerate(held):
                    out += [(k, d, t, SESSION)] if j == i else self._judge(k, d, a, t)
                return out
            if ok is None:                  # its plant not proven (yet): tried again later
                later.append(i)
        self.meta_at = later                # the others never will be (rejected when released)
        return []

    def finish(self) -> list[tuple]:
        """At the end: the held messages judged as well as they can be (events under the run
        key alone: recorded, never obeyed; the rest rejected)."""
        self._closed.set()
        out = self.poll()
        held, self.held, self.meta_at, self.held_bytes = self.held, [], [], 0
        for key, data, att, t_log in held:
            out += self._judge(key, data, att, t_log)
        try:
            self._sub.undeclare()
        except Exception:
            pass
        return out

    def _pairs(self, data: bytes, att) -> bool | None:
        """Is this the run's RunMeta (module docstring)?  If so, the session key is taken.  None:
        it names a plant not proven (yet)."""
        try:
            info = pr.decode_meta(data).info
            a = info.get("auth") or {}
            plant = bytes.fromhex(info["plant_peer_id"])
            ctl = bytes.fromhex(info["controller_peer_id"])
            np_, nc = bytes.fromhex(a["nonce_plant"]), bytes.fromhex(a["nonce_controller"])
        except (pr.ProtocolError, KeyError, TypeError, ValueError, AttributeError):
            return False
        if plant not in self.proven:
            return None
        try:
            trial = au.RunAuth(self.auth.secret if self.auth.keyed else None, self.auth.run_id,
                               "recorder", self.auth.me, self.auth.mode)
            trial.pair(plant, ctl, np_, nc)
        except ValueError:
            return False
        if trial.check("meta", data, att, peer=plant) != SESSION:
            return False
        self.auth.pair(plant, ctl, np_, nc)
        self.ids, self.meta, self.mode = {"plant": plant, "controller": ctl}, info, str(a.get("mode") or "unknown")
        return True

    def _judge(self, key: str, data: bytes, att, t_log: int) -> list[tuple]:
        out: list[tuple] = []
        topic = pr.topic_of(key) or ""
        if topic == "events" or topic.startswith("events/"):
            self._event(key, topic, data, att, t_log, out)
        elif topic == "meta":
            if self.ids is not None and self.auth.check("meta", data, att, self.ids["plant"]) == SESSION:
                out.append((key, data, t_log, SESSION))       # the run's RunMeta again
            else:
                self._reject(key, data, t_log, "auth", out)
        elif topic in ("timing", "record"):
            self._attached(key, topic, data, att, t_log, "plant", out)
        elif topic in ("foreign/controller/currents", "foreign/plant/sensors"):
            self._attached(key, topic, data, att, t_log,
                           "plant" if topic.startswith("foreign/controller") else "controller", out)
        elif topic in ("plant/sensors", "controller/currents") and self.wire:
            self._sealed(key, topic, data, t_log, out)
        else:
            self._reject(key, data, t_log, "auth", out)
        return out

    def _attached(self, key, topic, data, att, t_log, role, out) -> None:
        ids = self.ids
        if ids is not None and self.auth.check(topic, data, att, ids[role]) == SESSION:
            out.append((key, data, t_log, SESSION))
        else:
            self._reject(key, data, t_log, "auth", out)

    def _sealed(self, key, topic, data, t_log, out) -> None:
        """A SensorSample / CurrentCommand on the wire: its sender's id and MAC at its end."""
        role = topic.split("/", 1)[0]
        ids, tail = self.ids, au.ID_LEN + au.MAC_LEN
        if ids is None or len(data) < tail + pr.ENCAP_LEN or data[-tail:-au.MAC_LEN] != ids[role]:
            why = "peer"
        elif not au.equal(au.mac(self.auth.key(topic), data[:-au.MAC_LEN]), data[-au.MAC_LEN:]):
            why = "auth"
        else:
            out.append((key, data, t_log, SESSION))
            return
        self.rejected[why] += 1
        self.rejected_topics[topic] += 1
        out.append((f"{self.root}foreign/{topic}", data, t_log, FOREIGN))

    def _event(self, key, topic, data, att, t_log, out) -> None:
        role = topic[len("events/"):] if topic.startswith("events/") else None
        if role not in EVENT_SOURCES:
            self._reject(key, data, t_log, "auth", out)
            return
        how = self.auth.check(topic, data, att, None if self.ids is None else self.ids[role])
        if how == SESSION and self.ids is None:
            how = ""                                 # (cannot happen: no session key yet)
        try:
            src = pr.decode_event(data).source
        except pr.ProtocolError:
            src = None                               # authenticated but malformed: recorded as such
        if not how or (src is not None and src not in EVENT_SOURCES[role]):
            self._reject(key, data, t_log, "auth", out)
            return
        seq = _SEQ.unpack_from(data, pr.SEQ_OFFSET)[0] if len(data) >= pr.SEQ_OFFSET + 8 else -1
        if seq <= self.last_seq[role]:
            self._reject(key, data, t_log, "sequence", out)
            return
        self.last_seq[role] = seq
        out.append((key, data, t_log, how))

    def _reject(self, key, data, t_log, why: str, out: list) -> None:
        topic = pr.topic_of(key) or ""
        self.rejected[why] += 1
        self.rejected_topics[topic] += 1
        if topic == "events" or topic.startswith("events/"):
            out.append((f"{self.root}foreign/events", data, t_log, FOREIGN))

