"""The timing study's predictions confirmed in the time domain, and its grid on Dask."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bridge.cli import main
from loop import sampled as sd
from loop import timing_study as ts
from loop.scene import load_scene
from loop.system import compile_system, controller_runner
from plant.step import PlantRunner

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
    plant = PlantRunner(model, scheme, T / ratio, speed=0.0, latency=tau)
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
    from plant import integrator as ig
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
