"""The plant's two loops (the RUNNING phase of bridge/process/plant_node.py): lockstep and real time.

Each takes the :class:`ambhil.bridge.process.plant_node.PlantNode` and binds what its hot path needs to
locals first (one codec call per message, see bridge/protocol/wire.py; no numpy between ``recv()``
and ``put()``); on any exit it writes back ``steps_done``, the last output ``y`` and
``sim_ns`` for the summary.  Faults leave as :class:`ambhil.bridge.process.events.Fault`, stop requests as
:class:`ambhil.bridge.process.events.Stop` (lockstep) or ``end_reason = "stopped"`` (real time).  Lockstep runs
its ordinary steps in C where the extension is built (``ambhil.bridge.protocol._wire.plant_lockstep``, see
:func:`_lockstep_native`), the Python loop otherwise and for a trace or a latency in steps.
"""
from __future__ import annotations

import math
import queue
import time

import numpy as np

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import wire
from ambhil.bridge.process.events import Fault, Stop


def lockstep(node) -> None:
    """Publish sample k, wait for the reply with seq k, advance; stop requests arrive as
    watchdog wake-ups (docs/protocol.md, section 5)."""
    node.wd.start()
    if wire.NATIVE and node.delay_samples == 0 and not node.trace:
        node.loop = "C"
        _lockstep_native(node)
    else:
        _lockstep_python(node)


def _reply_slow(node, k, sim_ns, data):
    """The reply to step k when the message in hand (``data``) is not its fast-path reply:
    wake-ups, rejected and duplicate messages are handled (and recorded as received, except
    a foreign sender's) and the next ones awaited.  Returns ``(h, t1)``: the reply's
    ``(seq, step, sim_time_ns, recv_wall_ns, publish_wall_ns)`` and the round trip's end."""
    wd, recv, rx_mv, peer = node.wd, node.sub.recv, node.rx_mv, node.peer
    dec_c, unpack, keep_c = wire.decode_current, node.cc.unpack_into, node.rb.received
    reject, stop_fn, counts, ev = node.reject, node.stop_fn, node.counts, node.ev
    wall = time.time_ns
    first = True
    while True:
        if not first:
            data = recv().payload.to_bytes()
            h = dec_c(data, k, rx_mv, peer)
            if h is not None:                # the reply to k from the paired controller
                t1 = wall()
                keep_c((t1, data))
                return h, t1
        first = False
        if not data:
            if wd.pending > 0:
                wd.pending -= 1
                if node.peer_lost:
                    raise Fault(f"controller lost (liveliness) at step {k}")
                if wd.fired_mark == k:
                    raise Fault(f"controller timeout: no reply to step {k} "
                                f"within {node.reply_timeout * 1e3:g} ms")
                if stop_fn is not None and stop_fn():
                    raise Stop()
                continue
            reject(pr.TruncatedError("empty payload"), k)
            continue
        try:
            hh = unpack(data, rx_mv)
        except pr.ForeignError as e:      # not from the paired controller: never recorded
            reject(node.foreign(e, data), k)
            continue
        except pr.ProtocolError as e:
            keep_c((wall(), data))       # recorded as received, whatever it holds
            reject(e, k)
            continue
        keep_c((wall(), data))
        seq = hh[2]
        if seq == k:
            return hh[2:7], wall()       # the round trip ends after the decode, as on the fast path
        if seq < k:
            counts["duplicates"] += 1
            ev.emit(pr.EventKind.DUPLICATE, f"stale/duplicate reply seq {seq} "
                    f"while waiting for {k}", k, sim_ns)
        else:
            reject(pr.SequenceError(f"reply seq {seq} > outstanding {k}"), k)


