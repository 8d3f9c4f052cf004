"""The ANCF multibody model of a rotor: its arrays (:class:`ANCFArrays`), built from quaternion ANCF
beam elements (``plant/ancf_beam.py``) and nodal rigid bodies (``plant/ancf_disc.py``) by
:func:`build`, or from a compiled scene by :func:`from_model`.  The rest of the model reads these
arrays: the residual of a step with its AMB, unbalance and gravity forces
(``plant/ancf_residual.py``), its exact (complex-step) Jacobian (``plant/ancf_jacobian.py``),
statics (``plant/ancf_statics.py``), energies and angular momentum (``plant/ancf_energy.py``) and
the linearisation of the DAE for eigen-analysis (``plant/ancf_linearised.py``).

Unknowns of a step: ``x = [q (8 per node), mu (one per constraint)]``; constraints, in order:
the normalisation ``theta_i . theta_i - 1 = 0`` of every node, the prescribed spin (if any), and
fixed coordinates ``q_k = value`` (clamps in the statics tests; the axial position of the drive
node when the scene has no axial AMB).

Prescribed spin (chosen over a drive torque): the other rungs prescribe the speed (constant or a
run-up ramp), so the ANCF rung does the same.  Every node's attitude is ``theta_i (x) s(t)`` with
``s(t)`` the rotation by the prescribed spin angle ``phi(t)`` about the body axis
(``plant/ancf_disc.py``: an exact change of variables that keeps ``theta`` near identity, so an
implicit integrator does not damp the spin); the drive node (node 1) has no twist about it,
``(A(theta) e1)_y = 2 (x y + w z) = 0``, whose multiplier is the drive torque.  The rest of the
rotor follows through the torsional stiffness; gyroscopic coupling comes from the kinetic energy
(quadratic-velocity and base-spin terms), not from an added matrix.
"""
from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import numba as nb
import numpy as np

from . import ancf_beam as ab
from . import beam_element as be

ANCFArrays = namedtuple("ANCFArrays", [
    "conn",  # (ne, 2) int64 element nodes
    "prm",  # (ne, P_LEN) element parameters
    "nJ",  # (nn, 3) nodal body inertia diag(J_d, J_d, J_p)
    "nm",  # (nn,) nodal rigid mass (discs)
    "nF",  # (nn, 3) constant external force (gravity on discs, static loads)
    "nM",  # (nn, 3) constant external spatial moment
    "alpha",  # (1,) mass-proportional damping on translations
    "spin",  # (5,) node (-1: none), W0, W1, T0, T1
    "fix_idx", "fix_val",  # fixed coordinates
    "amb_node", "amb_axis",  # (na,) actuator node and axis (0 x, 1 y, 2 z)
    "amb_kx", "amb_ki", "amb_iop", "amb_xop", "amb_kc", "amb_gap", "amb_bias", "amb_ref",
    "amb_nl",  # (1,) 1: nonlinear force law
    "sens_node", "sens_axis",
    "unb_node", "unb_me", "unb_phase",
])


@nb.njit(cache=True)
def speed_profile(sp_, t):
    """(phi, Omega, dOmega/dt) of the prescribed spin: W0 until T0, linear to W1 at T1."""
    W0, W1, T0, T1 = sp_[1], sp_[2], sp_[3], sp_[4]
    if T1 <= T0 or t <= T0:
        return W0 * t, W0, 0.0
    a = (W1 - W0) / (T1 - T0)
    if t < T1:
        tau = t - T0
        return W0 * t + 0.5 * a * tau * tau, W0 + a * tau, a
    tau = T1 - T0
    return W0 * T1 + 0.5 * a * tau * tau + W1 * (t - T1), W1, 0.0


@nb.njit(cache=True)
def n_constraints(S):
    return S.nJ.shape[0] + (1 if S.spin[0] >= 0 else 0) + S.fix_idx.shape[0]


