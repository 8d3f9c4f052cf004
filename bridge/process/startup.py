"""Start-up handshake over zenoh liveliness (docs/protocol.md, section 5).

Every process of a run (role ``plant``, ``controller``, ``recorder``) declares

- ``ambhil/<run>/starting/<role>`` at once, before any heavy work (model build, kernel
  compilation), and holds it until it exits: "this process exists";
- ``ambhil/<run>/alive/<role>`` when it is ready (model and kernels built, subscriptions
  declared), also held until it exits.

and publishes its start-up progress as Event INFO lines on ``ambhil/<run>/events`` (source =
role; e.g. "compiling kernels (first run only) ..."), which it also prints on stderr as
``<role>: <text>`` and answers on the queryable ``ambhil/<run>/status/<role>`` (so a peer that
joins late sees the current step).

A peer waiting for others (:meth:`PeerWatch.wait`) waits as long as each of them is *present*
(either token); it fails only for a peer that

- never appears: no token for ``start_timeout`` s in total (the clock counts absence only), or
- dies: was seen, then lost both tokens.
"""
from __future__ import annotations

import sys
import threading
import time
from typing import Callable, Iterable

import zenoh

from ambhil.bridge.process import transport as tr
from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import auth as au
from ambhil.bridge.process.events import EventSink, Stop

ABSENT, STARTING, READY, GONE = "absent", "starting", "ready", "gone"


def starting_key(run_id: str, role: str) -> str:
    return f"{pr.keys(run_id).root}/starting/{role}"


def ready_key(run_id: str, role: str) -> str:
    return f"{pr.keys(run_id).root}/alive/{role}"


def status_key(run_id: str, role: str) -> str:
    return f"{pr.keys(run_id).root}/status/{role}"


class PeerError(tr.TransportError):
    """A peer never appeared or died before the run started."""


class Presence:
    """This process's side of the handshake.  ``Presence(session, run_id, role)`` declares the
    ``starting`` token immediately; :meth:`progress` reports a start-up step; :meth:`ready`
    declares the ``alive`` token; :meth:`close` undeclares both (exit does too).

    ``events`` is the process's one :class:`ambhil.bridge.process.events.EventSink` (the node reuses it, so
    Event seq numbers stay unique per source)."""

    def __init__(self, session, run_id: str, role: str, *, echo: bool = False,
                 secret: bytes | None = None, insecure: bool = False):
        self.session, self.run_id, self.role, self.echo = session, run_id, role, echo
        self.K = pr.keys(run_id)
        self._ready = None
        self.text = "starting"
        # the process's one view of the run's keys (docs/protocol.md 5.3): events, pairing, loop
        self.auth = au.RunAuth(secret, run_id, role, tr.peer_id(session),
                               None if secret is not None else ("insecure" if insecure else "none"))
        self.events = EventSink(session, run_id, role, self.auth)
        # the status queryable before the token: whoever sees the token can query at once (a
        # query sent before the queryable's declaration reached the peer had no one to answer)
        self._queryable = session.declare_queryable(status_key(run_id, role), self._on_query)
        self._starting = tr.declare_token(session, starting_key(run_id, role))

    @classmethod
    def open(cls, run_id: str, role: str, *, listen=None, connect=None, echo: bool = True,
             secret: bytes | None = None, insecure: bool = False):
        """Open a session and declare presence at once (for the CLI processes)."""
        return cls(tr.open_session(listen, connect), run_id, role, echo=echo, secret=secret,
                   insecure=insecure)

    def _on_query(self, query):
        try:
            query.reply(query.key_expr, f"{self.role}: {self.text}".encode())
        except Exception:
            pass

    def progress(self, text: str) -> None:
        self.text = text
        if self.echo:
            try:
                print(f"{self.role}: {text}", file=sys.stderr, flush=True)
            except OSError:         # stderr gone (the `ambhil run` that reads it died): go on
                self.echo = False
        self.events.emit(pr.EventKind.INFO, text, force=True)

    def ready(self) -> None:
        if self._ready is None:
            self._ready = tr.declare_token(self.session, ready_key(self.run_id, self.role))
            self.text = "ready"

    @property
    def is_ready(self) -> bool:
        return self._ready is not None

    def close(self, session_too: bool = False) -> None:
        tr.close_quietly(self._queryable, self._ready, self._starting)
        self._ready = self._starting = self._queryable = None
        if session_too:
            tr.close_quietly(self.session)


def wait_matching(pub, watch: "PeerWatch", role: str, cap: float, stop=None) -> None:
    """Block until ``pub`` has a matching subscriber of ``role`` (puts before that are lost),
    as long as ``role`` is present; ``cap`` s is the last resort."""
    t_end = time.monotonic() + cap
    while not pub.matching_status.matching:
        st = watch.state(role)
        if st in (GONE, ABSENT):
            raise PeerError(f"{role} went away before its subscriber matched {pub.key_expr}")
        if stop is not None and stop():
            raise Stop()
        if time.monotonic() > t_end:
            raise PeerError(f"{role} is alive but its subscriber did not match {pub.key_expr} "
                            f"within {cap:g} s")
        time.sleep(0.002)


