"""Many same-size messages of one channel into an MCAP file at once, the bytes exactly those
of one ``mcap.writer.Writer.add_message`` call per message.

Why: ``add_message`` is about 13 us of Python per message (a ``Message`` dataclass, seven
``struct.pack`` writes, a seek back to patch the record length, the statistics and the chunk's
message index, one by one).  The recorder writes three messages per step of the loop
(SensorSample, CurrentCommand, StepTiming), so at 6-8k steps/s it kept a third of the other CPU
busy, and that work slowed the loop on its own CPU by a few per cent (docs/performance.md,
"The recorder's own work").  Here a run of messages becomes one numpy record array (the MCAP
Message record: opcode, length, channel, sequence, log time, publish time, data) written to the
open chunk in one call, with the same chunk message index, the same statistics and the same
chunk boundaries as the per-message path: the file is byte for byte the one ``add_message``
would write (tests/test_mcap_bulk.py), so readers, the summary and ``ambhil recover`` see no
difference.

The library has no bulk call, so this uses the writer's chunk builder and statistics through
their (name-mangled) attributes.  Where they are not what this module knows (another
``mcap`` release, chunking off), :func:`add_messages` falls back to ``add_message`` per
message: slower, never different.
"""
from __future__ import annotations

import numpy as np

try:                                     # the library's own record pieces, checked below
    from mcap._chunk_builder import ChunkBuilder
    from mcap.data_stream import RecordBuilder
    from mcap.opcode import Opcode
    from mcap.records import MessageIndex
    _MESSAGE = int(Opcode.MESSAGE)
except ImportError:                      # pragma: no cover - another mcap layout
    ChunkBuilder = RecordBuilder = MessageIndex = None
    _MESSAGE = 0x05

if MessageIndex is not None:
    class _Index(MessageIndex):
        """A chunk's message index whose bulk-added entries are kept as (k, 2) arrays in
        ``blocks`` (entries ``add_message`` appends after them go to ``records`` as usual) and
        written in one call: the library writes two ``struct.pack`` per message when the chunk
        is finalised.  Same bytes."""

        def __init__(self, channel_id, records):
            super().__init__(channel_id=channel_id, records=[])
            self.blocks = [np.asarray(records, "<u8").reshape(-1, 2)] if records else []

        def add(self, block):
            if self.records:                 # add_message's entries came first: keep the order
                self.blocks.append(np.asarray(self.records, "<u8").reshape(-1, 2))
                self.records.clear()
            self.blocks.append(block)

        def write(self, stream):
            parts = self.blocks + ([np.asarray(self.records, "<u8").reshape(-1, 2)] if self.records else [])
            entries = np.concatenate(parts) if parts else np.zeros((0, 2), "<u8")
            stream.start_record(Opcode.MESSAGE_INDEX)
            stream.write2(self.channel_id)
            stream.write4(len(entries) * 16)
            stream.write(entries.tobytes())
            stream.finish_record()

_HEAD = 31                               # opcode u8, length u64, channel u16, seq u32, log u64, publish u64
_dtypes: dict[int, np.dtype] = {}


def _record_dtype(size: int) -> np.dtype:
    dt = _dtypes.get(size)
    if dt is None:
        dt = _dtypes[size] = np.dtype([("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"),
                                       ("log", "<u8"), ("pub", "<u8"), ("data", f"V{size}")])
    return dt


def _parts(writer):
    """(chunk builder, statistics, chunk size, finalize-if-full) of an mcap Writer, or None."""
    if ChunkBuilder is None:
        return None
    d = vars(writer)
    cb, st = d.get("_Writer__chunk_builder"), d.get("_Writer__statistics")
    size, fin = d.get("_Writer__chunk_size"), getattr(writer, "_Writer__maybe_finalize_chunk", None)
    if (type(cb) is not ChunkBuilder or st is None or not isinstance(size, int) or fin is None
            or type(cb.record_writer) is not RecordBuilder or not hasattr(cb.record_writer, "_buffer")
            or not hasattr(st, "channel_message_counts")):
        return None
    return cb, st, size, fin


def supported(writer) -> bool:
    """True where :func:`add_messages` takes the bulk path on ``writer``."""
    return _parts(writer) is not None


def add_messages(writer, channel_id: int, log_time, data, publish_time, sequence,
                 bulk: bool = True) -> None:
    """Add ``N`` messages of ``channel_id`` to ``writer`` (an ``mcap.writer.Writer``), in order.

    ``data``: an (N,) numpy array of fixed-size records (any dtype; its bytes are the payloads)
    or an (N, size) uint8 array; ``log_time``, ``publish_time``, ``sequence``: N non-negative
    integers each (sequence < 2**32), as ``add_message`` takes them.  ``bulk=False`` forces
    the per-message path (the reference the bulk path is tested against)."""
    data = np.ascontiguousarray(data)
    N = len(data)
    if N == 0:
        return
    size = data.itemsize * (data.size // N)
    payload = data.view(np.uint8).reshape(N, size)
    log = np.asarray(log_time, np.int64).reshape(N)
    pub = np.asarray(publish_time, np.int64).reshape(N)
    seq = np.asarray(sequence, np.int64).reshape(N)
    if (log < 0).any() or (pub < 0).any() or (seq < 0).any() or (seq > 0xFFFFFFFF).any():
        raise ValueError("MCAP message times and sequence numbers must be non-negative "
                         "(sequence < 2**32)")
    parts = _parts(writer) if bulk else None
    if parts is None:
        add = writer.add_message
        for c, lg, d, pb, sq in zip([channel_id] * N, log.tolist(), map(bytes, payload), pub.tolist(),
                                    seq.tolist()):
            add(c, lg, d, pb, sq)
        return
    cb, st, chunk_size, finalize = parts
    rec = np.empty(N, _record_dtype(size))
    rec["op"] = _MESSAGE
    rec["len"] = 22 + size
    rec["ch"] = channel_id
    rec["seq"] = seq
    rec["log"] = log
    rec["pub"] = pub
    rec["data"] = payload.view(f"V{size}").reshape(N)
    raw = rec.view(np.uint8).reshape(N, _HEAD + size)
    rsize = _HEAD + size
    # statistics as add_message keeps them, message by message (min/max over the run)
    lo, hi = int(log.min()), int(log.max())
    st.message_start_time = lo if st.message_count == 0 else min(st.message_start_time, lo)
    st.message_end_time = max(st.message_end_time, hi)
    st.channel_message_counts[channel_id] += N
    st.message_count += N
    i = 0
    while i < N:
        # add_message finalizes the chunk right after the message that takes it past chunk_size
        c0 = cb.record_writer.count
        m = min(N - i, (chunk_size - c0) // rsize + 1) if c0 <= chunk_size else 1
        part = log[i:i + m]
        plo, phi = (lo, hi) if m == N else (int(part.min()), int(part.max()))
        cb.message_start_time = plo if cb.num_messages == 0 else min(cb.message_start_time, plo)
        cb.message_end_time = max(cb.message_end_time, phi)
        idx = cb.message_indices.get(channel_id)
        if type(idx) is not _Index:      # new, or begun by add_message: same records, same place
            idx = cb.message_indices[channel_id] = _Index(channel_id, idx.records if idx else [])
        block = np.empty((m, 2), "<u8")
        block[:, 0] = log[i:i + m]
        block[:, 1] = np.arange(c0, c0 + m * rsize, rsize)
        idx.add(block)
        cb.num_messages += m
        cb.record_writer.write(memoryview(raw[i:i + m]))
        finalize()
        i += m
