"""Pairing of a run's plant and controller (docs/protocol.md, sections 5.1 and 5.3).

Each process has a 16-byte *peer id* (the Python nodes use their zenoh session id) that ends
every SensorSample / CurrentCommand it sends (followed by the message's MAC), that it attaches
with a MAC (zenoh attachment ``id || mac``) to the other messages it publishes, and that it
announces with the liveliness token ``ambhil/<run>/peer/<role>/<id as 32 hex digits>`` once it
is ready.

An announcement proves nothing (anyone can declare a token or copy an id), so pairing is a
challenge-response on the run secret (protocol 3):

- every plant and controller answers challenges on the queryable ``ambhil/<run>/pair/<role>/<id>``
  (:class:`Responder`, declared before the token): a query ``challenger_id || nonce_q`` gets the
  reply ``nonce_r || proof``, ``proof = H16(K_run, "ambhil/3/pair" 0 role 0 id challenger nonce_q
  nonce_r)`` (:func:`ambhil.bridge.protocol.auth.pair_proof`);
- the plant challenges every announced controller (:func:`challenge`, :class:`Pairing`): an id
  that proves the secret is a controller, one that does not is a *stranger* (named, ignored: it
  neither pairs nor blocks); exactly one proven controller pairs, two are refused.  The session
  key then derives from both ids and both nonces;
- the controller pairs with the RunMeta that carries one of the nonces it answered and whose MAC
  verifies under that session key (:func:`meta_pairs`): the plant has proven the secret on a
  fresh nonce of the controller's own;
- the recorder challenges the announced plants and takes the RunMeta of a proven one.

Without a key (mode ``none`` / ``insecure``) the same exchange runs with the all-zero secret:
it still keeps out a stale process of an older run, not a forger.
"""
from __future__ import annotations

import collections
import threading
import time

import zenoh

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import auth as au
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


class Responder:
    """Answers pairing challenges on ``ambhil/<run>/pair/<role>/<id>`` with this process's
    proof of the secret.  ``candidates`` keeps the last ``keep`` challenges answered,
    ``(challenger_id, nonce_q, nonce_r)``: the sessions a controller may be paired into
    (:func:`meta_pairs`)."""

    def __init__(self, session, auth: au.RunAuth, keep: int = 64):
        self.auth = auth
        self.candidates: collections.deque = collections.deque(maxlen=keep)
        self.answered = 0
        self._q = session.declare_queryable(pr.pair_key(auth.run_id, auth.role, auth.me),
                                            self._on_query)

    def _on_query(self, query):
        try:
            p = query.payload
            data = b"" if p is None else p.to_bytes()
            if len(data) != ID_LEN + au.NONCE_LEN:
                return
            cid, nq = data[:ID_LEN], data[ID_LEN:]
            nr = au.nonce()
            self.candidates.append((cid, nq, nr))
            self.answered += 1
            query.reply(query.key_expr, nr + self.auth.proof(cid, nq, nr))
        except Exception:
            pass

    def undeclare(self):
        try:
            self._q.undeclare()
        except Exception:
            pass


def challenge(session, auth: au.RunAuth, role: str, pid: bytes, timeout: float = 0.5):
    """Challenge peer ``pid`` of ``role``: ``(nonce_q, nonce_r)`` if one reply on its pairing key
    proves the secret (every reply of every queryable on the key is looked at: a stranger that
    copied the id and answers too cannot hide the real one), else None."""
    nq = au.nonce()
    try:
        replies = session.get(pr.pair_key(auth.run_id, role, pid), payload=auth.me + nq,
                              target=zenoh.QueryTarget.ALL,
                              consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout)
        for r in replies:
            ok = r.ok
            if ok is None:
                continue
            data = ok.payload.to_bytes()
            if len(data) != au.NONCE_LEN + au.MAC_LEN:
                continue
            nr, tag = data[:au.NONCE_LEN], data[au.NONCE_LEN:]
            if auth.check_proof(role, pid, nq, nr, tag):
                return nq, nr
    except Exception:
        return None
    return None


def meta_pairs(auth: au.RunAuth, responder: Responder, payload, attachment) -> dict | None:
    """Controller side: pair with this RunMeta if it was made for one of the challenges
    ``responder`` answered (its ``auth`` nonces and plant id) and its MAC verifies under that
    session key; returns the decoded RunMeta dict (``auth`` paired), else None (nothing
    changed)."""
    if attachment is None:
        return None
    att = bytes(attachment)
    if len(att) != au.ATTACH_LEN:
        return None
    pid = att[:ID_LEN]
    try:
        meta = pr.decode_meta(bytes(payload)).info
        a = meta.get("auth") or {}
        np_, nc = bytes.fromhex(a["nonce_plant"]), bytes.fromhex(a["nonce_controller"])
    except Exception:
        return None
    for cid, nq, nr in list(responder.candidates):
        if cid == pid and au.equal(nq, np_) and au.equal(nr, nc):
            k_s = au.session_key(auth.secret, auth.run_id, pid, auth.me, nq, nr)
            tag = au.mac(au.topic_key(k_s, "meta"), bytes(payload) + pid)
            if au.equal(tag, att[ID_LEN:]):
                auth.pair(pid, auth.me, nq, nr)
                return meta
    return None


