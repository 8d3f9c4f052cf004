"""How well a plant step resolves the auxiliary bearings' contact: the fixed-step plant's "step
control" for impacts.

The plant integrates with a fixed step ``h`` (a real-time plant cannot stop to locate an event), so
a contact must last many steps for the implicit step to follow it: the force rises and falls over
the contact time ``t_c`` of the station's effective mass on the contact spring,

    t_c = pi sqrt(m / k)                                   (linear law)
    t_c = 2 (d_max / v0) B(1/(n+1), 1/2) / (n+1)           (Hertz, F = K d^n; at the impact speed v0)

with ``m = 1 / (Ca_y M^-1 Ca_y^T)`` the mass the station's y axis sees (for a rigid rotor on two
bearings: about its share of the rotor's mass) and, for the Hertz law, ``v0 = sqrt(2 g c)``, the
speed of a free fall through the clearance (``g`` the scene's gravity, else 9.81 m/s^2).

A plan whose step resolves a contact in fewer than :data:`MIN_STEPS` steps is refused (the impact
would be one or two steps of a stiff spring: the first-order schemes then lose most of the bounce
and the second-order ones ring); below :data:`GOOD_STEPS` the run is made and says so (the
convergence with the step is shown by ``ambhil study`` and docs/contact.md, section Validation).
"""
from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

MIN_STEPS = 4
GOOD_STEPS = 20


def station_masses(model) -> dict[str, float]:
    """The effective mass (kg) each auxiliary-bearing station's y axis sees: 1 / (c M^-1 c^T)."""
    out = {}
    rows = {ax: k for k, ax in enumerate(model.axes)}
    solve = None
    for a in model.spec.ambs:
        if getattr(a, "auxiliary", None) is None:
            continue
        if solve is None:
            M = model.M
            solve = spla.factorized(sp.csc_matrix(M)) if sp.issparse(M) else (lambda b, M=np.asarray(M): np.linalg.solve(M, b))
        Ca = model.Ca
        c = np.asarray(Ca[rows[(a.name, "y")]].toarray()).ravel() if sp.issparse(Ca) else np.asarray(Ca[rows[(a.name, "y")]])
        out[a.name] = float(1.0 / (c @ solve(c)))
    return out


def contact_times(model) -> dict[str, float]:
    """The contact time t_c (s) of each auxiliary-bearing station (module docstring)."""
    g = float(getattr(model.spec.model, "gravity", 0.0) or 9.81)
    by = {a.name: a.auxiliary for a in model.spec.ambs if getattr(a, "auxiliary", None) is not None}
    return {name: by[name].contact_time(m, math.sqrt(2.0 * g * by[name].clearance))
            for name, m in station_masses(model).items()}


def resolution(model, h: float) -> dict[str, tuple[float, float]]:
    """Per station (t_c in s, plant steps per contact t_c / h)."""
    return {name: (tc, tc / h) for name, tc in contact_times(model).items()}


def check(model, h: float) -> list[str]:
    """Refuse (ValueError, one line) a step that resolves a contact in fewer than MIN_STEPS steps;
    return a note per station resolved in fewer than GOOD_STEPS."""
    notes = []
    for name, (tc, nsteps) in resolution(model, h).items():
        need = f"[simulation] step <= {tc / GOOD_STEPS:.3g} s resolves it in {GOOD_STEPS}"
        if nsteps < MIN_STEPS:
            raise ValueError(f"plant step {h:g} s resolves the contact at auxiliary bearing {name} (t_c = "
                             f"{tc:.3g} s) in {nsteps:.2g} steps, fewer than {MIN_STEPS}: the impact cannot be "
                             f"followed; {need}")
        if nsteps < GOOD_STEPS:
            notes.append(f"auxiliary bearing {name}: the plant step {h:g} s resolves a contact (t_c = {tc:.3g} s) "
                         f"in only {nsteps:.3g} steps: contact figures are rough; {need}")
    return notes
