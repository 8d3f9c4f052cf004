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

The fixed point is found by splitting off the mean map ``Fm = sum_j p_j F_j``:
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


def ms_spectral_radius(js: JumpSystem, iters: int = 400, tol: float = 1e-10) -> float:
    """Spectral radius of ``P -> sum p_j F_j P F_j^T`` (< 1: mean-square stable).  Exact
    (Kronecker form) for small loops; for large ones by power iteration on positive
    semidefinite P (the operator is positive, so its dominant eigenvector is a PSD matrix)."""
    n = js.F[0].shape[0]
    if n <= 40:
        Kr = sum(pj * np.kron(Fj, Fj) for pj, Fj in zip(js.p, js.F) if pj > 0)
        return float(np.max(np.abs(np.linalg.eigvals(Kr))))
    P = np.eye(n) / n
    r_old = 0.0
    for k in range(iters):
        Q = js.second_moment_map(P)
        r = float(np.linalg.norm(Q, "fro") / max(np.linalg.norm(P, "fro"), 1e-300))
        P = Q / max(np.linalg.norm(Q, "fro"), 1e-300)
        if k > 10 and abs(r - r_old) < tol * max(r, 1e-12):
            break
        r_old = r
    return r


def stationary_covariance(js: JumpSystem, tol: float = 1e-10, max_iter: int = 500) -> np.ndarray:
    """``P = sum_j p_j (F_j P F_j^T + W_j)``; raises ValueError if the loop is not mean-square
    stable (no stationary covariance exists)."""
    Fm = js.mean_map
    if np.max(np.abs(np.linalg.eigvals(Fm))) >= 1.0:
        raise ValueError("the mean loop is unstable: no stationary covariance")
    Wm = sum(pj * Wj for pj, Wj in zip(js.p, js.W))
    deltas = [(pj, Fj - Fm) for pj, Fj in zip(js.p, js.F) if pj > 0]
    jitter = any(np.any(D != 0) for _, D in deltas)
    P = sla.solve_discrete_lyapunov(Fm, Wm)
    if not jitter:
        return P
    for _ in range(max_iter):
        Q = Wm + sum(pj * (D @ P @ D.T) for pj, D in deltas)
        P_new = sla.solve_discrete_lyapunov(Fm, Q)
        if not np.all(np.isfinite(P_new)):
            break
        if np.linalg.norm(P_new - P) <= tol * np.linalg.norm(P_new):
            return 0.5 * (P_new + P_new.T)
        P = P_new
    raise ValueError("the stationary covariance did not converge: the loop is not mean-square stable")


def worst_case_bound(js: JumpSystem, P: np.ndarray | None = None) -> tuple[float, float]:
    """Bounds on the joint spectral radius (the growth of the worst deterministic sequence of
    modes): ``(lower, upper)``.  Lower: the largest spectral radius of one mode repeated.
    Upper: ``max_j ||F_j||`` in the norm of the ellipsoid ``P`` (default: the mean-square
    Lyapunov solution); an upper bound below 1 means stable for *every* latency sequence."""
    lower = max(float(np.max(np.abs(np.linalg.eigvals(F)))) for F in js.F)
    if P is None:
        try:
            P = stationary_covariance(JumpSystem(js.F, js.p, tuple(np.eye(len(js.F[0])) for _ in js.F)))
        except ValueError:
            return lower, float("inf")
    Lc = np.linalg.cholesky(P + 1e-300 * np.eye(len(P)))
    Li = np.linalg.inv(Lc)
    upper = max(float(np.linalg.norm(Li @ F @ Lc, 2)) for F in js.F)
    return lower, upper
