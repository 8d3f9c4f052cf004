"""Plant/controller nodes over zenoh in separate OS processes (loopback, random ports).

Also hosts the stand-in step objects and process helpers used by test_recorder.py and
test_replay.py (imported as ``test_nodes``)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

TESTS = os.path.dirname(os.path.abspath(__file__))

from ambhil.bridge import protocol as pr
from ambhil.bridge.process import transport as tr
from ambhil.bridge.process.config import ControllerNodeConfig, PlantNodeConfig  # noqa: E402
from ambhil.bridge.process.controller_node import run_controller  # noqa: E402
from ambhil.bridge.process.plant_node import run_plant  # noqa: E402
from ambhil.bridge.process.reference import run_inprocess  # noqa: E402


# ----------------------------------------------------------------- stand-in step objects
class SpringPlant:
    """Per axis a mass on a spring with light damping, exact zero-order-hold discretisation
    (x_{k+1} = Ad x_k + Bd u_k); output = displacement."""

    def __init__(self, n_axes=4, period=1e-3, wn=200.0, zeta=0.02, gain=1.0, x0=1e-4):
        from scipy.linalg import expm
        self.n_axes, self.period = n_axes, period
        A = np.array([[0.0, 1.0], [-wn ** 2, -2 * zeta * wn]])
        B = np.array([[0.0], [gain]])
        M = expm(np.block([[A, B], [np.zeros((1, 3))]]) * period)
        self.Ad, self.Bd = M[:2, :2].copy(), M[:2, 2].copy()
        self.x0 = x0
        self.safe = False
        self.reset()

    def reset(self):
        self.x = np.zeros((2, self.n_axes))
        self.x[0] = self.x0 * (1.0 + np.arange(self.n_axes))
        self.step_index, self.sim_time = 0, 0.0
        return self.x[0].copy()

    def advance(self, u):
        self.x = self.Ad @ self.x + np.outer(self.Bd, np.asarray(u, dtype=float))
        self.step_index += 1
        self.sim_time = self.step_index * self.period
        return self.x[0].copy()

    def safe_state(self):
        self.safe = True


class PController:
    """u = -kp*y - kd*(y - y_prev)/T (kd optional)."""

    def __init__(self, n_axes=4, kp=2e4, kd=50.0, period=1e-3):
        self.n_axes, self.kp, self.kd, self.T = n_axes, kp, kd, period
        self.prev = None

    def reset(self):
        self.prev = None

    def step(self, y):
        y = np.asarray(y, dtype=float)
        d = np.zeros_like(y) if self.prev is None else (y - self.prev) / self.T
        self.prev = y.copy()
        return -self.kp * y - self.kd * d


class SharedSpringPlant(SpringPlant):
    """SpringPlant with the bridge's fast-path interface (``advance_shared`` returns its own
    buffer, as PlantRunner does), keeping its own log of inputs and outputs: a lockstep run
    without ``trace`` (which the C loop of bridge/protocol/_plant_lockstep.c serves) can still be compared with
    the in-process reference.  From step ``raise_at`` its step raises, from ``nan_at`` its
    output is NaN, from ``status_at`` it reports a fatal status (as PlantRunner does)."""
    FATAL = (3,)

    def __init__(self, raise_at=None, nan_at=None, status_at=None, **kw):
        self.raise_at, self.nan_at, self.status_at = raise_at, nan_at, status_at
        self.status = 0
        super().__init__(**kw)

    def reset(self):
        y = super().reset()
        self.y = y.copy()
        self.log_y, self.log_u = [y.copy()], []
        return y

    def advance_shared(self, u):
        if self.raise_at is not None and self.step_index >= self.raise_at:
            raise RuntimeError("the plant step failed (test)")
        self.log_u.append(np.array(u, dtype=float))
        self.y[:] = self.advance(u)
        if self.nan_at is not None and self.step_index >= self.nan_at:
            self.y[0] = np.nan
        if self.status_at is not None and self.step_index >= self.status_at:
            self.status = 3
        self.log_y.append(self.y.copy())
        return self.y

    @property
    def fault(self):
        return "rotor reached the stator (test)" if self.status else None


class SharedPController(PController):
    """PController whose ``step_shared`` returns the same buffer each step (the fast path of
    bridge/process/controller_node.py, served by the C loop); from sample ``raise_at`` its step raises
    ValueError, from ``nan_at`` its output is NaN."""

    def __init__(self, raise_at=None, nan_at=None, **kw):
        super().__init__(**kw)
        self.raise_at, self.nan_at, self.n = raise_at, nan_at, 0
        self.out = np.zeros(self.n_axes)

    def step_shared(self, y):
        if self.raise_at is not None and self.n >= self.raise_at:
            raise ValueError("the controller step failed (test)")
        self.out[:] = self.step(y)
        if self.nan_at is not None and self.n >= self.nan_at:
            self.out[1] = np.nan
        self.n += 1
        return self.out


class HangingController(PController):
    """Answers ``hang_after`` samples, then stops answering (sleeps)."""

    def __init__(self, hang_after=50, **kw):
        super().__init__(**kw)
        self.hang_after, self.n = hang_after, 0

    def step(self, y):
        self.n += 1
        if self.n > self.hang_after:
            time.sleep(3600)
        return super().step(y)


class SlowController(PController):
    """Answers every sample, but takes ``delay`` s per step for steps in ``window``."""

    def __init__(self, window=(100, 140), delay=1.3e-3, **kw):
        super().__init__(**kw)
        self.window, self.delay, self.n = window, delay, 0

    def step(self, y):
        self.n += 1
        if self.window[0] <= self.n < self.window[1]:
            time.sleep(self.delay)
        return super().step(y)


class BlowUpPlant(SpringPlant):
    """Output turns NaN at ``at`` (a numerical blow-up)."""

    def __init__(self, at=50, **kw):
        super().__init__(**kw)
        self.at = at

    def advance(self, u):
        y = super().advance(u)
        return y * np.nan if self.step_index >= self.at else y


class TouchdownPlant(SpringPlant):
    """Reports a fatal status the way PlantRunner does (``status``, ``FATAL``, ``fault``)."""
    FATAL = (3,)

    def __init__(self, at=30, **kw):
        super().__init__(**kw)
        self.at, self.status = at, 0

    def advance(self, u):
        y = super().advance(u)
        if self.step_index >= self.at:
            self.status = 3
        return y

    @property
    def fault(self):
        return "rotor reached the stator (test)" if self.status else None


# ----------------------------------------------------------------- process helpers
PRE = f"import sys; sys.path[:0] = [{TESTS!r}]; import test_nodes as t; "


def py(code: str, env=None, **kw) -> subprocess.Popen:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", **(env or {}))
    return subprocess.Popen([sys.executable, "-c", PRE + code], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def _plant_proc(ep, run_id, n_steps, out_npz=None, kind="spring", slow_start=0.0, die_after=None,
                start_timeout=60, plant_kw=None, **kw):
    """A plant process.  ``slow_start``: declare itself (``starting/plant``) at once, then take
    that long before it is ready (a cold kernel compilation); ``die_after``: once the
    controller is there, exit that long later, never ready (a crash during start-up)."""
    from ambhil.bridge.process.startup import STARTING, PeerWatch, Presence
    plant = {"spring": SpringPlant, "blowup": BlowUpPlant, "touchdown": TouchdownPlant,
             "shared": SharedSpringPlant}[kind](**(plant_kw or {}))
    trace = kind != "shared"      # the shared plant keeps its own log (and the C loop runs)
    presence = None
    if slow_start or die_after is not None:
        presence = Presence(tr.open_session(ep, kw.get("connect")), run_id, "plant")
        presence.progress("compiling kernels (test) ...")
        if die_after is not None:
            PeerWatch(presence.session, run_id).wait(["controller"], 120, until=STARTING)
            time.sleep(die_after)
            os._exit(3)
        time.sleep(slow_start)
    s = run_plant(plant, PlantNodeConfig(run_id, n_steps, listen=ep, trace=trace,
                                         start_timeout=start_timeout, **kw), presence=presence)
    tr_ = s.pop("trace") if trace else {"y": np.array(plant.log_y), "u": np.array(plant.log_u)}
    if out_npz:
        np.savez(out_npz, y=tr_["y"], u=tr_["u"])
    print(json.dumps(s))


def _controller_proc(ep, run_id, kind="p", start_timeout=60, sample_timeout=60.0, **kw):
    c = {"p": PController, "hang": HangingController, "slow": SlowController,
         "shared": SharedPController}[kind](**kw)
    s = run_controller(c, ControllerNodeConfig(run_id, connect=ep, start_timeout=start_timeout,
                                               sample_timeout=sample_timeout))
    print(json.dumps(s))


def wait_samples(ep, run_id, count, proc, timeout=300):
    """Block until the plant has published ``count`` samples (the run is going), seen by a
    subscriber of our own; fails if ``proc`` (the plant) ends first."""
    s = connect_session(ep)
    seen = []
    sub = s.declare_subscriber(pr.keys(run_id).sensors, lambda smp: seen.append(1))
    t_end = time.monotonic() + timeout
    try:
        while len(seen) < count:
            assert proc.poll() is None, f"plant ended before {count} samples: {proc.communicate()}"
            assert time.monotonic() < t_end, "no samples"
            time.sleep(0.005)
    finally:
        tr.close_quietly(sub, s)


def last_json(p: subprocess.Popen, timeout=180) -> dict:
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:  # never leave an orphan behind a failed test
        p.kill()
        out, err = p.communicate()
    lines = [ln for ln in out.strip().splitlines() if ln.startswith("{")]
    assert lines, f"process printed no summary; stderr: {err[-2000:]}"
    return json.loads(lines[-1])


def announced_id(session, run_id, role, timeout=120.0) -> bytes:
    """The peer id ``role`` announced for the run (bridge/process/pairing.py), read from its token."""
    from ambhil.bridge.process.pairing import peer_key
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        for r in session.liveliness().get(peer_key(run_id, role), timeout=5.0):
            if r.ok is not None:
                return bytes.fromhex(str(r.ok.key_expr).rsplit("/", 1)[-1])
        time.sleep(0.01)
    raise AssertionError(f"{role} announced no peer id for {run_id}")


def endpoint() -> str:
    return tr.tcp_endpoint(tr.free_port())


def wait_listening(ep, timeout=300.0):
    """Block until something accepts TCP connections on ``ep`` (the plant is listening): a
    zenoh peer that connects too early gives up on that endpoint."""
    import socket
    host, port = ep.split("/", 1)[1].rsplit(":", 1)
    t_end = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((host, int(port)), timeout=1.0) as sk:
                if sk.getsockname() != sk.getpeername():   # not a TCP self-connect
                    return
        except OSError:
            pass
        if time.monotonic() > t_end:
            raise AssertionError(f"nothing listens on {ep}")
        time.sleep(0.02)


def connect_session(ep, timeout=300.0):
    """Our own zenoh session to a process just spawned that will listen on ``ep``: connect only
    once it listens (a peer that connects too early can give up on the endpoint: under two busy
    loops the link then never came, and the test waited 120 s for peers it could not see)."""
    wait_listening(ep, timeout)
    # an observer of the plant only: no gossip, no listener of its own, so no link but the one
    # to the plant is ever made (fewer links racing to form while the run starts)
    return tr.open_session(connect=ep, gossip=False)


def wait_alive(watch, keys, procs, timeout=300.0):
    """``watch.wait_for(keys)``, but a spawned process that has exited ends the wait at once
    with its output (not a 120 s wait for a peer that is dead, and no word of why)."""
    try:
        watch.wait_for(keys, timeout, stop=lambda: any(q.poll() is not None for q in procs))
    except tr.TransportError as e:
        outs = []
        for q in procs:
            if q.poll() is not None:
                out, err = q.communicate()
                outs.append(f"exit {q.returncode}: {(out or '')[-500:]} {(err or '')[-1500:]}")
            else:
                outs.append("running")
        raise AssertionError(f"{e}; processes: {outs}") from None


# ----------------------------------------------------------------- tests
def test_inprocess_reference_is_stable():
    Y, U = run_inprocess(SpringPlant(), PController(), 400)
    assert Y.shape == (401, 4) and U.shape == (400, 4)
    assert np.all(np.isfinite(Y)) and abs(Y[-1]).max() < abs(Y[0]).max()


@pytest.mark.parametrize("delay,loop", [(0, "python"), (2, "python"), (0, "c"), (0, "pure")])
def test_lockstep_two_processes_bit_identical(tmp_path, delay, loop):
    """Each way the lockstep loops run: ``python``: the plant's Python loop (a trace, or a
    latency in steps), and a controller returning a new array each step (the C loop hands every
    step back to Python); ``c``: step objects with the shared-buffer fast path, so both loops
    run their ordinary steps in C (bridge/protocol/_plant_lockstep.c, _controller_lockstep.c); ``pure``: the same objects with the C
    extension disabled (AMBHIL_PURE_WIRE=1: Python loops, Python codec)."""
    from ambhil.bridge.protocol import wire
    if loop == "c" and not wire.NATIVE:
        pytest.skip("the C extension ambhil.bridge.protocol._wire is not built")
    ep, run = endpoint(), f"lock{delay}{loop}"
    n = 600
    shared = loop in ("c", "pure")
    env = {"AMBHIL_PURE_WIRE": "1"} if loop == "pure" else None
    c = py(f"t._controller_proc({ep!r}, {run!r}, kind={'shared' if shared else 'p'!r})", env=env)
    p = py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r}, "
           f"delay_samples={delay}, kind={'shared' if shared else 'spring'!r})", env=env)
    sp, sc = last_json(p), last_json(c)
    if loop == "c":       # the C loops ran nearly every step (back in Python: the first
        # step, a new output object, and the watchdog's wake-ups every 0.1 s)
        assert sp["loop"] == sc["loop"] == "C", (sp, sc)
        assert sp["loop_handbacks"] < n // 10 and sc["loop_handbacks"] < n // 10, (sp, sc)
    else:
        assert sp["loop"] == sc["loop"] == "python", (sp, sc)
        if loop == "python":  # a new array each step: after two hand-backs the Python loop serves it
            assert 2 <= sc["loop_handbacks"] < 10, sc   # (a watchdog wake-up may come between)
    assert sp["fault"] is None and sc["fault"] is None, (sp, sc)
    assert sp["steps"] == n and sc["steps"] == n
    assert sp["rejected_total"] == 0 and sp["duplicates"] == 0
    Y, U = run_inprocess(SpringPlant(), PController(), n, delay_samples=delay)
    got = np.load(tmp_path / "tr.npz")
    assert np.array_equal(got["y"], Y), "trajectory differs from the in-process reference"
    assert np.array_equal(got["u"], U)
    # a different gain must give a different trajectory (the comparison can fail)
    Y2, _ = run_inprocess(SpringPlant(), PController(kp=2.1e4), n, delay_samples=delay)
    assert not np.array_equal(got["y"], Y2)


def test_default_reply_timeouts():
    """Real time: 10 controller periods; lockstep: only the last-resort cap (a live controller
    is waited for, a dead one is caught by liveliness)."""
    from ambhil.bridge.process.plant_node import PEER_WAIT_CAP_S, PlantNode
    kw = dict(listen=None, connect=None, n_steps=10, delay_samples=0, reply_timeout=None,
              start_timeout=1, wait_recorder=False, max_overruns=None, warmup_steps=None,
              timing_batch=200, meta=None, trace=False, spin_s=None, guard_s=None,
              cpus=None, end_grace_s=0, wait_cap_s=PEER_WAIT_CAP_S)
    assert PlantNode(SpringPlant(), PlantNodeConfig("x", mode="realtime", **kw)).cfg.reply_timeout == 10 * 1e-3
    assert PlantNode(SpringPlant(), PlantNodeConfig("x", mode="lockstep", **kw)).cfg.reply_timeout == PEER_WAIT_CAP_S >= 60


def _needs(rx):
    from ambhil.bridge.process.deadline import DeadlineTimer
    if rx == "deadline" and DeadlineTimer is None:
        pytest.skip("ambhil.bridge.process._deadline not built (pip install -e . with a C compiler)")


@pytest.mark.parametrize("mode,rx", [("realtime", "deadline"), ("realtime", "callback"),
                                     ("lockstep", None)])
def test_killed_controller_detected_by_liveliness(mode, rx):
    """kill -9 of the controller mid-run ends the run through its liveliness token, not a
    timeout: the reply timeout is set far beyond what the test waits (how fast: see
    python -m benchmarks.faults).  Real time with either receive path (bridge/process/deadline.py)."""
    _needs(rx)
    ep, run = endpoint(), f"kill-{mode}-{rx}"
    c = py(f"t._controller_proc({ep!r}, {run!r})")
    extra = f", rt_receive={rx!r}" if rx else ""
    p = py(f"t._plant_proc({ep!r}, {run!r}, 10**6, mode={mode!r}, reply_timeout=600.0{extra})")
    wait_samples(ep, run, 200, p)
    c.kill()
    sp = last_json(p, timeout=120)
    assert sp["fault"] and "controller lost (liveliness)" in sp["fault"], sp
    assert 0 < sp["steps"] < 10**6


def test_hung_controller_times_out_in_lockstep():
    """A controller that is alive but never answers again: lockstep waits for it up to the
    cap (--reply-timeout), then faults at the step it stopped answering."""
    ep, run = endpoint(), "hang"
    c = py(f"t._controller_proc({ep!r}, {run!r}, kind='hang', hang_after=100)")
    p = py(f"t._plant_proc({ep!r}, {run!r}, 5000, reply_timeout=2.0)")
    sp = last_json(p)
    c.kill()
    c.communicate()
    assert sp["fault"] and "controller timeout: no reply to step 100 within 2000 ms" in sp["fault"], sp
    assert sp["steps"] == 100


def test_lockstep_waits_through_an_os_stall(tmp_path):
    """Issue 10: a scheduling stall of the controller (SIGSTOP for 0.5 s, 5x the old 100 ms
    lockstep timeout) must not end a lockstep run: its liveliness token stays, the plant
    waits, and the run completes bit-identical to the in-process loop."""
    import signal
    ep, run, n = endpoint(), "stall", 20000
    c = py(f"t._controller_proc({ep!r}, {run!r})")
    p = py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r})")
    wait_samples(ep, run, 200, p)
    os.kill(c.pid, signal.SIGSTOP)
    time.sleep(0.5)
    os.kill(c.pid, signal.SIGCONT)
    sp, sc = last_json(p), last_json(c)
    assert sp["fault"] is None and sc["fault"] is None, (sp, sc)
    assert sp["steps"] == n
    Y, U = run_inprocess(SpringPlant(), PController(), n)
    got = np.load(tmp_path / "tr.npz")
    assert np.array_equal(got["y"], Y) and np.array_equal(got["u"], U)
    assert sp["latency_us"]["max"] >= 0.4e6, sp["latency_us"]   # the stall was inside the run


def test_peers_wait_for_a_slow_starting_plant(tmp_path):
    """Issue 10: a peer that is there but still starting (cold kernel compilation) is waited
    for however long it takes: the controller's start_timeout (1 s) only counts absence, and
    the plant takes 6 s in its "starting" state.  Its current step can be queried."""
    from ambhil.bridge.process.startup import STARTING, PeerWatch
    ep, run, n = endpoint(), "slowstart", 300
    p = py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r}, slow_start=6.0)")
    s = connect_session(ep)
    w = PeerWatch(s, run)
    try:
        w.wait(["plant"], 120, until=STARTING)
        assert w.state("plant") == STARTING
        assert w.query_progress("plant", timeout=10) == "plant: compiling kernels (test) ..."
    finally:
        w.undeclare()
        tr.close_quietly(s)
    c = py(f"t._controller_proc({ep!r}, {run!r}, start_timeout=1)")
    sp, sc = last_json(p), last_json(c)
    assert sp["fault"] is None and sc["fault"] is None, (sp, sc)
    assert sp["steps"] == n and sc["steps"] == n
    Y, U = run_inprocess(SpringPlant(), PController(), n)
    got = np.load(tmp_path / "tr.npz")
    assert np.array_equal(got["y"], Y) and np.array_equal(got["u"], U)


def test_peer_that_never_appears_times_out_on_absence():
    ep, run = endpoint(), "absent"
    # the controller listens itself (nobody to connect to); no plant ever comes
    c = py(f"import ambhil.bridge.process.controller_node as cn, json; print(json.dumps(cn.run_controller("
           f"t.PController(), t.ControllerNodeConfig({run!r}, listen={ep!r}, start_timeout=1.0))))")
    sc = last_json(c)
    assert sc["fault"] and "plant did not appear within 1 s" in sc["fault"], sc
    assert sc["steps"] == 0


def test_peer_dying_while_starting_is_detected_at_once():
    """A plant that declares itself and dies before it is ready: the controller (which would
    wait 10 minutes for an absent plant) gives up as soon as the token goes away."""
    ep, run = endpoint(), "diestart"
    p = py(f"t._plant_proc({ep!r}, {run!r}, 100, die_after=1.0)")
    c = py(f"t._controller_proc({ep!r}, {run!r}, start_timeout=600)")
    sc = last_json(c, timeout=120)
    p.communicate()
    assert p.returncode == 3
    assert sc["fault"] and "plant process died before the run started" in sc["fault"], sc
    assert "compiling kernels (test)" in sc["fault"] or "token" in sc["fault"]


def test_malformed_currents_rejected_and_counted(tmp_path):
    """A rogue peer injects malformed / NaN / stale currents: the plant rejects and counts
    them and still completes bit-identically with the real controller.

    The rogue poses as the recorder (the plant waits for the recorder token), so the run
    cannot start, and finish, before the rogue is connected: the bad messages are queued
    in the plant's subscriber before step 0, whatever the process start-up times.  Like a
    recorder it listens and plant and controller connect to it (the topology of `ambhil run`):
    a session of ours that connected to the plant once saw neither peer's token in 300 s under
    two busy loops, while plant and controller ran and paired."""
    ep, ep_r, run = endpoint(), endpoint(), "rogue"
    K = pr.keys(run)
    n = 300
    s = tr.open_session(listen=ep_r)
    c = py(f"t._controller_proc([{ep!r}, {ep_r!r}], {run!r})")
    p = py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r}, wait_recorder=True, "
           f"connect={ep_r!r})")
    pub = tr.declare_publisher(s, K.currents)
    w = tr.LivelinessWatch(s, K.alive_all)
    wait_alive(w, [K.alive_plant, K.alive_controller], (p, c))
    tr.wait_matching(pub, 60)
    # posing as the paired controller (its announced peer id in each message, but without the
    # run's key: protocol 3): the header checks name their reason, everything that gets past
    # them is not sealed by the controller (`auth`) or not its id (`peer`); the checks of the
    # content (nonfinite, axes, length) of sealed messages: tests/test_mac.py, test_protocol.py
    ctl_id = announced_id(s, run, "controller")
    cc = pr.CurrentCodec(4, me=ctl_id)
    good = cc.encode(0, 0, 0, 0, 0, np.zeros(4))
    bad = [b"", good[:20], b"\x01\x00\x00\x00" + good[4:], good[:4] + b"\x07" + good[5:],
           good[:-40] + np.array([np.nan]).tobytes() + good[-32:],
           pr.CurrentCodec(3, me=ctl_id).encode(0, 0, 0, 0, 0, [1, 2, 3]),
           good[:-32] + b"\x00" + good[-32:], good]
    for b in bad:
        pub.put(b)
    token = tr.declare_token(s, K.alive_recorder)      # now the plant may start
    sp = last_json(p)
    sc = last_json(c)
    tr.close_quietly(token, w, pub, s)
    assert sp["fault"] is None and sp["steps"] == n, sp
    assert sc["fault"] is None and sc["steps"] == n, sc
    assert sp["rejected_total"] == len(bad), sp
    for reason in ("truncated", "encapsulation", "version", "auth"):
        assert sp["rejected"].get(reason, 0) >= 1, (reason, sp["rejected"])
    assert sp["rejected"]["auth"] + sp["rejected"].get("peer", 0) == 4, sp["rejected"]
    Y, U = run_inprocess(SpringPlant(), PController(), n)
    got = np.load(tmp_path / "tr.npz")
    assert np.array_equal(got["y"], Y) and np.array_equal(got["u"], U)


def test_realtime_mode_paced_and_reports_timing():
    """Paced: 500 steps at 1 kHz cannot take less than 499 periods of wall time (the reply
    timeout is generous so that a stall of a loaded machine is counted, not fatal)."""
    ep, run = endpoint(), "rt"
    c = py(f"t._controller_proc({ep!r}, {run!r})")
    p = py(f"t._plant_proc({ep!r}, {run!r}, 500, mode='realtime', reply_timeout=2.0)")   # 1 kHz
    sp = last_json(p)
    last_json(c)
    assert sp["fault"] is None and sp["steps"] == 500, sp
    assert sp["wall_s"] >= 0.499, sp["wall_s"]
    assert sp["latency_us"]["n"] > 0 and sp["lateness_us"]["n"] > 0


def test_realtime_clock_starts_after_the_first_reply(tmp_path):
    """Issue 10: the controller's first reply takes 0.3 s (300 periods).  The plant holds its
    start state until then and starts the clock at that reply: the currents of step 0 are the
    controller's answer to sample 0 (not held zeros), and the first steps equal the in-process
    loop.  Before, the plant integrated open loop with held currents for those 300 periods."""
    ep, run, n = endpoint(), "rt-first", 200
    c = py(f"t._controller_proc({ep!r}, {run!r}, kind='slow', window=(1, 2), delay=0.3)")
    p = py(f"t._plant_proc({ep!r}, {run!r}, {n}, {str(tmp_path / 'tr.npz')!r}, mode='realtime', "
           f"reply_timeout=2.0)")
    sp, _ = last_json(p), last_json(c)
    assert sp["fault"] is None and sp["steps"] == n, sp
    Y, U = run_inprocess(SpringPlant(), PController(), n)
    got = np.load(tmp_path / "tr.npz")
    assert np.array_equal(got["u"][0], U[0]) and np.any(U[0] != 0)
    assert np.array_equal(got["y"][:2], Y[:2])


@pytest.mark.parametrize("kind,expect", [("blowup", "plant output not finite at step 50"),
                                         ("touchdown", "rotor reached the stator (test) (step 30)")])
def test_plant_numerical_fault_ends_run_with_when_and_where(kind, expect):
    ep, run = endpoint(), f"fault-{kind}"
    c = py(f"t._controller_proc({ep!r}, {run!r})")
    p = py(f"t._plant_proc({ep!r}, {run!r}, 400, kind={kind!r})")
    sp, sc = last_json(p), last_json(c)
    assert sp["fault"] and expect in sp["fault"], sp["fault"]
    assert sp["steps"] < 400 and sc["fault"] is None and sc["plant_end"], (sp, sc)


@pytest.mark.parametrize("side,kw,steps,expect", [
    ("plant", {"raise_at": 50}, 50, "plant.advance raised at step 50: RuntimeError: the plant step failed (test)"),
    ("plant", {"nan_at": 50}, 50, "plant output not finite at step 50"),
    ("plant", {"status_at": 30}, 29, "rotor reached the stator (test) (step 30)"),
    ("controller", {"raise_at": 40}, 40, "controller output invalid at step 40: the controller step failed (test)"),
    ("controller", {"nan_at": 40}, 40, "controller produced non-finite currents at step 40: axis 1 = nan"),
])
@pytest.mark.parametrize("loop", ["C", "python"])
def test_step_object_failures_in_the_c_loops_name_the_step(side, kw, steps, expect, loop):
    """A failing step object in the C loops (bridge/protocol/_plant_lockstep.c, _controller_lockstep.c) ends the run with the same fault,
    naming the same step, as the Python loops (AMBHIL_PURE_WIRE=1): the step raised, its
    output is not finite, the plant reports a fatal status."""
    from ambhil.bridge.protocol import wire
    if loop == "C" and not wire.NATIVE:
        pytest.skip("the C extension ambhil.bridge.protocol._wire is not built")
    env = {"AMBHIL_PURE_WIRE": "1"} if loop == "python" else None
    ep, run = endpoint(), f"cfail-{side}-{next(iter(kw))}-{loop}"
    ckw = f", {next(iter(kw))}={next(iter(kw.values()))}" if side == "controller" else ""
    c = py(f"t._controller_proc({ep!r}, {run!r}, kind='shared'{ckw})", env=env)
    p = py(f"t._plant_proc({ep!r}, {run!r}, 400, kind='shared', "
           f"plant_kw={kw if side == 'plant' else {}!r})", env=env)
    sp, sc = last_json(p), last_json(c)
    assert sp["loop"] == sc["loop"] == loop, (sp, sc)
    if side == "plant":           # the steps completed, as the Python loop counts them
        assert sp["fault"] and expect in sp["fault"], sp["fault"]
        assert sp["steps"] == steps, sp["steps"]
        assert sc["fault"] is None and sc["plant_end"], sc
    else:                         # replies sent; the plant has advanced with each of them
        assert sc["fault"] and expect in sc["fault"], sc["fault"]
        assert sc["steps"] == steps and sp["steps"] == steps and sp["fault"], (sp, sc)


@pytest.mark.parametrize("rx", ["deadline", "callback"])
def test_realtime_hung_controller_detected_by_missing_replies(rx):
    """A controller that is alive but stops answering: the 300th silent period (reply timeout
    0.3 s at 1 kHz) ends the run; the default is 10 periods (test_default_reply_timeouts).
    With the deadline receive, every silent period is ended by the timer thread (one fire
    each): the loop never waits past a window."""
    _needs(rx)
    ep, run = endpoint(), f"rt-hang-{rx}"
    c = py(f"t._controller_proc({ep!r}, {run!r}, kind='hang', hang_after=100)")
    p = py(f"t._plant_proc({ep!r}, {run!r}, 5000, mode='realtime', reply_timeout=0.3, "
           f"rt_receive={rx!r})")
    sp = last_json(p)
    c.kill()
    c.communicate()
    assert sp["fault"] and "no reply for 300 periods" in sp["fault"], sp["fault"]
    assert sp["rt_receive"]["mode"] == rx, sp["rt_receive"]
    if rx == "deadline":
        assert sp["rt_receive"]["timer_fires"] >= 300, sp["rt_receive"]
    # samples 100.. are never answered; the 300th missing reply (sample 399 at the earliest)
    assert 100 + 299 <= sp["steps"] < 5000, sp["steps"]


@pytest.mark.parametrize("rx", ["deadline", "callback"])
def test_realtime_late_controller_is_held_not_declared_dead(rx):
    """Late replies are discarded and the last currents held (overruns), but a controller that
    keeps answering, however late, is alive: no fault."""
    _needs(rx)
    ep, run = endpoint(), f"rt-late-{rx}"
    c = py(f"t._controller_proc({ep!r}, {run!r}, kind='slow', window=(200, 600), delay=1.3e-3)")
    # 100 periods: ~400 late periods in a row would trip it if late replies did not count as alive
    p = py(f"t._plant_proc({ep!r}, {run!r}, 1000, mode='realtime', reply_timeout=0.1, "
           f"rt_receive={rx!r})")
    sp, _ = last_json(p), last_json(c)
    assert sp["fault"] is None, sp["fault"]
    assert sp["steps"] == 1000 and sp["late_replies"] >= 100 and sp["held"] >= 100, sp
    assert sp["overruns"] >= 100


def test_realtime_slow_start_within_warmup_is_not_a_dead_controller():
    """A controller that stalls 200 periods early in the run (cold caches) is still inside the
    warm-up (400 periods here), where the start grace applies: held, no fault.  Without that
    grace the 100-period rule would end the run at about step 103."""
    ep, run = endpoint(), "rt-slowstart"
    c = py(f"t._controller_proc({ep!r}, {run!r}, kind='slow', window=(3, 4), delay=0.2)")
    p = py(f"t._plant_proc({ep!r}, {run!r}, 1000, mode='realtime', reply_timeout=0.1, "
           f"warmup_steps=400)")
    sp, _ = last_json(p), last_json(c)
    assert sp["warmup_steps"] == 400, sp
    assert sp["fault"] is None and sp["steps"] == 1000, sp["fault"]
    # the stall held more periods than the 100-period reply timeout allows after the warm-up
    # (about 200 on a quiet machine; fewer under load, where late wakes of the plant re-anchor
    # its schedule and skip periods: 143 seen with two busy loops on both cores)
    assert sp["held"] > 100, sp


def test_free_port_never_hands_out_the_same_port_twice(monkeypatch):
    """Two endpoints chosen in a row (plant and recorder) must differ even when the random
    draw repeats: neither has bound its port yet, so both would look free."""
    import random
    monkeypatch.setattr(random.Random, "randrange", lambda self, a, b: 20001)
    first = tr.free_port()
    second = tr.free_port()
    assert second != first
