"""zenoh's runtime layout in ambhil's processes (bridge/process/transport.py, issue 16) and the windowed
rate estimator of the plant's summary and the benchmarks (bridge/timing.window_rates)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from ambhil.bridge.process.timing import window_rates  # noqa: E402

_PROBE = r"""
import json, os, sys, time
from ambhil.bridge.process import transport as tr
ep = tr.unix_endpoint("layout-%%d" %% os.getpid())
a = tr.open_session(listen=ep)
b = tr.open_session(connect=ep)
sub = tr.declare_subscriber(a, "layout/x")
pub = tr.declare_publisher(b, "layout/x")
t_end = time.monotonic() + 60
while not pub.matching_status.matching and time.monotonic() < t_end:
    time.sleep(0.01)
for i in range(200):
    pub.put(bytes([i %% 256]) * 8)
got = [sub.recv().payload.to_bytes()[0] for _ in range(200)]
names = sorted({open(f"/proc/self/task/{t}/comm").read().strip().split("-")[0]
                for t in os.listdir("/proc/self/task")})
print(json.dumps({"env": os.environ["ZENOH_RUNTIME"], "runtime": tr.RUNTIME,
                  "ok": got == [i %% 256 for i in range(200)], "threads": names}))
tr.close_quietly(sub, pub, b, a)
tr.remove_socket_files(ep)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/task")
def test_sockets_are_read_by_the_receive_thread_without_acceptor_or_network_threads():
    """With acc and net handed over to rx, a listening and a connecting session exchange
    messages and the process has zenoh rx threads but no acc/net threads (each of which
    would take one wake-up per message before the receive thread)."""
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    p = subprocess.run([sys.executable, "-c", _PROBE % {}], capture_output=True,
                       text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    r = json.loads(p.stdout.strip().splitlines()[-1])
    assert r["env"] == r["runtime"] and "acc: (handover: rx)" in r["env"]
    assert r["ok"]
    assert "rx" in r["threads"], r["threads"]
    assert "acc" not in r["threads"] and "net" not in r["threads"], r["threads"]


def test_window_rates_against_known_rates():
    # 20 windows of just over 0.1 s at known rates, a mark every 10 counts: each window closes
    # on its own last mark, so the estimator must give the known rates' percentiles
    rng = np.random.default_rng(3)
    marks, c, t0, true = [(0, 0)], 0, 0, []
    T = 100_000_001
    for r in rng.uniform(2000, 9000, 20):
        n = int(round(r * 0.1 / 10))
        for k in range(1, n + 1):
            marks.append((c + 10 * k, t0 + T * k // n))
        c, t0 = c + 10 * n, t0 + T
        true.append(10 * n * 1e9 / T)
    w = window_rates(marks, 0.1)
    assert w["n"] == 20 and w["window_s"] == 0.1
    for q in (10, 50, 90):
        assert w[f"p{q}"] == pytest.approx(np.percentile(true, q), abs=0.1)
    assert window_rates([(0, 0), (5, 10)]) == {"n": 0}        # no full window
    assert window_rates([]) == {"n": 0}


@pytest.mark.parametrize("lowlatency", [True, False])
def test_sessions_pool_several_receive_batches(lowlatency):
    """zenoh recycles a link's receive buffers only from a pool of buffer_size / batch; with its
    default (one batch) the sample the loop still holds keeps the only buffer and every message
    allocates and zeroes a new 64 KiB batch (docs/performance.md, issue 16).  Every ambhil
    session, whatever its transport settings, pools at least two, and the same-host run's
    default is four."""
    from ambhil.bridge.process import transport as tr
    c = tr.make_config("tcp/127.0.0.1:0", lowlatency=lowlatency)
    size = json.loads(c.get_json("transport/link/rx/buffer_size"))
    batch = json.loads(c.get_json("transport/link/tx/batch_size"))
    assert batch == tr.BATCH
    assert size // batch >= 2 and size // batch == tr.rx_buffers()


def test_a_bad_receive_pool_setting_fails_the_session_with_its_name(monkeypatch):
    from ambhil.bridge.process import transport as tr
    monkeypatch.setenv("AMBHIL_RX_BUFFERS", "0")
    with pytest.raises(tr.TransportError, match=r"AMBHIL_RX_BUFFERS='0': expected a whole number"):
        tr.open_session(tr.unix_endpoint(f"badpool-{os.getpid()}"))
    monkeypatch.setenv("AMBHIL_RX_BUFFERS", "2")
    assert json.loads(tr.make_config().get_json("transport/link/rx/buffer_size")) == 2 * tr.BATCH
