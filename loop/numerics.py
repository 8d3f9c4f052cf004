"""The numerics of the simulated loop: each scheme's amplification and numerical damping over a
controller period, and the checks that say when a scheme misreports the physical loop
(:func:`numerics_warning`: one line; :func:`check_numerics`: mode by mode against the exact and
the continuous closed loop of :mod:`ambhil.loop.analysis.modal`).  The loops compared are the
one-period maps of :mod:`ambhil.loop.period_map` (the simulated loop the kernels integrate; with
``zoh`` the exact, physical sampled loop)."""
from __future__ import annotations

from dataclasses import dataclass, field

import math

import numpy as np

from ambhil.plant import contact_step, plan as pl
from .period_map import STABILITY_TOL, LoopModes, physical_loop, sampled_loop
from .system import System, controller_runner


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


#: the stated tolerance of the numerics check: the simulated loop's decay/growth rate of the
#: exact sampled loop's least-damped mode may be off by this fraction of the exact rate.  A
#: lightly damped mode's resonance peak scales as 1 / rate, so 25 % is about 2 dB on that peak
#: (the spacing of the ISO 14839-3 sensitivity zone limits 3, 4, 5) and 25 % of the stability
#: margin the loop has in that mode.  Frequency errors alone (trapezoidal warping) are not warned
#: about: they change neither the verdict nor the margin.
RATE_TOLERANCE = 0.25
#: ... and the steady unbalance response at the sensors (the orbits simulate and run print) may
#: differ from the exact sampled loop's by this fraction (complex: amplitude and phase in one), the
#: 5 % the rungs and schemes are held to
ORBIT_TOLERANCE = 0.05
_RATIOS = (1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 25, 32, 40, 50, 64, 80, 100, 128, 160, 200)


def resolving_step(s: complex, period: float, rho_inf: float = 0.8,
                   schemes=("trapezoidal", "bdf2", "generalized-alpha", "bdf1"),
                   tolerance: float = RATE_TOLERANCE) -> tuple[str, int] | None:
    """Cheapest (scheme, steps per controller period) that keeps the rate of a mode ``s`` (1/s,
    continuous-time equivalent of a loop eigenvalue) within ``tolerance`` of ``Re s``: the scheme's
    exact amplification over a controller period as the kernel takes it
    (:func:`period_amplification`) applied to ``s``.  None if none does up to 200 steps."""
    best = None
    sr = abs(float(np.real(s)))
    for sc in schemes:
        for r in _RATIOS:
            if best is not None and r >= best[1]:
                break
            h = period / r
            sd = np.log(period_amplification(sc, s * h, r, rho_inf)) / period
            if abs(sd.real - s.real) <= tolerance * sr:
                best = (sc, r)
                break
    return best


def match_mode(loop: LoopModes, exact: LoopModes, k: int, n: int | None = None) -> int | None:
    """Index of ``loop``'s mode that is ``exact``'s mode ``k`` (upper half plane): by the modal
    assurance criterion of the displacement part of the eigenvectors when both loops carry them
    (``n`` coordinates; a scheme may move a mode's frequency by 15 % and its rate 100-fold, so
    the nearest eigenvalue can be another mode), else the nearest eigenvalue."""
    s = loop.s
    up = np.where((s.imag > 1e-6) & np.isfinite(s.real))[0]
    if not len(up):
        return None
    if n and loop.V is not None and exact.V is not None:
        qe = exact.V[:n, k]
        Q = loop.V[:n, up]
        num = np.abs(Q.conj().T @ qe) ** 2
        den = np.einsum("ij,ij->j", Q.conj(), Q).real * np.vdot(qe, qe).real
        mac = num / np.where(den > 0, den, np.inf)
        j = int(np.argmax(mac))
        if mac[j] >= 0.5:
            return int(up[j])
    return int(up[np.argmin(np.abs(s[up] - exact.s[k]))])


def _roundoff_rate(period: float) -> float:
    """Rates (1/s) below this are zero within the eigenvalue accuracy (STABILITY_TOL per period)."""
    return STABILITY_TOL / period


def orbit_error(loop: LoopModes, exact: LoopModes) -> float | None:
    """|Y - Y_exact| / |Y_exact| of the steady unbalance responses at the sensors (None when
    either loop lacks one: no unbalance, no spin, or not computed)."""
    if loop.unbalance is None or exact.unbalance is None:
        return None
    ref = float(np.linalg.norm(exact.unbalance))
    return float(np.linalg.norm(loop.unbalance - exact.unbalance) / ref) if ref > 0 else None


