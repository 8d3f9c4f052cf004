"""Per-step cost of each kind of law in process, against the built-in law (controller/law.py).

    .venv/bin/python -m benchmarks.laws [--repeat 5] [--duration 0.5] [--steps 20000] [--fmu FILE.fmu]

Laws, on scenes/paper_3amb.toml at rung modal (6 axes, 10 kHz):

    built-in         the PID fused with the sensor and amplifier (ControllerRunner, one numba loop)
    PIDLaw           the same PID as a Python law object (controller/pid_law.py) in a LawRunner
    Python (numpy)   a plain law of a user, a PD ``u = u_op - kp y - kd (y - y_prev) / T`` in numpy
    C (pid_law.so)   examples/c_law/pid_law.c through the C ABI (ctypes; built with cc here)
    LTI transfer     ``[controller] kind = "transfer"``, the same PID as one block (controller/law_lti.py)
    FMU (FMI 2.0/3.0) examples/fmu_law's PID per axis, built here (cc and fmpy), or ``--fmu FILE.fmu``

Three figures per law, each the median of ``--repeat`` runs interleaved across the laws:
``law.step``: the law object's call alone (what the C ABI's ctypes call costs, against a Python
law's), µs per call; ``controller``: one controller step alone (``runner.step_shared``, sensor -> law -> amplifier, no
plant), µs per step over ``--steps`` calls; ``loop``: ``simulate()`` of ``--duration`` s, wall time
of the loop per controller period (the plant's step included; every law but the built-in runs the
loop period by period in Python).  Ratios and the overhead in µs are against the built-in law.
"""
from __future__ import annotations

import importlib.util
import re
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import common

PYTHON_LAW = """\
import numpy as np


class Minimal:
    def __init__(self, meta):
        self.u_op = np.array(meta.u_op)
        self.kp = float(meta.controller["kp"])
        self.kd = float(meta.controller["kd"]) / meta.period
        self.y_prev = np.zeros(meta.n_axes)

    def step(self, t, y):
        u = self.u_op - self.kp * y - self.kd * (y - self.y_prev)
        self.y_prev = y.copy()
        return u
"""


PID_LAW = "from ambhil.controller.pid_law import PIDLaw  # noqa: F401\n"

TRANSFER = """[controller]
kind = "transfer"
sample_rate = 10000.0

[controller.transfer]
blocks = [{type = "pid", kp = 5.98869, ki = 20.0, kd = 3.245942e-03, derivative_filter = 1.0e-4}]
"""


def laws(tmp: Path, fmu: str | None) -> tuple[dict, list[str]]:
    """``{label: (scene file, law spec or None)}`` and notes on the laws left out."""
    base = common.scene("paper_3amb")
    out = {"built-in (fused)": (base, None)}
    (tmp / "pid.py").write_text(PID_LAW)
    (tmp / "minimal.py").write_text(PYTHON_LAW)
    out["PIDLaw (Python class)"] = (base, f"{tmp / 'pid.py'}:PIDLaw")
    out["Python (numpy)"] = (base, f"{tmp / 'minimal.py'}:Minimal")
    notes = []
    cc = shutil.which("cc")
    if cc is None:
        notes.append("C law: skipped (no C compiler cc)")
    else:
        so = tmp / "pid_law.so"
        subprocess.run([cc, "-O2", "-shared", "-fPIC", "-ffp-contract=off", "-I", str(common.ROOT / "include"),
                        "-o", str(so), str(common.ROOT / "examples/c_law/pid_law.c")], check=True)
        out["C (pid_law.so)"] = (base, str(so))
    if (common.ROOT / "controller/law_lti.py").is_file():
        src = Path(base).read_text()
        src = re.sub(r"^\[controller\].*?(?=^\[(?!controller))", TRANSFER + "\n", src, count=1, flags=re.M | re.S)
        (tmp / "transfer.toml").write_text(src)
        out["LTI transfer"] = (str(tmp / "transfer.toml"), None)
    else:
        notes.append("LTI law: skipped (no controller/law_lti.py in this tree)")
    if fmu:
        out["FMU"] = (base, str(Path(fmu).resolve()))
    elif cc is None or importlib.util.find_spec("fmpy") is None:
        notes.append("FMU law: skipped (building examples/fmu_law needs cc and fmpy; or pass --fmu FILE.fmu)")
    else:                           # the example FMU (a PID per axis), built here for FMI 2.0 and 3.0
        spec = importlib.util.spec_from_file_location("build_fmu", common.ROOT / "examples/fmu_law/build_fmu.py")
        build = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(build)
        for fmi in (2, 3):
            out[f"FMU (FMI {fmi}.0)"] = (base, str(build.build_fmu(tmp, fmi=fmi, cc=cc)))
    return out, notes


