"""The rotor's scene tables, one parser each: ``[model]``, ``[[shaft]]``, ``[[disc]]``,
``[[unbalance]]``, ``[speed]``, ``[damping]`` and ``[simulation]`` (the plant's time-domain
defaults) -> the dataclasses of :mod:`ambhil.plant.params`.  The bearings are in
``scene_bearings.py``; :func:`ambhil.loop.scene.parse_scene` calls them in the order of the file's
sections.

Each parser takes the whole TOML document ``doc`` and the file's name ``p`` (for messages); a
table that is absent gives its defaults.  Stations take the mesh's node positions ``node_z``
(from :func:`shaft`).
"""
from __future__ import annotations

from ambhil.plant.params import RUNGS, SCHEMES, Damping, Disc, ModelOptions, Section, Simulation, Speed, Unbalance
from .scene_table import SceneError, Table, station, tables

#: most shaft elements the model takes (over every section)
MAX_ELEMENTS = 1000


def model_options(doc: dict, p: str) -> ModelOptions:
    """``[model]``: the rung, the beam theory, the modal cutoff, rotary inertia, gravity."""
    t = Table(p, "[model]", doc.get("model", {}))
    model = ModelOptions(
        rung=t.string("rung", "full", choices=RUNGS),
        beam=t.string("beam", "euler-bernoulli", choices=("euler-bernoulli", "timoshenko")),
        modal_cutoff=t.num("modal_cutoff", None, positive=True),
        rotary_inertia=t.boolean("rotary_inertia", True),
        gravity=t.num("gravity", 0.0, nonneg=True),
    )
    t.done()
    return model


def shaft(doc: dict, p: str) -> tuple[list[Section], tuple[float, ...]]:
    """``[[shaft]]`` sections, left to right -> (sections, node_z: the mesh's node positions in m)."""
    sections: list[Section] = []
    raw_sections = tables(p, doc, "shaft")
    if not raw_sections:
        raise SceneError(f"{p}: [[shaft]]: at least one shaft section is required")
    for where, raw in raw_sections:
        t = Table(p, where, raw)
        s = Section(
            length=t.num("length", positive=True),
            outer_diameter=t.num("outer_diameter", positive=True),
            inner_diameter=t.num("inner_diameter", 0.0, nonneg=True),
            elements=t.integer("elements", 1, minimum=1, maximum=MAX_ELEMENTS),
            youngs_modulus=t.num("youngs_modulus", 2.11e11, positive=True),
            shear_modulus=t.num("shear_modulus", 8.12e10, positive=True),
            density=t.num("density", 7810.0, positive=True),
        )
        if s.inner_diameter >= s.outer_diameter:
            t.fail("inner_diameter", f"must be < outer_diameter ({s.outer_diameter:g} m), got {s.inner_diameter:g}")
        t.done()
        sections.append(s)
        if sum(x.elements for x in sections) > MAX_ELEMENTS:
            t.fail("elements", f"the shaft has {sum(x.elements for x in sections)} elements in all; the model "
                               f"takes at most {MAX_ELEMENTS}")
    z = [0.0]
    for s in sections:
        le = s.length / s.elements
        for k in range(s.elements):
            z.append(z[-1] + le)
    return sections, tuple(z)


def discs(doc: dict, p: str, node_z: tuple[float, ...]) -> list[Disc]:
    """``[[disc]]``: rigid discs at nodes (named disc1, disc2, ... unless named)."""
    out: list[Disc] = []
    for where, raw in tables(p, doc, "disc"):
        t = Table(p, where, raw)
        d = Disc(
            name=t.string("name", f"disc{len(out) + 1}"),
            node=station(t, node_z),
            mass=t.num("mass", positive=True),
            polar_inertia=t.num("polar_inertia", nonneg=True),
            diametral_inertia=t.num("diametral_inertia", nonneg=True),
        )
        t.done()
        out.append(d)
    return out


