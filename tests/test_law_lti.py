"""LTI laws written in the scene (controller/law_lti.py): ``[controller] kind = "transfer"`` and
``"statespace"``.  The closed loop of the analyses equals python-control's own interconnection
of the plant and the controller chain (built here from the documented formulas, not by the
module); a PID written as a transfer block gives the built-in's analyses and time domain; the
runner equals a direct discrete simulation; the simulated loop map equals loop/sampled.py;
bad tables are refused in one line naming the table and key."""
from __future__ import annotations

import dataclasses
import math
import re

import control
import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from ambhil.controller.law_lti import LTILaw, LTIWarning
from ambhil.loop import sampled as sd
from ambhil.loop.analysis import closed_loop, modal, sensitivity
from ambhil.loop.period_map import loop_matrix
from ambhil.loop.scene import load_scene
from ambhil.loop.scene_table import SceneError
from ambhil.loop.simulation import simulate
from ambhil.loop.system import axis_names, compile_system, controller_runner
from ambhil.plant.step import make_plan

SCENE = "scenes/paper_3amb.toml"
KP, KI, KD, TD = 5.98869, 20.0, 3.245942e-03, 1.0e-4      # the paper's gains (scenes/paper_3amb.toml)
PID = f'{{type = "pid", kp = {KP}, ki = {KI}, kd = {KD}, derivative_filter = {TD}}}'
CHAIN = ('blocks = [' + PID + ', {type = "notch", frequency = 600.0, width = 0.3, depth = 0.1}, '
         '{type = "lead_lag", zero = 1500.0, pole = 1000.0}, {type = "tf", num = [1.0], den = [2e-5, 1.0]}]')
W0, DEPTH, WIDTH = 2 * np.pi * 600.0, 0.1, 0.3
SPEED = 300.0


def scene_with(tmp, controller: str, name: str = "s.toml") -> str:
    """scenes/paper_3amb.toml with its [controller] table replaced."""
    src = open(SCENE).read()
    out = re.sub(r"\[controller\].*?\n\n", lambda _: controller.strip() + "\n\n", src, count=1, flags=re.S)
    path = tmp / name
    path.write_text(out)
    return str(path)


def transfer_scene(tmp, chain=CHAIN, extra="", name="tr.toml"):
    return scene_with(tmp, f'[controller]\nkind = "transfer"\nsample_rate = 10000.0\n{extra}\n'
                           f'[controller.transfer]\n{chain}\n', name)


def _fmt(M) -> str:
    return "[" + ", ".join("[" + ", ".join(repr(float(v)) for v in r) + "]" for r in np.atleast_2d(M)) + "]"


def mimo_law(na: int = 6):
    """A coupled MIMO law (its y and u in the loop's axes reversed, ``inputs`` / ``outputs``): the PID on
    every axis, a cross-coupling between x and y of each bearing through a first-order lag, and a
    static coupling between the first two bearings."""
    pid = control.ss(control.tf([KP * TD + KD, KP + KI * TD, KI], [TD, 1.0, 0.0]))
    K = -control.append(*[pid] * na)
    lag = control.ss(control.tf([0.2], [1 / (2 * np.pi * 150.0), 1.0]))
    cross = np.zeros((na, na))
    for b in range(0, na, 2):
        cross[b, b + 1], cross[b + 1, b] = 1.0, -1.0
    K = K + control.append(*[lag] * na) * control.ss([], [], [], cross)
    D = np.array(K.D, float)
    D[2, 0] += 0.1
    D[0, 2] -= 0.1
    return np.array(K.A, float), np.array(K.B, float), np.array(K.C, float), D


def mimo_scene(tmp, discrete: float = 0.0, name="ss.toml", **override):
    A, B, C, D = mimo_law()
    if discrete:
        d = control.c2d(control.ss(A, B, C, D), discrete, method="tustin")
        A, B, C, D = (np.array(m, float) for m in (d.A, d.B, d.C, d.D))
    axes = list(axis_names(load_scene(SCENE)))
    t = {"A": _fmt(A), "B": _fmt(B), "C": _fmt(C), "D": _fmt(D), "dt": repr(discrete),
         "inputs": "[" + ", ".join(f'"{a}"' for a in axes[::-1]) + "]",
         "outputs": "[" + ", ".join(f'"{a}"' for a in axes[::-1]) + "]"}
    t.update(override)
    body = "\n".join(f"{k} = {v}" for k, v in t.items())
    return scene_with(tmp, f'[controller]\nkind = "statespace"\nsample_rate = 10000.0\n'
                           f'[controller.statespace]\n{body}\n', name)


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    return tmp_path_factory.mktemp("lti")


