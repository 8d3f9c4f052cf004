"""The real-time plant's PM QoS request on the CPUs' wake-up latency (bridge/timing.py,
issue 16): checked against what the kernel reports, not against our own bookkeeping."""
import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bridge import timing  # noqa: E402

DEV = timing.CPU_LATENCY_DEV


def _kernel_value() -> int:
    """The kernel's current aggregate wake-up latency constraint (reading the device)."""
    with open(DEV, "rb") as f:
        return int.from_bytes(f.read(4), sys.byteorder, signed=True)


@pytest.mark.skipif(not (os.path.exists(DEV) and os.access(DEV, os.W_OK)),
                    reason=f"{DEV} absent or not writable here (the request needs root)")
def test_request_is_in_force_while_held_and_gone_after():
    before = _kernel_value()
    q = timing.CpuWakeLatency(3)
    try:
        assert q.held and q.status.startswith("held at 3 us"), q.status
        assert _kernel_value() <= 3           # the kernel takes the smallest request
    finally:
        q.release()
    assert not q.held
    assert _kernel_value() == before          # nothing left behind


def test_unavailable_device_is_reported_not_fatal(monkeypatch, tmp_path):
    monkeypatch.setattr(timing, "CPU_LATENCY_DEV", str(tmp_path / "no-such-device"))
    q = timing.CpuWakeLatency(0)
    assert not q.held and q.status.startswith("unavailable (") and "No such file" in q.status
    q.release()
    assert timing.CpuWakeLatency(None).status == "not requested"


def test_lockstep_run_makes_no_request_and_realtime_reports_it(tmp_path):
    """`ambhil plant`'s summary: lockstep holds nothing; real time says what it got."""
    from bridge.plant_node import PlantNode
    kw = dict(listen=None, connect=None, n_steps=10, delay_samples=0, reply_timeout=None,
              start_timeout=1, wait_recorder=False, max_overruns=None, warmup_steps=None,
              timing_batch=200, meta=None, stop=None, trace=False, spin_s=None, guard_s=None,
              cpus=None, session=None, end_grace_s=0.05, presence=None, wait_cap_s=1.0)

    class P:
        n_axes, period = 2, 1e-3
    assert PlantNode(P(), "x", mode="lockstep", cpu_wake_us=0, **kw).cpu_wake_us is None
    assert PlantNode(P(), "x", mode="realtime", cpu_wake_us=0, **kw).cpu_wake_us == 0
