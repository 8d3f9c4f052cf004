"""The law interface (controller/law.py): the built-in PID run as a law between the hardware
kernels equals the fused kernel bit for bit; a Python law is loaded by name and meets the same
hardware; a law that fails ends the run with one line naming the law and the step."""
from __future__ import annotations

import dataclasses
import re
import textwrap

import numpy as np
import pytest

from ambhil.controller.discrete import ControllerRunner
from ambhil.controller.law import LawError, LawMeta
from ambhil.controller.law_loader import law_factory, resolve
from ambhil.controller.law_runner import LawRunner
from ambhil.controller.params import Amplifier, ControllerParams, Sensor
from ambhil.controller.pid_law import PIDLaw
from ambhil.loop.simulation import simulate
from ambhil.loop.system import axis_names, compile_system, controller_runner

SCENE = "scenes/paper_3amb.toml"


@pytest.fixture(scope="module")
def modal():
    return compile_system(SCENE, rung="modal")


@pytest.mark.parametrize("changes", [{}, {"delay_samples": 2}, {"discretisation": "zoh"},
                                     {"anti_windup": False}])
def test_pid_as_a_law_equals_the_fused_kernel_bit_for_bit(modal, changes):
    """Random displacements large enough to saturate: same currents, same saturation count."""
    cfg = dataclasses.replace(modal.scene.controller, **changes)
    fused = ControllerRunner(cfg, modal.i_op)
    law = LawRunner(PIDLaw, cfg, modal.i_op, axes=axis_names(modal.scene))
    rng = np.random.default_rng(7)
    saturated = 0
    for k in range(5000):
        d = rng.normal(0.0, 3e-4 if k % 500 < 250 else 1e-6, modal.n_axes)
        a, b = fused.step(d), law.step(d)
        assert np.array_equal(a, b), (k, a, b)
        assert fused.saturated == law.saturated
        saturated += fused.saturated
    assert saturated > 0            # the limits were exercised


def test_hardware_with_lags_and_limits_equals_the_fused_kernel():
    cfg = ControllerParams(kp=3.0, ki=40.0, kd=2e-3, derivative_filter=1e-4, delay_samples=1,
                           sensor=Sensor(gain=1e4, time_constant=2e-5),
                           amplifier=Amplifier(gain=0.5, time_constant=1e-4, current_limit=2.0))
    i_op = [0.3, -0.2]
    fused, law = ControllerRunner(cfg, i_op), LawRunner(PIDLaw, cfg, i_op)
    assert np.array_equal(fused.step(np.zeros(2)), law.step(np.zeros(2)))
    rng = np.random.default_rng(3)
    for _ in range(3000):
        d = rng.normal(0.0, 2e-4, 2)
        assert np.array_equal(fused.step(d), law.step(d))


def test_runner_starts_in_equilibrium_at_the_operating_currents(modal):
    r = LawRunner(PIDLaw, modal.scene.controller, modal.i_op)
    for _ in range(50):
        i = r.step(np.zeros(modal.n_axes))
    np.testing.assert_allclose(i, modal.i_op, rtol=1e-12, atol=1e-15)


def test_slew_limit_bounds_the_current_step():
    """An amplifier with a slew limit: a step command reaches the coil as a ramp of
    slew_rate * T per sample (the fused kernel has no slew, so the PID runs as a law)."""
    cfg = ControllerParams(kp=1.0, amplifier=Amplifier(slew_rate=1000.0), sample_rate=1000.0)

    class Step:
        def __init__(self, meta):
            pass

        def step(self, t, y):
            return np.array([5.0])
    r = LawRunner(Step, cfg, [0.0])
    i = [r.step(np.zeros(1))[0] for _ in range(8)]
    np.testing.assert_allclose(i, [1.0, 2.0, 3.0, 4.0, 5.0, 5.0, 5.0, 5.0])


