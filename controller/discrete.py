"""Discrete per-axis AMB controller: sensor lag -> PID (filtered derivative) -> amplifier lag,
discretised at the controller's own sample rate, with current saturation, anti-windup and an
optional pure delay of n samples.

Every block of eq. 7 (controller/transfer.py) is discretised on its own by scipy
(``StateSpace.to_discrete``, method ``bilinear`` = Tustin or ``zoh``, from
``ControllerParams.discretisation``) and the blocks are evaluated in series each sample:

    y_s = G_s[y]           e = -y_s
    u   = k_p e + I[e] + D[e]           (I = k_i/s, D = k_d s/(1 + s T_d))
    u   = clip(u, +-u_max)              (u_max = current_limit / alpha_a, the amplifier's input range)
    i   = clip(G_A[u], +-current_limit)
    anti-windup (``[controller] anti_windup``): integrator clamping -- the integrator holds its
    state while the command is saturated and the error would drive it further into saturation.
    delay: the current computed at sample k is applied at sample k + delay_samples.

Because all blocks are discretised with the same method and rate, the linear part equals
``-H_d(z)`` with ``H_d`` the product of the discretised blocks; for Tustin,
``H_d(e^{i w T}) = H(i (2/T) tan(w T/2))`` exactly (frequency warping).

At ``reset`` the integrator (and amplifier) are preloaded so that the output at zero displacement
is the operating-point current ``i_op`` of each axis (misaligned bearings), i.e. the loop starts in
equilibrium.  The hot path is a numba kernel working in place on a flat state vector.
"""
from __future__ import annotations


import numba as nb
import numpy as np
import scipy.signal as sig

from .params import ControllerParams

# parameter vector layout
(P_AS, P_BS, P_CS, P_DS, P_AI, P_BI, P_CI, P_DI, P_AD, P_BD, P_CD, P_DD,
 P_AA, P_BA, P_CA, P_DA, P_KP, P_ILIM, P_ULIM, P_AW, P_DELAY, P_LEN) = range(22)
NX = 4  # states per axis: sensor, integrator, derivative, amplifier


def _block(num, den, Ts, method):
    """(a, b, c, d) of a first-order (or static) block discretised by scipy."""
    if len(den) == 1 or den[0] == 0:
        return 0.0, 0.0, 0.0, float(num[-1] / den[-1])
    ss = sig.lti(num, den).to_ss()
    d = ss.to_discrete(Ts, method=method)
    return float(d.A[0, 0]), float(d.B[0, 0]), float(d.C[0, 0]), float(d.D[0, 0])


def discretise(c: ControllerParams, sample_rate: float | None = None, method: str | None = None) -> np.ndarray:
    """Parameter vector of the discrete controller (blocks discretised by scipy)."""
    s, a = c.sensor, c.amplifier
    fs = sample_rate or c.sample_rate
    Ts = 1.0 / fs
    m = {"tustin": "bilinear", "zoh": "zoh"}[method or c.discretisation]
    p = np.zeros(P_LEN)
    p[P_AS:P_AS + 4] = _block([s.gain], [s.time_constant, 1.0] if s.time_constant > 0 else [1.0], Ts, m)
    p[P_AI:P_AI + 4] = _block([c.ki], [1.0, 0.0], Ts, m) if c.ki > 0 else (0.0, 0.0, 0.0, 0.0)
    if c.kd > 0:
        p[P_AD:P_AD + 4] = _block([c.kd, 0.0], [c.derivative_filter, 1.0], Ts, m)
    p[P_AA:P_AA + 4] = _block([a.gain], [a.time_constant, 1.0] if a.time_constant > 0 else [1.0], Ts, m)
    p[P_KP] = c.kp
    p[P_ILIM] = a.current_limit
    p[P_ULIM] = a.current_limit / a.gain
    p[P_AW] = 1.0 if c.anti_windup else 0.0
    p[P_DELAY] = c.delay_samples
    return p


