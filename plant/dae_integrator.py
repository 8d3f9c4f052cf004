"""Fixed-step integrators of the index-3 DAE of the ANCF rung

    M(q) q'' + Q_v(q, q') - Q(q, q', t) + Phi_q^T lambda = 0,      Phi(q, t) = 0:

* ``bdf1`` (the paper's): ``q+ = q + h v+``, ``v+ = v + h a+``, equilibrium and constraints at t+;
* ``generalized-alpha``: Arnold & Bruls (2007) for index-3 DAEs (Chung-Hulbert parameters from
  the spectral radius ``rho_inf``; ``rho_inf = 1`` is the non-dissipative trapezoidal member),
  equilibrium and constraints at t+, the acceleration-like variable ``a`` carrying the
  alpha-weighting.

Both solve for ``x = [q+, mu]`` (``mu`` the multipliers scaled by the step) by Newton with a
sparse LU (SuperLU) of the exact Jacobian (``plant/ancf_jacobian.py``), kept across steps while
Newton converges fast and refreshed when it does not ("modified Newton"; the count of
refactorisations is reported).  The constraint residual after each step is monitored
(``max_drift``); non-convergence is reported like the linear rungs' (status code + one line).

Auxiliary bearings (``contact``, ``plant/ancf_contact.py``): their forces enter the residual at the
AMB nodes' x/y rows, their 2x2 Jacobians the step matrix; the matrix is refactorised whenever the set
of stations in contact differs from the one it was factorised with (an impact changes the Jacobian by
the contact stiffness: the old factorisation would contract too slowly), and the contact state
(``c``, (m, NC), the linear rungs' ``C_*``) is committed after each step.  :meth:`set_arrays` swaps the
AMB arrays between steps (a coil loss or a drop: the lost axes' coefficients zeroed).
"""
from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import ancf_contact as ac
from . import integrator as ig
from .ancf_jacobian import JacobianAssembler
from .ancf_model import ANCFArrays, n_constraints, speed_profile
from .ancf_residual import amb_force_value, residual

OK, NEWTON_FAIL, NONFINITE, TOUCHDOWN = 0, 1, 2, 3  # same codes as plant/integrator.py
SCHEMES = ("bdf1", "generalized-alpha")


def galpha(rho: float):
    """(alpha_m, alpha_f, beta, gamma) of Chung & Hulbert for the spectral radius rho_inf."""
    if not 0.0 <= rho <= 1.0:
        raise ValueError(f"rho_inf must be in [0, 1], got {rho:g}")
    am_ = (2 * rho - 1) / (rho + 1)
    af = rho / (rho + 1)
    g = 0.5 + af - am_
    return am_, af, 0.25 * (g + 0.5) ** 2, g


def constraint_curvature(S, v) -> np.ndarray:
    """gamma = v^T Phi_qq v of every constraint (all are scleronomic: the spin is in the base), so
    that Phi_q q'' = -gamma at the acceleration level."""
    nn = S.nJ.shape[0]
    V = v.reshape(nn, 8)
    g = [2.0 * np.sum(V[:, 4:8] ** 2, axis=1)]
    if S.spin[0] >= 0:
        w, x, y, z = V[int(S.spin[0]), 4:8]
        g.append(np.array([4.0 * (x * y + w * z)]))  # Phi = 2 (x y + w z)
    g.append(np.zeros(S.fix_idx.shape[0]))
    return np.concatenate(g)


