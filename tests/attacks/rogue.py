"""A stranger on an ambhil run: the attacks of issue 31, raw zenoh, written from docs/protocol.md
(no ``ambhil`` import; the layouts are in wire3.py next to this file).

    python rogue.py '{"attack": "forged_id", "run": "r1", "connect": ["tcp/127.0.0.1:7447"], ...}'

One JSON argument (the rogue uses only zenoh, struct, os, sys, json, time, hashlib):
- ``attack``: forged_id | plus1 | replay | seq_stall | events | first_joiner | announcer |
  recorder_cert (the functions below, one per attack of issue 31);
- ``run``, ``connect`` / ``listen`` (endpoint lists), ``tls`` (zenoh ``transport/link/tls``, for
  a session with some certificate), ``gossip`` (default true);
- ``wait``: roles whose ``starting/`` or ``alive/`` token must be seen (a direct link) before
  the attack is armed; ``ready``: a file created once it is armed (the test starts the real
  controller only then); ``stats``: where the counts go (JSON) at the end;
- ``max_s``: give up after this long; the rogue also ends a second after the plant's tokens went,
  or once the file ``stop`` exists.

What it sends, it counts (``stats``): the test compares with what the run rejected.
"""
from __future__ import annotations

import json
import os
import sys
import time

import zenoh

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import wire3 as w  # noqa: E402

NOW = time.time_ns


class Rogue:
    def __init__(self, cfg: dict):
        self.cfg, self.run = cfg, cfg["run"]
        self.root = f"ambhil/{self.run}"
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("scouting/gossip/enabled", json.dumps(cfg.get("gossip", True)))
        c.insert_json5("listen/endpoints", json.dumps(cfg.get("listen") or []))
        c.insert_json5("connect/endpoints", json.dumps(cfg.get("connect") or []))
        c.insert_json5("transport/unicast/lowlatency", "true")       # docs/protocol.md 1: all agree
        c.insert_json5("transport/unicast/qos/enabled", "false")
        if cfg.get("tls"):
            c.insert_json5("transport/link/tls", json.dumps(cfg["tls"]))
        self.s = zenoh.open(c)
        self.me = os.urandom(16)
        self.tokens: set = set()          # liveliness keys seen, minus deleted
        self.ids: dict = {}               # role -> first peer id seen (copied from its token)
        self.last = None                  # the last genuine SensorSample seen (dict)
        self.meta = None                  # the RunMeta json seen
        self.stats = {"attack": cfg["attack"], "sent": 0, "samples_seen": 0}
        self.keep = [self.s.liveliness().declare_subscriber(f"{self.root}/**", self._on_token,
                                                            history=True)]
        self.plant_seen = False

    # ---- what the rogue sees
    def _on_token(self, smp):
        k = str(smp.key_expr)
        if smp.kind == zenoh.SampleKind.PUT:
            self.tokens.add(k)
            parts = k.split("/")
            if len(parts) == 5 and parts[2] == "peer":
                try:
                    pid = bytes.fromhex(parts[4])
                except ValueError:
                    return
                if pid != self.me:
                    self.ids.setdefault(parts[3], pid)
        else:
            self.tokens.discard(k)

    def present(self, role) -> bool:
        return any(f"{self.root}/{s}/{role}" in self.tokens for s in ("starting", "alive"))

    def watch_samples(self, on_sample=None):
        def cb(smp):
            data = smp.payload.to_bytes()
            try:
                h = w.loop_header(data)
            except Exception:
                return
            if h["kind"] != "sample":
                return
            self.last = h
            self.stats["samples_seen"] += 1
            if on_sample is not None:
                on_sample(h, data)
        self.keep.append(self.s.declare_subscriber(f"{self.root}/plant/sensors", cb))

    def watch_meta(self):
        def cb(smp):
            try:
                self.meta = w.read_meta(smp.payload.to_bytes())
            except Exception:
                pass
        self.keep.append(self.s.declare_subscriber(f"{self.root}/meta", cb))

    def token(self, key):
        self.keep.append(self.s.liveliness().declare_token(f"{self.root}/{key}"))

    def send(self, pub, data, **kw):
        pub.put(data, **kw)
        self.stats["sent"] += 1

    # ---- life
    def arm_and_run(self, arm):
        t_end = time.monotonic() + float(self.cfg.get("max_s", 120))
        stop = self.cfg.get("stop")
        while not all(self.present(r) for r in self.cfg.get("wait", [])):
            if time.monotonic() > t_end or (stop and os.path.exists(stop)):
                self.stats["error"] = f"never saw {self.cfg.get('wait')}: {sorted(self.tokens)}"
                return self.finish()
            time.sleep(0.01)
        tick = arm()
        if self.cfg.get("ready"):
            open(self.cfg["ready"], "w").close()
        gone_at = None
        while time.monotonic() < t_end and not (stop and os.path.exists(stop)):
            if self.present("plant"):
                self.plant_seen, gone_at = True, None
            elif self.plant_seen:
                gone_at = gone_at or time.monotonic()
                if time.monotonic() - gone_at > 1.0:
                    break
            if tick is not None:
                tick()
            time.sleep(0.002)
        self.finish()

    def finish(self):
        self.stats["ids"] = {r: p.hex() for r, p in dict(self.ids).items()}
        self.stats["me"] = self.me.hex()
        if self.cfg.get("stats"):
            with open(self.cfg["stats"] + ".tmp", "w") as fh:
                json.dump(dict(self.stats), fh)
            os.replace(self.cfg["stats"] + ".tmp", self.cfg["stats"])
        sys.stdout.flush()
        os._exit(0)           # zenoh callback threads would keep the interpreter alive