class PeerWatch:
    """States of the run's processes from their liveliness tokens: for each role ABSENT
    (never seen), STARTING, READY, or GONE (seen, then both tokens deleted).

    ``on_change(role, state)`` runs on a zenoh thread (never block in it).  Progress lines
    of peers (Event INFO) are kept in ``progress[role]``."""

    def __init__(self, session, run_id: str, on_change: Callable[[str, str], None] | None = None,
                 me: str | None = None):
        self.session, self.run_id, self.me = session, run_id, me
        self.K = pr.keys(run_id)
        self._tokens: dict[str, set] = {}        # role -> {"starting", "alive"}
        self._seen: set[str] = set()
        self.progress: dict[str, str] = {}
        self._cond = threading.Condition()
        self._on_change = on_change
        root = self.K.root
        self._n_root = len(root.split("/"))
        self._live = session.liveliness().declare_subscriber(f"{root}/*/*", self._cb, history=True)
        self._ev = session.declare_subscriber(self.K.events, self._on_event)

    def _cb(self, sample):
        parts = str(sample.key_expr).split("/")
        if len(parts) != self._n_root + 2 or parts[-2] not in ("starting", "alive"):
            return
        kind, role = parts[-2], parts[-1]
        put = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            before = self._state(role)
            toks = self._tokens.setdefault(role, set())
            (toks.add if put else toks.discard)(kind)
            if put:
                self._seen.add(role)
            after = self._state(role)
            self._cond.notify_all()
        if after != before and self._on_change is not None:
            self._on_change(role, after)

    def _on_event(self, sample):
        try:
            e = pr.decode_event(sample.payload.to_bytes())
        except pr.ProtocolError:
            return
        if e.kind == pr.EventKind.INFO and e.source != self.me:
            with self._cond:
                self.progress[e.source] = e.text
                self._cond.notify_all()

    def _state(self, role: str) -> str:
        toks = self._tokens.get(role, ())
        if "alive" in toks:
            return READY
        if "starting" in toks:
            return STARTING
        return GONE if role in self._seen else ABSENT

    def state(self, role: str) -> str:
        with self._cond:
            return self._state(role)

    def query_progress(self, role: str, timeout: float = 1.0) -> str | None:
        """The current start-up step of ``role`` (its status queryable), or None."""
        try:
            for r in self.session.get(status_key(self.run_id, role), timeout=timeout):
                if r.ok is not None:
                    return r.ok.payload.to_string()
        except Exception:
            pass
        return None

    def wait(self, roles: Iterable[str], start_timeout: float, *, until: str = READY,
             stop: Callable[[], bool] | None = None, report: Callable[[str], None] | None = None,
             what: str = "") -> None:
        """Block until every role in ``roles`` is ``until`` (READY, or STARTING = present).

        A present peer (either token) is waited for without limit; a peer with no token counts
        against ``start_timeout`` (absence only, per peer); a peer that was seen and lost its
        tokens raises at once.  ``stop()`` true -> :class:`ambhil.bridge.process.events.Stop`.  ``report(text)``
        gets a line whenever a peer's state or progress changes."""
        roles = list(roles)
        absent = {r: 0.0 for r in roles}
        last_t = time.monotonic()
        shown: dict[str, tuple] = {}
        queried: set[str] = set()
        ok_states = (READY,) if until == READY else (READY, STARTING)
        while True:
            with self._cond:
                states = {r: self._state(r) for r in roles}
                progress = dict(self.progress)
            now = time.monotonic()
            dt, last_t = now - last_t, now
            for r, st in states.items():
                if st == GONE:
                    raise PeerError(f"{r} process died before the run started (its liveliness "
                                    f"token {starting_key(self.run_id, r)} went away"
                                    + (f"; last step: {progress[r]})" if r in progress else ")"))
                if st == ABSENT:
                    absent[r] += dt
                    if absent[r] > start_timeout:
                        raise PeerError(f"{r} did not appear within {start_timeout:g} s (no "
                                        f"liveliness token {starting_key(self.run_id, r)}; "
                                        f"is it started, with this run id and endpoint?)")
            if all(st in ok_states for st in states.values()):
                return
            if stop is not None and stop():
                raise Stop()
            if report is not None:
                for r, st in states.items():
                    if st == STARTING and r not in progress and r not in queried:
                        queried.add(r)          # a peer that joined late: ask for its step
                        txt = self.query_progress(r)
                        if txt:
                            with self._cond:
                                self.progress.setdefault(r, txt.split(": ", 1)[-1])
                            progress[r] = self.progress[r]
                    key = (st, progress.get(r))
                    if st not in ok_states and shown.get(r) != key:
                        shown[r] = key
                        detail = f" ({r}: {progress[r]})" if st == STARTING and r in progress else ""
                        report(f"waiting for {r}{what}: {st}{detail}")
            with self._cond:
                self._cond.wait(0.05)

    def undeclare(self):
        tr.close_quietly(self._ev, self._live)