@pytest.fixture(scope="module")
def builtin():
    return compile_system(SCENE, rung="modal")


# --------------------------------------------------------------------------- (a) vs python-control
def _lag(gain, tau):
    return control.tf([gain], [tau, 1.0]) if tau > 0 else control.tf([gain], [1.0])


def _notch():
    """The documented notch: z_p = width / 2, z_z = depth width / 2."""
    zp, zz = WIDTH / 2, DEPTH * WIDTH / 2
    return control.tf([1.0, 2 * zz * W0, W0 ** 2], [1.0, 2 * zp * W0, W0 ** 2])


def _rest():
    """CHAIN after its pid block."""
    return (_notch() * control.tf([1 / (2 * np.pi * 1500.0), 1.0], [1 / (2 * np.pi * 1000.0), 1.0])
            * control.tf([1.0], [2e-5, 1.0]))


def _closed_loop_eigs_by_control(m, K_y_to_u):
    """Closed-loop eigenvalues of python-control's interconnection: the plant (loop/sampled.py
    plant_of: coil current deviations -> sensor displacements) fed back through
    i = G_A K(s) G_s y, K the law from sensor outputs to amplifier inputs."""
    p = sd.plant_of(m, SPEED)
    P = control.ss(p.A, p.B, p.C, np.zeros((m.n_axes, m.n_axes)))
    s, a = m.scene.controller.sensor, m.scene.controller.amplifier
    na = m.n_axes
    chain = (control.append(*[control.ss(_lag(a.gain, a.time_constant))] * na) * K_y_to_u
             * control.append(*[control.ss(_lag(s.gain, s.time_constant))] * na))
    cl = control.feedback(P, chain, sign=+1)
    return np.linalg.eigvals(np.array(cl.A, float))


def _match(a, b):
    assert len(a) == len(b)
    r, c = linear_sum_assignment(np.abs(a[:, None] - b[None, :]))
    return np.abs(a[r] - b[c]) / np.maximum(np.abs(a[r]), 1.0)


def test_transfer_closed_loop_equals_python_controls_interconnection(tmp):
    m = compile_system(transfer_scene(tmp), rung="modal")
    C = control.tf([KP * TD + KD, KP + KI * TD, KI], [TD, 1.0, 0.0]) * _rest()
    K = control.append(*[control.ss(-C)] * m.n_axes)          # u = C e, e = -y
    ref = _closed_loop_eigs_by_control(m, K)
    ours = np.linalg.eigvals(closed_loop.build(m, SPEED, sparse=False).dense_standard())
    err = _match(ours, ref)
    assert err.max() < 1e-8, err.max()
    # the notch is where it was asked: its gain at the centre is the depth
    assert abs(_notch()(1j * W0)) == pytest.approx(DEPTH, rel=1e-12)


def test_mimo_statespace_closed_loop_equals_python_controls_interconnection(tmp):
    m = compile_system(mimo_scene(tmp), rung="modal")
    assert m.H.D.shape == (m.n_axes, m.n_axes)
    A, B, C, D = mimo_law()
    na = m.n_axes
    R = np.eye(na)[::-1]                                      # inputs and outputs: the axes reversed
    K = control.ss(A, B @ R, R @ C, R @ D @ R)
    ref = _closed_loop_eigs_by_control(m, K)
    ours = np.linalg.eigvals(closed_loop.build(m, SPEED, sparse=False).dense_standard())
    err = _match(ours, ref)
    assert err.max() < 1e-8, err.max()
    # the sparse build (the full rung's path) is the same matrix
    sp = closed_loop.build(m, SPEED, sparse=True)
    assert np.allclose(sp.dense_standard(), closed_loop.build(m, SPEED, sparse=False).dense_standard(),
                       rtol=0, atol=0)


