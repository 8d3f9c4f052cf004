"""The simulated sampled loop and its numerics: the one-period map of the loop the kernels
actually integrate (:func:`loop_matrix`, :func:`sampled_loop`; with ``zoh`` the exact, physical
sampled loop), each scheme's amplification and numerical damping over a controller period, and
the checks that say when a scheme misreports the physical loop (:func:`numerics_warning`: one
line; :func:`check_numerics`: mode by mode against the exact and the continuous closed loop of
:mod:`loop.analysis.modal`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from controller import discrete as dc
from plant import integrator as ig
from plant import plan as pl
from plant.step import make_plan, private_plan
from .system import System, controller_runner


def loop_matrix(model: System, plan: ig.PlantArrays, ctrl: dc.ControllerRunner, ratio: int) -> tuple[np.ndarray, int]:
    """Linear one-period map of the simulated discrete loop (plant state, controller state),
    built by running the kernels on unit vectors; unbalance removed, scene must be LTI.
    Returns (matrix, periods spanned); the map always spans one controller period (the second
    value is kept for callers that raise the eigenvalues to 1/span).

    The kernels are run with the fault checks neutralised (gaps set to infinity): a unit vector
    puts the rotor metres outside its gap, and ``plant_advance`` stops a period at the first
    touchdown, so with ``ratio > 1`` the columns would otherwise hold a truncated period (a map
    with spurious eigenvalues far outside the unit circle).  The pure delay's ring buffer is read
    back in age order (slot k = the current applied k periods from now), so the map is the true
    one-period map and its eigenvalues carry the right frequencies."""
    if plan.ip[ig.I_NL] or plan.ip[ig.I_RUNUP]:
        raise ValueError("the discrete loop matrix needs a linear time-invariant scene")
    p = private_plan(plan._replace(Ur=np.zeros_like(plan.Ur), Ui=np.zeros_like(plan.Ui), Gcs=np.zeros_like(plan.Gcs),
                                   iop=np.zeros_like(plan.iop), gap=np.full_like(plan.gap, np.inf)))
    n = model.n
    scheme = int(p.ip[ig.I_SCHEME])
    ns = 4 * n if scheme in (ig.BDF2, ig.GALPHA) else 2 * n
    nd = int(ctrl.params[dc.P_DELAY])
    na = model.n_axes
    nx = len(ctrl.state) - 1
    N = ns + nx
    L = np.zeros((N, N))
    wk, ws = pl.new_workspace(p)
    y = np.zeros(na); cur = np.zeros(na)
    cp = ctrl.params.copy()
    cp[dc.P_ILIM] = cp[dc.P_ULIM] = np.inf  # the linear loop: no saturation
    for j in range(N):
        s = np.zeros(4 * n + 1); x = np.zeros(nx + 1)  # ring index x[-1] = 0: slot k in age order
        s[4 * n] = 1.0
        if j < ns:
            s[j] = 1.0
        else:
            x[j - ns] = 1.0
        ig.sense(p, s, y)
        dc.controller_step(cp, x, y, cur)
        ig.plant_advance(p, s, cur, ratio, wk, ws, y)
        L[:ns, j] = s[:ns]
        xc = x[:nx]
        if nd:
            k = int(x[nx])  # the ring index has moved on by one slot
            xc = xc.copy()
            for a in range(na):
                b = na * dc.NX + a * nd
                xc[b:b + nd] = np.roll(x[b:b + nd], -k)
        L[ns:, j] = xc
    return L, 1


def scheme_amplification(scheme: str, lam_h: complex, rho_inf: float = 0.8) -> complex:
    """Principal root of the scheme applied to y' = lam y over one step (lam_h = lam h)."""
    z = complex(lam_h)
    if scheme == "bdf1":
        return 1 / (1 - z)
    if scheme == "trapezoidal":
        return (1 + z / 2) / (1 - z / 2)
    if scheme == "zoh":
        return np.exp(z)
    if scheme == "bdf2":
        r = np.roots([1 - 2 * z / 3, -4 / 3, 1 / 3])
    else:
        A, B = _galpha_matrices(z, rho_inf)
        r = np.linalg.eigvals(np.linalg.solve(A, B))
    return complex(r[np.argmin(np.abs(r - np.exp(z)))])


