"""The summary of an `ambhil run`: what went wrong first, then the figures (steps, overruns,
latency, orbits against the touchdown clearance, injected faults, files), as one JSON line
(``--json``) or as lines for a person."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ambhil.loop.scene import touchdown_note
from ambhil.bridge.cli.arguments import law_label


@dataclass
class Outcome:
    """Everything the summary reports on one run."""
    args: object
    scene: object
    model: object
    run_id: str
    latency: float
    transport: dict
    record: bool
    pre: object                      # ambhil.loop.timing_study.Precheck or None
    cal: dict | None                 # bridge/cli/rt_check.py calibrate (real time)
    results: dict                    # name -> (summary, stderr, exit code)
    interrupted: str | None
    reasons: list[str]
    recorded: int | None
    foreign: str | None
    incomplete: bool
    orbits: list = field(default_factory=list)
    injected: list = field(default_factory=list)
    orbit_err: str | None = None
    rate: dict | None = None
    files: list[Path] = field(default_factory=list)
    auth: dict | None = None         # bridge/cli/keyfile.py RunKey.describe: mode, text, per_run, key_file

    @property
    def fs(self) -> float:
        return self.scene.controller.sample_rate

    @property
    def law(self) -> str:
        """The law the run's controller ran: ``--law``, else the scene's (``--controller CMD``: the command)."""
        if getattr(self.args, "controller", None):
            return f"--controller {self.args.controller}"
        return law_label(getattr(self.args, "law", None), self.scene)


def _fmt(st: dict) -> str:
    return (f"p50 {st.get('p50', float('nan')):.1f} / p99 {st.get('p99', float('nan')):.1f} / "
            f"max {st.get('max', float('nan')):.1f} us" if st.get("n") else "n/a")


def summary(o: Outcome) -> dict:
    """The JSON summary (``--json``)."""
    sp, sc, sr = (o.results[k][0] for k in ("plant", "controller", "recorder"))
    scene = o.scene
    return {"command": "run", "ok": not o.reasons, "failed": o.reasons, "run_id": o.run_id, "scene": scene.name,
            "law": o.law,
            "rung": o.model.rung, "mode": o.args.mode, "controller_rate_hz": o.fs, "latency_s": o.latency,
            "transport": o.transport, "recorded": o.record, "auth": o.auth,
            "strangers": strangers(o),
            "precheck": None if o.pre is None else {"stable": o.pre.stable, "note": o.pre.line},
            "rejected_note": o.foreign,
            "plant": sp, "controller": sc, "recorder": sr, "recorded_steps": o.recorded,
            "orbits": [{"station": nm, "largest_radius_m": r, "touchdown_clearance_m": scene.plant.amb(nm).clearance,
                        "fraction_of_touchdown_clearance": f} for nm, r, f in o.orbits],
            "touchdown_clearance_note": touchdown_note(scene.plant.ambs) or None,
            "fault_events": o.injected,
            "files": [str(f) for f in o.files],
            "calibration": o.cal, "rate": o.rate}


def strangers(o: Outcome) -> list[str]:
    """The peer ids (hex) that announced themselves in the run and failed the pairing proof."""
    out = []
    for name in ("plant", "controller", "recorder"):
        for x in ((o.results.get(name) or (None,))[0] or {}).get("strangers") or []:
            if x not in out:
                out.append(x)
    return out


def _plant_lines(o: Outcome, sp: dict, sc: dict | None) -> None:
    fs = o.fs
    print(f"  steps      {sp['steps']}/{sp['n_steps']} ({sp['steps'] / fs:.3f} s simulated) "
          f"in {sp['wall_s']:.2f} s wall, {sp['steps_per_s']:.0f} steps/s")
    if o.args.mode == "realtime":
        warm = min(sp.get("warmup_steps", 0), sp["steps"])
        counted = sp["steps"] - warm
        frac = sp["overruns"] / counted if counted else 0.0
        held = sp.get("held", 0)
        print(f"  overruns   {sp['overruns']} of {counted} periods after the {warm}-period warm-up "
              f"({100 * frac:.2f} %); currents held in {held} of all {sp['steps']} periods "
              f"({100 * held / max(sp['steps'], 1):.2f} %, warm-up included)")
        if frac > 0.01 and not (o.rate and not o.rate["kept"]):
            print(f"  note       more than 1 % overruns: this machine does not sustain {fs:g} Hz real time "
                  f"with this plant (docs/hil.md); lockstep runs at any rate")
    else:
        print(f"  overruns   {sp['overruns']}")
    if sc:
        print(f"  loops      plant {sp.get('loop')}, controller {sc.get('loop')} (C: bridge/protocol/_plant_lockstep.c / _controller_lockstep.c run "
              f"the ordinary steps; {sp.get('loop_handbacks', 0)} / {sc.get('loop_handbacks', 0)} "
              f"handed back to Python)")
    print(f"  latency    round trip {_fmt(sp['latency_us'])}; controller TET {_fmt(sp['tet_us'])}")
    if o.args.mode == "realtime":
        print(f"  wake late  {_fmt(sp['lateness_us'])}; CPU wake-up latency request: "
              f"{sp.get('cpu_wake_latency')}")
        rr = sp.get("rt_receive") or {}
        print(f"  receive    {rr.get('mode')} ({rr.get('why')}"
              + (f"; timer on CPU {rr['timer_cpu']}, fired {rr.get('timer_fires')} times"
                 if rr.get("mode") == "deadline" else "") + ")")


def _recording_lines(o: Outcome, sp: dict | None) -> None:
    scene = o.scene
    for e in o.injected:
        params = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in e["params"].items())
        print(f"  fault      {e['phase']:5s} t={e['t_s']:.4g} s (step {e['step']}): {e['kind']}"
              + (f" {e['axis']}" if e.get("axis") else "") + (f" {params}" if params else ""))
    if o.incomplete:
        print(f"  recording  INCOMPLETE: the .mcap stops after {o.recorded} of the plant's {sp['steps']} steps")
    for nm, r, frac in o.orbits:
        print(f"  orbit {nm:4s} largest radius {r * 1e6:8.2f} um = {100 * frac:5.1f}% of the touchdown clearance "
              f"{scene.plant.amb(nm).clearance * 1e6:g} um" + (" (of a failed run)" if o.reasons else ""))
    if o.orbits and touchdown_note(scene.plant.ambs):
        print(f"  note       {touchdown_note(scene.plant.ambs)}")
    if o.rate and o.rate.get("reference_orbits_m"):
        print("  reference  in-process loop of the same scene (what a run that kept its rate records): "
              + ", ".join(f"orbit {nm} {q * 1e6:.2f} um" for (nm, _, _), q in zip(o.orbits, o.rate["reference_orbits_m"])))
    if o.orbit_err:
        print(f"  orbit: could not read the recording: {o.orbit_err}")
    for nm, c in ((sp or {}).get("contact") or {}).get("bearings", {}).items():   # auxiliary bearings
        if not c.get("events"):
            print(f"  contact {nm:4s} none: the shaft never touched this auxiliary bearing")
            continue
        print(f"  contact {nm:4s} {c['events']} event{'s' if c['events'] != 1 else ''}, peak "
              f"{c['peak_force_N']:.4g} N, max penetration {c['max_penetration_m'] * 1e6:.3g} um, friction "
              f"{c['friction_energy_J']:.4g} J, race {c['race_speed_end']:.4g} rad/s at the end"
              + (", in contact at the end" if c.get("in_contact_at_end") else ""))


def print_human(o: Outcome) -> None:
    """The summary for a person: what went wrong first, then the figures."""
    sp, sc = o.results["plant"][0], o.results["controller"][0]
    fs, latency = o.fs, o.latency
    print(f"run {o.run_id}: scene {o.scene.name}, rung {o.model.rung}, mode {o.args.mode}, controller {fs:g} Hz "
          f"(law {o.law})"
          + (f", latency {latency * 1e6:g} us ({latency * fs:g} periods)" if latency else ""))
    if o.reasons:
        print(f"  {'STOPPED' if o.interrupted else 'FAILED':10s} {'; '.join(o.reasons)}")
    touched = {nm: c for nm, c in ((sp or {}).get("contact") or {}).get("bearings", {}).items() if c.get("events")}
    if touched:     # the rotor was on its auxiliary bearings: say so before the figures
        nm, c = max(touched.items(), key=lambda kv: kv[1]["peak_force_N"] or 0.0)
        print(f"  TOUCHDOWN  on the auxiliary bearings {', '.join(touched)}: peak {c['peak_force_N']:.4g} N ({nm}); "
              f"contact lines below")
    print(f"  transport  {o.transport['text']}")
    if o.auth:
        print(f"  auth       {o.auth['text']}")
    if o.cal:
        print(f"  machine    {o.cal['line']}")
    if o.pre is not None and not o.pre.stable:
        print(f"  predicted  {o.pre.line}")
    if sp:
        _plant_lines(o, sp, sc)
    if o.foreign:
        print(f"  REJECTED   {o.foreign}")
    _recording_lines(o, sp)
    print(f"  files      {', '.join(map(str, o.files)) or 'none'}"
          + (f" (marked .failed: the run {'was stopped' if o.interrupted else 'failed'}; the MCAP's "
             f"ambhil.run_end metadata says why)"
             if o.reasons and o.files else ""))
