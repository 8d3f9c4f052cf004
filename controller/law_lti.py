"""LTI control laws written in the scene: ``[controller] kind = "transfer"`` (per-axis transfer
functions built from blocks) and ``kind = "statespace"`` (one MIMO state space), built with
python-control (``control.tf``, ``control.ss``, ``control.c2d``).

kind = "transfer": the same SISO law on every axis, acting like the PID on ``e = -y``::

    u = u_op + C(s) e,   C(s) = the product of [controller.transfer] blocks, in order

Blocks (frequencies are numbers in Hz):

    {type = "pid", kp, ki = 0, kd = 0, derivative_filter = T_d}   kp + ki/s + kd s/(1 + s T_d)
    {type = "notch", frequency = f, width = b, depth = g}         (s^2 + 2 z_z w s + w^2) / (s^2 + 2 z_p w s + w^2)
                       w = 2 pi f, z_p = b / 2, z_z = g b / 2: the gain is g at f (0 <= g < 1; 0 a
                       full notch) and 1 far from it; b is the relative width (the -3 dB band of a
                       full notch is b f wide)
    {type = "lead_lag", zero = f_z, pole = f_p}                   (1 + s/w_z) / (1 + s/w_p), gain 1 at DC
    {type = "gain", k = k}                                        k
    {type = "tf", num = [...], den = [...]}                       any proper transfer function in s
                                                                  (coefficients, highest power first)

``[controller.transfer.axes]`` may give an axis (``"A-x" = [blocks]``) a chain of its own.

kind = "statespace": ``u = u_op + (C x + D y)`` -- y -> u as written, sign included (MIMO);
``[controller.statespace]`` ``A, B, C, D`` (``A = []`` for a static law), ``dt`` (0: continuous,
discretised at the loop's period by ``[controller] discretisation``; > 0: discrete, equal to the
loop's period), ``inputs`` / ``outputs`` (the order of y and u: each axis of the loop once;
default the loop's axes).  An unstable controller is allowed (:attr:`LTILaw.note` says so).

Each law runs as ``x+ = Ad x + Bd y``, ``u = u_op + Cd x + Dd y`` with ``(Ad, Bd, Cd, Dd)`` in the
loop's axis order (the sign of ``e = -y`` folded in), the matrices the sampled-loop analyses read
(:func:`runner_matrices`).  The frequency-domain analyses use the continuous current law
:func:`current_law` (``i = -H(s) y_d``, ``H = G_A C G_s``; SISO for one chain on every axis, else
na x na); a discrete statespace law enters them by its inverse Tustin transform (exact on the
warped frequency axis).
"""
from __future__ import annotations

import math
import warnings

import control
import numba as nb
import numpy as np
import scipy.signal as sig

from . import discrete as dc
from . import hardware as hw
from . import transfer
from .law import LawError
from .params import ControllerParams

BLOCKS = ("pid", "notch", "lead_lag", "gain", "tf")
_KEYS = {"pid": ("kp", "ki", "kd", "derivative_filter"), "notch": ("frequency", "width", "depth"),
         "lead_lag": ("zero", "pole"), "gain": ("k",), "tf": ("num", "den")}


class LTIWarning(UserWarning):
    """An LTI law that is allowed but worth a word (an unstable controller)."""


