"""The timing study's predictions confirmed in the time domain, and its grid on Dask."""
from __future__ import annotations

import json

import numpy as np
import pytest

from ambhil.bridge.cli.main import main
from ambhil.loop import sampled as sd
from ambhil.loop import timing_study as ts
from ambhil.loop.scene import load_scene
from ambhil.loop.system import compile_system, controller_runner
from ambhil.plant.run_options import RunOptions
from ambhil.plant.step import PlantRunner

SCENE = "scenes/paper_3amb.toml"


@pytest.fixture(scope="module")
def full():
    return compile_system(SCENE, rung="full")


def critical(F, T, hz=1250.0):
    """The eigenpair of the loop map nearest the lightly damped ~1.25 kHz mode that crosses the
    boundary (shift-invert Arnoldi: one LU of the map instead of a full eigen-decomposition)."""
    from scipy.sparse.linalg import eigs
    mu, V = eigs(F, k=1, sigma=np.exp(2j * np.pi * hz * T))
    return mu[0], V[:, 0]


def measured_growth(model, lp, tau, scheme, ratio, v, periods=1200):
    """Start the plant and controller runners on Re(v) (the mode alone) and read the growth
    rate of the sensed displacement off two windows of its RMS."""
    L, T = lp.layout, lp.T
    plant = PlantRunner(model, RunOptions(integrator=scheme, h=T / ratio, speed=0.0, latency=tau))
    ctrl = controller_runner(model)
    plant.reset()
    ctrl.reset()
    z = np.real(v) / np.max(np.abs(np.real(v)[L.x]))  * 1e-6
    n = model.n
    plant.s[:2 * n] = z[L.x]
    ctrl.state[:L.nc] = z[L.xc]
    d, m = plant.late
    if plant.ring is not None:
        D = plant.ring.shape[0]
        for j in range(1, d + 1):                       # u_{-j}
            plant.ring[(-j) % D] = z[L.buf(j - 1)]
        if m:
            plant.ring[(-d - 1) % D] = z[L.a]             # the current on the coil at t = 0
    y = plant.y.copy()
    from ambhil.plant import integrator as ig
    ig.sense(plant.plan, plant.s, y)
    ys = []
    for _ in range(periods):
        ys.append(y[np.argmax(np.abs(lp.plant.C @ z[L.x]))])
        y = plant.advance(ctrl.step(y))
    ys = np.array(ys)
    w = 200
    r1, r2 = np.sqrt(np.mean(ys[100:100 + w] ** 2)), np.sqrt(np.mean(ys[-w:] ** 2))
    return np.log(r2 / r1) / ((periods - w - 100) * T)


def test_time_domain_growth_matches_the_prediction_on_both_sides_of_the_boundary(full):
    """Paper 3-AMB scene, full rung, 10 kHz: the boundary is near 52 us of latency.  For three
    latencies below it and three above (fractional ones included: plant steps of T/5), the
    growth rate of the critical mode measured in the time domain (the plant and controller
    runners of the HIL processes) matches the sampled-loop prediction within 5 % and the
    stable/unstable classification agrees; with the exact (zoh) plant and with trapezoidal."""
    T = 1.0 / full.scene.controller.sample_rate
    lp = sd.SampledLoop(sd.plant_of(full, 0.0), sd.controller_of(controller_runner(full)), max_latency=1.2e-4)
    bound = 5.2e-5  # ts.TimingModel(full, 0.0).largest_latency(1e4, 2e-4) gives 52.3 us
    cases = [(0.0, "zoh"), (2e-5, "zoh"), (4e-5, "zoh"), (6e-5, "zoh"), (8e-5, "zoh"), (1e-4, "zoh"),
             (4e-5, "trapezoidal"), (8e-5, "trapezoidal")]
    for tau, scheme in cases:
        mu, v = critical(lp.mode(tau), T)
        predicted = np.log(abs(mu)) / T
        g = measured_growth(full, lp, tau, scheme, 5, v)
        assert (g > 0) == (predicted > 0) == (tau > bound), (tau, scheme, g, predicted)
        assert g == pytest.approx(predicted, rel=0.05), (tau, scheme, g, predicted)


def test_grid_results_are_identical_in_process_and_on_a_local_cluster():
    scene = load_scene(SCENE)
    spec = ts.StudySpec(rates=np.array([8000.0, 20000.0]), delays=np.array([0.0, 0.5, 1.5]), rung="modal",
                        latency=ts.parse_latency("uniform:10us", 0.01))
    results = []
    for kw in ({}, {"workers": 2}):
        c = ts.client_for(**kw)
        try:
            results.append(ts.run(scene, spec, c))
        finally:
            c.close()
    a, b = results
    assert a.points == b.points
    assert [g["largest_latency_s"] for g in a.grid] == [g["largest_latency_s"] for g in b.grid]
    assert a.jitter == b.jitter and a.zone_rates == b.zone_rates