def _galpha_matrices(z: complex, rho_inf: float):
    """[y+, yd+ h] = A^-1 B [y, yd h] for generalised-alpha on y' = lam y, z = lam h."""
    am, af, g = pl.galpha_params(rho_inf)
    A = np.array([[1, -g], [-z * af, am]], dtype=complex)
    B = np.array([[1, 1 - g], [z * (1 - af), -(1 - am)]], dtype=complex)
    return A, B


def period_amplification(scheme: str, lam_h: complex, ratio: int, rho_inf: float = 0.8) -> complex:
    """Amplification of y' = lam y over one controller period of ``ratio`` plant steps, as the
    kernel takes it: the multistep memory is dropped at every controller update (bdf2 restarts
    with one trapezoidal step, generalised-alpha starts from consistent rates yd = lam y), so
    the map over a period is a scalar function of y alone (exact, not the principal root)."""
    z, k = complex(lam_h), int(ratio)
    if scheme == "bdf2":
        y0, y1 = 1.0 + 0j, scheme_amplification("trapezoidal", z)
        for _ in range(k - 1):
            y0, y1 = y1, (4 / 3 * y1 - 1 / 3 * y0) / (1 - 2 * z / 3)
        return complex(y1)
    if scheme == "generalized-alpha":
        A, B = _galpha_matrices(z, rho_inf)
        x = np.linalg.matrix_power(np.linalg.solve(A, B), k) @ np.array([1.0, z])
        return complex(x[0])
    return complex(scheme_amplification(scheme, z, rho_inf) ** k)


def numerical_damping(scheme: str, w: float, h: float, rho_inf: float = 0.8, ratio: int | None = None) -> float:
    """Damping ratio the scheme gives an undamped mode of frequency w (rad/s) at step h: from its
    principal root (``ratio=None``), or over a controller period of ``ratio`` steps with the
    restart at the update, as simulated (see :func:`period_amplification`)."""
    if ratio is None:
        R, T = scheme_amplification(scheme, 1j * w * h, rho_inf), h
    else:
        R, T = period_amplification(scheme, 1j * w * h, ratio, rho_inf), ratio * h
    s = np.log(R) / T
    return float(-s.real / abs(s))


def _frequency_error(scheme: str, w: float, h: float, ratio: int, rho_inf: float) -> float:
    s = np.log(period_amplification(scheme, 1j * w * h, ratio, rho_inf)) / (ratio * h)
    return float(abs(s.imag / w - 1.0))


#: a loop is reported unstable when its spectral radius exceeds 1 by more than this (per period):
#: eigenvalues of the loop map are accurate to ~1e-12 here, and 1e-9 per period at 10 kHz is an
#: e-folding time of over a day
STABILITY_TOL = 1e-9