def numerics_warning(model: System, integrator: str, h: float | None = None, *, speed: float | None = None,
                     sample_rate: float | None = None, rho_inf: float | None = None, method: str | None = None,
                     loop: LoopModes | None = None, exact: LoopModes | None = None) -> str | None:
    """One line when the plant integrator changes what the simulated loop says (None otherwise):

    * the stability verdict: the simulated loop (``loop``: the scheme at step ``h`` with the
      scene's discrete controller, as the kernels run it) is stable and the exact sampled loop
      (``exact``: the plant integrated exactly, zoh, same controller; the physical loop) is not,
      or the other way round;
    * the margin: the rate (Re s, 1/s) of the exact loop's least-damped in-band mode differs in
      the simulated loop by more than RATE_TOLERANCE (25 %) of the exact rate; or
    * the orbit: the steady unbalance response at the sensors differs by more than
      ORBIT_TOLERANCE (5 %) (:func:`unbalance_response`; when both loops carry it).

    The line is labelled ``numerical damping`` when the scheme's own damping at that mode
    (:func:`numerical_damping`, over a controller period as simulated) explains at least half of
    the rate error, ``numerical error`` otherwise; it names the mode, both rates, the tolerance
    and the cheapest scheme and step that keep the rate within it (:func:`resolving_step`)."""
    if integrator == "zoh":
        return None
    ctrl = controller_runner(model, sample_rate=sample_rate, method=method)
    T = ctrl.period
    hh = h or T
    rho = rho_inf
    if rho is None:
        rho = getattr(getattr(model.scene, "simulation", None), "rho_inf", None) or 0.8
    if exact is None:
        exact = physical_loop(model, speed=speed, sample_rate=sample_rate, method=method)
    if loop is None:
        loop = sampled_loop(model, integrator, hh, speed=speed, ctrl=ctrl, rho_inf=rho, vectors=True,
                            response=True)
    sim = f"{integrator} at h={hh:.3g} s"
    oe = orbit_error(loop, exact) if loop.stable and exact.stable else None
    part, fix = _mode_warning(loop, exact, integrator, hh, T, rho, model.n)
    parts = [part] if part else []
    if oe is not None and oe > ORBIT_TOLERANCE:
        txt = _orbit_text(loop, exact, oe, speed)
        if not parts:
            parts.append(f"numerical error: {sim}: {txt}")
            fix = "orbit"
        else:
            parts.append(txt)
    if not parts:
        return None
    contact = any(getattr(a, "auxiliary", None) is not None for a in model.spec.ambs)
    if contact and isinstance(fix, tuple):   # the step must also resolve a contact (plant/contact_step.py)
        tc = min(tc for tc, _ in contact_step.resolution(model, T).values())
        need = math.ceil(T * contact_step.GOOD_STEPS / tc)
        if need > fix[1]:
            fix = (fix[0], next((r for r in _RATIOS if r >= need), need))
    return "; ".join(parts) + _remedy(fix, T, contact)


#: how the warning names the physical loop
_EXACT = "the exact sampled loop (plant integrated exactly, same discrete controller)"


def _mode_warning(loop: LoopModes, exact: LoopModes, integrator: str, hh: float, T: float, rho: float,
                  n: int) -> tuple[str | None, tuple[str, int] | None]:
    """The verdict and margin part of :func:`numerics_warning`, about one mode of the exact loop
    (its least-damped in-band mode; on a stability flip the growing one): (the text, None when
    that mode is within the tolerance; the scheme and steps per period that resolve the mode,
    :func:`resolving_step`, None for a non-oscillatory mode)."""
    floor = _roundoff_rate(T)
    flip = exact.stable != loop.stable
    k = exact.least_damped()
    if flip and (k is None or (not exact.stable and exact.s[k].real <= floor)):
        k = exact.dominant  # the growing mode is not an in-band oscillatory one: name the dominant
    if k is None:
        return None, None
    sim = f"{integrator} at h={hh:.3g} s"
    se = exact.s[k]
    w, f = abs(se.imag), abs(se.imag) / (2 * np.pi)
    zeta = float(-se.real / abs(se)) if abs(se) > 0 else 0.0
    j = match_mode(loop, exact, k, n)
    sl = loop.s[j] if j is not None else complex(-np.inf)
    err = float(sl.real - se.real)
    tol = RATE_TOLERANCE * abs(se.real)
    zn = numerical_damping(integrator, w, hh, rho, ratio=max(1, int(round(T / hh)))) if w > 0 else 0.0
    zn = 0.0 if abs(zn) < 1e-12 else zn
    label = "numerical damping" if zn * w >= 0.5 * abs(err) and err < 0 else "numerical error"

    def rate(x: complex) -> str:
        return f"{'grows' if x.real > floor else 'decays'} at {abs(x.real):.3g} 1/s"
    fix = resolving_step(se, T, rho) if w > 0 else None
    if flip and not exact.stable:
        mode = f"{f:.4g} Hz mode (zeta {zeta:.2g})" if w > 0 else "non-oscillatory mode"
        got = f"{abs(sl.imag) / 2 / np.pi:.4g} Hz, {rate(sl)}" if j is not None else "no such mode"
        return (f"{label} hides an instability: in {_EXACT} the {mode} {rate(se)}, but {sim} has it at "
                f"{got} (numerical damping zeta {zn:.2g}): the simulated loop looks stable and the run "
                f"cannot show the growth"), fix
    if flip:
        return (f"numerical error shows a false instability: {sim} makes the loop unstable "
                f"({loop.describe(loop.dominant)}) where {_EXACT} is stable"), fix
    if not (np.isfinite(err) and abs(err) > max(tol, floor)):
        return None, fix
    mname = f"the loop's least-damped mode ({f:.4g} Hz, zeta {zeta:.2g})"
    if se.real > floor:
        what = f"{'slows' if err < 0 else 'speeds up'} the growth of {mname} by {abs(err):.3g} 1/s"
        so = ("understates" if err < 0 else "overstates") + " how fast the loop diverges"
    else:
        what = (f"{'adds' if err < 0 else 'removes'} {abs(err):.3g} 1/s of decay {'to' if err < 0 else 'from'} "
                f"{mname}")
        so = ("overstates" if err < 0 else "understates") + " the loop's stability margin"
    return (f"{label}: {sim} {what}: it {rate(se)} in {_EXACT}, {rate(sl)} in the simulated loop (at "
            f"{abs(sl.imag) / 2 / np.pi:.4g} Hz; numerical damping zeta {zn:.2g}); tolerance {tol:.3g} "
            f"1/s ({RATE_TOLERANCE:.0%} of the exact rate): the simulation {so}"), fix


