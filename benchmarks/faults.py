"""How fast faults are caught and how little a crash loses (the timing claims the tests no
longer make, since they must hold on a loaded machine).

    .venv/bin/python -m benchmarks.faults [--repeat 5] [--only kill|sigkill]

- ``kill``: a controller killed with SIGKILL mid-run; time from the kill to the plant's fault
  (liveliness DELETE), in real time (1 kHz) and lockstep.  The reply timeout is set to 600 s,
  so only liveliness can end the run.  Claim in docs/hil.md: < 10 periods (10 ms at 1 kHz).
- ``sigkill``: a recorder recording 20k msg/s killed with SIGKILL; how long before the kill the
  last recovered message was logged (the flush interval is 20 ms).  Claim: < 50 ms.

Uses the stand-in processes of tests/test_nodes.py and tests/test_recorder.py.  Prints each run
and the medians.
"""
from __future__ import annotations

import os
import signal
import tempfile
import time

from benchmarks import common


def _stand_ins():
    """tests/test_recorder.py and the tests/test_nodes.py it imports (as ``test_nodes``; the
    test modules put their own folder on the path, as under pytest)."""
    from tests import test_recorder as trc
    return trc.tn, trc


def kill_detect(mode: str) -> float:
    tn, _ = _stand_ins()
    ep, run = tn.endpoint(), f"bench-kill-{mode}"
    c = tn.py(f"t._controller_proc({ep!r}, {run!r})")
    p = tn.py(f"t._plant_proc({ep!r}, {run!r}, 10**6, mode={mode!r}, reply_timeout=600.0)")
    tn.wait_samples(ep, run, 500, p)
    t_kill = time.time_ns()
    c.kill()
    sp = tn.last_json(p, timeout=120)
    c.communicate()
    assert sp["fault"] and "controller lost" in sp["fault"], sp
    return (sp["fault_wall_ns"] - t_kill) / 1e6


def sigkill_loss() -> float:
    tn, trc = _stand_ins()
    from ambhil.bridge.recording.recover import recover
    with tempfile.TemporaryDirectory() as d:
        ep, run = tn.endpoint(), "bench-kill9"
        out, fixed = os.path.join(d, "k.mcap"), os.path.join(d, "fixed.mcap")
        fl = tn.py(f"import test_recorder as tr_; tr_._flood_proc({ep!r}, {run!r}, 10000, 300.0)")
        r = tn.py(f"import test_recorder as tr_; tr_._recorder_proc({ep!r}, {run!r}, {out!r}, source='wire')")
        while not (os.path.exists(out) and os.path.getsize(out) > 200_000):
            time.sleep(0.01)
        time.sleep(1.0)                           # steady state
        t_kill = time.time_ns()
        os.kill(r.pid, signal.SIGKILL)
        r.communicate()
        tn.last_json(fl)
        recover(out, fixed)
        _, msgs, _ = trc.read_all(fixed)
        # publish_time is the wall time of arrival (log_time is simulation time in the recorded layout)
        return (t_kill - max(m.publish_time for _, _, m in msgs)) / 1e6


def main(argv=None):
    ap = common.parser(__doc__, repeat=5)
    ap.add_argument("--only", choices=("kill", "sigkill"))
    a = ap.parse_args(argv)
    common.header("faults", "how fast faults are caught, how little a crash loses")
    cases = []
    if a.only in (None, "kill"):
        cases += [("controller kill -> plant fault, real time 1 kHz (ms)", lambda: kill_detect("realtime")),
                  ("controller kill -> plant fault, lockstep (ms)", lambda: kill_detect("lockstep"))]
    if a.only in (None, "sigkill"):
        cases += [("recorder SIGKILL: last recovered message before the kill (ms)", sigkill_loss)]
    for name, fn in cases:
        vals = []
        for i in range(a.repeat):
            vals.append(fn())
            print(f"{name}: run {i + 1}: {vals[-1]:.2f}", flush=True)
        common.report(name, vals)


if __name__ == "__main__":
    main()
