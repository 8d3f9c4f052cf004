"""PNG plots of the frequency-domain analyses (matplotlib, Agg backend).  Frequencies and speeds
are in Hz throughout; every legend entry names an artist that is drawn."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.colors as mcolors  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

HZ = 1 / (2 * np.pi)
#: Campbell points of modes more damped than this are not drawn (see campbell())
CAMPBELL_ZETA_MAX = 0.5
_WHIRL_MARK = {"forward": "^", "backward": "v", "mixed": "o", "axial": "s"}
_WHIRL_Z = {"backward": 2, "mixed": 3, "axial": 3, "forward": 4}  # forward drawn above backward


def _save(fig, path):
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def campbell(path: Path, name: str, camp: dict, criticals, speed_max: float, reference_hz=(), reference: str = ""):
    """Damped natural frequencies over spin speed, coloured by damping ratio (log scale), marker by
    whirl (forward drawn above backward); below, the damping ratio of every drawn mode.  Modes with
    zeta > CAMPBELL_ZETA_MAX are left out: they are the real, overdamped poles of the loop (the
    integral action's slow poles, split into small imaginary parts by the gyroscopic coupling)
    that would otherwise lie along 0 Hz."""
    fig, (ax, az) = plt.subplots(2, 1, figsize=(7.5, 8), sharex=True, gridspec_kw={"height_ratios": [3, 1.3]})
    keep = camp["zeta"] <= CAMPBELL_ZETA_MAX
    dropped = int((~keep).sum())
    zmin = max(float(np.min(camp["zeta"][keep])) if keep.any() else 1e-4, 1e-4)
    norm = mcolors.LogNorm(vmin=zmin, vmax=CAMPBELL_ZETA_MAX)
    sc = None
    for whirl in ("backward", "mixed", "axial", "forward"):
        sel = keep & (camp["whirl"] == whirl)
        if not sel.any():
            continue
        kw = dict(marker=_WHIRL_MARK[whirl], c=np.maximum(camp["zeta"][sel], zmin), cmap="viridis", norm=norm,
                  s=22 if whirl == "forward" else 16, edgecolors="k", linewidths=0.3, zorder=_WHIRL_Z[whirl])
        sc = ax.scatter(camp["speed"][sel] * HZ, camp["freq"][sel] * HZ, label=whirl, **kw)
        az.scatter(camp["speed"][sel] * HZ, camp["zeta"][sel], **{**kw, "s": 10})
    s = np.array([0, speed_max]) * HZ
    ax.plot(s, s, "k--", lw=1, label="1x (synchronous)", zorder=1)
    for k, c in enumerate(criticals):
        ax.plot(c.hz, c.hz, "x", color="red", ms=10, mew=2, zorder=6, label="critical speed (computed)" if k == 0 else None)
        ax.annotate(f"{k + 1}: {c.hz:.1f} Hz", (c.hz, c.hz), textcoords="offset points", xytext=(6, -12), fontsize=8,
                    color="darkred", zorder=7)
    if reference_hz:
        r = np.asarray(reference_hz)
        ax.plot(r, r, "o", mfc="none", mec="k", ms=11, mew=1.2, zorder=5,
                label=f"published ({reference})" if reference else "published")
    if sc is not None:
        fig.colorbar(sc, ax=[ax, az], label="damping ratio zeta (log)", pad=0.02)
    ax.set_ylabel("damped natural frequency (Hz)")
    ax.set_xlim(0, speed_max * HZ); ax.set_ylim(0, speed_max * HZ * 1.05)
    ax.set_title(f"Campbell diagram, closed loop: {name}" +
                 (f"\n({dropped} points of overdamped modes, zeta > {CAMPBELL_ZETA_MAX:g}, not drawn)" if dropped else ""),
                 fontsize=10)
    ax.legend(loc="upper left", fontsize=8); ax.grid(alpha=0.3)
    az.set_yscale("log"); az.set_ylabel("zeta"); az.set_xlabel("spin speed (Hz)"); az.grid(alpha=0.3, which="both")
    fig.savefig(path, dpi=110, bbox_inches="tight"); plt.close(fig)


def _unb_title(unbalances) -> str:
    if not unbalances:
        return "no unbalance"
    return "unbalance " + ", ".join(f"{u.magnitude * 1e3:g} g m at node {u.node + 1} ({np.degrees(u.phase):.0f} deg)"
                                    for u in unbalances)


def unbalance(path: Path, results: dict, node_labels: dict, clearance: float | None = None,
              unbalances=None, clearance_note: str = ""):
    """Orbit semi-axes (0-peak) and phase of x over spin speed (Hz).  Where the orbit is elliptic
    (an anisotropic bearing) the major (solid) and minor (dashed) semi-axes are both drawn."""
    fig, (ax, ap) = plt.subplots(2, 1, figsize=(8, 7.5), sharex=True, gridspec_kw={"height_ratios": [2.2, 1]})
    k_col = 0
    top = 0.0
    for name, res in results.items():
        maj, mnr = res.radius, res.minor
        for j, k in enumerate(res.nodes):
            col = f"C{k_col % 10}"; k_col += 1
            lab = (f"{name}: " if len(results) > 1 else "") + node_labels.get(k, f"node {k + 1}")
            f = res.speeds * HZ
            top = max(top, float(np.nanmax(maj[:, j])))
            ax.semilogy(f, maj[:, j], color=col, label=lab)
            elliptic = np.nanmax(np.abs(maj[:, j] - mnr[:, j]) / np.maximum(maj[:, j], 1e-300)) > 0.02
            if elliptic:
                ax.semilogy(f, mnr[:, j], color=col, ls="--", lw=1, label=f"{lab}: minor semi-axis")
            pos = res.speeds > 0  # no response (and no phase) at standstill
            ph = np.degrees(np.unwrap(np.angle(res.x[pos, j])))
            ap.plot(f[pos], ph, color=col)
    if clearance:
        ax.axhline(clearance, color="r", lw=1.2, ls="-.", label=f"touchdown clearance C_min = {clearance * 1e6:.0f} um"
                   + (f" ({clearance_note})" if clearance_note else ""))
        for frac, z in ((0.3, "A/B"), (0.4, "B/C"), (0.5, "C/D")):
            ax.axhline(frac * clearance, color="0.6", lw=0.8, ls=":")
            ax.text(1.0, frac * clearance, f"{z} ", fontsize=6, color="0.4", va="center", ha="right",
                    transform=ax.get_yaxis_transform())
        ax.text(0.0, 0.3 * clearance, " ISO 14839-2 zones (0.3/0.4/0.5 C_min, unverified)", fontsize=6, color="0.4",
                va="top", transform=ax.get_yaxis_transform())
        top = max(top, clearance)
    if top > 0:
        ax.set_ylim(top * 1e-4, top * 2)
    ax.set_ylabel("orbit semi-axis, 0-peak (m)\n(solid: major)")
    ap.set_ylabel("phase of x (deg)"); ap.set_xlabel("spin speed (Hz)")
    ax.set_title("Unbalance response: " + _unb_title(unbalances or ()), fontsize=9)
    ax.grid(alpha=0.3, which="both"); ap.grid(alpha=0.3)
    ax.legend(fontsize=7)
    _save(fig, path)


def _axis_lines(axes, values):
    """(index, colour, style, label) per axis: x solid, y dashed; y left out where equal to x."""
    out, col = [], {}
    for j, (amb, ax) in enumerate(axes):
        col.setdefault(amb, f"C{len(col) % 10}")
        if ax == "y" and j > 0 and axes[j - 1][0] == amb and np.allclose(values[:, j], values[:, j - 1], rtol=1e-6):
            out[-1] = (out[-1][0], out[-1][1], "-", f"{amb}-x = {amb}-y")
            continue
        out.append((j, col[amb], {"x": "-", "y": "--", "z": ":"}[ax], f"{amb}-{ax}"))
    return out


def sensitivity(path: Path, name: str, res):
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    f = res.freqs * HZ
    A = np.abs(res.S)
    for j, c, ls, lab in _axis_lines(res.axes, A):
        ax.semilogx(f, 20 * np.log10(A[:, j]), color=c, ls=ls,
                    label=f"{lab}: peak {res.peaks[j]:.2f} at {res.peak_freqs[j] * HZ:.1f} Hz (zone {res.zones[j]})")
        ax.plot(res.peak_freqs[j] * HZ, 20 * np.log10(res.peaks[j]), "o", color=c, ms=5, mec="k", mew=0.5)
    for lim, z in ((3, "A/B"), (4, "B/C"), (5, "C/D")):
        ax.axhline(20 * np.log10(lim), color="0.6", ls=":", lw=1)
        ax.text(f[0], 20 * np.log10(lim) + 0.3, z, fontsize=7, color="0.4")
    ax.set_xlabel("frequency (Hz)"); ax.set_ylabel("|S| (dB)")
    ax.set_title(f"ISO 14839-3 sensitivity at {res.speed * HZ:.1f} Hz spin: {name}\n(dots: refined peaks)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7); _save(fig, path)


def bode(path: Path, name: str, ol):
    """Open loop L_j of every axis (loop broken at that axis, the others closed): gain and phase,
    the gain crossovers (phase margins) and phase crossovers (gain margins) marked."""
    fig, (ag, ap) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    f = ol.freqs * HZ
    for j, c, ls, lab in _axis_lines(ol.axes, ol.L):
        m = ol.margins[j]
        pm, up, lo = m.phase_margin, m.upper_gm, m.lower_gm
        txt = [f"PM {pm[0]:.1f} deg @ {pm[1] * HZ:.0f} Hz" if pm else "no gain crossover"]
        if up:
            txt.append(f"GM +{20 * np.log10(up[0]):.1f} dB @ {up[1] * HZ:.0f} Hz")
        if lo:
            txt.append(f"GM {20 * np.log10(lo[0]):.1f} dB @ {lo[1] * HZ:.0f} Hz")
        ag.semilogx(f, 20 * np.log10(np.abs(ol.L[:, j])), color=c, ls=ls, label=f"{lab}: " + ", ".join(txt))
        ph = np.degrees(np.angle(ol.L[:, j]))
        ap.semilogx(f, np.where(ph > 0, ph - 360, ph), color=c, ls=ls)  # phase in (-360, 0]
        if pm:
            ag.plot(pm[1] * HZ, 0, "o", color=c, mec="k", mew=0.5)
        for g, w in m.gain_margins:
            if (up and w == up[1]) or (lo and w == lo[1]):
                ap.plot(w * HZ, -180, "s", color=c, mec="k", mew=0.5)
    ag.axhline(0, color="k", lw=0.8)
    ap.axhline(-180, color="k", lw=0.8)
    ag.set_ylabel("|L| (dB)"); ap.set_ylabel("arg L (deg)"); ap.set_xlabel("frequency (Hz)")
    ap.set_ylim(-360, 0); ap.set_yticks(range(-360, 1, 90))
    ag.set_title(f"Open loop per axis (broken at that axis, others closed) at {ol.speed * HZ:.1f} Hz spin: {name}\n"
                 "dots: gain crossovers (phase margin); squares: phase crossovers of the gain margins", fontsize=9)
    for a in (ag, ap):
        a.grid(alpha=0.3, which="both")
    ag.legend(fontsize=7); _save(fig, path)


def stability(path: Path, name: str, st, nominal: float | None = None):
    """Least damping ratio of the closed loop over spin speed (every mode up to st.fmax)."""
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    s = st.speeds * HZ
    ax.plot(s, st.zeta, "k-", lw=1.2, zorder=1)
    sc = ax.scatter(s, st.zeta, c=st.freq * HZ, cmap="plasma", s=20, zorder=2, edgecolors="k", linewidths=0.3)
    fig.colorbar(sc, ax=ax, label="frequency of that mode (Hz)")
    ax.axhline(0, color="r", lw=1)
    if nominal is not None:
        ax.axvline(nominal * HZ, color="0.5", ls=":", lw=1)
        ax.text(nominal * HZ, 0.02, "nominal ", fontsize=7, color="0.4", va="bottom", ha="right",
                transform=ax.get_xaxis_transform())
    k = int(np.argmin(st.zeta))
    ax.annotate(f"min zeta {st.zeta[k]:.3g} at {s[k]:.0f} Hz\n({st.freq[k] * HZ:.0f} Hz {st.whirl[k]} mode)",
                (s[k], st.zeta[k]), textcoords="offset points", fontsize=8,
                xytext=(-170, -40) if s[k] > 0.5 * s[-1] else (10, 15),
                arrowprops=dict(arrowstyle="->", lw=0.7))
    ax.set_xlabel("spin speed (Hz)"); ax.set_ylabel("least damping ratio (< 0: unstable)")
    ax.set_title(f"Stability over speed, every closed-loop mode up to {st.fmax * HZ:.0f} Hz: {name}", fontsize=10)
    ax.grid(alpha=0.3); _save(fig, path)


def support_sweep(path: Path, name: str, sw):
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 6.5), sharex=True)
    hz = sw.criticals * HZ
    for k in range(hz.shape[1]):
        ax = a1 if k < 2 else a2
        ax.plot(sw.positions, hz[:, k], "o-", ms=3, label=f"critical {k + 1}")
        ax.axhline(sw.baseline[k] * HZ, ls="--", lw=1, color=ax.lines[-1].get_color())
    a1.set_ylabel("rigid critical speeds (Hz)"); a2.set_ylabel("flexible critical speeds (Hz)")
    a2.set_xlabel(f"distance of AMB {sw.amb} from the first AMB (m)")
    a1.set_title(f"Support-position sweep (dashed: without AMB {sw.amb}): {name}")
    for a in (a1, a2):
        a.grid(alpha=0.3); a.legend(fontsize=8)
    _save(fig, path)
