"""Does the timing study, fed the latency a real-time run measured across a network, predict what
that run does?

    .venv/bin/python -m docs.tools.netns_prediction [--cases 0:0@500,100:50@250,1000:200@250]
        [--seconds 3] [--h 5e-5]

(root: network namespaces, tests/netns.py.)  For each case ``DELAY_US:JITTER_US@RATE_HZ`` (link
delay and jitter each direction, 0:0 = a bare veth pair; controller rate), plant and controller run in two namespaces joined by that link, in real time
with the currents applied at their measured arrival (``ambhil plant --currents-at arrival``: the
simulated coils see the machine's and the network's latency, rounded up to the plant step
``--h``; the plant integrates with the exact zoh scheme), on ``scenes/net_rigid_1khz.toml``
with its controller at that rate.  Then ``ambhil study timing SCENE --rates RATE --delays
<median measured latency> --jitter-from <the run's recording>`` gives the prediction:
mean-square stability under the measured latency distribution and losses (held periods), the
growth rate at the median latency, and the unbalance amplitude at the sensors.  Printed per
setting: round trip and latency percentiles, held periods, the prediction, and what the run did
(completed or the fault; the steady orbit: largest displacement amplitude of any sensor axis over
the last second, against the predicted amplitude).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from tests import netns  # noqa: E402   (run from the repository root: python -m docs.tools...)

SCENE = ROOT / "scenes" / "net_rigid_1khz.toml"


def one(link: str, rate: float, seconds: float, h: float, tmp: Path) -> dict:
    from ambhil.bridge.protocol import FLAG_HELD, FLAG_WARMUP
    from ambhil.bridge.recording.replay import load_run
    d, j = (float(x) for x in link.split(":"))
    scene = tmp / f"net_{rate:g}hz.toml"
    scene.write_text(SCENE.read_text().replace("sample_rate = 1000.0", f"sample_rate = {rate:g}"))
    run_id = f"pred-{d:g}-{j:g}"
    with netns.NetPair("pred", d, j) as net:
        res = net.run(str(scene), run_id, str(tmp), mode="realtime",
                      plant_args=["--duration", str(seconds), "--currents-at", "arrival", "--integrator", "zoh",
                                  "--h", str(h), "--reply-timeout", "2000"])
        what = net.describe()
    sp = res["plant"][0] or {}
    mcap = tmp / f"{run_id}.mcap"
    run = load_run(str(mcap))
    tim = run["timing"]
    live = (tim["flags"] & FLAG_WARMUP) == 0
    ok = live & ((tim["flags"] & FLAG_HELD) == 0) & (tim["rtt_ns"] > 0)
    rtt = tim["rtt_ns"][ok] * 1e-3
    lat = (tim["rtt_ns"][ok] + np.maximum(tim["lateness_ns"][ok], 0)) * 1e-3
    med = float(np.median(lat))
    st = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "study", "timing", str(scene), "--rates", f"{rate:g}",
                         "--delays", f"0,{med:.1f}us", "--jitter-from", str(mcap), "--no-sensitivity", "--json"],
                        capture_output=True, text=True, cwd=ROOT)
    if st.returncode != 0:
        raise SystemExit(f"study failed: {st.stderr.strip().splitlines()[-1]}")
    study = json.loads(st.stdout.strip().splitlines()[-1])
    at_med = [p for p in study["points"] if p["latency_s"] > 0][0]
    emp = [x for x in study["jitter"] if x["jitter"] != "none"]
    y = run["sensors"]["v"]
    last = y[-int(rate):] if len(y) >= 2 * rate else y[len(y) // 2:]
    amp = float(np.max((last.max(axis=0) - last.min(axis=0)) / 2))
    # growth of the run's envelope: largest |displacement| in consecutive half-second windows
    w = max(1, int(rate / 2))
    env = [float(np.abs(y[i:i + w]).max()) for i in range(len(y) // 2 - (len(y) // 2) % w, len(y) - w + 1, w)]
    growth = float(np.log(env[-1] / env[0]) / ((len(env) - 1) * w / rate)) if len(env) > 1 else None
    return {"link": what, "rtt_us": np.percentile(rtt, [50, 99]).tolist() + [float(rtt.max())],
            "latency_us": np.percentile(lat, [50, 99]).tolist() + [float(lat.max())],
            "held": int((live & ((tim["flags"] & FLAG_HELD) != 0)).sum()), "periods": int(live.sum()),
            "predicted_ms_stable": emp[0]["ms_stable"] if emp else None,
            "predicted_growth_at_median": at_med["growth_rate"], "predicted_unbalance_m": at_med["unbalance_max_m"],
            "margin_us": study["scene_point"]["margin_s"] * 1e6 if study["scene_point"]["stable"] else 0.0,
            "run_fault": sp.get("fault"), "steps": sp.get("steps"), "n_steps": sp.get("n_steps"),
            "run_amplitude_m": amp, "run_growth": growth}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="0:0@500,100:50@250,1000:200@250",
                    help="DELAY_US:JITTER_US@RATE_HZ per case, comma-separated (0:0: a bare veth pair)")
    ap.add_argument("--seconds", type=float, default=3.0, help="simulated (= wall) seconds per run")
    ap.add_argument("--h", type=float, default=5e-5, help="plant step, s (arrival resolution)")
    a = ap.parse_args()
    why = netns.unavailable()
    if why:
        raise SystemExit(f"netns_prediction: {why}")
    print(f"$ {' '.join([os.path.relpath(sys.executable, ROOT)] + sys.argv)}")
    with tempfile.TemporaryDirectory() as tmp:
        for case in a.cases.split(","):
            link, _, rate = case.partition("@")
            rate = float(rate or 250)
            r = one(link, rate, a.seconds, a.h, Path(tmp))
            print(f"\n{r['link']}, controller {rate:g} Hz (latency margin {r['margin_us']:.0f} us)")
            print(f"  measured   round trip p50/p99/max {'/'.join(f'{v:.0f}' for v in r['rtt_us'])} us; "
                  f"latency (+ wake lateness) {'/'.join(f'{v:.0f}' for v in r['latency_us'])} us; "
                  f"held {r['held']} of {r['periods']} periods")
            ms = r["predicted_ms_stable"]
            pu = r["predicted_unbalance_m"]
            print(f"  predicted  {'STABLE' if ms else 'UNSTABLE'} (mean-square, measured distribution + losses); "
                  f"growth at the median latency {r['predicted_growth_at_median']:.3g} 1/s; unbalance amplitude "
                  + (f"{pu * 1e6:.3f} um" if pu else "- (unstable)"))
            print(f"  run        {r['steps']}/{r['n_steps']} steps, "
                  + (f"FAULT: {r['run_fault']}" if r["run_fault"] else "completed")
                  + (f"; amplitude over the last second {r['run_amplitude_m'] * 1e6:.3f} um"
                     + (f" = {r['run_amplitude_m'] / pu:.3f} x predicted" if pu else "")
                     if not r["run_fault"] else "")
                  + (f"; envelope growth over the second half {r['run_growth']:.3g} 1/s"
                     if r["run_growth"] is not None else ""))


if __name__ == "__main__":
    main()
