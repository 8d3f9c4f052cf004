"""Compile the plant's parameters into an immutable model: matrices, operators and parameters of one rung.

The model is the MuJoCo-style split's "model": analyses and the step function only read it.
It is immutable: a frozen dataclass whose arrays (its FE rotor's included) are read-only, so an
accidental write raises; nothing is cached in it but :attr:`Model.dense` (derived from it).  What
a computation keeps between calls lives with the caller: the integrator's factorisation in the
plant's state or runner (``plant/step.py``), the loop layer's sampled loops in a cache of its own.

Generalised coordinates ``eta`` are the full FE DOFs (rung ``full``), Craig-Bampton coordinates
(``modal``) or rigid-body coordinates (``rigid``); ``q = T eta`` maps back to the FE DOFs.

Per AMB axis ``j`` (x and y of every radial AMB, then z of the axial AMB, if any):

    f_j = k_x,j * (Ca eta)_j + k_i,j * i_j        (linearised force at the actuator node)
    y_j = (Cs eta)_j                               (displacement at the sensor node)

so the linear plant is ``M eta'' + (C + Omega G) eta' + K_eff eta = Ba diag(k_i) i + f_ext`` with
``K_eff = K - Ba diag(k_x) Ca``.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from . import magnetic_bearing as mb
from . import reduction
from .rotor import FERotor, X, Y, Z, assemble
from .params import ParameterError, PlantSpec


def _ro(a):
    """Freeze an array (or a sparse matrix's arrays) so a compiled model cannot be modified."""
    if isinstance(a, np.ndarray):
        a.setflags(write=False)
    elif sp.issparse(a):
        for arr in (a.data, getattr(a, "indices", None), getattr(a, "indptr", None)):
            if arr is not None:
                arr.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Model:
    spec: PlantSpec
    rotor: FERotor
    rung: str
    T: np.ndarray | None  # basis, FE DOFs x generalised coordinates (None: identity)
    M: object  # dense ndarray (reduced rungs) or scipy.sparse csc (full rung)
    C: object
    G: object
    K: object
    axes: tuple[tuple[str, str], ...]  # (AMB name, 'x'|'y'|'z') per axis
    act_dof: np.ndarray  # FE DOF of each axis' actuator
    sens_dof: np.ndarray  # FE DOF of each axis' sensor
    Ba: object  # n x n_axes force distribution
    Ca: object  # n_axes x n actuator displacement
    Cs: object  # n_axes x n sensor displacement
    force_constant: np.ndarray  # k per axis
    gap: np.ndarray
    bias: np.ndarray
    offset: np.ndarray  # stator offset per axis (misalignment)
    x_op: np.ndarray  # rotor displacement relative to the stator at the operating point
    i_op: np.ndarray  # control current at the operating point
    kx: np.ndarray
    ki: np.ndarray
    K_eff: object
    unb_dof: np.ndarray  # FE DOF of x for each unbalance (y = +1)
    unb_me: np.ndarray  # magnitude kg m
    unb_phase: np.ndarray
    # the static equilibrium under [model] gravity on the ancf rung (None otherwise; the linear
    # rungs' is only ``load``, plant/linear_statics.py): an operating-point result of
    # compile_model, read by plant/ancf_model.from_model
    gravity: GravityOperatingPoint | None = None
    # s, the input period: the plant holds its coil currents over one period and returns the
    # sensor readings at its end (the controller's, given to compile_model; None: not given)
    period: float | None = None
    # N per axis: the force each AMB axis exerts on the rotor at the operating point (its share of
    # the weight under [model] gravity; None: zeros).  The nonlinear force law's remainder is taken
    # about it (plant/integrator._add_nonlinear).
    load: np.ndarray | None = None
    # N per axis: a constant force on the rotor at each axis' actuator DOF, in the deviation
    # coordinates about the operating point (None: zeros): -load on an axis whose coils are lost
    # (plant/faults.model_without_axes), the weight share that AMB no longer carries
    f_const: np.ndarray | None = None

    @property
    def loads(self) -> np.ndarray:
        """``load`` as an array (zeros when not set)."""
        return np.zeros(self.n_axes) if self.load is None else np.asarray(self.load, float)

    @property
    def constant_forces(self) -> np.ndarray:
        """``f_const`` as an array (zeros when not set)."""
        return np.zeros(self.n_axes) if self.f_const is None else np.asarray(self.f_const, float)

    @property
    def n(self) -> int:
        return self.M.shape[0]

    @property
    def n_axes(self) -> int:
        return len(self.axes)

    @property
    def sparse(self) -> bool:
        return sp.issparse(self.M)

    def D(self, speed: float):
        """Velocity matrix C + Omega G at spin speed Omega (rad/s)."""
        return self.C + speed * self.G

    def node_rows(self, nodes, axes=(X, Y)) -> np.ndarray:
        """Output matrix (len(nodes)*len(axes) x n) of the displacements of FE nodes."""
        dofs = [self.rotor.dof(k, a) for k in nodes for a in axes]
        return self.fe_rows(dofs)

    def fe_rows(self, dofs) -> np.ndarray:
        if self.T is None:
            R = np.zeros((len(dofs), self.n))
            R[np.arange(len(dofs)), dofs] = 1.0
            return R
        return self.T[np.asarray(dofs)]

    def unbalance_forces(self, speed: float) -> np.ndarray:
        """Complex force amplitudes in generalised coordinates at spin speed Omega:
        x: m e Omega^2 e^{i phi}, y: -i m e Omega^2 e^{i phi} (forward, as Re(F e^{i Omega t}))."""
        if len(self.unb_dof) == 0:
            return np.zeros(self.n, dtype=complex)
        a = self.unb_me * speed**2 * np.exp(1j * self.unb_phase)
        dofs = np.concatenate([self.unb_dof, self.unb_dof + 1])
        amp = np.concatenate([a, -1j * a])
        return self.fe_rows(dofs).T @ amp

    @cached_property
    def dense(self) -> tuple[np.ndarray, ...]:
        """(M, C, G, K_eff, Ba, Ca, Cs) as dense arrays."""
        f = lambda A: A.toarray() if sp.issparse(A) else np.asarray(A)
        return tuple(_ro(f(A)) for A in (self.M, self.C, self.G, self.K_eff, self.Ba, self.Ca, self.Cs))


def bearing_axes(spec: PlantSpec):
    """One tuple per AMB axis, in the order of every per-axis vector (x, y of each radial AMB,
    then z of the axial AMB): ((AMB name, axis letter), actuator node, sensor node, axis DOF,
    force constant, gap, bias current, stator offset)."""
    out = []
    for a in spec.ambs:
        for ax, e in ((X, a.misalignment[0]), (Y, a.misalignment[1])):
            out.append(((a.name, "xy"[ax]), a.node, a.sensor_node, ax, a.force_constant, a.gap, a.bias_current, e))
    if spec.axial_amb is not None:
        z = spec.axial_amb
        out.append(((z.name, "z"), z.node, z.node, Z, z.force_constant, z.gap, z.bias_current, 0.0))
    return out


def operating_currents(spec: PlantSpec, rung: str | None = None) -> np.ndarray:
    """Control current of every AMB axis at the operating point: what the loop must deliver at
    zero displacement to hold a misaligned bearing (no model compilation needed), and under
    ``[model] gravity`` its share of the rotor's weight: on the ancf rung (the scene's, or
    ``rung``) from its statics (:func:`gravity_operating_point`), on the linear rungs from the FE
    rotor's (:func:`ambhil.plant.linear_statics.gravity_loads`)."""
    if spec.model.gravity:
        if (rung or spec.model.rung) == "ancf":
            return gravity_operating_point(spec)[3]
        from .linear_statics import gravity_loads
        return np.array([o.i for o in loaded_operating_points(spec, gravity_loads(spec, assemble(spec)))])
    return np.array([mb.operating_point(k, s0, i0, e).i for *_, k, s0, i0, e in bearing_axes(spec)])


def loaded_operating_points(spec: PlantSpec, load) -> list:
    """The operating point (:func:`ambhil.plant.magnetic_bearing.loaded_operating_point`) of every
    AMB axis carrying ``load`` (N per axis, bearing_axes order); a share the bias current cannot
    carry is a ParameterError naming the AMB, the axis, the gravity and the load."""
    ops = []
    for (name, *_, k, s0, i0, e), f in zip(bearing_axes(spec), load):
        try:
            ops.append(mb.loaded_operating_point(k, s0, i0, e, float(f)))
        except ValueError as err:
            raise ParameterError(f"{spec.path}: AMB {name[0]} {name[1]}: under [model] gravity = "
                                 f"{spec.model.gravity:g} m/s^2 it carries {f:.4g} N of the rotor's weight: {err}") from None
    return ops


def compile_model(spec: PlantSpec, rung: str | None = None, rotor: FERotor | None = None,
                  period: float | None = None) -> Model:
    """Compile the plant's parameters at their rung, or at ``rung``.  ``rotor``: an FE rotor
    already assembled from these very parameters (e.g. ``other_model.rotor``), reused as is.
    ``period``: the input period (s), the controller's sample period (the modal rung's default
    cutoff follows it; a step object holds the currents over it)."""
    rung = rung or spec.model.rung
    rotor = rotor if rotor is not None else assemble(spec)
    for a in (rotor.node_z, rotor.M, rotor.K, rotor.G, rotor.C):  # part of the model: read-only too
        _ro(a)
    dpn = rotor.dpn

    axes, act, sens, kconst, gap, bias, off = [], [], [], [], [], [], []
    for ax_name, node, sensor_node, axis, k, s0, i0, e in bearing_axes(spec):
        axes.append(ax_name)
        act.append(node * dpn + axis)
        sens.append(sensor_node * dpn + axis)
        kconst.append(k); gap.append(s0); bias.append(i0); off.append(e)
    act, sens = np.array(act), np.array(sens)
    kconst, gap, bias, off = map(np.array, (kconst, gap, bias, off))
    ops = [mb.operating_point(k, s0, i0, e) for k, s0, i0, e in zip(kconst, gap, bias, off)]
    kx = np.array([o.kx for o in ops]); ki = np.array([o.ki for o in ops])
    x_op = np.array([o.x for o in ops]); i_op = np.array([o.i for o in ops])
    gravity = load = None
    if rung == "ancf" and spec.model.gravity:
        kx, ki, x_op, i_op, gravity = gravity_operating_point(spec)
        load = gravity.load
    elif spec.model.gravity:  # the linear rungs: the FE rotor's reactions with the AMB nodes held
        from .linear_statics import gravity_loads
        load = _ro(gravity_loads(spec, rotor))
        ops = loaded_operating_points(spec, load)
        kx, ki, x_op, i_op = (_ro(np.array([getattr(o, a) for o in ops])) for a in ("kx", "ki", "x", "i"))

    na = len(axes)
    if rung in ("full", "ancf"):
        # ancf: the nonlinear multibody model is built by plant/ancf_model.from_model when it is
        # integrated; the matrices here (the full FE rung's) are its small-motion linearisation
        # for the linear analyses (docs/ancf.md)
        T = None
        M, C, G, K = rotor.M, rotor.C, rotor.G, rotor.K
        n = rotor.ndof
        Ba = sp.csc_matrix((np.ones(na), (act, np.arange(na))), shape=(n, na))
        Ca = Ba.T.tocsr()
        Cs = sp.csr_matrix((np.ones(na), (np.arange(na), sens)), shape=(na, n))
        K_eff = (K - Ba @ sp.diags(kx) @ Ca).tocsc()
        M, C, G, K, K_eff, Ba, Ca, Cs = (_ro(A.copy()) for A in (M, C, G, K, K_eff, Ba, Ca, Cs))
    else:
        if rung == "rigid":
            T = reduction.rigid(rotor)
        elif rung == "modal":
            cutoff = spec.model.modal_cutoff
            if cutoff is None:
                if period is None:
                    raise ParameterError(f"{spec.path}: the modal rung needs [model] modal_cutoff or the input period")
                cutoff = reduction.default_cutoff(1.0 / period)
            T = reduction.craig_bampton(rotor, np.concatenate([act, sens]), cutoff)
        else:
            raise ValueError(f"unknown model rung {rung!r} (rigid, modal, full, ancf)")
        proj = lambda A: _ro(np.asarray(T.T @ (A @ T)))
        M, C, G, K = proj(rotor.M), proj(rotor.C), proj(rotor.G), proj(rotor.K)
        if rung == "rigid":
            K = _ro(np.zeros_like(M))
            C = _ro(spec.damping.mass_proportional * M)
        Ca = _ro(T[act].copy()); Cs = _ro(T[sens].copy()); Ba = _ro(Ca.T.copy())
        K_eff = _ro(K - Ba @ np.diag(kx) @ Ca)

    unb_dof = np.array([u.node * dpn + X for u in spec.unbalances], dtype=int)
    return Model(spec=spec, rotor=rotor, rung=rung, T=_ro(T) if T is not None else None,
                 M=M, C=C, G=G, K=K, axes=tuple(axes), act_dof=_ro(act), sens_dof=_ro(sens), Ba=Ba, Ca=Ca, Cs=Cs,
                 force_constant=_ro(kconst), gap=_ro(gap), bias=_ro(bias), offset=_ro(off), x_op=_ro(x_op),
                 i_op=_ro(i_op), kx=_ro(kx), ki=_ro(ki), K_eff=K_eff, unb_dof=_ro(unb_dof),
                 unb_me=_ro(np.array([u.magnitude for u in spec.unbalances])),
                 unb_phase=_ro(np.array([u.phase for u in spec.unbalances])), gravity=gravity,
                 period=None if period is None else float(period), load=load)


@dataclass(frozen=True)
class GravityOperatingPoint:
    """The static equilibrium under ``[model] gravity`` on the ancf rung (docs/ancf.md section 2.1):
    the rotor held at zero displacement at the AMBs, each AMB axis carrying ``load`` (N, its
    compatibility share of the weight) with the control current ``i_op`` of the exact force law."""
    load: np.ndarray  # force of each AMB axis on the rotor at the operating point (N)
    q: np.ndarray  # the sagged ANCF configuration (plant/ancf_model.py coordinates)
    weight: float  # the rotor's weight (shaft + discs), N


def gravity_operating_point(spec: PlantSpec):
    """Operating point of every AMB axis when the AMBs carry the rotor's weight (ancf rung):
    the AMB loads from the ANCF statics with the AMB nodes held (plant/ancf_statics.gravity_statics),
    the currents that give them (exact force law at the misalignment position x_op) and the exact
    derivatives there.  Returns (kx, ki, x_op, i_op, GravityOperatingPoint)."""
    from . import ancf_statics
    load, q = ancf_statics.gravity_statics(spec)
    ops = loaded_operating_points(spec, load)
    weight = float(spec.model.gravity) * (sum(s.density * np.pi / 4 * (s.outer_diameter**2 - s.inner_diameter**2) * s.length
                                              for s in spec.sections) + sum(d.mass for d in spec.discs))
    gop = GravityOperatingPoint(load=_ro(np.asarray(load, float)), q=_ro(np.asarray(q, float)), weight=weight)
    arr = lambda k: _ro(np.array([getattr(o, k) for o in ops]))
    return arr("kx"), arr("ki"), arr("x"), arr("i"), gop