class Pairing:
    """This process's announcement (``peer/<role>/<id>``, with its :class:`Responder`) and its
    view of the ``other`` role's announcements.  ``announce()`` declares responder and token;
    ``wait(watch, cap, stop)`` challenges every announced ``other`` and returns the paired id
    once exactly one has proven the secret (raises :class:`PairingError` for two or more);
    ``strangers`` lists ids that were announced but failed the proof (``on_stranger(id)`` is
    called once for each), ``extra`` proven ids announced after pairing (``on_extra(id)``), both
    on a zenoh or the waiting thread.  ``nonces`` = (nonce_q, nonce_r) of the pairing."""

    def __init__(self, session, run_id: str, role: str, other: str, pid: bytes | None = None,
                 auth: au.RunAuth | None = None):
        self.session, self.run_id, self.role, self.other = session, run_id, role, other
        self.id = pid if pid is not None else peer_id(session)
        self.auth = auth if auth is not None else au.RunAuth(None, run_id, role, self.id)
        self.paired: bytes | None = None
        self.nonces = None
        self.extra: list[bytes] = []
        self.strangers: list[bytes] = []
        self.on_extra = None
        self.on_stranger = None
        self.responder = None
        self._ids: set[bytes] = set()
        self._proven: dict[bytes, tuple] = {}
        self._tried: dict[bytes, float] = {}
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
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._ids.add(pid)
                late = self.paired is not None and pid != self.paired
            else:
                self._ids.discard(pid)
                late = False
            self._cond.notify_all()
        if late:        # announced after pairing: prove it off the zenoh thread
            threading.Thread(target=self._late, args=(pid,), daemon=True).start()

    def _late(self, pid: bytes):
        if self._prove(pid) is not None:
            with self._cond:
                new = pid not in self.extra
                if new:
                    self.extra.append(pid)
            if new and self.on_extra is not None:
                self.on_extra(pid)
        else:
            self._stranger(pid)

    def _prove(self, pid: bytes):
        got = challenge(self.session, self.auth, self.other, pid)
        if got is not None:
            with self._cond:
                self._proven[pid] = got
        return got

    def _stranger(self, pid: bytes):
        with self._cond:
            new = pid not in self.strangers and pid not in self._proven
            if new:
                self.strangers.append(pid)
        if new and self.on_stranger is not None:
            self.on_stranger(pid)

    def announce(self) -> None:
        if self._token is None:
            if self.responder is None:      # the responder first: whoever sees the token can challenge
                self.responder = Responder(self.session, self.auth)
            self._token = self.session.liveliness().declare_token(
                peer_key(self.run_id, self.role, self.id))

    def wait(self, watch, cap: float, stop=None, settle_s: float = 0.02,
             retry_s: float = 0.5, absent_timeout: float = 30.0) -> bytes:
        """Pair with the single announced ``other`` that proves the secret (as long as the
        ``other`` is present, ``cap`` s as the last resort).  Every announced id is challenged
        (again every ``retry_s`` while it fails: its responder may not have reached us yet); one
        that failed its first challenge is named a stranger.  ``settle_s`` after the first proof
        lets a second announcement already on its way be seen.  Only strangers came and went:
        the real ``other`` is waited for ``absent_timeout`` s more."""
        t_end = time.monotonic() + cap
        t_first = t_gone = None
        while True:
            now = time.monotonic()
            with self._cond:
                todo = [p for p in self._ids
                        if p not in self._proven and now - self._tried.get(p, -1e9) >= retry_s]
                for p in todo:
                    self._tried[p] = now
            for p in todo:
                if self._prove(p) is None:
                    self._stranger(p)
            with self._cond:
                proven = sorted(p for p in self._proven if p in self._ids)
                now = time.monotonic()
                if proven:
                    if t_first is None:
                        t_first = now
                    if now - t_first >= settle_s:
                        break
                st = watch.state(self.other) if watch is not None else None
                if st in (GONE, ABSENT) and not self._ids:
                    # only strangers came and went: wait for the real one as for an absent
                    # peer (``absent_timeout``); a peer that went away unannounced: at once
                    if not self.strangers:
                        raise PeerError(f"{self.other} went away before it announced its peer "
                                        f"id ({peer_key(self.run_id, self.other)})")
                    if t_gone is None:
                        t_gone = now
                    elif now - t_gone > absent_timeout:
                        raise PeerError(f"no {self.other} for {absent_timeout:g} s after the "
                                        f"strangers {', '.join(p.hex() for p in self.strangers)} "
                                        f"went away")
                else:
                    t_gone = None
                if stop is not None and stop():
                    raise Stop()
                if now > t_end:
                    who = (f"; strangers that failed the pairing proof (no key?): "
                           f"{', '.join(p.hex() for p in self.strangers)}" if self.strangers else "")
                    raise PeerError(f"{self.other} is alive but no {self.other} proved the run's "
                                    f"key on {pr.pair_key(self.run_id, self.other)} within "
                                    f"{cap:g} s{who} (docs/protocol.md, 5.3)")
                self._cond.wait(0.01)
        if len(proven) > 1:
            raise PairingError(
                f"run {self.run_id}: {len(proven)} {self.other}s announced "
                f"({', '.join(i.hex() for i in proven)}); refusing to pair with any: stop the "
                f"extra {self.other} or use another run id")
        self.paired = proven[0]
        self.nonces = self._proven[self.paired]
        with self._cond:        # announced while we settled and not the paired one: late
            late = [p for p in self._ids if p != self.paired and p not in self._proven
                    and p not in self.strangers]
        for p in late:
            threading.Thread(target=self._late, args=(p,), daemon=True).start()
        return self.paired

    def undeclare(self):
        if self.responder is not None:
            self.responder.undeclare()
        for o in (self._token, self._sub):
            try:
                if o is not None:
                    o.undeclare()
            except Exception:
                pass
        self._token = None


class PairingError(PeerError):
    """More than one peer of a role announced itself for the run."""
