"""The timing study: what sample rate and loop latency a rotor tolerates, with what margin.

Each point of the grid (controller rate fs = 1/T, loop latency tau, spin speed) is the exact
sampled loop of ``loop/sampled.py`` with the scene's plant (any rung) and the scene's controller
rediscretised at fs.  A point reports the spectral radius, growth rate and frequency of the worst
mode, the smallest damping ratio, the ISO 14839-3 sensitivity peak of the sampled loop and its
zone, and the unbalance amplitude at the sensors.  With jitter and lost updates it reports
mean-square stability and the stationary standard deviation of displacement and current under
noise (``loop/jitter.py``).  Derived answers: per rate the largest tolerable latency (bisection
on the spectral radius), the lowest rate for an ISO zone at a given latency, the scene's own
latency margin.

Grids run on Dask (``dask.distributed``): one task per (rate, speed), in-process by default,
a ``LocalCluster`` of N processes, or an existing scheduler; each worker compiles the scene's
model once (``_model``) and reuses it for every point it gets.
"""
from __future__ import annotations

import hashlib
import math
import pickle
from dataclasses import dataclass, field

import numpy as np

from . import jitter as jt
from . import sampled as sd
from . import units
from .system import System, compile_system, controller_runner

ZONE_LIMITS = {"A": 3.0, "B": 4.0, "C": 5.0}
GIVE_UP = 0.1  # s: the latency up to which the boundary search looks


# --------------------------------------------------------------------------- one model per worker
_MODELS: dict = {}


def _model(scene, rung: str | None, speed: float) -> "TimingModel":
    key = (hashlib.sha1(pickle.dumps(scene)).hexdigest(), rung, float(speed))
    if key not in _MODELS:
        _MODELS[key] = TimingModel(compile_system(scene, rung), speed)
    return _MODELS[key]