# --------------------------------------------------------------------------- building the model
@dataclass
class Beam:
    """A straight shaft segment for :func:`build`: length, element count and section data."""
    length: float
    elements: int
    EA: float
    EI: float
    GJ: float
    rhoA: float
    rhoI: float  # rho I per unit length (diametral; polar = 2 rhoI)


def build(beams, *, discs=(), beta=0.0, alpha=0.0, gravity=(0.0, 0.0, 0.0), spin=None, fixed=(),
          ambs=None, unbalances=(), node_force=None, node_moment=None, z0=0.0):
    """ANCFArrays of a straight shaft along +z made of ``beams`` (list of Beam).
    ``discs``: (node, mass, J_p, J_d); ``spin``: None or (node, W0, W1, T0, T1): the base spin
    profile of every node, and the drive node whose twist about it is held (-1: none);
    ``fixed``: (coordinate index, value); ``ambs``: dict of per-axis arrays (see ANCFArrays);
    ``unbalances``: (node, me, phase).  Returns (S, node_z)."""
    prm, z, conn = [], [z0], []
    nJ = [np.zeros(3)]
    node = 0
    for b in beams:
        l = b.length / b.elements
        for _ in range(b.elements):
            p = np.zeros(ab.P_LEN)
            p[ab.P_L], p[ab.P_EA], p[ab.P_EI], p[ab.P_GJ], p[ab.P_RHOA] = l, b.EA, b.EI, b.GJ, b.rhoA
            p[ab.P_BETA], p[ab.P_ALPHA] = beta, alpha
            p[ab.P_GX:ab.P_GZ + 1] = gravity
            prm.append(p)
            conn.append((node, node + 1))
            jl = 0.5 * l * np.array([b.rhoI, b.rhoI, 2.0 * b.rhoI])
            nJ[-1] = nJ[-1] + jl
            nJ.append(jl.copy())
            z.append(z[-1] + l)
            node += 1
    nn = node + 1
    nJ = np.array(nJ)
    nm = np.zeros(nn)
    for (k, m, Jp, Jd) in discs:
        nm[k] += m
        nJ[k] += (Jd, Jd, Jp)
    nF = np.zeros((nn, 3)) if node_force is None else np.asarray(node_force, float).copy()
    nF += nm[:, None] * np.asarray(gravity, float)[None, :]
    nM = np.zeros((nn, 3)) if node_moment is None else np.asarray(node_moment, float).copy()
    spn = np.array([-1.0, 0, 0, 0, 0]) if spin is None else np.array(spin, float)
    fi = np.array([f[0] for f in fixed], dtype=np.int64)
    fv = np.array([f[1] for f in fixed], dtype=float)
    A = ambs or {}
    ia = lambda k: np.asarray(A.get(k, []), dtype=np.int64)
    fa = lambda k: np.asarray(A.get(k, []), dtype=float)
    S = ANCFArrays(conn=np.array(conn, dtype=np.int64), prm=np.array(prm), nJ=nJ, nm=nm, nF=nF, nM=nM,
                   alpha=np.array([alpha]), spin=spn, fix_idx=fi, fix_val=fv,
                   amb_node=ia("node"), amb_axis=ia("axis"), amb_kx=fa("kx"), amb_ki=fa("ki"), amb_iop=fa("iop"),
                   amb_xop=fa("xop"), amb_kc=fa("kc"), amb_gap=fa("gap"), amb_bias=fa("bias"), amb_ref=fa("ref"),
                   amb_nl=np.array([int(A.get("nonlinear", 0))], dtype=np.int64),
                   sens_node=ia("sens_node"), sens_axis=ia("sens_axis"),
                   unb_node=np.array([u[0] for u in unbalances], dtype=np.int64),
                   unb_me=np.array([u[1] for u in unbalances], dtype=float),
                   unb_phase=np.array([u[2] for u in unbalances], dtype=float))
    return S, np.array(z)


def beams_of_spec(spec) -> list[Beam]:
    out = []
    for s in spec.sections:
        A, I = be.section_properties(s.outer_diameter, s.inner_diameter)
        out.append(Beam(s.length, s.elements, s.youngs_modulus * A, s.youngs_modulus * I,
                        s.shear_modulus * 2 * I, s.density * A, s.density * I))
    return out


