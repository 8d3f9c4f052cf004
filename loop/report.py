"""The frequency-domain report of one or more scenes (`ambhil analyze`): tables and PNG plots."""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import plots
from .analysis import margins, modal, sensitivity, support_sweep, unbalance, vibration
from .scene import Scene, load_scene
from .system import System, compile_system

HZ = 1 / (2 * np.pi)


@dataclass
class SceneReport:
    scene: Scene
    model: System
    criticals: list
    least: modal.Mode
    unstable: list
    sens: sensitivity.SensitivityResult
    unb: unbalance.UnbalanceResult
    sweep: support_sweep.SweepResult | None
    open_loop: margins.OpenLoop | None = None
    vib: vibration.VibrationResult | None = None
    stab: margins.StabilityMap | None = None


def output_nodes(scene: Scene) -> list[int]:
    if scene.analysis.output_nodes:
        return list(scene.analysis.output_nodes)
    nodes = [a.node for a in scene.plant.ambs] + [u.node for u in scene.plant.unbalances]
    return list(dict.fromkeys(nodes))


def node_labels(scene: Scene) -> dict[int, str]:
    lab = {k: f"node {k + 1}" for k in range(scene.plant.n_nodes)}
    for a in scene.plant.ambs:
        lab[a.node] = f"node {a.node + 1} (AMB {a.name})"
    for d in scene.plant.discs:
        lab[d.node] = f"node {d.node + 1} ({d.name})"
    return lab


def _quiet(label: str):
    return None


def run_scene(scene: Scene, out: Path | None, sweep: bool = True, campbell_points: int = 41,
              progress=_quiet) -> SceneReport:
    """Analyse one scene; ``progress(label)`` returns a ``callback(done, total)`` or None."""
    model = compile_system(scene)
    smax = scene.analysis.frequency_max
    solver = modal.Solver(model)
    crit = modal.critical_speeds(model, speed_max=1.1 * smax, solver=solver)  # every one in the range
    nominal = scene.plant.speed.nominal
    fmodes = 2 * np.pi * 5000.0
    modes = solver.all(nominal, fmodes)
    least = min(modes, key=lambda m: m.damping_ratio)
    unstable = [m for m in modes if m.eigenvalue.real > 0]
    poles = [m.eigenvalue.imag for m in modes if m.damping_ratio < 0.3]
    sens = sensitivity.sensitivity(model, nominal, poles=poles)
    ol = margins.open_loop(model, nominal)
    lo, hi, npts = scene.plant.speed.sweep
    nodes = output_nodes(scene)
    nodes += [a.sensor_node for a in scene.plant.ambs if a.sensor_node not in nodes]
    unb = unbalance.response(model, np.linspace(lo, hi, npts), nodes=nodes)
    vib = vibration.evaluate(model)
    sw = None
    if sweep and scene.analysis.sweep_amb:
        sw = support_sweep.sweep(scene, scene.analysis.sweep_amb, progress=progress(f"{scene.name}: support sweep"))
    stab = None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        speeds = np.linspace(0.0, smax, campbell_points)
        camp = modal.campbell(model, speeds, 1.1 * smax, progress=progress(f"{scene.name}: Campbell"))
        plots.campbell(out / f"{scene.name}_campbell.png", scene.name, camp, crit, smax,
                       scene.analysis.reference_criticals, scene.analysis.reference)
        stab = margins.stability_over_speed(model, speeds, fmodes, progress=progress(f"{scene.name}: stability"))
        plots.stability(out / f"{scene.name}_stability.png", scene.name, stab, nominal)
        c, given = vibration.clearance(model)
        plots.unbalance(out / f"{scene.name}_unbalance.png", {scene.name: unb}, node_labels(scene), clearance=c,
                        unbalances=scene.plant.unbalances, clearance_note="" if given else "assumed: half the gap")
        plots.sensitivity(out / f"{scene.name}_sensitivity.png", scene.name, sens)
        plots.bode(out / f"{scene.name}_open_loop.png", scene.name, ol)
        if sw is not None:
            plots.support_sweep(out / f"{scene.name}_support_sweep.png", scene.name, sw)
    return SceneReport(scene, model, crit, least, unstable, sens, unb, sw, ol, vib, stab)


def _fmt_table(rows: list[list[str]]) -> str:
    from rich import box
    from rich.console import Console
    from rich.table import Table
    t = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False, header_style=None)
    for k, head in enumerate(rows[0]):
        t.add_column(head, justify="left" if k == 0 else "right", no_wrap=True)
    for r in rows[1:]:
        t.add_row(*r)
    con = Console(width=10_000, color_system=None, highlight=False, record=True, file=io.StringIO())
    con.print(t)
    return "\n".join(line.rstrip() for line in con.export_text().splitlines())