class TimingModel:
    """The continuous plant of one system at one speed, and its sampled loops by rate."""

    def __init__(self, system: System, speed: float, grid: bool = True):
        self.system, self.speed, self.grid = system, float(speed), grid
        self.plant = sd.plant_of(system, speed)
        self._loops: dict = {}
        self._unb = system.unbalance_forces(speed) if speed > 0 else None

    def loop(self, rate: float, max_latency: float = 0.0) -> sd.SampledLoop:
        runner = controller_runner(self.system, sample_rate=rate)
        d_need = sd.split(max_latency + runner.config.delay_samples / rate, 1.0 / rate)[0] + 1
        if (rate, d_need) in self._loops:  # exact key: a result never depends on what ran before
            return self._loops[(rate, d_need)]
        lp = sd.SampledLoop(self.plant, sd.controller_of(runner), max_latency=d_need / rate, modal_holds=self.grid)
        self._loops[(rate, d_need)] = lp
        return lp

    def radius(self, rate: float, tau: float) -> float:
        lp = self.loop(rate, tau)
        return float(np.max(np.abs(np.linalg.eigvals(lp.mode(tau)))))

    def point(self, rate: float, tau: float, sensitivity: bool = True) -> dict:
        lp = self.loop(rate, tau)
        st = sd.stability(lp.mode(tau), lp.T)
        out = {"rate_hz": rate, "latency_s": tau, "latency_periods": tau * rate, "speed_rad_s": self.speed,
               "spectral_radius": st.spectral_radius, "growth_rate": st.growth_rate,
               "mode_hz": st.frequency_hz, "min_damping_ratio": st.min_damping_ratio,
               "min_damping_hz": st.min_damping_hz, "stable": st.stable}
        skipped = {}  # figure -> why it is not computed (never a non-finite number)
        if sensitivity and st.stable:
            peak, fpk, zone, _ = sd.sensitivity_peak(lp, tau)
            out.update(sensitivity_peak=peak, sensitivity_hz=fpk, zone=zone)
        else:
            out.update(sensitivity_peak=None, sensitivity_hz=None, zone="unstable" if sensitivity else None)
            skipped["sensitivity_peak"] = "the sampled loop is unstable" if sensitivity else "not requested"
        if self._unb is not None and st.stable:
            amp = np.abs(sd.unbalance_amplitudes(lp, tau, self._unb, self.speed))
            out["unbalance_max_m"] = float(amp.max())
        else:
            out["unbalance_max_m"] = None
            skipped["unbalance_max_m"] = "the sampled loop is unstable" if self._unb is not None else "no spin"
        out["not_computed"] = not_computed(skipped)
        return out

    # ---- derived answers
    def largest_latency(self, rate: float, tau_max: float, tol: float | None = None, give_up: float = GIVE_UP) -> float:
        """Largest latency with every smaller latency stable: a scan in steps of T/8 up to
        ``tau_max``, then (still stable) doubling until unstable, then bisection on the spectral
        radius to ``tol``; 0 if unstable without latency, ``inf`` if stable up to ``give_up`` s."""
        T = 1.0 / rate
        tol = tol or 1e-3 * T
        if self.radius(rate, 0.0) >= 1.0:
            return 0.0
        lo, hi = 0.0, None
        for tau in np.arange(T / 8, tau_max + 1e-15 * T, T / 8):
            if self.radius(rate, tau) >= 1.0:
                hi = tau
                break
            lo = tau
        while hi is None:
            if 2 * lo > give_up:
                return math.inf
            if self.radius(rate, 2 * lo) >= 1.0:
                hi = 2 * lo
            else:
                lo = 2 * lo
        while hi - lo > tol:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self.radius(rate, mid) < 1.0 else (lo, mid)
        return lo

    def jitter_point(self, rate: float, tau0: float, dist: "Latency", noise: "Noise") -> dict:
        values, probs = dist.modes(tau0, 1.0 / rate)
        lp = self.loop(rate, float(values.max()) if len(values) else tau0)
        Fs, Ws = [], []
        skipped = {}
        try:
            Qf = noise.force_covariance(lp)
        except FloatingPointError as e:  # no variance figures, the stability verdict still holds
            Qf, skipped["y_std_m"] = np.zeros((lp.plant.n, lp.plant.n)), str(e)
        for tau in values:
            F, E = lp.mode(tau, with_input=True)
            Fs.append(F)
            Ws.append(noise.covariance(lp, E, Qf))
        if dist.loss > 0:
            F = lp.lost()
            E = np.zeros((lp.layout.size, lp.layout.na))
            if lp.layout.D:
                E[lp.layout.buf(0)] = np.eye(lp.layout.na)
            Fs.append(F)
            Ws.append(noise.covariance(lp, E, Qf))
        p = np.concatenate([probs * (1.0 - dist.loss), [dist.loss] if dist.loss > 0 else []])
        js = jt.JumpSystem(tuple(Fs), p, tuple(Ws))
        ms = jt.ms_test(js)
        out = {"rate_hz": rate, "latency_s": tau0, "jitter": dist.label, "loss": dist.loss,
               "ms_stable": ms.stable, "mean_radius": ms.mean_radius,
               "jitter_ratio": ms.jitter_ratio if math.isfinite(ms.jitter_ratio) else None,
               "noise": noise.label, "y_std_m": None, "u_std_A": None,
               "worst_case_lower": None, "worst_case_upper": None}
        if out["jitter_ratio"] is None:
            skipped["jitter_ratio"] = ("the mean loop is unstable" if ms.mean_radius >= 1.0
                                       else "the splitting iteration diverged")
        L = lp.layout
        P, why = None, skipped.pop("y_std_m", None)
        if why is None and not ms.stable:
            why = "not mean-square stable: no stationary variance"
        if why is None:
            try:
                P = jt.stationary_covariance(js)
            except ValueError as e:  # at the boundary the fixed point does not converge: not stationary
                why = str(e)
        if P is not None:
            Cy = lp.plant.C
            y = float(np.sqrt(np.max(np.diag(Cy @ P[L.x, L.x] @ Cy.T))))
            u = float(np.sqrt(np.max(np.diag(P[L.a, L.a]))))
            if math.isfinite(y) and math.isfinite(u):
                out.update(y_std_m=y, u_std_A=u)
                try:
                    lo, hi = jt.worst_case_bound(js)
                    out["worst_case_lower"] = lo if math.isfinite(lo) else None
                    out["worst_case_upper"] = hi if math.isfinite(hi) else None
                    if out["worst_case_upper"] is None:
                        skipped["worst_case_upper"] = "no mean-square Lyapunov ellipsoid"
                except np.linalg.LinAlgError as e:
                    skipped["worst_case_lower"] = skipped["worst_case_upper"] = f"singular ellipsoid ({e})"
            else:
                why = "the stationary covariance is not finite"
        if why is not None:
            skipped = {k: why for k in ("y_std_m", "u_std_A", "worst_case_lower", "worst_case_upper")} | skipped
        out["not_computed"] = not_computed(skipped)
        return out


