"""Real-time round trips of plant and controller on two hosts: loopback vs a veth link vs a veth
link with delay and jitter.

    .venv/bin/python -m benchmarks.netns [--links lo,0:0,100:50] [--rate 500] [--seconds 2]
        [--repeat 3] [--scene scenes/net_rigid_1khz.toml]

(root: network namespaces, tests/netns.py.)  Each link: ``lo`` = plant, controller and recorder
on loopback in one namespace; ``D:J`` = plant and recorder in one namespace, controller in
another, joined by a veth pair (``0:0``) or by a link delaying each frame D +- J us each way
(netem where the kernel has it, else the relay namespace of tests/netns.py, which adds its own
forwarding time).  Each run: ``ambhil record``/``plant``/``controller`` (the mesh of ``ambhil
run``, unpinned) in real time for ``--seconds`` at ``--rate`` (the scene's controller rate
replaced), reply timeout 2 s so stalls are counted, not fatal.  Printed per link, median over
``--repeat`` fresh runs (interleaved): round trip p50/p99/max (us, plant publish -> reply
received), overruns (held or late-wake periods after the warm-up), and the runs' spread.
"""
from __future__ import annotations

import statistics
import tempfile
from pathlib import Path

from benchmarks import common
from tests import netns


def one(link: str, scene: Path, seconds: float, tmp: Path, k: int) -> dict:
    net = netns.Loopback() if link == "lo" else netns.NetPair("bench", *(float(x) for x in link.split(":")))
    with net:
        res = net.run(str(scene), f"b{k}", str(tmp), mode="realtime",
                      plant_args=["--duration", str(seconds), "--reply-timeout", "2000"])
        what = net.describe().split(" (")[0]
    sp, err, code = res["plant"]
    if sp is None:
        raise SystemExit(f"{what}: plant gave no summary: {err.strip().splitlines()[-1:]}")
    counted = max(sp["steps"] - sp["warmup_steps"], 1)
    return {"what": what, "p50": sp["latency_us"].get("p50"), "p99": sp["latency_us"].get("p99"),
            "max": sp["latency_us"].get("max"), "overruns": 100.0 * sp["overruns"] / counted,
            "fault": sp["fault"]}


def main(argv=None) -> None:
    ap = common.parser(__doc__, repeat=3)
    ap.add_argument("--links", default="lo,0:0,100:50")
    ap.add_argument("--rate", type=float, default=500.0)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--scene", default="net_rigid_1khz")
    a = ap.parse_args(argv)
    why = netns.unavailable()
    if why:
        raise SystemExit(f"benchmarks.netns: {why}")
    common.header("netns", "real-time round trips across a network link")
    print(f"# {a.rate:g} Hz, {a.seconds:g} s per run, {a.repeat} runs")
    links = a.links.split(",")
    rows = {ln: [] for ln in links}
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "scene.toml"
        import re
        scene.write_text(re.sub(r"sample_rate\s*=\s*[0-9.eE+-]+", f"sample_rate = {a.rate:g}",
                                Path(common.scene(a.scene)).read_text()))
        k = 0
        for _ in range(a.repeat):
            for ln in links:
                rows[ln].append(one(ln, scene, a.seconds, Path(tmp), k))
                k += 1
    print(f"{'link':40s} {'RTT p50':>8s} {'p99':>8s} {'max':>8s} {'overruns':>9s}  (us; runs: p50 range)")
    for ln in links:
        rs = rows[ln]
        med = {key: statistics.median(r[key] for r in rs if r[key] is not None) for key in ("p50", "p99", "max", "overruns")}
        faults = [r["fault"] for r in rs if r["fault"]]
        print(f"{rs[0]['what']:40s} {med['p50']:8.0f} {med['p99']:8.0f} {med['max']:8.0f} {med['overruns']:8.2f}%"
              f"  ({min(r['p50'] for r in rs):.0f}-{max(r['p50'] for r in rs):.0f})"
              + (f"  faults: {faults}" if faults else ""))


if __name__ == "__main__":
    main()
