"""The plant's real-time loop (the RUNNING phase of bridge/process/plant_node.py in real-time mode).

Step 0 is a handshake; from step 1 on, sample k is published at its absolute deadline and
its reply applied over k -> k+1 if it arrives in its window, else the last currents are held
(docs/protocol.md, section 5).  :func:`realtime` takes the
:class:`ambhil.bridge.process.plant_node.PlantNode` and binds what its hot path needs to locals first (one
codec call per message, see bridge/protocol/wire.py); on any exit it writes back
``steps_done``, the last output ``y`` and ``sim_ns`` for the summary.  Faults leave as
:class:`ambhil.bridge.process.events.Fault`, a stop request as ``end_reason = "stopped"``.

The loop's named steps are closures bound once before it starts (:func:`_window_receiver`,
:func:`_settler`): a closure reads its bound names as fast as the loop's own locals, so a
named step costs one call per period, not an attribute look-up per name.  The lockstep loop
is bridge/process/plant_lockstep.py.
"""
from __future__ import annotations

import math
import queue
import time

import numpy as np

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import auth as au
from ambhil.bridge.protocol import wire
from ambhil.bridge.process.events import Fault
from ambhil.bridge.process.timing import wait_until

FIRST_REPLY_GRACE_S = 0.5      # s; miss limit during the warm-up


def realtime(node) -> None:
    """Step 0 is a handshake: sample 0 is published and its reply awaited as long as the
    controller is alive (the plant holds its start state); the clock starts then.  From step 1
    on, absolute deadlines (sleep then spin); the reply to k is applied over k -> k+1 if it
    arrives in its window, else the last currents are held (docs/protocol.md, section 5)."""
    plant, n, period_ns, cfg = node.plant, node.n, node.period_ns, node.cfg
    lat, rtt, flags = node.lat, node.rtt, node.flags
    trace, Y, U = cfg.trace, node.Y, node.U
    stop_fn = node.stop_fn
    put, keep_s, me = node.pub.put, node.rb.sent, node.me
    wall = time.time_ns
    now = time.perf_counter_ns
    spin_ns = int((min(150e-6, 0.2 * node.period) if cfg.spin_s is None else cfg.spin_s) * 1e9)
    guard_fixed = None if cfg.guard_s is None else int(cfg.guard_s * 1e9)
    t_batch = cfg.timing_batch
    adv_est = 0.0
    u = np.zeros(n)                # currents applied (held on a missing reply)
    u_mv = node.cc.view(u)
    # currents applied at their arrival: the previous period's currents for the first m plant
    # steps, m = ceil((wake lateness + round trip) / h)
    arrival = cfg.currents_at == "arrival"
    u_old = np.zeros(n)
    h_ns = period_ns / plant.ratio if arrival else 0.0
    enc_s = wire.encode_sensor
    get_until = _receiver(node)
    y, y_mv = node.y, node.y_mv
    rb = node.rb                   # the recording, off the loop's path (see plant_lockstep.py)
    to_wall = wall() - now()       # replies are stamped with perf_counter_ns on arrival
    receive = _window_receiver(node, get_until, to_wall, u_mv)
    settle = _settler(node)
    rb.flush(wall())
    rb_due = rb.due - to_wall      # on the perf_counter clock
    steps_done = sim_ns = 0
    try:
        sim_ns = plant.step_index * period_ns
        first = _first_step(node, get_until, to_wall, sim_ns, u, u_mv)
        if first is None:
            node.end_reason = "stopped"
            return
        y, y_mv = first
        steps_done = 1
        seen = miss_run = 0
        t_start = now()                  # the clock: sample k is due at t_start + k*T
        for k in range(1, cfg.n_steps):
            if stop_fn is not None and (k & 63) == 0 and stop_fn():
                node.end_reason = "stopped"
                break
            deadline = t_start + k * period_ns
            # -- wait for the deadline (sleep then spin), publish sample k
            lat[k] = late = wait_until(deadline, spin_ns)
            sim_ns = plant.step_index * period_ns
            t0 = now()
            msg = enc_s(y_mv, k, plant.step_index, sim_ns, wall(), me)
            put(msg if msg is not None else node.encode_fault(k, sim_ns, y_mv))
            keep_s(msg)
            if late > period_ns:
                flags[k] |= pr.FLAG_LATE_WAKE
                node.counts["late_wakes"] += 1
                # re-anchor the schedule at this late wake instead of bursting samples to
                # catch up: the controller must see its sample period, never a burst
                t_start += late
                deadline += late
            if arrival:
                u_old[:] = u
            # -- receive window for the reply to k, then its flags and counts
            guard = guard_fixed if guard_fixed is not None else spin_ns + int(2 * adv_est)
            got, seen, alive = receive(k, deadline + period_ns - guard, t0, seen, sim_ns)
            miss_run = settle(k, got, alive, miss_run)
            if trace:
                Y[k] = y
                U[k] = u
            # -- advance over k -> k+1
            ta = now()
            if arrival and got is not None:
                m = math.ceil((late + int(rtt[k])) / h_ns)
                y, y_mv = node.advance_arriving_checked(u_old, u, m, k)
            else:
                y, y_mv = node.advance_checked(u, k)
            adv_est = 0.9 * adv_est + 0.1 * (now() - ta)
            steps_done = k + 1
            if steps_done - node.tbatch["start"] >= t_batch:
                node.flush_timing(steps_done)
            if ta >= rb_due:
                rb.flush(ta + to_wall)
                rb_due = rb.due - to_wall
    finally:
        node.steps_done, node.y, node.sim_ns = steps_done, y, sim_ns