def test_study_timing_command_prints_one_json_line(capsys, tmp_path):
    code = main(["study", "timing", SCENE, "--rung", "modal", "--rates", "8k,20k", "--delays", "0:1T:3",
                 "--no-sensitivity", "--out", str(tmp_path), "--json"])
    out = capsys.readouterr().out.strip().splitlines()
    assert code == 0 and len(out) == 1
    res = json.loads(out[0])
    lat = {b["rate_hz"]: b["largest_latency_s"] for b in res["boundaries"]}
    assert lat[20000.0] > lat[8000.0]           # a faster controller tolerates more latency here
    assert (tmp_path / "timing_map.png").exists() and (tmp_path / "timing_points.csv").exists()


# --------------------------------------------------------------------------- honest figures and plots
def _strict_json(text):
    def bad(c):
        raise ValueError(f"non-finite number {c} in a study result")
    return json.loads(text, parse_constant=bad)


def test_no_non_finite_figure_anywhere_in_a_study_result(capsys, tmp_path):
    """A rate whose loop is unstable (4 kHz: no sensitivity peak) and jitter the loop does not
    survive in mean square (uniform 0-150 us at 10 kHz: no stationary variance): timing.json is
    strict JSON (no Infinity/NaN), every figure left out is None with its reason in
    ``not_computed``, and the table says "not computed" instead of printing a value or "-"."""
    code = main(["study", "timing", SCENE, "--rung", "modal", "--rates", "4k,10k", "--delays", "0:1T:3",
                 "--jitter", "uniform:150us", "--out", str(tmp_path)])
    table = capsys.readouterr().out
    assert code == 0
    res = _strict_json((tmp_path / "timing.json").read_text())
    from ambhil.bridge.cli.study_timing import _reason
    unstable = [p for p in res["points"] if not p["stable"]]
    assert unstable and all(p["sensitivity_peak"] is None and _reason(p, "sensitivity_peak")
                            == "the sampled loop is unstable" for p in unstable)
    bad = [j for j in res["jitter"] if not j["ms_stable"]]
    assert bad and all(j["y_std_m"] is None and "not mean-square stable" in _reason(j, "y_std_m") for j in bad)
    for p in res["points"] + res["jitter"]:
        for k, v in p.items():
            if v is None and k not in ("zone", "sensitivity_hz", "unbalance_max_m"):
                assert k in p["not_computed"], (k, p)
    assert "inf" not in table.lower().replace("information", "")
    assert table.count("not computed (no stationary variance)") == len(bad)
    assert "speed (rad/s)" in table


def test_force_noise_on_the_full_rung_gives_a_finite_variance(full):
    """Force noise at every AMB on the full rung at 10 kHz (fast modes to 4.6e6 1/s): a finite
    displacement std beside the mean-square verdict, equal to the sum of the series
    ``P = sum_k F^k W F^kT`` (squared Smith iteration: positive terms only, no solver; the
    loop's states differ by 1e10 in scale, and an unscaled Lyapunov solve is 1 % off here)."""
    m = ts.TimingModel(full, 327.19)
    noise = ts.Noise("force", 1e-2)
    j = m.jitter_point(1e4, 0.0, ts.Latency(), noise)
    assert j["ms_stable"] and j["not_computed"] == ""
    assert np.isfinite(j["y_std_m"]) and np.isfinite(j["u_std_A"]) and j["y_std_m"] > 0
    lp = m.loop(1e4, 0.0)
    F, E = lp.mode(0.0, with_input=True)
    P = noise.covariance(lp, E, noise.force_covariance(lp))
    for _ in range(40):  # rho(F)^(2^40) = e^(-0.257 * 1e-4 * 2^40): converged
        P, F = P + F @ P @ F.T, F @ F
    L = lp.layout
    y = np.sqrt(np.max(np.diag(lp.plant.C @ P[L.x, L.x] @ lp.plant.C.T)))
    assert j["y_std_m"] == pytest.approx(y, rel=1e-6)