def test_mimo_sensitivity_is_the_diagonal_of_the_sensitivity_matrix(tmp):
    """S_jj from the dynamic stiffness equals the diagonal of (I + P K)^-1 of python-control's
    interconnection, P the plant and K the chain (disturbance at the sensor signals)."""
    m = compile_system(mimo_scene(tmp), rung="modal")
    w = 2 * np.pi * np.array([20.0, 51.4, 150.0, 700.0])
    S = sensitivity.evaluate_S(m, SPEED, w)
    p = sd.plant_of(m, SPEED)
    from ambhil.controller.transfer import evaluate_matrix
    for k, wk in enumerate(w):
        Pw = p.C @ np.linalg.solve(1j * wk * np.eye(p.n) - p.A, p.B)
        H = evaluate_matrix(m.H, np.array([1j * wk]))[0]
        Sm = np.linalg.inv(np.eye(m.n_axes) + Pw @ H)         # i = -H y
        np.testing.assert_allclose(S[k], np.diag(Sm), rtol=1e-9)


# --------------------------------------------------------------------------- (b) the PID as a block
def test_pid_as_a_transfer_block_gives_the_builtins_analyses(tmp, builtin):
    m = compile_system(transfer_scene(tmp, "blocks = [" + PID + "]", name="pid.toml"), rung="modal")
    assert m.H.D.shape == (1, 1)                              # one chain on every axis: SISO
    a, b = modal.critical_speeds(builtin), modal.critical_speeds(m)
    assert len(a) == len(b) > 2
    for x, y in zip(a, b):
        assert y.speed == pytest.approx(x.speed, rel=1e-10)
        assert y.damping_ratio == pytest.approx(x.damping_ratio, rel=1e-8)
    sa, sb = sensitivity.sensitivity(builtin, 0.0), sensitivity.sensitivity(m, 0.0)
    np.testing.assert_allclose(sb.peaks, sa.peaks, rtol=1e-9)


@pytest.mark.parametrize("changes", [{}, {"discretisation": "zoh"}, {"delay_samples": 1}])
def test_pid_as_a_transfer_block_runs_like_the_builtin(tmp, builtin, changes):
    """Tustin and ZOH are both linear in the system, so the product of the discretised blocks
    (the built-in: P + I + D, each on its own) and the discretised sum (one pid block) are the
    same discrete law; only the realisation differs: round-off, 1e-10 of the orbit."""
    extra = "\n".join(f"{k} = {v!r}".replace("'", '"') for k, v in changes.items())
    m = compile_system(transfer_scene(tmp, "blocks = [" + PID + "]", extra, name="pidrun.toml"), rung="modal")
    ref = builtin if not changes else compile_system(load_scene(SCENE).with_controller(**changes), rung="modal")
    a, b = simulate(ref, 0.03, speed=SPEED), simulate(m, 0.03, speed=SPEED)
    assert b.meta["law"] == "[controller] kind = 'transfer'" and b.fault is None
    assert np.abs(b.orbit - a.orbit).max() <= 1e-10 * np.abs(a.orbit).max()


# --------------------------------------------------------------------------- (c) the runner, directly
def test_runner_equals_a_direct_discrete_simulation(tmp):
    """sensor -> law -> amplifier of the runner against python-control's forced_response of the
    Tustin transform of the whole chain G_A C G_s (Tustin of a product is the product)."""
    m = compile_system(transfer_scene(tmp), rung="modal")
    r = controller_runner(m)
    assert isinstance(r.law, LTILaw)
    c = m.scene.controller
    T = r.period
    blocks = [_lag(c.amplifier.gain, c.amplifier.time_constant),
              control.tf([KP * TD + KD, KP + KI * TD, KI], [TD, 1.0, 0.0]), _notch(),
              control.tf([1 / (2 * np.pi * 1500.0), 1.0], [1 / (2 * np.pi * 1000.0), 1.0]),
              control.tf([1.0], [2e-5, 1.0]), _lag(c.sensor.gain, c.sensor.time_constant)]
    chain = control.ss(blocks[0])
    for b in blocks[1:]:
        chain = chain * control.ss(b)                         # in series, as state space
    Hd = control.c2d(chain, T, method="tustin")
    rng = np.random.default_rng(5)
    d = rng.normal(0.0, 1e-6, (400, m.n_axes))               # small: no limit reached
    cur = np.array([r.step(dk) for dk in d]) - np.asarray(m.i_op)
    for a in range(m.n_axes):
        ref = -control.forced_response(Hd, U=d[:, a]).outputs
        assert np.abs(cur[:, a] - ref).max() <= 1e-9 * np.abs(ref).max()