@dataclass
class LoopModes:
    """Eigenvalues of the one-period map of a sampled loop (plant integrated by ``integrator`` at
    step ``h``, discrete controller at ``period``), as ``s = ln(mu) / period``.  ``f_plant``: the
    frequency (Hz) the plant part of each eigenvector moves at, ``Im(q^H M v / q^H M q)`` (equal
    to ``Im s`` for a mode below the Nyquist frequency, larger for a mode aliased into the band);
    ``V``: eigenvectors (plant state first), when asked for."""
    integrator: str
    h: float
    period: float
    mu: np.ndarray
    f_plant: np.ndarray | None = None
    V: np.ndarray | None = field(default=None, repr=False)

    @property
    def s(self) -> np.ndarray:
        mu = self.mu.astype(complex)
        out = np.full(mu.shape, -np.inf + 0j)
        nz = mu != 0
        out[nz] = np.log(mu[nz]) / self.period
        return out

    @property
    def spectral_radius(self) -> float:
        return float(np.max(np.abs(self.mu))) if len(self.mu) else 0.0

    @property
    def stable(self) -> bool:
        return self.spectral_radius <= 1.0 + STABILITY_TOL

    @property
    def dominant(self) -> int:
        """Index of the eigenvalue of largest modulus (upper half plane of a conjugate pair)."""
        r = np.abs(self.mu)
        cand = np.where(r >= r.max() * (1 - 1e-12))[0]
        return int(cand[np.argmax(self.mu[cand].imag)])

    @property
    def growth_rate(self) -> float:
        """ln(spectral radius) / period, 1/s (negative: the slowest decay)."""
        return float(np.log(self.spectral_radius) / self.period) if self.spectral_radius > 0 else -np.inf

    @property
    def frequency_hz(self) -> float:
        return float(abs(self.s[self.dominant].imag) / (2 * np.pi))

    def least_damped(self, fmin_hz: float = 0.0) -> int | None:
        """Index of the oscillatory mode (frequency > fmin_hz, upper half plane) of lowest damping
        ratio; modes aliased from above the Nyquist frequency (known from ``f_plant``) are skipped."""
        s = self.s
        ok = (s.imag > max(2 * np.pi * fmin_hz, 1e-6)) & np.isfinite(s.real)
        if self.f_plant is not None:
            ok &= self.f_plant <= 1.05 * 0.5 / self.period
        idx = np.where(ok)[0]
        if not len(idx):
            return None
        z = -s[idx].real / np.abs(s[idx])
        return int(idx[np.argmin(z)])

    def describe(self, k: int) -> str:
        sk = self.s[k]
        return f"{abs(sk.imag) / 2 / np.pi:.4g} Hz, {'grows' if sk.real > 0 else 'decays'} at {abs(sk.real):.3g} 1/s"


def sampled_loop(model: System, integrator: str = "zoh", h: float | None = None, *, speed: float | None = None,
                 sample_rate: float | None = None, method: str | None = None, rho_inf: float | None = None,
                 ctrl: dc.ControllerRunner | None = None, plan: ig.PlantArrays | None = None,
                 vectors: bool = False) -> LoopModes:
    """Eigen-analysis of the sampled loop as simulated: plant ``integrator`` at step ``h`` (default:
    the controller period), the scene's discrete controller (or ``ctrl``), linear force law,
    constant ``speed`` (default: the scene's).  ``integrator="zoh"`` is the exact sampled-data
    loop (the physical one).  ``plan``: use this plan (e.g. a PlantRunner's) instead."""
    ctrl = ctrl or controller_runner(model, sample_rate=sample_rate, method=method)
    if plan is None:
        hh = h or ctrl.period
        ratio = max(1, int(round(ctrl.period / hh)))
        sim = getattr(model.scene, "simulation", None)
        if speed is None:
            speed = getattr(sim, "speed", None)
            speed = speed if speed is not None else (model.spec.speed.value or 0.0)
        plan = make_plan(model, integrator, hh, speed=speed, run_up=(speed, speed, 0.0, 1.0), nonlinear=False,
                         rho_inf=rho_inf, ratio=ratio)
    hh = float(plan.fp[ig.F_H])
    ratio = int(round(ctrl.period / hh))
    if ratio < 1 or abs(ctrl.period / hh - ratio) > 1e-9 * ratio:
        raise ValueError(f"controller period {ctrl.period:g} s is not an integer multiple of the plant step {hh:g} s")
    L, _ = loop_matrix(model, plan, ctrl, ratio)
    name = ig.SCHEMES[int(plan.ip[ig.I_SCHEME])]
    if not vectors:
        return LoopModes(name, hh, ctrl.period, np.linalg.eigvals(L))
    mu, V = np.linalg.eig(L)
    n = model.n
    q, v = V[:n], V[n:2 * n]
    M = model.M
    Mq = np.asarray(M @ q)
    qMq = np.einsum("ij,ij->j", q.conj(), Mq).real
    qMv = np.einsum("ij,ij->j", v.conj(), Mq).conj()  # q^H M v (M symmetric)
    with np.errstate(divide="ignore", invalid="ignore"):
        fp = np.where(qMq > 0, np.abs((qMv / np.where(qMq > 0, qMq, 1.0)).imag) / (2 * np.pi), 0.0)
    return LoopModes(name, hh, ctrl.period, mu, fp, V)


