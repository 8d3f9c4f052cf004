"""The C ABI of laws (include/ambhil_law.h, controller/law_c.py): examples/c_law/pid_law.c, the
built-in PID as firmware would write it, reproduces the built-in fused law bit for bit (compiled
with ``-ffp-contract=off``: no fused multiply-add, so the C code does the IEEE operations numba's
kernel does, in the same order); a library missing a symbol, a law refusing to start and a law
returning a fault code are each named in one line.  Skipped where there is no C compiler."""
from __future__ import annotations

import re
import shutil
import subprocess
import textwrap
from pathlib import Path

import numpy as np
import pytest

from ambhil.controller.law import LawError, LawMeta
from ambhil.controller.law_c import CLaw
from ambhil.controller.law_loader import law_factory, resolve
from ambhil.controller.law_runner import LawRunner
from ambhil.controller.params import ControllerParams
from ambhil.controller.pid_law import PIDLaw
from ambhil.loop.scene_faults import parse_fault_spec
from ambhil.loop.simulation import simulate
from ambhil.loop.system import compile_system
from ambhil.plant.faults import FaultSchedule

ROOT = Path(__file__).resolve().parents[1]
CC = shutil.which("cc")
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler (cc) to build the C laws")

# no FMA contraction: the same IEEE operations as numba's kernel (bit for bit)
CFLAGS = ["-O2", "-shared", "-fPIC", "-ffp-contract=off", "-Wall", "-Werror"]


