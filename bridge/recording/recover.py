"""MCAP file health: tell a complete recording from a truncated one or a file that is not MCAP
(:func:`check`), and recover the readable prefix of a truncated one (e.g. recorder killed by
SIGKILL) into a new file (:func:`recover`).

Everything up to the last complete chunk survives; the partial tail is dropped.  Same counts as
the Go ``mcap recover`` on our files (tooling.md §3.5).  Nothing is ever written over the
source: the copy goes to a temporary file beside the destination, renamed into place at the end."""
from __future__ import annotations

import os
from pathlib import Path

from mcap.reader import NonSeekingReader
from mcap.records import Header
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

MAGIC = b"\x89MCAP0\r\n"
_FOOTER_LEN = 1 + 8 + 8 + 8 + 4            # opcode, record length, summary start, offset start, crc


class RecordingError(ValueError):
    """A recording that cannot be read as asked: the message is one line, fit for the user."""


def check(path: str) -> str:
    """``"complete"`` or ``"truncated"``; raise RecordingError if ``path`` is missing, empty,
    a folder or not an MCAP file."""
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{path}: no such recording")
    if p.is_dir():
        raise RecordingError(f"{path}: is a folder, not an MCAP file")
    size = p.stat().st_size
    with open(p, "rb") as f:
        head = f.read(len(MAGIC))
        if head != MAGIC:
            what = "empty file" if size == 0 else "does not start with the MCAP magic"
            raise RecordingError(f"{path}: not an MCAP file ({what})")
        if size < 2 * len(MAGIC) + _FOOTER_LEN:
            return "truncated"
        f.seek(size - len(MAGIC) - _FOOTER_LEN)
        tail = f.read()
    return "complete" if tail[0] == 0x02 and tail.endswith(MAGIC) else "truncated"


def truncated_message(path: str) -> str:
    return (f"{path}: truncated MCAP (its recorder was killed or the disk filled?); "
            f"restore the readable part with `ambhil recover {path}`")


def same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).resolve() == Path(b).resolve()


def recover(src: str, dst: str, *, keep_empty: bool = True) -> int:
    """Copy every readable schema, channel, message and metadata record of ``src`` into a
    well-formed ``dst``.  Returns the number of messages recovered.  Refuses ``dst`` = ``src``
    (RecordingError); writes a temporary file renamed to ``dst`` when done, so an existing
    ``dst`` is replaced only by a finished file, and (``keep_empty=False``) not at all when no
    message was recovered."""
    if same_file(src, dst):
        raise RecordingError(f"{dst}: is the source recording; recover writes a new file (give another destination)")
    tmp = Path(dst).with_name(f".{Path(dst).name}.{os.getpid()}.part")
    n, sm, cm = 0, {}, {}
    try:
        with open(src, "rb") as f, open(tmp, "wb") as o:
            w = Writer(o, compression=CompressionType.ZSTD, chunk_size=1024 * 1024)
            profile = ""
            try:                # the source's profile (ros2 for the recorded layout, docs/hil.md)
                rec = next(StreamReader(f).records)
                profile = rec.profile if isinstance(rec, Header) else ""
            except Exception:
                pass
            f.seek(0)
            w.start(profile=profile, library="ambhil-recover")
            reader = NonSeekingReader(f)
            try:
                for sch, ch, m in reader.iter_messages(log_time_order=False):
                    if sch is not None and sch.id not in sm:
                        sm[sch.id] = w.register_schema(sch.name, sch.encoding, sch.data)
                    if ch.id not in cm:
                        cm[ch.id] = w.register_channel(ch.topic, ch.message_encoding,
                                                       sm.get(ch.schema_id, 0), ch.metadata)
                    w.add_message(cm[ch.id], m.log_time, m.data, m.publish_time, m.sequence)
                    n += 1
            except Exception:
                pass            # truncated tail
            try:
                f.seek(0)
                for md in NonSeekingReader(f).iter_metadata():
                    w.add_metadata(md.name, dict(md.metadata))
            except Exception:
                pass
            w.add_metadata("ambhil.recovered", {"source": str(src), "messages": str(n)})
            w.finish()
        if n or keep_empty:
            os.replace(tmp, dst)
    finally:
        tmp.unlink(missing_ok=True)
    return n



RUN_END = "ambhil.run_end"
RECORDER_END = "ambhil.rec_end"     # the recorder's ambhil.run_end once superseded (same length)


