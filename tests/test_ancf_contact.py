"""Auxiliary-bearing contact and the rotor drop on the ancf rung (plant/ancf_contact.py,
plant/ancf_faults.py, plant/dae_integrator.py): the drop of a small scene against the full FE
rung, the energy bookkeeping of the contact, its Jacobian, and the faults the rung takes."""
from __future__ import annotations

import copy

import numpy as np
import pytest

from ambhil.loop.scene import parse_scene
from ambhil.loop.simulation import simulate
from ambhil.loop.system import compile_system
from ambhil.plant import ancf_contact as ac
from ambhil.plant import ancf_energy as ae
from ambhil.plant import ancf_model as am
from ambhil.plant import beam_element as be
from ambhil.plant import integrator as ig
from ambhil.plant.auxiliary_bearing import AuxiliaryBearing
from ambhil.plant.dae_integrator import DAEIntegrator

AUX = {"clearance": 2.5e-4, "stiffness": 1e8, "damping": 1e4, "friction": 0.2, "race_inertia": 4e-5,
       "race_drag": 5e-5}
AMB = {"gap": 5e-4, "bias_current": 2.0, "turns": 200, "pole_area": 6e-4}
# scenes/rotor_drop.toml's rotor, AMBs and auxiliary bearings on a 10-element mesh (the ANCF model is
# then cheap): 20.2 kg under gravity, the AMBs at 0.1 m and 0.9 m, the impeller at mid-span
SCENE = {"scene": {"name": "drop_small"}, "model": {"rung": "full", "gravity": 9.81},
         "shaft": [{"length": 1.0, "outer_diameter": 0.05, "elements": 10}],
         "disc": [{"name": "imp", "node": 6, "mass": 4.9, "polar_inertia": 0.0245, "diametral_inertia": 0.0124}],
         "amb": [dict(name="A", node=2, auxiliary=dict(AUX), **AMB), dict(name="B", node=10, auxiliary=dict(AUX), **AMB)],
         "sensor": {"gain": 1e4}, "amplifier": {"gain": 1.0, "time_constant": 1e-4, "current_limit": 2.0},
         "controller": {"kp": 1.2, "ki": 10.0, "kd": 1.5e-3, "derivative_filter": 1e-4, "sample_rate": 10000.0},
         "speed": {"value": 600.0}, "damping": {"stiffness_proportional": 2e-6},
         "simulation": {"integrator": "bdf1", "step": 1e-5},
         "fault": [{"kind": "drop", "at": 0.005}]}


def _scene(**over):
    d = copy.deepcopy(SCENE)
    d.update(over)
    return parse_scene(d, "drop_small.toml")


def _events(res, bearing="A"):
    return [e for e in res.contact["events"] if e["bearing"] == bearing]


def test_drop_on_the_ancf_rung_matches_the_full_rung():
    """Drop at 600 rad/s under gravity, BDF1 at 1e-5 s on both rungs: the first impact at the same
    step, its peak force, energy lost and the flight time to the second impact within 1 %."""
    sc = _scene()
    runs = {rung: simulate(compile_system(sc, rung=rung), 0.02) for rung in ("full", "ancf")}
    full, ancf = runs["full"], runs["ancf"]
    assert ancf.fault is None and full.fault is None
    c = ancf.contact
    assert c["names"] == ("A", "B") and c["fn"].shape == (len(ancf.t), 2)
    assert [(e["kind"], e["phase"]) for e in ancf.meta["fault_events"]] == [("drop", "start")]
    ef, ea = _events(full), _events(ancf)
    assert len(ea) >= 3 and [e["phase"] for e in ea[:3]] == ["start", "end", "start"]
    assert abs(ea[0]["t_s"] - ef[0]["t_s"]) < 1.5e-5                       # first contact: same step
    for k in ("peak_force_N", "energy_J"):
        assert ea[1][k] == pytest.approx(ef[1][k], rel=0.01), k
    flight = lambda ev: ev[2]["t_s"] - ev[1]["t_s"]                       # rebound: time in the air
    assert flight(ea) == pytest.approx(flight(ef), rel=0.03)
    sa, sf = c["summary"]["A"], full.contact["summary"]["A"]
    for k in ("friction_energy_J", "damping_energy_J", "impulse_N_s"):
        assert sa[k] == pytest.approx(sf[k], rel=0.01), k
    assert sa["friction_energy_J"] > 1.0 and sa["damping_energy_J"] > 0.0


