"""``[amb.auxiliary]``: the auxiliary (touchdown) bearing of an AMB in the scene -> RadialAMB.auxiliary,
one clearance shared with ``touchdown_clearance``, its defaults, and every bad input a one-line
error naming ``auxiliary.<key>``."""
import copy
import tomllib

import pytest
from ambhil.loop.scene import SceneError, load_scene, parse_scene
from ambhil.plant.auxiliary_bearing import AuxiliaryBearing
from helpers import BASE

AUX = {"stiffness": 2e8, "damping": 2e3, "friction": 0.2}


def doc(aux=None, **amb_keys):
    """BASE with ``aux`` as AMB A's auxiliary table (and more keys of AMB A)."""
    d = copy.deepcopy(BASE)
    d["amb"][0].update(amb_keys)
    if aux is not None:
        d["amb"][0]["auxiliary"] = aux
    return d


def err(d):
    with pytest.raises(SceneError) as e:
        parse_scene(d, "bad.toml")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("bad.toml: ")
    return msg


def test_subtable_gives_the_auxiliary_bearing_with_its_defaults():
    """Written as TOML ([amb.auxiliary] right after its [[amb]], and inline): the clearance from
    the AMB's touchdown_clearance, the journal radius half the shaft's outer diameter, the other
    keys AuxiliaryBearing's defaults; an AMB without the table has none."""
    text = """
[model]
rung = "modal"
modal_cutoff = 5000.0
[[shaft]]
length = 0.5
outer_diameter = 0.05
elements = 10
[[shaft]]
length = 0.5
outer_diameter = 0.06
elements = 10
[[amb]]
name = "A"
node = 11
gap = 5e-4
touchdown_clearance = 2.5e-4
bias_current = 1.0
turns = 100
pole_area = 5e-4
[amb.auxiliary]
stiffness = 2e8
damping = 2e3
friction = 0.2
race_inertia = 1e-4
race_drag = 1e-5
[[amb]]
name = "B"
node = 19
gap = 5e-4
bias_current = 1.0
turns = 100
pole_area = 5e-4
auxiliary = { clearance = 2e-4, stiffness = 1e9, exponent = 1.5, restitution = 0.6, shaft_radius = 0.02 }
[[amb]]
name = "C"
node = 3
gap = 5e-4
bias_current = 1.0
turns = 100
pole_area = 5e-4
[controller]
kp = 1.0
"""
    s = parse_scene(tomllib.loads(text), "t.toml")
    a, b, c = s.plant.ambs
    # node 11 joins the 50 mm and the 60 mm sections: the larger journal
    assert a.auxiliary == AuxiliaryBearing(clearance=2.5e-4, stiffness=2e8, shaft_radius=0.03, damping=2e3,
                                           friction=0.2, race_inertia=1e-4, race_drag=1e-5)
    assert a.touchdown_clearance == a.clearance == 2.5e-4
    # the auxiliary clearance becomes the AMB's touchdown clearance (one truth)
    assert b.auxiliary == AuxiliaryBearing(clearance=2e-4, stiffness=1e9, shaft_radius=0.02, exponent=1.5,
                                           restitution=0.6)
    assert b.touchdown_clearance == b.clearance == 2e-4
    assert c.auxiliary is None and c.touchdown_clearance is None
    assert a.auxiliary.race_r == pytest.approx(0.03 + 2.5e-4)


def test_journal_radius_inside_a_section_and_at_the_shaft_end():
    s = parse_scene(doc(dict(AUX, clearance=1e-4)), "t.toml")
    assert s.plant.ambs[0].auxiliary.shaft_radius == 0.025
    d = doc(dict(AUX, clearance=1e-4), node=1)
    assert parse_scene(d, "t.toml").plant.ambs[0].auxiliary.shaft_radius == 0.025


def test_analysis_default_does_not_override_the_auxiliary_clearance():
    d = doc(dict(AUX, clearance=1e-4))
    d["analysis"] = {"touchdown_clearance": 2e-4}
    a, b = parse_scene(d, "t.toml").plant.ambs
    assert (a.touchdown_clearance, a.auxiliary.clearance, b.touchdown_clearance) == (1e-4, 1e-4, 2e-4)