def test_mimo_law_runs_and_its_discrete_matrices_are_control_c2d(tmp):
    m = compile_system(mimo_scene(tmp), rung="modal")
    r = controller_runner(m)
    A, B, C, D = mimo_law()
    R = np.eye(m.n_axes)[::-1]
    d = control.c2d(control.ss(A, B @ R, R @ C, R @ D @ R), r.period, method="tustin")
    for ours, ref in zip((r.law.Ad, r.law.Bd, r.law.Cd, r.law.Dd), (d.A, d.B, d.C, d.D)):
        np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    res = simulate(m, 0.02, speed=SPEED, stability_check=True)
    assert res.fault is None and res.instability is None
    # the same law written discrete (dt = the period): the same run
    md = compile_system(mimo_scene(tmp, discrete=r.period, name="ssd.toml"), rung="modal")
    rd = simulate(md, 0.02, speed=SPEED)
    assert np.abs(rd.orbit - res.orbit).max() <= 1e-9 * np.abs(res.orbit).max()
    # and its continuous equivalent for the analyses (inverse Tustin) is the continuous law
    ev = lambda s: np.sort_complex(np.linalg.eigvals(closed_loop.build(s, SPEED, sparse=False).dense_standard()))
    assert _match(ev(md), ev(m)).max() < 1e-7


# --------------------------------------------------------------------------- (d) the sampled loop
@pytest.mark.parametrize("kind,delay", [("transfer", 0), ("transfer", 2), ("statespace", 0), ("statespace", 1)])
def test_simulated_loop_map_equals_the_sampled_loop(tmp, kind, delay):
    extra = f"delay_samples = {delay}"
    path = (transfer_scene(tmp, extra=extra, name=f"d{delay}.toml") if kind == "transfer"
            else mimo_scene(tmp, name=f"sd{delay}.toml"))
    sc = load_scene(path)
    if kind == "statespace":
        sc = sc.with_controller(delay_samples=delay)
    m = compile_system(sc, rung="modal")
    r = controller_runner(m)
    plan = make_plan(m, "zoh", r.period, speed=SPEED, nonlinear=False, ratio=1)
    L, span = loop_matrix(m, plan, r, 1)
    ours = sd.SampledLoop(sd.plant_of(m, SPEED), sd.controller_of(r)).mode(0.0)
    rho_k = np.max(np.abs(np.linalg.eigvals(L))) ** (1 / span)
    rho = np.max(np.abs(np.linalg.eigvals(ours)))
    assert rho == pytest.approx(rho_k, rel=1e-10)
    assert (rho < 1.0) == (delay == 0)      # the paper's loop has about half a period of latency margin