def not_computed(skipped: dict) -> str:
    """``"figure, figure: why; figure: why"`` for the figures a point leaves None (a study never
    reports a non-finite number as a result); "" when everything was computed."""
    by: dict = {}
    for k, why in skipped.items():
        by.setdefault(why, []).append(k)
    return "; ".join(f"{', '.join(ks)}: {why}" for why, ks in by.items())


# --------------------------------------------------------------------------- latency distributions and noise
@dataclass(frozen=True)
class Latency:
    """Latency per period: the nominal tau plus a random part, and a probability of loss."""
    kind: str = "none"  # none | uniform | normal | empirical
    width: float = 0.0  # s: uniform [0, width] added; normal: sigma, clipped at +-3 sigma and at 0
    samples: np.ndarray | None = field(default=None, repr=False)  # empirical latencies, s
    loss: float = 0.0
    bins: int = 12

    @property
    def label(self) -> str:
        if self.kind == "empirical":
            return f"empirical ({len(self.samples)} samples)"
        return "none" if self.kind == "none" else f"{self.kind}:{self.width * 1e6:g}us"

    def modes(self, tau0: float, T: float) -> tuple[np.ndarray, np.ndarray]:
        """Latency values and probabilities (a histogram of ``bins`` cells)."""
        if self.kind == "none" or (self.kind != "empirical" and self.width == 0):
            return np.array([tau0]), np.array([1.0])
        if self.kind == "uniform":
            v = tau0 + self.width * (np.arange(self.bins) + 0.5) / self.bins
            return v, np.full(self.bins, 1.0 / self.bins)
        if self.kind == "normal":
            edges = np.linspace(-3 * self.width, 3 * self.width, self.bins + 1)
            from scipy.stats import norm
            p = np.diff(norm.cdf(edges / self.width))
            v = np.maximum(tau0 + 0.5 * (edges[1:] + edges[:-1]), 0.0)
            return v, p / p.sum()
        s = np.asarray(self.samples, float)
        counts, edges = np.histogram(s, bins=self.bins)
        keep = counts > 0
        return 0.5 * (edges[1:] + edges[:-1])[keep], counts[keep] / counts.sum()


@dataclass(frozen=True)
class Noise:
    """White disturbance for the variance figures: ``sensor`` (discrete, std in m per axis) or
    ``force`` (continuous white force at every AMB actuator, PSD in N^2/Hz, one-sided)."""
    kind: str = "sensor"
    level: float = 1e-6

    @property
    def label(self) -> str:
        return f"{self.kind}:{self.level:g}"

    def force_covariance(self, lp: sd.SampledLoop) -> np.ndarray | None:
        if self.kind != "force":
            return None
        Bw = lp.plant.Bw
        Q = Bw @ Bw.T * (self.level / 2.0)  # one-sided PSD -> two-sided intensity
        radius = float(np.max(np.abs(lp.eig_A[0])))
        return sd.noise_covariance(lp.plant.A, Q, lp.T, radius)  # int_0^T e^{A s} Q e^{A^T s} ds

    def covariance(self, lp: sd.SampledLoop, E: np.ndarray, Qf: np.ndarray | None) -> np.ndarray:
        L = lp.layout
        W = np.zeros((L.size, L.size))
        if self.kind == "sensor":
            G = lp.sensor_input(E)
            W += (self.level ** 2) * (G @ G.T)
        else:
            W[L.x, L.x] = Qf
        return W


