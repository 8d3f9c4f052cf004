"""Recorder throughput: a publisher process floods SensorSample+CurrentCommand pairs as fast
as it can (reliable, BLOCK congestion control) into a recorder process; reports messages/s
written (first to last receive time) and loss.  Median of several runs.

    .venv/bin/python -m benchmarks.recorder [--messages 200000] [--repeat 3]
"""
from __future__ import annotations

import json
import os
import subprocess
import tempfile
import time

from benchmarks import common


def _flood(ep, run_id, n_msgs):
    import numpy as np
    from ambhil.bridge import protocol as pr
    from ambhil.bridge.process import transport as tr
    K = pr.keys(run_id)
    s = tr.open_session(listen=ep)
    toks = [tr.declare_token(s, K.alive_plant), tr.declare_token(s, K.alive_controller)]
    ps, pc = tr.declare_publisher(s, K.sensors), tr.declare_publisher(s, K.currents)
    evp = tr.declare_publisher(s, K.events)
    w = tr.LivelinessWatch(s, K.alive_all)
    w.wait_for([K.alive_recorder], 30)
    tr.wait_matching(ps, 10)
    time.sleep(0.05)
    sc, cc = pr.SensorCodec(4), pr.CurrentCodec(4)
    y = np.ones(4)
    t0 = time.perf_counter()
    for k in range(n_msgs // 2):
        ps.put(sc.encode(k, k, k * 100_000, k, y))
        pc.put(cc.encode(k, k, k * 100_000, k, k, y))
    dt = time.perf_counter() - t0
    evp.put(pr.encode_event(pr.Event(pr.EventKind.RUN_END, "bench end", "plant")))
    print(json.dumps({"sent": 2 * (n_msgs // 2) + 1, "publish_rate": round(n_msgs / dt)}))
    time.sleep(1.0)
    tr.close_quietly(w, ps, pc, evp, *toks, s)


def _rec(ep, run_id, out):
    from ambhil.bridge.recording.recorder import RecorderConfig, record
    print(json.dumps(record(run_id, out, RecorderConfig(connect=ep, start_timeout=30, source="wire"))))


def one_run(n_msgs: int) -> dict:
    from ambhil.bridge.process.transport import free_port, tcp_endpoint
    from mcap.reader import make_reader
    ep = tcp_endpoint(free_port())
    out = os.path.join(tempfile.mkdtemp(), "bench.mcap")
    pre = "from benchmarks import recorder as b; "
    r = common.popen(pre + f"b._rec({ep!r}, 'bench', {out!r})", stdout=subprocess.PIPE, text=True)
    f = common.run(pre + f"b._flood({ep!r}, 'bench', {n_msgs})", timeout=600)
    ro, _ = r.communicate(timeout=600)
    fl = json.loads(f.stdout.strip().splitlines()[-1])
    rs = json.loads(ro.strip().splitlines()[-1])
    times = []
    with open(out, "rb") as fh:
        for _, ch, m in make_reader(fh).iter_messages(log_time_order=False):
            if not ch.topic.endswith("events"):
                times.append(m.publish_time)       # wall time of arrival (log_time: simulation time)
    rate = (len(times) - 1) / ((max(times) - min(times)) / 1e9)
    return {"sent": fl["sent"], "recorded": rs["messages"], "lost": fl["sent"] - rs["messages"],
            "publish_rate": fl["publish_rate"], "record_rate": round(rate),
            "bytes": os.path.getsize(out)}


def main(argv=None):
    ap = common.parser(__doc__, repeat=3)
    ap.add_argument("--messages", type=int, default=200_000)
    a = ap.parse_args(argv)
    common.header("recorder", "recorder throughput, a publisher flooding sensor/current pairs")
    runs = []
    for i in range(a.repeat):
        r = one_run(a.messages)
        runs.append(r)
        print(f"run {i + 1}: recorded {r['recorded']}/{r['sent']} (lost {r['lost']}), "
              f"{r['record_rate']} msg/s written, publisher offered {r['publish_rate']} msg/s, "
              f"{r['bytes'] / r['recorded']:.1f} B/msg", flush=True)
    common.report("messages written per s", [r["record_rate"] for r in runs],
                  note=f"lost {max(r['lost'] for r in runs)} (max)")


if __name__ == "__main__":
    main()
