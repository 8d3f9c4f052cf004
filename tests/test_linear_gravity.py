"""``[model] gravity`` on the linear rungs (rigid, modal, full): the AMBs' shares of the weight
(plant/linear_statics.gravity_loads) against statics computed here independently, and the loaded
operating point compile_model builds from them (Model.load, x_op, i_op, k_x, k_i)."""
import copy
import dataclasses as dc

import numpy as np
import pytest
from ambhil.loop.scene import load_scene, parse_scene
from ambhil.plant import magnetic_bearing as mb
from ambhil.plant.linear_statics import gravity_loads
from ambhil.plant.model import compile_model, operating_currents
from ambhil.plant.params import ParameterError
from ambhil.plant.rotor import assemble
from helpers import BASE

G = 9.81
D, RHO, L = 0.05, 7810.0, 1.0
W_SHAFT = G * RHO * np.pi / 4 * D**2 * L  # the uniform 1 m x 50 mm shaft of helpers.BASE, N


def spec(nodes=(3, 19), discs=(), g=G, rung="full", **amb):
    """BASE (20 elements, nodes 1..21 at 0.05 m) with AMBs at ``nodes`` (1-based), ``discs``
    as (node, mass) and gravity ``g``; ``amb``: keys of every AMB (a stronger bearing)."""
    d = copy.deepcopy(BASE)
    d["model"] = {"rung": rung, "gravity": g, "modal_cutoff": 5000.0}
    d["amb"] = [dict(BASE["amb"][0], name=chr(65 + k), node=n, **amb) for k, n in enumerate(nodes)]
    d["disc"] = [{"node": n, "mass": m, "polar_inertia": 0.0, "diametral_inertia": 0.0} for n, m in discs]
    return parse_scene(d, "g.toml").plant


def z(node):
    return (node - 1) * L / 20


def test_two_supports_take_the_weight_by_the_lever_rule():
    """Statically determinate: the symmetric beam's supports carry w L / 2 each; with an overhang
    and two discs the lever rule about each support (shaft weight at its middle, disc weights at
    their nodes) gives the shares; x (and the axial axis) carry nothing."""
    s = spec()
    load = gravity_loads(s, assemble(s))
    assert np.allclose(load, [0, W_SHAFT / 2, 0, W_SHAFT / 2], rtol=1e-12, atol=1e-12 * W_SHAFT)
    na, nb, discs = 1, 15, ((8, 12.0), (21, 3.0))  # A at the left end, B at 0.7 m: 0.3 m overhang
    s = spec((na, nb), discs)
    load = gravity_loads(s, assemble(s))
    za, zb = z(na), z(nb)
    parts = [(W_SHAFT, L / 2)] + [(G * m, z(n)) for n, m in discs]
    ra = sum(w * (zb - zc) / (zb - za) for w, zc in parts)
    rb = sum(w * (zc - za) / (zb - za) for w, zc in parts)
    assert np.allclose(load[1::2], [ra, rb], rtol=1e-11), (load, ra, rb)
    assert abs((ra + rb) / sum(w for w, _ in parts) - 1) < 1e-12 and rb > ra > 0  # B next to the overhang
    assert np.all(load[0::2] == 0.0)
    # an axial AMB: its axis carries nothing, the radial shares are the same
    d = copy.deepcopy(BASE)
    d["model"] = {"gravity": G}
    d["axial_amb"] = {"node": 11, "gap": 5e-4, "bias_current": 1.0, "turns": 100, "pole_area": 5e-4}
    sa = parse_scene(d, "g.toml").plant
    la = gravity_loads(sa, assemble(sa))
    assert la.shape == (5,) and la[4] == 0.0 and np.allclose(la[:4], [0, W_SHAFT / 2, 0, W_SHAFT / 2], rtol=1e-12)


def test_three_supports_continuous_beam_and_the_weight():
    """Statically indeterminate: a uniform beam over three equally spaced supports (ends and
    middle) carries 3/8, 10/8, 3/8 of w a (a the span), the two-span continuous beam's classic
    result (compatibility at the middle support; exact at the nodes for Hermite-cubic elements
    under the consistent load); and the paper's 3-AMB rotor's shares sum to its weight (shaft +
    discs, from the scene) and balance its moment about node 1."""
    s = spec((1, 11, 21))
    load = gravity_loads(s, assemble(s))
    wa = W_SHAFT / 2
    assert np.allclose(load[1::2], [3 / 8 * wa, 10 / 8 * wa, 3 / 8 * wa], rtol=1e-10), load
    p = load_scene("scenes/paper_3amb.toml").plant
    p = dc.replace(p, model=dc.replace(p.model, gravity=G))
    load = gravity_loads(p, assemble(p))
    mass_s = [sc.density * np.pi / 4 * (sc.outer_diameter**2 - sc.inner_diameter**2) * sc.length for sc in p.sections]
    W = G * (sum(mass_s) + sum(d.mass for d in p.discs))
    assert abs(load[1::2].sum() / W - 1) < 1e-12 and np.all(load[0::2] == 0.0)
    # moment about z = 0: the shaft (uniform here) at its middle, the discs at their nodes
    zz = np.asarray(p.node_z)
    m_w = G * (sum(mass_s) * p.length / 2 + sum(d.mass * zz[d.node] for d in p.discs))
    m_r = sum(f * zz[a.node] for f, a in zip(load[1::2], p.ambs))
    assert abs(m_r / m_w - 1) < 1e-12
    assert np.all(load[1::2] > 0)


