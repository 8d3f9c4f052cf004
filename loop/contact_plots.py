"""The plots of a run with auxiliary (touchdown) bearings (matplotlib, Agg backend, as
loop/orbit_plots.py): where the shaft went in each bearing's clearance, how hard it hit, and
whether it whirled (loop/contact_results.py says the same in numbers)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .contact_results import analyse, force_text, in_contact, whirl_ratio_series
from .orbit_plots import _faults_title, _mark_times, speed_title
from .orbits import time_marks


def plot_contact(res, out_dir) -> list[Path]:
    """``contact_orbits.png`` (per bearing the orbit within the clearance circle, the rows in
    contact marked), ``contact_force.png`` (per bearing the normal force over time with the
    contact log's event peaks, which fall between record rows, and the race speed against the
    shaft's surface speed referred to the race) and ``whirl_ratio.png`` (windowed orbit-angle
    rate over the spin speed where the orbit runs at the clearance: -1 x R_s/(R_i - R_s) is a
    rolling backward whirl on a held race, +1 synchronous forward whirl).  Nothing without
    ``res.contact``."""
    if getattr(res, "contact", None) is None or not len(res.t):
        return []
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rep = analyse(res)
    marks = time_marks(res)
    title = f"{res.meta.get('scene', '')} [{res.meta.get('rung', '')}] {speed_title(res.meta)}" + _faults_title(marks)
    out = []
    for name, fig in (("contact_orbits.png", _orbits(plt, res, rep, title)),
                      ("contact_force.png", _forces(plt, res, rep, title, marks)),
                      ("whirl_ratio.png", _ratio(plt, res, rep, title, marks))):
        p = out_dir / name
        fig.savefig(p, dpi=110)
        plt.close(fig)
        out.append(p)
    return out


def _orbits(plt, res, rep, title):
    cd = res.contact
    m = len(rep.bearings)
    fig, ax = plt.subplots(1, m, figsize=(5 * m, 5.2), squeeze=False)
    circle = np.linspace(0, 2 * np.pi, 361)
    for k, bc in enumerate(rep.bearings):
        a = ax[0, k]
        x, y = np.asarray(cd["x"])[:, k] * 1e6, np.asarray(cd["y"])[:, k] * 1e6
        on = in_contact(np.asarray(cd["d"])[:, k], np.asarray(cd["fn"])[:, k])
        c = bc.clearance * 1e6
        a.plot(c * np.cos(circle), c * np.sin(circle), color="C3", lw=1.2, label=f"clearance {c:g} um")
        a.plot(x, y, lw=0.4, color="C0", label="shaft centre")
        if on.any():
            a.plot(x[on], y[on], ".", ms=2, color="C3", label="in contact")
        a.plot(x[:1], y[:1], "o", ms=4, mfc="none", color="k", label="start")
        a.plot(x[-1:], y[-1:], "o", ms=4, color="k", label="end")
        a.set_aspect("equal", adjustable="datalim")
        a.axhline(0, color="0.7", lw=0.5); a.axvline(0, color="0.7", lw=0.5); a.grid(alpha=0.3)
        a.set_xlabel("x (um)"); a.set_ylabel("y (um, gravity along -y)")
        seen = sorted({e.name for e in bc.whirl_episodes} - {bc.whirl.name})
        a.set_title(f"{bc.name}: {bc.events} contact{'s' if bc.events != 1 else ''}, peak {force_text(bc.peak_force_N)}\n"
                    f"at the end: {bc.whirl.name}" + (f"; earlier: {', '.join(seen)}" if seen else ""), fontsize=10)
        a.legend(fontsize=7, loc="upper right")
    fig.suptitle("shaft centre in the auxiliary bearings' clearance\n" + title)
    fig.tight_layout()
    return fig


def _forces(plt, res, rep, title, marks):
    cd = res.contact
    t = np.asarray(res.t, float)
    m = len(rep.bearings)
    fig, ax = plt.subplots(m, 2, figsize=(13, 2.4 + 2.0 * m), sharex=True, squeeze=False)
    r_s, r_i = cd.get("shaft_radius"), cd.get("race_radius")
    for k, bc in enumerate(rep.bearings):
        a = ax[k, 0]
        a.plot(t, np.asarray(cd["fn"])[:, k], lw=0.6, label="normal force (record)")
        ev = [e for e in cd.get("events") or () if e.get("bearing") == bc.name and e.get("phase") == "end"]
        if ev:
            a.plot([e["t_s"] for e in ev], [e.get("peak_force_N", np.nan) for e in ev], "v", ms=3, color="C3",
                   label="event peak (contact log)")
        a.set_ylabel(f"{bc.name}: force (N)"); a.grid(alpha=0.3); a.legend(fontsize=7, loc="upper right")
        _mark_times(a, marks, labels=k == 0)
        b = ax[k, 1]
        b.plot(t, np.asarray(cd["race_speed"])[:, k], lw=0.8, label="race speed")
        if r_s is not None and r_i is not None:
            b.plot(t, np.asarray(res.speed, float) * float(r_s[k]) / float(r_i[k]), lw=0.6, ls="--", color="0.4",
                   label="spin x R_s/R_i (rolling)")
        b.set_ylabel(f"{bc.name}: rad/s"); b.grid(alpha=0.3); b.legend(fontsize=7, loc="upper right")
        _mark_times(b, marks, labels=False)
    ax[-1, 0].set_xlabel("t (s)"); ax[-1, 1].set_xlabel("t (s)")
    fig.suptitle("auxiliary bearings: contact force and race speed\n" + title)
    fig.tight_layout()
    return fig


def _ratio(plt, res, rep, title, marks):
    cd = res.contact
    fig, a = plt.subplots(1, 1, figsize=(10, 4.4))
    lo, hi = -1.0, 1.0
    for k, bc in enumerate(rep.bearings):
        t, ratio = whirl_ratio_series(res, k)
        a.plot(t, ratio, lw=0.8, label=f"{bc.name}: {bc.whirl.name}")
        lo, hi = min(lo, np.nanmin(ratio, initial=lo)), max(hi, np.nanmax(ratio, initial=hi))
    a.axhline(1.0, color="0.5", lw=0.6, ls=":")
    a.axhline(0.0, color="0.5", lw=0.6)
    r_s, r_i = cd.get("shaft_radius"), cd.get("race_radius")
    note = ""
    if r_s is not None:
        gap = float(r_i[0]) - float(r_s[0]) if r_i is not None else float(cd["clearance"][0])
        ref = -float(r_s[0]) / gap
        if ref >= lo - 0.5 * (hi - lo):                   # in view: drawn; far below the data: named
            a.axhline(ref, color="C3", lw=0.6, ls="--", label=f"rolling backward whirl -R_s/(R_i-R_s) = {ref:.3g}")
        else:
            note = f"; rolling backward whirl on a held race at {ref:.3g} (out of view)"
    a.set_xlim(float(res.t[0]), float(res.t[-1]))
    a.set_xlabel("t (s)"); a.set_ylabel("orbit rate / spin speed")
    a.set_title("whirl ratio where the orbit runs at the clearance (>= 90 %); blank elsewhere" + note, fontsize=10)
    a.grid(alpha=0.3); a.legend(fontsize=8, loc="best")
    _mark_times(a, marks)
    fig.suptitle(title)
    fig.tight_layout()
    return fig
