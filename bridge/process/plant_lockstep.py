"""The plant's lockstep loop (the RUNNING phase of bridge/process/plant_node.py in lockstep mode).

Sample k is published, the reply with seq k awaited, the plant advanced (docs/protocol.md,
section 5).  :func:`lockstep` takes the :class:`ambhil.bridge.process.plant_node.PlantNode` and binds what its
hot path needs to locals first (one codec call per message, see bridge/protocol/wire.py; no
numpy between ``recv()`` and ``put()``); on any exit it writes back ``steps_done``, the last
output ``y`` and ``sim_ns`` for the summary.  Faults leave as
:class:`ambhil.bridge.process.events.Fault`, stop requests as :class:`ambhil.bridge.process.events.Stop`.
The ordinary steps run in C where the extension is built (``ambhil.bridge.protocol.wire.PlantLockstep``,
see :func:`_lockstep_native`), the Python loop otherwise and for a trace or a latency in steps.
The real-time loop is bridge/process/plant_realtime.py.
"""
from __future__ import annotations

import time

import numpy as np

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import auth as au
from ambhil.bridge.protocol import wire
from ambhil.bridge.protocol.wire import LoopCode
from ambhil.bridge.process.events import Fault, Stop


def lockstep(node) -> None:
    """Publish sample k, wait for the reply with seq k, advance; stop requests arrive as
    watchdog wake-ups (docs/protocol.md, section 5)."""
    node.wd.start()
    if wire.NATIVE and node.cfg.delay_samples == 0 and not node.cfg.trace:
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
                                f"within {node.cfg.reply_timeout * 1e3:g} ms")
                if stop_fn is not None and stop_fn():
                    raise Stop()
                continue
            reject(pr.TruncatedError("empty payload"), k)
            continue
        try:
            hh = unpack(data, rx_mv)
        except pr.ProtocolError as e:
            if e.reason in au.UNSEALED:   # not the paired controller's (or not sealed): never
                reject(node.foreign(e, data), k)     # in the run's channels, kept apart
                continue
            keep_c((wall(), data))       # the controller's, malformed: recorded as received
            reject(e, k)
            continue
        seq = hh[2]
        if seq == k:
            keep_c((wall(), data))
            return hh[2:7], wall()       # the round trip ends after the decode, as on the fast path
        if seq < k:                      # sealed by the controller for a step already answered:
            counts["duplicates"] += 1    # in lockstep only a replay of captured traffic does that
            reject(node.foreign(pr.SequenceError(f"reply seq {seq} replayed while waiting for "
                                                 f"{k}"), data), k)
        else:
            keep_c((wall(), data))
            reject(pr.SequenceError(f"reply seq {seq} > outstanding {k}"), k)


def _lockstep_native(node) -> None:
    """The lockstep loop with its ordinary steps in C (:class:`wire.PlantLockstep`): the same
    calls, stamps and recording as :func:`_lockstep_python`; ``run()`` hands the loop back
    here with a :class:`wire.LoopCode` for a flush and for anything else (a message off the
    fast path, a new output object or a plant status, an exception: :func:`_step_in_python`).
    The TET goes straight into ``node.tet``."""
    rb = node.rb
    sent, received = rb.lists
    lp = wire.PlantLockstep(
        y_mv=node.y_mv, y_obj=node.y_obj, rx_mv=node.rx_mv, u=node.rx, advance=node.advance,
        plant=node.plant, has_status=node.has_status, put=node.pub.put, recv=node.sub.recv,
        sent=sent, received=received, rtt=node.rtt, tet=node.tet, wmark=node.wd.progress,
        me=node.me, peer=node.peer, period_ns=node.period_ns, k_end=node.cfg.n_steps,
        next_flush=node.cfg.timing_batch)
    t_batch = node.cfg.timing_batch
    y = node.y
    rb.flush(time.time_ns())
    try:
        while lp.k < lp.k_end:
            lp.rb_due = rb.due
            code = lp.run()
            if code == LoopCode.DONE:
                break
            if code == LoopCode.FLUSH:           # step k - 1 done, a flush is due
                t1 = lp.t1
            else:                                # step k needs Python
                y, t1 = _step_in_python(node, lp, code, y)
            k = lp.k
            if k >= lp.next_flush:
                node.flush_timing(k)
                lp.next_flush = k + t_batch
            if t1 >= rb.due:
                rb.flush(t1)
    finally:
        node.steps_done, node.y, node.sim_ns = lp.steps_done, y, lp.sim_ns