def _orbit_text(loop: LoopModes, exact: LoopModes, oe: float, speed: float | None) -> str:
    """The orbit part of :func:`numerics_warning`: how far the steady unbalance response is off."""
    amp = float(np.linalg.norm(loop.unbalance) / np.linalg.norm(exact.unbalance) - 1)
    W = float(np.real(speed)) if speed is not None else None
    at = f" at {W:.4g} rad/s" if W else ""
    return (f"the steady unbalance response at the sensors{at} is {abs(amp):.1%} {'smaller' if amp < 0 else 'larger'} "
            f"than in the exact sampled loop (complex error {oe:.1%}; tolerance {ORBIT_TOLERANCE:.0%})")


def _remedy(fix, T: float, contact: bool = False) -> str:
    """The warning's closing clause: what keeps the error within the tolerance (``fix``: the
    scheme and steps per period of :func:`resolving_step`, ``"orbit"``, or None); with auxiliary
    bearings (``contact``) zoh is not offered (it cannot integrate contact) and the step offered
    also resolves a contact."""
    zoh = "" if contact else "; zoh is exact (linear scenes)"
    if fix == "orbit":
        return "; a second-order scheme (trapezoidal) or a smaller step reduces it" + zoh
    if fix:
        return (f"; {fix[0]} at h={T / fix[1]:.3g} s ({fix[1]} step{'s' if fix[1] > 1 else ''} per controller "
                f"period) keeps that mode's rate within the tolerance" + zoh)
    return zoh


def numerics_skipped(nonlinear: bool = False, run_up: bool = False, latency: float = 0.0) -> str | None:
    """Why the numerics check does not run for this simulation (None when it does): it compares
    linear time-invariant loop maps, so it needs the linearised force law, a constant speed and no
    loop latency."""
    why = [w for w, c in (("the exact AMB force law (nonlinear)", nonlinear), ("a speed run-up", run_up),
                          ("a loop latency", bool(latency))) if c]
    if not why:
        return None
    return (f"numerics check skipped: it compares linear time-invariant loops, and this run has "
            f"{' and '.join(why)}; run the same scene linear at constant speed to check the integrator and step")


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


def numerics_note(model: System, integrator: str | None = None, h: float | None = None, *,
                  speed: float | None = None, nonlinear: bool = False, run_up: bool = False,
                  latency: float = 0.0) -> tuple[str, str] | None:
    """What the CLIs print before a run about the plant integrator: ``("warning", line)`` when
    :func:`numerics_warning` speaks, ``("note", why)`` when the check cannot run
    (:func:`numerics_skipped`), None when the integrator is within the tolerance.  ``integrator``
    / ``h``: the flags (None: the scene's; the ancf rung's DAE scheme as its runner chooses it)."""
    why = numerics_skipped(nonlinear, run_up, latency)
    if why:
        return "note", why
    sim = model.spec.simulation
    scheme = integrator or sim.integrator
    if model.rung == "ancf" and not integrator:
        from ambhil.plant.ancf_step import default_scheme
        scheme = default_scheme(sim.integrator)
    line = numerics_warning(model, scheme, h or sim.step, speed=speed)
    return ("warning", line) if line else None