def unbalances(doc: dict, p: str, node_z: tuple[float, ...]) -> list[Unbalance]:
    """``[[unbalance]]``: magnitude (kg m) and phase (rad) at a station."""
    out: list[Unbalance] = []
    for where, raw in tables(p, doc, "unbalance"):
        t = Table(p, where, raw)
        out.append(Unbalance(node=station(t, node_z), magnitude=t.num("magnitude", nonneg=True),
                             phase=t.num("phase", 0.0)))
        t.done()
    return out


def speed(doc: dict, p: str) -> Speed:
    """``[speed]``: a constant ``value`` or a sweep ``range`` (rad/s), and its ``points``."""
    t = Table(p, "[speed]", doc.get("speed", {}))
    if t.has("value") and t.has("range"):
        t.fail("value", "give either 'value' (constant speed) or 'range' (sweep), not both")
    if t.has("range"):
        lo, hi = t.pair("range")
        if lo < 0 or hi <= lo:
            t.fail("range", f"must be [start, stop] with 0 <= start < stop rad/s, got [{lo:g}, {hi:g}]")
        out = Speed(start=lo, stop=hi, points=t.integer("points", 400, minimum=2, maximum=10_000))
    else:
        out = Speed(value=t.num("value", 0.0, nonneg=True), points=t.integer("points", 400, minimum=2,
                                                                               maximum=10_000))
    t.done()
    return out


def damping(doc: dict, p: str) -> Damping:
    """``[damping]``: Rayleigh damping, mass- (1/s) and stiffness-proportional (s)."""
    t = Table(p, "[damping]", doc.get("damping", {}))
    out = Damping(mass_proportional=t.num("mass_proportional", 0.0, nonneg=True),
                  stiffness_proportional=t.num("stiffness_proportional", 0.0, nonneg=True))
    if out.stiffness_proportional > 1.0:  # beyond it the step matrix ~ beta K (singular: rigid modes)
        t.fail("stiffness_proportional", f"must be <= 1 s (beta = 1 s already overdamps every flexible mode), "
                                         f"got {out.stiffness_proportional:g}")
    t.done()
    return out


def simulation(doc: dict, p: str, node_z: tuple[float, ...]) -> Simulation:
    """``[simulation]``: the time-domain defaults (integrator, step, duration, force law, run-up,
    Newton, recorded nodes).  The input period is not here: it is the controller's sample period
    (:attr:`ambhil.loop.scene.Scene.period`)."""
    t = Table(p, "[simulation]", doc.get("simulation", {}))
    # whether the controller period is a whole number of steps is checked where the step is used
    # (plant.step.PlantRunner), so that `simulate --h` can override an inconsistent step
    step = t.num("step", None, positive=True)
    run_up = t.pair("run_up", None)
    if run_up is not None and (run_up[0] < 0 or run_up[1] < 0):
        t.fail("run_up", f"speeds must be >= 0 rad/s, got {list(run_up)!r}")
    run_up_time = t.pair("run_up_time", (0.0, 1.0))
    if not 0 <= run_up_time[0] < run_up_time[1]:
        t.fail("run_up_time", f"must be [t0, t1] with 0 <= t0 < t1 s, got {list(run_up_time)!r}")
    sim_nodes = t.nodes("output_nodes", len(node_z))
    rho = t.num("rho_inf", 0.8, nonneg=True)
    if rho > 1:
        t.fail("rho_inf", f"must be in [0, 1], got {rho:g}")
    out = Simulation(
        integrator=t.string("integrator", "bdf1", choices=SCHEMES),
        step=step, rho_inf=rho, duration=t.num("duration", 0.5, positive=True),
        force_law=t.string("force_law", "linear", choices=("linear", "nonlinear")),
        speed=t.num("speed", None, nonneg=True), run_up=run_up, run_up_time=run_up_time,
        newton_iterations=t.integer("newton_iterations", 10, minimum=1, maximum=1000),
        newton_tol=t.num("newton_tol", 1e-10, positive=True),
        output_nodes=tuple(sim_nodes), record_every=t.integer("record_every", 1, minimum=1),
    )
    if out.integrator == "zoh" and (out.force_law == "nonlinear" or run_up is not None):
        t.fail("integrator", "zoh (exact) needs a linear time-invariant scene: no nonlinear force law, no run_up")
    t.done()
    return out