def report_text(reports: list[SceneReport]) -> str:
    out = []
    n = max(4, max(len(r.criticals) for r in reports))
    rows = [["scene", "rung"] + [f"crit {k + 1} (Hz)" for k in range(n)] + ["least zeta", "S peak", "zone"]]
    for r in reports:
        cs = [f"{c.hz:.2f} {c.kind[0]}" for c in r.criticals] + ["-"] * (n - len(r.criticals))
        worst = int(np.argmax(r.sens.peaks))
        rows.append([r.scene.name, r.model.rung] + cs +
                     [f"{r.least.damping_ratio:.4f}", f"{r.sens.peaks[worst]:.2f}", r.sens.zones[worst]])
        ref = r.scene.analysis.reference_criticals
        if ref:
            rows.append(["  published", ""] + [f"{v:.2f}" for v in ref] + ["-"] * (n - len(ref)) + ["", "", ""])
            d = [f"{100 * (c.hz / v - 1):+.1f}%" for c, v in zip(r.criticals, ref)]
            rows.append(["  difference", ""] + d + ["-"] * (n - len(d)) + ["", "", ""])
    out.append("Critical speeds (forward whirl crossing 1x; r = rigid, f = flexible), stability and sensitivity")
    out.append(_fmt_table(rows))
    for r in reports:
        sc = r.scene
        out.append("")
        out.append(f"[{sc.name}] {sc.description}".rstrip())
        out.append(f"  model: rung {r.model.rung}, {r.model.n} coordinates, {sc.plant.n_nodes - 1} elements, "
                   f"mass {r.model.rotor.mass:.1f} kg; AMB k_x / k_i: " +
                   ", ".join(f"{a}{x} {kx:.3g} N/m / {ki:.3g} N/A" for j, ((a, x), kx, ki) in
                             enumerate(zip(r.model.axes, r.model.kx, r.model.ki))
                             if x != "y" or not np.isclose(kx, r.model.kx[j - 1])))
        m = r.least
        out.append(f"  stability at {sc.plant.speed.nominal:.0f} rad/s: least-damped mode {m.frequency_hz:.2f} Hz "
                   f"({m.whirl}), zeta = {m.damping_ratio:.4f}" +
                   (f"; UNSTABLE modes: " + ", ".join(f"{u.frequency_hz:.1f} Hz (Re = {u.eigenvalue.real:+.3g}/s)"
                                                       for u in r.unstable) if r.unstable else "; all modes stable"))
        sens = ", ".join(f"{a}-{x} {p:.2f} ({20 * np.log10(p):.1f} dB, zone {z}) at {f * HZ:.0f} Hz"
                         for (a, x), p, z, f in zip(r.sens.axes, r.sens.peaks, r.sens.zones, r.sens.peak_freqs) if x != "y")
        out.append(f"  sensitivity (ISO 14839-3, x axes; y alike when isotropic; peaks refined at the loop's poles): {sens}")
        if r.open_loop is not None:
            out.append("  open loop per axis (broken there, others closed; y alike when not shown): " + "; ".join(_margin_txt(m) for m in r.open_loop.margins
                                                                                       if _show_axis(r.open_loop, m)))
        if r.stab is not None:
            k = int(np.argmin(r.stab.zeta))
            out.append(f"  stability over 0..{r.stab.speeds[-1] * HZ:.0f} Hz spin: least zeta {r.stab.zeta[k]:.4f} at "
                       f"{r.stab.speeds[k] * HZ:.1f} Hz spin ({r.stab.freq[k] * HZ:.1f} Hz {r.stab.whirl[k]} mode)")
        if r.vib is not None:
            v = r.vib
            out.append(f"  vibration (ISO 14839-2, zone limits 0.3/0.4/0.5 C_min unverified): C_min = {v.clearance * 1e6:.0f} um"
                       + ("" if v.clearance_given else " (assumed: half the smallest gap; set [analysis] touchdown_clearance)")
                       + "; " + ", ".join(f"{s.amb} {s.d_max * 1e6:.2f} um = {s.ratio:.3f} C_min (zone {s.zone}) at "
                                          f"{s.at_speed * HZ:.1f} Hz" for s in v.stations))
        labels = node_labels(sc)
        for j, k in enumerate(r.unb.nodes):
            pk = ", ".join(f"{s * HZ:.2f} Hz: {a:.3g} m" for s, a in r.unb.peaks(j))
            out.append(f"  unbalance peaks at {labels[k]}: {pk or 'none'}")
        if r.sweep is not None:
            inc = r.sweep.increase()
            out.append(f"  support sweep of AMB {r.sweep.amb}: {len(r.sweep.nodes)} positions; baseline without it: " +
                       ", ".join(f"{v * HZ:.2f}" for v in r.sweep.baseline) + " Hz")
            for k in range(inc.shape[1]):
                if np.all(np.isnan(inc[:, k])):
                    continue
                j = int(np.nanargmax(inc[:, k]))
                out.append(f"    critical {k + 1}: largest change {inc[j, k]:+.2f}% at x = {r.sweep.positions[j]:.3f} m "
                           f"(node {r.sweep.nodes[j] + 1}, {r.sweep.criticals[j, k] * HZ:.2f} Hz)")
    return "\n".join(out)