# --------------------------------------------------------------------------- blocks -> C(s)
def _num(where: str, b: dict, key: str, default=None, positive=False, nonneg=False) -> float:
    v = b.get(key, default)
    if v is None:
        raise LawError(f"{where}: key {key!r} is required")
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise LawError(f"{where}: key {key!r} must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise LawError(f"{where}: key {key!r} must be > 0, got {v!r}")
    if nonneg and v < 0:
        raise LawError(f"{where}: key {key!r} must be >= 0, got {v!r}")
    return float(v)


def _poly(where: str, b: dict, key: str) -> list[float]:
    v = b.get(key)
    if (not isinstance(v, list) or not v or
            any(isinstance(c, bool) or not isinstance(c, (int, float)) or not math.isfinite(c) for c in v)):
        raise LawError(f"{where}: key {key!r} must be a list of finite numbers, got {v!r}")
    return [float(c) for c in v]


def block_tf(b, where: str) -> control.TransferFunction:
    """One block of a chain as a continuous ``control.tf``."""
    if not isinstance(b, dict):
        raise LawError(f"{where}: must be a table {{type = ...}}, got {b!r}")
    kind = b.get("type")
    if kind not in BLOCKS:
        raise LawError(f"{where}: key 'type' must be one of {', '.join(BLOCKS)}, got {kind!r}")
    where = f"{where} ({kind})"
    extra = sorted(set(b) - {"type", *_KEYS[kind]})
    if extra:
        raise LawError(f"{where}: unknown key {extra[0]!r} (known: {', '.join(_KEYS[kind])})")
    if kind == "pid":
        kp = _num(where, b, "kp", nonneg=True)
        ki = _num(where, b, "ki", 0.0, nonneg=True)
        kd = _num(where, b, "kd", 0.0, nonneg=True)
        Td = _num(where, b, "derivative_filter", 0.0, nonneg=True)
        if kd > 0 and Td <= 0:
            raise LawError(f"{where}: key 'derivative_filter' must be > 0 when kd > 0 "
                           f"(a pure derivative is not realisable)")
        # the polynomials of controller/transfer.py pid(), so a pid block is the built-in's G_c
        if kd > 0:
            num, den = ([kp * Td + kd, kp + ki * Td, ki], [Td, 1.0, 0.0]) if ki > 0 else ([kp * Td + kd, kp], [Td, 1.0])
        elif ki > 0:
            num, den = [kp, ki], [1.0, 0.0]
        else:
            num, den = [kp], [1.0]
        return control.tf(num, den)
    if kind == "notch":
        w = 2 * math.pi * _num(where, b, "frequency", positive=True)
        width = _num(where, b, "width", positive=True)
        depth = _num(where, b, "depth", nonneg=True)
        if depth >= 1:
            raise LawError(f"{where}: key 'depth' is the gain at the centre, must be < 1, got {depth!r}")
        zp, zz = width / 2, depth * width / 2
        return control.tf([1.0, 2 * zz * w, w * w], [1.0, 2 * zp * w, w * w])
    if kind == "lead_lag":
        wz = 2 * math.pi * _num(where, b, "zero", positive=True)
        wp = 2 * math.pi * _num(where, b, "pole", positive=True)
        return control.tf([1.0 / wz, 1.0], [1.0 / wp, 1.0])
    if kind == "gain":
        return control.tf([_num(where, b, "k")], [1.0])
    num, den = _poly(where, b, "num"), _poly(where, b, "den")
    den = list(np.trim_zeros(den, "f"))
    if not den:
        raise LawError(f"{where}: key 'den' is all zeros")
    num = list(np.trim_zeros(num, "f")) or [0.0]
    if len(num) > len(den):
        raise LawError(f"{where}: improper (num of degree {len(num) - 1} > den of degree {len(den) - 1})")
    return control.tf(num, den)


def chain(blocks, where: str) -> control.StateSpace:
    """C(s): the product of the blocks, as a continuous ``control.ss`` (blocks in series)."""
    if not isinstance(blocks, list) or not blocks:
        raise LawError(f"{where}: must be a non-empty list of blocks {{type = ...}}, got {blocks!r}")
    out = None
    for k, b in enumerate(blocks):
        s = control.ss(block_tf(b, f"{where}[{k}]"))
        out = s if out is None else s * out
    return out


def transfer_chains(table: dict, axes) -> list[control.StateSpace]:
    """The continuous C(s) of every axis from ``[controller.transfer]``."""
    where = "[controller.transfer]"
    if not isinstance(table, dict):
        raise LawError(f"{where}: must be a table with key 'blocks', got {table!r}")
    extra = sorted(set(table) - {"blocks", "axes"})
    if extra:
        raise LawError(f"{where}: unknown key {extra[0]!r} (known: blocks, axes)")
    if "blocks" not in table:
        raise LawError(f"{where}: key 'blocks' is required (a list of blocks {{type = ...}})")
    base = chain(table["blocks"], f"{where} blocks")
    per = table.get("axes", {})
    if not isinstance(per, dict):
        raise LawError(f"[controller.transfer.axes]: must be a table of axis = [blocks], got {per!r}")
    for name in per:
        if name not in axes:
            raise LawError(f"[controller.transfer.axes]: key {name!r} is not an axis of the loop "
                           f"({', '.join(axes)})")
    return [chain(per[a], f"[controller.transfer.axes] {a!r}") if a in per else base for a in axes]


# --------------------------------------------------------------------------- statespace
def _matrix(where: str, t: dict, key: str, rows: int | None, cols: int | None) -> np.ndarray:
    v = t.get(key)
    if v is None:
        raise LawError(f"{where}: key {key!r} is required (a list of rows)")
    try:
        m = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise LawError(f"{where}: key {key!r} must be a list of rows of numbers") from None
    if m.size == 0:
        m = np.zeros((rows or 0, cols or 0))
    if m.ndim != 2 or not np.isfinite(m).all():
        raise LawError(f"{where}: key {key!r} must be a list of rows of finite numbers (a matrix)")
    if (rows is not None and m.shape[0] != rows) or (cols is not None and m.shape[1] != cols):
        raise LawError(f"{where}: key {key!r} is {m.shape[0]} x {m.shape[1]}, expected "
                       f"{rows if rows is not None else 'any'} x {cols if cols is not None else 'any'}")
    return m


def _order(where: str, t: dict, key: str, axes) -> list[int]:
    names = t.get(key, list(axes))
    if not isinstance(names, list) or sorted(map(str, names)) != sorted(axes) or len(set(names)) != len(names):
        raise LawError(f"{where}: key {key!r} must name each axis of the loop once "
                       f"({', '.join(axes)}), got {names!r}")
    return [list(axes).index(n) for n in names]


def statespace(table: dict, axes, period: float) -> tuple[control.StateSpace, list[int], list[int]]:
    """``[controller.statespace]`` as a ``control.ss`` (continuous, or discrete at ``period``) with
    the axis index of each of its inputs and outputs."""
    where = "[controller.statespace]"
    if not isinstance(table, dict):
        raise LawError(f"{where}: must be a table (A, B, C, D, dt, inputs, outputs), got {table!r}")
    extra = sorted(set(table) - {"A", "B", "C", "D", "dt", "inputs", "outputs"})
    if extra:
        raise LawError(f"{where}: unknown key {extra[0]!r} (known: A, B, C, D, dt, inputs, outputs)")
    ins, outs = _order(where, table, "inputs", axes), _order(where, table, "outputs", axes)
    A = _matrix(where, table, "A", None, None)
    n = A.shape[0]
    if A.shape[1] != n:
        raise LawError(f"{where}: key 'A' is {A.shape[0]} x {A.shape[1]}, must be square")
    B = _matrix(where, table, "B", n, len(ins))
    C = _matrix(where, table, "C", len(outs), n)
    D = _matrix(where, table, "D", len(outs), len(ins))
    dt = _num(where, table, "dt", 0.0, nonneg=True)
    if dt > 0 and abs(dt - period) > 1e-9 * period:
        raise LawError(f"{where}: key 'dt' = {dt:g} s must equal the loop's period "
                       f"1/[controller] sample_rate = {period:g} s (or be 0: continuous)")
    return control.ss(A, B, C, D, period if dt > 0 else 0), ins, outs


# --------------------------------------------------------------------------- the law
def _method(config: dict, method: str | None = None) -> str:
    return method or str(config.get("discretisation", "tustin"))


def discrete_system(controller: dict, axes, period: float, method: str | None = None):
    """``(Ad, Bd, Cd, Dd, note)`` of the law in the loop's axis order: ``x+ = Ad x + Bd y``,
    ``u - u_op = Cd x + Dd y``; ``note``: a word on an unstable controller, else None."""
    kind, m = controller.get("kind"), _method(controller, method)
    na = len(axes)
    if kind == "transfer":
        cs = transfer_chains(controller.get("transfer"), axes)
        parts = [control.c2d(c, period, method=m) for c in cs]
        Ad = _blkdiag([p.A for p in parts])
        Bd = -_blkdiag([p.B for p in parts])      # e = -y
        Cd = _blkdiag([p.C for p in parts])
        Dd = -_blkdiag([p.D for p in parts])
        cont = cs
    elif kind == "statespace":
        s, ins, outs = statespace(controller.get("statespace"), axes, period)
        d = s if s.dt else control.c2d(s, period, method=m)
        nx = d.A.shape[0]
        Ad = np.array(d.A, float).reshape(nx, nx)
        Bd, Cd, Dd = np.zeros((nx, na)), np.zeros((na, nx)), np.zeros((na, na))
        Bd[:, ins] = np.asarray(d.B, float).reshape(nx, len(ins))
        Cd[outs, :] = np.asarray(d.C, float).reshape(len(outs), nx)
        Dd[np.ix_(outs, ins)] = np.asarray(d.D, float).reshape(len(outs), len(ins))
        cont = [s]
    else:
        raise LawError(f"[controller] kind = {kind!r} is not an LTI law (transfer | statespace)")
    return Ad, Bd, Cd, Dd, _note(kind, cont, Ad)


def _note(kind: str, cont, Ad) -> str | None:
    """One line when the controller itself has a growing mode (allowed: the loop may still be stable)."""
    if Ad.size == 0:
        return None
    z = np.linalg.eigvals(Ad)
    k = int(np.argmax(np.abs(z)))
    if abs(z[k]) <= 1 + 1e-9:
        return None
    return (f"[controller.{kind}]: the controller itself is unstable (a discrete pole at |z| = "
            f"{abs(z[k]):.6g}); the closed loop may still be stable: see the analyses")


def _blkdiag(ms) -> np.ndarray:
    ms = [np.atleast_2d(np.asarray(m, float)) if np.size(m) else np.zeros(np.shape(m)) for m in ms]
    r, c = sum(m.shape[0] for m in ms), sum(m.shape[1] for m in ms)
    out, i, j = np.zeros((r, c)), 0, 0
    for m in ms:
        out[i:i + m.shape[0], j:j + m.shape[1]] = m
        i, j = i + m.shape[0], j + m.shape[1]
    return out


class LTILaw:
    """The scene's LTI law (``meta.controller``: the ``[controller]`` table with its ``transfer`` or
    ``statespace`` sub-table) discretised at ``meta.period``; ``x``: its state (1-D float64),
    ``Ad, Bd, Cd, Dd``: the discrete system in the loop's axis order."""

    def __init__(self, meta):
        self.meta = meta
        self.Ad, self.Bd, self.Cd, self.Dd, self.note = discrete_system(meta.controller, meta.axes, meta.period)
        if self.note:
            warnings.warn(self.note, LTIWarning, stacklevel=2)
        self.u_op = np.array(meta.u_op, dtype=np.float64)
        n, na = np.shape(self.Ad)[0] if np.size(self.Ad) else 0, len(meta.axes)
        c = lambda m, r, k: np.ascontiguousarray(m, dtype=np.float64).reshape(r, k)  # noqa: E731
        self.Ad, self.Bd = c(self.Ad, n, n), c(self.Bd, n, na)
        self.Cd, self.Dd = c(self.Cd, na, n), c(self.Dd, na, na)
        self.x = np.zeros(n)
        self._xn = np.zeros(n)
        self._u = np.empty(len(meta.axes))

    def reset(self) -> None:
        self.x[:] = 0.0

    def step(self, t: float, y: np.ndarray) -> np.ndarray:
        u = self._u
        ss_step(self.Ad, self.Bd, self.Cd, self.Dd, self.u_op, self.x, self._xn, y, u)
        return u


@nb.njit(cache=True, _nrt=False)
def ss_step(A, B, C, D, u_op, x, xn, y, u):
    """One sample of the discrete law in place: ``u = u_op + C x + D y``, ``x <- A x + B y``
    (``xn``: scratch of the state's size)."""
    for i in range(u.shape[0]):
        acc = u_op[i]
        for j in range(x.shape[0]):
            acc += C[i, j] * x[j]
        for j in range(y.shape[0]):
            acc += D[i, j] * y[j]
        u[i] = acc
    for i in range(x.shape[0]):
        acc = 0.0
        for j in range(x.shape[0]):
            acc += A[i, j] * x[j]
        for j in range(y.shape[0]):
            acc += B[i, j] * y[j]
        xn[i] = acc
    for i in range(x.shape[0]):
        x[i] = xn[i]


# --------------------------------------------------------------------------- for the analyses
def _scipy(s) -> sig.StateSpace:
    A, B, C, D = (np.asarray(m, float) for m in (s.A, s.B, s.C, s.D))
    n, (p, m) = A.shape[0], np.atleast_2d(D).shape
    return sig.StateSpace(A.reshape(n, n), B.reshape(n, m), C.reshape(p, n), np.atleast_2d(D))


def _undo_tustin(d: control.StateSpace) -> control.StateSpace:
    """The continuous system whose Tustin transform at ``d.dt`` is ``d`` (scipy's bilinear inverted)."""
    T = d.dt
    Ad, Bd, Cd, Dd = (np.asarray(m, float) for m in (d.A, d.B, d.C, d.D))
    n = Ad.shape[0]
    if n == 0:
        return control.ss(Ad, Bd, Cd, Dd)
    P = Ad + np.eye(n)
    if np.linalg.cond(P) > 1e12:
        raise LawError("[controller.statespace]: a discrete pole at z = -1 has no continuous equivalent "
                       "(the frequency-domain analyses need one)")
    Pi = np.linalg.inv(P)
    A = (2 / T) * (Ad - np.eye(n)) @ Pi
    B = (2 / T) * Pi @ Bd
    C = 2 * Cd @ Pi
    D = Dd - 0.5 * C @ Bd
    return control.ss(A, B, C, D)


def _lag(gain: float, tau: float) -> control.StateSpace:
    return control.ss(control.tf([gain], [tau, 1.0])) if tau > 0 else control.ss([], [], [], [[gain]])


def current_law(config: ControllerParams, axes, period: float | None = None) -> sig.StateSpace:
    """The continuous current law of an LTI kind, ``i = -H(s) y_d`` (y_d: rotor displacement at
    the sensors), as controller/transfer.py's ``current_law`` gives it for the PID:
    ``H = G_A C(s) G_s``.  One chain on every axis: SISO (1 x 1, applied per axis); per-axis
    chains or a statespace law: ``na x na`` in the loop's axis order."""
    period = period or config.period
    na = len(axes)
    if config.kind == "transfer":
        cs = transfer_chains(config.lti.get("transfer"), axes)
        if all(c is cs[0] for c in cs):
            return transfer.amplifier(config.amplifier) * _scipy(cs[0]) * transfer.sensor(config.sensor)
        K = control.append(*cs)            # C(s) per axis on the diagonal
        sign = 1.0
    elif config.kind == "statespace":
        s, ins, outs = statespace(config.lti.get("statespace"), axes, period)
        if s.dt:
            s = _undo_tustin(s)
        Pin = np.zeros((len(ins), na)); Pin[range(len(ins)), ins] = 1.0
        Pout = np.zeros((na, len(outs))); Pout[outs, range(len(outs))] = 1.0
        K = control.ss([], [], [], Pout) * s * control.ss([], [], [], Pin)
        sign = -1.0                          # u = K y_s, so i = G_A K G_s y_d = -H y_d
    else:
        raise LawError(f"[controller] kind = {config.kind!r} is not an LTI law (transfer | statespace)")
    GA = control.append(*[_lag(config.amplifier.gain, config.amplifier.time_constant)] * na)
    GS = control.append(*[_lag(config.sensor.gain, config.sensor.time_constant)] * na)
    return _scipy(GA * K * GS * sign)


def check(config: ControllerParams, axes) -> None:
    """Build the law of an LTI kind for the loop's ``axes`` at its period, discrete and continuous:
    LawError (one line naming the table and key) when it cannot be."""
    discrete_system({**config.table, "kind": config.kind, "discretisation": config.discretisation},
                    tuple(axes), config.period)
    current_law(config, tuple(axes))


# --------------------------------------------------------------------------- the runner's linear map
def runner_matrices(runner) -> tuple[np.ndarray, int, int]:
    """The linear map of one sample of a :class:`ambhil.controller.law_runner.LawRunner` whose
    law is an :class:`LTILaw` (or the built-in :class:`ambhil.controller.pid_law.PIDLaw`, which
    runs there when the amplifier has a slew limit), read off the runner's own kernels and law by unit inputs (limits
    and slew off, the delay taken out): ``[[Ac, Bc], [Cc, Dc]]`` on the state ``[sensor states,
    amplifier states, law state]`` and the displacements; returns (matrix, states, delay_samples)."""
    from .pid_law import PIDLaw         # the built-in law run between the hardware (a slew limit)
    law = getattr(runner, "law", None)
    if not isinstance(law, (LTILaw, PIDLaw)):
        raise TypeError(f"law {getattr(runner, 'name', runner)!r} is not an LTI law: no linear map")
    p = runner.hw_params.copy()
    nd = int(p[dc.P_DELAY])
    p[dc.P_DELAY] = 0
    p[dc.P_ILIM] = p[dc.P_ULIM] = p[dc.P_LEN] = np.inf
    na, nl = runner.n_axes, law.x.shape[0]
    nx = 2 * na + nl
    hw_idx = np.array([a * hw.NH for a in range(na)] + [a * hw.NH + 1 for a in range(na)], dtype=int)
    saved = law.x.copy()
    pid_params = law.params.copy() if isinstance(law, PIDLaw) else None
    if pid_params is not None:
        law.params[dc.P_ULIM] = np.inf   # its input limit (and so its anti-windup) off: the linear law
    cols = []
    try:
        for j in range(nx + na + 1):           # the last: all zero, the affine offset (u_op)
            h = np.zeros(hw.state_size(na, 0))
            law.x[:] = 0.0
            d = np.zeros(na)
            if j < 2 * na:
                h[hw_idx[j]] = 1.0
            elif j < nx:
                law.x[j - 2 * na] = 1.0
            elif j < nx + na:
                d[j - nx] = 1.0
            y, cur = np.zeros(na), np.zeros(na)
            hw.sensor_step(p, h, d, y)
            u = np.array(law.step(0.0, y), dtype=float)
            hw.amplifier_step(p, h, u, cur)
            cols.append(np.concatenate([h[hw_idx], law.x, cur]))
    finally:
        law.x[:] = saved
        if pid_params is not None:
            law.params[:] = pid_params
    M = np.array(cols).T
    return M[:, :-1] - M[:, -1:], nx, nd
