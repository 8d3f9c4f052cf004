"""Each kind of law over zenoh: a lockstep `ambhil run --law` of the C law (examples/c_law),
the example FMU (examples/fmu_law, FMI 2.0 and 3.0) and an LTI law of the scene
(`[controller] kind = "transfer"`) records exactly what `simulate` computes with the same law,
bit for bit; and a real-time run with a Python law keeps its clock and names its law."""
import importlib.util
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "paper_3amb.toml"
CC = shutil.which("cc")
TRANSFER = """[controller]
kind = "transfer"
sample_rate = 10000.0
discretisation = "tustin"
[controller.transfer]
blocks = [{type = "pid", kp = 5.98869, ki = 20.0, kd = 3.245942e-03, derivative_filter = 1.0e-4},
          {type = "notch", frequency = 600.0, width = 0.3, depth = 0.1}]
"""


def cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT)


def law_of(kind: str, tmp: Path) -> tuple[str, str | None]:
    """(scene file, --law value or None) of a law kind, built into ``tmp``."""
    if kind == "lti":
        src = re.sub(r"^\[controller\].*?(?=^\[(?!controller))", TRANSFER + "\n", SCENE.read_text(),
                     count=1, flags=re.M | re.S)
        (tmp / "transfer.toml").write_text(src)
        return str(tmp / "transfer.toml"), None
    if CC is None:
        pytest.skip("no C compiler (cc): the C law and the FMU are built from source")
    if kind == "c":
        so = tmp / "pid_law.so"
        subprocess.run([CC, "-O2", "-shared", "-fPIC", "-ffp-contract=off", "-I", str(ROOT / "include"),
                        "-o", str(so), str(ROOT / "examples/c_law/pid_law.c")], check=True)
        return str(SCENE), str(so)
    if importlib.util.find_spec("fmpy") is None:
        pytest.skip("no fmpy: FMU laws need pip install 'ambhil[fmu]'")
    spec = importlib.util.spec_from_file_location("build_fmu", ROOT / "examples/fmu_law/build_fmu.py")
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    return str(SCENE), str(build.build_fmu(tmp, fmi=int(kind[-1]), cc=CC))


@pytest.mark.parametrize("kind", ["c", "fmu2", "fmu3", "lti"])
def test_lockstep_run_of_each_law_kind_equals_simulate_bit_for_bit(kind, tmp_path):
    from ambhil.bridge.recording.load import load_run
    from ambhil.loop.simulation import simulate
    from ambhil.loop.system import compile_system
    scene, law = law_of(kind, tmp_path)
    r = cli("run", scene, "--rung", "modal", "--duration", "0.02", "--run-id", f"k{kind}",
            "--out", str(tmp_path), "--json", *(["--law", law] if law else []))
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads([ln for ln in r.stdout.splitlines() if ln.startswith("{")][-1])
    run = load_run(str(tmp_path / f"k{kind}.mcap"))
    res = simulate(compile_system(scene, rung="modal"), 0.02, law=law)
    assert summary["law"] == res.meta["law"] == run["meta"]["law"] != "pid"
    assert run["sensors"]["v"].shape == (200, 6)
    assert np.array_equal(run["sensors"]["v"], res.y[:200])
    assert np.array_equal(run["currents"]["v"], res.i[:200])
    assert np.abs(res.y).max() > 1e-7 and res.fault is None


def test_realtime_run_with_a_python_law_names_it_and_answers_every_sample(tmp_path):
    """Real time at the scene's 10 kHz (overruns allowed: the machine may be busy; what is
    checked is that the law answered every sample and is named)."""
    (tmp_path / "pd.py").write_text(
        "import numpy as np\n\nclass PD:\n    def __init__(self, meta):\n"
        "        c = meta.controller\n        self.kp, self.kd_T = c['kp'], c['kd'] / meta.period\n"
        "        self.u_op = np.array(meta.u_op)\n        self.y1 = None\n\n"
        "    def step(self, t, y):\n        d = 0.0 if self.y1 is None else y - self.y1\n"
        "        self.y1 = y.copy()\n        return self.u_op - self.kp * y - self.kd_T * d\n")
    r = cli("run", str(SCENE), "--rung", "modal", "--duration", "0.05", "--mode", "realtime",
            "--max-overruns", "100%", "--run-id", "rtlaw", "--out", str(tmp_path), "--json",
            "--law", f"{tmp_path / 'pd.py'}:PD")
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    s = json.loads([ln for ln in r.stdout.splitlines() if ln.startswith("{")][-1])
    assert s["law"] == "pd.py:PD" and s["controller"]["law"] == "pd.py:PD"
    assert s["controller"]["fault"] is None and s["plant"]["steps"] == 500
    assert s["controller"]["steps"] >= 450, s["controller"]     # a reply may be lost to a late wake
