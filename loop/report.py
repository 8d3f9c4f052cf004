"""The frequency-domain report of one or more scenes (`ambhil analyze`): tables and PNG plots."""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import plots
from .analysis import margins, modal, over_speed, sensitivity, support_sweep, unbalance, vibration
from .scene import Scene, SceneError, load_scene, touchdown_note
from .system import System, black_box_reason, compile_system

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
    over: over_speed.OverSpeed | None = None  # sensitivity, margins, least damping over the operating speeds


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
    fmodes = 2 * np.pi * 5000.0
    # over the operating speeds: the worst sensitivity (speed refined), least margins, least damping
    ovs = over_speed.scan(model, fmax=fmodes, progress=progress(f"{scene.name}: sensitivity over speed"))
    least, unstable = ovs.least.least, list(ovs.least.unstable)
    wp = ovs.worst_point
    sens, ol = wp.sens, wp.open_loop  # at the speed of the worst sensitivity peak
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
        plots.stability(out / f"{scene.name}_stability.png", scene.name, stab, operating=ovs.intervals)
        plots.unbalance(out / f"{scene.name}_unbalance.png", {scene.name: unb}, node_labels(scene),
                        clearance={a.name: a.clearance for a in scene.plant.ambs}, unbalances=scene.plant.unbalances,
                        clearance_note=("assumed: half the magnetic gap" if touchdown_note(scene.plant.ambs) else ""))
        plots.sensitivity(out / f"{scene.name}_sensitivity.png", scene.name, sens, over=ovs)
        if ol is None:
            ol = margins.open_loop(model, wp.speed)
        plots.bode(out / f"{scene.name}_open_loop.png", scene.name, ol)
        if sw is not None:
            plots.support_sweep(out / f"{scene.name}_support_sweep.png", scene.name, sw)
    return SceneReport(scene, model, crit, least, unstable, sens, unb, sw, ol, vib, stab, ovs)


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
    rows = [["scene", "rung"] + [f"crit {k + 1} (Hz)" for k in range(n)]
            + ["least zeta", "zeta at spin (Hz)", "S peak", "zone", "S at spin (Hz)"]]
    for r in reports:
        cs = [f"{c.hz:.2f} {c.kind[0]}" for c in r.criticals] + ["-"] * (n - len(r.criticals))
        w = _worst_sens(r)
        rows.append([r.scene.name, r.model.rung] + cs +
                     [f"{r.least.damping_ratio:.4f}", _spin(r, _least_speed(r)), f"{w[0]:.2f}", w[1], _spin(r, w[3])])
        ref = r.scene.analysis.reference_criticals
        if ref:
            rows.append(["  published", ""] + [f"{v:.2f}" for v in ref] + ["-"] * (n - len(ref)) + [""] * 5)
            d = [f"{100 * (c.hz / v - 1):+.1f}%" for c, v in zip(r.criticals, ref)]
            rows.append(["  difference", ""] + d + ["-"] * (n - len(d)) + [""] * 5)
    out.append("Critical speeds (forward whirl crossing 1x; r = rigid, f = flexible); least damping and ISO 14839-3 "
               "sensitivity peak (continuous-time loop): the worst over the operating speeds, at the spin speed given")
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
        if r.over is not None:
            out.append(f"  operating speeds: {_operating_txt(r.over)}")
        out.append(f"  stability{' over the operating speeds' if r.over is not None else ''}: least-damped mode "
                   f"{m.frequency_hz:.2f} Hz ({m.whirl}), zeta = {m.damping_ratio:.4f} at {_spin(r, _least_speed(r))} Hz spin" +
                   (f"; UNSTABLE modes: " + ", ".join(f"{u.frequency_hz:.1f} Hz (Re = {u.eigenvalue.real:+.3g}/s)"
                                                       for u in r.unstable) if r.unstable else "; all modes stable"))
        out.extend(_sensitivity_lines(r))
        if r.over is not None:
            mw = r.over.margins()
            n_ol = sum(p.open_loop is not None for p in r.over.points)
            over_txt = (f"the least margins over the {n_ol} grid speeds (not refined in speed)" if n_ol > 1
                        else f"at {r.over.points[0].speed * HZ:.1f} Hz spin")
            out.append(f"  open loop per axis (broken there, others closed), {over_txt}; y axes where they differ from x: "
                       + "; ".join(_margin_worst_txt(w) for j, w in enumerate(mw)
                                   if w.axis[1] != "y" or j == 0 or _margin_worst_txt(w).split(" ", 1)[1]
                                   != _margin_worst_txt(mw[j - 1]).split(" ", 1)[1]))
        elif r.open_loop is not None:
            out.append("  open loop per axis (broken there, others closed; y alike when not shown): " + "; ".join(_margin_txt(m) for m in r.open_loop.margins
                                                                                       if _show_axis(r.open_loop, m)))
        if r.stab is not None:
            k = int(np.argmin(r.stab.zeta))
            out.append(f"  stability over 0..{r.stab.speeds[-1] * HZ:.0f} Hz spin: least zeta {r.stab.zeta[k]:.4f} at "
                       f"{r.stab.speeds[k] * HZ:.1f} Hz spin ({r.stab.freq[k] * HZ:.1f} Hz {r.stab.whirl[k]} mode)")
        if r.vib is not None:
            v = r.vib
            note = touchdown_note(sc.plant.ambs)
            out.append("  vibration (ISO 14839-2: largest orbit against each AMB's touchdown clearance C_min, zone "
                       "limits 30/40/50 % of C_min unverified): "
                       + ", ".join(f"{s.amb} {s.d_max * 1e6:.2f} um = {100 * s.ratio:.1f} % of {s.clearance * 1e6:g} um "
                                   f"(zone {s.zone}) at {s.at_speed * HZ:.1f} Hz"
                                   for s in v.stations)
                       + (f"; {note}" if note else ""))
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