def build(src: Path, out: Path) -> Path:
    r = subprocess.run([CC, *CFLAGS, "-I", str(ROOT / "include"), "-o", str(out), str(src)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return out


def build_text(tmp: Path, name: str, code: str) -> str:
    (tmp / f"{name}.c").write_text(textwrap.dedent(code))
    return str(build(tmp / f"{name}.c", tmp / f"{name}.so"))


@pytest.fixture(scope="module")
def pid_so(tmp_path_factory) -> str:
    return str(build(ROOT / "examples/c_law/pid_law.c", tmp_path_factory.mktemp("c_law") / "pid_law.so"))


def scene_with(tmp: Path, base: str, old: str, new: str) -> str:
    src = open(ROOT / "scenes" / base).read()
    assert old in src
    (tmp / base).write_text(src.replace(old, new))
    return str(tmp / base)


def test_c_pid_equals_the_builtin_law_bit_for_bit_on_the_paper_scene(pid_so):
    m = compile_system(str(ROOT / "scenes/paper_3amb.toml"), rung="modal")
    a, b = simulate(m, 0.2), simulate(m, 0.2, law=pid_so)
    assert b.fault is None and b.steps == a.steps == 2000 and b.meta["law"] == "pid_law.so"
    assert np.array_equal(a.y, b.y) and np.array_equal(a.i, b.i)


def test_c_pid_equals_the_builtin_law_with_operating_currents_and_saturation(pid_so, tmp_path):
    """The misaligned bearing B needs 1.33 A at rest (the integrator starts at u_op); with the
    current limit lowered to 1.4 A the amplifier input is limited for hundreds of samples and the
    anti-windup holds the integrator."""
    m = compile_system(scene_with(tmp_path, "paper_3amb_misaligned.toml", "current_limit = 4.0",
                                  "current_limit = 1.4"), rung="modal")
    assert np.abs(m.i_op).max() > 1.0
    a, b = simulate(m, 0.2), simulate(m, 0.2, law=pid_so)
    assert (np.abs(a.i) >= 1.4 * (1 - 1e-12)).sum() > 100          # the limit was exercised
    assert b.fault is None and np.array_equal(a.y, b.y) and np.array_equal(a.i, b.i)


def test_controller_restart_resets_the_c_law(pid_so):
    """A fault schedule's controller restart: the C law's ambhil_law_reset and the built-in
    runner's reset give the same loop afterwards."""
    m = compile_system(str(ROOT / "scenes/paper_3amb.toml"), rung="modal")
    faults = FaultSchedule((parse_fault_spec("controller_restart:at=0.05s", m.scene.plant, 1),))
    a, b = simulate(m, 0.1, faults=faults), simulate(m, 0.1, faults=faults, law=pid_so)
    assert b.fault is None and np.array_equal(a.i, b.i) and np.array_equal(a.y, b.y)
    c = simulate(m, 0.1, law=pid_so)
    assert not np.array_equal(b.i, c.i)                               # the restart did something


def test_c_law_runs_in_the_law_runner_and_frees_its_state_once(pid_so):
    cfg = ControllerParams(kp=2.0, ki=30.0, kd=1e-3, derivative_filter=1e-4)
    r = LawRunner(law_factory(resolve(pid_so))[0], cfg, [0.5, -0.25], axes=["A-x", "A-y"], name="pid_law.so")
    assert isinstance(r.law, CLaw)
    np.testing.assert_allclose(r.step(np.zeros(2)), [0.5, -0.25], rtol=1e-12)  # holds i_op at rest
    r.law.close()
    r.law.close()                                                     # a second close does nothing
    with pytest.raises(LawError, match="used after close"):
        r.step(np.zeros(2))


MINIMAL = """\
    #include <stdlib.h>
    #include "ambhil_law.h"
    typedef struct { int n; long k; } law_t;
    void *ambhil_law_new(int n, double T, const char *axes, const char *json)
    { law_t *s = calloc(1, sizeof *s); s->n = n; return s; }
    int ambhil_law_step(void *state, double t, const double *y, double *u)
    { law_t *s = state; for (int a = 0; a < s->n; a++) u[a] = -y[a];
      return ++s->k > 25 ? 3 : 0; }
    void ambhil_law_reset(void *state) { ((law_t *)state)->k = 0; }
    """


def test_a_library_missing_a_symbol_is_named(tmp_path):
    so = build_text(tmp_path, "nofree", MINIMAL)
    with pytest.raises(LawError, match=r"^law nofree.so: missing symbol ambhil_law_free \(the C ABI "
                                       r"of include/ambhil_law.h\)$"):
        CLaw(so, LawMeta.of(ControllerParams(kp=1.0), [0.0]))


def test_a_law_refusing_to_start_is_named(tmp_path):
    so = build_text(tmp_path, "refuse", MINIMAL.replace("law_t *s = calloc", "return NULL; law_t *s = calloc")
                    + "void ambhil_law_free(void *s) { free(s); }\n")
    m = compile_system(str(ROOT / "scenes/paper_3amb.toml"), rung="modal")
    with pytest.raises(LawError, match=r"^law refuse.so: ambhil_law_new returned NULL .*6 axes"):
        simulate(m, 0.01, law=so)


@pytest.mark.parametrize("named", [True, False])
def test_a_fault_code_ends_the_run_naming_the_law_the_code_and_the_step(tmp_path, named):
    code = MINIMAL + "void ambhil_law_free(void *s) { free(s); }\n"
    if named:
        code += 'const char *ambhil_law_fault_name(int c) { return c == 3 ? "coil overtemperature" : 0; }\n'
    so = build_text(tmp_path, "faulty", code)
    m = compile_system(str(ROOT / "scenes/paper_3amb.toml"), rung="modal")
    r = simulate(m, 0.01, law=so)
    assert r.steps == 25 and "\n" not in r.fault
    name = " (coil overtemperature)" if named else ""
    assert r.fault == f"law faulty.so: step 25: ambhil_law_step returned fault code 3{name} at t = 0.0025 s"


def test_pid_law_refuses_more_axes_than_its_arrays_hold_and_equals_pid_law_up_to_them(pid_so):
    """16 axes (its MAX_AXES) against the built-in law's class, step for step; 17 are refused."""
    cfg = ControllerParams(kp=3.0, ki=40.0, kd=2e-3, derivative_filter=1e-4)
    i_op = np.linspace(-0.5, 0.5, 16)
    with pytest.raises(LawError, match="ambhil_law_new returned NULL"):
        CLaw(pid_so, LawMeta.of(cfg, np.zeros(17)))
    meta = LawMeta.of(cfg, i_op)
    c, p = CLaw(pid_so, meta), PIDLaw(meta)
    rng = np.random.default_rng(5)
    for k in range(200):
        y = rng.normal(0.0, 0.3, 16)
        assert np.array_equal(c.step(k * meta.period, y), p.step(k * meta.period, y))
    c.close()


def test_header_compiles_as_cpp_and_declares_the_abi(tmp_path):
    """The shipped header: C++ sees C linkage (the extern "C" guard)."""
    cxx, nm = shutil.which("c++"), shutil.which("nm")
    if cxx is None or nm is None:
        pytest.skip("no C++ compiler or nm")
    (tmp_path / "h.cpp").write_text('#include "ambhil_law.h"\nint main() { return ambhil_law_new(1, 1e-4, "A-x", "{}") != 0; }\n')
    r = subprocess.run([cxx, "-c", "-I", str(ROOT / "include"), "-o", str(tmp_path / "h.o"), str(tmp_path / "h.cpp")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    syms = subprocess.run([nm, str(tmp_path / "h.o")], capture_output=True, text=True).stdout
    assert re.search(r"\bU ambhil_law_new$", syms, re.M), syms           # unmangled
