"""Lockstep plant+controller throughput vs. the zenoh ping-pong floor, in one run.

    .venv/bin/python benchmarks/bench_lockstep.py [--steps 20000] [--runs 3] [--axes 4]
        [--pin | --placement shared|split|none]

Each run starts fresh processes: a ping-pong pair (floor), then a plant and a controller
process running ambhil.bridge.process.plant_node / ambhil.bridge.process.controller_node lockstep with trivial step objects (constant outputs).
Prints per-run figures and the medians, and the ratio lockstep rate / floor rate.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)


class TrivialPlant:
    def __init__(self, n_axes=4, period=1e-4):
        import numpy as np
        self.n_axes, self.period = n_axes, period
        self._y = np.full(n_axes, 1e-6)
        self.step_index = 0

    def reset(self):
        self.step_index = 0
        return self._y

    @property
    def sim_time(self):
        return self.step_index * self.period

    def advance(self, u):
        self.step_index += 1
        return self._y

    def safe_state(self):
        pass


class TrivialController:
    def __init__(self, n_axes=4):
        import numpy as np
        self.n_axes = n_axes
        self._u = np.zeros(n_axes)

    def reset(self):
        pass

    def step(self, y):
        return self._u


def _plant(endpoint, steps, axes, cpus):
    from ambhil.bridge.process.plant_node import run_plant
    s = run_plant(TrivialPlant(axes), "bench", listen=endpoint, n_steps=steps, cpus=cpus,
                  start_timeout=60)
    print(json.dumps(s))


def _controller(endpoint, axes, cpus):
    from ambhil.bridge.process.controller_node import run_controller
    s = run_controller(TrivialController(axes), "bench", connect=endpoint, cpus=cpus,
                       start_timeout=60)
    print(json.dumps(s))


def measure_lockstep(steps=20000, axes=4, pin=False) -> dict:
    from ambhil.bridge.process.transport import free_port, tcp_endpoint
    ep = tcp_endpoint(free_port())
    from bench_pingpong import placement_cpus
    cpus_plant, cpus = placement_cpus(pin)
    pre = f"import sys; sys.path.insert(0, {ROOT!r}); sys.path.insert(0, {HERE!r}); import bench_lockstep as b; "
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    c = subprocess.Popen([sys.executable, "-c", pre + f"b._controller({ep!r}, {axes}, {cpus!r})"],
                         env=env, stdout=subprocess.PIPE, text=True)
    p = subprocess.run([sys.executable, "-c", pre + f"b._plant({ep!r}, {steps}, {axes}, {cpus_plant!r})"],
                       env=env, capture_output=True, text=True, timeout=300)
    c_out, _ = c.communicate(timeout=30)
    if p.returncode != 0:
        raise RuntimeError(p.stderr.strip()[-500:])
    s = json.loads(p.stdout.strip().splitlines()[-1])
    s["controller"] = json.loads(c_out.strip().splitlines()[-1])
    if s["fault"]:
        raise RuntimeError(s["fault"])
    return s


def main(argv=None):
    import bench_pingpong as pp
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--axes", type=int, default=4)
    ap.add_argument("--pin", action="store_true", help="same as --placement shared")
    ap.add_argument("--placement", choices=pp.PLACEMENTS, default=None,
                    help="shared: both processes on the last CPU; split: one CPU each; none: unpinned")
    a = ap.parse_args(argv)
    a.pin = a.placement or ("shared" if a.pin else "none")
    from ambhil.bridge import protocol as pr
    size = pr.SensorCodec(a.axes).size          # the SensorSample of a.axes axes (sender id included)
    floors, locks = [], []
    for i in range(a.runs):
        f = pp.measure_floor(a.steps, 2000, size, a.pin)
        s = measure_lockstep(a.steps, a.axes, a.pin)
        floors.append(f)
        locks.append(s)
        print(f"run {i + 1}: floor {f['rate_hz']:.0f} rt/s (rtt p50 {f['p50']} p99 {f['p99']} us) | "
              f"lockstep {s['steps_per_s']:.0f} steps/s, CPU/step plant {s['cpu_us_per_step']} "
              f"controller {s['controller']['cpu_us_per_step']} us (rtt p50 {s['latency_us']['p50']} p99 "
              f"{s['latency_us']['p99']} max {s['latency_us']['max']} us) | ratio "
              f"{s['steps_per_s'] / f['rate_hz']:.2f}", flush=True)
    fr = statistics.median(f["rate_hz"] for f in floors)
    lr = statistics.median(s["steps_per_s"] for s in locks)
    from ambhil.bridge.protocol import wire
    print(f"wire codec: {'C (ambhil.bridge.protocol._wire)' if wire.NATIVE else 'pure-Python twin'}"
          f"{' (AMBHIL_PURE_WIRE set)' if os.environ.get('AMBHIL_PURE_WIRE') else ''}")
    print(f"MEDIAN over {a.runs} runs ({a.axes} axes, placement {a.pin}): floor {fr:.0f} round trips/s "
          f"(rtt p50 {statistics.median(f['p50'] for f in floors):.1f} us), lockstep {lr:.0f} steps/s "
          f"(rtt p50 {statistics.median(s['latency_us']['p50'] for s in locks):.1f} us), "
          f"ratio {lr / fr:.2f}")


if __name__ == "__main__":
    main()
