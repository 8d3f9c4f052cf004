"""AMB force law: linearisation against finite differences and the paper's eq. 8-9."""
import math

import numpy as np
import pytest

from ambhil.plant import magnetic_bearing as mb

K, S0, I0 = 1.2e-5, 1.5e-4, 2.0


@pytest.mark.parametrize("offset", [0.0, 2e-5, -5e-5, 1e-4])
def test_linearisation_matches_finite_differences(offset):
    op = mb.operating_point(K, S0, I0, offset)
    assert mb.force(K, S0, I0, op.x, op.i) == pytest.approx(0.0, abs=1e-9)  # force-free operating point
    hx, hi = 1e-10, 1e-7
    fdx = (mb.force(K, S0, I0, op.x + hx, op.i) - mb.force(K, S0, I0, op.x - hx, op.i)) / (2 * hx)
    fdi = (mb.force(K, S0, I0, op.x, op.i + hi) - mb.force(K, S0, I0, op.x, op.i - hi)) / (2 * hi)
    assert op.kx == pytest.approx(fdx, rel=1e-6)
    assert op.ki == pytest.approx(fdi, rel=1e-6)


@pytest.mark.parametrize("offset", [0.0, 1e-4, -7e-5])
def test_operating_point_reproduces_paper_eq_8_9(offset):
    op = mb.operating_point(K, S0, I0, offset)
    kx, ki = mb.paper_coefficients(K, S0, I0, offset)
    assert op.kx == pytest.approx(kx, rel=1e-12)
    assert op.ki == pytest.approx(ki, rel=1e-12)


def test_centred_values_and_misalignment_factor():
    op0 = mb.operating_point(K, S0, I0, 0.0)
    assert op0.kx == pytest.approx(K * I0**2 / S0**3)
    assert op0.ki == pytest.approx(K * I0 / S0**2)
    e = 1e-4  # Table 1 of the paper: e_bar = 2/3 -> both coefficients x 1/(1 - 4/9) = 1.8
    op = mb.operating_point(K, S0, I0, e)
    assert op.kx / op0.kx == pytest.approx(1.8)
    assert op.i == pytest.approx(I0 * e / S0)


def test_general_derivatives_off_the_operating_point():
    x, i = 3e-5, 0.4
    kx, ki = mb.force_derivatives(K, S0, I0, x, i)
    h = 1e-10
    assert kx == pytest.approx((mb.force(K, S0, I0, x + h, i) - mb.force(K, S0, I0, x - h, i)) / (2 * h), rel=1e-6)
    assert ki == pytest.approx((mb.force(K, S0, I0, x, i + 1e-7) - mb.force(K, S0, I0, x, i - 1e-7)) / 2e-7, rel=1e-6)


def test_force_constant_includes_pole_angle():
    from helpers import scene
    a = scene().plant.ambs[0]
    assert a.force_constant == pytest.approx(4e-7 * math.pi * 100**2 * 5e-4 * math.cos(math.radians(22.5)))
