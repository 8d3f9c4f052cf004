"""Figures of the timing study (loop/timing_study.py): the rate x latency map, the stability
margin against latency at the scene's rate, the variance against jitter and loss."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.colors  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402

from .timing_study import ZONE_LIMITS, StudyResult  # noqa: E402


def _grid(res: StudyResult, key: str, speed: float):
    """(rates, latency axis, values, boundary) with latency in periods when the grid was given in
    periods (a regular grid), else in us."""
    rows = [g for g in res.grid if g["speed_rad_s"] == speed]
    rates = np.array([g["rate_hz"] for g in rows])
    f = (lambda g: g["rate_hz"]) if res.spec.in_periods else (lambda g: 1e6)
    lat = np.array([[p["latency_s"] * f(g) for p in g["points"]] for g in rows])
    val = np.array([[np.nan if p.get(key) is None else p[key] for p in g["points"]] for g in rows], float)
    bound = np.array([g["largest_latency_s"] * f(g) for g in rows])
    return rates, lat, val, bound


def rate_latency_map(res: StudyResult, path: Path, speed: float | None = None) -> Path:
    """Growth rate of the worst mode (colour) and sensitivity peak (ISO zone contours) over rate
    x latency, with the stability boundary found by bisection and the scene's operating point."""
    speed = res.spec.speeds[0] if speed is None else speed
    rates, lat, g, bound = _grid(res, "growth_rate", speed)
    _, _, S, _ = _grid(res, "sensitivity_peak", speed)
    R = np.repeat(rates[:, None], lat.shape[1], axis=1)
    fig, ax = plt.subplots(figsize=(8.5, 5.5))
    lim = max(np.nanmax(np.abs(g)), 1.0)
    norm = matplotlib.colors.SymLogNorm(linthresh=1.0, vmin=-lim, vmax=lim)
    pc = ax.pcolormesh(R / 1e3, lat, g, cmap="RdBu_r", norm=norm, shading="nearest")
    fig.colorbar(pc, ax=ax, label="growth rate of the worst mode (1/s); > 0 unstable")
    if np.isfinite(S).sum() > 3 and len(rates) > 1 and lat.shape[1] > 1:
        Sf = np.where(np.isfinite(S), S, 1e3)
        cs = ax.contour(R / 1e3, lat, Sf, levels=[ZONE_LIMITS["A"], ZONE_LIMITS["B"]], colors=["k", "0.4"],
                        linestyles=["-", "--"], linewidths=1)
        ax.clabel(cs, fmt={ZONE_LIMITS["A"]: "ISO A|B (S=3)", ZONE_LIMITS["B"]: "B|C (S=4)"}, fontsize=8)
    b = np.where(np.isfinite(bound), bound, np.nan)
    ax.plot(rates / 1e3, b, "k.-", lw=2, label="stability boundary (largest latency)")
    sp = res.scene_point
    ax.plot(sp["rate_hz"] / 1e3, sp["latency_s"] * (sp["rate_hz"] if res.spec.in_periods else 1e6), "*", ms=16,
            mfc="gold", mec="k", label=f"scene: {sp['rate_hz'] / 1e3:g} kHz, {sp['latency_s'] * 1e6:g} us"
                                       + ("" if sp["stable"] else " (UNSTABLE)"))
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.set_xlabel("controller sample rate (kHz)")
    ax.set_ylabel("loop latency beyond the controller's own delay "
                  + ("(controller periods)" if res.spec.in_periods else "(us)"))
    ax.set_ylim(0, np.nanmax(lat))
    ax.set_title(f"{res.scene} [{res.rung}] at {speed / (2 * math.pi):.1f} Hz spin: sampled-loop stability")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def margin_against_latency(res: StudyResult, path: Path) -> Path:
    """Spectral radius and least damping ratio against latency, at the scene's rate (from the grid
    row nearest to it), with the boundary."""
    fs0 = res.scene_point["rate_hz"]
    rows = [g for g in res.grid if g["speed_rad_s"] == res.spec.speeds[0]]
    g = min(rows, key=lambda r: abs(math.log(r["rate_hz"] / fs0)))
    lat = np.array([p["latency_s"] * 1e6 for p in g["points"]])
    zeta = np.array([p["min_damping_ratio"] for p in g["points"]])
    rho = np.array([p["spectral_radius"] for p in g["points"]])
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(lat, zeta, "o-")
    ax[0].axhline(0, color="r", lw=1)
    ax[0].set_xlabel("loop latency (us)")
    ax[0].set_ylabel("least damping ratio of the sampled loop")
    ax[1].plot(lat, rho, "o-")
    ax[1].axhline(1, color="r", lw=1, label="stability limit")
    ax[1].set_xlabel("loop latency (us)")
    ax[1].set_ylabel("spectral radius per period")
    bound = g["largest_latency_s"] * 1e6
    for a in ax:
        if math.isfinite(bound):
            a.axvline(bound, color="k", ls="--", lw=1, label=f"boundary {bound:.1f} us")
        if a.get_legend_handles_labels()[0]:  # no legend without a labelled artist
            a.legend(fontsize=8)
    fig.suptitle(f"{res.scene} [{res.rung}] at {g['rate_hz']:g} Hz")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def variance_against_jitter(res: StudyResult, path: Path) -> Path | None:
    """Stationary displacement standard deviation against jitter width and loss probability."""
    pts = [j for j in res.jitter if j.get("y_std_m") is not None]
    if len(pts) < 2:
        return None
    fig, ax = plt.subplots(figsize=(7, 4))
    base = pts[0]["y_std_m"]
    labels = [f"{j['jitter']}, loss {j['loss']:.3g}" for j in pts]
    vals = [j["y_std_m"] / base if math.isfinite(j["y_std_m"]) and math.isfinite(base) else np.nan for j in pts]
    ax.barh(range(len(pts)), vals, color=["C0" if j["ms_stable"] else "C3" for j in pts])
    ax.set_yticks(range(len(pts)), labels, fontsize=8)
    ax.axvline(1, color="k", lw=1)
    ax.set_xlabel("displacement std / std without jitter (red: not mean-square stable)")
    ax.set_title(f"{res.scene} [{res.rung}] at {res.scene_point['rate_hz']:g} Hz: jitter and loss ({pts[0]['noise']})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