# ---- the attacks -----------------------------------------------------------------------------
def forged_id(r: Rogue, plus=0):
    """1 (and 3 with ``plus=1``): answer every SensorSample, under the controller's copied id,
    with well-formed +-amps currents (seq of the sample + ``plus``) and a MAC it cannot compute
    (random, or zeros with ``"mac": "zeros"``)."""
    pub = r.s.declare_publisher(f"{r.root}/controller/currents")
    amps = float(r.cfg.get("amps", 3.9))

    def on_sample(h, _data):
        cid = r.ids.get("controller")
        if cid is None:
            return
        u = [amps if a % 2 == 0 else -amps for a in range(h["n"])]
        mac = bytes(16) if r.cfg.get("mac") == "zeros" else os.urandom(16)
        q = h["seq"] + plus
        r.send(pub, w.current(q, h["step"] + plus, h["sim"], NOW(), NOW(), u, cid, mac))
    r.keep.append(pub)
    r.watch_samples(on_sample)


def plus1(r: Rogue):
    forged_id(r, plus=1)


def replay(r: Rogue):
    """2: capture the CurrentCommands of the plant's RecordBatches; answer each live sample with
    one captured command re-put verbatim (stale seq, genuine MAC) and one with the live
    seq/step/sim patched in (its MAC no longer fits)."""
    pub = r.s.declare_publisher(f"{r.root}/controller/currents")
    captured: list = []
    r.stats.update(captured=0, verbatim=0, patched=0)

    def on_batch(smp):
        try:
            for topic, data in w.read_record_batch(smp.payload.to_bytes()):
                if topic == 1:
                    captured.append(data)
                    r.stats["captured"] += 1
        except Exception:
            pass

    def on_sample(h, _data):
        if not captured:
            return
        old = captured[r.stats["verbatim"] % len(captured)]
        if w.loop_header(old)["seq"] == h["seq"]:        # that would be the genuine reply itself
            return
        r.send(pub, old)
        r.stats["verbatim"] += 1
        r.send(pub, w.patch_seq(old, h["seq"], h["step"], h["sim"]))
        r.stats["patched"] += 1
    r.keep += [pub, r.s.declare_subscriber(f"{r.root}/record", on_batch)]
    r.watch_samples(on_sample)


def seq_stall(r: Rogue):
    """4: one SensorSample under the plant's copied id with seq = live + 60000 (inside the 2^16
    window), once ``after`` samples were seen.  With ``"unauth": true`` (a run without a key)
    its MAC is the right one, computed from RunMeta with the all-zero secret."""
    pub = r.s.declare_publisher(f"{r.root}/plant/sensors")
    after, jump = int(r.cfg.get("after", 100)), int(r.cfg.get("jump", 60000))
    r.stats.update(forged_seq=None, mac="random")
    r.watch_meta()

    def on_sample(h, data):
        if r.stats["forged_seq"] is not None or h["seq"] < after:
            return
        q = h["seq"] + jump
        msg = w.sample(q, h["step"] + jump, h["sim"], NOW(), h["v"], data[-32:-16], os.urandom(16))
        if r.cfg.get("unauth") and r.meta is not None:
            k_s = w.session_from_meta(r.meta, r.run)
            if k_s is not None:
                msg = w.seal(msg, w.topic_key(k_s, "plant/sensors"))
                r.stats["mac"] = "valid (all-zero secret)"
        r.stats["forged_seq"] = q
        r.send(pub, msg)
    r.keep.append(pub)
    r.watch_samples(on_sample)