def _step_in_python(node, lp, code, y):
    """Step ``lp.k``, handed back by the C loop with ``code``, finished here as the Python
    loop would; returns ``(y, t1)``, the output and the round trip's end, with ``lp`` moved
    on to the next step (``y`` in: the last output, kept if ``code`` does not bring one)."""
    k = lp.k
    node.loop_handbacks += 1
    if code == LoopCode.SLOW:                    # the message in hand is not the fast-path reply
        h, t1 = _reply_slow(node, k, lp.sim_ns, lp.data)
        node.rtt[k] = t1 - lp.t0
        node.tet[k] = h[4] - h[3]
        try:
            y = node.advance(node.rx)
        except Exception as e:
            raise Fault(f"plant.advance raised at step {k}: {type(e).__name__}: {e}") from e
    elif code == LoopCode.CHECK:                 # advanced; a new output object or a status
        y, t1 = lp.y, lp.t1
    elif code == LoopCode.RAISED:
        e = lp.exc
        raise Fault(f"plant.advance raised at step {k}: {type(e).__name__}: {e}") from e
    else:                                        # LoopCode.NONFINITE: nothing sent
        node.encode_fault(k, lp.sim_ns, lp.y_mv)
        raise Fault(f"plant output not finite at step {k}")
    if y is not lp.y_obj or (node.has_status and node.plant.status):
        lp.y_mv = node.check_output(y, k)
        lp.y_obj = node.y_obj                    # None (not aliased): every step comes back here
    lp.k = lp.steps_done = k + 1
    return y, t1


def _lockstep_python(node) -> None:
    """The lockstep loop in Python: with the C extension not built, a fixed latency in steps
    or a trace of y and u."""
    plant, wd = node.plant, node.wd
    recv = node.sub.recv
    put = node.pub.put
    wall = time.time_ns
    period_ns = node.period_ns
    extra = _delay_and_trace(node)
    # hot path: one codec call per message (bridge/protocol/wire.py, C when built); the common
    # case is a well-formed reply with seq == k from the paired controller (its peer id ends
    # the payload, docs/protocol.md 5.1), anything else takes the validating slow path
    # (_reply_slow: protocol.CurrentCodec.unpack_into, which names a foreign sender first)
    enc_s, dec_c = wire.encode_sensor, wire.decode_current
    rx_mv = node.rx_mv
    rtt_mv = memoryview(node.rtt)
    advance = node.advance
    has_status = node.has_status
    t_batch = node.cfg.timing_batch
    next_flush = t_batch
    wmark = wd.progress
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
        for k in range(node.cfg.n_steps):
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
            if extra is not None:
                u = extra(k, y)
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


def _delay_and_trace(node):
    """``extra(k, y) -> u`` for the Python lockstep loop, once the reply to k is in: the
    currents applied over step k (with ``delay_samples`` = d, the reply to k - d through a
    ring of the last d + 1 replies, zeros before), and the trace rows ``Y[k] = y``,
    ``U[k] = u``.  None when there is neither a latency nor a trace."""
    delay, trace, Y, U = node.cfg.delay_samples, node.cfg.trace, node.Y, node.U
    D = delay + 1
    if D == 1 and not trace:
        return None
    n, rx, rx_mv = node.n, node.rx, node.rx_mv
    ring = np.zeros((D, n))
    ring_mv = [memoryview(ring[i]).cast("B") for i in range(D)]
    zeros = np.zeros(n)

    def extra(k, y):
        u = rx
        if D > 1:
            ring_mv[k % D][:] = rx_mv
            u = ring[(k - delay) % D] if k >= delay else zeros
        if trace:
            Y[k] = y
            U[k] = u
        return u
    return extra