def parse_latency(spec: str | None, loss: float = 0.0) -> Latency:
    """``uniform:20us``, ``normal:5us`` or None; ``loss`` a probability in [0, 1)."""
    if not 0.0 <= loss < 1.0:
        raise ValueError(f"--loss must be a probability in [0, 1), got {loss}")
    if not spec:
        return Latency(loss=loss)
    kind, _, w = spec.partition(":")
    if kind not in ("uniform", "normal") or not w:
        raise ValueError(f"--jitter must be uniform:WIDTH or normal:SIGMA (e.g. uniform:20us), got {spec!r}")
    return Latency(kind=kind, width=units.time(w, what="--jitter"), loss=loss)


# --------------------------------------------------------------------------- the grid, on Dask
@dataclass
class StudySpec:
    rates: np.ndarray  # Hz
    delays: np.ndarray  # latency values: periods if ``in_periods`` else s
    in_periods: bool = True
    speeds: tuple[float, ...] = (0.0,)
    rung: str | None = None
    sensitivity: bool = True
    latency: Latency = field(default_factory=Latency)
    noise: Noise = field(default_factory=Noise)
    zones: tuple[str, ...] = ("A", "B")

    def taus(self, rate: float) -> np.ndarray:
        return np.asarray(self.delays, float) / rate if self.in_periods else np.asarray(self.delays, float)

    def tau_max(self, rate: float) -> float:
        return max(float(self.taus(rate).max()), 3.0 / rate)


def _one_thread(fn):
    """Run a task with one BLAS thread: the numbers then do not depend on where it runs (Dask
    workers are started with one thread; BLAS results depend on the thread count)."""
    import functools

    @functools.wraps(fn)
    def task(*a, **k):
        from threadpoolctl import threadpool_limits
        with threadpool_limits(limits=1):
            return fn(*a, **k)
    return task


@_one_thread
def _grid_task(scene, spec: StudySpec, rate: float, speed: float) -> dict:
    m = _model(scene, spec.rung, speed)
    pts = [m.point(rate, float(tau), spec.sensitivity) for tau in spec.taus(rate)]
    return {"rate_hz": rate, "speed_rad_s": speed, "points": pts, **_boundary(m, rate, spec.tau_max(rate))}


def _boundary(m: TimingModel, rate: float, tau_max: float) -> dict:
    """The largest latency at ``rate``, or None with why (stable up to the search limit)."""
    lm = m.largest_latency(rate, tau_max)
    return {"largest_latency_s": lm if math.isfinite(lm) else None, "search_limit_s": GIVE_UP,
            "not_computed": "" if math.isfinite(lm) else
            f"largest_latency_s: stable at every latency up to {GIVE_UP * 1e3:g} ms (the search limit)"}


@_one_thread
def _jitter_task(scene, spec: StudySpec, rate: float, speed: float, tau0: float, dist: Latency) -> dict:
    return _model(scene, spec.rung, speed).jitter_point(rate, tau0, dist, spec.noise)