def physical_loop(model: System, speed: float | None = None, sample_rate: float | None = None,
                  method: str | None = None) -> LoopModes:
    """The exact (zoh) sampled-data loop of a model with its discrete controller, eigenvectors
    included; computed once per (sample rate, speed, discretisation) and kept in model.extras."""
    ctrl = controller_runner(model, sample_rate=sample_rate, method=method)
    key = ("physical_loop", ctrl.period, speed, method)
    if key not in model.extras:
        model.extras[key] = sampled_loop(model, "zoh", ctrl.period, speed=speed, ctrl=ctrl, vectors=True)
    return model.extras[key]


#: numerics_warning also speaks when the simulated loop's rate of the least-damped mode is off by
#: more than this fraction (the 5 % the rungs and schemes are held to, issue 15)
RATE_TOLERANCE = 0.05
#: a resolving scheme must damp the mode by less than this fraction of its physical margin and
#: place its frequency within this relative error (the growth rate of a marginal mode is ~10x
#: more sensitive to the frequency than the frequency itself)
RESOLVE_DAMPING_FRACTION = 0.02
RESOLVE_FREQUENCY_ERROR = 1e-3
_RATIOS = (1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 25, 32, 40, 50, 64, 80, 100, 128, 160, 200)


def resolving_step(w: float, zeta: float, period: float, rho_inf: float = 0.8,
                   schemes=("trapezoidal", "bdf2", "generalized-alpha", "bdf1")) -> tuple[str, int] | None:
    """Cheapest (scheme, steps per controller period) whose numerical damping at w (rad/s) is below
    RESOLVE_DAMPING_FRACTION |zeta| and whose frequency error is below RESOLVE_FREQUENCY_ERROR."""
    best = None
    for sc in schemes:
        for r in _RATIOS:
            h = period / r
            if abs(numerical_damping(sc, w, h, rho_inf, ratio=r)) <= RESOLVE_DAMPING_FRACTION * abs(zeta) \
                    and _frequency_error(sc, w, h, r, rho_inf) <= RESOLVE_FREQUENCY_ERROR:
                if best is None or r < best[1]:
                    best = (sc, r)
                break
    return best


