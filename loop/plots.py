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


def _unb_text(unbalances) -> str:
    if not unbalances:
        return "no unbalance"
    return "unbalance " + ", ".join(f"{u.magnitude * 1e3:g} g m at node {u.node + 1} ({np.degrees(u.phase):.0f} deg)"
                                    for u in unbalances)


def _unb_title(unbalances) -> str:
    """The unbalance a response plot is driven by: a sequence of ``Unbalance`` (one scene), or
    {scene name: its unbalances} (a comparison; one text where all scenes share it), or None
    where unknown (then the title claims nothing)."""
    if unbalances is None:
        return ""
    if not isinstance(unbalances, dict):
        return _unb_text(unbalances)
    texts = {name: _unb_text(u) for name, u in unbalances.items()}
    if len(set(texts.values())) <= 1:
        return next(iter(texts.values()), "")
    return "\n".join(f"{name}: {t}" for name, t in texts.items())


def unbalance(path: Path, results: dict, node_labels: dict, clearance: float | dict | None = None,
              unbalances=None, clearance_note: str = ""):
    """Orbit semi-axes (0-peak) and phase of x over spin speed (Hz).  Where the orbit is elliptic
    (an anisotropic bearing) the major (solid) and minor (dashed) semi-axes are both drawn.
    ``clearance``: the touchdown clearance (m), one for all or {AMB name: its own}."""
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
    # {AMB: touchdown clearance} (or one value for all): one line per distinct value, naming its AMBs
    groups: dict = {}
    for nm, c in (clearance.items() if isinstance(clearance, dict) else [("", clearance)] if clearance else []):
        groups.setdefault(float(c), []).append(nm)
    for k, (c, names) in enumerate(sorted(groups.items())):
        who = f" {', '.join(n for n in names if n)}" if len(groups) > 1 else ""
        ax.axhline(c, color="r", lw=1.2, ls=("-.", "--", ":")[k % 3],
                   label=f"touchdown clearance C_min{who} = {c * 1e6:g} um" + (f" ({clearance_note})" if clearance_note else ""))
        top = max(top, c)
    if len(groups) == 1:
        c = next(iter(groups))
        for frac, z in ((0.3, "A/B"), (0.4, "B/C"), (0.5, "C/D")):
            ax.axhline(frac * c, color="0.6", lw=0.8, ls=":")
            ax.text(1.0, frac * c, f"{z} ", fontsize=6, color="0.4", va="center", ha="right",
                    transform=ax.get_yaxis_transform())
        ax.text(0.0, 0.3 * c, " ISO 14839-2 zones (0.3/0.4/0.5 C_min, unverified)", fontsize=6, color="0.4",
                va="top", transform=ax.get_yaxis_transform())
    elif groups:  # zone limits differ per AMB: the report gives each station's zone
        ax.text(0.0, 0.85 * min(groups), " ISO 14839-2 zones per AMB: 0.3/0.4/0.5 of its C_min (report.txt)", fontsize=6,
                color="0.4", va="top", transform=ax.get_yaxis_transform())
    if top > 0:
        ax.set_ylim(top * 1e-4, top * 2)
    ax.set_ylabel("orbit semi-axis, 0-peak (m)\n(solid: major)")
    ap.set_ylabel("phase of x (deg)"); ap.set_xlabel("spin speed (Hz)")
    what = _unb_title(unbalances)
    ax.set_title("Unbalance response" + (f": {what}" if what else ""), fontsize=9)
    ax.grid(alpha=0.3, which="both"); ap.grid(alpha=0.3)
    ax.legend(fontsize=7)
    _save(fig, path)