def set_run_end(path: str, **fields) -> dict | None:
    """Give a complete recording's ``ambhil.run_end`` metadata the run's verdict, in place (e.g.
    ``status="failed", fault="..."`` when ``ambhil run`` fails a run that its recorder saw end
    normally: too many overruns, a loop that grows, ``--strict``).  The recorder's record stays
    where it is, renamed ``ambhil.rec_end`` (a name of the same length: no byte moves); a new
    ``ambhil.run_end``, the recorder's fields updated by ``fields``, is appended to the data
    section, and the summary section is written again (indexes, statistics, CRCs).  Only the
    file's tail is rewritten (and the data section read once for its CRC).  Returns the new
    record, or None when the file is not complete or has no run_end (nothing changed)."""
    import io
    import struct
    import zlib
    from mcap.data_stream import ReadDataStream, RecordBuilder
    from mcap.opcode import Opcode
    from mcap.reader import make_reader
    from mcap.records import DataEnd, Footer, Metadata, MetadataIndex, Statistics, SummaryOffset
    if check(path) != "complete":
        return None
    with open(path, "r+b") as f:
        summary = make_reader(f).get_summary()
        f.seek(-(len(MAGIC) + _FOOTER_LEN), os.SEEK_END)
        summary_start = struct.unpack_from("<Q", f.read(_FOOTER_LEN), 9)[0]
        idx = [m for m in summary.metadata_indexes if m.name == RUN_END] if summary else []
        if not summary_start or not idx:
            return None
        old = idx[-1]
        f.seek(old.offset)
        rec = f.read(old.length)
        md = Metadata.read(ReadDataStream(io.BytesIO(rec[9:])))
        info = {**md.metadata, **{k: "" if v is None else str(v) for k, v in fields.items()}}
        name_at = old.offset + 9 + 4          # opcode, record length, the name's length
        assert rec[13:13 + len(RUN_END)] == RUN_END.encode() and len(RECORDER_END) == len(RUN_END)
        f.seek(name_at)
        f.write(RECORDER_END.encode())
        data_end = summary_start - (1 + 8 + 4)          # where the DataEnd record starts
        b = RecordBuilder()
        Metadata(name=RUN_END, metadata=info).write(b)
        new = b.end()
        f.seek(data_end)
        f.write(new)
        end = f.tell()
        f.seek(0)                     # the data section's CRC: magic and every record before DataEnd
        crc, left = 0, end
        while left:
            chunk = f.read(min(left, 1 << 22))
            crc, left = zlib.crc32(chunk, crc), left - len(chunk)
        f.seek(end)
        DataEnd(crc).write(b)
        f.write(b.end())
        s_start = f.tell()
        metas = [MetadataIndex(offset=m.offset, length=m.length,
                               name=RECORDER_END if m is old else m.name) for m in summary.metadata_indexes]
        metas.append(MetadataIndex(offset=data_end, length=len(new), name=RUN_END))
        sb, groups = RecordBuilder(), []

        def group(op, records):
            g0 = sb.count
            for r in records:
                r.write(sb)
            if records:
                groups.append(SummaryOffset(group_opcode=op, group_start=s_start + g0, group_length=sb.count - g0))
        st = summary.statistics
        group(Opcode.SCHEMA, list(summary.schemas.values()))
        group(Opcode.CHANNEL, list(summary.channels.values()))
        if st is not None:
            group(Opcode.STATISTICS, [Statistics(
                message_count=st.message_count, schema_count=st.schema_count,
                channel_count=st.channel_count, attachment_count=st.attachment_count,
                metadata_count=st.metadata_count + 1, chunk_count=st.chunk_count,
                message_start_time=st.message_start_time, message_end_time=st.message_end_time,
                channel_message_counts=st.channel_message_counts)])
        group(Opcode.CHUNK_INDEX, list(summary.chunk_indexes))
        group(Opcode.ATTACHMENT_INDEX, list(summary.attachment_indexes))
        group(Opcode.METADATA_INDEX, metas)
        off_start = s_start + sb.count
        for g in groups:
            g.write(sb)
        sdata = sb.end()
        scrc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, s_start, off_start), zlib.crc32(sdata))
        f.write(sdata)
        Footer(summary_start=s_start, summary_offset_start=off_start, summary_crc=scrc).write(b)
        f.write(b.end())
        f.write(MAGIC)
        f.truncate()
    return info


def run_end_of(path: str) -> dict | None:
    """A recording's ``ambhil.run_end`` metadata (the last of that name), None if it has none."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        ends = [dict(m.metadata) for m in make_reader(f).iter_metadata() if m.name == RUN_END]
    return ends[-1] if ends else None


def mark_run_failed(path: str, why: str) -> dict | None:
    """``ambhil run`` failed a run for ``why`` (its FAILED line): the recording's run_end says
    ``failed`` with ``why`` as its fault (:func:`set_run_end`; ``recorder_status``: what the
    recorder had written), unless it says ``stopped`` (an interruption) or already says failed
    for that very reason.  Returns the new record or None (file unchanged)."""
    end = run_end_of(path)
    if end is None or end.get("status") == "stopped":
        return None
    fault = end.get("fault") or ""
    if end.get("status") == "failed" and why in (fault, f"plant: {fault}", f"controller: {fault}"):
        return None
    return set_run_end(path, status="failed", fault=why, recorder_status=end.get("status", ""))