def describe(p: np.ndarray, i_op, config: ControllerParams | None = None) -> dict:
    """The discrete law as plain JSON-able data (RunMeta ``controller``, docs/protocol.md §5.2): what
    another implementation needs to reproduce :func:`controller_step` bit for bit without the
    scene.  Floats are Python floats (``json`` writes them so that they read back exactly);
    an infinite limit is ``None`` (JSON has no infinity)."""
    fin = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731
    blk = lambda o: {"a": float(p[o]), "b": float(p[o + 1]), "c": float(p[o + 2]),  # noqa: E731
                     "d": float(p[o + 3])}
    out = {"law": "sensor-pid-amplifier", "n_axes": len(np.atleast_1d(i_op)),
           "sensor": blk(P_AS), "integral": blk(P_AI), "derivative": blk(P_AD),
           "amplifier": blk(P_AA), "kp": float(p[P_KP]),
           "current_limit": fin(p[P_ILIM]), "input_limit": fin(p[P_ULIM]),
           "anti_windup": bool(p[P_AW] != 0.0), "delay_samples": int(p[P_DELAY]),
           "i_op": [float(v) for v in np.atleast_1d(np.asarray(i_op, float))]}
    if config is not None:
        s, a = config.sensor, config.amplifier
        out.update({"rate_hz": float(config.sample_rate), "discretisation": config.discretisation,
                    "continuous": {"kp": config.kp, "ki": config.ki, "kd": config.kd,
                                   "derivative_filter_s": config.derivative_filter,
                                   "sensor_gain": s.gain, "sensor_time_constant_s": s.time_constant,
                                   "amplifier_gain": a.gain,
                                   "amplifier_time_constant_s": a.time_constant,
                                   "current_limit": fin(a.current_limit)}})
    return out


def state_size(n_axes: int, delay: int) -> int:
    return n_axes * NX + n_axes * delay + 1


@nb.njit(cache=True, _nrt=False)
def controller_step(p, x, y, cur):
    """One controller sample in place: state x, measured displacements y -> coil currents cur.
    Returns the number of saturated axes."""
    na = y.shape[0]
    nd = int(p[P_DELAY])
    ilim, ulim = p[P_ILIM], p[P_ULIM]
    nsat = 0
    for a in range(na):
        o = a * NX
        # sensor
        xs = x[o]
        ys = p[P_CS] * xs + p[P_DS] * y[a]
        x[o] = p[P_AS] * xs + p[P_BS] * y[a]
        e = -ys
        # PID
        xi = x[o + 1]
        ui = p[P_CI] * xi + p[P_DI] * e
        xd = x[o + 2]
        ud = p[P_CD] * xd + p[P_DD] * e
        x[o + 2] = p[P_AD] * xd + p[P_BD] * e
        u = p[P_KP] * e + ui + ud
        sat = False
        if u > ulim:
            u_s = ulim
            sat = True
        elif u < -ulim:
            u_s = -ulim
            sat = True
        else:
            u_s = u
        # amplifier
        xa = x[o + 3]
        i = p[P_CA] * xa + p[P_DA] * u_s
        x[o + 3] = p[P_AA] * xa + p[P_BA] * u_s
        if i > ilim:
            i = ilim
            sat = True
        elif i < -ilim:
            i = -ilim
            sat = True
        # integrator with clamping anti-windup
        if sat and p[P_AW] != 0.0 and e * u > 0.0:
            pass
        else:
            x[o + 1] = p[P_AI] * xi + p[P_BI] * e
        if sat:
            nsat += 1
        if nd > 0:
            base = na * NX + a * nd
            k = int(x[x.shape[0] - 1])
            cur[a] = x[base + k]
            x[base + k] = i
        else:
            cur[a] = i
    if nd > 0:
        x[x.shape[0] - 1] = (x[x.shape[0] - 1] + 1.0) % nd
    return nsat