def _free_shaft(law, h, friction=0.2):
    """A 1 m shaft with a 4.9 kg disc, no AMB force, no spin, no damping: it starts 0.15 mm off the
    bearings' centre moving down at 0.07 m/s onto two auxiliary bearings (nodes 2 and 6)."""
    A, I = be.section_properties(0.05, 0.0)
    beams = [am.Beam(1.0, 6, 2.1e11 * A, 2.1e11 * I, 2.1e11 / 2.6 * 2 * I, 7850 * A, 7850 * I)]
    nodes = [1, 5]
    ax = dict(node=[n for n in nodes for _ in (0, 1)], axis=[0, 1, 0, 1], kx=[0.0] * 4, ki=[0.0] * 4, iop=[0.0] * 4,
              xop=[0.0] * 4, kc=[0.0] * 4, gap=[5e-4] * 4, bias=[1.0] * 4, ref=[0.0] * 4,
              sens_node=[n for n in nodes for _ in (0, 1)], sens_axis=[0, 1, 0, 1])
    S, z = am.build(beams, discs=[(3, 4.9, 0.0245, 0.0124)], spin=(0, 0.0, 0.0, 0.0, 0.0), fixed=[(2, 0.0)], ambs=ax)
    aux = AuxiliaryBearing(clearance=2.5e-4, shaft_radius=0.025, friction=friction, race_inertia=4e-5, **law).validate()
    C = ac.ContactArrays(aux_p=np.array([aux.array()] * 2), aux_ax=np.array([[0, 1], [2, 3]]),
                         aux_dof=np.array([[8 * n, 8 * n + 1] for n in nodes]))
    q0, v0 = am.straight_state(S, z), np.zeros(8 * S.nJ.shape[0])
    q0[0::8] += 1.5e-4
    v0[1::8] = -0.07
    return S, aux, DAEIntegrator(S, q0, v0, h, "generalized-alpha", rho_inf=1.0, tol=1e-11, maxit=10, contact=C)


def _energy_error(law, h, duration=0.02):
    """Largest |E + E_contact + C_ED + C_EF - E0| / E0 over a run with five impacts per bearing
    (E: kinetic + strain energy of the shaft, E_contact: the contact springs' and the races' energy)."""
    S, aux, dae = _free_shaft(law, h)

    def energy():
        c = dae.c
        stored = sum(aux.elastic_energy(c[j, ig.C_D]) + 0.5 * aux.race_inertia * c[j, ig.C_W] ** 2 for j in range(2))
        return ae.kinetic_energy(S, dae.q, dae.v, dae.t) + ae.strain_energy(S, dae.q) + stored
    E0 = energy()
    worst = 0.0
    for _ in range(int(round(duration / h))):
        assert dae.step(np.zeros(4)) == 0
        worst = max(worst, abs(energy() + dae.c[:, ig.C_ED].sum() + dae.c[:, ig.C_EF].sum() - E0))
    assert np.all(dae.c[:, ig.C_NEV] >= 4) and np.all(dae.c[:, ig.C_EF] > 0)
    return worst / E0


def test_contact_energy_is_accounted_and_converges_with_the_step():
    """Hertz contact (elastic, e = 1) with sliding friction against the race, the non-dissipative
    generalised-alpha (rho_inf = 1): what the shaft and the races lose is the friction energy C_EF
    to first order in h (the bookkeeping sums the end-of-step powers): 1.8e-3 of E0 at 1e-5 s,
    half that at 5e-6 s."""
    hertz = dict(stiffness=3e10, exponent=1.5, restitution=1.0)
    e1, e2 = _energy_error(hertz, 1e-5), _energy_error(hertz, 5e-6)
    assert e1 < 3e-3 and e2 < 0.6 * e1


