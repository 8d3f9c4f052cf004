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
    """(rates, latency axis, values, boundary): rates ascending (Hz), the latency axis one value
    per column, in periods when the grid was given in periods, else in us (the same at every
    rate either way: the study's own ``delays``), values (rates x latencies, NaN where not
    computed), the boundary per rate (NaN where none was found)."""
    rows = sorted((g for g in res.grid if g["speed_rad_s"] == speed), key=lambda g: g["rate_hz"])
    rates = np.array([g["rate_hz"] for g in rows])
    lat = np.asarray(res.spec.delays, float) * (1.0 if res.spec.in_periods else 1e6)
    f = (lambda g: g["rate_hz"]) if res.spec.in_periods else (lambda g: 1e6)
    val = np.array([[np.nan if p.get(key) is None else p[key] for p in g["points"]] for g in rows], float)
    bound = np.array([np.nan if g["largest_latency_s"] is None else g["largest_latency_s"] * f(g) for g in rows])
    return rates, lat, val, bound


def _edges(c: np.ndarray, log: bool) -> np.ndarray:
    """Cell edges around sorted centres ``c`` (geometric midpoints on a log axis): one cell per
    value even where the grid is uneven, so nothing is left to pcolormesh to guess."""
    c = np.asarray(c, float)
    if len(c) == 1:
        return c * np.array([0.9, 1.1]) if log else c + np.array([-0.5, 0.5]) * max(abs(c[0]), 1.0)
    m = np.sqrt(c[1:] * c[:-1]) if log else 0.5 * (c[1:] + c[:-1])
    first = c[0] ** 2 / m[0] if log else 2 * c[0] - m[0]
    last = c[-1] ** 2 / m[-1] if log else 2 * c[-1] - m[-1]
    return np.concatenate([[first], m, [last]])


def rate_latency_map(res: StudyResult, path: Path, speed: float | None = None) -> Path:
    """Growth rate of the worst mode (colour) and sensitivity peak (ISO zone contours) over rate
    x latency, with the stability boundary found by bisection and the scene's operating point."""
    speed = res.spec.speeds[0] if speed is None else speed
    rates, lat, g, bound = _grid(res, "growth_rate", speed)
    _, _, S, _ = _grid(res, "sensitivity_peak", speed)
    order = np.argsort(lat)
    lat, g, S = lat[order], g[:, order], S[:, order]
    fig, ax = plt.subplots(figsize=(8.5, 5.5))
    lim = max(np.nanmax(np.abs(g)), 1.0)
    norm = matplotlib.colors.SymLogNorm(linthresh=1.0, vmin=-lim, vmax=lim)
    pc = ax.pcolormesh(_edges(rates, True) / 1e3, _edges(lat, False), g.T, cmap="RdBu_r", norm=norm,
                       shading="flat")
    fig.colorbar(pc, ax=ax, label="growth rate of the worst mode (1/s); > 0 unstable")
    if np.isfinite(S).sum() > 3 and len(rates) > 1 and len(lat) > 1:
        Sf = np.where(np.isfinite(S), S, 1e3)
        cs = ax.contour(rates / 1e3, lat, Sf.T, levels=[ZONE_LIMITS["A"], ZONE_LIMITS["B"]], colors=["k", "0.4"],
                        linestyles=["-", "--"], linewidths=1)
        ax.clabel(cs, fmt={ZONE_LIMITS["A"]: "ISO A|B (S=3)", ZONE_LIMITS["B"]: "B|C (S=4)"}, fontsize=8)
    b = np.where(np.isfinite(bound), bound, np.nan)
    ax.plot(rates / 1e3, b, "k.-", lw=2, label="stability boundary (largest latency)")
    sp = res.scene_point
    ax.plot(sp["rate_hz"] / 1e3, sp["latency_s"] * (sp["rate_hz"] if res.spec.in_periods else 1e6), "*", ms=16,
            mfc="gold", mec="k", clip_on=False, zorder=5,
            label=f"scene: {sp['rate_hz'] / 1e3:g} kHz, {sp['latency_s'] * 1e6:g} us"
                  + ("" if sp["stable"] else " (UNSTABLE)"))
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.set_xlabel("controller sample rate (kHz)")
    ax.set_ylabel("loop latency beyond the controller's own delay "
                  + ("(controller periods)" if res.spec.in_periods else "(us)"))
    ax.set_ylim(min(0.0, lat.min()), lat.max() if lat.max() > 0 else 1.0)
    ax.set_title(f"{res.scene} [{res.rung}] at {speed / (2 * math.pi):.1f} Hz spin: sampled-loop stability")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def margin_against_latency(res: StudyResult, path: Path) -> Path:
    """Spectral radius and least damping ratio against latency at the scene's own rate (the
    study's latency grid evaluated at that rate, ``res.scene_row``), with the bisected boundary
    and the scene's own setting marked."""
    row, sp = res.scene_row, res.scene_point
    fs0 = sp["rate_hz"]
    pts = sorted(row["points"], key=lambda p: p["latency_s"])
    lat = np.array([p["latency_s"] * 1e6 for p in pts])
    zeta = np.array([p["min_damping_ratio"] for p in pts])
    rho = np.array([p["spectral_radius"] for p in pts])
    fig, ax = plt.subplots(1, 2, figsize=(10, 4.2))
    ax[0].plot(lat, zeta, "o-", label=f"at {fs0:g} Hz")
    ax[0].axhline(0, color="r", lw=1)
    ax[0].set_xlabel("loop latency beyond the controller's own delay (us)")
    ax[0].set_ylabel("least damping ratio of the sampled loop")
    ax[1].plot(lat, rho, "o-", label=f"at {fs0:g} Hz")
    ax[1].axhline(1, color="r", lw=1, label="stability limit")
    ax[1].set_xlabel("loop latency beyond the controller's own delay (us)")
    ax[1].set_ylabel("spectral radius per period")
    ax[1].ticklabel_format(axis="y", useOffset=False)
    bound = row["largest_latency_s"]
    for a, y in zip(ax, ("min_damping_ratio", "spectral_radius")):
        a.plot(sp["latency_s"] * 1e6, sp[y], "*", ms=14, mfc="gold", mec="k", zorder=5, clip_on=False,
               label=f"scene's setting ({sp['latency_s'] * 1e6:g} us)")
        if bound is not None:
            a.axvline(bound * 1e6, color="k", ls="--", lw=1, label=f"boundary {bound * 1e6:.1f} us")
        a.legend(fontsize=8)
    fig.suptitle(f"{res.scene} [{res.rung}] at the scene's rate, {fs0:g} Hz"
                 + ("" if bound is not None else
                    f": stable at every latency up to {row['search_limit_s'] * 1e3:g} ms"))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _noise(res: StudyResult) -> str:
    n = res.spec.noise
    return (f"sensor noise {n.level:g} m std" if n.kind == "sensor"
            else f"force noise {n.level:g} N^2/Hz at every AMB axis")


