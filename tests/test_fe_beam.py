"""FE shaft against analytic beam theory."""
import numpy as np
import pytest
import scipy.linalg as sla

from ambhil.plant import beam_element as be
from ambhil.plant.rotor import assemble
from helpers import scene

E, RHO, L, D = 2.11e11, 7810.0, 2.0, 0.01  # slender: L/D = 200, rotary inertia negligible


def plane(rot):
    """x-plane DOFs (x, phi_x) of every node."""
    return np.sort(np.concatenate([np.arange(0, rot.ndof, rot.dpn), np.arange(2, rot.ndof, rot.dpn)]))


def uniform(elements=60, beam="euler-bernoulli", D=D, L=L, G=8.12e10):
    return assemble(scene(shaft=[{"length": L, "outer_diameter": D, "elements": elements,
                                  "youngs_modulus": E, "density": RHO, "shear_modulus": G}],
                          model={"rung": "full", "beam": beam},
                          amb=[{"name": "A", "node": 1, "gap": 1e-3, "bias_current": 1, "turns": 10, "pole_area": 1e-4},
                               {"name": "B", "node": elements + 1, "gap": 1e-3, "bias_current": 1, "turns": 10,
                                "pole_area": 1e-4}]).plant)


def freqs(rot, drop=()):
    idx = np.setdiff1d(plane(rot), drop)
    w2 = sla.eigvalsh(rot.K[idx][:, idx].toarray(), rot.M[idx][:, idx].toarray())
    return np.sqrt(np.clip(w2, 0, None)) / (2 * np.pi)


def test_free_free_euler_bernoulli_within_0p1_percent():
    A, I = be.section_properties(D, 0.0)
    c = np.sqrt(E * I / (RHO * A)) / (2 * np.pi * L**2)
    beta_l = np.array([4.730040745, 7.853204624, 10.99560784, 14.13716549])
    f = freqs(uniform(60))
    assert np.all(f[:2] < 1e-3 * f[2])  # two rigid-body modes
    np.testing.assert_allclose(f[2:6], beta_l**2 * c, rtol=1e-3)


def test_pinned_pinned_euler_bernoulli_within_0p1_percent():
    rot = uniform(60)
    A, I = be.section_properties(D, 0.0)
    c = np.sqrt(E * I / (RHO * A)) / (2 * np.pi * L**2)
    f = freqs(rot, drop=[0, rot.ndof - rot.dpn])
    n = np.arange(1, 6)
    np.testing.assert_allclose(f[:5], (n * np.pi) ** 2 * c, rtol=1e-3)


def test_pinned_pinned_timoshenko_against_frequency_equation():
    Dt, Lt, G = 0.2, 1.0, 8.12e10  # stubby shaft: shear and rotary inertia matter
    rot = uniform(60, "timoshenko", D=Dt, L=Lt, G=G)
    f = freqs(rot, drop=[0, rot.ndof - rot.dpn])
    A, I = be.section_properties(Dt, 0.0)
    kap = be.cowper_shear_coefficient(Dt, 0.0, E / (2 * G) - 1)
    ref = []
    for n in range(1, 4):
        k = n * np.pi / Lt
        # (kGA k^2 - rho A w^2)(EI k^2 + kGA - rho I w^2) - (kGA k)^2 = 0, lower root
        a = RHO * A * RHO * I
        b = -(kap * G * A * k**2 * RHO * I + RHO * A * (E * I * k**2 + kap * G * A))
        cc = kap * G * A * k**2 * (E * I * k**2 + kap * G * A) - (kap * G * A * k) ** 2
        w2 = (-b - np.sqrt(b * b - 4 * a * cc)) / (2 * a)
        ref.append(np.sqrt(w2) / (2 * np.pi))
    np.testing.assert_allclose(f[:3], ref, rtol=2e-3)
    # and Euler-Bernoulli overestimates the stubby shaft noticeably
    f_eb = freqs(uniform(60, D=Dt, L=Lt), drop=[0, rot.ndof - rot.dpn])
    assert f_eb[2] > 1.05 * f[2]


def test_rigid_body_properties_exact():
    rot = uniform(20)
    A, I = be.section_properties(D, 0.0)
    m = RHO * A * L
    assert rot.mass == pytest.approx(m, rel=1e-12)
    assert rot.cog == pytest.approx(L / 2, rel=1e-12)
    assert rot.transverse_inertia == pytest.approx(m * L**2 / 12 + RHO * I * L, rel=1e-10)
    assert rot.polar_inertia == pytest.approx(2 * RHO * I * L, rel=1e-10)


def test_gyroscopic_matrix_skew_and_energy_neutral():
    rot = uniform(10)
    G = rot.G.toarray()
    np.testing.assert_allclose(G, -G.T, atol=1e-15)
    assert np.abs(G).max() > 0
