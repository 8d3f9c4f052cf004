"""The ANCF rung (plant/ancf_*.py, plant/dae_integrator.py): element derivatives, large-rotation
statics, small-motion frequencies against the full FE rung and analytic values, conservation,
and the closed loop against the full FE rung.  See docs/ancf.md."""
import numpy as np
import pytest

from plant import ancf_beam as ab
from plant import ancf_model as am


def _random_element(rng):
    q = np.zeros(16)
    for n in range(2):
        q[8 * n:8 * n + 3] = rng.standard_normal(3) * 0.1 + [0, 0, 0.5 * n]
        q[8 * n + 3] = 0.01 * rng.standard_normal()
        th = np.array([1, 0, 0, 0]) + 0.3 * rng.standard_normal(4)
        q[8 * n + 4:8 * n + 8] = th / np.linalg.norm(th)
    prm = np.zeros(ab.P_LEN)
    prm[ab.P_L], prm[ab.P_EA], prm[ab.P_EI], prm[ab.P_GJ], prm[ab.P_RHOA] = 0.5, 3.0, 2.0, 1.5, 1.2
    return q, prm


def test_element_force_is_the_energy_gradient():
    rng = np.random.default_rng(0)
    for _ in range(3):
        q, prm = _random_element(rng)
        z = np.zeros(16)
        f = np.zeros(16)
        ab.element_force(q, z, z, prm, 0.0, f)
        g = np.zeros(16)
        for k in range(16):
            e = np.zeros(16); e[k] = 1e-6
            g[k] = (ab.element_energy(q + e, prm) - ab.element_energy(q - e, prm)) / 2e-6
        assert np.max(np.abs(g - f)) < 1e-7 * np.max(np.abs(f))


def test_element_jacobian_against_finite_differences():
    """Complex-step Jacobian of the full element force (inertia, quadratic velocity terms,
    elastic, Kelvin-Voigt and mass-proportional damping) vs central differences."""
    rng = np.random.default_rng(1)
    q, prm = _random_element(rng)
    prm[ab.P_BETA], prm[ab.P_ALPHA] = 0.3, 0.2
    v, a = rng.standard_normal(16), rng.standard_normal(16)
    cv, ca = 2.0, 3.0
    J = np.zeros((16, 16))
    ab.element_jacobian(q, v, a, prm, 1.0, cv, ca, J)
    Jf = np.zeros((16, 16))
    for k in range(16):
        e = np.zeros(16); e[k] = 1e-6
        fp, fm = np.zeros(16), np.zeros(16)
        ab.element_force(q + e, v + cv * e, a + ca * e, prm, 1.0, fp)
        ab.element_force(q - e, v - cv * e, a - ca * e, prm, 1.0, fm)
        Jf[:, k] = (fp - fm) / 2e-6
    assert np.max(np.abs(J - Jf)) < 1e-8 * np.max(np.abs(J))


def test_quaternion_kinematics():
    """A(theta) orthonormal; body rate 2 G theta' and spatial rate 2 E theta' match A'."""
    rng = np.random.default_rng(2)
    th = rng.standard_normal(4); th /= np.linalg.norm(th)
    thd = rng.standard_normal(4); thd -= th * (th @ thd)
    A = ab.rotation_matrix(th)
    assert np.allclose(A.T @ A, np.eye(3), atol=1e-14) and np.isclose(np.linalg.det(A), 1.0)
    h = 1e-7
    Ad = (ab.rotation_matrix(th + h * thd) - ab.rotation_matrix(th - h * thd)) / (2 * h)
    Wb = A.T @ Ad
    wb = 2 * ab.G_matrix(th) @ thd
    assert np.allclose([Wb[2, 1], Wb[0, 2], Wb[1, 0]], wb, atol=1e-7)
    Ws = Ad @ A.T
    assert np.allclose([Ws[2, 1], Ws[0, 2], Ws[1, 0]], 2 * ab.E_matrix(th) @ thd, atol=1e-7)
    assert np.allclose(np.array(ab.axis_e3(*th)), A[:, 2])


def test_end_moment_closes_the_cantilever_into_a_circle():
    """M = 2 pi EI / L at the tip of a clamped straight beam bends it into a full circle: the
    tip returns to the root (within 1e-3 L) with its section turned by 2 pi."""
    L, EI, ne = 1.0, 2.0, 16
    nn = ne + 1
    M = np.zeros((nn, 3)); M[-1, 0] = 2 * np.pi * EI / L
    S, z = am.build([am.Beam(L, ne, EA=1e4, EI=EI, GJ=1.5, rhoA=1.0, rhoI=1e-3)],
                    fixed=[(0, 0), (1, 0), (2, 0), (5, 0), (6, 0), (7, 0)], node_moment=M)
    q, _ = am.solve_static(S, am.straight_state(S, z), steps=8)
    tip = q[8 * ne:8 * ne + 3]
    assert np.linalg.norm(tip) < 1e-3 * L
    th = q[8 * ne + 4:8 * ne + 8]
    assert abs(abs(th[0]) - 1.0) < 1e-6  # a rotation by 2 pi: theta = -1
    # half the moment: a half circle; a moment about +x turns +z towards -y: tip at (0, -2R, 0)
    M[-1, 0] = np.pi * EI / L
    S2 = S._replace(nM=M)
    q2, _ = am.solve_static(S2, am.straight_state(S, z), steps=4)
    assert np.linalg.norm(q2[8 * ne:8 * ne + 3] - [0, -2 * L / np.pi, 0]) < 1e-3 * L
