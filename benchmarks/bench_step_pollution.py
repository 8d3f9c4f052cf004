"""Does the plant step's memory slow the loop's messaging?  One real lockstep loop (a
`ambhil.bridge.process.plant_node` plant and a `ambhil.bridge.process.controller_node` controller process on the last CPU, Unix
socket, the scene's axes), whose plant does a different kind of work between messages in
interleaved blocks of ``--block`` steps:

- ``none``: nothing (the loop alone);
- ``spin``: a busy wait of ``--spin-us`` (default: the full rung's step, measured at start) that
  touches no memory;
- ``full``: the full FE rung's real step (`PlantRunner.advance_shared` of the scene);
- ``modal``: the modal rung's real step.

The plant returns constant outputs (the steps' results are discarded), so the traffic is the
same in every mode.  Per step the plant records when its ``advance`` was entered and left
(``perf_counter_ns``); the **loop time** of a step is the time from leaving ``advance`` to
entering the next one: the round trip (put, the controller's receive, step, reply, the plant's
receive and decode) plus the plant's bookkeeping, everything but the work.  If the full rung's
100-150 KiB of band matrices evicted what the messaging needs, its loop time would exceed the
spin's, which does the same wall time of work without memory.

    .venv/bin/python benchmarks/bench_step_pollution.py [--steps 60000] [--block 500] [--runs 2]

Prints per mode the median work and loop time over blocks (each block's median; the first 50
steps of a block, and blocks in the first 2000 steps, dropped) and, paired within each cycle of
four blocks (the machine's regime moves between cycles, not within one), the median of the
block's loop time minus the ``spin`` block's, and in how many cycles it was above.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

from bench_lockstep import TrivialPlant  # noqa: E402

MODES = ("none", "spin", "full", "modal")


class ModePlant(TrivialPlant):
    """Constant outputs; between messages the work of mode ``(step // block) % 4``."""

    def __init__(self, scene: str, block: int, spin_us: float, n_steps: int):
        import numpy as np
        from bench_run import steppers
        self.full = steppers(scene, "full")[:2]
        self.modal = steppers(scene, "modal")[:2]
        self.n_axes = steppers(scene, "rigid")[4]
        for adv, u in (self.full, self.modal):
            for _ in range(200):
                adv(u)
        if spin_us <= 0:               # the full step's wall time, warm
            adv, u = self.full
            t0 = time.perf_counter_ns()
            for _ in range(500):
                adv(u)
            spin_us = (time.perf_counter_ns() - t0) / 500 / 1e3
        self.spin_ns = int(spin_us * 1e3)
        super().__init__(self.n_axes, 1e-4)
        self.block = block
        self.t_in = np.zeros(n_steps + 1, np.int64)
        self.t_out = np.zeros(n_steps + 1, np.int64)

    def advance(self, u):
        pc = time.perf_counter_ns
        k = self.step_index
        t = pc()
        self.t_in[k] = t
        mode = (k // self.block) % 4
        if mode == 1:
            end = t + self.spin_ns
            while pc() < end:
                pass
        elif mode == 2:
            self.full[0](self.full[1])
        elif mode == 3:
            self.modal[0](self.modal[1])
        self.step_index = k + 1
        self.t_out[k] = pc()
        return self._y


def _plant(scene, ep, steps, block, spin_us, cpus, out):
    import numpy as np
    from ambhil.bridge.process.plant_node import run_plant
    p = ModePlant(scene, block, spin_us, steps)
    s = run_plant(p, "pollution", listen=ep, n_steps=steps, cpus=cpus, start_timeout=120)
    np.savez(out, t_in=p.t_in[:p.step_index], t_out=p.t_out[:p.step_index])
    print(json.dumps({"fault": s["fault"], "steps_per_s": s["steps_per_s"], "spin_us": p.spin_ns / 1e3}))


def _controller(ep, axes, cpus):
    from bench_lockstep import TrivialController
    from ambhil.bridge.process.controller_node import run_controller
    run_controller(TrivialController(axes), "pollution", connect=ep, cpus=cpus, start_timeout=120)


def analyse(t_in, t_out, block: int, skip: int = 50, first: int = 2000):
    """Per mode: lists of per-block medians (work us, loop us), blocks in step order."""
    import numpy as np
    work = (t_out - t_in)[:-1] / 1e3
    loop = (t_in[1:] - t_out[:-1]) / 1e3
    out = {m: [] for m in MODES}
    for b in range(first // block, len(loop) // block):
        sel = slice(b * block + skip, (b + 1) * block - 1)
        out[MODES[b % 4]].append((b, float(np.median(work[sel])), float(np.median(loop[sel]))))
    return out


def one_run(scene, steps, block, spin_us):
    from bench_pingpong import endpoint_for
    from ambhil.bridge.process.transport import remove_socket_files
    ep = endpoint_for("unix", "pollution")
    last = os.cpu_count() - 1
    out = os.path.join(tempfile.mkdtemp(prefix="ambhil-pollution-"), "t.npz")
    from ambhil.loop.scene import load_scene
    from ambhil.plant.model import bearing_axes
    axes = len(bearing_axes(load_scene(scene).plant))
    pre = f"import sys; sys.path.insert(0, {ROOT!r}); sys.path.insert(0, {HERE!r}); import bench_step_pollution as b; "
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    try:
        c = subprocess.Popen([sys.executable, "-c", pre + f"b._controller({ep!r}, {axes}, [{last}])"], cwd=ROOT, env=env)
        p = subprocess.run([sys.executable, "-c", pre + f"b._plant({scene!r}, {ep!r}, {steps}, {block}, "
                            f"{spin_us}, [{last}], {out!r})"], cwd=ROOT, env=env, capture_output=True, text=True,
                           timeout=1800)
        try:
            c.wait(timeout=60)
        except subprocess.TimeoutExpired:
            c.kill()
    finally:
        remove_socket_files(ep)
    if p.returncode != 0:
        raise RuntimeError(p.stderr.strip()[-600:])
    s = json.loads(p.stdout.strip().splitlines()[-1])
    if s["fault"]:
        raise RuntimeError(s["fault"])
    import numpy as np
    d = np.load(out)
    return s, analyse(d["t_in"], d["t_out"], block)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=os.path.join(ROOT, "scenes", "paper_3amb.toml"))
    ap.add_argument("--steps", type=int, default=60000)
    ap.add_argument("--block", type=int, default=500)
    ap.add_argument("--spin-us", type=float, default=0.0, help="busy wait of the spin mode (0: the full step's)")
    ap.add_argument("--runs", type=int, default=2)
    a = ap.parse_args(argv)
    if a.block < 100:
        raise SystemExit(f"--block {a.block}: need at least 100 steps per block")
    if a.steps < 2000 + 8 * a.block:
        raise SystemExit(f"--steps {a.steps}: need at least {2000 + 8 * a.block} (two blocks of each mode)")
    print(f"load {os.getloadavg()[0]:.1f}; {a.steps} steps, modes in blocks of {a.block}; plant + controller "
          f"on CPU {os.cpu_count() - 1}", flush=True)
    for r in range(a.runs):
        s, res = one_run(os.path.abspath(a.scene), a.steps, a.block, a.spin_us)
        spin = {b // 4: lp for b, _, lp in res["spin"]}
        med = {m: statistics.median(lp for _, _, lp in res[m]) for m in MODES}
        print(f"run {r + 1}: {s['steps_per_s']:.0f} steps/s overall, spin {s['spin_us']:.1f} us")
        for m in MODES:
            d = [lp - spin[b // 4] for b, _, lp in res[m] if b // 4 in spin]
            print(f"  {m:6s} work {statistics.median(w for _, w, _ in res[m]):6.2f} us, loop {med[m]:6.2f} us; "
                  f"against the spin block of the same cycle: median {statistics.median(d):+5.2f} us, "
                  f"above it in {sum(x > 0 for x in d)}/{len(d)} cycles", flush=True)


if __name__ == "__main__":
    main()
