"""Statics of the ANCF model: equilibrium without inertia by Newton with load stepping
(:func:`solve_static`), and the sag of a scene's rotor under ``[model] gravity`` with the AMB
nodes held, whose reactions are the AMBs' shares of the weight (:func:`gravity_statics`)."""
from __future__ import annotations

import numpy as np

from . import ancf_beam as ab
from .ancf_jacobian import JacobianAssembler
from .ancf_model import ANCFArrays, beams_of_spec, build, n_constraints, straight_state
from .ancf_residual import residual


def solve_static(S: ANCFArrays, q0, loads_scale=None, steps: int = 1, tol: float = 1e-10, maxit: int = 50):
    """Static equilibrium (no inertia) by Newton with load stepping: the external nodal loads
    (nF, nM, gravity) are scaled by k/steps.  Returns (q, multipliers)."""
    n = q0.shape[0]
    nc = int(n_constraints(S))
    x = np.concatenate([q0, np.zeros(nc)])
    asm = JacobianAssembler(S)
    z = np.zeros(n)
    import scipy.sparse.linalg as spla
    for k in range(1, steps + 1):
        s = k / steps
        Sk = S._replace(nF=S.nF * s, nM=S.nM * s, prm=_scaled_gravity(S.prm, s))
        asm.S = Sk
        R = np.zeros(n + nc)
        prev = np.inf
        for it in range(maxit):
            residual(Sk, x, z, 0.0, z, 0.0, 0.0, np.zeros(max(1, S.amb_node.shape[0])), 1.0, 0.0, R)
            A = asm.matrix(x, z, 0.0, z, 0.0, 0.0, np.zeros(max(1, S.amb_node.shape[0])), 1.0, 0.0)
            dx = spla.spsolve(A, -R)
            x += dx
            d, scale = np.max(np.abs(dx[:n])), max(1.0, np.max(np.abs(x[:n])))
            if d < tol * scale or (it > 3 and d > 0.5 * prev and d < 1e-7 * scale):
                break  # converged, or stagnating at the rounding level of the residual
            prev = d
        else:
            raise RuntimeError(f"static Newton did not converge at load step {k}/{steps}")
    asm.S = S
    return x[:n], x[n:]


def _scaled_gravity(prm, s):
    p = prm.copy()
    p[:, ab.P_GX:ab.P_GZ + 1] *= s
    return p


def gravity_statics(spec, steps: int = 1):
    """Static equilibrium under ``[model] gravity`` with the rotor held at zero displacement (x and
    y) at the radial AMBs' nodes: what the PIDs' integral action settles to.  The AMB nodes are
    held by constraints ``q = 0`` (the axial position and the twist at the drive node as in
    :func:`ambhil.plant.ancf_model.from_model`); the AMB reactions are the constraint
    multipliers, so the statically indeterminate shares of the weight follow from the shaft's compatibility.  Returns
    ``(reactions, q)``: the force (N) each AMB axis exerts on the rotor, in the order of
    :func:`ambhil.plant.model.bearing_axes`, and the sagged configuration."""
    from .params import ParameterError
    g = float(spec.model.gravity or 0.0)
    if spec.axial_amb is not None:
        raise ParameterError(f"{spec.path}: [model] rung 'ancf' does not support an [axial_amb] yet")
    for a in spec.ambs:
        if a.sensor_node != a.node:
            raise ParameterError(f"{spec.path}: AMB {a.name}: gravity on the ancf rung needs the sensor at the "
                                 f"actuator node (sensor_node {a.sensor_node + 1} != node {a.node + 1})")
    drive = 0
    held = [(8 * a.node + ax, 0.0) for a in spec.ambs for ax in (0, 1)]
    S, z = build(beams_of_spec(spec), discs=[(d.node, d.mass, d.polar_inertia, d.diametral_inertia) for d in spec.discs],
                 gravity=(0.0, -g, 0.0), spin=(drive, 0.0, 0.0, 0.0, 0.0),
                 fixed=[(8 * drive + 2, spec.node_z[0])] + held, z0=spec.node_z[0])
    q, mu = solve_static(S, straight_state(S, z), steps=steps)
    # residual rows: internal - external + Phi_q^T mu = 0 with Phi = q[k] - 0, so the force the
    # support exerts on the rotor is -mu
    return -mu[len(mu) - len(held):], q
