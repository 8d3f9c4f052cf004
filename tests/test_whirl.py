"""Forward/backward whirl split of a symmetric disc rotor against its analytic solution.

Rigid rotor (mass m, transverse inertia I_t, polar inertia I_p about the COG) on two identical
bearings at +-a from the COG, each a pure stiffness k (P-only controller, no lags, no damping):
    translation:   w^2 = 2k/m
    conical:       I_t w^2 -+ I_p Omega w - 2 k a^2 = 0   (upper sign: forward whirl)
"""
import numpy as np
import pytest

from ambhil.loop.analysis import modal
from ambhil.loop.system import compile_system
from helpers import scene

L = 1.0


def disc_rotor(rung):
    return compile_system(scene(
        shaft=[{"length": L, "outer_diameter": 0.05, "elements": 20, "youngs_modulus": 2.11e15}],
        disc=[{"name": "d", "node": 11, "mass": 30.0, "polar_inertia": 1.2, "diametral_inertia": 0.4}],
        model={"rung": rung}), rung=rung)


@pytest.mark.parametrize("rung", ["rigid", "full"])
@pytest.mark.parametrize("speed", [0.0, 500.0, 2000.0])
def test_whirl_split_matches_analytic(rung, speed):
    m = disc_rotor(rung)
    r = m.rotor
    k = m.ki[0] * m.H.D[0, 0] - m.kx[0]  # net bearing stiffness of a P-only loop
    assert k > 0
    a = r.node_z[18] - r.cog
    assert r.node_z[2] - r.cog == pytest.approx(-a)
    It, Ip, mass = r.transverse_inertia, r.polar_inertia, r.mass
    wt = np.sqrt(2 * k / mass)
    kc = 2 * k * a * a
    wf = (Ip * speed + np.sqrt((Ip * speed) ** 2 + 4 * It * kc)) / (2 * It)
    wb = (-Ip * speed + np.sqrt((Ip * speed) ** 2 + 4 * It * kc)) / (2 * It)
    modes = modal.Solver(m).all(speed, 1.5 * max(wf, wt))
    rigid = [md for md in modes if md.rigid_fraction > 0.99]
    freqs = sorted(md.eigenvalue.imag for md in rigid)
    rtol = 1e-9 if rung == "rigid" else 2e-3  # the full rung's shaft is stiff but not rigid
    np.testing.assert_allclose(freqs, sorted([wt, wt, wf, wb]), rtol=rtol)
    for md in rigid:
        assert abs(md.eigenvalue.real) < 1e-6 * abs(md.eigenvalue)  # undamped
    if speed > 0:
        fwd = [md for md in rigid if md.whirl == "forward"]
        bwd = [md for md in rigid if md.whirl == "backward"]
        assert max(md.eigenvalue.imag for md in fwd) == pytest.approx(wf, rel=rtol)
        assert min(md.eigenvalue.imag for md in bwd) == pytest.approx(wb, rel=rtol)


def test_forward_critical_of_conical_mode():
    """Synchronous forward whirl: (I_t - I_p) w^2 = 2 k a^2."""
    m = disc_rotor("rigid")
    r = m.rotor
    k = m.ki[0] * m.H.D[0, 0] - m.kx[0]
    a = r.node_z[18] - r.cog
    w_crit = np.sqrt(2 * k * a * a / (r.transverse_inertia - r.polar_inertia))
    cs = modal.critical_speeds(m, count=2, speed_max=5 * w_crit)
    assert [c.kind for c in cs] == ["rigid", "rigid"]
    assert any(c.speed == pytest.approx(w_crit, rel=1e-7) for c in cs)
    assert any(c.speed == pytest.approx(np.sqrt(2 * k / r.mass), rel=1e-7) for c in cs)


def test_axial_amb_mode_is_labelled_axial_and_not_a_critical():
    """Axial AMB, P-only loop: the rigid axial mode is sqrt(k_net / m), labelled axial, and never
    reported as a (lateral) critical speed."""
    sc = scene(axial_amb={"node": 1, "gap": 5e-4, "bias_current": 1.0, "turns": 60, "pole_area": 5e-4},
               disc=[{"name": "d", "node": 11, "mass": 30.0, "polar_inertia": 1.2, "diametral_inertia": 0.4}])
    for rung in ("rigid", "full"):
        m = compile_system(sc, rung=rung)
        assert m.axes[-1][1] == "z" and m.rotor.dpn == 5
        k_net = m.ki[-1] * m.H.D[0, 0] - m.kx[-1]
        w_ax = np.sqrt(k_net / m.rotor.mass)
        modes = modal.Solver(m).all(100.0, 3 * w_ax)
        ax = [md for md in modes if md.whirl == "axial"]
        assert len(ax) >= 1
        assert min(md.eigenvalue.imag for md in ax) == pytest.approx(w_ax, rel=1e-6 if rung == "rigid" else 1e-3)
        cs = modal.critical_speeds(m, count=6, speed_max=3 * w_ax)
        assert all(abs(c.speed - w_ax) > 1e-3 * w_ax for c in cs)
