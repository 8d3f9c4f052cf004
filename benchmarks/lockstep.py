"""Lockstep steps/s against the transport bound: the loop over zenoh against the fastest a loop
adding nothing to the floor but the two steps could go.

    .venv/bin/python -m benchmarks.lockstep [--repeat 3] [--plants trivial,rigid,modal,full]
        [--scene scenes/paper_3amb.toml] [--duration 1.0] [--recorder both|on|off]
        [--steps 20000] [--axes 6] [--placement shared|split|none] [--transport unix|tcp]
        [--laws pid,pid-python,minimal,FILE.py:CLASS,FILE.so,FILE.fmu]

Per run and plant, in fresh processes, interleaved so the machine's state hits every row alike:

- the floor right before (benchmarks.floor: the two-process ping-pong with the loop's
  SensorSample size, transport and placement; this machine's load moves it within seconds);
- ``trivial``: a plant and a controller process (ambhil.bridge.process.plant_node /
  controller_node) with constant step objects, ``--steps`` steps: the loop's own cost;
- ``rigid`` / ``modal`` / ``full``: ``ambhil run SCENE --rung R --duration D --json`` (the
  command users run, placement auto) with its recorder and with ``--no-record``
  (``--recorder both``, the order alternating run by run), ``--duration`` simulated seconds;
- bound = 1 / (floor round trip + plant step + controller step), the two steps timed in
  process (median of 200-call batches): the rate of a loop that adds nothing to the floor.
- ``--laws``: each rung's run once per law, ``ambhil run --law``: ``pid`` the built-in (the
  fused kernel), ``pid-python`` the same PID as a Python class (controller/pid_law.py: the
  law interface's own cost), ``minimal`` a minimal Python law in numpy (a PD, ``u = u_op - kp y
  - kd (y - y_prev) / T``: the proportional law alone does not hold the paper's rotor), or any
  law by name (``FILE.py:CLASS``, ``FILE.so``, ``FILE.fmu``); its controller step enters its bound.

Prints per run the rates, then a table of medians: steps/s, the fraction of the bound (the
figure to compare across machines), the recorder's cost and the CPU time per step of plant +
controller (all their threads: the loop's own work, which other load inflates far less than
wall time).  For a comparison of two settings or two checkouts in the same seconds on a busy
machine: benchmarks.sliced.
"""
from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

from benchmarks import common, floor

RUNGS = ("rigid", "modal", "full")

#: the laws --laws names by a word; anything else is a law's name (controller/law_loader.py)
MINIMAL_LAW = """
import numpy as np


class Minimal:
    \"\"\"u = u_op - kp y - kd (y - y_prev) / T: a minimal Python law (numpy, a PD).\"\"\"

    def __init__(self, meta):
        c = meta.controller
        self.u_op = np.array(meta.u_op)
        self.kp, self.kd_T = c["kp"], c["kd"] / meta.period
        self.reset()

    def reset(self):
        self.y1 = np.zeros(len(self.u_op))

    def step(self, t, y):
        u = self.u_op - self.kp * y - self.kd_T * (y - self.y1)
        self.y1 = y.copy()
        return u
"""
PID_PYTHON_LAW = """
from ambhil.controller.pid_law import PIDLaw


class PIDPython(PIDLaw):
    \"\"\"The built-in PID as a user's Python class.\"\"\"
"""


def law_spec(name: str, folder: str) -> str | None:
    """The law ``name`` of ``--laws`` as ``ambhil run --law`` takes it (None: the built-in)."""
    if name == "pid":
        return None
    words = {"minimal": ("minimal_law.py", MINIMAL_LAW, "Minimal"),
             "pid-python": ("pid_python_law.py", PID_PYTHON_LAW, "PIDPython")}
    if name in words:
        f, text, cls = words[name]
        path = os.path.join(folder, f)
        with open(path, "w") as fh:
            fh.write(text)
        return f"{path}:{cls}"
    from ambhil.controller.law_loader import resolve
    return resolve(name, os.getcwd())


