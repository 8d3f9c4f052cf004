"""The ``ambhil.run_end`` metadata record: how a run ended and how much of it its recording holds,
so that a failed or truncated recording is recognisable from the file alone.

The recorder writes it last (:func:`run_end_status`: ``status`` completed / truncated / failed /
stopped, ``fault``, ``end_reason``, ``steps_planned``, ``steps_run``, ``steps_recorded``,
``currents_recorded``, ``rejected``: every message the run's processes rejected, as JSON
``{reason: n}`` (``auth``: no valid MAC, ``peer``: another sender's id, ``sequence``: a replay,
...; ``{}``: none): the plant's (from its RUN_END), the controller's (from its last event) and
the traffic of the run's keys the recorder did not take; ``rejected_by``: the same per process,
``auth``: how the run authenticated, RunMeta ``auth.mode``: ``key`` / ``none`` / ``insecure``,
``unknown`` for a run of an older protocol or without a RunMeta), and for a plant with auxiliary
bearings ``contact``: its contact summary per bearing as JSON (the plant's ``contact_summary``
event, bridge/process/plant_contact.py: events, peak force, penetration, energies, race speed);
``ambhil run`` may give it the run's own verdict afterwards, in place
(:func:`mark_run_failed`, :func:`set_run_end`); :func:`run_end_of` reads it."""
from __future__ import annotations

import io
import json
import os
import struct
import zlib

from ambhil.bridge import protocol as pr
from ambhil.bridge.recording.recover import FOOTER_LEN, MAGIC, check

RUN_END = "ambhil.run_end"
RECORDER_END = "ambhil.rec_end"     # the recorder's ambhil.run_end once superseded (same length)
_DATA_END_LEN = 1 + 8 + 4           # the DataEnd record: opcode, record length, data section CRC


def run_end_status(run: dict, end_reason: str, sensors: int, currents: int,
                   rejected: dict | None = None, auth: str | None = None) -> dict:
    """The ``ambhil.run_end`` record: how the run ended and how much of it the file holds;
    ``rejected`` ({reason: n}) and ``auth`` (the mode) as the module docstring says.  ``status``
    is the recorder's own verdict: rejected traffic does not change it (it is not the run's)."""
    pe = run.get("plant_end")
    steps_run = pe.get("steps") if pe else None
    fault = (pe.get("fault") if pe else None) or run.get("fault")
    recorded = min(sensors, currents)
    if pe is not None:
        reason = pe.get("reason")
        if reason == "completed":
            status = "completed" if isinstance(steps_run, int) and recorded >= steps_run else "truncated"
        elif reason in ("stopped", "interrupted"):
            status = "stopped"
        else:
            status = "failed"
    elif end_reason.startswith(("signal", "stop", "max duration", "ambhil run")):
        status = "stopped"          # the recording stopped before the run ended
    else:                           # plant lost without RUN_END, peers never came, ...
        status = "failed"
        fault = fault or (end_reason[len("error: "):] if end_reason.startswith("error: ")
                          else f"recorder: {end_reason} before the run ended")
    return {"status": status, "fault": fault, "end_reason": end_reason,
            "steps_planned": run.get("n_steps"), "steps_run": steps_run,
            "steps_recorded": sensors, "currents_recorded": currents,
            **_rejected(run, rejected),
            "auth": auth or "unknown",
            **({"contact": json.dumps(run["contact"], separators=(",", ":"))} if run.get("contact") else {})}


def _rejected(run: dict, recorder: dict | None) -> dict:
    """``rejected``: every message the run's processes rejected, by reason (the plant's from its
    RUN_END, the controller's from its last event, the recorder's own), and ``rejected_by`` the
    same per process (JSON text)."""
    def clean(d):
        return {k: int(v) for k, v in sorted((d or {}).items()) if isinstance(v, int) and v}
    by = {"plant": clean((run.get("plant_end") or {}).get("rejected")),
          "controller": clean((run.get("controller_end") or {}).get("rejected")),
          "recorder": clean(recorder)}
    total: dict = {}
    for d in by.values():
        for k, v in d.items():
            total[k] = total.get(k, 0) + v
    return {"rejected": json.dumps(dict(sorted(total.items())), separators=(",", ":")),
            "rejected_by": json.dumps({k: v for k, v in by.items() if v}, separators=(",", ":"))}


