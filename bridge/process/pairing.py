"""Pairing of a run's plant and controller (docs/protocol.md, section 5.1).

Each process has a 16-byte *peer id* (the Python nodes use their zenoh session id) that ends
every SensorSample / CurrentCommand it sends (``uint8[16] peer``, protocol version 2: checked
in the same C call as the sequence number), that it attaches (zenoh attachment) to the other
messages it publishes (``events``, ``meta``, ``timing``, ``record``), and that it announces
with the liveliness token ``ambhil/<run>/peer/<role>/<id as 32 hex digits>`` once it is ready.  The plant pairs with the
single announced controller, the controller with the single announced plant; a second
announcement of the same role before the run starts is refused (two controllers for one run),
and after it is counted and reported.  Every sensor sample or current command that does not end
with the paired id is rejected (reason ``peer``), counted, reported as Event
REJECTED and never integrated or answered: another zenoh session on the machine cannot take
over the loop.

This stops accidental and naive takeovers (a stale or second controller, a test script, a
replay of the wrong run).  The id is not a secret: against a peer that forges it,
use zenoh's access control and mutual TLS (docs/hil.md, "Secure runs").
"""
from __future__ import annotations

import threading
import time

import zenoh

from ambhil.bridge import protocol as pr
from ambhil.bridge.process.transport import ID_LEN, peer_id
from ambhil.bridge.process.events import Stop
from ambhil.bridge.process.startup import ABSENT, GONE, PeerError

def peer_key(run_id: str, role: str, pid: bytes | None = None) -> str:
    root = pr.keys(run_id).root
    return f"{root}/peer/{role}/{pid.hex() if pid is not None else '*'}"


def attached(sample) -> bytes | None:
    """The attachment of a zenoh sample as bytes (None if it has none)."""
    a = sample.attachment
    return None if a is None else a.to_bytes()


class Pairing:
    """This process's announcement (``peer/<role>/<id>``) and its view of the ``other`` role's
    announcements.  ``announce()`` declares the token; ``wait(watch, cap, stop)`` returns the
    paired id once exactly one ``other`` is announced (raises :class:`PairingError` for two or
    more); ``extra`` lists ids announced after pairing, ``on_extra(id)`` is called for each
    (on a zenoh thread)."""

    def __init__(self, session, run_id: str, role: str, other: str, pid: bytes | None = None):
        self.session, self.run_id, self.role, self.other = session, run_id, role, other
        self.id = pid if pid is not None else peer_id(session)
        self.paired: bytes | None = None
        self.extra: list[bytes] = []
        self.on_extra = None
        self._ids: set[bytes] = set()
        self._cond = threading.Condition()
        self._token = None
        self._sub = session.liveliness().declare_subscriber(peer_key(run_id, other), self._cb,
                                                            history=True)

    def _cb(self, sample):
        tail = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            pid = bytes.fromhex(tail)
        except ValueError:
            return
        if len(pid) != ID_LEN:
            return
        new = False
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._ids.add(pid)
                if self.paired is not None and pid != self.paired and pid not in self.extra:
                    self.extra.append(pid)
                    new = True
            else:
                self._ids.discard(pid)
            self._cond.notify_all()
        if new and self.on_extra is not None:
            self.on_extra(pid)

    def announce(self) -> None:
        if self._token is None:
            self._token = self.session.liveliness().declare_token(
                peer_key(self.run_id, self.role, self.id))

    def wait(self, watch, cap: float, stop=None, settle_s: float = 0.02) -> bytes:
        """Pair with the single announced ``other`` (as long as it is present, ``cap`` s as the
        last resort).  ``settle_s`` after the first announcement lets a second one that is
        already on its way arrive, so that two announced peers are seen as two."""
        t_end = time.monotonic() + cap
        t_first = None
        with self._cond:
            while True:
                now = time.monotonic()
                if self._ids:
                    if t_first is None:
                        t_first = now
                    if now - t_first >= settle_s:
                        break
                st = watch.state(self.other) if watch is not None else None
                if st in (GONE, ABSENT) and not self._ids:
                    raise PeerError(f"{self.other} went away before it announced its peer id "
                                    f"({peer_key(self.run_id, self.other)})")
                if stop is not None and stop():
                    raise Stop()
                if now > t_end:
                    raise PeerError(f"{self.other} is alive but announced no peer id "
                                    f"({peer_key(self.run_id, self.other)}) within {cap:g} s: "
                                    f"a {self.other} of an older protocol? (docs/protocol.md, 5.1)")
                self._cond.wait(0.01)
            ids = sorted(self._ids)
            if len(ids) > 1:
                raise PairingError(
                    f"run {self.run_id}: {len(ids)} {self.other}s announced "
                    f"({', '.join(i.hex() for i in ids)}); refusing to pair with any: stop the "
                    f"extra {self.other} or use another run id")
            self.paired = ids[0]
            return self.paired

    def undeclare(self):
        for o in (self._token, self._sub):
            try:
                if o is not None:
                    o.undeclare()
            except Exception:
                pass
        self._token = None


class PairingError(PeerError):
    """More than one peer of a role announced itself for the run."""