def _first_step(node, get_until, to_wall, sim_ns, u, u_mv):
    """Step 0: the handshake (:func:`_handshake`), then its reply applied (``u``, through
    its view ``u_mv``) and the plant advanced.  Returns the plant's output and its view
    ``(y, y_mv)``, or None on a stop request before the reply."""
    first = _handshake(node, get_until, to_wall, sim_ns)
    if first is None:
        return None
    t0, t_rx = first
    node.rtt[0] = t_rx - t0
    u_mv[:] = node.rx_mv
    if node.cfg.warmup_steps > 0:
        node.flags[0] |= pr.FLAG_WARMUP
    if node.cfg.trace:
        node.Y[0] = node.y
        node.U[0] = u
    return node.advance_checked(u, 0)


def _receiver(node):
    """The real-time receive (bridge/process/deadline.py): ``get_until(window_end)`` returns
    ``(t_rx, payload)`` (``payload`` None: the controller was lost) or raises
    :class:`queue.Empty` when the window is over.  With the deadline timer, the timer is told
    the window (arm) and when its reply is in (done): one id per window."""
    now = time.perf_counter_ns
    dl = node.dl
    if dl is None:
        get, get_nowait = node.rxq.get, node.rxq.get_nowait

        def get_until(window_end):
            rem = window_end - now()
            return get(timeout=rem * 1e-9) if rem > 0 else get_nowait()
        return get_until
    tid = [0]
    arm, done = dl.arm, dl.done
    recv = node.sub.recv
    Empty = queue.Empty

    def get_until(window_end):
        tid[0] += 1
        arm(tid[0], window_end)
        while True:
            smp = recv()
            t_rx = now()             # the round trip ends when the loop has the reply
            data = smp.payload.to_bytes()
            if data:
                done(tid[0])
                return t_rx, data
            # an empty put: a wake-up (timer, lost peer; Waker)
            if node.peer_lost:
                return t_rx, None
            if t_rx >= window_end:
                raise Empty
    return get_until


def _handshake(node, get_until, to_wall, sim_ns):
    """Step 0, the start handshake: sample 0 is published and its reply awaited as long as
    the controller lives (the plant holds its start state, ``reset()``, not integrating);
    the clock starts when it is in.  Returns ``(t0, t_rx)``, the round trip's start and end
    (``node.tet[0]`` and ``node.rx_mv`` filled), or None on a stop request."""
    plant, y_mv, tet = node.plant, node.y_mv, node.tet
    rx_mv, peer, unpack = node.rx_mv, node.peer, node.cc.unpack_into
    reject, keep_c, stop_fn = node.reject, node.rb.received, node.stop_fn
    now, wall = time.perf_counter_ns, time.time_ns
    t0 = now()
    msg = wire.encode_sensor(y_mv, 0, plant.step_index, sim_ns, wall(), node.me)
    node.pub.put(msg if msg is not None else node.encode_fault(0, sim_ns, y_mv))
    node.rb.sent(msg)
    t_cap = t0 + int(node.cfg.wait_cap_s * 1e9)
    while True:
        try:
            t_rx, data = get_until(now() + 100_000_000)
        except queue.Empty:
            if stop_fn is not None and stop_fn():
                return None
            if now() > t_cap:
                raise Fault(f"controller alive but no reply to the first sample within "
                            f"{node.cfg.wait_cap_s:g} s")
            continue
        if data is None:
            raise Fault("controller lost (liveliness) before its first reply")
        h = wire.decode_current(data, 0, rx_mv, peer)
        if h is not None:
            keep_c((t_rx + to_wall, data))
            tet[0] = h[4] - h[3]
            return t0, t_rx
        try:
            h = unpack(data, rx_mv)
        except pr.ProtocolError as e:
            if e.reason in au.UNSEALED:   # not the paired controller's: never recorded
                reject(node.foreign(e, data), 0)
                continue
            keep_c((t_rx + to_wall, data))
            reject(e, 0)
            continue
        keep_c((t_rx + to_wall, data))
        if h[2] == 0:
            tet[0] = h[6] - h[5]
            return t0, t_rx
        reject(pr.SequenceError(f"reply seq {h[2]} > outstanding 0"), 0)