def _lockstep_native(node) -> None:
    """The lockstep loop with its ordinary steps in C (``ambhil.bridge.protocol._wire.plant_lockstep``): the
    same calls, stamps and recording as :func:`_lockstep_python`, which it returns to for
    anything else (a message off the fast path, a new output object or a plant status, a
    flush, an exception).  The TET goes straight into ``node.tet``."""
    plant = node.plant
    drive = wire._wire.plant_lockstep
    rb = node.rb
    args = [node.y_mv, node.y_obj, node.rx_mv, node.rx, node.advance, plant, node.has_status,
            node.pub.put, node.sub.recv, *rb.lists, node.rtt, node.tet, None,
            node.wd.progress, node.me, node.peer, node.period_ns, 0, node.n_steps, 0, 0]
    st = args[13] = np.zeros(2, np.int64)       # (steps done, sim_time_ns of the last step begun)
    rtt, tet, u, advance = node.rtt, node.tet, node.rx, node.advance
    has_status, t_batch, n_steps = node.has_status, node.timing_batch, node.n_steps
    y = node.y
    next_flush = t_batch
    rb.flush(time.time_ns())
    k = 0
    try:
        while k < n_steps:
            args[18], args[20], args[21] = k, next_flush, rb.due
            code, k, a, b = drive(*args)
            if code == 0:                        # all steps done
                break
            if code == 2:                        # step k - 1 done, a flush is due
                t1 = a
            else:                                # step k needs Python
                node.loop_handbacks += 1
                if code == 1:                    # the message in hand is not the fast-path reply
                    h, t1 = _reply_slow(node, k, int(st[1]), b)
                    rtt[k] = t1 - a
                    tet[k] = h[4] - h[3]
                    try:
                        y = advance(u)
                    except Exception as e:
                        raise Fault(f"plant.advance raised at step {k}: {type(e).__name__}: {e}") from e
                elif code == 3:                  # advanced; a new output object or a status
                    y, t1 = a, b
                elif code == 4:
                    raise Fault(f"plant.advance raised at step {k}: {type(a).__name__}: {a}") from a
                else:                            # code 5: not finite, nothing sent
                    node.encode_fault(k, int(st[1]), args[0])
                    raise Fault(f"plant output not finite at step {k}")
                if y is not args[1] or (has_status and plant.status):
                    args[0] = node.check_output(y, k)
                    args[1] = node.y_obj         # None (not aliased): every step comes back here
                k += 1
                st[0] = k
            if k >= next_flush:
                node.flush_timing(k)
                next_flush = k + t_batch
            if t1 >= rb.due:
                rb.flush(t1)
    finally:
        node.steps_done, node.y, node.sim_ns = int(st[0]), y, int(st[1])


def _lockstep_python(node) -> None:
    """The lockstep loop in Python: with the C extension not built, a fixed latency in steps
    or a trace of y and u."""
    plant, n, wd = node.plant, node.n, node.wd
    recv = node.sub.recv
    put = node.pub.put
    wall = time.time_ns
    period_ns = node.period_ns
    delay_samples, trace, Y, U = node.delay_samples, node.trace, node.Y, node.U
    D = delay_samples + 1
    ring = np.zeros((D, n))
    ring_mv = [memoryview(ring[i]).cast("B") for i in range(D)]
    zeros = np.zeros(n)
    # hot path: one codec call per message (bridge/protocol/wire.py, C when built); the common
    # case is a well-formed reply with seq == k from the paired controller (its peer id ends
    # the payload, docs/protocol.md 5.1), anything else takes the validating slow path
    # (_reply_slow: protocol.CurrentCodec.unpack_into, which names a foreign sender first)
    enc_s, dec_c = wire.encode_sensor, wire.decode_current
    rx_mv = node.rx_mv
    rtt_mv = memoryview(node.rtt)
    advance = node.advance
    has_status = node.has_status
    t_batch = node.timing_batch
    next_flush = t_batch
    wmark = wd.progress
    extras = D > 1 or trace
    keep_reply = node.replies.append
    me, peer = node.me, node.peer
    y, y_mv, y_obj = node.y, node.y_mv, node.y_obj
    u = node.rx
    # the recording leaves the loop's path: the bytes sent and received are kept (list
    # appends) and handed to the recorder in batches (bridge/protocol/record_batch.py)
    rb = node.rb
    keep_s, keep_c = rb.sent, rb.received
    rb.flush(wall())
    rb_due = rb.due
    steps_done = sim_ns = 0
    try:
        for k in range(node.n_steps):
            step_i = plant.step_index
            sim_ns = step_i * period_ns      # sim time = step x period (docs/protocol.md)
            wmark[0] = k
            t0 = wall()                      # publish stamp and round-trip start
            msg = enc_s(y_mv, k, step_i, sim_ns, t0, me)
            if msg is None:
                node.encode_fault(k, sim_ns, y_mv)   # raises the non-finite fault with details
            put(msg)
            keep_s(msg)
            smp = recv()
            data = smp.payload.to_bytes()
            h = dec_c(data, k, rx_mv, peer)
            if h is not None:                # the reply to k from the paired controller
                t1 = wall()
                keep_c((t1, data))
            else:
                h, t1 = _reply_slow(node, k, sim_ns, data)
            rtt_mv[k] = t1 - t0
            keep_reply(h)                    # TET = h[4] - h[3], filled in by flush_timing
            if extras:
                if D > 1:
                    ring_mv[k % D][:] = rx_mv
                    u = ring[(k - delay_samples) % D] if k >= delay_samples else zeros
                if trace:
                    Y[k] = y
                    U[k] = u
            try:
                y = advance(u)
            except Exception as e:
                raise Fault(f"plant.advance raised at step {k}: {type(e).__name__}: {e}")
            if y is not y_obj or (has_status and plant.status):
                y_mv = node.check_output(y, k)
                y_obj = node.y_obj
            steps_done = k + 1
            if steps_done >= next_flush:
                node.flush_timing(steps_done)
                next_flush = steps_done + t_batch
            if t1 >= rb_due:
                rb.flush(t1)
                rb_due = rb.due
    finally:
        node.steps_done, node.y, node.sim_ns = steps_done, y, sim_ns


