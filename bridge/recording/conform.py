"""Conformance of a controller process in any language (docs/controllers.md): replay a recording's
sensor stream to it over zenoh as the plant would (lockstep, :func:`ambhil.bridge.recording.controller_replay.to_controller`),
and compare its currents with the recorded ones, axis by axis.

This module adds, around ``to_controller``: the controller process (any command line, or the
built-in ``ambhil controller SCENE``, or one started by hand) and the per-axis table of the
largest deviation.  ``to_controller`` publishes the recorded RunMeta, sealed under the session
key of its pairing with the controller (so that a controller that reads its law from RunMeta
gets it, docs/protocol.md §5.2, and pairs by it, §5.3).  With a key (``secret``) the controller
under test must be given the same key (its own ``--key-file``), or it cannot pair.
"""
from __future__ import annotations

import os
import shlex
import subprocess
import tempfile
import threading
import time

import numpy as np

from ambhil.bridge.process import transport as tr
from ambhil.bridge import protocol as pr
from ambhil.bridge.recording.controller_replay import to_controller
from ambhil.bridge.recording.load import axis_names, load_run

EXIT_GRACE_S = 30.0      # s a controller may take to exit after RUN_END (last resort; it is told)
WAIT_CAP_S = 300.0       # s; last-resort cap on waiting for a live controller to get ready


class ConformanceError(RuntimeError):
    """The controller under test could not be started or never became ready (one line)."""


def controller_command(cmd: str, run_id: str, connect: str) -> list[str]:
    """``--controller-cmd`` text -> argv: ``{run_id}`` and ``{connect}`` are replaced (the replay's
    run id and endpoint); a leading ``ambhil`` runs this very installation's CLI."""
    try:
        argv = [a.replace("{run_id}", run_id).replace("{connect}", connect) for a in shlex.split(cmd)]
    except ValueError as e:
        raise ConformanceError(f"--controller-cmd {cmd!r}: {e}") from None
    if not argv:
        raise ConformanceError("--controller-cmd: empty command")
    if argv[0] == "ambhil":
        import sys
        argv = [sys.executable, "-m", "ambhil.bridge.cli"] + argv[1:]
    return argv


class _Process:
    """The controller under test as a child process; its output goes to a temporary file (shown,
    last lines, when it fails)."""

    def __init__(self, argv: list[str], run_id: str, connect: str):
        self.argv = argv
        self.log = tempfile.TemporaryFile(mode="w+")
        env = dict(os.environ, AMBHIL_RUN_ID=run_id, AMBHIL_CONNECT=connect, PYTHONUNBUFFERED="1")
        try:
            self.p = subprocess.Popen(argv, stdout=self.log, stderr=subprocess.STDOUT, env=env,
                                      start_new_session=True)
        except OSError as e:
            raise ConformanceError(f"cannot start the controller `{shlex.join(argv)}`: {e}") from None

    def tail(self, n: int = 3) -> str:
        self.log.seek(0)
        lines = [ln.rstrip() for ln in self.log.read().splitlines() if ln.strip()]
        return " | ".join(lines[-n:])

    def finish(self, grace: float) -> dict:
        """Wait for the process to exit by itself (it was sent RUN_END); kill it after ``grace``."""
        try:
            code = self.p.wait(timeout=grace)
            killed = False
        except subprocess.TimeoutExpired:
            self.p.kill()
            code, killed = self.p.wait(), True
        out = {"exit_code": code, "killed": killed, "output_tail": self.tail()}
        self.log.close()
        return out


def _wait_ready(session, run_id: str, proc: _Process | None, start_timeout: float) -> None:
    """Until ``alive/controller``: as long as the launched process runs (up to WAIT_CAP_S), or,
    for a controller started by hand, as long as it holds ``starting/controller`` (absence for
    ``start_timeout`` in total gives up)."""
    K = pr.keys(run_id)
    cond = threading.Condition()
    seen: set[str] = set()

    def _cb(key, alive):
        with cond:
            (seen.add if alive else seen.discard)(key.rsplit("/", 2)[-2])
            cond.notify_all()
    watch = tr.LivelinessWatch(session, f"{K.root}/*/controller", _cb)
    try:
        t0 = last = time.monotonic()
        absent = 0.0
        with cond:
            while "alive" not in seen:
                now = time.monotonic()
                if proc is not None:
                    code = proc.p.poll()
                    if code is not None:
                        raise ConformanceError(f"the controller `{shlex.join(proc.argv)}` exited "
                                               f"with code {code} before it was ready: {proc.tail()}")
                    if now - t0 > WAIT_CAP_S:
                        raise ConformanceError(f"the controller `{shlex.join(proc.argv)}` runs but "
                                               f"declared no {K.alive_controller} within "
                                               f"{WAIT_CAP_S:g} s: {proc.tail()}")
                elif "starting" not in seen:
                    absent += now - last
                    if absent > start_timeout:
                        raise ConformanceError(f"no controller on run {run_id} within "
                                               f"{start_timeout:g} s")
                last = now
                cond.wait(0.05)
    finally:
        watch.undeclare()