def note_event(run: dict, data: bytes) -> None:
    """What the run_end needs from an Event the recorder took: the plant's RUN_END (reason,
    steps, fault, its rejections), the controller's last event (its rejections), the plant's
    contact summary and the first FAULT text of the run, into ``run``."""
    try:
        e = pr.decode_event(data)
    except pr.ProtocolError:
        return
    if e.kind == pr.EventKind.FAULT and run["fault"] is None:
        run["fault"] = f"{e.source}: {e.text}"
    elif e.kind == pr.EventKind.INFO:
        if e.source == "controller" and e.text.startswith('{"controller_end"'):
            try:
                run["controller_end"] = json.loads(e.text)["controller_end"]
            except (ValueError, KeyError, TypeError):
                run["controller_end"] = {}
        elif e.source == "plant" and e.text.startswith('{"contact_summary"'):
            try:
                run["contact"] = json.loads(e.text)["contact_summary"]
            except (ValueError, KeyError, TypeError):
                pass
    elif e.kind == pr.EventKind.RUN_END and e.source == "plant":
        try:
            info = json.loads(e.text)
        except ValueError:
            info = {}
        run["plant_end"] = info if isinstance(info, dict) else {}


def set_run_end(path: str, **fields) -> dict | None:
    """Give a complete recording's ``ambhil.run_end`` metadata the run's verdict, in place (e.g.
    ``status="failed", fault="..."`` when ``ambhil run`` fails a run that its recorder saw end
    normally: too many overruns, a loop that grows, ``--strict``).  The recorder's record stays
    where it is, renamed ``ambhil.rec_end`` (a name of the same length: no byte moves); a new
    ``ambhil.run_end``, the recorder's fields updated by ``fields``, is appended to the data
    section, and the summary section is written again (indexes, statistics, CRCs).  Only the
    file's tail is rewritten (and the data section read once for its CRC).  Returns the new
    record, or None when the file is not complete or has no run_end (nothing changed)."""
    from mcap.reader import make_reader
    if check(path) != "complete":
        return None
    with open(path, "r+b") as f:
        summary = make_reader(f).get_summary()
        f.seek(-(len(MAGIC) + FOOTER_LEN), os.SEEK_END)
        summary_start = struct.unpack_from("<Q", f.read(FOOTER_LEN), 9)[0]
        idx = [m for m in summary.metadata_indexes if m.name == RUN_END] if summary else []
        if not summary_start or not idx:
            return None
        old = idx[-1]
        info = _supersede(f, old, fields)
        data_end = summary_start - _DATA_END_LEN          # where the DataEnd record starts
        new_len = _append_data_end(f, data_end, info)
        _write_summary(f, summary, old, data_end, new_len)
        f.truncate()
    return info


def _supersede(f, old, fields: dict) -> dict:
    """Rename the recorder's run_end record ``old`` (its metadata index entry) to RECORDER_END in
    place; returns its fields updated by ``fields`` (the new record's)."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Metadata
    f.seek(old.offset)
    rec = f.read(old.length)
    md = Metadata.read(ReadDataStream(io.BytesIO(rec[9:])))
    info = {**md.metadata, **{k: "" if v is None else str(v) for k, v in fields.items()}}
    name_at = old.offset + 9 + 4          # opcode, record length, the name's length
    assert rec[13:13 + len(RUN_END)] == RUN_END.encode() and len(RECORDER_END) == len(RUN_END)
    f.seek(name_at)
    f.write(RECORDER_END.encode())
    return info


def _append_data_end(f, data_end: int, info: dict) -> int:
    """The new run_end record written where the DataEnd record was, then a DataEnd with the CRC
    of the data section (the magic and every record before it); returns the new record's length."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import DataEnd, Metadata
    b = RecordBuilder()
    Metadata(name=RUN_END, metadata=info).write(b)
    new = b.end()
    f.seek(data_end)
    f.write(new)
    end = f.tell()
    f.seek(0)
    crc, left = 0, end
    while left:
        chunk = f.read(min(left, 1 << 22))
        crc, left = zlib.crc32(chunk, crc), left - len(chunk)
    f.seek(end)
    DataEnd(crc).write(b)
    f.write(b.end())
    return len(new)


def _write_summary(f, summary, old, data_end: int, new_len: int) -> None:
    """The summary section again, from the file position on: schemas, channels, statistics (one
    metadata record more), chunk, attachment and metadata indexes (``old`` renamed, the new
    record at ``data_end`` added), their summary offsets, the footer and its CRC, the magic."""
    from mcap.data_stream import RecordBuilder
    from mcap.opcode import Opcode
    from mcap.records import Footer, MetadataIndex, Statistics, SummaryOffset
    s_start = f.tell()
    metas = [MetadataIndex(offset=m.offset, length=m.length,
                           name=RECORDER_END if m is old else m.name) for m in summary.metadata_indexes]
    metas.append(MetadataIndex(offset=data_end, length=new_len, name=RUN_END))
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
    b = RecordBuilder()
    Footer(summary_start=s_start, summary_offset_start=off_start, summary_crc=scrc).write(b)
    f.write(b.end())
    f.write(MAGIC)


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