def realtime(node) -> None:
    """Step 0 is a handshake: sample 0 is published and its reply awaited as long as the
    controller is alive (the plant holds its start state); the clock starts then.  From step 1
    on, absolute deadlines (sleep then spin); the reply to k is applied over k -> k+1 if it
    arrives in its window, else the last currents are held (docs/protocol.md, section 5)."""
    plant, n, period, period_ns = node.plant, node.n, node.period, node.period_ns
    lat, rtt, tet, flags = node.lat, node.rtt, node.tet, node.flags
    trace, Y, U = node.trace, node.Y, node.U
    counts, ev, reject, stop_fn = node.counts, node.ev, node.reject, node.stop_fn
    warmup_steps, max_overruns = node.warmup_steps, node.max_overruns
    put = node.pub.put
    wall = time.time_ns
    now = time.perf_counter_ns
    spin_ns = int((min(150e-6, 0.2 * period) if node.spin_s is None else node.spin_s) * 1e9)
    guard_fixed = None if node.guard_s is None else int(node.guard_s * 1e9)
    adv_est = 0.0
    u = np.zeros(n)                # currents applied (held on a missing reply)
    u_mv = node.cc.view(u)
    # currents applied at their arrival: the previous period's currents for the first m plant
    # steps, m = ceil((wake lateness + round trip) / h)
    arrival = node.currents_at == "arrival"
    u_old = np.zeros(n)
    h_ns = period_ns / plant.ratio if arrival else 0.0
    rx_mv = node.rx_mv
    unpack = node.cc.unpack_into
    me, peer, foreign = node.me, node.peer, node.foreign
    Empty = queue.Empty
    # the receive (bridge/process/deadline.py): get_until(window_end) returns (t_rx, payload)
    # or raises Empty when the window is over; the deadline timer is told the
    # window (arm) and when its reply is in (done): one id per window
    tid = [0]
    dl = node.dl
    if dl is not None:
        arm, done = dl.arm, dl.done
        recv = node.sub.recv

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
    else:
        get, get_nowait = node.rxq.get, node.rxq.get_nowait

        def get_until(window_end):
            rem = window_end - now()
            return get(timeout=rem * 1e-9) if rem > 0 else get_nowait()
    enc_s, dec_c = wire.encode_sensor, wire.decode_current
    miss_run = 0
    miss_limit = max(1, int(round(node.reply_timeout / period)))
    # during the warm-up the controller gets a grace (first replies over a fresh link and with
    # cold caches can take ms on a loaded machine)
    first_limit = max(miss_limit, int(round(node.first_reply_grace_s / period)))
    seen = -1
    y, y_mv = node.y, node.y_mv
    rb = node.rb                   # the recording, off the loop's path (see lockstep)
    keep_s, keep_c = rb.sent, rb.received
    to_wall = wall() - now()       # replies are stamped with perf_counter_ns on arrival
    rb.flush(wall())
    rb_due = rb.due - to_wall      # on the perf_counter clock
    steps_done = sim_ns = 0
    try:
        # -- step 0, the start handshake: the clock starts when the controller has answered
        # sample 0; until then the plant holds its start state (reset(), not integrating)
        sim_ns = plant.step_index * period_ns
        t0 = now()
        msg = enc_s(y_mv, 0, plant.step_index, sim_ns, wall(), me)
        put(msg if msg is not None else node.encode_fault(0, sim_ns, y_mv))
        keep_s(msg)
        t_cap = t0 + int(node.wait_cap_s * 1e9)
        while True:
            try:
                t_rx, data = get_until(now() + 100_000_000)
            except Empty:
                if stop_fn is not None and stop_fn():
                    node.end_reason = "stopped"
                    return
                if now() > t_cap:
                    raise Fault(f"controller alive but no reply to the first sample within "
                                f"{node.wait_cap_s:g} s")
                continue
            if data is None:
                raise Fault("controller lost (liveliness) before its first reply")
            h = dec_c(data, 0, rx_mv, peer)
            if h is not None:
                keep_c((t_rx + to_wall, data))
                tet[0] = h[4] - h[3]
                break
            try:
                h = unpack(data, rx_mv)
            except pr.ForeignError as e:      # not from the paired controller: never recorded
                reject(foreign(e, data), 0)
                continue
            except pr.ProtocolError as e:
                keep_c((t_rx + to_wall, data))
                reject(e, 0)
                continue
            keep_c((t_rx + to_wall, data))
            if h[2] == 0:
                tet[0] = h[6] - h[5]
                break
            reject(pr.SequenceError(f"reply seq {h[2]} > outstanding 0"), 0)
        rtt[0] = t_rx - t0
        u_mv[:] = rx_mv
        seen = 0
        if warmup_steps > 0:
            flags[0] |= pr.FLAG_WARMUP
        if trace:
            Y[0] = y
            U[0] = u
        y, y_mv = node.advance_checked(u, 0)
        steps_done = 1
        t_start = now()                  # the clock: sample k is due at t_start + k*T
        for k in range(1, node.n_steps):
            if stop_fn is not None and (k & 63) == 0 and stop_fn():
                node.end_reason = "stopped"
                break
            deadline = t_start + k * period_ns
            # -- wait for the deadline (sleep then spin), publish sample k
            t = now()
            rem = deadline - spin_ns - t
            if rem > 0:
                time.sleep(rem * 1e-9)
            t = now()
            while t < deadline:
                t = now()
            late = t - deadline
            lat[k] = late
            sim_ns = plant.step_index * period_ns
            t0 = now()
            msg = enc_s(y_mv, k, plant.step_index, sim_ns, wall(), me)
            put(msg if msg is not None else node.encode_fault(k, sim_ns, y_mv))
            keep_s(msg)
            if late > period_ns:
                flags[k] |= pr.FLAG_LATE_WAKE
                counts["late_wakes"] += 1
                # re-anchor the schedule at this late wake instead of bursting samples to
                # catch up: the controller must see its sample period, never a burst
                t_start += late
                deadline += late
            if arrival:
                u_old[:] = u
            # -- receive window for the reply to k
            guard = guard_fixed if guard_fixed is not None else spin_ns + int(2 * adv_est)
            window_end = deadline + period_ns - guard
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
                except pr.ForeignError as e:  # not from the paired controller: never recorded
                    reject(foreign(e, data), k)
                    continue
                except pr.ProtocolError as e:
                    keep_c((t_rx + to_wall, data))
                    reject(e, k)
                    continue
                keep_c((t_rx + to_wall, data))
                seq = h[2]
                if seq == k and got is None:
                    got = h
                    u_mv[:] = rx_mv
                    rtt[k] = t_rx - t0
                    tet[k] = h[6] - h[5]
                    break                    # advance now; later messages: next window
                elif seq <= seen or seq == k:
                    counts["duplicates"] += 1
                    ev.emit(pr.EventKind.DUPLICATE, f"duplicate reply seq {seq}", k, sim_ns)
                elif seq < k:
                    counts["late_replies"] += 1
                    seen = max(seen, seq)
                    alive = True             # late, but answering: not a dead controller
                    ev.emit(pr.EventKind.OVERRUN, f"late reply seq {seq} discarded "
                            f"at step {k}", k, sim_ns)
                else:
                    reject(pr.SequenceError(f"reply seq {seq} > outstanding {k}"), k)
            warm = k < warmup_steps
            if got is not None:
                seen = k
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
            if trace:
                Y[k] = y
                U[k] = u
            ta = now()
            if arrival and got is not None:
                m = math.ceil((late + int(rtt[k])) / h_ns)
                y, y_mv = node.advance_arriving_checked(u_old, u, m, k)
            else:
                y, y_mv = node.advance_checked(u, k)
            adv_est = 0.9 * adv_est + 0.1 * (now() - ta)
            steps_done = k + 1
            if steps_done - node.tbatch["start"] >= node.timing_batch:
                node.flush_timing(steps_done)
            if ta >= rb_due:
                rb.flush(ta + to_wall)
                rb_due = rb.due - to_wall
    finally:
        node.steps_done, node.y, node.sim_ns = steps_done, y, sim_ns