@pytest.mark.parametrize("rung", ["rigid", "modal", "full"])
def test_compile_model_loads_the_bearings_at_every_linear_rung(rung):
    """Model.load is the FE statics' shares at every linear rung; the operating point carries
    them with the exact force law (F(x_op, i_op) = load, k_x, k_i its derivatives: the loaded pair
    is stiffer); the controller's preload (operating_currents, no model) is the same i_op bit for
    bit; without gravity nothing changes (load None, i_op 0)."""
    s = spec(rung=rung, bias_current=3.0)
    m = compile_model(s, period=1e-4)
    assert np.array_equal(m.load, gravity_loads(s, m.rotor)) and m.gravity is None
    assert np.allclose(mb.force(m.force_constant, m.gap, m.bias, m.x_op, m.i_op), m.load, rtol=1e-12, atol=1e-9)
    kx, ki = mb.force_derivatives(m.force_constant, m.gap, m.bias, m.x_op, m.i_op)
    assert np.array_equal(m.kx, kx) and np.array_equal(m.ki, ki)
    assert np.all(m.i_op[1::2] > 0) and np.all(m.i_op[0::2] == 0) and np.all(m.kx[1::2] > m.kx[0::2])
    assert np.array_equal(operating_currents(s), m.i_op)
    assert not m.load.flags.writeable
    s0 = spec(rung=rung, g=0.0, bias_current=3.0)
    m0 = compile_model(s0, period=1e-4)
    assert m0.load is None and np.all(m0.i_op == 0.0) and np.array_equal(m0.loads, np.zeros(4))
    assert np.array_equal(m0.kx, m.kx[0::2].repeat(2))  # x unloaded: the same k_x as without gravity


def test_a_share_beyond_the_bias_capacity_is_refused_naming_the_amb():
    """BASE's AMBs (k i0^2/s0^2 = 23 N per axis at i0 = 1 A) cannot carry 1 m of 50 mm steel
    (15.3 kg) and a 100 kg disc: refused on the linear rungs as on the ancf rung."""
    s = spec(discs=((11, 100.0),))
    with pytest.raises(ParameterError, match=r"g.toml: AMB A y: under \[model\] gravity = 9.81 m/s\^2 it carries "
                                             r"[0-9.]+ N of the rotor's weight: .*bias current 1 A"):
        compile_model(s)
    with pytest.raises(ParameterError, match="AMB A y"):
        operating_currents(s)


def test_controller_runner_refuses_a_current_limit_below_the_load_current_on_a_linear_rung():
    """_check_limit now applies to every rung under gravity."""
    from ambhil.loop.system import compile_system, controller_runner
    d = copy.deepcopy(BASE)
    d["model"] = {"rung": "rigid", "gravity": G}
    for a in d["amb"]:
        a["bias_current"] = 3.0
    d["amplifier"] = {"gain": 1.0, "current_limit": 0.1}
    sc = parse_scene(d, "g.toml")
    m = compile_system(sc)
    assert np.max(m.i_op) > 0.1
    for arg in (sc, m):
        with pytest.raises(ParameterError, match=r"AMB A y: carrying its share of the weight under \[model\] gravity "
                                                 r"needs [0-9.]+ A, beyond \[amplifier\] current_limit = 0.1 A"):
            controller_runner(arg)
    d["amplifier"]["current_limit"] = 2.0
    controller_runner(parse_scene(d, "g.toml"))  # enough current: accepted


def test_ancf_rung_keeps_its_statics_and_sets_load():
    from ambhil.plant import ancf_statics
    s = spec(bias_current=3.0)
    m = compile_model(s, "ancf")
    assert m.gravity is not None and np.array_equal(m.load, m.gravity.load)
    assert np.array_equal(m.load, ancf_statics.gravity_statics(s)[0])
    # and the linear statics agree with the nonlinear one's (microns of sag: linear)
    assert np.allclose(gravity_loads(s, m.rotor), m.load, rtol=1e-6, atol=1e-9)


def test_drop_scene_before_the_drop_holds_the_rotor_under_either_force_law():
    """scenes/rotor_drop.toml without its drop (0.1 s at 600 rad/s, modal rung, gravity on): no
    fault, the orbit at the AMBs stays small against the 0.25 mm clearance, and the mean sensor
    displacement and current deviation equal the no-gravity run's (within 1e-8 m, 1e-3 A) with
    the linearised and with the exact force law (whose remainder is taken about Model.load: without
    that it would be the whole 99 N share, load / k_x ~ 0.1 mm against the AMB's stiffness)."""
    from ambhil.loop.simulation import simulate
    from ambhil.loop.system import compile_system
    sc = load_scene("scenes/rotor_drop.toml")
    sc = dc.replace(sc, faults=type(sc.faults)(()))
    out = {}
    for g in (0.0, G):
        m = compile_system(dc.replace(sc, plant=dc.replace(sc.plant, model=dc.replace(sc.plant.model, gravity=g))))
        for nl in (False, True):
            r = simulate(m, 0.1, nonlinear=nl)
            assert r.fault is None
            late = r.t > 0.05
            assert np.abs(r.y).max() < 0.03 * 2.5e-4
            out[g, nl] = r.y[late].mean(axis=0), r.i[:-1][late[:-1]].mean(axis=0) - m.i_op
    assert np.all(compile_system(sc).i_op[1::2] > 0.4)
    for nl in (False, True):
        assert np.max(np.abs(out[G, nl][0] - out[0.0, nl][0])) < 1e-8, out
        assert np.max(np.abs(out[G, nl][1] - out[0.0, nl][1])) < 1e-3, out
