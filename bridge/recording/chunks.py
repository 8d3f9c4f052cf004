"""Reading a complete recording chunk by chunk, without a Python object per message: the
fast path of :func:`ambhil.bridge.recording.load.load_run` and
:func:`ambhil.bridge.recording.replay.to_rerun` (a run of any length in flat time and memory).
Only the MCAP records are parsed here; what a message means is :mod:`ambhil.bridge.recording.layout`'s."""
from __future__ import annotations

import struct

import numpy as np

_REC = struct.Struct("<BQ")
_MSG_HEAD = struct.Struct("<HIQQ")        # channel id, sequence, log_time, publish_time


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "zstd":
        import zstandard
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame
        return lz4.frame.decompress(data)
    return bytes(data)


def iter_chunks(f, summary, progress=None):
    """The messages of a complete MCAP file, chunk by chunk in file order, without a Python object
    per message: yields ``(buf, {channel id: (starts, ends, log_times)})`` where ``buf`` is the
    chunk's decompressed records and ``buf[starts[i]:ends[i]]`` a message's data.  ``progress(done,
    total)`` in compressed bytes after each chunk."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk
    idx = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    total = sum(c.chunk_length for c in idx) or 1
    done = 0
    unpack_rec, unpack_msg = _REC.unpack_from, _MSG_HEAD.unpack_from
    for ci in idx:
        f.seek(ci.chunk_start_offset + 1 + 8)
        ch = Chunk.read(ReadDataStream(f))
        buf = _decompress(ch.compression, ch.data, ch.uncompressed_size)
        out: dict[int, tuple[list, list, list]] = {}
        p, n = 0, len(buf)
        while p < n:
            op, ln = unpack_rec(buf, p)
            if op == 0x05:
                cid, _, lt, _ = unpack_msg(buf, p + 9)
                o = out.get(cid)
                if o is None:
                    o = out[cid] = ([], [], [])
                o[0].append(p + 31)
                o[1].append(p + 9 + ln)
                o[2].append(lt)
            p += 9 + ln
        done += ci.chunk_length
        yield buf, out
        if progress is not None:
            progress(done, total)


def gather(buf: bytes, starts, size: int, dtype) -> np.ndarray:
    """Fixed-size messages at ``starts`` of ``buf`` as one structured array (one copy)."""
    s = np.asarray(starts, np.int64)
    b = np.frombuffer(buf, np.uint8)
    return b[s[:, None] + np.arange(size)].reshape(-1).view(dtype)