@pytest.fixture(scope="module")
def uneven():
    """The uneven log grid 5k:40k:6 (no grid rate at the scene's 10 kHz) with jitter that the
    loop does not survive in mean square."""
    from ambhil.bridge.cli.study_timing import parse_rates
    scene = load_scene(SCENE)
    spec = ts.StudySpec(rates=parse_rates("5k:40k:6"), delays=np.linspace(0, 2, 5), rung="modal",
                        sensitivity=False, latency=ts.parse_latency("uniform:150us", 0.05))
    c = ts.client_for()
    try:
        return ts.run(scene, spec, c)
    finally:
        c.close()


def _figure_of(monkeypatch, fn, *args):
    from ambhil.loop import timing_plots as tp
    figs = []
    monkeypatch.setattr(tp.plt, "close", figs.append)
    fn(*args)
    return figs[-1]


def test_rate_latency_map_on_an_uneven_grid_raises_no_warning(uneven, tmp_path):
    import warnings
    from ambhil.loop import timing_plots as tp
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tp.rate_latency_map(uneven, tmp_path / "map.png")


def test_margin_plot_is_drawn_at_the_scenes_own_rate(uneven, tmp_path, monkeypatch):
    from ambhil.loop import timing_plots as tp
    fs0 = load_scene(SCENE).controller.sample_rate
    assert fs0 not in [g["rate_hz"] for g in uneven.grid]
    fig = _figure_of(monkeypatch, tp.margin_against_latency, uneven, tmp_path / "m.png")
    assert f"{fs0:g} Hz" in fig._suptitle.get_text()
    m = ts.TimingModel(compile_system(SCENE, rung="modal"), uneven.spec.speeds[0])
    line = fig.axes[1].lines[0]
    taus = np.asarray(line.get_xdata()) * 1e-6
    assert all(np.min(np.abs(taus - t)) < 1e-15 for t in np.linspace(0, 2, 5) / fs0)  # the study's latencies
    assert taus.max() >= 1.25 * uneven.scene_point["largest_latency_s"] - 1e-15     # and past the boundary
    np.testing.assert_allclose(line.get_ydata(), [m.radius(fs0, t) for t in taus], rtol=1e-12)
    bound = [ln for ln in fig.axes[1].lines if ln.get_label().startswith("boundary")][0]
    assert bound.get_xdata()[0] == pytest.approx(uneven.scene_point["largest_latency_s"] * 1e6)


def test_jitter_plot_colours_the_unstable_rows_and_keeps_its_title(uneven, tmp_path, monkeypatch):
    import matplotlib.colors as mc
    from ambhil.loop import timing_plots as tp
    fig = _figure_of(monkeypatch, tp.variance_against_jitter, uneven, tmp_path / "j.png")
    ax = fig.axes[0]
    bars = [p for p in ax.patches if p.get_height() > 0]
    assert len(bars) == len(uneven.jitter)
    red = mc.to_rgb("C3")
    for j, b in zip(uneven.jitter, sorted(bars, key=lambda b: b.get_y())):
        assert np.isfinite(b.get_width()) and b.get_width() > 0
        assert (mc.to_rgb(b.get_facecolor()) == red) == (not j["ms_stable"])
    assert any(not j["ms_stable"] for j in uneven.jitter)
    # a longer scene name and a measured distribution's labels: the title stays on the figure
    from dataclasses import replace
    long = replace(uneven, scene="paper_3amb_misaligned",
                   jitter=[dict(j, jitter="empirical (400000 samples)") for j in uneven.jitter])
    for res in (uneven, long):
        fig = _figure_of(monkeypatch, tp.variance_against_jitter, res, tmp_path / "j.png")
        fig.canvas.draw()
        t = fig.axes[0].title.get_window_extent()
        assert t.x0 >= 0 and t.x1 <= fig.bbox.width and t.y1 <= fig.bbox.height, (t, fig.bbox)


def test_worst_case_bound_of_one_stable_mode_is_below_one(full):
    """One timing mode, stable: with ``P = F P F^T + I`` the norm of F in the ellipsoid P is below 1
    (Lyapunov: ``L^-1 F P F^T L^-T = I - L^-1 L^-T``) and not below the spectral radius.  On the
    full rung (states spanning ten decades) the bound is only meaningful in balanced coordinates."""
    from ambhil.loop import jitter as jt
    lp = ts.TimingModel(full, 327.19).loop(1e4, 0.0)
    F = lp.mode(0.0)
    lower, upper = jt.worst_case_bound(jt.JumpSystem((F,), np.array([1.0]), (np.zeros_like(F),)))
    assert lower == pytest.approx(np.max(np.abs(np.linalg.eigvals(F))), rel=1e-12)
    assert lower <= upper < 1.0
