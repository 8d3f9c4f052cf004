"""Plant and controller loops over zenoh, for any duck-typed step objects.

Plant step object::

    n_axes: int; period: float (controller period, s)
    reset() -> y0 (n_axes displacements); advance(currents) -> y (one period, currents held)
    step_index: int; sim_time: float (s); safe_state()   # called on a fault

Controller step object::

    n_axes: int; reset(); step(y) -> currents (n_axes)

Optional fast paths: ``plant.advance_shared(u)`` / ``controller.step_shared(y)`` may return
their own output buffer (no copy), and a plant may expose ``status`` (0 = OK), ``FATAL``
(statuses that end the run) and ``fault`` (one-line text).  The arrays the bridge passes in
(``u``, ``y``) are its own preallocated buffers, overwritten every period: copy what you keep.
The plant's sim time on the wire is ``step_index * period`` (integer ns).

Modes
-----
``lockstep``: the plant publishes sample k and waits for the currents answering seq k
before advancing; with ``delay_samples=n`` it applies the currents computed from sample
k-n (zeros before that).  Deterministic: same trajectory as :func:`run_inprocess`.

``realtime``: sample k is published at the absolute deadline ``t0 + k*T``; the reply must
arrive before ``t0 + (k+1)*T - guard``; it is then applied over the interval k -> k+1
(same arithmetic as lockstep with no delay).  A missing reply -> last currents held,
overrun counted.  Replies are timestamped on arrival (zenoh callback) for the round trip.

Watchdog: liveliness DELETE of the peer, or no reply/sample within the timeout, ends the
run with ``summary["fault"]`` set to a one-line reason (plant: after ``safe_state()``).
"""
from __future__ import annotations

import json
import math
import platform
import queue
import threading
import time
from typing import Callable

import numpy as np

from . import transport as tr          # sets ZENOH_RUNTIME before zenoh is imported
from . import protocol as pr
from . import wire
from .timing import histogram_us, pin_cpus, set_timer_slack, stats_us

LOCKSTEP = "lockstep"
REALTIME = "realtime"
MODES = (LOCKSTEP, REALTIME)
MIN_LOCKSTEP_TIMEOUT = 0.1     # s; lockstep wall time is unrelated to sim periods
FIRST_REPLY_GRACE_S = 0.5      # s; real time: wait this long for the very first reply


def exit_code(summary: dict) -> int:
    """0 for a clean run, 1 if the run ended with a fault."""
    return 1 if summary.get("fault") else 0


def _stop_fn(stop) -> Callable[[], bool] | None:
    if stop is None:
        return None
    if hasattr(stop, "is_set"):
        return stop.is_set
    return stop


class EventSink:
    """Publishes Event messages; at most ``max_per_s`` per second (excess counted)."""

    def __init__(self, session, key: str, source: str, max_per_s: int = 200):
        self.pub = tr.declare_publisher(session, key)
        self.source = source
        self.seq = 0
        self.max_per_s = max_per_s
        self._win = 0
        self._n_in_win = 0
        self.suppressed = 0
        self.log: list[pr.Event] = []      # FAULT / RUN_* kept for the summary

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
        ev = pr.Event(kind, text[:4096], self.source, self.seq, step, sim_time_ns, time.time_ns())
        self.seq += 1
        if kind in (pr.EventKind.FAULT, pr.EventKind.RUN_END, pr.EventKind.RUN_START):
            self.log.append(ev)
        try:
            self.pub.put(pr.encode_event(ev))
        except Exception:
            pass


class _Watchdog(threading.Thread):
    """Fires ``waker.wake()`` when ``progress[0]`` has not changed for ``timeout`` s while
    ``active``; also ticks every ``tick`` s while the owner is blocked, and when
    ``stop()`` becomes true, so signal handlers and stop requests get a chance to run."""

    def __init__(self, waker: tr.Waker, timeout: float, stop=None, tick: float = 0.1):
        super().__init__(daemon=True, name="ambhil-watchdog")
        self.waker = waker
        self.timeout = timeout
        self.stop = stop
        self.tick = tick
        self.progress = [-1]       # owner writes progress[0] (a list store: cheapest hot-path write)
        self.active = False
        self.fired_mark = None
        self.pending = 0
        self.done = False

    def wake(self):
        self.pending += 1
        self.waker.wake()

    def run(self):
        check = max(min(self.timeout / 5.0, self.tick), 0.0005)
        last, t_last, t_tick = None, time.monotonic(), time.monotonic()
        while not self.done:
            time.sleep(check)
            now = time.monotonic()
            if self.stop is not None and self.stop():
                self.wake()
                continue
            m = self.progress[0]
            if m != last:
                last, t_last, t_tick = m, now, now
                continue
            if self.active and now - t_last >= self.timeout and self.fired_mark != m:
                self.fired_mark = m
                self.wake()
            elif now - t_tick >= self.tick:
                t_tick = now
                self.wake()