# -- the trivial loop: constant step objects in the two node processes ------------------------

class TrivialPlant:
    def __init__(self, n_axes=6, period=1e-4):
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
    def __init__(self, n_axes=6):
        import numpy as np
        self.n_axes = n_axes
        self._u = np.zeros(n_axes)

    def reset(self):
        pass

    def step(self, y):
        return self._u


def _plant(endpoint, steps, axes, cpus):
    from ambhil.bridge.process.config import PlantNodeConfig
    from ambhil.bridge.process.plant_node import run_plant
    s = run_plant(TrivialPlant(axes), PlantNodeConfig("bench", steps, listen=endpoint, cpus=cpus, start_timeout=60))
    print(json.dumps(s))


def _controller(endpoint, axes, cpus):
    from ambhil.bridge.process.config import ControllerNodeConfig
    from ambhil.bridge.process.controller_node import run_controller
    s = run_controller(TrivialController(axes), ControllerNodeConfig("bench", connect=endpoint, cpus=cpus,
                                                                     start_timeout=60))
    print(json.dumps(s))


def measure_trivial(steps=20000, axes=6, placement="shared", transport="unix") -> dict:
    """One lockstep run of the trivial loop; the plant's summary, the controller's under ``controller``."""
    ep = floor.endpoint_for(transport, "lockstep")
    cpus_plant, cpus = floor.placement_cpus(placement)
    pre = "from benchmarks import lockstep as b; "
    c = common.popen(pre + f"b._controller({ep!r}, {axes}, {cpus!r})", stdout=subprocess.PIPE, text=True)
    try:
        p = common.run(pre + f"b._plant({ep!r}, {steps}, {axes}, {cpus_plant!r})")
        if p.returncode != 0:
            raise RuntimeError(common.tail(p.stderr))
        c_out, _ = c.communicate(timeout=30)
    finally:
        if c.poll() is None:
            c.kill()
        from ambhil.bridge.process.transport import remove_socket_files
        remove_socket_files(ep)
    s = common.last_json(p.stdout)
    s["controller"] = common.last_json(c_out)
    if s["fault"]:
        raise RuntimeError(s["fault"])
    return s


# -- the real loop: `ambhil run` per rung --------------------------------------------------------

def steppers(scene_path: str, rung: str, law: str | None = None):
    """The rung's plant runner and the scene's controller runner (of ``law``, a resolved name)
    through the bridge's hot-path calls, reset: ``(advance, currents, step, output, axes)``."""
    import numpy as np
    from ambhil.loop.scene import load_scene
    from ambhil.loop.system import compile_system, controller_runner
    from ambhil.plant.step import PlantRunner
    scene = load_scene(scene_path)
    p = PlantRunner(compile_system(scene, rung=rung))
    c = controller_runner(scene, law=law)
    p.reset()
    c.reset()
    u = np.zeros(p.n_axes)
    adv = getattr(p, "advance_shared", p.advance)
    stp = getattr(c, "step_shared", c.step)
    return adv, u, stp, adv(u), p.n_axes


def step_costs(scene_path: str, rung: str, calls: int = 200, batches: int = 15,
               law: str | None = None) -> tuple[float, float, int]:
    """(plant step s, controller step s, axes): medians of ``batches`` timed batches."""
    adv, u, stp, y, n_axes = steppers(scene_path, rung, law)
    tp, tc = [], []
    for _ in range(batches):
        t0 = time.perf_counter_ns()
        for _ in range(calls):
            y = adv(u)
        t1 = time.perf_counter_ns()
        for _ in range(calls):
            stp(y)
        t2 = time.perf_counter_ns()
        tp.append((t1 - t0) / calls)
        tc.append((t2 - t1) / calls)
    return statistics.median(tp) * 1e-9, statistics.median(tc) * 1e-9, n_axes


