"""The real-time plant's PM QoS request on the CPUs' wake-up latency (bridge/process/timing.py,
issue 16): checked against what the kernel reports, not against our own bookkeeping."""
import os
import sys

import pytest

from ambhil.bridge.process import timing

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
    from ambhil.bridge.process.config import PlantNodeConfig
    from ambhil.bridge.process.plant_node import PlantNode
    kw = dict(listen=None, connect=None, n_steps=10, delay_samples=0, reply_timeout=None,
              start_timeout=1, wait_recorder=False, max_overruns=None, warmup_steps=None,
              timing_batch=200, meta=None, trace=False, spin_s=None, guard_s=None,
              cpus=None, end_grace_s=0.05, wait_cap_s=1.0)

    class P:
        n_axes, period = 2, 1e-3
    assert PlantNode(P(), PlantNodeConfig("x", mode="lockstep", cpu_wake_us=0, **kw)).cfg.cpu_wake_us is None
    assert PlantNode(P(), PlantNodeConfig("x", mode="realtime", cpu_wake_us=0, **kw)).cfg.cpu_wake_us == 0


def test_cpuidle_driver_is_read_from_the_kernel_file(monkeypatch, tmp_path):
    f = tmp_path / "current_driver"
    f.write_text("haltpoll\n")
    monkeypatch.setattr(timing, "CPUIDLE_DRIVER", str(f))
    assert timing.cpuidle_driver() == "haltpoll"
    monkeypatch.setattr(timing, "CPUIDLE_DRIVER", str(tmp_path / "absent"))
    assert timing.cpuidle_driver() is None


@pytest.mark.parametrize("driver, effective", [("none", False), ("haltpoll", True), (None, None)])
def test_request_says_when_it_cannot_act(monkeypatch, tmp_path, driver, effective):
    """Without a cpuidle driver an idle CPU halts whatever PM QoS asks (measured: a step after a
    50 us sleep costs the same with the request held), so a held request must not read as if it
    kept the CPUs polling.  The device is a plain file here, so no root is needed."""
    dev = tmp_path / "cpu_dma_latency"
    dev.write_bytes(b"")
    monkeypatch.setattr(timing, "CPU_LATENCY_DEV", str(dev))
    drv = tmp_path / "current_driver"
    if driver is not None:
        drv.write_text(driver + "\n")
    monkeypatch.setattr(timing, "CPUIDLE_DRIVER", str(drv))
    q = timing.CpuWakeLatency(0)
    try:
        assert q.held and q.status.startswith("held at 0 us")
        assert dev.read_bytes() == (0).to_bytes(4, sys.byteorder, signed=True)
        assert q.effective is effective
        assert ("no effect here" in q.status) == (effective is False), q.status
    finally:
        q.release()
