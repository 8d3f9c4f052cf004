"""What a plant step costs where the loop runs it, against the warm step the bound uses.

    .venv/bin/python benchmarks/bench_cold_step.py [--scene scenes/paper_3amb.toml]
        [--rungs full,modal] [--cycles 6] [--block 500]

One process on the last CPU times ``PlantRunner.advance_shared`` (the plant's hot path) of each
rung, a block of ``--block`` calls per mode, the modes interleaved over ``--cycles`` cycles:

- ``warm``: back to back (what bench_sliced.py's bound and bench_step.py time);
- ``after a round trip``: each step after one zenoh round trip to a pong process on the same
  CPU (the scene's SensorSample size, Unix socket, ambhil's session settings): the loop's
  situation, where the messaging of both processes, zenoh's threads and the kernel run between
  two steps;
- ``after 1 MiB + Python``: after writing 1 MiB of numpy memory and some branchy Python (a
  sort, json, a regex; about 70 us): cache and branch-predictor pollution of the same size,
  with no other process or thread;
- ``after a 50 us sleep``: the CPU goes idle between steps (on a VM an idle vCPU halts: a VM
  exit, and the host runs something else on the core), as in real-time mode between periods;
- ``after a 50 us sleep, idle spinner``: the same with a SCHED_IDLE busy-loop process on the CPU,
  which runs only when nothing else would, so the CPU never idles.

Prints per rung and mode the median over cycles of each block's median step time, and the
excess over ``warm``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

MODES = ("warm", "after a round trip", "after 1 MiB + Python", "after a 50 us sleep",
         "after a 50 us sleep, idle spinner")
SPIN = ("import os, sys; os.sched_setaffinity(0, {%d}); "
        "os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0)); sys.stdout.write('spinning\\n'); "
        "sys.stdout.flush()\nwhile True: pass")


def main(argv=None):
    import numpy as np
    import bench_pingpong as pp
    from bench_run import steppers
    from ambhil.bridge.process import transport as tr
    from ambhil.bridge import protocol as pr
    from ambhil.bridge.process.timing import pin_cpus
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=os.path.join(ROOT, "scenes", "paper_3amb.toml"))
    ap.add_argument("--rungs", default="full,modal")
    ap.add_argument("--cycles", type=int, default=6)
    ap.add_argument("--block", type=int, default=500)
    a = ap.parse_args(argv)
    if a.cycles < 1 or a.block < 10:
        raise SystemExit(f"--cycles {a.cycles} --block {a.block}: need at least 1 cycle of 10 calls")
    last = os.cpu_count() - 1
    pin_cpus([last])
    runners = {r: steppers(a.scene, r) for r in a.rungs.split(",")}
    size = pr.SensorCodec(next(iter(runners.values()))[4]).size
    print(f"load {os.getloadavg()[0]:.1f}; all on CPU {last}; {a.cycles} cycles of {a.block} steps per mode",
          flush=True)
    ep = pp.endpoint_for("unix", "coldstep")
    code = (f"import sys; sys.path.insert(0, {ROOT!r}); sys.path.insert(0, {HERE!r}); "
            f"import bench_pingpong as b; b._pong({ep!r}, {size}, [{last}], 'unix')")
    pong = subprocess.Popen([sys.executable, "-c", code], env=dict(os.environ, ZENOH_RUNTIME=tr.RUNTIME))
    spinner = None
    s = tr.open_session(listen=ep)
    try:
        sub, pub = tr.declare_subscriber(s, "bench/pong"), tr.declare_publisher(s, "bench/ping")
        w = tr.LivelinessWatch(s, "bench/alive/*")
        w.wait_for(["bench/alive/pong"], 60)
        tr.wait_matching(pub, 60, "pong")
        payload = bytes(size)
        put, recv = pub.put, sub.recv
        for _ in range(2000):
            put(payload)
            recv()
        buf = np.zeros(1 << 17)
        rows = [((i * 7919) % 1000) / 7.0 for i in range(300)]
        doc = {f"k{i}": [i, str(i), {"a": i * 1.5}] for i in range(40)}
        pat, txt = re.compile(r"(\w+)=(\d+)"), " ".join(f"key{i}={i}" for i in range(60))

        def rt():
            put(payload)
            recv()

        def pollute():
            buf.__iadd__(1.0)
            sorted(rows)
            json.dumps(doc)
            pat.findall(txt)

        def nap():
            time.sleep(50e-6)
        before = {MODES[0]: None, MODES[1]: rt, MODES[2]: pollute, MODES[3]: nap, MODES[4]: nap}
        res = {(r, m): [] for r in runners for m in MODES}
        pc = time.perf_counter_ns
        for cyc in range(a.cycles):
            for m in MODES:
                if m == MODES[4]:
                    spinner = subprocess.Popen([sys.executable, "-c", SPIN % last], stdout=subprocess.PIPE, text=True)
                    spinner.stdout.readline()
                for r, (adv, u, *_rest) in runners.items():
                    f = before[m]
                    ts = []
                    for _ in range(a.block):
                        if f is not None:
                            f()
                        t0 = pc()
                        adv(u)
                        ts.append(pc() - t0)
                    res[(r, m)].append(statistics.median(ts) / 1e3)
                if spinner is not None:
                    spinner.kill()
                    spinner.wait()
                    spinner = None
        put(b"stop")
        for r in runners:
            warm = statistics.median(res[(r, MODES[0])])
            print(f"{r}:")
            for m in MODES:
                v = statistics.median(res[(r, m)])
                print(f"  {m:34s} {v:6.2f} us ({v - warm:+5.2f} us, {100 * (v / warm - 1):+4.0f} %)  "
                      f"cycles {', '.join(f'{x:.1f}' for x in res[(r, m)])}", flush=True)
    finally:
        if spinner is not None:
            spinner.kill()
        tr.close_quietly(s)
        try:
            pong.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pong.kill()
        tr.remove_socket_files(ep)


if __name__ == "__main__":
    main()