def sensitivity(path: Path, name: str, res, over=None):
    """|S| of every axis over frequency at one spin speed (``res``); with ``over``
    (analysis.over_speed.OverSpeed) that speed is the worst one, and a second panel draws every
    axis' peak over the evaluated spin speeds, each axis' worst marked."""
    if over is None:
        fig, ax = plt.subplots(figsize=(7.5, 4.8))
    else:
        fig, (ax, a2) = plt.subplots(2, 1, figsize=(7.5, 8), gridspec_kw={"height_ratios": [1.6, 1]})
    f = res.freqs * HZ
    A = np.abs(res.S)
    for j, c, ls, lab in _distinct_lines(res.axes, A):
        ax.semilogx(f, 20 * np.log10(A[:, j]), color=c, ls=ls,
                    label=f"{lab}: peak {res.peaks[j]:.2f} at {res.peak_freqs[j] * HZ:.1f} Hz (zone {res.zones[j]})")
        ax.plot(res.peak_freqs[j] * HZ, 20 * np.log10(res.peaks[j]), "o", color=c, ms=5, mec="k", mew=0.5)
    for a in ([ax] if over is None else [ax, a2]):
        for lim, z in ((3, "A/B"), (4, "B/C"), (5, "C/D")):
            a.axhline(20 * np.log10(lim), color="0.6", ls=":", lw=1)
    for lim, z in ((3, "A/B"), (4, "B/C"), (5, "C/D")):
        ax.text(f[0], 20 * np.log10(lim) + 0.3, z, fontsize=7, color="0.4")
    ax.set_xlabel("frequency (Hz)"); ax.set_ylabel("|S| (dB)")
    at = f"at {res.speed * HZ:.1f} Hz spin"
    if over is not None:
        w = over.worst[over.worst_axis]
        at += f", the speed of the worst peak over the operating speeds ({w.axis[0]}-{w.axis[1]})"
    ax.set_title(f"ISO 14839-3 sensitivity, continuous-time loop: {name}\n{at}; dots: refined peaks", fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    if over is not None:
        sp = over.speeds * HZ
        P = over.peaks
        for lo, hi, src in over.intervals:
            if hi > lo:
                a2.axvspan(lo * HZ, hi * HZ, color="0.93", zorder=0)
            else:
                a2.axvline(lo * HZ, color="0.6", ls="--", lw=0.8)
                a2.text(lo * HZ, 0.02, f" {src}", fontsize=6, color="0.4", rotation=90, va="bottom",
                        transform=a2.get_xaxis_transform())
        for j, c, ls, lab in _distinct_lines(over.axes, P):
            wj = over.worst[j]
            a2.plot(sp, 20 * np.log10(P[:, j]), color=c, ls=ls, marker=".", ms=4,
                    label=f"{lab}: worst {wj.peak:.2f} (zone {wj.zone}) at {wj.speed * HZ:.1f} Hz spin")
            a2.plot(wj.speed * HZ, 20 * np.log10(wj.peak), "o", color=c, ms=6, mec="k", mew=0.5)
        a2.set_xlabel("spin speed (Hz)"); a2.set_ylabel("peak |S| (dB)")
        a2.set_title("peak of each axis over the evaluated spin speeds (shaded: the operating range; dots: worst)",
                     fontsize=8)
        for lim, z in ((3, "A/B"), (4, "B/C"), (5, "C/D")):
            a2.text(1.0, 20 * np.log10(lim), f"{z} ", fontsize=6, color="0.4", va="bottom", ha="right",
                    transform=a2.get_yaxis_transform())
        a2.grid(alpha=0.3); a2.legend(fontsize=6, loc="best", framealpha=0.85)
    _save(fig, path)


def phase_deg(L: np.ndarray, initial: float = -180.0) -> np.ndarray:
    """Continuous phase of a frequency response (deg), as python-control draws it: unwrapped
    along the frequency grid (``numpy.unwrap``: no step between adjacent points exceeds 180 deg)
    and shifted by whole turns so that the first point lies within 180 deg of ``initial``."""
    ph = np.degrees(np.unwrap(np.angle(L)))
    if len(ph):
        ph = ph - 360.0 * np.round((ph[0] - initial) / 360.0)
    return ph


def _distinct_lines(axes, L):
    """(column, colour, style, label) per distinct curve (open loop, sensitivity): x solid, y
    dashed, one colour per AMB; an axis whose values equal an earlier one's over the whole grid is
    merged into its label ("A-x = A-y = C-x"), so no curve is silently hidden under an equal one."""
    out, col = [], {}
    for j, (amb, ax) in enumerate(axes):
        col.setdefault(amb, f"C{len(col) % 10}")
        same = next((k for k, e in enumerate(out) if np.allclose(L[:, j], L[:, e[0]], rtol=1e-6, atol=0)), None)
        if same is not None:
            e = out[same]
            out[same] = (e[0], e[1], e[2], f"{e[3]} = {amb}-{ax}")
            continue
        out.append((j, col[amb], {"x": "-", "y": "--", "z": ":"}.get(ax, "-"), f"{amb}-{ax}"))
    return out


def _coincide(a: np.ndarray, b: np.ndarray, frac: float = 0.02) -> bool:
    """True where two responses lie on top of each other in the plot (within 0.2 dB and 2 deg)
    over more than ``frac`` of the grid."""
    same = (np.abs(20 * np.log10(np.abs(a) / np.abs(b))) < 0.2) & (np.abs(np.angle(a / b, deg=True)) < 2)
    return bool(np.mean(same) > frac)


def bode(path: Path, name: str, ol):
    """Open loop L_j of every axis (loop broken at that axis, the others closed): gain and phase,
    the gain crossovers (phase margins) and phase crossovers (gain margins) marked.  The phase is
    continuous (:func:`phase_deg`); the phase crossovers are where it passes -180 deg + k 360 deg.
    Where curves of different axes coincide over part of the range, the earlier one is drawn
    wider beneath the later ones (:func:`_coincide`), so both stay visible; axes equal over the whole range share
    one curve and one legend entry."""
    from matplotlib.ticker import MultipleLocator
    fig, (ag, ap) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    f = ol.freqs * HZ
    lines = _distinct_lines(ol.axes, ol.L)
    cover = [sum(_coincide(ol.L[:, j], ol.L[:, e[0]]) for e in lines[k + 1:]) for k, (j, *_) in enumerate(lines)]
    lo_ph, hi_ph = np.inf, -np.inf
    for k, (j, c, ls, lab) in enumerate(lines):
        m = ol.margins[j]
        pm, up, lo = m.phase_margin, m.upper_gm, m.lower_gm
        txt = [f"PM {pm[0]:.1f} deg @ {pm[1] * HZ:.0f} Hz" if pm else "no gain crossover"]
        if up:
            txt.append(f"GM +{20 * np.log10(up[0]):.1f} dB @ {up[1] * HZ:.0f} Hz")
        if lo:
            txt.append(f"GM {20 * np.log10(lo[0]):.1f} dB @ {lo[1] * HZ:.0f} Hz")
        lw, z = 1.0 + min(cover[k], 2), 2 + k   # wider beneath each later curve it coincides with
        ag.semilogx(f, 20 * np.log10(np.abs(ol.L[:, j])), color=c, ls=ls, lw=lw, zorder=z,
                    label=f"{lab}: " + ", ".join(txt))
        ph = phase_deg(ol.L[:, j])
        lo_ph, hi_ph = min(lo_ph, float(ph.min())), max(hi_ph, float(ph.max()))
        ap.semilogx(f, ph, color=c, ls=ls, lw=lw, zorder=z)
        if pm:
            ag.plot(pm[1] * HZ, 0, "o", color=c, mec="k", mew=0.5, zorder=10)
        lf = np.log(f)
        for g, w in m.gain_margins:
            if (up and w == up[1]) or (lo and w == lo[1]):
                at = np.interp(np.log(w * HZ), lf, ph)   # the branch of -180 deg the curve crosses there
                ap.plot(w * HZ, -180 + 360 * np.round((at + 180) / 360), "s", color=c, mec="k", mew=0.5, zorder=10)
    ag.axhline(0, color="k", lw=0.8)
    if np.isfinite(lo_ph):
        for k180 in range(int(np.floor((lo_ph + 180) / 360)), int(np.ceil((hi_ph + 180) / 360)) + 1):
            ap.axhline(-180 + 360 * k180, color="k", lw=0.8)
        pad = 0.05 * max(hi_ph - lo_ph, 90)
        ap.set_ylim(90 * np.floor((lo_ph - pad) / 90), 90 * np.ceil((hi_ph + pad) / 90))
    ap.yaxis.set_major_locator(MultipleLocator(90 if ap.get_ylim()[1] - ap.get_ylim()[0] <= 1080 else 180))
    ag.set_ylabel("|L| (dB)"); ap.set_ylabel("arg L (deg, continuous)"); ap.set_xlabel("frequency (Hz)")
    ag.set_title(f"Open loop per axis (broken at that axis, others closed) at {ol.speed * HZ:.1f} Hz spin: {name}\n"
                 "dots: gain crossovers (phase margin); squares: phase crossovers of the gain margins", fontsize=9)
    for a in (ag, ap):
        a.grid(alpha=0.3, which="both")
    ag.legend(fontsize=7); _save(fig, path)


def _mode_segments(st, jump: float = 0.05) -> list[tuple[int, int]]:
    """[start, stop) index runs over which the least-damped mode is one branch: a new run starts
    where its frequency jumps by more than ``jump`` (relative) or its whirl changes."""
    out, k0 = [], 0
    for k in range(1, len(st.speeds)):
        # at standstill forward and backward whirl coincide: the whirl named there does not split a run
        whirl_changed = st.whirl[k] != st.whirl[k - 1] and st.speeds[k - 1] > 0
        if abs(st.freq[k] - st.freq[k - 1]) > jump * max(abs(st.freq[k - 1]), 1e-9) or whirl_changed:
            out.append((k0, k)); k0 = k
    out.append((k0, len(st.speeds)))
    return out


def stability(path: Path, name: str, st, operating=None):
    """Least damping ratio of the closed loop over spin speed: at each speed the least-damped of
    every closed-loop mode up to st.fmax, so the curve follows whichever mode that is; each run of
    one mode is labelled with its frequency and whirl.  ``operating``: the scene's operating
    speeds, ``[(lo, hi, source), ...]`` rad/s, shaded (a range) or drawn as a line (one speed)."""
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    s = st.speeds * HZ
    ax.plot(s, st.zeta, "k-", lw=1.2, zorder=1)
    sc = ax.scatter(s, st.zeta, c=st.freq * HZ, cmap="plasma", s=20, zorder=2, edgecolors="k", linewidths=0.3)
    fig.colorbar(sc, ax=ax, label="frequency of the least-damped mode (Hz)")
    ax.axhline(0, color="r", lw=1)
    for lo, hi, src in operating or ():
        if hi > lo:
            ax.axvspan(lo * HZ, hi * HZ, color="0.93", zorder=0, label=f"operating speeds ({src})")
        else:
            ax.axvline(lo * HZ, color="0.5", ls=":", lw=1, label=f"{src} {lo * HZ:.1f} Hz")
    segs = _mode_segments(st)
    for i, (a, b) in enumerate(segs):
        m = (a + b - 1) // 2
        lo, hi = np.min(st.freq[a:b]) * HZ, np.max(st.freq[a:b]) * HZ
        ax.annotate((f"{lo:.0f}-{hi:.0f}" if hi - lo >= 1 else f"{lo:.0f}") + f" Hz {st.whirl[b - 1]} mode",
                    (s[m], st.zeta[m]), fontsize=7, bbox=dict(fc="white", ec="none", alpha=0.7, pad=1),
                    textcoords="offset points", xytext=(0, -14 if i % 2 == 0 else 8), ha="center", color="0.2")
    k = int(np.argmin(st.zeta))
    ax.annotate(f"min zeta {st.zeta[k]:.3g} at {s[k]:.0f} Hz spin\n({st.freq[k] * HZ:.0f} Hz {st.whirl[k]} mode)",
                (s[k], st.zeta[k]), textcoords="offset points", fontsize=8,
                xytext=(-170, -40) if s[k] > 0.5 * s[-1] else (10, 15),
                arrowprops=dict(arrowstyle="->", lw=0.7))
    ax.set_xlabel("spin speed (Hz)"); ax.set_ylabel("least damping ratio (< 0: unstable)")
    ax.set_title(f"Stability over speed: {name}\nthe least-damped of all closed-loop modes up to {st.fmax * HZ:.0f} Hz "
                 "at each speed" + (f" ({len(segs)} modes in turn, labelled)" if len(segs) > 1
                                    else " (one mode throughout, labelled)"), fontsize=9)
    ax.grid(alpha=0.3)
    if operating:
        ax.legend(fontsize=7, loc="best")
    _save(fig, path)


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