@_one_thread
def _zone_rate_task(scene, spec: StudySpec, speed: float, tau: float, zone: str, rates) -> dict:
    """Lowest rate (Hz) whose sampled sensitivity peak is inside ``zone`` at latency ``tau``:
    the grid first, then bisection (log rate) between the last failing and the first passing rate."""
    m = _model(scene, spec.rung, speed)
    lim = ZONE_LIMITS[zone]

    def ok(rate):
        if m.radius(rate, tau) >= 1.0:
            return False
        return sd.sensitivity_peak(m.loop(rate, tau), tau)[0] < lim
    rs = np.sort(np.asarray(rates, float))
    flags = [ok(r) for r in rs]
    if not flags[-1]:
        return {"zone": zone, "latency_s": tau, "lowest_rate_hz": None, "note": f"not reached up to {rs[-1]:g} Hz"}
    k = len(rs) - 1
    while k > 0 and flags[k - 1]:
        k -= 1
    if k == 0:
        return {"zone": zone, "latency_s": tau, "lowest_rate_hz": float(rs[0]), "note": "reached at the lowest rate studied"}
    lo, hi = rs[k - 1], rs[k]
    while hi / lo > 1.002:
        mid = math.sqrt(lo * hi)
        lo, hi = (lo, mid) if ok(mid) else (mid, hi)
    return {"zone": zone, "latency_s": tau, "lowest_rate_hz": float(hi), "note": ""}


@dataclass
class StudyResult:
    scene: str
    rung: str
    spec: StudySpec
    grid: list  # one dict per (rate, speed): points + largest latency
    scene_point: dict  # the scene's own rate and latency: point, largest latency, margin
    zone_rates: list
    jitter: list
    scene_row: dict | None = None  # the scene's own rate over the study's latencies (and 0): points, boundary

    @property
    def points(self) -> list[dict]:
        return [p for g in self.grid for p in g["points"]]


