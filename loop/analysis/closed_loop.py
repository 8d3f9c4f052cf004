"""Closed-loop state space of rotor + per-axis AMB loops (sensor lag, PID, amplifier lag).

Descriptor form ``E X' = A X`` with ``X = [eta; eta'; x_c]`` (rotor coordinates, their rates and
the controller states of every axis, ``n_c`` per axis):

    E = blkdiag(I, M, I)
    A = [[ 0,                        I,   0                 ],
         [ -(K_eff + Ba Ki Dh Cs),   -D,  -Ba Ki (I (x) Ch)  ],
         [ (I (x) Bh) Cs,             0,   I (x) Ah          ]]

with ``(Ah, Bh, Ch, Dh)`` the state space of the current law ``i = -H(s) y``, one per axis (SISO,
``n_c`` states each).  An na x na law (an LTI kind of ``[controller]`` that couples the axes,
controller/law_lti.py) enters whole: ``I (x) Ah`` -> ``Ah`` and so on, ``x_c`` its ``n_c`` states,
``Dh`` an na x na matrix.  An input matrix for
a disturbance added to the measured displacement (ISO 14839-3 sensitivity) is provided too.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from ambhil.controller.transfer import is_siso
from ..system import System


@dataclass(frozen=True)
class ClosedLoop:
    E: object
    A: object
    n: int  # rotor coordinates
    nc: int  # controller states per axis (SISO law), of the whole law (MIMO)
    Bd: object  # disturbance at the sensor signal of each axis -> state derivative (E X' = A X + Bd d)
    Cy: object  # measured displacement (without the disturbance) of each axis

    @property
    def size(self) -> int:
        return self.A.shape[0]

    def dense_standard(self) -> np.ndarray:
        """E^-1 A as a dense array (E is block diagonal with M in the middle)."""
        A = self.A.toarray() if sp.issparse(self.A) else np.array(self.A)
        M = self.E[self.n:2 * self.n, self.n:2 * self.n]
        M = M.toarray() if sp.issparse(M) else np.asarray(M)
        cf = sla.cho_factor(M)
        A[self.n:2 * self.n] = sla.cho_solve(cf, A[self.n:2 * self.n])
        return A


def build(model: System, speed: float, sparse: bool | None = None) -> ClosedLoop:
    sparse = model.sparse if sparse is None else sparse
    if not is_siso(model.H):
        return _build_mimo(model, speed, sparse)
    Ah, Bh, Ch, Dh = (np.atleast_2d(np.asarray(m, dtype=float)) for m in (model.H.A, model.H.B, model.H.C, model.H.D))
    nc = Ah.shape[0] if Ah.size else 0
    na, n = model.n_axes, model.n
    Ki = sp.diags(model.ki)
    Ia = sp.identity(na, format="csr")
    Ba, Cs = sp.csr_matrix(model.Ba), sp.csr_matrix(model.Cs)
    K = sp.csr_matrix(model.K_eff) + Ba @ Ki @ (Dh[0, 0] * Cs)
    D = sp.csr_matrix(model.D(speed))
    M = sp.csr_matrix(model.M)
    I = sp.identity(n, format="csr")
    Z = lambda r, c: sp.csr_matrix((r, c))
    if nc:
        AC = sp.kron(Ia, sp.csr_matrix(Ah)); BC = sp.kron(Ia, sp.csr_matrix(Bh)); CC = sp.kron(Ia, sp.csr_matrix(Ch))
        A = sp.bmat([[Z(n, n), I, Z(n, na * nc)],
                     [-K, -D, -(Ba @ Ki @ CC)],
                     [BC @ Cs, Z(na * nc, n), AC]], format="csc")
        Bd = sp.vstack([Z(n, na), -(Ba @ Ki * Dh[0, 0]), BC], format="csc")
    else:
        A = sp.bmat([[Z(n, n), I], [-K, -D]], format="csc")
        Bd = sp.vstack([Z(n, na), -(Ba @ Ki * Dh[0, 0])], format="csc")
    E = sp.block_diag([I, M, sp.identity(na * nc)], format="csc")
    Cy = sp.hstack([Cs, Z(na, n + na * nc)], format="csr")
    if not sparse:
        A, E, Bd, Cy = A.toarray(), E.toarray(), Bd.toarray(), Cy.toarray()
    return ClosedLoop(E=E, A=A, n=n, nc=nc, Bd=Bd, Cy=Cy)


def _build_mimo(model: System, speed: float, sparse: bool) -> ClosedLoop:
    """The closed loop with an na x na current law (its states once, not per axis)."""
    Ah, Bh, Ch, Dh = (np.asarray(m, dtype=float) for m in (model.H.A, model.H.B, model.H.C, model.H.D))
    na, n = model.n_axes, model.n
    nc = Ah.shape[0] if Ah.size else 0
    if Dh.shape != (na, na):
        raise ValueError(f"the current law is {Dh.shape[0]} x {Dh.shape[1]}, the loop has {na} axes")
    Ki = sp.diags(model.ki)
    Ba, Cs = sp.csr_matrix(model.Ba), sp.csr_matrix(model.Cs)
    BK = Ba @ Ki
    K = sp.csr_matrix(model.K_eff) + BK @ sp.csr_matrix(Dh) @ Cs
    D = sp.csr_matrix(model.D(speed))
    I = sp.identity(n, format="csr")
    Z = lambda r, c: sp.csr_matrix((r, c))
    if nc:
        Ah, Bh, Ch = (sp.csr_matrix(Ah.reshape(nc, nc)), sp.csr_matrix(Bh.reshape(nc, na)),
                      sp.csr_matrix(Ch.reshape(na, nc)))
        A = sp.bmat([[Z(n, n), I, Z(n, nc)], [-K, -D, -(BK @ Ch)], [Bh @ Cs, Z(nc, n), Ah]], format="csc")
        Bd = sp.vstack([Z(n, na), -(BK @ sp.csr_matrix(Dh)), Bh], format="csc")
    else:
        A = sp.bmat([[Z(n, n), I], [-K, -D]], format="csc")
        Bd = sp.vstack([Z(n, na), -(BK @ sp.csr_matrix(Dh))], format="csc")
    E = sp.block_diag([I, sp.csr_matrix(model.M), sp.identity(nc)], format="csc")
    Cy = sp.hstack([Cs, Z(na, n + nc)], format="csr")
    if not sparse:
        A, E, Bd, Cy = A.toarray(), E.toarray(), Bd.toarray(), Cy.toarray()
    return ClosedLoop(E=E, A=A, n=n, nc=nc, Bd=Bd, Cy=Cy)
