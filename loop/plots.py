"""PNG plots of the frequency-domain analyses (matplotlib, Agg backend)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

HZ = 1 / (2 * np.pi)


def campbell(path: Path, name: str, camp: dict, criticals, speed_max: float):
    fig, ax = plt.subplots(figsize=(7, 5))
    for whirl, style in (("forward", dict(c="tab:blue", s=6)), ("backward", dict(c="tab:orange", s=6)),
                         ("mixed", dict(c="0.5", s=4)), ("axial", dict(c="tab:green", s=4))):
        sel = camp["whirl"] == whirl
        if sel.any():
            ax.scatter(camp["speed"][sel] * HZ, camp["freq"][sel] * HZ, label=whirl, **style)
    s = np.array([0, speed_max]) * HZ
    ax.plot(s, s, "k--", lw=1, label="1x")
    for c in criticals:
        ax.plot(c.hz, c.hz, "rx", ms=9)
        ax.annotate(f"{c.hz:.1f} Hz", (c.hz, c.hz), textcoords="offset points", xytext=(6, -12), fontsize=8)
    ax.set_xlabel("spin speed (Hz)"); ax.set_ylabel("damped natural frequency (Hz)")
    ax.set_xlim(0, speed_max * HZ); ax.set_ylim(0, speed_max * HZ * 1.05)
    ax.set_title(f"Campbell diagram, closed loop: {name}"); ax.legend(loc="upper left", fontsize=8); ax.grid(alpha=0.3)
    fig.tight_layout(); fig.savefig(path, dpi=110); plt.close(fig)


def unbalance(path: Path, results: dict, node_labels: dict):
    fig, ax = plt.subplots(figsize=(7, 5))
    for name, res in results.items():
        for j, k in enumerate(res.nodes):
            ax.semilogy(res.speeds, res.radius[:, j], label=f"{name}: {node_labels.get(k, f'node {k + 1}')}")
    ax.set_xlabel("spin speed (rad/s)"); ax.set_ylabel("orbit radius, 0-peak (m)")
    ax.set_title("Unbalance response"); ax.grid(alpha=0.3, which="both"); ax.legend(fontsize=7)
    fig.tight_layout(); fig.savefig(path, dpi=110); plt.close(fig)


def sensitivity(path: Path, name: str, res):
    fig, ax = plt.subplots(figsize=(7, 4.5))
    f = res.freqs * HZ
    for j, (amb, axis) in enumerate(res.axes):
        ax.semilogx(f, 20 * np.log10(np.abs(res.S[:, j])), label=f"{amb}-{axis}")
    for lim, z in ((3, "A/B"), (4, "B/C"), (5, "C/D")):
        ax.axhline(20 * np.log10(lim), color="0.6", ls=":", lw=1)
        ax.text(f[0], 20 * np.log10(lim) + 0.3, z, fontsize=7, color="0.4")
    ax.set_xlabel("frequency (Hz)"); ax.set_ylabel("|S| (dB)")
    ax.set_title(f"ISO 14839-3 sensitivity at {res.speed:.0f} rad/s: {name}"); ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=3); fig.tight_layout(); fig.savefig(path, dpi=110); plt.close(fig)


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
    fig.tight_layout(); fig.savefig(path, dpi=110); plt.close(fig)