def controller_us(runner, d: np.ndarray, steps: int) -> float:
    """µs per ``step_shared`` call (after a reset; the law's clock keeps running)."""
    runner.reset()
    step = runner.step_shared
    t0 = time.perf_counter()
    for _ in range(steps):
        step(d)
    return 1e6 * (time.perf_counter() - t0) / steps


def law_us(runner, steps: int) -> float | None:
    """µs per ``law.step(t, y)`` call alone (None for the fused built-in law: it has no law object)."""
    law = getattr(runner, "law", None)
    if law is None:
        return None
    step, y = law.step, runner._y
    t0 = time.perf_counter()
    for _ in range(steps):
        step(0.0, y)
    return 1e6 * (time.perf_counter() - t0) / steps


def main(argv=None) -> None:
    ap = common.parser(__doc__, repeat=5)
    ap.add_argument("--duration", type=float, default=0.5, help="simulate() duration, s (default 0.5)")
    ap.add_argument("--steps", type=int, default=20000, help="controller steps alone per run (default 20000)")
    ap.add_argument("--fmu", default=None, help="an FMU law to measure as well")
    a = ap.parse_args(argv)
    common.header("laws", "per-step cost of each law kind in process, against the built-in law")
    from ambhil.loop.simulation import simulate
    from ambhil.loop.system import compile_system, controller_runner
    with tempfile.TemporaryDirectory(prefix="ambhil-bench-laws-") as tmp:
        cases, notes = laws(Path(tmp), a.fmu)
        models = {k: compile_system(scene, rung="modal") for k, (scene, _) in cases.items()}
        runners = {k: controller_runner(models[k], law=law) for k, (_, law) in cases.items()}
        d = np.random.default_rng(1).normal(0.0, 1e-6, models["built-in (fused)"].n_axes)
        alone = {k: [] for k in cases}
        ctrl = {k: [] for k in cases}
        loop = {k: [] for k in cases}
        for k, (_, law) in cases.items():            # kernels loaded, libraries built and opened
            simulate(models[k], 0.01, law=law)
            controller_us(runners[k], d, 100)
        for _ in range(a.repeat):
            for k, (_, law) in cases.items():
                ctrl[k].append(controller_us(runners[k], d, a.steps))
                alone[k].append(law_us(runners[k], a.steps))
                r = simulate(models[k], a.duration, law=law)
                if r.fault or r.steps * models[k].scene.period < a.duration * (1 - 1e-9):
                    raise SystemExit(f"{k}: the run ended early: {r.fault or r.instability}")
                loop[k].append(r.us_per_period)
        for r in runners.values():
            getattr(r, "close", lambda: None)()
    c0, l0 = (statistics.median(ctrl["built-in (fused)"]), statistics.median(loop["built-in (fused)"]))
    rows = []
    for k in cases:
        print(f"{k}: controller " + " ".join(f"{x:.3g}" for x in ctrl[k]) + " µs/step; loop "
              + " ".join(f"{x:.3g}" for x in loop[k]) + " µs/period")
    for k in cases:
        c, l_ = statistics.median(ctrl[k]), statistics.median(loop[k])
        w = "-" if alone[k][0] is None else f"{statistics.median(alone[k]):.3g}"
        rows.append([k, w, f"{c:.3g}", f"{c / c0:.1f}", f"{l_:.3g}", f"{l_ / l0:.1f}", f"{l_ - l0:+.3g}"])
    print(f"paper_3amb modal, 6 axes, 10 kHz; medians of {a.repeat} runs: controller = {a.steps} steps "
          f"alone, loop = simulate() of {a.duration} s")
    common.table(["law", "law.step µs", "controller µs/step", "x built-in", "loop µs/period", "x built-in",
                  "loop overhead µs/period"], rows)
    for n in notes:
        print(f"# {n}")


if __name__ == "__main__":
    main()
