"""What a busy *other* CPU costs the loop: one recorded `ambhil run` (plant and controller on
the last CPU, recorder on the others, as `--placement auto` places them) while a busy loop
pinned to the other CPUs is switched on and off every ``--toggle`` seconds.  The loop's rate
in the on and off windows comes from the recording itself (each SensorSample's publish wall
time), so both halves are measured in the same run, seconds apart.

Why: the recorder runs on the other CPU, off the loop's critical path, yet its own work
(transcoding and writing the MCAP) slowed the loop by a few per cent (docs/performance.md,
"The recorder's own work").  On this kind of VM two vCPUs are not independent: what one does
slows the other (shared core resources, caches, memory bandwidth on the host).

    .venv/bin/python benchmarks/bench_neighbour_load.py [--rung full] [--duration 20] [--toggle 0.5]

Prints the median steps/s of the windows with the busy loop and without, and the cost.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from ambhil.bridge.protocol.messages import ENCAP_LEN  # noqa: E402

_PUB_WALL = ENCAP_LEN + 32                     # SensorSample.publish_wall_ns (docs/protocol.md §3)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=os.path.join(ROOT, "scenes", "paper_3amb.toml"))
    ap.add_argument("--rung", default="full")
    ap.add_argument("--duration", type=float, default=20.0, help="simulated s (10k steps each)")
    ap.add_argument("--toggle", type=float, default=0.5, help="s between switching the busy loop")
    ap.add_argument("--settle", type=float, default=0.05, help="s left out after each switch")
    a = ap.parse_args(argv)
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        sys.exit("needs two CPUs or more: the loop on the last, the busy loop on the others")
    others = ",".join(map(str, cpus[:-1]))
    out = tempfile.mkdtemp(prefix="ambhil-neighbour-")
    run = subprocess.Popen([sys.executable, "-m", "ambhil.bridge.cli", "run", a.scene, "--rung", a.rung,
                            "--duration", str(a.duration), "--out", out, "--json"], cwd=ROOT,
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    hog = subprocess.Popen(["taskset", "-c", others, "sh", "-c", "while :; do :; done"])
    os.kill(hog.pid, signal.SIGSTOP)
    switches, on = [], False
    try:
        while run.poll() is None:
            on = not on
            os.kill(hog.pid, signal.SIGCONT if on else signal.SIGSTOP)
            switches.append((time.time_ns(), on))
            time.sleep(a.toggle)
    finally:
        hog.kill()
        hog.wait()
    summary = json.loads(run.stdout.read().strip().splitlines()[-1])
    if not summary.get("ok"):
        sys.exit(f"the run failed: {summary.get('failed') or summary.get('plant', {}).get('fault')}")
    from ambhil.bridge.recording.replay import load_run
    raw = load_run(glob.glob(os.path.join(out, "*.mcap"))[0])["sensors"]["raw"]
    pub = np.array([int.from_bytes(b[_PUB_WALL:_PUB_WALL + 8], "little", signed=True) for b in raw])
    rates: dict[bool, list[float]] = {True: [], False: []}
    settle = int(a.settle * 1e9)
    for (t0, state), (t1, _) in zip(switches, switches[1:]):
        n = np.count_nonzero((pub >= t0 + settle) & (pub < t1))
        if n > 100:                          # a window inside the loop (not start-up or the end)
            rates[state].append(n / ((t1 - t0 - settle) / 1e9))
    if len(rates[True]) < 3 or len(rates[False]) < 3:
        sys.exit(f"too few windows inside the loop ({len(rates[True])} on, {len(rates[False])} off): "
                 f"raise --duration")
    off, busy = np.median(rates[False]), np.median(rates[True])
    print(f"{a.rung} rung, recorded, loop on CPU {cpus[-1]}, busy loop on CPU {others} every other "
          f"{a.toggle:g} s window")
    print(f"  other CPU idle (but for the recorder): {off:.0f} steps/s (median of {len(rates[False])} windows)")
    print(f"  other CPU busy:                        {busy:.0f} steps/s (median of {len(rates[True])} windows)")
    print(f"  a busy neighbour costs the loop {100 * (1 - busy / off):+.1f} %")


if __name__ == "__main__":
    main()