def events(r: Rogue):
    """5: Events under the plant's copied id on ``events/plant``: FAULT_INJECTED
    controller_restart (one every ``every`` samples, up to ``count``) and, once ``end_after``
    samples were seen, one RUN_END "completed"; random MACs, and a few without attachment."""
    key = f"{r.root}/events/plant"
    pub = r.s.declare_publisher(key)
    every, count = int(r.cfg.get("every", 5)), int(r.cfg.get("count", 300))
    end_after = int(r.cfg.get("end_after", 300))
    r.stats.update(restarts=0, run_ends=0, unattached=0)
    seq = [1000]

    def put(kind, h, text):
        pid = r.ids.get("plant", bytes(16))
        ev = w.event(kind, seq[0], h["step"] + 1, h["sim"], NOW(), "plant", text)
        seq[0] += 1
        if seq[0] % 10 == 0:
            r.send(pub, ev)
            r.stats["unattached"] += 1
        else:
            r.send(pub, ev, attachment=w.attachment(pid, None, ev, os.urandom(16)))

    def on_sample(h, _data):
        if h["seq"] % every == 0 and r.stats["restarts"] < count:
            put(w.FAULT_INJECTED, h, json.dumps({"kind": "controller_restart", "axis": None,
                                                 "params": {}, "phase": "start"}))
            r.stats["restarts"] += 1
        if h["seq"] >= end_after and not r.stats["run_ends"]:
            put(w.RUN_END, h, json.dumps({"reason": "completed", "steps": h["step"], "fault": None}))
            r.stats["run_ends"] += 1
    r.keep.append(pub)
    r.watch_samples(on_sample)


def _pose_as_controller(r: Rogue, answer_samples=True):
    """Declare ``alive/controller``, a pairing queryable that answers garbage proofs, and
    ``peer/controller/<own id>``; answer samples with zero-MAC currents under its own id."""
    r.stats.update(challenges=0)

    def on_query(q):
        r.stats["challenges"] += 1
        try:
            q.reply(q.key_expr, os.urandom(32))          # nonce_r || proof: garbage
        except Exception:
            pass
    r.keep.append(r.s.declare_queryable(f"{r.root}/pair/controller/{r.me.hex()}", on_query))
    r.token(f"starting/controller")
    r.token(f"alive/controller")
    r.token(f"peer/controller/{r.me.hex()}")
    if answer_samples:
        pub = r.s.declare_publisher(f"{r.root}/controller/currents")
        r.keep.append(pub)
        r.watch_samples(lambda h, _d: r.send(pub, w.current(h["seq"], h["step"], h["sim"], NOW(),
                                                             NOW(), [3.9] * h["n"], r.me)))


def first_joiner(r: Rogue):
    """6: join before the real controller and pose as one (tokens, a queryable with garbage
    proofs, replies under its own id)."""
    _pose_as_controller(r)


def announcer(r: Rogue):
    """7: announce ``count`` controllers (peer tokens only) before the real one."""
    for _ in range(int(r.cfg.get("count", 2))):
        r.token(f"peer/controller/{os.urandom(16).hex()}")
    r.watch_samples()


def recorder_cert(r: Rogue):
    """8: a session with the recorder's certificate: poses as controller (tokens, garbage
    proofs) and puts RUN_END on events/plant and events/controller, once samples flow."""
    _pose_as_controller(r, answer_samples=False)
    pubs = {role: r.s.declare_publisher(f"{r.root}/events/{role}") for role in ("plant", "controller")}
    r.keep += list(pubs.values())
    r.stats.update(run_ends=0)

    def on_sample(h, _data):
        if h["seq"] < int(r.cfg.get("end_after", 200)) or r.stats["run_ends"] >= 20:
            return
        for role, pub in pubs.items():
            ev = w.event(w.RUN_END, 5000 + r.stats["run_ends"], h["step"], h["sim"], NOW(), role,
                         json.dumps({"reason": "completed", "steps": h["step"], "fault": None}))
            pid = r.ids.get(role, r.me)
            r.send(pub, ev, attachment=w.attachment(pid, None, ev, os.urandom(16)))
        r.stats["run_ends"] += 1
    r.watch_samples(on_sample)


ATTACKS = {f.__name__: f for f in (forged_id, plus1, replay, seq_stall, events, first_joiner,
                                   announcer, recorder_cert)}

if __name__ == "__main__":
    cfg = json.loads(sys.argv[1])
    rogue = Rogue(cfg)
    try:
        rogue.arm_and_run(lambda: ATTACKS[cfg["attack"]](rogue))
    except BaseException as e:     # zenoh's threads would keep a failed rogue alive: say why, end
        rogue.stats["error"] = f"{type(e).__name__}: {e}"
        rogue.finish()
