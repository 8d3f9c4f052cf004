"""The layout of the plant kernels' arrays: the plan (:class:`PlantArrays`, built by
:mod:`ambhil.plant.plan`), its integer and float parameters (``I_*``, ``F_*``), the scalar workspace
(``W_*``), the status codes, and the auxiliary bearings' part of the state vector (``C_*``).  The
kernels (:mod:`ambhil.plant.integrator`, :mod:`ambhil.plant.contact_kernels`) and everything that
reads their arrays share these names; :mod:`ambhil.plant.integrator` re-exports them."""
from __future__ import annotations

from collections import namedtuple

SCHEMES = ("bdf1", "bdf2", "trapezoidal", "generalized-alpha", "zoh")
BDF1, BDF2, TRAP, GALPHA, ZOH = range(5)
ORDER = {"bdf1": 1, "bdf2": 2, "trapezoidal": 2, "generalized-alpha": 2, "zoh": None}

# status codes written to the workspace scalars
OK, NEWTON_FAIL, NONFINITE, TOUCHDOWN = 0, 1, 2, 3
STATUS_TEXT = {OK: "ok", NEWTON_FAIL: "Newton did not converge", NONFINITE: "state is not finite (blow-up)",
               TOUCHDOWN: "rotor reached the stator (|x| >= gap)"}

# scalar workspace layout (float64 array `ws`)
W_OMEGA_F, W_STATUS, W_FAIL_T, W_FAIL_IT, W_FAIL_RES, W_FAIL_AX, W_NFAIL, W_MAXIT, W_NREFAC, W_LEN = range(10)

PlantArrays = namedtuple("PlantArrays", [
    "ip",  # int64: scheme, n, na, bw, nonlinear, runup, maxit, dense, ns
    "fp",  # float64: h, beta_h, omega, am, af, gamma, czd, tol, refac_tol, W0, W1, T0, T1, Omega_nominal
    "Mb", "Cb", "Gb", "Kb", "Db",  # row-band storage (Db = C + W0 G) (n, 2bw+1): A[i, j] = Ab[i, j - i + bw]
    "Sb",  # S at the factorisation speed (unfactorised, row-band)
    "LU",  # banded LU of S (in place of S; L unit lower)
    "LU1",  # bdf2: LU of the trapezoidal (re)start step matrix; generalized-alpha: LU of M
    "ki", "kx", "iop", "xop", "kc", "gap", "bias",
    "Ur", "Ui",  # unbalance: f = W^2 Re(U e^{i th}) + W' Re(-i U e^{i th})
    "Phi", "Gi", "Gcs",  # dense affine step s+ = Phi s + Gi (i - i_op) + Gcs [cos th_n, sin th_n], transposed
    "GbR",  # G in row-band storage (refactorisation during run-ups)
    "ca_ptr", "ca_idx", "ca_val",  # Ca in CSR form (sparse rows for the full rung)
    "cs_ptr", "cs_idx", "cs_val",  # Cs in CSR form (the sensor rows: a few DOFs each)
    "u_idx",  # the DOFs where Ur or Ui is non-zero (unbalance acts at a few nodes)
    "f0",  # N per axis: constant force at the axis' actuator (-load on a lost axis: the weight drops)
    "load",  # N per axis: the AMB force at the operating point (the nonlinear remainder is taken about it)
    "aux_p",  # (m, A_LEN) auxiliary-bearing parameters per station (plant/auxiliary_bearing.py)
    "aux_ax",  # (m, 2) int64: the x and y axis of each auxiliary-bearing station
])
I_SCHEME, I_N, I_NA, I_BW, I_NL, I_RUNUP, I_MAXIT, I_DENSE, I_NS, I_AUX, I_F0 = range(11)

# per auxiliary-bearing station, NC floats of the state vector after the step count (s[4n + 1 + j NC:]):
# race speed; impact normal speed of the current contact event (0: not in contact); force on the shaft;
# normal and friction force; penetration (< 0 out of contact); friction power; cumulative friction and
# contact-damping energy and normal impulse; number of contact events; peak force and penetration of
# the run; start and end time, peak force, energy lost, impact and separation speed of the current or
# last event; shaft centre relative to the bearing centre; friction torque on the shaft; the current or
# last event's largest penetration
(C_W, C_V0, C_FX, C_FY, C_FN, C_FT, C_D, C_PF, C_EF, C_ED, C_IMP, C_NEV, C_PEAK, C_DMAX, C_TS, C_TE, C_EPEAK,
 C_EE, C_EV0, C_EVOUT, C_X, C_Y, C_TQ, C_EDMAX, NC) = range(25)
CONTACT_FIELDS = ("race_speed", "v0", "fx", "fy", "fn", "ft", "d", "friction_power", "e_friction", "e_damping",
                  "impulse", "events", "peak_force", "max_penetration", "event_start", "event_end", "event_peak",
                  "event_energy", "event_v0", "event_v_out", "x", "y", "friction_torque", "event_max_penetration")
F_H, F_BH, F_OM, F_AM, F_AF, F_G, F_CZD, F_TOL, F_REFAC, F_W0, F_W1, F_T0, F_T1, F_WNOM, F_TH0 = range(15)