def per_axis(replies: dict, recorded: dict, names: list[str], *, tolerance: float = 0.0,
             where: dict | None = None) -> list[dict]:
    """Largest |replayed - recorded| per axis over the seqs both have, with its seq (and, from
    ``where`` = {seq: (step, sim time s)}, its step and time), and how many samples exceed
    ``tolerance`` (``over``) from which seq on (``first_over``)."""
    seqs = sorted(set(replies) & set(recorded))
    n = len(names)
    if not seqs:
        return [{"axis": names[j], "max_abs_dev": None, "seq": None, "over": 0, "first_over": None}
                for j in range(n)]
    R = np.array([replies[s] for s in seqs])
    C = np.array([recorded[s] for s in seqs])
    D = np.abs(R - C)
    D[~np.isfinite(D)] = np.inf            # a NaN reply deviates (np.argmax would skip it)
    out = []
    for j in range(n):
        k = int(np.argmax(D[:, j]))
        over = np.flatnonzero(D[:, j] > tolerance)
        a = {"axis": names[j], "max_abs_dev": float(D[k, j]),
             "seq": int(seqs[k]) if D[k, j] > 0 else None,
             "recorded": float(C[k, j]), "replayed": float(R[k, j]),
             "over": int(len(over)), "first_over": int(seqs[over[0]]) if len(over) else None}
        if where is not None and a["seq"] is not None and a["seq"] in where:
            a["step"], a["t_s"] = where[a["seq"]]
        out.append(a)
    return out


def _seq_ranges(seqs: list[int], limit: int = 6) -> str:
    """'5, 9-12, 40' (at most ``limit`` ranges, then '...')."""
    runs: list[list[int]] = []
    for s in seqs:
        if runs and s == runs[-1][1] + 1:
            runs[-1][1] = s
        else:
            runs.append([s, s])
    txt = [f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:limit]]
    return ", ".join(txt) + (", ..." if len(runs) > limit else "")


def _run_end(mcap_path: str) -> dict:
    """The recording's ``ambhil.run_end`` metadata ({} if absent or unreadable)."""
    from mcap.reader import make_reader
    try:
        with open(mcap_path, "rb") as f:
            for m in make_reader(f).iter_metadata():
                if m.name == "ambhil.run_end":
                    return dict(m.metadata)
    except Exception:
        pass
    return {}


def not_compared(sent_seqs, recorded: dict, run_end: dict, mode: str | None) -> dict | None:
    """The samples sent whose reply could not be compared because the recording has no current
    for their seq: how many, which, and why (from the recording's run_end and mode)."""
    missing = [int(s) for s in sent_seqs if int(s) not in recorded]
    if not missing:
        return None
    last = max(recorded) if recorded else -1
    tail = all(s > last for s in missing)
    # (a run that `ambhil run` failed after its recorder saw it end keeps that in recorder_status)
    if tail and run_end.get("status") == "failed" and run_end.get("recorder_status") in (None, "", "failed"):
        why = (f"the recorded run failed before their replies were recorded"
               + (f" ({run_end['fault']})" if run_end.get("fault") else ""))
    elif tail:
        why = ("the recording ends before their replies"
               + (" (a real-time run ends without waiting for its last replies)" if mode == "realtime" else ""))
    else:
        why = ("the recorded run has no current for them"
               + (" (real-time: replies that did not reach the plant)" if mode == "realtime" else ""))
    return {"count": len(missing), "seqs": missing[:1000], "seq_text": _seq_ranges(missing), "why": why}


def causes(res: dict) -> list[str]:
    """Why a conformance result fails, one phrase per cause (empty: it passes): the replay's
    fault (controller timeout, lost, transport), the controller's exit, deviations over the
    tolerance (per axis: how many samples, the largest, its seq, step and time), nothing
    compared."""
    out = []
    if res.get("fault"):
        out.append(str(res["fault"]))
    tol = res.get("tolerance", 0.0)
    bad = [a for a in res.get("axes", ()) if a.get("over")]
    if bad:
        top = max(bad, key=lambda a: a["max_abs_dev"])
        where = f"seq {top['seq']}"
        if top.get("step") is not None:
            where += f", step {top['step']}, t = {top['t_s']:.6g} s"
        n_ax = len(res.get("axes", ()))
        which = (f"all {n_ax} axes" if len(bad) == n_ax > 1 else
                 ("axis " if len(bad) == 1 else "axes ") + ", ".join(a["axis"] for a in bad))
        out.append(f"currents deviate by more than {tol:g} A on {which} in "
                   f"{max(a['over'] for a in bad)} of {res.get('compared', 0)} compared samples "
                   f"(first at seq {min(a['first_over'] for a in bad)}); largest "
                   f"{top['max_abs_dev']:.3g} A on axis {top['axis']} at {where}: recorded "
                   f"{top['recorded']:+.12g} A, replayed {top['replayed']:+.12g} A")
    if not res.get("compared") and not res.get("fault"):
        out.append("no sample could be compared"
                   + (": the recording has no current for any sample sent" if res.get("not_compared") else ""))
    return out