def _versions() -> dict:
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


def _view(codec, a):
    """``(memoryview, key)`` for a step object's output vector: ``key`` is ``a`` itself when
    the view aliases it (a float64 C-contiguous array, typically a buffer the step object
    reuses), so the view can be reused while the object returns the same array; else None."""
    mv = codec.view(a)
    alias = isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous
    return mv, (a if alias else None)


def _sim_ns(plant) -> int:
    return int(round(float(plant.sim_time) * 1e9))


# --------------------------------------------------------------------------- reference
def run_inprocess(plant, controller, n_steps: int, delay_samples: int = 0):
    """Reference loop in one process with the lockstep arithmetic.
    Returns ``(Y, U)``: Y[k] = sample k (n_steps+1 rows), U[k] = currents applied k -> k+1."""
    n = plant.n_axes
    Y = np.empty((n_steps + 1, n))
    U = np.empty((n_steps, n))
    ring = np.zeros((delay_samples + 1, n))
    y = np.asarray(plant.reset(), dtype=float)
    controller.reset()
    for k in range(n_steps):
        Y[k] = y
        c = np.asarray(controller.step(y), dtype=float)
        if delay_samples:
            ring[k % (delay_samples + 1)] = c
            u = ring[(k - delay_samples) % (delay_samples + 1)] if k >= delay_samples else np.zeros(n)
        else:
            u = c
        U[k] = u
        y = np.asarray(plant.advance(u), dtype=float)
    Y[n_steps] = y
    return Y, U


# --------------------------------------------------------------------------- plant
class _Fault(Exception):
    pass


class _Stop(Exception):
    """A stop request seen by the lockstep loop (the watchdog wakes it): a clean end."""


