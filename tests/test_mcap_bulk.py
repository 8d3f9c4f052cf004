"""bridge/recording/mcap_bulk.py: many messages at once must write the very bytes of one
``mcap.writer.Writer.add_message`` per message (the library's own path is the reference), and
the recorder's batch path (record_batch.runs + Writer.put_block) the same file as the
per-payload path it replaced."""
from __future__ import annotations

import io

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from ambhil.bridge.recording import mcap_bulk
from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol import record_batch
from ambhil.bridge.recording import layout as rc
from ambhil.bridge.recording.writer import Writer as RecordedWriter


def _file(bulk: bool, chunk_size: int, seed: int, compression=CompressionType.ZSTD) -> bytes:
    """Two channels of different payload sizes, bulk runs of 0-120 messages (some crossing the
    chunk size), single add_message calls in between (before and after bulk entries of the same
    chunk) and explicit flushes (chunk boundaries of their own)."""
    rng = np.random.default_rng(seed)
    f = io.BytesIO()
    w = Writer(f, compression=compression, chunk_size=chunk_size)
    w.start(profile="ambhil-test", library="test")
    sid = w.register_schema("t/msg/T", "ros2msg", b"uint8[] d")
    chans = [w.register_channel("/a", "cdr", sid), w.register_channel("/b", "cdr", sid)]
    for k in range(60):
        ch = chans[k % 2]
        size = 48 if k % 2 == 0 else 77
        n = int(rng.integers(0, 120))
        data = rng.integers(0, 256, (n, size), dtype=np.uint8)
        log = rng.integers(0, 10**15, n)
        pub = rng.integers(0, 10**15, n)
        seq = rng.integers(0, 2**32, n)
        mcap_bulk.add_messages(w, ch, log, data, pub, seq, bulk=bulk)
        if k % 5 == 2:
            w.add_message(chans[0], int(rng.integers(0, 10**15)), b"single", 7, 3)
        if k % 13 == 6:
            w.flush()
    w.finish()
    return f.getvalue()


@pytest.mark.parametrize("chunk_size", [700, 5000, 1 << 20])
@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.NONE])
def test_bulk_writes_the_bytes_of_add_message_per_message(chunk_size, compression):
    w = Writer(io.BytesIO())
    assert mcap_bulk.supported(w)                  # else this compares the fallback with itself
    a = _file(True, chunk_size, seed=chunk_size, compression=compression)
    b = _file(False, chunk_size, seed=chunk_size, compression=compression)
    assert a == b
    # and an independent reader sees every message, in order, with its fields
    msgs = [(c.topic, m.log_time, m.publish_time, m.sequence, len(m.data))
            for _, c, m in make_reader(io.BytesIO(a)).iter_messages(log_time_order=False)]
    assert len(msgs) > 3000
    assert {t for t, *_ in msgs} == {"/a", "/b"}


def test_fallback_where_the_writer_is_not_chunked():
    f1, f2 = io.BytesIO(), io.BytesIO()
    for f, bulk in ((f1, True), (f2, False)):
        w = Writer(f, use_chunking=False)
        w.start()
        sid = w.register_schema("s", "ros2msg", b"")
        ch = w.register_channel("/c", "cdr", sid)
        mcap_bulk.add_messages(w, ch, [3, 1, 2], np.arange(12, dtype=np.uint8).reshape(3, 4),
                               [5, 6, 7], [0, 1, 2], bulk=bulk)
        w.finish()
    assert not mcap_bulk.supported(Writer(io.BytesIO(), use_chunking=False))
    assert f1.getvalue() == f2.getvalue()
    got = [(m.log_time, m.data) for _, _, m in make_reader(io.BytesIO(f1.getvalue())).iter_messages(
        log_time_order=False)]
    assert got == [(3, bytes([0, 1, 2, 3])), (1, bytes([4, 5, 6, 7])), (2, bytes([8, 9, 10, 11]))]


