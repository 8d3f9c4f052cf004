"""The verdict of an `ambhil run`: what went wrong, first things first (a run that did not keep
its rate, the user's stop, a peer that died, a fault, a loop predicted to grow, traffic from
another process, an incomplete recording).  Any reason fails the run (exit 1, 130 if stopped).
Traffic rejected by any process (by reason, ``auth`` = no valid MAC under the run's key) and
strangers (peers that failed the pairing proof) are reported, and fail the run under
``--strict``: its files are then ``.failed`` and the recording's run_end says failed."""
from __future__ import annotations

from ambhil.bridge.cli.children import exit_text
from ambhil.bridge.cli.rt_check import reference_orbits
from ambhil.bridge.cli.run_files import recorded_samples
from ambhil.bridge.cli.simulate import not_steady


def foreign_report(sp: dict | None, sc: dict | None, sr: dict | None = None) -> str | None:
    """One line on the messages the plant, controller and recorder rejected, by reason (``auth``:
    no valid MAC under the run's key), and the strangers (peers that announced themselves and
    failed the pairing proof); None if none: a run that saw another process publish into it, or
    malformed traffic, says so."""
    parts = []
    for role, s in (("plant", sp), ("controller", sc), ("recorder", sr)):
        total = (s or {}).get("rejected_total")
        if total is None and s:
            total = sum(v for v in (s.get("rejected") or {}).values() if isinstance(v, int))
        if total:
            why = ", ".join(f"{k} {v}" for k, v in sorted(s["rejected"].items()) if v)
            parts.append(f"{role} rejected {total} messages ({why})")
    extra = (sp or {}).get("foreign_peers") or 0
    if extra:
        parts.append(f"{extra} further controller(s) announced themselves")
    if sc and sc.get("foreign_run_ends"):
        parts.append(f"controller ignored {sc['foreign_run_ends']} RUN_END events not from its plant")
    seen = []
    for s in (sp, sc, sr):
        for x in (s or {}).get("strangers") or []:
            if x not in seen:
                seen.append(x)
                parts.append(f"stranger {x} failed the pairing proof")
    if not parts:
        return None
    # a wrong peer id or a wrong MAC: another process put messages into the run
    peer = sum((s.get("rejected", {}).get(r) or 0) for s in (sp, sc) if s for r in ("peer", "auth"))
    # plant and controller put what they reject as foreign again for the recorder (bridge/process/events.py,
    # ForeignCopies: at most 1000 each); an external controller's summary may not say
    copied = sum((s.get("foreign_copied") or 0) for s in (sp, sc) if s)
    kept = ("its messages are in the recording under foreign/" if copied >= peer else
            f"{copied} of its {peer} messages are in the recording under foreign/" if copied else
            "its messages are not in the recording")
    return ("; ".join(parts) + (f": another process published into this run (ignored; {kept})"
                                if peer else ""))


def overrun_count(args):
    """``--max-overruns N`` (a count) is the plant's: it halts after N overruns."""
    lim = getattr(args, "max_overruns", None)
    return lim[1] if lim and lim[0] == "count" else None


def rate_check(args, scene, model, sp: dict | None, orbits: list, latency: float) -> dict | None:
    """Did a real-time run keep its rate?  ``--max-overruns P%``: more than P % of the periods
    after the warm-up overran -> ``kept`` False, and ``reason`` says so in one line with how far
    the run's largest orbit is from the in-process loop's of the same scene (bridge/cli/rt_check.py;
    what a run that kept its rate records).  None for lockstep, no limit or no plant summary."""
    lim = getattr(args, "max_overruns", None)
    if args.mode != "realtime" or not sp or not lim or lim[0] != "percent":
        return None
    warm = min(sp.get("warmup_steps", 0), sp["steps"])
    counted = sp["steps"] - warm
    pct = 100.0 * sp["overruns"] / counted if counted else 0.0
    out = {"overrun_percent": pct, "limit_percent": lim[1], "kept": pct <= lim[1],
           "reference": "in-process loop (ambhil.loop.simulation.simulate), same scene, rung, integrator, step, latency",
           "reference_orbits_m": None, "reason": None}
    if out["kept"]:
        return out
    fs = scene.controller.sample_rate
    text = (f"the loop did not keep {fs:g} Hz: {sp['overruns']} of {counted} periods overran ({pct:.2f} % > "
            f"--max-overruns {lim[1]:g} %), so its results are not the scene's")
    ref = reference_orbits(scene, model, args, sp["steps"], latency) if sp["steps"] else None
    if ref and orbits:
        out["reference_orbits_m"] = ref
        pairs = [(nm, r, q) for (nm, r, _), q in zip(orbits, ref) if q > 0]
        if pairs:
            nm, r, q = max(pairs, key=lambda t: abs(t[1] - t[2]))   # the largest difference
            text += (f": orbit {nm} {r * 1e6:.2f} um against {q * 1e6:.2f} um in process "
                     f"({100 * (r / q - 1):+.0f} %)")
    out["reason"] = text
    return out


def _last_words(err: str) -> str:
    """A dying peer's own last words (its one-line error), if any."""
    lines = [ln for ln in err.strip().splitlines() if "error:" in ln]
    return f" ({lines[-1].strip()})" if lines else ""


def failures(results: dict, early: dict, interrupted: str | None, pre, strict: bool, mcap,
             record: bool) -> tuple[list[str], int | None, str | None, bool]:
    """(reasons, sensor samples recorded, the rejected-traffic line, recording incomplete) from the
    processes' ``results`` (name -> (summary, stderr, exit code)) and the peers that ended early."""
    sp, sc, sr = (results[k][0] for k in ("plant", "controller", "recorder"))
    reasons = []
    if interrupted:
        reasons.append(f"interrupted by the user ({interrupted})")
    if "controller" in early and not (sc and sc.get("fault")):
        reasons.append(f"controller {early['controller']} during the run{_last_words(results['controller'][1])}")
    if "recorder" in early:
        reasons.append(f"recorder: {sr['write_error']}" if sr and sr.get("write_error")
                       else f"recorder {early['recorder']} during the run{_last_words(results['recorder'][1])}")
    # a law that failed at a step is the cause (the plant then only lost its controller): named first
    law_fault = str((sc or {}).get("fault") or "").startswith("law ")
    for name in ("controller", "plant") if law_fault else ("plant", "controller"):
        s, err, code = results[name]
        if s is None:
            if name in early:
                continue
            tail = err.strip().splitlines()[-1] if err.strip() else None
            reasons.append(f"{name} gave no summary ({exit_text(code)}" + (f": {tail})" if tail else ")"))
        elif s.get("fault"):
            reasons.append(f"{name}: {s['fault']}")
    if not interrupted and not (sp or {}).get("fault"):
        if (nst := not_steady(pre)):        # the rule of `simulate`: a loop that grows has no steady orbit
            reasons.append(nst)
    recorded = None                         # sensor samples in the file
    if record and sr is not None:
        recorded = sr.get("steps_recorded")
    elif record:
        if "recorder" not in early:
            reasons.append(f"recorder gave no summary ({exit_text(results['recorder'][2])})")
        recorded = recorded_samples(mcap)
    foreign = foreign_report(sp, sc, sr)
    if foreign and strict:
        reasons.append(f"--strict: {foreign}")
    incomplete = sp is not None and recorded is not None and recorded < sp["steps"]
    if incomplete:
        reasons.append(f"recording incomplete: {recorded} of the plant's {sp['steps']} steps recorded")
    return reasons, recorded, foreign, incomplete
