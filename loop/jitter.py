"""Jitter and lost updates as a Markov jump linear system (the Jitterbug method).

Each period the loop takes one of a finite set of timing modes (a latency value of a histogram,
or a lost update) independently with probabilities ``p_j``: ``z_{k+1} = F_j z_k + w_k``.
With ``W_j`` the covariance of the noise entering in mode j, the second moment
``P_k = E[z_k z_k^T]`` obeys ``P_{k+1} = sum_j p_j (F_j P_k F_j^T + W_j)``, so

- the loop is mean-square stable iff the spectral radius of the operator
  ``P -> sum_j p_j F_j P F_j^T`` (in Kronecker form ``sum_j p_j F_j (x) F_j``) is below 1
  (Costa, Fragoso & Marques, *Discrete-Time Markov Jump Linear Systems*, 2005), and
- the stationary covariance is the fixed point ``P = sum_j p_j (F_j P F_j^T + W_j)``
  (Lincoln & Cervin, "Jitterbug", CDC 2002).

Both are decided without the n^2 x n^2 Kronecker matrix (too large for a flexible rotor) by
splitting off the mean map ``Fm = sum_j p_j F_j``:
``P = Fm P Fm^T + sum_j p_j (Delta_j P Delta_j^T + W_j)`` with ``Delta_j = F_j - Fm``; each
iteration is one discrete Lyapunov solve, and without jitter it is exactly one (the ordinary
discrete Lyapunov equation).  Convergence is geometric with the ratio of the jitter part.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla


@dataclass(frozen=True)
class JumpSystem:
    F: tuple[np.ndarray, ...]  # one loop map per timing mode
    p: np.ndarray  # probabilities (sum 1)
    W: tuple[np.ndarray, ...]  # noise covariance entering per mode

    def __post_init__(self):
        p = np.asarray(self.p, float)
        if len(p) != len(self.F) or len(self.W) != len(self.F):
            raise ValueError("one probability and one noise covariance per mode")
        if np.any(p < 0) or abs(p.sum() - 1.0) > 1e-9:
            raise ValueError(f"mode probabilities must be >= 0 and sum to 1, got {p}")

    @property
    def mean_map(self) -> np.ndarray:
        return sum(pj * Fj for pj, Fj in zip(self.p, self.F))

    def second_moment_map(self, P: np.ndarray) -> np.ndarray:
        return sum(pj * (Fj @ P @ Fj.T) for pj, Fj in zip(self.p, self.F) if pj > 0)


def ms_spectral_radius(js: JumpSystem) -> float:
    """Spectral radius of ``P -> sum p_j F_j P F_j^T`` from its Kronecker form ``sum p_j F_j (x)
    F_j`` (n^2 x n^2, dense): exact, for small loops (n <= 40) and as the reference in tests."""
    n = js.F[0].shape[0]
    if n > 40:
        raise ValueError(f"the Kronecker form of a {n}-state loop is too large; use ms_test")
    Kr = sum(pj * np.kron(Fj, Fj) for pj, Fj in zip(js.p, js.F) if pj > 0)
    return float(np.max(np.abs(np.linalg.eigvals(Kr))))


@dataclass(frozen=True)
class MeanSquare:
    stable: bool
    mean_radius: float  # spectral radius of the mean map sum p_j F_j
    jitter_ratio: float  # Perron root of P -> Lyap(Fm, sum p_j D_j P D_j^T); stable iff < 1 (and mean < 1)


def _splitting(js: JumpSystem, W: np.ndarray, tol: float, max_iter: int):
    """Iterate ``P <- Lyap(Fm, W + sum p_j D_j P D_j^T)`` from ``Lyap(Fm, W)``; returns (P, ratio,
    converged).  The ratio of successive increments is the Perron root of the jitter operator."""
    Fm = js.mean_map
    # in balanced coordinates (z = S z', S diagonal, powers of 2: exact): the states of a loop
    # differ by 1e10 in scale (metres, amperes, controller states), and unbalanced the Lyapunov
    # solver leaves a residual of 5 % on the full rung (1 % in the displacement std)
    _, (sc, _) = sla.matrix_balance(Fm, permute=False, separate=True)
    r = 1.0 / sc
    Fm = r[:, None] * Fm * sc[None, :]
    W = r[:, None] * W * r[None, :]
    deltas = [(pj, r[:, None] * Fj * sc[None, :] - Fm) for pj, Fj in zip(js.p, js.F) if pj > 0]
    deltas = [(pj, D) for pj, D in deltas if np.any(D != 0)]
    P = sla.solve_discrete_lyapunov(Fm, W)

    def back(P):
        return sc[:, None] * P * sc[None, :]
    if not deltas:
        return back(P), 0.0, True
    dP, ratio = P, 0.0
    for k in range(max_iter):
        step = sla.solve_discrete_lyapunov(Fm, sum(pj * (D @ dP @ D.T) for pj, D in deltas))
        ratio = float(np.trace(step) / max(np.trace(dP), 1e-300))
        P, dP = P + step, step
        if not np.all(np.isfinite(P)) or ratio >= 1.0 and k > 5:
            return back(P), ratio, False
        if np.trace(step) <= tol * np.trace(P):
            return back(0.5 * (P + P.T)), ratio, True
    return back(P), ratio, ratio < 1.0


def ms_test(js: JumpSystem, tol: float = 1e-10, max_iter: int = 2000) -> MeanSquare:
    """Mean-square stability without the n^2 x n^2 matrix: with ``Fm = sum p_j F_j`` and
    ``D_j = F_j - Fm`` the second-moment operator splits into ``L_Fm + L_D`` (both positive),
    and ``rho(L_Fm + L_D) < 1`` iff ``rho(Fm) < 1`` and ``rho((I - L_Fm)^-1 L_D) < 1``; the
    latter is the convergence ratio of the splitting iteration."""
    rm = float(np.max(np.abs(np.linalg.eigvals(js.mean_map))))
    if rm >= 1.0:
        return MeanSquare(False, rm, float("inf"))
    n = js.F[0].shape[0]
    _, ratio, ok = _splitting(js, np.eye(n), tol, max_iter)
    return MeanSquare(ok and ratio < 1.0, rm, ratio)


def stationary_covariance(js: JumpSystem, tol: float = 1e-10, max_iter: int = 2000) -> np.ndarray:
    """``P = sum_j p_j (F_j P F_j^T + W_j)``; raises ValueError if the loop is not mean-square
    stable (no stationary covariance exists)."""
    if np.max(np.abs(np.linalg.eigvals(js.mean_map))) >= 1.0:
        raise ValueError("the mean loop is unstable: no stationary covariance")
    Wm = sum(pj * Wj for pj, Wj in zip(js.p, js.W))
    P, _, ok = _splitting(js, Wm, tol, max_iter)
    if not ok:
        raise ValueError("the stationary covariance did not converge: the loop is not mean-square stable")
    return P


def worst_case_bound(js: JumpSystem, P: np.ndarray | None = None) -> tuple[float, float]:
    """Bounds on the joint spectral radius (the growth of the worst deterministic sequence of
    modes): ``(lower, upper)``.  Lower: the largest spectral radius of one mode repeated.
    Upper: ``max_j ||F_j||`` in the norm of the ellipsoid ``P`` (default: the mean-square
    Lyapunov solution); an upper bound below 1 means stable for *every* latency sequence."""
    lower = max(float(np.max(np.abs(np.linalg.eigvals(F)))) for F in js.F)
    Fs = js.F
    if P is None:  # any ellipsoid gives a bound; this one in balanced coordinates (as _splitting),
        # where P = sum_j p_j F_j P F_j^T + I has eigenvalues >= 1 (unbalanced, the states' 1e10
        # spread of scales puts P beyond eigh's reach: a "bound" of 381 on the full rung)
        _, (sc, _) = sla.matrix_balance(js.mean_map, permute=False, separate=True)
        Fs = tuple((1.0 / sc)[:, None] * F * sc[None, :] for F in js.F)
        try:
            P = stationary_covariance(JumpSystem(Fs, js.p, tuple(np.eye(len(F)) for F in Fs)))
        except ValueError:
            return lower, float("inf")
    lam, Q = np.linalg.eigh(0.5 * (P + P.T))  # P = Lc Lc^T, robust to the states' disparate scales
    lam = np.maximum(lam, 1e-14 * lam.max())
    Lc, Li = Q * np.sqrt(lam), (Q / np.sqrt(lam)).T
    upper = max(float(np.linalg.norm(Li @ F @ Lc, 2)) for F in Fs)
    return lower, upper