def test_negative_times_are_refused_before_anything_is_written():
    w = Writer(io.BytesIO())
    w.start()
    ch = w.register_channel("/c", "cdr", w.register_schema("s", "ros2msg", b""))
    with pytest.raises(ValueError, match="non-negative"):
        mcap_bulk.add_messages(w, ch, [1, -1], np.zeros((2, 4), np.uint8), [0, 0], [0, 0])
    with pytest.raises(ValueError, match="2\\*\\*32"):
        mcap_bulk.add_messages(w, ch, [1, 1], np.zeros((2, 4), np.uint8), [0, 0], [0, 2**32])


def _batches(seed: int):
    """RecordBatches as the plant packs them, with a short sensor payload and a current
    command holding a NaN now and then (malformed: recorded on their own channel)."""
    rng = np.random.default_rng(seed)
    sc, cc = pr.SensorCodec(6), pr.CurrentCodec(6)
    out, k = [], 0
    for b in range(120):
        per = int(rng.integers(1, 90))
        s = [sc.encode(k + j, k + j, (k + j) * 100_000, 10**18 + k + j, rng.normal(size=6)) for j in range(per)]
        c = [(10**18 + 50 + k + j, cc.encode(k + j, k + j, (k + j) * 100_000, 1, 2, rng.normal(size=6)))
             for j in range(per)]
        if b % 17 == 3:
            s[0] = s[0][:-3]
        if b % 19 == 4:
            c[-1] = (c[-1][0], c[-1][1][:60] + np.float64(np.nan).tobytes() + c[-1][1][68:])
        k += per
        b_s = record_batch.Batcher(None)
        for m in s:
            b_s.sent(m)
        for m in c:
            b_s.received(m)
        out.append(b_s._pack_py(b_s._s, b_s._c, len(s), len(c)))
    return out


def test_recorder_batch_path_writes_what_the_per_payload_path_writes():
    """record_batch.runs + Writer.put_block (the recorder, bulk) against record_batch.decode +
    Writer.put (one wire payload at a time, mcap's add_message): the same file."""
    batches = _batches(3)
    keys = {record_batch.SENSORS: "ambhil/r/plant/sensors", record_batch.CURRENTS: "ambhil/r/controller/currents"}
    files = []
    for fast in (True, False):
        f = io.BytesIO()
        w = Writer(f, chunk_size=32 * 1024)
        w.start(profile=rc.PROFILE, library=rc.LIBRARY)
        rw = RecordedWriter(w, "r")
        for i, data in enumerate(batches):
            if fast:
                _, parts = record_batch.runs(data)
                for topic, log, where, count, size in parts:
                    wt = "SensorSample" if topic == record_batch.SENSORS else "CurrentCommand"
                    if size is not None:
                        rw.put_block(keys[topic], wt, data, where, count, size, log)
                    else:
                        rw.put_many(keys[topic], wt, where, log.tolist())
            else:
                _, _, _, msgs = record_batch.decode(data)
                for topic in (record_batch.SENSORS, record_batch.CURRENTS):
                    mine = [(lg, p) for tp, lg, p in msgs if tp == topic]
                    good = [(lg, p) for lg, p in mine if _well_formed(topic, p)]
                    bad = [(lg, p) for lg, p in mine if not _well_formed(topic, p)]
                    for lg, p in good + bad:     # the recorder puts a batch's malformed ones last
                        rw.put(keys[topic], p, lg)
            if i % 29 == 7:
                w.flush()
        w.finish()
        files.append((f.getvalue(), dict(rw.per_key)))
    assert files[0][1] == files[1][1]
    assert files[0][1]["ambhil/r/malformed/plant/sensors"] > 0
    assert files[0][1]["ambhil/r/malformed/controller/currents"] > 0
    assert files[0][0] == files[1][0]


def _well_formed(topic: int, p: bytes) -> bool:
    try:
        (pr.decode_sensor if topic == record_batch.SENSORS else pr.decode_current)(p)
        return True
    except pr.ProtocolError:
        return False
