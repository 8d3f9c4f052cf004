"""The recorder's CPU per recorded message: the plant's RecordBatches (SensorSample and
CurrentCommand payloads of a six-axis run, 60 steps per batch as at 6k steps/s) transcoded into
the recorded MCAP layout, three ways on the same batches, in one run:

- ``per message``: each payload through ``Writer.put`` (one ``mcap`` ``add_message`` each);
- ``put_many``: the numpy transcoding of a batch, then one ``add_message`` per message;
- ``bulk``: ``record_batch.runs`` + ``Writer.put_block`` (payloads read in place, one numpy
  write into the chunk, ``bridge/recording/mcap_bulk.py``): the recorder now.

All three files are compared byte for byte (they must be equal).  Prints the median over
``--repeat`` passes of us per message and the ratios.

    .venv/bin/python -m benchmarks.record_batch [--steps 12000] [--per-batch 60] [--repeat 7]
"""
from __future__ import annotations

import io
import statistics
import sys
import time

import numpy as np

from mcap.writer import CompressionType, Writer

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import record_batch
from ambhil.bridge.recording import layout as rc, writer as rcw
from benchmarks import common

KEYS = {record_batch.SENSORS: "ambhil/b/plant/sensors", record_batch.CURRENTS: "ambhil/b/controller/currents"}
WTYPE = {record_batch.SENSORS: "SensorSample", record_batch.CURRENTS: "CurrentCommand"}


def batches(steps: int, per: int, n: int = 6) -> list[bytes]:
    rng = np.random.default_rng(0)
    sc, cc = pr.SensorCodec(n), pr.CurrentCodec(n)
    out = []
    for b0 in range(0, steps, per):
        bt = record_batch.Batcher(None)
        for k in range(b0, min(b0 + per, steps)):
            wall = 1_700_000_000_000_000_000 + k * 150_000
            bt.sent(sc.encode(k, k, k * 100_000, wall, rng.normal(size=n)))
            bt.received((wall + 120_000, cc.encode(k, k, k * 100_000, wall + 60_000, wall + 90_000,
                                                   rng.normal(size=n))))
        out.append(bt._pack_py(bt._s, bt._c, len(bt._s), len(bt._c)))
    return out


def record(data: list[bytes], how: str) -> bytes:
    f = io.BytesIO()
    w = Writer(f, compression=CompressionType.ZSTD, chunk_size=64 * 1024)
    w.start(profile=rc.PROFILE, library=rc.LIBRARY)
    rw = rcw.Writer(w, "b")
    for i, d in enumerate(data):
        if how == "bulk":
            for topic, log, where, count, size in record_batch.runs(d)[1]:
                if size is not None:
                    rw.put_block(KEYS[topic], WTYPE[topic], d, where, count, size, log)
                else:
                    rw.put_many(KEYS[topic], WTYPE[topic], where, log.tolist())
        else:
            msgs = record_batch.decode(d)[3]
            for topic in (record_batch.SENSORS, record_batch.CURRENTS):
                sel = [(lg, p) for tp, lg, p in msgs if tp == topic]
                if how == "put_many":
                    from ambhil.bridge.recording import mcap_bulk
                    _put_many_per_message(rw, mcap_bulk, topic, sel)
                else:
                    for lg, p in sel:
                        rw.put(KEYS[topic], p, lg, WTYPE[topic])
        if i % 2 == 1:                       # the recorder flushes every 20 ms: every 2nd batch
            w.flush()
    w.finish()
    return f.getvalue()


def _put_many_per_message(rw, mcap_bulk, topic, sel):
    """put_many with the bulk write switched off: numpy transcoding, add_message per message."""
    real = mcap_bulk.add_messages
    rcw.add_messages = lambda *a, **k: real(*a, **k, bulk=False)
    try:
        rw.put_many(KEYS[topic], WTYPE[topic], [p for _, p in sel], [lg for lg, _ in sel])
    finally:
        rcw.add_messages = real


def main(argv=None):
    ap = common.parser(__doc__, repeat=7)
    ap.add_argument("--steps", type=int, default=12000)
    ap.add_argument("--per-batch", type=int, default=60)
    a = ap.parse_args(argv)
    common.header("record_batch", "the recorder's CPU per recorded message, three paths")
    data = batches(a.steps, a.per_batch)
    n_msgs = 2 * a.steps
    ways = ("per message", "put_many", "bulk")
    files = {w: record(data, w.split()[0]) for w in ways}       # warm-up, and the files
    same = len({files[w] for w in ways}) == 1
    t = {w: [] for w in ways}
    for _ in range(a.repeat):
        for w in ways:                       # interleaved: the same machine regime for each
            t0 = time.perf_counter()
            record(data, w.split()[0])
            t[w].append(time.perf_counter() - t0)
    med = {w: statistics.median(t[w]) / n_msgs * 1e6 for w in ways}
    print(f"{a.steps} steps, 6 axes, {a.per_batch} steps per RecordBatch, {n_msgs} messages; "
          f"median of {a.repeat} passes")
    for w in ways:
        print(f"  {w:12s} {med[w]:6.2f} us per message  ({med['per message'] / med[w]:.1f}x the per-message path)")
    print(f"  files byte-identical: {same}")
    if not same:
        sys.exit("the three paths wrote different files")


if __name__ == "__main__":
    main()