def initial_state(p: np.ndarray, i_op: np.ndarray) -> np.ndarray:
    """Controller state in equilibrium at zero displacement with output i_op per axis."""
    na = len(i_op)
    nd = int(p[P_DELAY])
    x = np.zeros(state_size(na, nd))
    for a, i0 in enumerate(np.asarray(i_op, float)):
        if i0 == 0.0:
            continue
        amp_dc = p[P_DA] + (p[P_CA] * p[P_BA] / (1 - p[P_AA]) if p[P_AA] != 1 else 0.0)
        u = i0 / amp_dc
        if p[P_CI] != 0.0:
            x[a * NX + 1] = u / p[P_CI]
        if p[P_BA] != 0.0:
            x[a * NX + 3] = p[P_BA] * u / (1 - p[P_AA])
        if nd:
            x[na * NX + a * nd: na * NX + (a + 1) * nd] = i0
    return x


def frequency_response(p: np.ndarray, w: np.ndarray, Ts: float) -> np.ndarray:
    """Linear (unsaturated) discrete current law H_d(e^{i w Ts}) such that i = -H_d y,
    including the pure delay; evaluated from the discretised block coefficients."""
    z = np.exp(1j * np.asarray(w, float) * Ts)
    blk = lambda o: p[o + 3] + p[o + 2] * p[o + 1] / (z - p[o])
    H = blk(P_AS) * (p[P_KP] + blk(P_AI) + blk(P_AD)) * blk(P_AA)
    return H * z ** (-int(p[P_DELAY]))


class ControllerRunner:
    """The controller process's loop body: ``reset() -> None``, ``step(y) -> currents``.

    ``config``: the controller's parameters; ``i_op``: the operating-point current of each axis
    (what the loop must deliver at zero displacement, e.g. to hold a misaligned bearing), which
    also sets the number of axes.  Attributes ``n_axes``, ``period`` (s), ``step_index``;
    ``params`` is the discretised parameter vector and ``state`` the flat controller state."""

    def __init__(self, config: ControllerParams, i_op, sample_rate: float | None = None,
                 method: str | None = None):
        self.config = config
        self.i_op = np.array(i_op, dtype=float).reshape(-1)
        self.n_axes = len(self.i_op)
        self.sample_rate = float(sample_rate or config.sample_rate)
        self.period = 1.0 / self.sample_rate
        self.params = discretise(config, self.sample_rate, method)
        self.currents = np.zeros(self.n_axes)
        self._y = np.zeros(self.n_axes)
        self.saturated = 0
        self.reset()

    def reset(self) -> None:
        self.state = initial_state(self.params, self.i_op)
        self.step_index = 0
        self.saturated = 0

    def step(self, y: np.ndarray) -> np.ndarray:
        if np.shape(y) != (self.n_axes,):
            raise ValueError(f"controller expects {self.n_axes} displacements, got shape {np.shape(y)}")
        # copy into our own writable buffer: one kernel specialisation whatever the caller passes
        # (a read-only view of wire bytes would otherwise trigger a fresh numba compile mid-run)
        self._y[:] = y
        self.saturated = controller_step(self.params, self.state, self._y, self.currents)
        self.step_index += 1
        return self.currents.copy()


    def step_shared(self, y: np.ndarray) -> np.ndarray:
        """Bridge hot path of :meth:`step`: ``y`` must be a writable C-contiguous float64 array
        of ``n_axes`` values (not checked), and the returned array is the runner's own output
        buffer, overwritten by the next call.  Same arithmetic as :meth:`step`."""
        self.saturated = controller_step(self.params, self.state, y, self.currents)
        self.step_index += 1
        return self.currents


def step(params: np.ndarray, state: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pure controller step: (state, measured displacements) -> (new state, coil currents)."""
    x = np.array(state, dtype=np.float64)
    cur = np.zeros(len(y))
    controller_step(params, x, np.ascontiguousarray(y, dtype=np.float64), cur)
    return x, cur
