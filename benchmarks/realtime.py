"""Which controller rates does this machine sustain in real-time mode?

    .venv/bin/python -m benchmarks.realtime [--rates 1000,2000,5000,10000]
        [--kinds trivial,modal,full] [--seconds 1.0] [--repeat 1] [--placement shared|split|none]
        [--scene scenes/paper_3amb.toml] [--transport unix|tcp] [--cpu-wake-us 0,off]
        [--rt-receive deadline,callback]

For each plant kind and controller rate, a plant process and a controller process run
``ambhil.bridge.process.plant_node / ambhil.bridge.process.controller_node`` in real-time mode (absolute deadlines, sleep-then-spin pacing, late replies
held) for ``--seconds`` of wall time, without a recorder.  Kinds: ``trivial`` = constant step
objects (transport and pacing only); ``modal`` / ``full`` = the scene's rotor (modal-reduced or
full FE, BDF1) with the discrete PID (``ControllerRunner`` at that rate).

Printed per cell: overrun fraction (periods whose currents were held or whose wake was more
than a period late, after the warm-up), held replies, round trip p50/p99 and wake lateness p99
(us), and the fault if the run ended early (the run whose overruns are the median of ``--repeat``).  ``--cpu-wake-us``: the plant's PM QoS request on the
CPUs' wake-up latency (``ambhil plant --cpu-wake-us``; default 0, as `ambhil run`); a list such as
``0,off`` runs each cell with each setting, interleaved run by run, in one invocation.
``--rt-receive``: how the plant waits for each reply (``ambhil plant --rt-receive``, bridge/process/deadline.py);
a list such as ``deadline,callback`` interleaves the two the same way.  The reply timeout is set to 50 ms so that a
scheduling stall is counted, not fatal.  A rate is "sustained" here when overruns < 1 %.
"""
from __future__ import annotations

import json
import statistics
import subprocess

from benchmarks import common, floor


def _objects(kind: str, rate: float, scene_path: str):
    if kind == "trivial":
        from benchmarks.lockstep import TrivialController, TrivialPlant
        return TrivialPlant(4, 1.0 / rate), TrivialController(4)
    import numpy as np
    from ambhil.loop.system import compile_system, controller_runner
    from ambhil.loop.scene import load_scene
    from ambhil.plant.run_options import RunOptions
    from ambhil.plant.step import PlantRunner
    scene = load_scene(scene_path)
    model = compile_system(scene, rung=kind)
    period = 1.0 / rate
    h = min(scene.plant.simulation.step, period)
    plant = PlantRunner(model, RunOptions(integrator="bdf1", h=period / max(1, round(period / h))), period=period)
    ctrl = controller_runner(model, sample_rate=rate)
    plant.reset(); plant.advance(np.zeros(plant.n_axes))         # compile/load kernels
    ctrl.reset(); ctrl.step(np.zeros(ctrl.n_axes))
    return plant, ctrl


def _plant(endpoint, kind, rate, seconds, scene, cpus, spin_s=None, cpu_wake_us=0, rt_receive="auto"):
    from ambhil.bridge.process.config import PlantNodeConfig
    from ambhil.bridge.process.plant_node import run_plant
    plant, _ = _objects(kind, rate, scene)
    s = run_plant(plant, PlantNodeConfig("rt", int(seconds * rate), listen=endpoint, mode="realtime",
                                         reply_timeout=0.05, cpus=cpus, start_timeout=60, spin_s=spin_s,
                                         cpu_wake_us=cpu_wake_us, rt_receive=rt_receive))
    print(json.dumps(s))


def _controller(endpoint, kind, rate, scene, cpus):
    from ambhil.bridge.process.config import ControllerNodeConfig
    from ambhil.bridge.process.controller_node import run_controller
    _, ctrl = _objects(kind, rate, scene)
    s = run_controller(ctrl, ControllerNodeConfig("rt", connect=endpoint, cpus=cpus, start_timeout=60))
    print(json.dumps(s))


