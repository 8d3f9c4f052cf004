"""What a plant or controller process is told to do: one frozen dataclass each, built once (by
the CLI from its flags, by a test or benchmark directly) and passed whole to
:func:`ambhil.bridge.process.plant_node.run_plant` / :func:`ambhil.bridge.process.controller_node.
run_controller`, which keep it as ``node.cfg`` and read every field there (no copies).

The step object (``plant``, ``controller``) and the live objects of the process (its zenoh
``session``, its :class:`~ambhil.bridge.process.startup.Presence`, a ``stop`` callable or event)
are not configuration: they are passed beside it.

A value that depends on the plant (the default ``reply_timeout`` of 10 periods, the real-time
warm-up) is left None here and settled by the node, which knows the period: its ``node.cfg``
is :meth:`PlantNodeConfig.settled`, a copy with those values filled in.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

LOCKSTEP = "lockstep"
REALTIME = "realtime"
MODES = (LOCKSTEP, REALTIME)
CURRENTS_AT = ("sample", "arrival")
PEER_WAIT_CAP_S = 300.0        # s; last-resort cap on waiting for a live peer (lockstep reply,
                               # real-time first reply); a dead peer is caught by liveliness


@dataclass(frozen=True)
class PlantNodeConfig:
    """The plant process's run (docs: :func:`ambhil.bridge.process.plant_node.run_plant`).

    ``listen`` / ``connect``: zenoh endpoints (the plant normally listens).  ``mode``: lockstep or
    realtime.  ``n_steps``: controller periods to run.  ``delay_samples``: lockstep, apply the
    currents of sample k-n.  ``reply_timeout`` (s): real time, the controller is dead after that
    long without a reply (default 10 periods); lockstep, a last-resort cap (default
    ``wait_cap_s``).  ``start_timeout`` (s): how long a peer may be *absent*.  ``wait_recorder``:
    start only once a recorder is present.  ``max_overruns``: real time, halt after that many.
    ``warmup_steps``: real time, periods not counted (default: 50 ms, at least 10, at most a
    tenth of the run).  ``timing_batch``: periods per Timing message.  ``meta``: the RunMeta
    dict.  ``trace``: keep every sample and current (summary ``trace``).  ``spin_s`` /
    ``guard_s``: real-time pacing.  ``cpus``: pin the process.  ``end_grace_s``: wait for the
    last replies at the end.  ``currents_at`` (real time): ``sample`` or ``arrival``.
    ``cpu_wake_us`` (real time): the PM QoS request (None: none).  ``rt_receive`` (real time):
    ``auto``, ``deadline`` or ``callback``.  ``secret``: the run's 32-byte secret (None: an
    unauthenticated run, ``insecure`` saying it was asked for off loopback; docs/protocol.md
    5.3)."""
    run_id: str
    n_steps: int
    mode: str = LOCKSTEP
    listen: str | None = None
    connect: list[str] | str | None = None
    delay_samples: int = 0
    reply_timeout: float | None = None
    start_timeout: float = 30.0
    wait_recorder: bool = False
    max_overruns: int | None = None
    warmup_steps: int | None = None
    timing_batch: int = 200
    meta: dict | None = None
    trace: bool = False
    spin_s: float | None = None
    guard_s: float | None = None
    cpus: list[int] | None = None
    end_grace_s: float = 0.05
    wait_cap_s: float = PEER_WAIT_CAP_S
    currents_at: str = "sample"
    cpu_wake_us: int | None = 0
    rt_receive: str = "auto"
    secret: bytes | None = field(default=None, repr=False)   # the run secret (docs/protocol.md 5.3)
    insecure: bool = False        # no secret, said so (--insecure)

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.n_steps < 1:
            raise ValueError("n_steps must be >= 1")
        if self.delay_samples < 0 or (self.delay_samples and self.mode != LOCKSTEP):
            raise ValueError("delay_samples must be >= 0 and is only valid in lockstep mode")
        if self.currents_at not in CURRENTS_AT:
            raise ValueError(f"currents_at must be one of {CURRENTS_AT}, got {self.currents_at!r}")
        if self.currents_at == "arrival" and self.mode != REALTIME:
            raise ValueError("currents applied at their arrival: real-time mode only")

    def settled(self, period: float) -> PlantNodeConfig:
        """This run with what depends on the plant's ``period`` (s) filled in, as the node
        keeps it (``node.cfg``): ``reply_timeout`` (real time 10 periods, lockstep
        ``wait_cap_s``), ``warmup_steps`` (real time 50 ms, at least 10, at most a tenth of
        the run; lockstep 0) and ``cpu_wake_us`` (lockstep None: no request)."""
        realtime = self.mode == REALTIME
        reply_timeout, warmup_steps = self.reply_timeout, self.warmup_steps
        if reply_timeout is None:
            reply_timeout = 10 * period if realtime else self.wait_cap_s
        if warmup_steps is None:
            warmup_steps = min(max(int(0.05 / period), 10), self.n_steps // 10) if realtime else 0
        return replace(self, reply_timeout=reply_timeout, warmup_steps=warmup_steps,
                       cpu_wake_us=self.cpu_wake_us if realtime else None)


@dataclass(frozen=True)
class ControllerNodeConfig:
    """The controller process's run (docs: :func:`ambhil.bridge.process.controller_node.
    run_controller`): ``connect`` / ``listen`` zenoh endpoints; ``sample_timeout`` (s) a
    last-resort cap on a silent but live plant; ``start_timeout`` (s) how long the plant may be
    *absent*; ``cpus`` pin the process; ``secret`` / ``insecure`` as for the plant."""
    run_id: str
    connect: list[str] | str | None = None
    listen: str | None = None
    sample_timeout: float = 300.0
    start_timeout: float = 30.0
    cpus: list[int] | None = None
    secret: bytes | None = field(default=None, repr=False)   # the run secret (docs/protocol.md 5.3)
    insecure: bool = False
