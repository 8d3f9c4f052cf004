"""MCAP file health: tell a complete recording from a truncated one or a file that is not MCAP
(:func:`check`), and recover the readable prefix of a truncated one (e.g. recorder killed by
SIGKILL) into a new file (:func:`recover`).

Everything up to the last complete chunk survives; the partial tail is dropped.  Same counts as
the Go ``mcap recover`` on our files (shared/reference/tooling.md §3.5).  Nothing is ever written over the
source: the copy goes to a temporary file beside the destination, renamed into place at the end."""
from __future__ import annotations

import os
from pathlib import Path

from mcap.reader import NonSeekingReader
from mcap.records import Header
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

MAGIC = b"\x89MCAP0\r\n"
FOOTER_LEN = 1 + 8 + 8 + 8 + 4            # opcode, record length, summary start, offset start, crc


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
        if size < 2 * len(MAGIC) + FOOTER_LEN:
            return "truncated"
        f.seek(size - len(MAGIC) - FOOTER_LEN)
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