def ambhil_run(scene: str, rung: str, duration: float, record: bool, transport: str, out: str,
               law: str | None = None) -> dict:
    """``ambhil run`` (with ``--law law``) to completion; its JSON summary."""
    argv = [sys.executable, "-m", "ambhil.bridge.cli", "run", scene, "--rung", rung, "--duration", str(duration),
            "--json", "--out", out, "--transport", transport] + ([] if record else ["--no-record"]) \
        + (["--law", law] if law else [])
    p = subprocess.run(argv, cwd=common.ROOT, capture_output=True, text=True, timeout=600)
    try:
        s = common.last_json(p.stdout)
    except RuntimeError:
        raise RuntimeError(f"ambhil run gave no summary (exit {p.returncode}): {common.tail(p.stderr, 400)}")
    if not s["ok"]:
        raise RuntimeError(f"ambhil run failed: {s['failed']}")
    return s


def _cpu(s: dict) -> float:
    """CPU time per step of plant + controller (all their threads, us)."""
    return (s["plant"]["cpu_us_per_step"] or 0) + (s["controller"]["cpu_us_per_step"] or 0)


def one_run(row_key: tuple, a, costs: dict, k: int) -> dict:
    """Floor, then the loop(s) of ``row_key = (plant, law name, law spec)``: a row of figures."""
    plant, _, law = row_key
    tp, tc, n_axes = costs[row_key]
    from ambhil.bridge import protocol as pr
    f = floor.measure_floor(20000 if plant == "trivial" else 10000, 2000, pr.SensorCodec(n_axes).size,
                            a.placement if plant == "trivial" else "shared", a.kind)
    bound = 1.0 / (1.0 / f["rate_hz"] + tp + tc)
    row = {"floor": f["rate_hz"], "floor_p50": f["p50"], "bound": bound}
    if plant == "trivial":
        s = measure_trivial(a.steps, n_axes, a.placement, a.kind)
        row.update(rec=None, norec=s["steps_per_s"], p50=s["latency_us"]["p50"],
                   cpu_norec=s["cpu_us_per_step"] + s["controller"]["cpu_us_per_step"])
    else:
        kinds = {"both": (True, False), "on": (True,), "off": (False,)}[a.recorder]
        order = kinds if k % 2 == 0 else kinds[::-1]
        res = {rec: ambhil_run(a.scene, plant, a.duration, rec, a.transport, a.out, law) for rec in order}
        row.update(rec=res[True]["plant"]["steps_per_s"] if True in res else None,
                   norec=res[False]["plant"]["steps_per_s"] if False in res else None,
                   p50=res[order[0]]["plant"]["latency_us"]["p50"],
                   cpu_rec=_cpu(res[True]) if True in res else None,
                   cpu_norec=_cpu(res[False]) if False in res else None)
    return row


def _of(x, b):
    return f"{x:.0f} ({x / b:.2f})" if x else "-"


