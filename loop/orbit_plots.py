"""The orbit plots of a simulated run (matplotlib, Agg backend): per output node the whirl radius
over time, the x-y orbit against the touchdown clearance and that AMB's coil currents; every
AMB's control currents over time.  Time plots mark the scheduled faults and a run-up's ramp."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .orbits import time_marks
from .sim_result import SimResult


def plot_orbits(res: SimResult, out_dir, nodes=None, gaps: dict | None = None,
                clearances: dict | None = None) -> list[Path]:
    """``orbit_node<k>.png`` per output node (whirl radius over time, the x-y orbit with +y up and
    the touchdown clearance circle of an AMB node, that AMB's coil currents) and ``currents.png``
    (every AMB's control currents over time).  ``clearances``: {1-based node: touchdown clearance
    (m)} of the AMB nodes, the circle the orbit is judged against; ``gaps``: {1-based node:
    magnetic gap (m)}, drawn apart (grey, dashed) where it is in view.  A clearance much larger
    than the orbit is drawn in an inset at its own scale, so the orbit stays readable.  Every
    time plot marks each scheduled fault's start and end and a run-up's ramp (:func:`time_marks`);
    the titles name the speed, or the run-up's range (:func:`speed_title`)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    out = []
    gaps, clearances = gaps or {}, clearances or {}
    nodes = nodes or res.nodes
    every = int(res.meta.get("record_every", 1))
    n_i = min(res.steps // every, len(res.i))            # answered samples (the last row has none)
    stations = _stations(res.axes)
    amb_at = {nd: name for name, nd in _amb_nodes(res, stations, clearances or gaps)}
    marks = time_marks(res)
    for nd in nodes:
        if nd not in res.nodes:
            continue
        fig = _node_figure(plt, res, nd, amb_at.get(nd), stations, n_i, gaps, clearances, marks)
        p = Path(out_dir) / f"orbit_node{nd}.png"
        fig.savefig(p, dpi=110); plt.close(fig)
        out.append(p)
    if stations and n_i:
        fig = _currents_figure(plt, res, stations, n_i, marks)
        p = Path(out_dir) / "currents.png"
        fig.savefig(p, dpi=110); plt.close(fig)
        out.append(p)
    return out


def _node_figure(plt, res: SimResult, nd, st, stations, n_i, gaps, clearances, marks):
    """One output node: whirl radius over time, the x-y orbit (with the clearance circle of an AMB
    node) and, at an AMB node (station ``st``), that AMB's coil currents."""
    j = res.nodes.index(nd)
    x, y = res.orbit[:, j, 0] * 1e6, res.orbit[:, j, 1] * 1e6
    fig, ax = plt.subplots(1, 3 if st else 2, figsize=(15 if st else 10, 4.4))
    ax[0].plot(res.t, np.hypot(x, y), lw=0.6)
    ax[0].set_xlabel("t (s)"); ax[0].set_ylabel("orbit radius (um)")
    ax[0].set_title(f"node {nd}: whirl radius"); ax[0].grid(alpha=0.3)
    _mark_times(ax[0], marks)
    ax[1].plot(x, y, lw=0.4)
    ax[1].plot(x[-1:], y[-1:], "o", ms=3, color="C0")
    ax[1].set_aspect("equal", adjustable="datalim"); ax[1].set_xlabel("x (um)"); ax[1].set_ylabel("y (um)")
    ax[1].axhline(0, color="0.7", lw=0.5); ax[1].axvline(0, color="0.7", lw=0.5); ax[1].grid(alpha=0.3)
    title = f"node {nd}" + (f" (AMB {st})" if st else "") + f": orbit ({res.meta['integrator']}, h={res.meta['h']:g} s)"
    g = clearances.get(nd)
    if g:
        title += _draw_clearance(ax[1], x, y, g * 1e6, gaps[nd] * 1e6 if gaps.get(nd) else None)
    ax[1].set_title(title, fontsize=10)
    if st:
        for k, (axn, col) in enumerate(stations[st]):
            ax[2].plot(res.t[:n_i], res.i[:n_i, col], lw=0.6, label=f"{st}-{axn}")
        ax[2].set_xlabel("t (s)"); ax[2].set_ylabel("control current (A)")
        ax[2].set_title(f"AMB {st}: coil currents"); ax[2].legend(fontsize=8, loc="upper right"); ax[2].grid(alpha=0.3)
        _mark_times(ax[2], marks)
    fig.suptitle(f"{res.meta['scene']} [{res.meta['rung']}] {speed_title(res.meta)}" + _faults_title(marks))
    fig.tight_layout()
    return fig


def _draw_clearance(ax, x, y, g_um, mg_um) -> str:
    """The touchdown clearance circle of radius ``g_um`` (and the magnetic gap ``mg_um``, dashed,
    if given) on an orbit plot: at the orbit's scale when that keeps the orbit readable, else in
    an inset at its own scale.  Returns the title's line on the largest radius."""
    r_max = float(np.nanmax(np.hypot(x, y))) if len(x) else 0.0
    circle = np.linspace(0, 2 * np.pi, 361)
    title = (f"\nlargest radius {r_max:.3g} um = {100 * r_max / g_um:.1f} % of the touchdown clearance "
             f"{g_um:g} um")
    if r_max > 0.3 * g_um:                                   # same scale: draw it
        ax.plot(g_um * np.cos(circle), g_um * np.sin(circle), color="C3", lw=1.2,
                label=f"touchdown clearance {g_um:g} um")
        if mg_um:
            ax.plot(mg_um * np.cos(circle), mg_um * np.sin(circle), color="0.5", lw=1.0, ls="--",
                    label=f"magnetic gap {mg_um:g} um")
        ax.legend(loc="upper right", fontsize=8)
    else:                                                   # inset at the clearance's scale
        ins = ax.inset_axes([0.76, 0.7, 0.23, 0.23])        # in the corner the orbit leaves free
        if mg_um:
            ins.plot(mg_um * np.cos(circle), mg_um * np.sin(circle), color="0.5", lw=0.8, ls="--")
        ins.plot(g_um * np.cos(circle), g_um * np.sin(circle), color="C3", lw=1.0)
        ins.plot(x, y, lw=0.6, color="C0")
        ins.set_aspect("equal"); ins.set_xticks([]); ins.set_yticks([])
        ins.set_xlabel(f"touchdown clearance {g_um:g} um" + (f"\n(dashed: magnetic gap {mg_um:g} um)"
                                                             if mg_um else ""),
                       fontsize=7, color="C3", labelpad=1)
    return title


def _currents_figure(plt, res: SimResult, stations, n_i, marks):
    """Every AMB's control currents over time, one row per AMB."""
    fig, ax = plt.subplots(len(stations), 1, figsize=(10, 2.2 + 1.8 * len(stations)), sharex=True, squeeze=False)
    for r, (st, cols) in enumerate(stations.items()):
        a = ax[r, 0]
        for axn, col in cols:
            a.plot(res.t[:n_i], res.i[:n_i, col], lw=0.6, label=f"{st}-{axn}")
        a.set_ylabel(f"AMB {st} (A)"); a.legend(fontsize=8, loc="upper right"); a.grid(alpha=0.3)
        _mark_times(a, marks, labels=r == 0)
    ax[-1, 0].set_xlabel("t (s)")
    fig.suptitle(f"{res.meta['scene']} [{res.meta['rung']}]: control currents per AMB axis\n{speed_title(res.meta)}"
                 + _faults_title(marks))
    fig.tight_layout()
    return fig


def speed_title(meta: dict) -> str:
    """The spin speed of a run for a title: ``at 327.2 rad/s (3124 rpm)``, or for a run-up
    ``run-up 1000 -> 2000 rad/s (9549 -> 19099 rpm), t 0.02-0.04 s``."""
    rpm = 60 / (2 * np.pi)
    ru = meta.get("run_up")
    if ru:
        w0, w1, t0, t1 = (float(v) for v in ru[:4])
        return f"run-up {w0:.4g} -> {w1:.4g} rad/s ({w0 * rpm:.0f} -> {w1 * rpm:.0f} rpm), t {t0:g}-{t1:g} s"
    w = float(meta.get("speed", 0.0))
    return f"at {w:.1f} rad/s ({w * rpm:.0f} rpm)"


def _faults_title(marks) -> str:
    n = sum(m["kind"] == "fault" for m in marks)
    return f"\n{n} scheduled fault{'s' if n > 1 else ''}: shaded from start (dashed) to end (dotted)" if n else ""


def _mark_times(ax, marks, labels: bool = True) -> None:
    """Shade each fault's window (red, dashed start, dotted end; to the right edge if it does not
    end) and a run-up's ramp (grey), with its name at the top of the axes."""
    if not marks:
        return
    tr = ax.get_xaxis_transform()
    right = ax.get_xlim()[1]
    for k, m in enumerate(marks):
        fault = m["kind"] == "fault"
        col = "C3" if fault else "0.4"
        t0 = m["start_s"]
        t1 = m["end_s"] if m["end_s"] is not None else right
        ax.axvspan(t0, t1, color=col, alpha=0.08 if fault else 0.06, lw=0, zorder=0)
        ax.axvline(t0, color=col, ls="--", lw=0.9, zorder=1)
        if m["end_s"] is not None:
            ax.axvline(m["end_s"], color=col, ls=":", lw=0.9, zorder=1)
        if labels:
            ax.text(t0, 0.98 - 0.1 * (k % 4), f" {m['label']}" + ("" if m["end_s"] is not None else " (to the end)"),
                    transform=tr, fontsize=7, color="darkred" if fault else "0.3", va="top", ha="left", zorder=5,
                    bbox=dict(fc="white", alpha=0.75, lw=0, pad=0.5))
    ax.set_xlim(right=right)


def _stations(axes) -> dict:
    """{station: [(axis, column), ...]} from ``SimResult.axes`` labels ``"A:x"``."""
    out: dict = {}
    for col, lab in enumerate(axes):
        st, _, axn = str(lab).partition(":")
        out.setdefault(st, []).append((axn, col))
    return out


def _amb_nodes(res: SimResult, stations: dict, gaps: dict):
    """(station, 1-based node) pairs: the meta's AMB nodes when known, else the ``gaps`` (or
    clearances) order."""
    nodes = res.meta.get("amb_nodes")
    if isinstance(nodes, dict):
        return [(st, int(nodes[st])) for st in stations if st in nodes]
    return list(zip(stations, gaps))