def run_plant(plant, run_id: str, *, listen=None, connect=None, mode: str = LOCKSTEP,
              n_steps: int, delay_samples: int = 0, reply_timeout: float | None = None,
              start_timeout: float = 30.0, wait_recorder: bool = False,
              max_overruns: int | None = None, warmup_steps: int | None = None,
              timing_batch: int = 200, meta: dict | None = None, stop=None, trace: bool = False,
              spin_s: float | None = None, guard_s: float | None = None, cpus=None,
              session=None, end_grace_s: float = 0.05) -> dict:
    """Run the plant side of a HIL run.  The plant normally *listens* (``listen=
    "tcp/127.0.0.1:PORT"``); controller and recorder connect.  Returns a summary dict;
    ``summary["fault"]`` is None or a one-line reason (see :func:`exit_code`)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if n_steps < 1:
        raise ValueError("n_steps must be >= 1")
    if delay_samples < 0 or (delay_samples and mode != LOCKSTEP):
        raise ValueError("delay_samples must be >= 0 and is only valid in lockstep mode")
    stop_fn = _stop_fn(stop)
    K = pr.keys(run_id)
    n = int(plant.n_axes)
    period = float(plant.period)
    period_ns = int(round(period * 1e9))
    if reply_timeout is None:
        reply_timeout = 10 * period if mode == REALTIME else max(10 * period, MIN_LOCKSTEP_TIMEOUT)
    if warmup_steps is None:
        warmup_steps = 0 if mode == LOCKSTEP else min(max(int(0.05 / period), 10), n_steps // 10)
    pin_cpus(cpus)
    if mode == REALTIME:
        set_timer_slack(1000)
    own_session = session is None
    if own_session:
        session = tr.open_session(listen, connect)
    sc, cc = pr.SensorCodec(n), pr.CurrentCodec(n)
    rejected = {r: 0 for r in pr.REASONS}
    counts = {"duplicates": 0, "late_replies": 0, "held": 0, "late_wakes": 0}
    lat = np.zeros(n_steps, np.int64)
    rtt = np.zeros(n_steps, np.int64)
    tet = np.zeros(n_steps, np.int64)
    flags = np.zeros(n_steps, np.uint8)
    Y = np.empty((n_steps + 1, n)) if trace else None
    U = np.empty((n_steps, n)) if trace else None
    state = {"peer_lost": False}
    fault = None
    end_reason = "completed"
    steps_done = 0
    overruns = 0
    wd = None
    objs = []
    ev = EventSink(session, K.events, "plant")
    sim_ns = 0
    k = 0
    cpu_s = None
    try:
        rxq: queue.SimpleQueue | None = None
        if mode == LOCKSTEP:
            sub = tr.declare_subscriber(session, K.currents, 1024)
            waker = tr.Waker(session, K.currents)
            wd = _Watchdog(waker, reply_timeout, stop_fn)
            wd.active = True
            on_lost = wd.wake
        else:
            rxq = queue.SimpleQueue()
            _now = time.perf_counter_ns

            def _cb(s, _q=rxq, _now=_now):
                _q.put((_now(), s.payload.to_bytes()))
            sub = tr.declare_callback_subscriber(session, K.currents, _cb)
            on_lost = lambda: rxq.put((time.perf_counter_ns(), None))  # noqa: E731
        pub = tr.declare_publisher(session, K.sensors)
        meta_pub = tr.declare_publisher(session, K.meta)
        timing_pub = tr.declare_publisher(session, K.timing)
        objs += [sub, pub, meta_pub, timing_pub]

        def _live(key, alive):
            if key == K.alive_controller and not alive:
                state["peer_lost"] = True
                on_lost()
        watch = tr.LivelinessWatch(session, K.alive_all, _live)
        token = tr.declare_token(session, K.alive_plant)
        objs += [watch, token]
        need = [K.alive_controller] + ([K.alive_recorder] if wait_recorder else [])
        watch.wait_for(need, start_timeout, stop_fn)
        tr.wait_matching(pub, start_timeout, "controller")
        if state["peer_lost"]:
            raise _Fault("controller lost before start")
        info = {"run_id": run_id, "mode": mode, "n_axes": n, "period_s": period,
                "rate_hz": 1.0 / period, "n_steps": n_steps, "delay_samples": delay_samples,
                "reply_timeout_s": reply_timeout, "versions": _versions(),
                "wall_start_ns": time.time_ns()}
        info.update(meta or {})
        meta_pub.put(pr.encode_meta(pr.RunMeta(info, wall_ns=time.time_ns())))
        ev.emit(pr.EventKind.RUN_START, json.dumps({"mode": mode, "n_steps": n_steps}), force=True)

        tbatch = {"seq": 0, "start": 0}

        replies = []          # lockstep: reply tuples of the current timing batch (for TET)

        def flush_timing(upto):
            a = tbatch["start"]
            if replies:
                tet[a:a + len(replies)] = [r[4] - r[3] for r in replies]
                replies.clear()
            if upto <= a:
                return
            t = pr.Timing(a, a * period_ns, period_ns, overruns, lat[a:upto], rtt[a:upto],
                          tet[a:upto], flags[a:upto], tbatch["seq"])
            tbatch["seq"] += 1
            tbatch["start"] = upto
            try:
                timing_pub.put(pr.encode_timing(t))
            except Exception:
                pass

        def reject(e: pr.ProtocolError, k):
            rejected[e.reason] += 1
            ev.emit(pr.EventKind.REJECTED, f"currents rejected at step {k}: {e}", k)

        y = np.asarray(plant.reset(), dtype=float)
        if y.shape != (n,):
            raise _Fault(f"plant.reset() returned shape {y.shape}, expected ({n},)")
        # hot path (see bridge/wire.py): vectors move as bytes through memoryviews of
        # preallocated arrays; timing rows are written through memoryviews, not numpy
        advance = getattr(plant, "advance_shared", None) or plant.advance
        fatal = tuple(getattr(plant, "FATAL", ()))
        has_status = hasattr(plant, "status")
        y_mv, y_obj = _view(sc, y)
        pack = sc.pack_from
        unpack = cc.unpack_into
        rx = np.zeros(n)                   # received currents (scratch)
        rx_mv = cc.view(rx)
        rtt_mv = memoryview(rtt)
        newton_warned = False

        def _advance(u, k):
            nonlocal y
            try:
                y = advance(u)
            except Exception as e:
                raise _Fault(f"plant.advance raised at step {k}: {type(e).__name__}: {e}")
            _check_output(k)

        def _check_output(k):
            """New output object -> new view; non-OK plant status -> fault or warning."""
            nonlocal y_obj, y_mv, newton_warned
            if y is not y_obj:
                try:
                    y_mv, y_obj = _view(sc, y)
                except (ValueError, TypeError) as e:
                    raise _Fault(f"plant output invalid at step {k}: {e}")
            if has_status and plant.status:
                rep = getattr(plant, "fault", None) or f"status {plant.status}"
                if plant.status in fatal:
                    raise _Fault(f"{rep} (step {k + 1})")
                if not newton_warned:
                    newton_warned = True
                    ev.emit(pr.EventKind.WARNING, f"plant: {rep} (step {k + 1})", k + 1,
                            _sim_ns(plant), force=True)

        def _encode(k, sim_ns):
            try:
                return pack(k, plant.step_index, sim_ns, wall(), y_mv)
            except pr.NonFiniteError as e:
                raise _Fault(f"plant output not finite at step {k} (t = {sim_ns * 1e-9:.6g} s): {e}")

        t_wall0 = time.perf_counter()
        t_cpu0 = time.process_time()
        put = pub.put
        wall = time.time_ns
        now = time.perf_counter_ns

        if mode == LOCKSTEP:
            wd.start()
            recv = sub.recv
            D = delay_samples + 1
            ring = np.zeros((D, n))
            ring_mv = [memoryview(ring[i]).cast("B") for i in range(D)]
            zeros = np.zeros(n)
            # hot path: one codec call per message (bridge/wire.py, C when built); the common
            # case is a well-formed reply with seq == k, anything else takes the validating
            # slow path (protocol.CurrentCodec.unpack_into)
            enc_s, dec_c = wire.encode_sensor, wire.decode_current
            t_batch = timing_batch
            next_flush = t_batch
            wmark = wd.progress
            extras = D > 1 or trace
            keep_reply = replies.append
            u = rx
            for k in range(n_steps):           # stop requests arrive as watchdog wake-ups
                step_i = plant.step_index
                sim_ns = step_i * period_ns      # sim time = step x period (docs/protocol.md)
                wmark[0] = k
                t0 = wall()                      # publish stamp and round-trip start
                msg = enc_s(y_mv, k, step_i, sim_ns, t0)
                if msg is None:
                    _encode(k, sim_ns)           # raises the non-finite fault with details
                put(msg)
                while True:
                    data = recv().payload.to_bytes()
                    h = dec_c(data, k, rx_mv)
                    if h is not None:
                        break
                    if not data:
                        if wd.pending > 0:
                            wd.pending -= 1
                            if state["peer_lost"]:
                                raise _Fault(f"controller lost (liveliness) at step {k}")
                            if wd.fired_mark == k:
                                raise _Fault(f"controller timeout: no reply to step {k} "
                                             f"within {reply_timeout * 1e3:g} ms")
                            if stop_fn is not None and stop_fn():
                                raise _Stop()
                            continue
                        reject(pr.TruncatedError("empty payload"), k)
                        continue
                    try:
                        hh = unpack(data, rx_mv)
                    except pr.ProtocolError as e:
                        reject(e, k)
                        continue
                    seq = hh[2]
                    if seq == k:
                        h = hh[2:7]
                        break
                    if seq < k:
                        counts["duplicates"] += 1
                        ev.emit(pr.EventKind.DUPLICATE, f"stale/duplicate reply seq {seq} "
                                f"while waiting for {k}", k, sim_ns)
                    else:
                        reject(pr.SequenceError(f"reply seq {seq} > outstanding {k}"), k)
                rtt_mv[k] = wall() - t0
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
                    raise _Fault(f"plant.advance raised at step {k}: {type(e).__name__}: {e}")
                if y is not y_obj or (has_status and plant.status):
                    _check_output(k)
                steps_done = k + 1
                if steps_done >= next_flush:
                    flush_timing(steps_done)
                    next_flush = steps_done + t_batch
        else:
            spin_ns = int((min(150e-6, 0.2 * period) if spin_s is None else spin_s) * 1e9)
            guard_fixed = None if guard_s is None else int(guard_s * 1e9)
            adv_est = 0.0
            u = np.zeros(n)                # currents applied (held on a missing reply)
            u_mv = cc.view(u)
            get = rxq.get
            Empty = queue.Empty
            enc_s, dec_c = wire.encode_sensor, wire.decode_current
            miss_run = 0
            miss_limit = max(1, int(round(reply_timeout / period)))
            # the miss watchdog arms at the first reply; until then the controller gets a start
            # grace (first messages over a fresh link can take ms on a loaded machine)
            first_limit = max(miss_limit, int(round(FIRST_REPLY_GRACE_S / period)))
            answered = False
            t_start = now() + max(2 * period_ns, 2_000_000)
            seen = -1
            for k in range(n_steps):
                if stop_fn is not None and (k & 63) == 0 and stop_fn():
                    end_reason = "stopped"
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
                msg = enc_s(y_mv, k, plant.step_index, sim_ns, wall())
                put(msg if msg is not None else _encode(k, sim_ns))   # _encode raises
                if late > period_ns:
                    flags[k] |= pr.FLAG_LATE_WAKE
                    counts["late_wakes"] += 1
                    # re-anchor the schedule at this late wake instead of bursting samples to
                    # catch up: the controller must see its sample period, never a burst
                    t_start += late
                    deadline += late
                # -- receive window for the reply to k
                guard = guard_fixed if guard_fixed is not None else spin_ns + int(2 * adv_est)
                window_end = deadline + period_ns - guard
                got = None
                alive = False
                while True:
                    rem = window_end - now()
                    try:
                        item = get(timeout=rem * 1e-9) if rem > 0 else rxq.get_nowait()
                    except Empty:
                        break
                    t_rx, data = item
                    if data is None:
                        raise _Fault(f"controller lost (liveliness) at step {k}")
                    h = dec_c(data, k, rx_mv)
                    if h is not None:            # fast path: the reply to k, well-formed
                        got = h
                        u_mv[:] = rx_mv
                        rtt[k] = t_rx - t0
                        tet[k] = h[4] - h[3]
                        break
                    try:
                        h = unpack(data, rx_mv)
                    except pr.ProtocolError as e:
                        reject(e, k)
                        continue
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
                    answered = True
                else:
                    flags[k] |= pr.FLAG_HELD
                    counts["held"] += 1
                    if alive:
                        answered = True
                        miss_run = 0
                    miss_run += 1
                    # during the warm-up the start grace still applies (first replies over a
                    # fresh link and cold caches can take ms); after it, reply_timeout
                    if answered and miss_run >= (first_limit if warm else miss_limit):
                        raise _Fault(f"controller timeout: no reply for {miss_run} periods "
                                     f"(last at step {k - miss_run}; {1 / period:g} Hz, "
                                     f"its liveliness token still present: hung, or too slow "
                                     f"for real time on this machine, see docs/hil.md)")
                    if not answered and miss_run >= first_limit:
                        raise _Fault(f"controller never answered: no reply in the first "
                                     f"{miss_run} periods ({miss_run * period * 1e3:g} ms)")
                if warm:
                    flags[k] |= pr.FLAG_WARMUP
                elif flags[k] & (pr.FLAG_HELD | pr.FLAG_LATE_WAKE):
                    overruns += 1
                    if max_overruns is not None and overruns > max_overruns:
                        raise _Fault(f"overrun limit: {overruns} overruns > {max_overruns} "
                                     f"(step {k})")
                if trace:
                    Y[k] = y
                    U[k] = u
                ta = now()
                _advance(u, k)
                adv_est = 0.9 * adv_est + 0.1 * (now() - ta)
                steps_done = k + 1
                if steps_done - tbatch["start"] >= timing_batch:
                    flush_timing(steps_done)
        if trace:
            Y[steps_done] = y
        wall_s = time.perf_counter() - t_wall0
        cpu_s = time.process_time() - t_cpu0
    except _Stop:
        end_reason = "stopped"
        wall_s = time.perf_counter() - t_wall0
        cpu_s = time.process_time() - t_cpu0
    except _Fault as f:
        fault = str(f)
        wall_s = time.perf_counter() - t_wall0 if "t_wall0" in locals() else 0.0
    except tr.TransportError as e:
        fault = str(e)
        wall_s = 0.0
    except KeyboardInterrupt:
        fault = "interrupted"
        wall_s = 0.0
    fault_wall_ns = None
    if fault is not None:
        fault_wall_ns = time.time_ns()
        ev.emit(pr.EventKind.FAULT, fault, steps_done, sim_ns, force=True)
        try:
            plant.safe_state()
        except Exception as e:  # still report the original fault
            fault += f" (safe_state raised {type(e).__name__}: {e})"
        end_reason = "fault"
    try:
        if "flush_timing" in locals():
            flush_timing(steps_done)
    except Exception:
        pass
    if wd is not None:
        wd.done = True
    ev.emit(pr.EventKind.RUN_END, json.dumps({"reason": end_reason, "steps": steps_done,
                                              "fault": fault}), steps_done, sim_ns, force=True)
    time.sleep(end_grace_s)          # let the controller/recorder see RUN_END before DELETE
    tr.close_quietly(*reversed(objs))
    if own_session:
        tr.close_quietly(session)
    sel = slice(min(warmup_steps, steps_done), steps_done)
    ok = sel
    summary = {
        "role": "plant", "run_id": run_id, "mode": mode, "steps": steps_done,
        "n_steps": n_steps, "period_s": period, "delay_samples": delay_samples,
        "wall_s": round(wall_s, 6),
        "cpu_us_per_step": round(cpu_s / steps_done * 1e6, 2) if steps_done and cpu_s else None,
        "steps_per_s": round(steps_done / wall_s, 1) if wall_s > 0 else 0.0,
        "warmup_steps": warmup_steps, "overruns": overruns, **counts,
        "latency_us": stats_us(rtt[ok][rtt[ok] > 0]) if steps_done else {"n": 0},
        "tet_us": stats_us(tet[ok][rtt[ok] > 0]) if steps_done else {"n": 0},
        "lateness_us": stats_us(lat[ok]) if mode == REALTIME and steps_done else {"n": 0},
        "latency_histogram_us": histogram_us(rtt[ok][rtt[ok] > 0]),
        "rejected": {k2: v for k2, v in rejected.items() if v},
        "rejected_total": sum(rejected.values()),
        "events_suppressed": ev.suppressed,
        "fault": fault, "fault_wall_ns": fault_wall_ns, "end_reason": end_reason,
    }
    if trace:
        summary["trace"] = {"y": Y[:steps_done + 1], "u": U[:steps_done]}
    return summary


# --------------------------------------------------------------------------- controller
def run_controller(controller, run_id: str, *, connect=None, listen=None,
                   sample_timeout: float = 1.0, start_timeout: float = 30.0, stop=None,
                   cpus=None, session=None) -> dict:
    """Run the controller side: answer every SensorSample with a CurrentCommand carrying
    the same seq.  Ends on the plant's RUN_END event (clean), or with a fault if the plant's
    liveliness token disappears without RUN_END, or no sample arrives for
    ``sample_timeout`` s after the first one."""
    stop_fn = _stop_fn(stop)
    K = pr.keys(run_id)
    n = int(controller.n_axes)
    pin_cpus(cpus)
    own_session = session is None
    if own_session:
        session = tr.open_session(listen, connect)
    sc, cc = pr.SensorCodec(n), pr.CurrentCodec(n)
    rejected = {r: 0 for r in pr.REASONS}
    state = {"ended": None, "plant_lost": False, "plant_seen": False}
    objs = []
    ev = EventSink(session, K.events, "controller")
    fault = None
    steps = dups = gaps = 0
    last_seq = -1
    try:
        sub = tr.declare_subscriber(session, K.sensors, 1024)
        waker = tr.Waker(session, K.sensors)
        wd = _Watchdog(waker, sample_timeout, stop_fn)
        pub = tr.declare_publisher(session, K.currents)
        objs += [sub, pub]

        def _on_event(s):
            try:
                e = pr.decode_event(s.payload.to_bytes())
            except pr.ProtocolError:
                return
            if e.kind == pr.EventKind.RUN_END and e.source in ("plant", "replay"):
                state["ended"] = e.text
                wd.wake()
        objs.append(tr.declare_callback_subscriber(session, K.events, _on_event))

        def _live(key, alive):
            if key == K.alive_plant:
                if alive:
                    state["plant_seen"] = True
                else:
                    state["plant_lost"] = True
                    wd.wake()
        watch = tr.LivelinessWatch(session, K.alive_all, _live)
        objs.append(watch)
        watch.wait_for([K.alive_plant], start_timeout, stop_fn)
        tr.wait_matching(pub, start_timeout, "plant")
        objs.append(tr.declare_token(session, K.alive_controller))
        controller.reset()
        wd.start()
        t_cpu0 = None
        recv = sub.recv
        wall = time.time_ns
        put = pub.put
        # hot path: see SensorCodec.pack_from (no numpy between recv() and put())
        step = getattr(controller, "step_shared", None) or controller.step
        y_in = np.zeros(n)
        y_mv = sc.view(y_in)
        unpack = sc.unpack_into
        c_obj, c_mv = None, None
        # hot path: one codec call per message (bridge/wire.py, C when built): a well-formed
        # sample with the next seq; anything else takes the validating slow path
        dec_s, enc_c = wire.decode_sensor, wire.encode_current
        wd.active = True
        wmark = wd.progress
        t_cpu0 = time.process_time()
        while True:
            data = recv().payload.to_bytes()
            t_rx = wall()
            h = dec_s(data, last_seq + 1, y_mv)
            if h is None:               # slow path: wake-ups, malformed, duplicates, gaps
                if not data:
                    if wd.pending > 0:
                        wd.pending -= 1
                        if state["ended"] is not None:
                            break
                        if state["plant_lost"]:
                            # RUN_END may still be in flight on the events callback
                            time.sleep(0.02)
                            if state["ended"] is not None:
                                break
                            raise _Fault(f"plant lost (liveliness) after {steps} samples")
                        if wd.fired_mark == steps and steps > 0:
                            raise _Fault(f"plant timeout: no sample for {sample_timeout * 1e3:g} "
                                         f"ms after seq {last_seq}")
                        if stop_fn is not None and stop_fn():
                            break
                        continue
                    rejected["truncated"] += 1
                    ev.emit(pr.EventKind.REJECTED, "sensor sample rejected: empty payload")
                    continue
                try:
                    hh = unpack(data, y_mv)
                except pr.ProtocolError as e:
                    rejected[e.reason] += 1
                    ev.emit(pr.EventKind.REJECTED, f"sensor sample rejected: {e}")
                    continue
                seq = hh[2]
                if seq <= last_seq:
                    dups += 1
                    ev.emit(pr.EventKind.DUPLICATE, f"duplicate/stale sample seq {seq} "
                            f"(last {last_seq}) ignored", hh[3], hh[4])
                    continue
                if seq != last_seq + 1:
                    gaps += seq - last_seq - 1
                    ev.emit(pr.EventKind.GAP, f"samples {last_seq + 1}..{seq - 1} missing",
                            hh[3], hh[4])
                h = hh[2:6]
            last_seq = h[0]
            try:
                c = step(y_in)
                if c is not c_obj:
                    c_mv, c_obj = _view(cc, c)
            except (ValueError, TypeError) as e:
                raise _Fault(f"controller output invalid at step {h[1]}: {e}")
            msg = enc_c(c_mv, last_seq, h[1], h[2], t_rx, wall())
            if msg is None:
                v = cc._vec.unpack(c_mv)
                bad = next(i for i, x in enumerate(v) if not math.isfinite(x))
                raise _Fault(f"controller produced non-finite currents at step {h[1]}: "
                             f"axis {bad} = {v[bad]}")
            put(msg)
            steps += 1
            wmark[0] = steps
    except _Fault as f:
        fault = str(f)
    except tr.TransportError as e:
        fault = str(e)
    except KeyboardInterrupt:
        fault = "interrupted"
    if fault:
        ev.emit(pr.EventKind.FAULT, fault, force=True)
    if "wd" in locals():
        wd.done = True
    tr.close_quietly(*reversed(objs))
    if own_session:
        tr.close_quietly(session)
    return {"role": "controller", "run_id": run_id, "steps": steps, "duplicates": dups,
            "gaps": gaps, "rejected": {k: v for k, v in rejected.items() if v},
            "rejected_total": sum(rejected.values()),
            "cpu_us_per_step": (round((time.process_time() - t_cpu0) / steps * 1e6, 2)
                                if steps and locals().get("t_cpu0") is not None else None),
            "plant_end": state["ended"], "fault": fault}