def main(argv=None):
    ap = common.parser(__doc__, repeat=3)
    ap.add_argument("--plants", default="trivial,modal,full",
                    help="comma-separated: trivial (constant step objects) and/or rungs " + ",".join(RUNGS))
    ap.add_argument("--scene", default=common.scene("paper_3amb"))
    ap.add_argument("--duration", type=float, default=1.0, help="simulated s per `ambhil run`")
    ap.add_argument("--recorder", choices=("both", "on", "off"), default="both",
                    help="`ambhil run` with its recorder, with --no-record, or both (alternating)")
    ap.add_argument("--steps", type=int, default=20000, help="steps of the trivial loop")
    ap.add_argument("--axes", type=int, default=6, help="axes of the trivial loop")
    ap.add_argument("--placement", choices=floor.PLACEMENTS, default="shared",
                    help="the trivial loop's and its floor's (ambhil run places itself)")
    ap.add_argument("--transport", choices=("auto", "unix", "tcp"), default="auto")
    ap.add_argument("--laws", default="pid",
                    help="comma-separated laws of every rung's run: pid (built-in), pid-python (the PID as a "
                         "Python class), minimal (a PD in numpy), or a law's name FILE.py:CLASS / FILE.so / FILE.fmu")
    a = ap.parse_args(argv)
    plants = common.csv(a.plants)
    bad = [p for p in plants if p not in ("trivial",) + RUNGS]
    if bad:
        raise SystemExit(f"benchmarks.lockstep: error: unknown plant(s) {bad}")
    a.scene = common.scene(a.scene)
    from ambhil.bridge.cli.run_transport import choose_transport
    a.kind = choose_transport(a.transport, "probe")[0]["kind"]
    common.header("lockstep", f"lockstep steps/s against the transport bound; {os.path.basename(a.scene)}, "
                              f"transport {a.kind}, {a.duration} s per ambhil run, {a.steps} trivial steps, "
                              f"laws {a.laws}")
    a.out = tempfile.mkdtemp(prefix="ambhil-bench-lockstep-")
    laws = [(name, law_spec(name, a.out)) for name in common.csv(a.laws)]
    keys = [(p, "-", None) for p in plants if p == "trivial"] + [(p, n, spec) for p in plants if p != "trivial"
                                                                for n, spec in laws]
    costs = {key: (0.0, 0.0, a.axes) if key[0] == "trivial" else step_costs(a.scene, key[0], law=key[2])
             for key in keys}
    for key in keys:
        if key[0] != "trivial":
            print(f"step {key[0]:5s} law {key[1]}: plant {costs[key][0] * 1e6:.2f} us, controller "
                  f"{costs[key][1] * 1e6:.2f} us", flush=True)
    rows = {key: [] for key in keys}
    for k in range(a.repeat):
        for key in keys:
            r = one_run(key, a, costs, k)
            rows[key].append(r)
            p = key[0] if key[0] == "trivial" else f"{key[0]} {key[1]}"
            print(f"run {k + 1} {p:7s}: floor {r['floor']:.0f} rt/s -> bound {r['bound']:.0f} steps/s | "
                  + (f"with recorder {_of(r['rec'], r['bound'])} | " if r["rec"] else "")
                  + (f"{'loop' if p == 'trivial' else 'no recorder'} {_of(r['norec'], r['bound'])}" if r["norec"] else "")
                  + f" | rtt p50 {r['p50']:.0f} us", flush=True)
    med = statistics.median

    def col(rs, key, frac=False):
        v = [x[key] / (x["bound"] if frac else 1) for x in rs if x.get(key)]
        return (f"{med(v):.2f}" if frac else f"{med(v):.0f}") if v else "-"
    print(f"medians of {a.repeat} runs; (fraction of the bound)")
    common.table(["plant", "law", "plant step us", "controller step us", "floor rt/s", "bound steps/s",
                  "with recorder steps/s", "(of bound)", "no recorder steps/s", "(of bound)",
                  "recorder cost", "CPU/step us"],
                 [[p[0], p[1], f"{costs[p][0] * 1e6:.2f}", f"{costs[p][1] * 1e6:.2f}", col(rs, "floor"), col(rs, "bound"),
                   col(rs, "rec"), col(rs, "rec", True), col(rs, "norec"), col(rs, "norec", True),
                   (f"{100 * med(1 - x['rec'] / x['norec'] for x in rs):+.1f} %" if rs[0]["rec"] and rs[0]["norec"] else "-"),
                   col(rs, "cpu_rec") if rs[0].get("cpu_rec") else col(rs, "cpu_norec")]
                  for p, rs in rows.items()])
    from ambhil.bridge.protocol import wire
    print(f"wire codec: {'C' if wire.NATIVE else 'pure-Python twin'}"
          f"{' (AMBHIL_PURE_WIRE set)' if os.environ.get('AMBHIL_PURE_WIRE') else ''}; load at end "
          f"{os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