def variance_against_jitter(res: StudyResult, path: Path) -> Path | None:
    """Stationary displacement standard deviation against jitter width and loss probability,
    relative to the jitter-free loop (absolute where that has none); a point with no stationary
    variance (not mean-square stable, or not computed) is a red hatched bar labelled with why."""
    pts = list(res.jitter)
    if len(pts) < 2:
        return None
    base = pts[0].get("y_std_m")
    rel = base is not None
    vals = [None if j.get("y_std_m") is None else (j["y_std_m"] / base if rel else j["y_std_m"] * 1e6)
            for j in pts]
    finite = [v for v in vals if v is not None]
    span = max(finite) * 1.15 if finite else 1.0
    fig, ax = plt.subplots(figsize=(8, 0.9 + 0.42 * len(pts) + 0.9))
    for k, (j, v) in enumerate(zip(pts, vals)):
        if v is not None:
            ax.barh(k, v, color="C0" if j["ms_stable"] else "C3")
        else:  # no variance to draw: the whole row says why
            why = next((part.partition(": ")[2] for part in (j.get("not_computed") or "").split("; ")
                        if "y_std_m" in part.partition(": ")[0].split(", ")), "not computed")
            ax.barh(k, span, color="C3" if not j["ms_stable"] else "0.75", alpha=0.35, hatch="//",
                    edgecolor="C3" if not j["ms_stable"] else "0.4")
            ax.text(0.01 * span, k, "NOT MEAN-SQUARE STABLE: no stationary variance" if not j["ms_stable"]
                    else f"variance not computed: {why}",
                    va="center", fontsize=7.5)
    ax.set_yticks(range(len(pts)), [f"{j['jitter']}, loss {j['loss']:.3g}" for j in pts], fontsize=8)
    ax.set_xlim(0, span)
    if rel:
        ax.axvline(1, color="k", lw=1)
    from matplotlib.patches import Patch
    ax.legend(handles=[Patch(color="C0", label="mean-square stable"),
                       Patch(facecolor="C3", alpha=0.35, hatch="//", edgecolor="C3",
                             label="not mean-square stable: no stationary variance")],
              fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1 - 0.5 / len(pts)), ncol=2)
    ax.set_xlabel("displacement std / std without jitter" if rel else "displacement std (um)")
    ax.set_title(f"{res.scene} [{res.rung}] at {res.scene_point['rate_hz']:g} Hz, latency "
                 f"{res.scene_point['latency_s'] * 1e6:g} us\njitter and loss under {_noise(res)}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