def measure(kind, rate, seconds, scene, placement, spin_s=None, transport="unix", cpu_wake_us=0,
            rt_receive="auto") -> dict:
    ep = floor.endpoint_for(transport, "-rt")
    cpus_plant, cpus_ctrl = floor.placement_cpus(placement)
    pre = "from benchmarks import realtime as b; "
    c = common.popen(pre + f"b._controller({ep!r}, {kind!r}, {rate}, {scene!r}, {cpus_ctrl!r})",
                     stdout=subprocess.PIPE, text=True)
    try:
        p = common.run(pre + f"b._plant({ep!r}, {kind!r}, {rate}, {seconds}, {scene!r}, {cpus_plant!r}, "
                             f"{spin_s!r}, {cpu_wake_us!r}, {rt_receive!r})", timeout=600)
        if p.returncode != 0:
            raise RuntimeError(common.tail(p.stderr, 800))
        c.communicate(timeout=60)
    finally:
        if c.poll() is None:
            c.kill()
        from ambhil.bridge.process.transport import remove_socket_files
        remove_socket_files(ep)
    return common.last_json(p.stdout)


def main(argv=None):
    ap = common.parser(__doc__, repeat=1)
    ap.add_argument("--rates", default="1000,2000,5000,10000")
    ap.add_argument("--kinds", default="trivial,modal,full")
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--placement", choices=floor.PLACEMENTS, default="shared")
    ap.add_argument("--spin-us", type=float, default=None,
                    help="busy-wait this long before each deadline (default: ambhil.bridge.process.plant_node / ambhil.bridge.process.controller_node' choice)")
    ap.add_argument("--scene", default=common.scene("paper_3amb"))
    ap.add_argument("--transport", choices=("unix", "tcp"), default="unix",
                    help="unix: Unix-domain sockets, what ambhil run uses on one host (default); tcp: loopback")
    ap.add_argument("--cpu-wake-us", default="0",
                    help="the plant's PM QoS wake-up latency request, us or 'off'; a comma list runs each")
    ap.add_argument("--rt-receive", default="auto",
                    help="the plant's reply wait (ambhil plant --rt-receive): auto, deadline or "
                         "callback; a comma list runs each")
    a = ap.parse_args(argv)
    a.scene = common.scene(a.scene)
    rates = [float(r) for r in a.rates.split(",")]
    wakes = [None if w.strip() == "off" else int(w) for w in a.cpu_wake_us.split(",")]
    variants = [(w, r.strip()) for w in wakes for r in a.rt_receive.split(",")]
    common.header("realtime", "which controller rates this machine sustains in real time")
    print(f"# {a.seconds:g} s per run, placement {a.placement}, spin {a.spin_us} us, "
          f"transport {a.transport}, reply timeout 50 ms, "
          f"CPU wake-up request {a.cpu_wake_us} us, receive {a.rt_receive}; "
          f"overruns counted after the warm-up")
    print(f"{'kind':8s} {'rate Hz':>8s} {'wake us':>7s} {'receive':>8s} {'overruns':>9s} {'held':>6s} {'rtt p50':>8s} "
          f"{'rtt p99':>8s} {'late p99':>9s}  fault / request")
    for kind in a.kinds.split(","):
        for rate in rates:
            rows = {v: [] for v in variants}
            for _ in range(a.repeat):          # interleaved: each setting sees the same machine
                for v in variants:
                    rows[v].append(measure(kind, rate, a.seconds, a.scene, a.placement,
                                           None if a.spin_us is None else a.spin_us * 1e-6,
                                           a.transport, v[0], v[1]))
            for v in variants:
                w = v[0]
                fr = [r["overruns"] / max(1, r["steps"] - r["warmup_steps"]) for r in rows[v]]
                i = fr.index(statistics.median_low(fr))
                r = rows[v][i]
                lat = r["latency_us"]
                late = r["lateness_us"]
                used = (r.get("rt_receive") or {}).get("mode", "?")
                print(f"{kind:8s} {rate:8.0f} {'off' if w is None else w:>7} {used:>8s} {100 * fr[i]:8.2f}% {r['held']:6d} "
                      f"{lat.get('p50', 0):8.1f} {lat.get('p99', 0):8.1f} {late.get('p99', 0):9.1f}  "
                      f"{r['fault'] or r.get('cpu_wake_latency') or ''}", flush=True)


if __name__ == "__main__":
    main()
