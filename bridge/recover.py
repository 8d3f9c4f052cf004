"""Recover the readable prefix of a truncated MCAP file (e.g. recorder killed by SIGKILL).

Everything up to the last complete chunk survives; the partial tail is dropped.  Same
counts as the Go ``mcap recover`` on our files (tooling.md §3.5)."""
from __future__ import annotations

from mcap.reader import NonSeekingReader
from mcap.writer import CompressionType, Writer


def recover(src: str, dst: str) -> int:
    """Copy every readable schema, channel, message and metadata record of ``src`` into a
    well-formed ``dst``.  Returns the number of messages recovered."""
    n, sm, cm = 0, {}, {}
    with open(src, "rb") as f, open(dst, "wb") as o:
        w = Writer(o, compression=CompressionType.ZSTD, chunk_size=1024 * 1024)
        w.start(profile="", library="ambhil-recover")
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
        w.add_metadata("ambhil.recovered", {"source": src, "messages": str(n)})
        w.finish()
    return n