def _spin(r, speed: float) -> str:
    return f"{speed * HZ:.1f}"


def _least_speed(r) -> float:
    return r.over.least.speed if r.over is not None else r.scene.plant.speed.nominal


def _worst_sens(r) -> tuple[float, str, float, float]:
    """(peak, zone, rad/s, spin rad/s) of the worst axis over the operating speeds."""
    if r.over is not None:
        w = r.over.worst[r.over.worst_axis]
        return w.peak, w.zone, w.freq, w.speed
    j = int(np.argmax(r.sens.peaks))
    return float(r.sens.peaks[j]), r.sens.zones[j], float(r.sens.peak_freqs[j]), r.sens.speed


def _operating_txt(ov) -> str:
    ivs = "; ".join((f"{lo * HZ:.1f}-{hi * HZ:.1f} Hz spin" if hi > lo else f"{lo * HZ:.1f} Hz spin")
                    + f" ({lo:g}{'-' + format(hi, 'g') if hi > lo else ''} rad/s, {src})" for lo, hi, src in ov.intervals)
    if not any(hi > lo for lo, hi, _ in ov.intervals):
        return ivs
    return f"{ivs}; {len(ov.points)} speeds evaluated (a grid over each range, each axis' worst refined)"


def _sens_txt(axes, peaks, zones, freqs, spins=None, show=None) -> str:
    return (", " if spins is None else "; ").join(f"{a}-{x} {p:.2f} ({20 * np.log10(p):.1f} dB, zone {z}) at {f * HZ:.0f} Hz"
                     + (f", {spins[j] * HZ:.1f} Hz spin" if spins is not None else "")
                     for j, ((a, x), p, z, f) in enumerate(zip(axes, peaks, zones, freqs)) if show is None or show[j])


def _differs(axes, *cols) -> list[bool]:
    """Show x axes, and a y axis where any figure differs from its x axis' (an anisotropic bearing)."""
    return [x != "y" or j == 0 or any(not np.isclose(c[j], c[j - 1], rtol=1e-6) for c in cols)
            for j, (_, x) in enumerate(axes)]


def _sensitivity_lines(r) -> list[str]:
    """The ISO 14839-3 lines: the worst over the operating speeds, and at the simulation speed."""
    if r.over is None:
        show = _differs(r.sens.axes, r.sens.peaks, r.sens.peak_freqs)
        return [f"  sensitivity (ISO 14839-3, continuous-time loop, at {r.sens.speed * HZ:.1f} Hz spin; y axes where they "
                f"differ from x): {_sens_txt(r.sens.axes, r.sens.peaks, r.sens.zones, r.sens.peak_freqs, show=show)}"]
    ov = r.over
    pk = [w.peak for w in ov.worst]
    fr = [w.freq for w in ov.worst]
    sp = [w.speed for w in ov.worst]
    show = _differs(ov.axes, pk, fr, sp)
    out = ["  sensitivity (ISO 14839-3, continuous-time loop; per axis the largest peak over the operating speeds, at "
           "the spin speed given; y axes where they differ from x): "
           + _sens_txt(ov.axes, pk, [w.zone for w in ov.worst], fr, sp, show)]
    sim = r.scene.plant.simulation.speed
    if sim is not None and any(w.speed != sim for w in ov.worst):
        p = ov.at(sim).sens
        show = _differs(p.axes, p.peaks, p.peak_freqs)
        out.append(f"  sensitivity at the [simulation] speed {sim:g} rad/s ({sim * HZ:.1f} Hz spin): "
                   + _sens_txt(p.axes, p.peaks, p.zones, p.peak_freqs, show=show)
                   + " (continuous-time loop; `study timing` takes this speed and evaluates the sampled loop, "
                     "discretised controller and zero-order hold, whose peaks are higher and approach these as the "
                     "rate grows)")
    return out