CASES = [
    # clearance vs the magnetic gap (5e-4), given in the sub-table or through touchdown_clearance
    (doc(dict(AUX, clearance=5e-4)),
     "[[amb]] #1 'A' key 'auxiliary.clearance': 0.0005 m must be smaller than this AMB's magnetic gap 0.0005 m"),
    (doc(dict(AUX, clearance=6e-4)), "key 'auxiliary.clearance': 0.0006 m must be smaller than this AMB's magnetic gap"),
    (doc(dict(AUX, clearance=1e-4), touchdown_clearance=2e-4),
     "[[amb]] #1 'A' key 'auxiliary.clearance': 0.0001 m differs from this AMB's touchdown_clearance 0.0002 m"),
    (doc(AUX), "[[amb]] #1 'A' key 'auxiliary.clearance': is required (or this [[amb]]'s touchdown_clearance)"),
    (doc({"clearance": 1e-4}), "[[amb]] #1 'A' key 'auxiliary.stiffness': is required"),
    (doc(dict(AUX, clearance=1e-4, stiffness=-1e8)), "[[amb]] #1 'A' key 'auxiliary.stiffness': -1e+08: must be > 0"),
    (doc(dict(AUX, clearance=1e-4, friction=1.5)), "[[amb]] #1 'A' key 'auxiliary.friction': 1.5: must be in 0..1"),
    (doc({"clearance": 1e-4, "stiffness": 1e8, "restitution": 0.5}),
     "[[amb]] #1 'A' key 'auxiliary.restitution': 0.5: is the Hertz law's e (exponent != 1)"),
    (doc({"clearance": 1e-4, "stiffness": 1e9, "exponent": 1.5, "damping": 100.0}),
     "[[amb]] #1 'A' key 'auxiliary.damping': 100: is the linear law's c_c (exponent = 1)"),
    (doc({"clearance": 1e-4, "stiffness": 1e9, "exponent": 3.0}), "key 'auxiliary.exponent': 3: must be in 1..2"),
    (doc(dict(AUX, clearance=1e-4, frictoin=0.2)),
     "[[amb]] #1 'A' key 'auxiliary.frictoin': unknown key (did you mean 'auxiliary.friction'?)"),
    (doc(dict(AUX, clearance=1e-4, friction="0.2")),
     "[[amb]] #1 'A' key 'auxiliary.friction': must be a number, got str '0.2'"),
    (doc(dict(AUX, clearance=1e-4, race_inertia=True)),
     "[[amb]] #1 'A' key 'auxiliary.race_inertia': must be a number, got bool True"),
    (doc(dict(AUX, clearance=1e-4, race_radius=0.01)),
     "key 'auxiliary.race_radius': 0.01: must be > shaft_radius (0.025 m)"),
    (doc(dict(AUX, clearance=float("nan"))), "key 'auxiliary.clearance': must be finite"),
    (doc(dict(AUX, clearance=1e-4, race_drag=-1.0)), "key 'auxiliary.race_drag': -1: must be >= 0 N m s"),
    (doc(0.2), "[[amb]] #1 'A' key 'auxiliary': must be a table"),
]


@pytest.mark.parametrize("d,expected", CASES, ids=[str(i) for i in range(len(CASES))])
def test_bad_auxiliary_input_is_one_line_naming_the_key(d, expected):
    msg = err(d)
    assert expected in msg, msg


def test_second_amb_is_named_in_its_error():
    d = copy.deepcopy(BASE)
    d["amb"][1]["auxiliary"] = {"clearance": 1e-4, "stiffness": 1e8, "friction": 2.0}
    assert err(d) == "bad.toml: [[amb]] #2 'B' key 'auxiliary.friction': 2: must be in 0..1"


def test_drop_scene_loads_with_auxiliary_bearings_under_both_ambs():
    s = load_scene("scenes/rotor_drop.toml")
    assert s.plant.model.gravity > 0 and s.plant.model.rung == "modal"
    for a in s.plant.ambs:
        aux = a.auxiliary
        assert aux is not None and aux.clearance == a.touchdown_clearance < a.gap
        assert 1e7 <= aux.stiffness <= 1e9 and 0.1 <= aux.friction <= 0.3 and aux.race_inertia > 0