def test_python_law_by_file_name_meets_metres_and_amperes(tmp_path):
    """With unity sensor and amplifier a law is handed metres and gives amperes: a law that
    returns y itself drives exactly the displacement as current."""
    f = tmp_path / "echo.py"
    f.write_text("class Echo:\n    def __init__(self, meta):\n        self.meta = meta\n"
                 "    def step(self, t, y):\n        return y * 1.0\n")
    factory, name = law_factory(resolve("echo.py:Echo", tmp_path))
    assert name == "echo.py:Echo"
    r = LawRunner(factory, ControllerParams(kp=1.0), [0.0, 0.0], axes=["A-x", "A-y"], name=name)
    assert r.law.meta.axes == ("A-x", "A-y") and r.law.meta.period == 1e-4
    np.testing.assert_array_equal(r.step(np.array([1e-5, -2e-5])), [1e-5, -2e-5])


def test_the_docs_minimal_law_holds_the_rotor(modal, tmp_path):
    """docs/controllers.md's first example, run as written against the paper scene."""
    src = (open("docs/controllers.md").read().split("```python\n", 1)[1].split("```", 1)[0])
    assert len(src.strip().splitlines()) <= 15
    (tmp_path / "my_law.py").write_text(src)
    r = simulate(modal, 0.2, law=resolve("my_law.py:MyLaw", tmp_path))
    assert r.fault is None and r.steps == 2000
    assert np.abs(r.y[-200:]).max() < 1e-3 * np.abs(r.y).max() + 1e-4


@pytest.mark.parametrize("body, says", [
    ("raise RuntimeError('boom')", "step 0 (t = 0 s) raised RuntimeError: boom"),
    ("return np.full(self.n, np.nan)", "returned a non-finite input for axis A-x: nan"),
    ("return np.zeros(self.n + 1)", f"returned shape (7,), expected (6,)"),
    ("return 'volts'", "returned str, not 6 numbers"),
])
def test_a_failing_law_ends_the_run_with_one_line_naming_it(modal, tmp_path, body, says):
    (tmp_path / "bad.py").write_text(textwrap.dedent(f"""\
        import numpy as np
        class Bad:
            def __init__(self, meta):
                self.n = meta.n_axes
            def step(self, t, y):
                {body}
        """))
    r = simulate(modal, 0.01, law=resolve("bad.py:Bad", tmp_path))
    assert r.steps == 0 and r.fault.startswith("law bad.py:Bad: ") and says in r.fault, r.fault
    assert "\n" not in r.fault


@pytest.mark.parametrize("spec, says", [
    ("nope.py:X", "no such file"),
    ("law.py", "FILE.py:CLASS"),
    ("law.txt", "not a law"),
    ("law.py:Missing", "has no 'Missing'"),
])
def test_a_law_that_cannot_be_loaded_is_named(tmp_path, spec, says):
    (tmp_path / "law.py").write_text("class L:\n    def step(self, t, y):\n        return y\n")
    (tmp_path / "law.txt").write_text("")
    with pytest.raises(LawError, match=says):
        law_factory(resolve(spec, tmp_path))


def test_scene_law_is_relative_to_the_scene_and_used_by_controller_runner(tmp_path):
    (tmp_path / "laws").mkdir()
    (tmp_path / "laws" / "p.py").write_text(
        "import numpy as np\nclass P:\n    def __init__(self, meta):\n        self.k = meta.params['k']\n"
        "        self.u0 = np.array(meta.u_op)\n    def step(self, t, y):\n        return self.u0 - self.k * y\n")
    src = re.sub(r"^\[controller\].*$", '[controller]\nlaw = "laws/p.py:P"', open(SCENE).read(),
                 count=1, flags=re.M)
    src += "\n[controller.params]\nk = 7.5\n"
    (tmp_path / "s.toml").write_text(src)
    r = controller_runner(tmp_path / "s.toml", rung="modal")
    assert isinstance(r, LawRunner) and r.name == "p.py:P" and r.law.k == 7.5
    assert r.meta.controller["kp"] == pytest.approx(5.98869)


def test_meta_gives_the_c_law_its_parameters_as_json(modal):
    meta = LawMeta.of(modal.scene.controller, modal.i_op, axis_names(modal.scene))
    import json
    d = json.loads(meta.params_json())
    assert d["axes"][0] == "A-x" and len(d["i_op"]) == 6 and d["controller"]["kp"] == pytest.approx(5.98869)
