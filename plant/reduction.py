"""Model-order reduction of the FE rotor: the bases behind the rigid and modal rungs.

* rigid: the rigid-body shapes about the centre of gravity (4 lateral DOF, +1 axial).  The
  reduced mass, polar inertia and gyroscopic matrix are exact projections of the FE model; the
  elastic stiffness is zero by definition of the rung.
* modal: Craig-Bampton.  The boundary DOFs (translations at every AMB actuator and sensor node,
  plus the axial AMB) stay physical, so bearing forces and sensor outputs are exact at DC and
  for every retained frequency; the interior is represented by fixed-interface modes up to a
  frequency cutoff.  ``q = T [q_b; eta]``, ``T = [[I, 0], [Psi, Phi]]``, ``Psi = -K_ii^-1 K_ib``.

Cutoff (issue 15).  Damping and gyroscopics are projected exactly (Rayleigh damping
``T^T (a M + b K) T = a M_r + b K_r``), and the boundary keeps the AMB input/output exact, so
what the modal rung loses is truncation: a system mode converges only when fixed-interface
modes well above it are kept.  A sampled AMB loop is decided by lightly damped flexible modes
near 1 kHz whose growth rate is a small difference (AMB negative damping from the sampling and
lag phase minus structural damping), so it needs far more than the mode's frequency: with the
former 2 kHz cutoff the 1.26 kHz mode of paper_3amb sat at 1.41 kHz and the modal rung reported
the stable 10 kHz loop unstable; the 0.80 kHz mode of rotor62_3amb grew 47 % too fast.  The
default (:func:`default_cutoff`) keeps modes up to the controller's sample rate (twice the
Nyquist frequency), and at least 10 kHz; measured errors of that mode's growth/decay rate
against the full rung: <= 1.7 % at 5, 10 and 20 kHz on paper_2amb, paper_3amb, rotor62_3amb
(docs/time_domain.md section 10).  That cutoff serves the time-domain loop; a frequency-domain
analysis that reduces the rotor only to find its answer (the seeds of the full rung's critical
speeds) takes its cutoff from the analysed frequency range instead (:func:`analysis_cutoff`), so its
cost does not grow with the controller's sample rate.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from .rotor import FERotor, rigid_basis


#: lower bound of the default cutoff, Hz
MIN_DEFAULT_CUTOFF = 10_000.0


def default_cutoff(sample_rate: float | None) -> float:
    """Default Craig-Bampton cutoff (Hz) for a loop sampled at ``sample_rate`` (Hz): the sample
    rate itself (twice the Nyquist frequency), at least MIN_DEFAULT_CUTOFF."""
    return max(MIN_DEFAULT_CUTOFF, float(sample_rate or 0.0))


#: Craig-Bampton cutoff of a frequency-domain analysis over the ratio of its highest frequency
ANALYSIS_CUTOFF_RATIO = 10.0


def analysis_cutoff(f_max_hz: float) -> float:
    """Craig-Bampton cutoff (Hz) of a reduction that serves a frequency-domain analysis up to
    ``f_max_hz`` (e.g. the seed model of the full rung's critical speeds): ANALYSIS_CUTOFF_RATIO
    times that frequency, whatever the controller's sample rate.  With the boundary DOFs physical,
    the closed-loop modes in the band then sit within about 3e-5 (relative) of the full rung's
    (rotor62_3amb, band 700 Hz, cutoff 7 kHz), close enough to seed a refinement on the full rung."""
    if not f_max_hz > 0:
        raise ValueError(f"analysis_cutoff: the highest analysed frequency must be > 0 Hz, not {f_max_hz!r}")
    return ANALYSIS_CUTOFF_RATIO * float(f_max_hz)


def craig_bampton(rotor: FERotor, boundary: np.ndarray, cutoff_hz: float) -> np.ndarray:
    n = rotor.ndof
    b = np.asarray(sorted(set(int(i) for i in boundary)))
    i = np.setdiff1d(np.arange(n), b)
    K, M = rotor.K, rotor.M
    Kii = K[i][:, i].tocsc()
    Kib = K[i][:, b].toarray()
    lu = spla.splu(Kii)
    Psi = -lu.solve(Kib)
    w2max = (2 * np.pi * cutoff_hz) ** 2
    w2, Phi = sla.eigh(Kii.toarray(), M[i][:, i].toarray(), subset_by_value=(-np.inf, w2max))
    T = np.zeros((n, len(b) + Phi.shape[1]))
    T[b, : len(b)] = np.eye(len(b))
    T[np.ix_(i, np.arange(len(b)))] = Psi
    T[np.ix_(i, np.arange(len(b), T.shape[1]))] = Phi
    return T


def rigid(rotor: FERotor) -> np.ndarray:
    return rigid_basis(rotor)
