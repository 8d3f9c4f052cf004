"""Controller FMUs (controller/law_fmu.py): the example FMU of examples/fmu_law, built here for
FMI 2.0 and 3.0 co-simulation, holds the paper rotor and gives the very numbers of the same law
written in Python; variables are matched by name or by the scene's [controller.fmu] table; a
malformed FMU, one for model exchange only, a missing variable or parameter and a failing doStep
are each one line naming the FMU."""
from __future__ import annotations

import dataclasses
import importlib.util
import re
import shutil
import sys
import zipfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from ambhil.controller.law import LawError
from ambhil.controller.law_loader import law_factory, resolve
from ambhil.controller.law_runner import LawRunner
from ambhil.loop.simulation import simulate
from ambhil.loop.system import axis_names, compile_system, controller_runner

pytest.importorskip("fmpy", reason="FMU laws need fmpy (pip install 'ambhil[fmu]')")

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "paper_3amb.toml"
CC = shutil.which("cc")
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler `cc` to build the example FMU")


def _build_module():
    spec = importlib.util.spec_from_file_location("build_fmu", ROOT / "examples" / "fmu_law" / "build_fmu.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


BUILD = _build_module()
OTHER_IN = [f"sensor{k}" for k in range(6)]
OTHER_OUT = [f"coil{k}" for k in range(6)]


@pytest.fixture(scope="module")
def fmus(tmp_path_factory):
    d = tmp_path_factory.mktemp("fmu")
    return {2: BUILD.build_fmu(d, 2), 3: BUILD.build_fmu(d, 3),
            "other": BUILD.build_fmu(d, 3, inputs=OTHER_IN, outputs=OTHER_OUT, file_name="other.fmu")}


@pytest.fixture(scope="module")
def modal():
    return compile_system(SCENE, rung="modal")


TWIN = str(ROOT / "examples" / "fmu_law" / "pid_twin.py") + ":PIDTwin"


def _twin_runner(config, i_op, axes):
    factory, name = law_factory(resolve(TWIN))
    return LawRunner(factory, config, i_op, axes=axes, name=name)


def _with(modal, **controller):
    """``modal`` with its scene's [controller] changed (``law_params``, ``table``, ...)."""
    c = dataclasses.replace(modal.scene.controller, **controller)
    return dataclasses.replace(modal, scene=dataclasses.replace(modal.scene, controller=c))


def _runner(modal, fmu, **controller):
    factory, name = law_factory(resolve(str(fmu)))
    c = dataclasses.replace(modal.scene.controller, **controller)
    return LawRunner(factory, c, modal.i_op, axes=axis_names(modal.scene), name=name)


@pytest.mark.parametrize("fmi", [2, 3])
def test_fmu_in_the_loop_equals_its_python_twin_bit_for_bit(modal, fmus, fmi):
    """0.2 s of the paper rotor (2000 periods) under the FMU and under the Python twin: the same
    displacements and currents bit for bit (C doubles without contraction, the same operations in
    the same order), the rotor held; against the built-in PID (Tustin, scipy) the orbit agrees to
    2 %: the example's derivative (backward Euler) and integral (forward Euler) differ from it."""
    r = simulate(modal, 0.2, law=resolve(str(fmus[fmi])))
    assert r.fault is None and r.steps == 2000 and r.meta["law"] == fmus[fmi].name
    twin = simulate(modal, 0.2, law=resolve(TWIN))
    assert twin.fault is None and twin.meta["law"] == "pid_twin.py:PIDTwin"
    assert np.array_equal(r.y, twin.y) and np.array_equal(r.i, twin.i)
    gap = modal.scene.plant.ambs[0].gap
    assert np.abs(r.y).max() < 0.1 * gap                      # levitated: the unbalance orbit only
    builtin = simulate(modal, 0.2)
    tail = slice(-500, None)
    amp, ref = np.abs(r.y[tail]).max(), np.abs(builtin.y[tail]).max()
    assert abs(amp - ref) < 0.02 * ref, (amp, ref)


def test_scene_table_maps_other_variable_names_and_sets_parameters(fmus, tmp_path):
    """[controller.fmu] names the variables (sensor0.., coil0..), [controller.params] sets the
    FMU's gains: the runner of the scene equals the twin of the same gains sample by sample."""
    shutil.copy(fmus["other"], tmp_path / "ctl.fmu")
    src = re.sub(r"^\[controller\].*$", '[controller]\nlaw = "ctl.fmu"', SCENE.read_text(), count=1, flags=re.M)
    src += (f"\n[controller.fmu]\ninputs = {OTHER_IN!r}\noutputs = {OTHER_OUT!r}\n"
            "\n[controller.params]\nkp = 4.5\nki = 12.0\nkd = 2.5e-3\n").replace("'", '"')
    (tmp_path / "s.toml").write_text(src)
    r = controller_runner(tmp_path / "s.toml", rung="modal")
    assert isinstance(r, LawRunner) and r.name == "ctl.fmu"
    twin = _twin_runner(r.config, r.i_op, r.meta.axes)
    assert twin.law.kp == 4.5
    rng = np.random.default_rng(5)
    for _ in range(300):
        d = rng.normal(0.0, 2e-5, 6)
        assert np.array_equal(r.step(d), twin.step(d))
    r.close()


def test_default_names_match_without_case_and_separators():
    """The rule of controller/law_fmu.py: input y_<axis> or <axis>, output u_<axis> or <axis>,
    compared without case, '-', '_', '.' and spaces."""
    from ambhil.controller.law_fmu import _mapping
    meta = SimpleNamespace(axes=("A-x", "B-y"), n_axes=2, controller={})
    vrs = iter(range(100))
    var = lambda n, c: SimpleNamespace(name=n, causality=c, type="Real", valueReference=next(vrs))  # noqa: E731
    ins, outs = [var("yAx", "input"), var("B_y", "input")], [var("U.A.X", "output"), var("u_b_y", "output"),
                                                            var("monitor", "output")]
    vin, vout = _mapping("f.fmu", meta, ins, outs, {v.name: v for v in ins + outs})
    assert [v.name for v in vin] == ["yAx", "B_y"] and [v.name for v in vout] == ["U.A.X", "u_b_y"]
    with pytest.raises(LawError, match="the FMU's input 'speed' is fed by no axis"):
        extra = ins + [var("speed", "input")]
        _mapping("f.fmu", meta, extra, outs, {v.name: v for v in extra + outs})


def test_missing_variable_is_named_with_the_fmus_real_ones(modal, fmus):
    with pytest.raises(LawError) as e:
        _runner(modal, fmus["other"])
    assert str(e.value).startswith("law other.fmu: no input y_A_x or A_x for axis A-x; its inputs: sensor0, ")
    assert "its outputs: coil0, " in str(e.value) and "\n" not in str(e.value)
    table = {"fmu": {"inputs": OTHER_IN[:5] + ["nope"], "outputs": OTHER_OUT}}
    with pytest.raises(LawError, match=r"law other.fmu: \[controller.fmu\] inputs: the FMU's variable 'nope' "
                                       r"\(axis C-y\) does not exist; its inputs: sensor0, .*"):
        _runner(modal, fmus["other"], table=table)
    table = {"fmu": {"inputs": OTHER_IN, "outputs": OTHER_OUT[:5] + ["sensor5"]}}
    with pytest.raises(LawError, match=r"the FMU's variable 'sensor5' \(axis C-y\) is an input, not an output"):
        _runner(modal, fmus["other"], table=table)


@pytest.mark.parametrize("params, says", [
    ({"kq": 1.0}, r"\[controller.params\] key 'kq' is not a variable of the FMU, not a parameter "
                  r"\(the FMU's parameters: kp, ki, kd, td, fail_after, u_op_A_x"),
    ({"y_A_x": 1.0}, "key 'y_A_x' is an input, not a parameter"),
    ({"kp": "big"}, r"\[controller.params\] kp = 'big': the FMU's parameter is Real"),
    ({"fail_after": 2.5}, r"fail_after = 2.5: the FMU's parameter is Integer"),
])
def test_a_parameter_the_fmu_does_not_have_is_named(modal, fmus, params, says):
    with pytest.raises(LawError, match="law pid_law_fmi2.fmu: .*" + says):
        _runner(modal, fmus[2], law_params=params)


def _rezip(src: Path, dst: Path, xml=None, drop=(), binary=None):
    """``src`` copied to ``dst`` with its modelDescription.xml edited by ``xml(text)``, the
    members starting with ``drop`` left out and the library's bytes replaced by ``binary``."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            if item.filename.startswith(tuple(drop)) and drop:
                continue
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml" and xml is not None:
                data = xml(data.decode()).encode()
            if item.filename.startswith("binaries/") and binary is not None:
                data = binary
            zout.writestr(item, data)
    return dst


def _not_a_zip(src: Path, d: Path) -> Path:
    (d / "bad.fmu").write_bytes(b"not a zip")
    return d / "bad.fmu"


@pytest.mark.parametrize("make, says", [
    (_not_a_zip, "not an FMU (not a zip archive)"),
    (lambda src, d: _rezip(src, d / "bad.fmu", drop=("modelDescription",)),
     "not an FMU (no modelDescription.xml in the archive)"),
    (lambda src, d: _rezip(src, d / "bad.fmu", xml=lambda t: t.replace("</fmiModelDescription>", "")),
     "a broken modelDescription.xml: "),
    (lambda src, d: _rezip(src, d / "bad.fmu", drop=("binaries",)),
     "no binary for this platform (binaries/linux64/pid_law.so); the FMU has none"),
    (lambda src, d: _rezip(src, d / "bad.fmu", binary=b"not a library"),
     "cannot instantiate the FMU for co-simulation: Failed to load shared library "),
])
def test_a_malformed_fmu_is_named(modal, fmus, tmp_path, make, says):
    bad = make(fmus[2], tmp_path)
    if sys.platform != "linux" and "binary" in says:
        says = "no binary for this platform"
    cwd = Path.cwd()
    with pytest.raises(LawError) as e:
        _runner(modal, bad)
    assert str(e.value).startswith("law bad.fmu: ") and says in str(e.value), str(e.value)
    assert "\n" not in str(e.value) and Path.cwd() == cwd


@pytest.mark.parametrize("fmi", [2, 3])
def test_an_fmu_for_model_exchange_only_is_refused(modal, fmus, tmp_path, fmi):
    me = _rezip(fmus[fmi], tmp_path / "me.fmu", xml=lambda t: re.sub(
        r"<CoSimulation[^>]*/>", '<ModelExchange modelIdentifier="pid_law"/>', t))
    with pytest.raises(LawError, match=r"^law me.fmu: an FMU for model exchange only; "
                                       r"a controller FMU must support co-simulation$"):
        _runner(modal, me)


@pytest.mark.parametrize("fmi", [2, 3])
def test_a_failing_dostep_ends_the_run_naming_the_law_the_status_and_the_time(modal, fmus, fmi):
    r = simulate(_with(modal, law_params={"fail_after": 500}), 0.2, law=resolve(str(fmus[fmi])))
    assert r.steps == 500 and "\n" not in r.fault
    assert r.fault == (f"law pid_law_fmi{fmi}.fmu: step 500 (t = 0.05 s) raised FMIError: fmi{fmi}DoStep "
                       f"returned fmi{fmi}Error (the FMU's log: Error: fail_after = 500 steps reached "
                       f"(t = 0.05 s))"), r.fault


@pytest.mark.parametrize("fmi", [2, 3])
def test_reset_starts_over_and_close_removes_the_extracted_fmu(modal, fmus, fmi):
    r = _runner(modal, fmus[fmi])
    folder = Path(r.law._state["dir"])
    assert folder.is_dir()
    d = np.random.default_rng(2).normal(0.0, 2e-5, (100, 6))
    first = np.array([r.step(x) for x in d])
    r.reset()
    again = np.array([r.step(x) for x in d])
    assert np.array_equal(first, again) and np.abs(first).max() > 0
    r.close()
    r.close()
    assert not folder.exists()


def test_without_fmpy_the_error_says_how_to_install_it(modal, fmus, monkeypatch):
    monkeypatch.setitem(sys.modules, "fmpy", None)
    with pytest.raises(LawError, match=r"^law pid_law_fmi2.fmu: FMU laws need fmpy: pip install 'ambhil\[fmu\]'$"):
        _runner(modal, fmus[2])


def test_build_script_cli_writes_the_fmu(tmp_path):
    """examples/fmu_law/build_fmu.py as a user runs it."""
    import subprocess
    out = subprocess.run([sys.executable, str(ROOT / "examples" / "fmu_law" / "build_fmu.py"), "--fmi", "3",
                          "--out", str(tmp_path), "--axes", "A-x,A-y"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    fmu = Path(out.stdout.strip())
    assert fmu == tmp_path / "pid_law_fmi3.fmu"
    import fmpy
    md = fmpy.read_model_description(str(fmu))
    assert [v.name for v in md.modelVariables if v.causality == "input"] == ["y_A_x", "y_A_y"]