def conform(mcap_path: str, run_id: str, *, listen: str, argv: list[str] | None = None,
            tolerance: float = 0.0, start_timeout: float = 30.0,
            reply_timeout: float = WAIT_CAP_S, secret: bytes | None = None,
            insecure: bool = False) -> dict:
    """Replay ``mcap_path`` to a controller (``argv``: launched here, else one started by hand
    connecting to ``listen``) on run ``run_id`` and compare.  ``passed``: every recorded sample
    answered, each axis's largest deviation <= ``tolerance`` (0 = bit for bit) and, for a launched
    controller, it exited 0 after the replay's RUN_END.  ``secret`` / ``insecure``: the run's key
    (the replay pairs with the controller under it, :func:`to_controller`)."""
    run = load_run(mcap_path)      # a bad file fails before anything starts (RecordingError)
    S, C = run["sensors"], run["currents"]
    if not len(S["seq"]):
        raise ValueError(f"{mcap_path}: no sensor samples recorded")
    n = S["v"].shape[1]
    names = axis_names(run["meta"], n)
    recorded = {int(s): C["v"][i] for i, s in enumerate(C["seq"])}
    session = tr.open_session(listen)
    # the replies to_controller took: sealed by the controller it paired with, one per seq
    replies: dict[int, np.ndarray] = {}
    proc = _Process(argv, run_id, listen) if argv else None
    exit_info = None
    try:
        try:
            _wait_ready(session, run_id, proc, start_timeout)
            res = to_controller(mcap_path, run_id, session=session, tolerance=tolerance,
                                reply_timeout=reply_timeout, start_timeout=start_timeout,
                                secret=secret, insecure=insecure, replies=replies)
        finally:
            if proc is not None:
                exit_info = proc.finish(EXIT_GRACE_S)
    finally:
        tr.close_quietly(session)
    where = {int(q): (int(st), float(t) / 1e9) for q, st, t in zip(S["seq"], S["step"], S["t_ns"])}
    axes = per_axis(replies, recorded, names, tolerance=tolerance, where=where)
    res.update({"axes": axes, "axis_names": names, "tolerance": tolerance,
                "controller": shlex.join(argv) if argv else "started by hand",
                "recorded_run": run["run_id"],
                "not_compared": not_compared(S["seq"][:res["sent"]], recorded, _run_end(mcap_path),
                                             run["meta"].get("mode"))})
    if exit_info is not None:
        res["controller_exit"] = exit_info
        if exit_info["killed"] or exit_info["exit_code"] != 0:
            why = (f"did not exit within {EXIT_GRACE_S:g} s of RUN_END" if exit_info["killed"]
                   else f"exited with code {exit_info['exit_code']}")
            tail = exit_info["output_tail"]
            res["fault"] = "; ".join(x for x in (res.get("fault"), f"the controller {why}"
                                                 + (f": {tail}" if tail else "")) if x)
    res["causes"] = causes(res)
    res["passed"] = not res["causes"]
    return res


def table(res: dict) -> list[str]:
    """Human lines: the verdict with its causes (a FAIL always names why), the samples not
    compared and why, then one row per axis."""
    tol = res["tolerance"]
    why = res.get("causes")
    if why is None:                       # a result of to_controller alone
        why = [] if res["passed"] else causes(res)
    top = max(res["axes"], key=lambda a: a["max_abs_dev"] or 0.0)
    dev = top["max_abs_dev"] or 0.0
    head = (f"{res.get('compared', 0)} of {res.get('sent', 0)} samples compared, largest deviation "
            f"{dev:.3g} A" + (f" on axis {top['axis']} at seq {top['seq']}" if dev > 0 else "")
            + f", tolerance {tol:g} A" + (" (bit for bit)" if tol == 0 else ""))
    if res["passed"]:
        lines = [f"conformance PASS: {head}"]
    else:
        lines = [f"conformance FAIL: {'; '.join(why) or 'unknown cause'}", f"  {head}"]
    nc = res.get("not_compared")
    if nc:
        lines.append(f"  not compared: {nc['count']} sample{'s' if nc['count'] != 1 else ''} "
                     f"(seq {nc['seq_text']}): {nc['why']}")
    for k in ("rejected", "foreign"):
        if res.get(k):
            lines.append(f"  ignored {res[k]} {'malformed' if k == 'rejected' else 'foreign'} "
                         f"repl{'ies' if res[k] != 1 else 'y'}")
    w = max([len("axis")] + [len(a["axis"]) for a in res["axes"]])
    lines.append(f"  {'axis':<{w}}  largest |deviation| (A)  at seq  t (s)       recorded (A)       "
                 f"replayed (A)       samples over tolerance")
    for a in res["axes"]:
        d = a["max_abs_dev"]
        if d is None:
            lines.append(f"  {a['axis']:<{w}}  {'-':>23}")
            continue
        t = f"{a['t_s']:<10.6g}" if a.get("t_s") is not None else f"{'-':<10}"
        at = (f"{a['seq']:>6}  {t}  {a['recorded']:<+18.12g} {a['replayed']:<+18.12g} {a.get('over', 0)}"
              if a["seq"] is not None else f"{'-':>6}")
        lines.append(f"  {a['axis']:<{w}}  {d:>23.3g}  {at}".rstrip())
    return lines