def numerics_warning(model: System, integrator: str, h: float | None = None, *, speed: float | None = None,
                     sample_rate: float | None = None, rho_inf: float | None = None, method: str | None = None,
                     loop: LoopModes | None = None, exact: LoopModes | None = None) -> str | None:
    """One line when the scheme misreports the physical sampled loop's least-damped mode (None
    otherwise): its numerical damping at that mode's frequency exceeds the mode's damping margin
    |zeta| (the run hides an instability or overstates a margin), or the simulated loop's
    growth/decay rate of that mode is off by more than RATE_TOLERANCE (5 %).  Label "numerically
    damped" when numerical damping explains it, "numerical error" otherwise (e.g. trapezoidal
    frequency warping at a coarse step).

    The physical loop is the exact (zoh) sampled-data loop of the same model and controller
    (``exact``); its least-damped mode below the Nyquist frequency sets the margin.  The scheme's
    numerical damping is the one it has over a controller period as simulated
    (:func:`numerical_damping` with the step ratio); ``loop`` is the scheme's own loop (computed
    when not given).  The line names the cheapest scheme and step that resolve the mode
    (:func:`resolving_step`)."""
    if integrator == "zoh":
        return None
    ctrl = controller_runner(model, sample_rate=sample_rate, method=method)
    T = ctrl.period
    hh = h or T
    ratio = max(1, int(round(T / hh)))
    rho = rho_inf
    if rho is None:
        rho = getattr(getattr(model.scene, "simulation", None), "rho_inf", None) or 0.8
    if exact is None:
        exact = physical_loop(model, speed=speed, sample_rate=sample_rate, method=method)
    if loop is None:
        loop = sampled_loop(model, integrator, hh, speed=speed, ctrl=ctrl, rho_inf=rho)
    k = exact.least_damped()
    if k is None:
        return None
    se = exact.s[k]
    w, f = abs(se.imag), abs(se.imag) / (2 * np.pi)
    zeta = float(-se.real / abs(se))
    zn = numerical_damping(integrator, w, hh, rho, ratio=ratio)
    zn = 0.0 if abs(zn) < 1e-12 else zn
    sl_all = loop.s
    up = np.where(sl_all.imag > 1e-6)[0]
    sl = sl_all[up[np.argmin(np.abs(sl_all[up] - se))]] if len(up) else complex(-np.inf)
    rate_err = abs(sl.real - se.real) / max(abs(se.real), 1e-12)
    hides = zeta < 0 and loop.stable
    false_alarm = zeta >= 0 and exact.stable and not loop.stable
    damped = zn > abs(zeta)
    if not (damped or hides or false_alarm or rate_err > RATE_TOLERANCE):
        return None
    sim = f"{integrator} at h={hh:.3g} s"
    if hides:
        txt = (f"numerically damped: the sampled loop is unstable ({f:.4g} Hz grows at {se.real:.3g} 1/s, zeta "
               f"{zeta:.2g}) but {sim} adds zeta {zn:.2g} there and hides it: the simulated loop looks stable")
    elif false_alarm:
        txt = (f"numerical error: {sim} shows an instability ({loop.describe(loop.dominant)}) that the exact "
               f"sampled loop does not have")
    else:
        # numerical damping shifts Re s by about -zn w: the label names it when it explains at least
        # half of the discrepancy (else frequency warping / phase error dominates)
        label = "numerically damped" if damped or zn * w >= 0.5 * abs(sl.real - se.real) else "numerical error"
        what = "grows" if se.real > 0 else "decays"
        if label == "numerically damped":
            so = "its damping is overstated" if zeta >= 0 else "its growth is understated"
        else:
            so = "its rate is misreported"
        txt = (f"{label}: the sampled loop's least-damped mode ({f:.4g} Hz, zeta {zeta:.2g}) {what} at "
               f"{abs(se.real):.3g} 1/s, {sim} has it at {abs(sl.imag) / 2 / np.pi:.4g} Hz "
               f"{'growing' if sl.real > 0 else 'decaying'} at {abs(sl.real):.3g} 1/s (numerical damping zeta {zn:.2g}"
               f"{', more than the margin' if damped else ''}): {so}")
    fix = resolving_step(w, zeta, T, rho)
    if fix:
        txt += f"; {fix[0]} at h={T / fix[1]:.3g} s ({fix[1]} steps per controller period) or zoh (exact, linear) resolves it"
    else:
        txt += "; zoh (exact, linear) resolves it"
    return txt


@dataclass
class NumericsReport:
    integrator: str
    h: float
    period: float
    spectral_radius: float  # of the simulated discrete loop (per period)
    modes: list = field(default_factory=list)  # per continuous mode: dict
    warnings: list = field(default_factory=list)
    exact_spectral_radius: float = float("nan")  # of the exact (zoh) sampled loop

    @property
    def stable(self) -> bool:
        return self.spectral_radius <= 1.0 + STABILITY_TOL

    def text(self) -> str:
        lines = [f"{self.integrator} h={self.h:g} s, controller period {self.period:g} s: discrete loop spectral "
                 f"radius {self.spectral_radius:.6f} ({'stable' if self.stable else 'UNSTABLE'}; exact sampled loop "
                 f"{self.exact_spectral_radius:.6f})"]
        for m in self.modes:
            lines.append(f"  mode {m['freq_hz']:9.2f} Hz  zeta_cont {m['zeta_cont']:+.4f}  zeta_exact "
                         f"{m['zeta_exact']:+.4f}  zeta_loop {m['zeta_loop']:+.4f}  zeta_num {m['zeta_num']:.4f}")
        lines += [f"  WARNING: {w}" for w in self.warnings]
        return "\n".join(lines)