# --------------------------------------------------------------------------- (e) bad input
@pytest.mark.parametrize("chain,match", [
    ('blocks = [{type = "notch", frequency = 212.0, width = 0.3, depth = 1.5}]',
     r"\[controller.transfer\] blocks\[0\] \(notch\): key 'depth'"),
    ('blocks = [{type = "pid", kp = 1.0}, {type = "bandpass"}]', r"blocks\[1\]: key 'type' must be one of"),
    ('blocks = [{type = "pid", kp = 1.0, kd = 1e-3}]', r"\(pid\): key 'derivative_filter' must be > 0"),
    ('blocks = [{type = "tf", num = [1.0, 0.0], den = [1.0]}]', r"\(tf\): improper"),
    ('blocks = [{type = "lead_lag", zero = 100.0, pole = 1000.0, gain = 2.0}]', r"\(lead_lag\): unknown key 'gain'"),
    ('blocks = []', r"\[controller.transfer\] blocks: must be a non-empty list"),
    ('blocks = [{type = "gain", k = 1.0}]\naxes = {"Q-x" = [{type = "gain", k = 2.0}]}',
     r"\[controller.transfer.axes\]: key 'Q-x' is not an axis"),
])
def test_bad_transfer_tables_are_one_line_errors(tmp, chain, match):
    with pytest.raises(SceneError, match=match) as e:
        load_scene(transfer_scene(tmp, chain, name="bad.toml"))
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("override,match", [
    ({"B": "[[1.0]]"}, r"\[controller.statespace\]: key 'B' is 1 x 1, expected 18 x 6"),
    ({"dt": "1e-3"}, r"key 'dt' = 0.001 s must equal the loop's period"),
    ({"inputs": '["A-x", "A-x"]'}, r"key 'inputs' must name each axis of the loop once"),
    ({"A": '[[1.0, 2.0]]'}, r"key 'A' is 1 x 2, must be square"),
])
def test_bad_statespace_tables_are_one_line_errors(tmp, override, match):
    with pytest.raises(SceneError, match=match) as e:
        load_scene(mimo_scene(tmp, name="bad_ss.toml", **override))
    assert "\n" not in str(e.value)


def test_kind_and_table_must_agree(tmp):
    with pytest.raises(SceneError, match=r"\[controller.transfer\]: table is required"):
        load_scene(scene_with(tmp, '[controller]\nkind = "transfer"\n', "k1.toml"))
    with pytest.raises(SceneError, match=r"\[controller.transfer\]: given, but \[controller\] kind = 'pid'"):
        load_scene(scene_with(tmp, f'[controller]\nkp = 1.0\n[controller.transfer]\nblocks = [{PID}]\n', "k2.toml"))


def test_an_unstable_controller_is_allowed_and_said(tmp):
    path = transfer_scene(tmp, 'blocks = [{type = "tf", num = [1.0], den = [1e-3, -1.0]}]', name="unst.toml")
    m = compile_system(path, rung="modal")                    # the analyses take it
    with pytest.warns(LTIWarning, match=r"the controller itself is unstable"):
        r = controller_runner(m)
    assert r.law.note and math.isfinite(r.step(np.zeros(m.n_axes))[0])


def test_slew_limited_builtin_pid_has_the_fused_kernels_sampled_loop(builtin):
    """A slew limit runs the built-in PID as a law (PIDLaw); its linear map (limits and slew off)
    is the fused kernel's: the same spectral radius, in loop/sampled.py and in the loop map."""
    sc = load_scene(SCENE)
    amp = dataclasses.replace(sc.controller.amplifier, slew_rate=1e4)
    m = compile_system(sc.with_controller(amplifier=amp), rung="modal")
    r, ref = controller_runner(m), controller_runner(builtin)
    assert type(r).__name__ == "LawRunner"
    def rho(c, mm):
        return np.max(np.abs(np.linalg.eigvals(sd.SampledLoop(sd.plant_of(mm, SPEED), sd.controller_of(c)).mode(0.0))))
    assert rho(r, m) == pytest.approx(rho(ref, builtin), rel=1e-12)
    plan = make_plan(m, "zoh", r.period, speed=SPEED, nonlinear=False, ratio=1)
    L, _ = loop_matrix(m, plan, r, 1)
    assert np.max(np.abs(np.linalg.eigvals(L))) == pytest.approx(rho(ref, builtin), rel=1e-10)


def test_static_statespace_law_closed_loop_equals_python_controls_interconnection(tmp):
    """``A = []``: a law without states (here a P law with a cross term) runs and is analysed."""
    D = -KP * np.eye(6)
    D[1, 0] = 0.5
    m = compile_system(scene_with(tmp, f'[controller]\nkind = "statespace"\n[controller.statespace]\n'
                                       f'A = []\nB = []\nC = []\nD = {_fmt(D)}\n', "static.toml"), rung="modal")
    r = controller_runner(m)
    assert r.law.Ad.shape == (0, 0) and np.array_equal(r.law.Dd, D)
    ref = _closed_loop_eigs_by_control(m, control.ss([], [], [], D))
    ours = np.linalg.eigvals(closed_loop.build(m, SPEED, sparse=False).dense_standard())
    assert _match(ours, ref).max() < 1e-8