def _window_receiver(node, get_until, to_wall, u_mv):
    """``receive(k, window_end, t0, seen, sim_ns) -> (got, seen, alive)``: the reply to sample
    k (published at ``t0``) awaited until ``window_end``; ``got`` its header or None, ``seen``
    the last seq answered (k once its reply is in), ``alive`` True if a late reply came (the
    controller answers, however late).  The reply's currents go to ``u_mv``; later messages
    wait for the next window."""
    rtt, tet, counts, ev = node.rtt, node.tet, node.counts, node.ev
    rx_mv, peer, dec_c = node.rx_mv, node.peer, wire.decode_current
    unpack, reject, foreign = node.cc.unpack_into, node.reject, node.foreign
    keep_c = node.rb.received
    Empty = queue.Empty

    def receive(k, window_end, t0, seen, sim_ns):
        got = None
        alive = False
        while True:
            try:
                item = get_until(window_end)
            except Empty:
                break
            t_rx, data = item
            if data is None:
                raise Fault(f"controller lost (liveliness) at step {k}")
            h = dec_c(data, k, rx_mv, peer)
            if h is not None:            # fast path: the reply to k, well-formed, paired
                keep_c((t_rx + to_wall, data))
                got = h
                u_mv[:] = rx_mv
                rtt[k] = t_rx - t0
                tet[k] = h[4] - h[3]
                break
            try:
                h = unpack(data, rx_mv)
            except pr.ProtocolError as e:
                if e.reason in au.UNSEALED:  # not the paired controller's: never recorded
                    reject(foreign(e, data), k)
                    continue
                keep_c((t_rx + to_wall, data))
                reject(e, k)
                continue
            seq = h[2]
            if seq <= seen or (seq == k and got is not None):
                # sealed by the controller for a seq already answered: a replay of captured
                # traffic (the controller answers each sample once), kept apart
                counts["duplicates"] += 1
                reject(foreign(pr.SequenceError(f"reply seq {seq} replayed (seq {seen} already "
                                                f"answered)"), data), k)
                continue
            keep_c((t_rx + to_wall, data))
            if seq == k and got is None:
                got = h
                u_mv[:] = rx_mv
                rtt[k] = t_rx - t0
                tet[k] = h[6] - h[5]
                break                    # advance now; later messages: next window
            elif seq < k:
                counts["late_replies"] += 1
                seen = max(seen, seq)
                alive = True             # late, but answering: not a dead controller
                ev.emit(pr.EventKind.OVERRUN, f"late reply seq {seq} discarded "
                        f"at step {k}", k, sim_ns)
            else:
                reject(pr.SequenceError(f"reply seq {seq} > outstanding {k}"), k)
        if got is not None:
            seen = k
        return got, seen, alive
    return receive


def _settler(node):
    """``settle(k, got, alive, miss_run) -> miss_run``: step k's flags after its window (held,
    warm-up), the held count and the run of missing replies, an overrun counted; a fault when
    the controller stays silent too long or the overruns pass ``max_overruns``."""
    flags, counts, period = node.flags, node.counts, node.period
    warmup_steps, max_overruns = node.cfg.warmup_steps, node.cfg.max_overruns
    miss_limit = max(1, int(round(node.cfg.reply_timeout / period)))
    # during the warm-up the controller gets a grace (first replies over a fresh link and with
    # cold caches can take ms on a loaded machine)
    first_limit = max(miss_limit, int(round(FIRST_REPLY_GRACE_S / period)))

    def settle(k, got, alive, miss_run):
        warm = k < warmup_steps
        if got is not None:
            miss_run = 0
        else:
            flags[k] |= pr.FLAG_HELD
            counts["held"] += 1
            if alive:
                miss_run = 0
            miss_run += 1
            # during the warm-up the start grace applies (first replies over a fresh link
            # and cold caches can take ms); after it, reply_timeout
            if miss_run >= (first_limit if warm else miss_limit):
                raise Fault(f"controller timeout: no reply for {miss_run} periods "
                            f"(last at step {k - miss_run}; {1 / period:g} Hz, "
                            f"its liveliness token still present: hung, or too slow "
                            f"for real time on this machine, see docs/hil.md)")
        if warm:
            flags[k] |= pr.FLAG_WARMUP
        elif flags[k] & (pr.FLAG_HELD | pr.FLAG_LATE_WAKE):
            node.overruns += 1
            if max_overruns is not None and node.overruns > max_overruns:
                raise Fault(f"overrun limit: {node.overruns} overruns > {max_overruns} "
                            f"(step {k})")
        return miss_run
    return settle