def check_numerics(model: System, integrator: str = "bdf1", h: float | None = None, speed: float = 0.0,
                   sample_rate: float | None = None, rho_inf: float = 0.8, fmax: float | None = None) -> NumericsReport:
    """Compare the simulated discrete loop with the exact sampled loop (zoh) and the continuous
    closed loop (modal.Solver), mode by mode: flags continuous poles with Re > 0 that the
    simulated loop shows as decaying (numerical damping hiding an instability), modes whose
    numerical damping zeta_num (over a controller period, as simulated) exceeds their physical
    damping, and adds the :func:`numerics_warning` line.  Loop eigenvalues are s = ln(mu)/T."""
    from .analysis import modal
    ctrl = controller_runner(model, sample_rate=sample_rate)
    lm = sampled_loop(model, integrator, h, speed=speed, rho_inf=rho_inf, ctrl=ctrl)
    ex = lm if integrator == "zoh" else sampled_loop(model, "zoh", ctrl.period, speed=speed, ctrl=ctrl, vectors=True)
    hh, ratio = lm.h, int(round(ctrl.period / lm.h))
    fny = np.pi / ctrl.period
    fmax = fmax or 0.9 * fny
    cont = modal.Solver(model).all(speed, fmax)
    rep = NumericsReport(integrator, hh, ctrl.period, lm.spectral_radius, exact_spectral_radius=ex.spectral_radius)
    sd, se = lm.s, ex.s
    sd_up, se_up = sd[sd.imag > 1e-6], se[se.imag > 1e-6]
    for m in cont:
        lam = m.eigenvalue
        if not len(sd_up) or not len(se_up):
            break
        sl = sd_up[int(np.argmin(np.abs(sd_up - lam)))]
        sx = se_up[int(np.argmin(np.abs(se_up - lam)))]
        zl, zx = -sl.real / abs(sl), -sx.real / abs(sx)
        zn = numerical_damping(integrator, abs(lam), hh, rho_inf, ratio=ratio)
        rep.modes.append(dict(freq_hz=lam.imag / 2 / np.pi, zeta_cont=m.damping_ratio, zeta_exact=float(zx),
                              zeta_loop=float(zl), zeta_num=zn, re_cont=lam.real, re_exact=float(sx.real),
                              re_loop=float(sl.real), whirl=m.whirl))
        if lam.real > 0 and sl.real < 0:
            rep.warnings.append(f"continuous closed-loop pole at {lam.imag / 2 / np.pi:.1f} Hz is unstable "
                                f"(Re {lam.real:+.3g} 1/s) but the {integrator} h={hh:g} s loop decays "
                                f"(Re {sl.real:+.3g} 1/s): numerical damping (zeta_num {zn:.3g}) hides it")
        elif zn > max(m.damping_ratio, 0.0) and zn > 1e-3:
            rep.warnings.append(f"mode {lam.imag / 2 / np.pi:.1f} Hz: numerical damping zeta_num {zn:.3g} of "
                                f"{integrator} at h={hh:g} s exceeds its physical damping {m.damping_ratio:.3g}")
    if rep.stable and any(m.eigenvalue.real > 0 for m in cont) and not any("hides" in w for w in rep.warnings):
        rep.warnings.append("the continuous closed loop is unstable but the simulated discrete loop is stable")
    line = numerics_warning(model, integrator, hh, speed=speed, sample_rate=sample_rate, rho_inf=rho_inf,
                            loop=lm, exact=ex)
    if line:
        rep.warnings.append(line)
    return rep


def identify_poles(Y: np.ndarray, rows: int = 40, cols: int = 1500, tol: float = 1e-10) -> np.ndarray:
    """Discrete poles (per sample) identified from a free response ``Y`` (samples x outputs) by the
    eigensystem realisation algorithm (Juang & Pappa 1985): an independent reading of a simulated
    loop's modes, to check the loop maps above against what the kernels actually do."""
    N, m = Y.shape
    J = np.unique(np.linspace(0, N - rows - 2, cols).astype(int))
    idx = J[None, :] + np.arange(rows)[:, None]
    H0 = Y[idx].transpose(0, 2, 1).reshape(rows * m, len(J))
    H1 = Y[idx + 1].transpose(0, 2, 1).reshape(rows * m, len(J))
    U, s, Vt = np.linalg.svd(H0, full_matrices=False)
    r = int(np.sum(s > tol * s[0]))
    Si = 1 / np.sqrt(s[:r])
    return np.linalg.eigvals((Si[:, None] * (U[:, :r].T @ H1 @ Vt[:r].T)) * Si[None, :])