def straight_state(S: ANCFArrays, node_z) -> np.ndarray:
    """q of the unstressed straight shaft along +z, identity attitudes."""
    nn = S.nJ.shape[0]
    q = np.zeros(8 * nn)
    q[2::8] = node_z
    q[4::8] = 1.0
    return q


def spin_velocity(S: ANCFArrays, W: float) -> np.ndarray:
    """v of a rigid spin W about +z of the straight shaft in its reference attitude."""
    nn = S.nJ.shape[0]
    v = np.zeros(8 * nn)
    v[7::8] = 0.5 * W
    return v


# --------------------------------------------------------------------------- from a scene
def from_model(model, speed: float = 0.0, run_up=None, nonlinear: bool = False):
    """ANCFArrays of a compiled scene model (``model.spec``; AMB axes, operating points and
    force constants from the model, so the force law is the very one of the other rungs).
    ``run_up = (W0, W1, T0, T1)``.  Returns (S, q0)."""
    from .params import ParameterError
    spec = model.spec
    if spec.axial_amb is not None:
        raise ParameterError(f"{spec.path}: [model] rung 'ancf' does not support an [axial_amb] yet")
    W0, W1, T0, T1 = (float(speed), float(speed), 0.0, 0.0) if run_up is None else map(float, run_up)
    g = float(getattr(spec.model, "gravity", 0.0) or 0.0)
    dpn = model.rotor.dpn
    act, sens = np.asarray(model.act_dof), np.asarray(model.sens_dof)
    gop = model.gravity if g else None
    # linearised law f = f_op + kx (x - x_op) + ki (i - i_op): f_op (the AMB's share of the weight)
    # folded into the current offset, so the kernels are those of the unloaded law
    iop = model.i_op if gop is None else np.asarray(model.i_op) - gop.load / np.asarray(model.ki)
    ambs = dict(node=act // dpn, axis=act % dpn, kx=model.kx, ki=model.ki, iop=iop, xop=model.x_op,
                kc=model.force_constant, gap=model.gap, bias=model.bias, ref=np.zeros(len(act)),
                nonlinear=int(bool(nonlinear)), sens_node=sens // dpn, sens_axis=sens % dpn)
    drive = 0
    S, z = build(beams_of_spec(spec), discs=[(d.node, d.mass, d.polar_inertia, d.diametral_inertia) for d in spec.discs],
                 beta=spec.damping.stiffness_proportional, alpha=spec.damping.mass_proportional,
                 gravity=(0.0, -g, 0.0), spin=(drive, W0, W1, T0, T1), fixed=[(8 * drive + 2, spec.node_z[0])],
                 ambs=ambs, unbalances=[(u.node, u.magnitude, u.phase) for u in spec.unbalances],
                 z0=spec.node_z[0])
    if not np.allclose(z, spec.node_z, atol=1e-12):
        raise ParameterError(f"{spec.path}: node positions of the ancf mesh differ from the FE rotor's")
    if g and gop is None:
        raise ParameterError(f"{spec.path}: [model] gravity needs the model compiled at rung 'ancf' "
                             f"(its gravity operating point), got rung {model.rung!r}")
    return S, (straight_state(S, z) if gop is None else np.array(gop.q))


def fe_view(S: ANCFArrays, q) -> np.ndarray:
    """The ANCF state as FE node DOFs [x, y, phi_x, phi_y] per node (phi = slope of the axis)."""
    nn = S.nJ.shape[0]
    Q = q.reshape(nn, 8)
    w, x, y, z = Q[:, 4], Q[:, 5], Q[:, 6], Q[:, 7]
    tx, ty, tz = 2 * (x * z + w * y), 2 * (y * z - w * x), w * w - x * x - y * y + z * z
    out = np.zeros((nn, 4))
    out[:, 0], out[:, 1] = Q[:, 0], Q[:, 1]
    out[:, 2], out[:, 3] = tx / tz, ty / tz
    return out.ravel()
