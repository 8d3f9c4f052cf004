"""The full rung's critical speeds do not depend on the controller's sample rate: neither their
values (the closed loop of the frequency-domain analyses is continuous) nor the size of the
Craig-Bampton model that seeds them (its cutoff follows the analysed range, not the rate)."""
import numpy as np
import scipy.sparse.linalg
import pytest

from ambhil.loop.analysis import modal
from ambhil.loop.scene import load_scene
from ambhil.loop.system import compile_system
from ambhil.plant import reduction

SCENE = "scenes/rotor62_3amb.toml"  # 62-node Timoshenko rotor on three AMBs, controller 10 kHz


@pytest.fixture(scope="module")
def rates():
    sc = load_scene(SCENE)
    return {r: compile_system(sc.with_controller(sample_rate=r)) for r in (10_000.0, 100_000.0)}


def test_seed_model_follows_the_analysed_range_not_the_rate(rates, monkeypatch):
    m10, m100 = rates[10_000.0], rates[100_000.0]
    smax = 1.1 * m100.scene.analysis.frequency_max
    s10, s100 = modal.seed_system(m10, smax), modal.seed_system(m100, smax)
    assert s10.n == s100.n
    np.testing.assert_array_equal(s10.T, s100.T)
    # far smaller than the modal rung of the 100 kHz scene (cutoff at the sample rate)
    assert compile_system(m100.scene, rung="modal", rotor=m100.rotor).n > 5 * s100.n
    with pytest.raises(ValueError, match="analysis_cutoff"):
        reduction.analysis_cutoff(0.0)
    assert modal.Solver(s100).use_dense  # a small dense eigenproblem, not ARPACK
    # the 100 kHz rotor's criticals need no ARPACK at all (before: a 226-coordinate seed model,
    # a 476-state closed loop, shift-invert Arnoldi at every secant step)
    def no_arpack(*a, **k):
        raise AssertionError("critical_speeds called ARPACK")
    monkeypatch.setattr(scipy.sparse.linalg, "eigs", no_arpack)   # the module object every caller uses
    assert len(modal.critical_speeds(m100)) == 4


def test_criticals_equal_at_both_rates_and_against_arnoldi(rates):
    c10 = [c.speed for c in modal.critical_speeds(rates[10_000.0])]
    c100 = modal.critical_speeds(rates[100_000.0])
    assert len(c10) == len(c100) == 4
    np.testing.assert_allclose([c.speed for c in c100], c10, rtol=1e-6)
    # second method: secant on the full state space, shift-invert Arnoldi at every speed (no
    # Craig-Bampton seeds, no refinement on Z(s))
    m = rates[100_000.0]
    arnoldi = modal.critical_speeds(m, solver=modal.Solver(m))
    np.testing.assert_allclose([c.speed for c in c100], [c.speed for c in arnoldi], rtol=1e-3)
    for c in c100:
        assert c.mode.eigenvalue.imag == pytest.approx(c.speed, rel=1e-8)
        assert c.mode.whirl in ("forward", "mixed")