def client_for(workers: int | None = None, scheduler: str | None = None):
    """A Dask client: an existing scheduler by address, a LocalCluster of ``workers`` processes,
    or (default) an in-process cluster of one thread."""
    import logging
    from dask.distributed import Client, LocalCluster
    logging.getLogger("distributed").setLevel(logging.ERROR)
    if scheduler:
        return Client(scheduler)
    if workers and workers > 1:
        return Client(LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=":0"))
    return Client(LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0"))


def run(scene, spec: StudySpec, client, progress=None) -> StudyResult:
    """Evaluate the grid, the scene's own point and margin, the lowest rates per ISO zone and the
    jitter/loss points; ``progress(done, total)`` is called as tasks finish."""
    from dask.distributed import as_completed
    fs0 = scene.controller.sample_rate
    speed0 = spec.speeds[0]
    tau0 = 0.0  # the latency beyond the controller's own delay_samples
    sc = client.scatter(scene, broadcast=True)
    futs = [client.submit(_grid_task, sc, spec, float(r), float(w), pure=False)
            for w in spec.speeds for r in spec.rates]
    own = client.submit(_own_task, sc, spec, fs0, speed0, pure=False)
    zfuts = [client.submit(_zone_rate_task, sc, spec, speed0, tau0, z, spec.rates, pure=False) for z in spec.zones]
    jfuts = [client.submit(_jitter_task, sc, spec, fs0, speed0, tau0, d, pure=False) for d in _jitter_sweep(spec.latency)]
    allf = futs + [own] + zfuts + jfuts
    for k, _ in enumerate(as_completed(allf)):
        if progress:
            progress(k + 1, len(allf))
    grid = [f.result() for f in futs]
    o = own.result()
    lmax = o["largest_latency_s"]
    scene_point = dict(o["points"][0], largest_latency_s=lmax,
                       margin_s=None if lmax is None else lmax - tau0,
                       margin_periods=None if lmax is None else (lmax - tau0) * fs0)
    if lmax is None:
        why = f"largest_latency_s, margin_s, margin_periods: stable at every latency up to {GIVE_UP * 1e3:g} ms"
        scene_point["not_computed"] = "; ".join(t for t in (scene_point["not_computed"], why) if t)
    m = compile_system(scene, spec.rung)
    return StudyResult(scene.name, m.rung, spec, grid, scene_point, [f.result() for f in zfuts],
                       [f.result() for f in jfuts], scene_row=o)


@_one_thread
def _own_task(scene, spec: StudySpec, fs0: float, speed: float) -> dict:
    """The scene's own rate: its point at the scene's latency (first, with sensitivity), the
    boundary, and stability over latency (the margin plot): the study's latencies at this rate
    and 12 steps up to 1.25 times the boundary (or the study's largest latency)."""
    m = _model(scene, spec.rung, speed)
    bound = _boundary(m, fs0, spec.tau_max(fs0))
    lm = bound["largest_latency_s"]
    top = max(float(spec.taus(fs0).max()), 1.25 * lm if lm else 0.0)
    taus = np.unique(np.concatenate([spec.taus(fs0), np.linspace(0.0, top, 13)]))
    pts = [m.point(fs0, 0.0, spec.sensitivity)] + [m.point(fs0, float(t), False) for t in taus[taus > 0]]
    return {"rate_hz": fs0, "speed_rad_s": speed, "points": pts, **bound}


def _jitter_sweep(lat: Latency) -> list[Latency]:
    """The distributions of the variance-against-jitter figure: no jitter, the width swept up to
    the requested one, the loss swept up to the requested one; or the measured one."""
    from dataclasses import replace
    if lat.kind == "empirical":
        return [Latency(), replace(lat, loss=0.0)] + ([lat] if lat.loss > 0 else [])
    out = [Latency()]
    if lat.kind != "none" and lat.width > 0:
        out += [replace(lat, width=lat.width * f, loss=0.0) for f in (0.25, 0.5, 0.75, 1.0)]
    if lat.loss > 0:
        out += [Latency(kind=lat.kind, width=lat.width, loss=lat.loss * f) for f in (0.25, 0.5, 1.0)]
    return out


# --------------------------------------------------------------------------- the check before a run
@dataclass(frozen=True)
class Precheck:
    stable: bool
    line: str | None  # one line for the user, None when nothing is worth saying


def precheck(system: System, speed: float, latency: float = 0.0, margin_periods: float = 0.25,
             rate: float | None = None) -> Precheck:
    """Check the scene's sampled loop (its rate, its delay, ``latency``) before a run: unstable
    (saying whether the continuous loop is stable, the growing mode, the nearest stable rate) or
    less than ``margin_periods`` of latency margin."""
    m = TimingModel(system, speed, grid=False)
    fs = float(rate or system.scene.controller.sample_rate)
    T = 1.0 / fs
    st = sd.stability(m.loop(fs, latency + margin_periods * T).mode(latency), T)
    where = f"{fs:g} Hz" + (f" with {latency * 1e6:g} us latency" if latency else "")
    if st.stable:
        if m.radius(fs, latency + margin_periods * T) > 1.0 + sd.STABILITY_TOL:
            return Precheck(True, f"the sampled loop at {where} is stable but has less than {margin_periods:g} "
                                  f"periods ({margin_periods * T * 1e6:.3g} us) of latency margin: "
                                  f"`ambhil study timing` shows how much")
        return Precheck(True, None)
    from .analysis.modal import Solver
    cont = max(mm.eigenvalue.real for mm in Solver(system).all(speed, 2 * np.pi * 0.5 * fs))
    head = ("the continuous loop is stable but the sampled loop is not" if cont < 0
            else "the loop is unstable (continuous and sampled)")
    txt = (f"{head}: at {where} a mode at {st.frequency_hz:.4g} Hz grows at {st.growth_rate:.3g} 1/s "
           f"(spectral radius {st.spectral_radius:.6f} per period)")
    if cont < 0:
        r = fs
        for _ in range(12):
            r *= 1.25
            if m.radius(r, latency) < 1.0:
                lo, hi = r / 1.25, r
                while hi / lo > 1.01:
                    mid = math.sqrt(lo * hi)
                    lo, hi = (lo, mid) if m.radius(mid, latency) < 1.0 else (mid, hi)
                txt += f"; nearest stable rate at this latency: {hi:.0f} Hz"
                break
        else:
            txt += f"; no stable rate up to {r:.0f} Hz at this latency"
    return Precheck(False, txt)
