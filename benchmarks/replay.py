"""Turning a long recording into the rerun viewer's file (issue 14: a 500k-step run, 93 MB of MCAP,
took ~6 minutes and 1.1 GB before the conversion was streamed).

    .venv/bin/python benchmarks/bench_replay.py [--mcap RUN.mcap | --steps 500000] [--repeat 3]

Without ``--mcap`` it first synthesises a recording equivalent to
``ambhil run scenes/paper_3amb.toml --rung modal --duration 50`` (10 kHz, 6 axes, 500 000 steps:
one SensorSample, one CurrentCommand and one StepTiming per step, the events of a run), written by
the recorder's own writer (bridge/recording/layout.py) with orbits of 8.5, 1.1 and 4 um.  Each conversion
(:func:`ambhil.bridge.recording.replay.to_rerun`) runs in a fresh process; printed: wall time and peak RSS of that
process (``ru_maxrss``), the median over ``--repeat`` runs.
"""
from __future__ import annotations

import json
import os
import tempfile
import time

from benchmarks import common


def synth(path: str, steps: int, n_axes: int = 6, rate: float = 10_000.0, run_id: str = "synth",
          layout: str = "ros2") -> None:
    """A recording of ``steps`` periods written like the recorder writes one (``layout="wire"``:
    like it wrote one before issue 14: wire bytes verbatim, topic = key, log time = wall time)."""
    import numpy as np
    from mcap.writer import CompressionType, Writer
    from ambhil.bridge import protocol as pr
    from ambhil.bridge.recording import layout as rc
    from ambhil.bridge.recording.writer import Writer as RecordedWriter
    K = pr.keys(run_id)
    period_ns = int(round(1e9 / rate))
    names = [f"{s}-{x}" for s in "ABC"[: n_axes // 2] for x in "xy"]
    meta = {"run_id": run_id, "n_axes": n_axes, "axis_names": names, "station_names": list("ABC")[: n_axes // 2],
            "gaps_m": [1.5e-4] * (n_axes // 2), "period_s": 1 / rate, "rate_hz": rate, "n_steps": steps,
            "mode": "lockstep"}
    rng = np.random.default_rng(1)
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD, chunk_size=64 * 1024)
        w.start(profile=rc.PROFILE if layout == "ros2" else "", library=rc.LIBRARY)
        rw = RecordedWriter(w, run_id) if layout == "ros2" else _WireWriter(w)
        wall0 = time.time_ns()
        rw.put(K.meta, pr.encode_meta(pr.RunMeta(meta, wall_ns=wall0)), wall0)
        rw.put(K.events, pr.encode_event(pr.Event(pr.EventKind.RUN_START, "{}", "plant", wall_ns=wall0)), wall0)
        amp = np.array([8.5e-6, 1.1e-6, 4e-6])[: n_axes // 2]
        w_rot = 2 * np.pi * 50
        blk = 20_000
        for k0 in range(0, steps, blk):
            k = np.arange(k0, min(k0 + blk, steps))
            t = k * period_ns
            ph = w_rot * t * 1e-9
            y = np.empty((len(k), n_axes))
            y[:, 0::2] = np.cos(ph)[:, None] * amp
            y[:, 1::2] = np.sin(ph)[:, None] * amp
            y += rng.normal(0, 2e-8, y.shape)
            i = -3e3 * y
            wall = wall0 + 14 * t          # a lockstep run: 14x slower than real time
            rw.put_vectors(K.sensors, "SensorSample", k, k, t, y, wall, pub=wall)
            rw.put_vectors(K.currents, "CurrentCommand", k, k, t, i, wall + 30_000, recv=wall + 20_000,
                           pub=wall + 27_000)
            for b0 in range(0, len(k), 200):
                n = min(200, len(k) - b0)
                rtt = rng.integers(40_000, 60_000, n)
                rtt[rng.random(n) < 0.001] = 7_000_000           # the 7 ms spikes
                tm = pr.Timing(int(k[b0]), int(t[b0]), period_ns, 0, np.zeros(n, np.int64), rtt,
                               rng.integers(6_000, 8_000, n), np.zeros(n, np.uint8))
                rw.put_timing(K.timing, tm, int(wall[b0]))
        rw.put(K.events, pr.encode_event(pr.Event(pr.EventKind.RUN_END, json.dumps({"reason": "completed"}),
                                                  "plant", steps, steps, steps * period_ns, time.time_ns())), time.time_ns())
        w.finish()


class _WireWriter:
    """The earlier layout, for the comparison with the conversion before issue 14."""

    def __init__(self, w):
        from ambhil.bridge import protocol as pr
        self.w, self.pr, self.ch = w, pr, {}
        self.sch = {t: w.register_schema(pr.schema_name(t), "ros2msg", d.encode()) for t, d in pr.MSG_DEFS.items()}

    def _cid(self, key):
        if key not in self.ch:
            t = self.pr.message_type_for_key(key)
            self.ch[key] = self.w.register_channel(key, "cdr", self.sch[t], {"type": t})
        return self.ch[key]

    def put(self, key, data, wall):
        sim = int.from_bytes(data[28:36], "little", signed=True)
        self.w.add_message(self._cid(key), wall, data, max(sim, 0), 0)

    def put_vectors(self, key, wtype, seq, step, sim, v, wall, pub=None, recv=None):
        pr, cid = self.pr, self._cid(key)
        for k in range(len(seq)):
            d = (pr.encode_sensor(int(seq[k]), int(step[k]), int(sim[k]), int(pub[k]), v[k]) if wtype == "SensorSample"
                 else pr.encode_current(int(seq[k]), int(step[k]), int(sim[k]), int(recv[k]), int(pub[k]), v[k]))
            self.w.add_message(cid, int(wall[k]), d, int(sim[k]), int(seq[k]) & 0xFFFFFFFF)

    def put_timing(self, key, tm, wall):
        self.w.add_message(self._cid(key), wall, self.pr.encode_timing(tm), tm.sim_time_ns, tm.step)


def _one(mcap: str, rrd: str) -> dict:
    """One conversion in a fresh process: its wall time and peak RSS."""
    code = ("import json, resource, sys, time; from ambhil.bridge.recording.replay import to_rerun;"
            "t = time.perf_counter(); info = to_rerun(%r, %r);"
            "print(json.dumps({'s': time.perf_counter() - t, 'rss_mb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,"
            " 'samples': info['samples']}))") % (mcap, rrd)
    p = common.run(code, timeout=600)
    if p.returncode != 0:
        raise RuntimeError(common.tail(p.stderr))
    return common.last_json(p.stdout)


def main(argv=None):
    ap = common.parser(__doc__, repeat=3)
    ap.add_argument("--mcap", help="an existing recording (default: synthesise one)")
    ap.add_argument("--steps", type=int, default=500_000)
    ap.add_argument("--layout", choices=("ros2", "wire"), default="ros2",
                    help="synthesise the recorded layout (default) or the earlier one (wire bytes verbatim)")
    a = ap.parse_args(argv)
    common.header("replay", "a long recording into the rerun viewer's file")
    with tempfile.TemporaryDirectory() as d:
        mcap = a.mcap
        if mcap is None:
            mcap = os.path.join(d, "synth.mcap")
            t = time.perf_counter()
            synth(mcap, a.steps, layout=a.layout)
            print(f"synthesised {mcap} ({a.layout} layout): {a.steps} steps, {os.path.getsize(mcap) / 1e6:.1f} MB "
                  f"in {time.perf_counter() - t:.1f} s")
        rrd = os.path.join(d, "out.rrd")
        runs = [_one(mcap, rrd) for _ in range(a.repeat)]
        for r in runs:
            print(f"  to_rerun: {r['s']:.1f} s, peak RSS {r['rss_mb']:.0f} MB ({r['samples']} samples)")
        common.report("to_rerun wall time", [r["s"] for r in runs], "s")
        common.report("to_rerun peak RSS", [r["rss_mb"] for r in runs], "MB",
                      note=f"MCAP {os.path.getsize(mcap) / 1e6:.1f} MB, rrd {os.path.getsize(rrd) / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