def test_contact_jacobian_against_central_differences():
    """The 2x2 blocks the step matrix gets (forward differences with the race solved in each) equal
    central differences of the residual through q+ (positions and the scheme's velocity)."""
    S, aux, dae = _free_shaft(dict(stiffness=1e8, damping=1e4), 1e-5)
    C, c = dae.C, dae.c
    q = dae.q.copy()
    q[1::8] -= np.sqrt((2.5e-4 + 5e-6) ** 2 - 1.5e-4 ** 2)   # 5 um into both bearings
    vel = np.zeros_like(q)
    vel[0::8], vel[1::8] = 0.01, -0.05                     # moving in, sliding against the held race
    cv = 1.0 / dae.h
    vh = vel - cv * q
    n, jc = q.shape[0], np.zeros((2, 2, 2))

    def res(qq):
        out = np.zeros(n)
        ac.add_contact(S, C, c, qq, vh + cv * qq, cv, 0.0, dae.h, 1.0, out, jc)
        return out
    mask = ac.add_contact(S, C, c, q, vh + cv * q, cv, 0.0, dae.h, 1.0, np.zeros(n), jc)
    J = jc.copy()
    assert mask == 3
    for j in range(2):
        for k in range(2):
            e = np.zeros(n)
            e[C.aux_dof[j, k]] = 1e-10
            d = (res(q + e) - res(q - e)) / 2e-10
            assert d[C.aux_dof[j]] == pytest.approx(J[j, :, k], rel=1e-3, abs=1e-4 * np.abs(J[j]).max())


def test_amb_loss_of_one_station_and_what_the_rung_refuses():
    """amb_loss of A: A's axes lose k_x, k_i and the force constant from the fault's step, B's keep
    them, and they come back at its end (events as on the linear rungs); a kind the ancf rung does
    not take is refused naming it; a drop's coast-down needs a run without a run-up."""
    from ambhil.plant.ancf_faults import ANCFFaultyPlant
    from ambhil.plant.ancf_step import ANCFRunner
    from ambhil.plant.run_options import RunOptions
    sc = _scene(fault=[{"kind": "amb_loss", "axis": "A", "at": 0.001, "duration": 0.001}])
    model = compile_system(sc, rung="ancf")
    plant = ANCFFaultyPlant(ANCFRunner(model), sc.faults)
    S0 = plant.S
    for k in range(25):
        plant.advance(model.i_op)
        if k == 10:
            assert np.all(plant.dae.S.amb_kx[:2] == 0) and np.all(plant.dae.S.amb_ki[:2] == 0)
            assert np.array_equal(plant.dae.S.amb_kx[2:], S0.amb_kx[2:])
    assert np.array_equal(plant.dae.S.amb_kx, S0.amb_kx)
    assert [(e["kind"], e["phase"], e["step"]) for e in plant.events] == [("amb_loss", "start", 10), ("amb_loss", "end", 20)]
    bad = _scene(fault=[{"kind": "sensor_zero", "axis": "A.x", "at": 0.001}])
    with pytest.raises(ValueError, match="not supported on the ancf rung yet .*sensor_zero"):
        simulate(compile_system(bad, rung="ancf"), 0.001)
    cd = _scene(fault=[{"kind": "drop", "at": 0.001, "coast_down": 0.01}])
    res = simulate(compile_system(cd, rung="ancf"), 0.004)
    assert res.speed[0] == 600.0 and res.speed[-1] == pytest.approx(600.0 * (1 - 0.003 / 0.01))
    with pytest.raises(ValueError, match="coast_down"):
        ANCFFaultyPlant(ANCFRunner(compile_system(cd, rung="ancf"), RunOptions(run_up=(0.0, 600.0, 0.0, 1.0))),
                        cd.faults)