def _margin_worst_txt(w) -> str:
    pm, up, lo = w.phase_margin, w.upper_gm, w.lower_gm
    t = [f"PM {pm[0]:.1f} deg at {pm[1] * HZ:.0f} Hz ({pm[2] * HZ:.1f} Hz spin)" if pm else "no gain crossover"]
    if w.no_crossover_at and pm:
        t.append("no gain crossover at " + ", ".join(f"{s * HZ:.1f}" for s in w.no_crossover_at) + " Hz spin")
    if up:
        t.append(f"GM x{up[0]:.2f} ({20 * np.log10(up[0]):+.1f} dB) at {up[1] * HZ:.0f} Hz ({up[2] * HZ:.1f} Hz spin)")
    if lo:
        t.append(f"lower GM x{lo[0]:.3f} ({20 * np.log10(lo[0]):+.1f} dB) at {lo[1] * HZ:.0f} Hz ({lo[2] * HZ:.1f} Hz spin)")
    return f"{w.axis[0]}-{w.axis[1]} " + ", ".join(t)


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
    for s in scenes:    # every figure of the report is of the closed loop: none without a linear law
        why = black_box_reason(s)
        if why:
            raise SceneError(f"{s.path}: the closed-loop analyses are not computed ({why})")
    outdir = Path(out) if out else None
    reports = [run_scene(s, outdir, sweep=sweep, progress=progress) for s in scenes]
    if outdir is not None and len(reports) > 1:
        plots.unbalance(outdir / "unbalance_compare.png",
                        {r.scene.name: unbalance.UnbalanceResult(r.unb.speeds, r.unb.nodes[:1], r.unb.x[:, :1], r.unb.y[:, :1])
                         for r in reports}, node_labels(reports[0].scene),
                        unbalances={r.scene.name: r.scene.plant.unbalances for r in reports})
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
        "least_damped": {"hz": r.least.frequency_hz, "zeta": r.least.damping_ratio, "whirl": r.least.whirl,
                         "spin_hz": _least_speed(r) * HZ},
        "unstable_modes": [{"hz": u.frequency_hz, "re": u.eigenvalue.real} for u in r.unstable],
        # per axis the worst over the operating speeds, with the spin speed where it occurs
        "operating_speeds_rad_s": [{"from": lo, "to": hi, "source": src} for lo, hi, src in r.over.intervals]
        if r.over else None,
        "sensitivity": [{"axis": f"{w.axis[0]}-{w.axis[1]}", "peak": w.peak, "zone": w.zone, "hz": w.freq * HZ,
                         "spin_hz": w.speed * HZ} for w in r.over.worst] if r.over else
                       [{"axis": f"{a}-{x}", "peak": p, "zone": z, "hz": f * HZ, "spin_hz": r.sens.speed * HZ}
                        for (a, x), p, z, f in zip(r.sens.axes, r.sens.peaks, r.sens.zones, r.sens.peak_freqs)],
        "open_loop": [{"axis": f"{m.axis[0]}-{m.axis[1]}",
                       "phase_margin_deg": m.phase_margin[0] if m.phase_margin else None,
                       "phase_margin_hz": m.phase_margin[1] * HZ if m.phase_margin else None,
                       "phase_margin_spin_hz": m.phase_margin[2] * HZ if m.phase_margin else None,
                       "gain_margin": m.upper_gm[0] if m.upper_gm else None,
                       "gain_margin_hz": m.upper_gm[1] * HZ if m.upper_gm else None,
                       "gain_margin_spin_hz": m.upper_gm[2] * HZ if m.upper_gm else None,
                       "lower_gain_margin": m.lower_gm[0] if m.lower_gm else None,
                       "lower_gain_margin_spin_hz": m.lower_gm[2] * HZ if m.lower_gm else None}
                      for m in (r.over.margins() if r.over else ())],
        "vibration_iso14839_2": ({"clearance_m": r.vib.clearance, "clearance_given": r.vib.clearance_given,
                                  "stations": [{"amb": s.amb, "d_max_m": s.d_max, "ratio": s.ratio, "zone": s.zone,
                                                "hz": s.at_speed * HZ, "touchdown_clearance_m": s.clearance,
                                                "touchdown_clearance_given": s.clearance_given}
                                               for s in r.vib.stations]} if r.vib else None),
        "unbalance_peaks": {str(k + 1): [{"hz": s * HZ, "amplitude_m": a} for s, a in r.unb.peaks(j)]
                            for j, k in enumerate(r.unb.nodes)},
    } for r in reports]