def _show_axis(ol, m) -> bool:
    """False for a y axis whose margins read as its x axis' (an isotropic bearing)."""
    j = ol.margins.index(m)
    if m.axis[1] != "y" or j == 0:
        return True
    return _margin_txt(m).split(" ", 1)[1] != _margin_txt(ol.margins[j - 1]).split(" ", 1)[1]


def _margin_txt(m) -> str:
    pm, up, lo = m.phase_margin, m.upper_gm, m.lower_gm
    t = [f"PM {pm[0]:.1f} deg at {pm[1] * HZ:.0f} Hz" if pm else "no gain crossover"]
    if up:
        t.append(f"GM x{up[0]:.2f} ({20 * np.log10(up[0]):+.1f} dB) at {up[1] * HZ:.0f} Hz")
    if lo:
        t.append(f"lower GM x{lo[0]:.3f} ({20 * np.log10(lo[0]):+.1f} dB) at {lo[1] * HZ:.0f} Hz")
    return f"{m.axis[0]}-{m.axis[1]} " + ", ".join(t)


def analyze(paths: list[str], out: str | None, sweep: bool = True, progress=_quiet) -> tuple[list[SceneReport], str]:
    """Analyse the scenes; with ``out`` also write the plots and report.txt there.  Returns the
    reports and the text report (a bad scene raises SceneError)."""
    scenes = [load_scene(p) for p in paths]
    outdir = Path(out) if out else None
    reports = [run_scene(s, outdir, sweep=sweep, progress=progress) for s in scenes]
    if outdir is not None and len(reports) > 1:
        plots.unbalance(outdir / "unbalance_compare.png",
                        {r.scene.name: unbalance.UnbalanceResult(r.unb.speeds, r.unb.nodes[:1], r.unb.x[:, :1], r.unb.y[:, :1])
                         for r in reports}, node_labels(reports[0].scene))
    text = report_text(reports)
    if outdir is not None:
        (outdir / "report.txt").write_text(text + "\n")
    return reports, text


def figures(reports: list[SceneReport]) -> list[dict]:
    """The report's figures as plain data (the CLI's --json)."""
    return [{
        "scene": r.scene.name, "path": str(r.scene.path), "rung": r.model.rung,
        "criticals": [{"hz": c.hz, "kind": c.kind} for c in r.criticals],
        "reference_criticals_hz": list(r.scene.analysis.reference_criticals or []),
        "least_damped": {"hz": r.least.frequency_hz, "zeta": r.least.damping_ratio, "whirl": r.least.whirl},
        "unstable_modes": [{"hz": u.frequency_hz, "re": u.eigenvalue.real} for u in r.unstable],
        "sensitivity": [{"axis": f"{a}-{x}", "peak": p, "zone": z, "hz": f * HZ}
                        for (a, x), p, z, f in zip(r.sens.axes, r.sens.peaks, r.sens.zones, r.sens.peak_freqs)],
        "open_loop": [{"axis": f"{m.axis[0]}-{m.axis[1]}",
                       "phase_margin_deg": m.phase_margin[0] if m.phase_margin else None,
                       "phase_margin_hz": m.phase_margin[1] * HZ if m.phase_margin else None,
                       "gain_margin": m.upper_gm[0] if m.upper_gm else None,
                       "gain_margin_hz": m.upper_gm[1] * HZ if m.upper_gm else None,
                       "lower_gain_margin": m.lower_gm[0] if m.lower_gm else None}
                      for m in (r.open_loop.margins if r.open_loop else ())],
        "vibration_iso14839_2": ({"clearance_m": r.vib.clearance, "clearance_given": r.vib.clearance_given,
                                  "stations": [{"amb": s.amb, "d_max_m": s.d_max, "ratio": s.ratio, "zone": s.zone,
                                                "hz": s.at_speed * HZ} for s in r.vib.stations]} if r.vib else None),
        "unbalance_peaks": {str(k + 1): [{"hz": s * HZ, "amplitude_m": a} for s, a in r.unb.peaks(j)]
                            for j, k in enumerate(r.unb.nodes)},
    } for r in reports]