class DAEIntegrator:
    def __init__(self, S: ANCFArrays, q0, v0, h: float, scheme: str = "bdf1", rho_inf: float = 0.8,
                 tol: float = 1e-10, maxit: int = 10, t0: float = 0.0, slow: float = 0.25, cur0=None,
                 contact: ac.ContactArrays | None = None):
        if scheme not in SCHEMES:
            raise ValueError(f"the ancf rung integrates with {' or '.join(SCHEMES)}, not {scheme!r}")
        if not (h > 0 and math.isfinite(h)):
            raise ValueError(f"plant step h must be > 0, got {h!r}")
        self.S, self.h, self.scheme = S, float(h), scheme
        self.rho_inf = float(rho_inf)
        self.tol, self.maxit, self.slow = float(tol), int(maxit), float(slow)
        self.n = q0.shape[0]
        self.nc = int(n_constraints(S))
        self.asm = JacobianAssembler(S)
        self.q = np.array(q0, dtype=float)
        self.v = np.array(v0, dtype=float)
        self.t = float(t0)
        self.mu = np.zeros(self.nc)
        self.R = np.zeros(self.n + self.nc)
        self.lu = None
        self.cur = np.zeros(max(1, S.amb_node.shape[0])) if cur0 is None else np.array(cur0, dtype=float)
        self.steps = 0
        self.newton_total = 0
        self.newton_max = 0
        self.refactorisations = 0
        self.max_drift = 0.0
        self.worst_gap = 0.0
        self.status = OK
        self.fail = None
        self.C = contact
        m = 0 if contact is None else contact.aux_p.shape[0]
        self.cs = ac.ContactState(S, contact, self.q) if m else None
        self.c = self.cs.c if m else np.zeros((0, ig.NC))  # the contact state (plant.integrator.C_*)
        self.jc = np.zeros((m, 2, 2))
        self._jpos = ac.jacobian_positions(self.asm.csc, contact) if m else None
        self._lu_mask = 0  # the stations in contact when the Jacobian was factorised
        if scheme == "generalized-alpha":
            self.am_, self.af, self.beta, self.gamma = galpha(self.rho_inf)
            self.qdd = self.consistent_acceleration(self.cur)  # (first call: with the operating-point currents)
            self.aa = self.qdd.copy()

    # ------------------------------------------------------------------ step coefficients
    def _coeffs(self):
        h, q, v = self.h, self.q, self.v
        if self.scheme == "bdf1":
            return -q / h, 1.0 / h, -q / (h * h) - v / h, 1.0 / (h * h), h * h, q + h * v
        am_, af, b, g = self.am_, self.af, self.beta, self.gamma
        base = (-q - h * v - h * h * (0.5 - b) * self.aa) / (h * h * b)  # a+ = base + q+/(h^2 b)
        ca = (1 - am_) / ((1 - af) * h * h * b)
        ah = ((1 - am_) * base + am_ * self.aa - af * self.qdd) / (1 - af)
        cv = g / (h * b)
        vh = v + h * (1 - g) * self.aa + h * g * base
        sd = h * h * b * (1 - af) / (1 - am_)
        pred = q + h * v + h * h * (0.5 - b) * self.aa + h * h * b * self.aa
        return vh, cv, ah, ca, sd, pred

    def consistent_acceleration(self, cur) -> np.ndarray:
        """q'' at the current state from M q'' + Phi_q^T lam = Q - Q_v, Phi_q q'' = -gamma."""
        n, nc = self.n, self.nc
        x = np.concatenate([self.q, np.zeros(nc)])
        z = np.zeros(n)
        J1 = self.asm.matrix(x, self.v, 0.0, -self.q, 1.0, self.t, cur, 1.0, 1.0)
        J0 = self.asm.matrix(x, self.v, 0.0, z, 0.0, self.t, cur, 1.0, 1.0)
        M = (J1 - J0).tocsc()[:n, :n]
        R = np.zeros(n + nc)
        residual(self.S, x, self.v, 0.0, z, 0.0, self.t, cur, 1.0, 1.0, R)
        self._contact(R, self.q, self.v, 0.0, self.t, 1.0)
        Phq = J0[n:, :n]
        gam = constraint_curvature(self.S, self.v)
        A = sp.bmat([[M, Phq.T], [Phq, None]]).tocsc()
        self.mass_lu = spla.splu(A, permc_spec="COLAMD", diag_pivot_thresh=0.1)
        sol = self.mass_lu.solve(np.concatenate([-R[:n], -gam]))
        return sol[:n]

    def _input_jump(self, cur):
        """Generalised-alpha with currents held over each period: q''_n was evaluated with the
        previous period's currents; move it to the right limit at t_n (the new currents), so the
        alpha-weighted acceleration history does not mix two periods' inputs (otherwise the
        currents act as if shifted by (alpha_f - alpha_m) h: a first-order error in the loop)."""
        S, n = self.S, self.n
        dF = np.zeros(n + self.nc)
        q = self.q
        for a in range(S.amb_node.shape[0]):
            k = 8 * S.amb_node[a] + S.amb_axis[a]
            xs = S.amb_xop[a] + q[k] - S.amb_ref[a]
            dF[k] = amb_force_value(S, a, xs, cur) - amb_force_value(S, a, xs, self.cur)
        if np.any(dF):
            self.qdd = self.qdd + self.mass_lu.solve(dF)[:n]

    def set_arrays(self, S: ANCFArrays) -> None:
        """Continue with the model arrays ``S`` (same shapes; a fault's AMB coefficients) from the
        next step.  Generalised-alpha moves its acceleration to the right limit of the force jump, as
        :meth:`_input_jump` does for the currents; the Jacobian is refactorised."""
        if self.scheme == "generalized-alpha":
            n = self.n
            dF = np.zeros(n + self.nc)
            for a in range(S.amb_node.shape[0]):
                k = 8 * S.amb_node[a] + S.amb_axis[a]
                xs = S.amb_xop[a] + self.q[k] - S.amb_ref[a]
                dF[k] += amb_force_value(S, a, xs, self.cur) - amb_force_value(self.S, a, xs, self.cur)
            if np.any(dF):
                self.qdd = self.qdd + self.mass_lu.solve(dF)[:n]
        self.S = S
        self.asm.S = S
        self.lu = None
        if self.cs is not None:
            self.cs.set_arrays(S)

    def _contact(self, R, q, v, cv, t, sd) -> int:
        """R -= sd F_c of the auxiliary bearings at (q, v, t); self.jc <- their Jacobian blocks;
        returns the mask of the stations in contact (0 without auxiliary bearings)."""
        if self._jpos is None:
            return 0
        W = speed_profile(self.S.spin, t)[1]
        return ac.add_contact(self.S, self.C, self.c, q, v, cv, W, self.h, sd, R, self.jc)

    # ------------------------------------------------------------------ one step
    def step(self, cur) -> int:
        h = self.h
        if self.scheme == "generalized-alpha" and not np.array_equal(cur, self.cur):
            self._input_jump(cur)
        self.cur = np.array(cur, dtype=float)
        tn = self.t + h
        vh, cv, ah, ca, sd, pred = self._coeffs()
        x = np.concatenate([pred, self.mu])
        R = self.R
        n = self.n
        prev = None
        ok = False
        it = 0
        limit = self.maxit
        while it < limit:
            it += 1
            self.worst_gap = residual(self.S, x, vh, cv, ah, ca, tn, cur, sd, 1.0, R)
            mask = self._contact(R, x[:n], vh + cv * x[:n], cv, tn, sd)
            if mask:  # an impact or a rolling contact: a few more iterations (as the linear rungs)
                limit = self.maxit + 20
            if self.lu is None or mask != self._lu_mask:
                self._factor(x, vh, cv, ah, ca, tn, cur, sd, mask)
            dx = self.lu.solve(-R)
            d = float(np.max(np.abs(dx[:n])))
            if not math.isfinite(d):
                break
            if prev is not None and d > self.slow * prev and d > self.tol:
                # slow contraction: refresh the Jacobian at this iterate and redo the correction
                self._factor(x, vh, cv, ah, ca, tn, cur, sd, mask)
                dx = self.lu.solve(-R)
                d = float(np.max(np.abs(dx[:n])))
            x += dx
            rate = d / prev if prev is not None and prev > 0 else 1.0
            prev = d
            # converged: the increment, or the error left after it (linear contraction estimate)
            if d <= self.tol or (rate < 0.9 and rate / (1.0 - rate) * d <= self.tol):
                ok = True
                break
        self.newton_total += it
        self.newton_max = max(self.newton_max, it)
        if not np.all(np.isfinite(x)):
            self._fault(NONFINITE, tn, it, float("inf"))
            return NONFINITE
        status = OK
        if not ok:
            self._fault(NEWTON_FAIL, tn, it, prev if prev is not None else float("nan"))
            status = NEWTON_FAIL
            self.lu = None
        qn = x[:n]
        vn = vh + cv * qn
        if self.scheme == "generalized-alpha":
            h2b = h * h * self.beta
            aa_new = (qn - self.q - h * self.v - h * h * (0.5 - self.beta) * self.aa) / h2b
            self.qdd = ah + ca * qn
            self.aa = aa_new
        self.q = qn.copy()
        self.v = vn
        self.mu = x[n:].copy()
        self.t = tn
        self.steps += 1
        if self._jpos is not None:
            self.cs.commit(self.q, self.v, tn, h)
        residual(self.S, x, vh, cv, ah, ca, tn, cur, sd, 1.0, R)
        self.max_drift = max(self.max_drift, float(np.max(np.abs(R[n:]))))
        if self.S.amb_nl[0] != 0 and self.worst_gap >= 1.0:
            self._fault(TOUCHDOWN, tn, it, self.worst_gap)
            return TOUCHDOWN
        return status

    def _factor(self, x, vh, cv, ah, ca, t, cur, sd, mask=0):
        A = self.asm.matrix(x, vh, cv, ah, ca, t, cur, sd, 1.0)
        if mask:  # the contact blocks of the stations in contact (self.jc: at this iterate)
            np.add.at(A.data, self._jpos.ravel(), self.jc.ravel())
        self._lu_mask = mask
        self.lu = spla.splu(A, permc_spec="COLAMD", diag_pivot_thresh=0.1)
        self.refactorisations += 1

    def _fault(self, code, t, it, res):
        if self.status == OK:
            self.status = code
            self.fail = (code, t, it, res)
        self.nfail = getattr(self, "nfail", 0) + 1

    @property
    def multipliers(self) -> np.ndarray:
        """Lagrange multipliers of the last step (unscaled)."""
        h = self.h
        sd = h * h if self.scheme == "bdf1" else h * h * self.beta * (1 - self.af) / (1 - self.am_)
        return self.mu / sd
