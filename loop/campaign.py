"""Fault campaigns: a list of cases (faults + pass/fail criteria) run against a controller.

A campaign file (TOML, e.g. ``scenes/faults_paper_3amb.toml``)::

    [campaign]                       # defaults for every case (optional)
    duration = "0.8s"                # simulated time of each case
    recovery_band = 0.1              # "recovered": every revolution's peak within +-10 % of the pre-fault orbit

    [[case]]
    name = "blade loss"
    faults = ["unbalance_step:at=0.3s,node=30,magnitude=0.002"]   # --fault specs, or [[case.fault]] tables
    max_orbit_fraction = 0.5         # largest orbit radius at every AMB <= 50 % of its touchdown clearance
    recovery_time = "0.2s"           # back within the band of the pre-fault orbit this long after the faults
    must_stay_stable = true          # no touchdown or blow-up, and the orbit does not grow at the end

    [[case]]
    name = "drop and re-levitation"  # a drop that ends: the AMBs come back and must lift the rotor
    faults = ["drop:at=0.1s,until=0.2s"]
    relevitation_time = "0.2s"       # lifted off the auxiliary bearings this long after the return (default 0.2 s)
    max_relevitation_force = 2000    # N, peak contact force after the return (default: reported only)
    no_backward_whirl = true         # default true

Metrics of a run (:func:`evaluate`), from the orbit at each AMB station (x, y of its two axes):

- ``max_orbit_fraction``: the largest radius over the whole run divided by that AMB's touchdown
  clearance (``RadialAMB.clearance``: the scene's ``touchdown_clearance``, else half the magnetic
  gap), the largest over the stations;
- ``pre_fault``: the mean per-revolution peak radius over the last quarter before the first fault;
- ``recovery_time``: from the *reference time* (the latest fault end, or the fault start of a fault
  that never ends) to the start of the first revolution after which every revolution's peak stays
  within ``recovery_band`` of ``pre_fault`` at every station (inf if never);
- ``stable``: the run completed without a plant fault, and the peak radius over the last 10 % of
  the run is at most 1.05 x that over the 10 % before (a growing orbit is not stable);
- re-levitation, judged in every case with a ``drop`` that ends (the AMBs come back at its end,
  ``t_return``, the latest such end): ``loop.contact_results.relevitation(res, t_return)`` gives
  the time to lift off the auxiliary bearings (None: never), the peak contact force after the
  return and whether the shaft whirled backward; limits ``relevitation_time`` (default 0.2 s),
  ``max_relevitation_force`` (default none: reported only), ``no_backward_whirl`` (default true).
  A case whose re-levitation cannot be measured (no contact record) fails: a criterion that was
  not checked never passes.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .scene import Scene
from .scene_faults import parse_fault, spec_value
from .scene_table import SceneError, Table
from ambhil.plant.faults import FaultSchedule, check_schedule
from ambhil.plant.params import ParameterError

#: the re-levitation limit on the time to lift off when a campaign gives none, s
RELEVITATION_TIME = 0.2


@dataclass(frozen=True)
class Case:
    name: str
    faults: FaultSchedule
    specs: tuple[str, ...]  # the faults as --fault specs (for `ambhil run`)
    duration: float
    max_orbit_fraction: float | None = None
    recovery_time: float | None = None
    recovery_band: float = 0.1
    must_stay_stable: bool = True
    # re-levitation (a drop that ends): the AMBs' return, s (None: not judged) and the limits
    t_return: float | None = None
    relevitation_time: float | None = None
    max_relevitation_force: float | None = None
    no_backward_whirl: bool = True

    @property
    def judges_relevitation(self) -> bool:
        return self.t_return is not None


@dataclass
class CaseResult:
    case: Case
    passed: bool
    metrics: dict
    failures: list[str] = field(default_factory=list)
    events: list = field(default_factory=list)


def _spec_text(raw: dict) -> str:
    """A [[case.fault]] table as a --fault spec."""
    return str(raw.get("kind", "")) + ":" + ",".join(f"{k}={v}" for k, v in raw.items() if k != "kind")


def load_campaign(path, scene: Scene) -> list[Case]:
    """Parse a campaign file against a scene (fault axes and nodes are checked against it)."""
    p = str(path)
    try:
        text = Path(path).read_bytes()[: 1 << 20].decode("utf-8")
        doc = tomllib.loads(text)
    except FileNotFoundError:
        raise SceneError(f"{p}: no such campaign file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise SceneError(f"{p}: cannot read the campaign: {e}") from None
    for k in doc:
        if k not in ("campaign", "case"):
            raise SceneError(f"{p}: unknown top-level key {k!r} (allowed: campaign, case)")
    t = Table(p, "[campaign]", doc.get("campaign", {}))
    dflt = {"duration": t.quantity("duration", t.raw("duration", scene.plant.simulation.duration), "time"),
            "recovery_band": t.num("recovery_band", 0.1, positive=True), **_relevitation_limits(t, {})}
    t.done()
    cases = doc.get("case", [])
    if not isinstance(cases, list) or not cases:
        raise SceneError(f"{p}: needs at least one [[case]] table")
    out = []
    for i, raw in enumerate(cases):
        where = f"[[case]] #{i + 1}"
        t = Table(p, where, raw)
        name = t.string("name")
        t.where = where = f"{where} {name!r}"
        fl = t.raw("faults", [])
        tables = t.raw("fault", [])
        if not isinstance(fl, list) or not all(isinstance(s, str) for s in fl):
            t.fail("faults", f"must be a list of fault specs such as \"amb_loss:at=0.1s,axis=B\", got {t.short(fl)}")
        if not isinstance(tables, list) or not all(isinstance(s, dict) for s in tables):
            t.fail("fault", "must be [[case.fault]] tables")
        specs, faults = [], []
        for j, s in enumerate(fl):
            kind, _, rest = s.partition(":")
            table: dict[str, Any] = {"kind": kind.strip()}
            for item in (x for x in rest.split(",") if x.strip()):
                k, eq, v = item.partition("=")
                if not eq:
                    t.fail("faults", f"[{j}] {s!r}: expected KIND:key=value,...")
                table[k.strip()] = spec_value(v.strip())
            faults.append(parse_fault(table, p, f"{where} faults[{j}]", scene.plant, len(faults) + 1))
            specs.append(s)
        for j, tab in enumerate(tables):
            faults.append(parse_fault(tab, p, f"{where} fault #{j + 1}", scene.plant, len(faults) + 1))
            specs.append(_spec_text(tab))
        if not faults:
            t.fail("faults", "a case needs at least one fault")
        dur = t.quantity("duration", t.raw("duration"), "time") if t.has("duration") else dflt["duration"]
        mof = t.num("max_orbit_fraction", None, positive=True)
        rec = t.quantity("recovery_time", t.raw("recovery_time"), "time") if t.has("recovery_time") else None
        first = min(f.start for f in faults)
        if not first > 0:
            t.fail("faults", "the first fault must start after 0 s (the pre-fault orbit is measured before it)")
        if not dur > first:
            t.fail("duration", f"{dur:g} s ends before the first fault at {first:g} s")
        try:
            check_schedule(FaultSchedule(tuple(faults)))
        except ParameterError as e:
            t.fail("faults", str(e))
        ends = [f.end for f in faults if f.kind == "drop" and math.isfinite(f.end)]
        rl = _relevitation_limits(t, dflt)
        if not ends and any(t.has(k) for k in rl):
            t.fail(next(k for k in rl if t.has(k)), "re-levitation is judged after a drop that ends (until or "
                                                    "duration: the AMBs come back); this case has none")
        t_return = max(ends) if ends else None
        if t_return is not None and not dur > t_return:
            t.fail("duration", f"{dur:g} s ends before the AMBs come back at {t_return:g} s (the drop's end)")
        out.append(Case(name=name, faults=FaultSchedule(tuple(faults)), specs=tuple(specs), duration=dur,
                        max_orbit_fraction=mof, recovery_time=rec,
                        recovery_band=t.num("recovery_band", dflt["recovery_band"], positive=True),
                        must_stay_stable=t.boolean("must_stay_stable", True),
                        t_return=t_return, **(rl if ends else {})))
        t.done()
    names = [c.name for c in out]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise SceneError(f"{p}: two cases are named {dup!r}")
    return out


def _relevitation_limits(t: Table, dflt: dict) -> dict:
    """The re-levitation keys of a table (``[campaign]``: defaults for every drop case; a case:
    its own, else the defaults)."""
    lim = dflt.get("relevitation_time", RELEVITATION_TIME)
    if t.has("relevitation_time"):
        lim = t.quantity("relevitation_time", t.raw("relevitation_time"), "time")
        if not lim > 0:
            t.fail("relevitation_time", f"must be > 0 s, got {lim:g}")
    return {"relevitation_time": lim,
            "max_relevitation_force": t.num("max_relevitation_force", dflt.get("max_relevitation_force"),
                                            positive=True),
            "no_backward_whirl": t.boolean("no_backward_whirl", dflt.get("no_backward_whirl", True))}


def judge_relevitation(case: Case, relev, why: str = "") -> tuple[dict, list[str]]:
    """Metrics and failures of a re-levitation case from ``relev`` (the object of
    ``loop.contact_results.relevitation``: ``time_s``, ``peak_force_N``, ``backward_whirl``,
    ``lines()``); ``relev`` None: not measured (``why``), which fails the case."""
    if relev is None:
        return ({"t_return_s": case.t_return, "measured": False, "why": why},
                [f"re-levitation not measured ({why})" if why else "re-levitation not measured"])
    ts, pk, bw = relev.time_s, float(relev.peak_force_N or 0.0), bool(relev.backward_whirl)
    m = {"t_return_s": case.t_return, "measured": True, "time_s": None if ts is None else float(ts),
         "peak_force_N": pk, "backward_whirl": bw, "lines": list(relev.lines())}
    fails = []
    lim = case.relevitation_time
    if ts is None:
        fails.append(f"never lifted off the auxiliary bearings after the AMBs came back at {case.t_return:g} s")
    elif lim is not None and not ts <= lim:
        fails.append(f"re-levitated after {ts:.3g} s > {lim:g} s")
    if case.max_relevitation_force is not None and not pk <= case.max_relevitation_force:
        fails.append(f"peak contact force after the return {pk:.4g} N > {case.max_relevitation_force:g} N")
    if case.no_backward_whirl and bw:
        fails.append("backward whirl on the auxiliary bearings")
    return m, fails


def _peaks(t, r, T):
    """Per-window peak of r over windows of length T: (window starts, peaks)."""
    edges = np.arange(t[0], t[-1] + 1e-12, T)
    idx = np.searchsorted(t, edges)
    pk = np.array([r[a:b].max() if b > a else np.nan for a, b in zip(idx[:-1], idx[1:])])
    return edges[:-1], pk


def evaluate(case: Case, t, xy, clearances, speed: float, completed: bool, fault: str | None,
             relev=None, relev_why: str = "") -> CaseResult:
    """Metrics and verdict of one case from its orbits ``xy`` (samples x stations x 2), the
    stations' touchdown clearances and the spin speed (revolution length; 10 ms windows at standstill);
    a re-levitation case also from ``relev`` (:func:`judge_relevitation`; None: not measured, ``relev_why``)."""
    t = np.asarray(t)
    r = np.hypot(xy[..., 0], xy[..., 1])                       # samples x stations
    clearances = np.asarray(clearances, float)
    T = 2 * math.pi / speed if speed > 0 else 0.01
    T = max(T, 2 * (t[1] - t[0]) if len(t) > 1 else T)
    f = case.faults.faults
    t0 = min(x.start for x in f)
    tref = max(x.end if math.isfinite(x.end) else x.start for x in f)
    m: dict[str, Any] = {"max_orbit_fraction": float(np.nanmax(r / clearances)) if len(r) else float("nan"),
                         "stations_max_radius_m": [float(np.nanmax(r[:, k])) for k in range(r.shape[1])]}
    fails = []
    pre = []
    for k in range(r.shape[1]):
        ok = (t >= 0.75 * t0) & (t < t0)
        _, pk = _peaks(t[ok], r[ok, k], T) if ok.sum() > 2 else (None, np.array([np.nan]))
        pre.append(float(np.nanmean(pk)) if np.isfinite(pk).any() else float("nan"))
    m["pre_fault_radius_m"] = pre
    # recovery: first window start after tref from which every window peak stays in the band
    rec = 0.0
    for k in range(r.shape[1]):
        ok = t >= tref
        if ok.sum() < 3 or not math.isfinite(pre[k]):
            rec = math.inf
            break
        st, pk = _peaks(t[ok], r[ok, k], T)
        bad = np.where(~(np.abs(pk - pre[k]) <= case.recovery_band * pre[k]))[0]
        if len(bad) == 0:
            continue
        rec = max(rec, (st[bad[-1] + 1] - tref) if bad[-1] + 1 < len(st) else math.inf)
    m["recovery_time_s"] = rec
    stable = completed and fault is None
    if stable and len(t) > 20:
        n = len(t)
        last, before = r[int(0.9 * n):].max(), r[int(0.8 * n):int(0.9 * n)].max()
        stable = bool(last <= 1.05 * before)
        m["growth_last_10pct"] = float(last / before) if before > 0 else float("nan")
    m["stable"] = stable
    if fault:
        m["fault"] = fault
    if case.max_orbit_fraction is not None and not m["max_orbit_fraction"] <= case.max_orbit_fraction:
        fails.append(f"orbit {100 * m['max_orbit_fraction']:.1f} % of the touchdown clearance > "
                     f"{100 * case.max_orbit_fraction:g} %")
    if case.recovery_time is not None and not rec <= case.recovery_time:
        fails.append("never recovered" if math.isinf(rec) else f"recovered after {rec:.3g} s > {case.recovery_time:g} s")
    if case.must_stay_stable and not stable:
        fails.append(f"not stable ({fault})" if fault else "not stable (orbit growing at the end)"
                     if completed else "run did not complete")
    if case.judges_relevitation:
        m["relevitation"], more = judge_relevitation(case, relev, relev_why)
        fails += more
    return CaseResult(case, not fails, m, fails)


def run_case(system, case: Case, law: str | None = None) -> CaseResult:
    """One case in process: ``simulate`` with the case's faults (and ``law``, a resolved name,
    instead of the scene's, controller/law_loader.py); orbits at the AMB nodes.  A law that fails
    at a step ends the case with its fault: not stable."""
    from .simulation import simulate
    nodes = [a.node + 1 for a in system.spec.ambs]
    res = simulate(system, case.duration, nodes=tuple(nodes), faults=case.faults, law=law)
    planned = int(round(case.duration / res.meta["period"]))
    relev, why = None, ""
    if case.judges_relevitation:
        if getattr(res, "contact", None) is None:
            aux = any(getattr(a, "auxiliary", None) is not None for a in system.spec.ambs)
            why = "the run kept no contact record" if aux else "the scene has no auxiliary bearings, [amb.auxiliary]"
        else:
            from .contact_results import relevitation
            relev = relevitation(res, case.t_return)
    cr = evaluate(case, res.t, res.orbit, [a.clearance for a in system.spec.ambs], res.meta["speed"],
                  res.steps >= planned, res.fault or res.instability, relev, why)
    cr.events = res.events or []
    return cr
