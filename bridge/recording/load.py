"""Load a recorded run into numpy arrays (:func:`load_run`): what replay to a controller,
conformance, the campaign and timing reports, and the tests read.

A recording of the recorded layout (:mod:`ambhil.bridge.recording.layout`) is read chunk by chunk,
no Python object per message (:mod:`ambhil.bridge.recording.chunks`); one of the earlier layout
(wire bytes verbatim) message by message.  Either way the result is the same: the samples and
currents with their wire bytes (protocol 3, restored: exact but for the mac, which a recording
does not keep, :mod:`ambhil.bridge.recording.layout`), the per-step timing, the events, the RunMeta, and what was
rejected and why.  The pieces shared with the replay to rerun (:mod:`ambhil.bridge.recording.replay`)
are here too: the run's channels (:func:`channels`), one chunk's messages of a channel as an array
(:func:`gather_channel`), the reasons a payload the recorder could not decode is rejected
(:func:`malformed_rows`)."""
from __future__ import annotations

import struct
from collections import Counter

import numpy as np
from mcap.reader import make_reader

from ambhil.bridge import protocol as pr
from ambhil.bridge.recording import layout as rc
from ambhil.bridge.recording.chunks import gather, iter_chunks
from ambhil.bridge.recording.recover import RecordingError, check, truncated_message

INT64 = 2 ** 63
_DECODE_ERRORS = (ValueError, OverflowError, TypeError, struct.error)   # ProtocolError is a ValueError


class _Malformed(ValueError):
    pass


def _vector(msg, n_by_type: dict, t: str):
    """Reject a sample/command whose seq or step does not fit int64 or whose axis count differs
    from the first one of its type."""
    if not (0 <= msg.seq < INT64 and 0 <= msg.step < INT64):
        raise _Malformed("seq or step out of range")
    v = getattr(msg, "displacement" if t == "SensorSample" else "current")
    n = n_by_type.setdefault(t, len(v))
    if len(v) != n:
        raise _Malformed(f"axis count {len(v)} != {n}")
    return msg


def _vec(msg):
    """The vector of a decoded SensorSample / CurrentCommand."""
    return msg.displacement if isinstance(msg, pr.SensorSample) else msg.current


def _timing(tm):
    if not 0 <= tm.step < INT64 or tm.step + len(tm.rtt_ns) >= INT64:
        raise _Malformed("step out of range")
    if not (len(tm.rtt_ns) == len(tm.tet_ns) == len(tm.wake_lateness_ns) == len(tm.flags)):
        raise _Malformed("timing arrays of different lengths")
    return tm


def load_run(mcap_path: str, *, raw: bool = True) -> dict:
    """Decode an ambhil MCAP (the recorded layout of :mod:`ambhil.bridge.recording.layout`, or the earlier one
    of wire bytes verbatim) into numpy arrays.  Malformed messages (failing protocol
    validation, seq/step beyond int64, axis count differing from the run's, inconsistent timing
    arrays) are skipped and counted in ``rejected`` (by reason in ``rejected_reasons``).  Returns
    dict with keys sensors/currents (``seq``, ``step``, ``t_ns``, ``v`` (N x n_axes), ``raw``
    (the wire bytes, restored exactly but for a zero mac; empty with ``raw=False``)), ``timing`` (per-step arrays),
    ``events`` (list of Event), ``meta`` (RunMeta.info or {}), ``run_id``.
    Raises :class:`ambhil.bridge.recording.recover.RecordingError` (one line, fit for the user) for a file that
    is not MCAP, is truncated (naming ``ambhil recover``) or cannot be read."""
    if check(mcap_path) == "truncated":
        raise RecordingError(truncated_message(mcap_path))
    got = _Read()
    try:
        with open(mcap_path, "rb") as f:
            got.read(f)
    except RecordingError:
        raise
    except Exception as e:
        raise RecordingError(f"{mcap_path}: unreadable MCAP ({type(e).__name__}: {e}); "
                             f"`ambhil recover {mcap_path}` may restore the readable part") from None
    got.decode_recorded()
    cols = got.columns(raw)
    timing = got.timing()
    return {"sensors": _pack(cols["SensorSample"], raw), "currents": _pack(cols["CurrentCommand"], raw),
            "timing": timing, "events": got.events, "meta": got.meta,
            "rejected": sum(got.reasons.values()), "rejected_reasons": dict(got.reasons),
            "run_id": got.run_id}


class _Read:
    """What :func:`load_run` read from a file, before it is put in columns."""

    def __init__(self):
        self.sens, self.cur, self.tim = [], [], []     # the earlier layout: (message, wire bytes)
        self.events, self.meta, self.reasons = [], {}, Counter()
        self.recorded: dict[str, list] = {}            # recorded vector / timing payloads, by type
        self.arrays: dict[str, list] = {}              # the same, decoded chunk by chunk (fast path)
        self.malformed = []                            # (wire type, payload) the recorder kept verbatim
        self.n_by_type: dict = {}
        self.run_id = None

    def read(self, f) -> None:
        reader = make_reader(f)
        summary = reader.get_summary()
        chans = channels(summary) if summary is not None else None
        fast = bool(chans) and not any(v[0].startswith("wire:") for v in chans.values())
        if fast:                # chunk by chunk, no Python object per message
            self.run_id = next(iter(chans.values()))[2].split("/")[1]
            self._read_chunks(f, summary, chans)
        f.seek(0)
        if not fast:
            self._read_messages(f)

    def _read_chunks(self, f, summary, chans) -> None:
        for buf, out in iter_chunks(f, summary):
            for cid, (starts, ends, _) in out.items():
                lay, t, _ = chans.get(cid, (None, None, None))
                if lay in (rc.SENSORS, rc.CURRENTS, rc.TIMING):
                    self.arrays.setdefault(lay, []).append(gather_channel(buf, lay, starts, ends, cid))
                elif lay in (rc.EVENT, rc.META, rc.MALFORMED):
                    for a, b in zip(starts, ends):
                        try:
                            self._fixed(lay, t, buf[a:b])
                        except _DECODE_ERRORS as e:
                            self.reasons[f"{t}: {type(e).__name__}"] += 1

    def _fixed(self, lay: str, t: str, data) -> None:
        """One recorded Event, RunMeta or Malformed message."""
        if lay == rc.EVENT:
            self.events.append(rc.decode_event(data))
        elif lay == rc.META:
            self.meta = rc.decode_meta(data).info
        else:
            self.malformed.append((t, rc.decode_malformed(data)[2]))

    def _read_messages(self, f) -> None:
        for sch, ch, m in make_reader(f).iter_messages(log_time_order=False):
            lay = rc.layout(sch) if sch is not None else None
            key = rc.channel_key(ch)
            if lay == rc.MALFORMED:
                key = ch.metadata.get("wire_key") or key.replace("/malformed/", "/", 1)
            t = pr.message_type_for_key(key)
            if t is None:
                continue
            self.run_id = self.run_id or key.split("/")[1]
            try:
                if lay in (rc.SENSORS, rc.CURRENTS, rc.TIMING):
                    self.recorded.setdefault(lay, []).append(m.data)
                elif lay in (rc.EVENT, rc.META, rc.MALFORMED):
                    self._fixed(lay, t, m.data)
                else:                                       # the earlier layout: wire bytes
                    d = rc.upgrade(t, m.data)               # protocol versions 1, 2 read as 3
                    _wire(t, d, self.sens, self.cur, self.tim, self.events, self.n_by_type)
                    if t == "RunMeta":
                        self.meta = pr.decode_meta(d).info
            except _Malformed as e:
                self.reasons[f"{t}: {e}"] += 1
            except _DECODE_ERRORS as e:
                self.reasons[f"{t}: {type(e).__name__}"] += 1

    def decode_recorded(self) -> None:
        """The recorded vector / timing payloads read message by message, as arrays (those read
        chunk by chunk already are)."""
        for rtype in (rc.SENSORS, rc.CURRENTS, rc.TIMING):
            if self.recorded.get(rtype):
                datas = self.recorded[rtype]
                n = 0 if rtype == rc.TIMING else (len(datas[0]) - (44 if rtype == rc.SENSORS else 52)) // 8
                self.arrays[rtype] = [rc.decode_vectors(rtype, n, datas)]

    def columns(self, raw: bool) -> dict[str, list]:
        """``{wire type: [(seq, step, t_ns, v, raw) column parts]}`` of SensorSample and
        CurrentCommand: those of the earlier layout, the recorded ones (out-of-range rows and an
        axis count other than the run's rejected), the malformed ones that decode after all."""
        cols = {"SensorSample": [], "CurrentCommand": []}
        for wt, items in (("SensorSample", self.sens), ("CurrentCommand", self.cur)):
            if items:
                cols[wt].append((np.array([it[0].seq for it in items], np.uint64),
                                 np.array([it[0].step for it in items], np.uint64),
                                 np.array([it[0].sim_time_ns for it in items], np.int64),
                                 np.array([_vec(it[0]) for it in items], float), [it[1] for it in items]))
        self._recorded_columns(cols, raw)
        self._malformed_columns(cols)
        return cols

    def _recorded_columns(self, cols: dict, raw: bool) -> None:
        reasons, n_by_type = self.reasons, self.n_by_type
        peers = rc.peer_ids(self.meta)             # the senders' ids that end the restored wire bytes
        for rtype in (rc.SENSORS, rc.CURRENTS):
            if not self.arrays.get(rtype):
                continue
            wt = rc.WIRE_OF[rtype]
            a = np.concatenate(self.arrays[rtype])
            n = a.dtype["v"].shape[0]
            n_by_type.setdefault(wt, n)
            ok = (a["seq"] < INT64) & (a["step"] < INT64)
            if n != n_by_type[wt]:
                reasons[f"{wt}: axis count {n} != {n_by_type[wt]}"] += len(a)
                continue
            if not ok.all():
                reasons[f"{wt}: seq or step out of range"] += int((~ok).sum())
                a = a[ok]
            cols[wt].append((a["seq"], a["step"], rc.stamp_ns(a["sec"], a["nanosec"]), np.array(a["v"]),
                             rc.wire_payloads(rtype, a, peers[wt]) if raw else []))

    def _malformed_columns(self, cols: dict) -> None:
        """The recorder could not decode them: why not, as before."""
        for wt, data in self.malformed:
            try:                                   # (kept verbatim: a recording of protocol 1 or 2 upgraded)
                _wire(wt, rc.upgrade(wt, data), sens2 := [], cur2 := [], [], [], self.n_by_type)
                for it in sens2 + cur2:            # decodes after all (another count than the recorder's)
                    m = it[0]
                    cols[wt].append((np.array([m.seq], np.uint64), np.array([m.step], np.uint64),
                                     np.array([m.sim_time_ns], np.int64), np.array([_vec(m)], float), [it[1]]))
            except _Malformed as e:
                self.reasons[f"{wt}: {e}"] += 1
            except _DECODE_ERRORS as e:
                self.reasons[f"{wt}: {type(e).__name__}"] += 1

    def timing(self) -> dict | None:
        """The per-step timing arrays, by step (None: no timing recorded)."""
        tparts = [(np.arange(t.step, t.step + len(t.rtt_ns)), t.rtt_ns, t.tet_ns, t.wake_lateness_ns,
                   np.asarray(t.flags, np.uint8), t.period_ns) for t in self.tim]
        if self.arrays.get(rc.TIMING):
            a = np.concatenate(self.arrays[rc.TIMING])
            ok = a["step"] < INT64
            if not ok.all():
                self.reasons["Timing: step out of range"] += int((~ok).sum())
                a = a[ok]
            if len(a):
                tparts.append((a["step"].astype(np.int64), a["rtt"], a["tet"], a["late"], a["flags"],
                               int(a["period"][0])))
        if not tparts:
            return None
        step = np.concatenate([p[0] for p in tparts]).astype(np.int64)
        o = np.argsort(step, kind="stable")
        return {"step": step[o], "rtt_ns": np.concatenate([p[1] for p in tparts])[o],
                "tet_ns": np.concatenate([p[2] for p in tparts])[o],
                "lateness_ns": np.concatenate([p[3] for p in tparts])[o],
                "flags": np.concatenate([p[4] for p in tparts])[o], "period_ns": tparts[0][5] or 1}


def _pack(parts, raw: bool) -> dict:
    """Column parts of one wire type as one set of arrays, in seq order."""
    if not parts:
        return {"seq": np.zeros(0, np.int64), "step": np.zeros(0, np.int64),
                "t_ns": np.zeros(0, np.int64), "v": np.zeros((0, 0)), "raw": []}
    seq = np.concatenate([p[0] for p in parts]).astype(np.int64)
    o = np.argsort(seq, kind="stable")
    raws = [r for p in parts for r in p[4]]
    return {"seq": seq[o], "step": np.concatenate([p[1] for p in parts]).astype(np.int64)[o],
            "t_ns": np.concatenate([p[2] for p in parts])[o],
            "v": np.concatenate([p[3] for p in parts])[o],
            "raw": [raws[i] for i in o] if raw else []}


def channels(summary) -> dict:
    """{channel id: (recorded layout, wire type, wire key)} of an ambhil recording's channels."""
    out = {}
    for cid, ch in summary.channels.items():
        lay = rc.layout(summary.schemas.get(ch.schema_id))
        key = rc.channel_key(ch)
        if lay == rc.MALFORMED:
            key = ch.metadata.get("wire_key") or key.replace("/malformed/", "/", 1)
        wt = pr.message_type_for_key(key)
        if lay is not None and wt is not None:
            out[cid] = (lay, wt, key)
    return out


def gather_channel(buf, lay, starts, ends, where) -> np.ndarray:
    """One chunk's messages of a fixed-layout recorded channel as a structured array."""
    size = ends[0] - starts[0]
    if not (np.asarray(ends) - np.asarray(starts) == size).all():
        raise ValueError(f"channel {where}: recorded messages of unequal size")
    n = 0 if lay == rc.TIMING else (size - (44 if lay == rc.SENSORS else 52)) // 8
    return gather(buf, starts, size, rc.rec_dtype(lay, n))


def _wire(t, data, sens, cur, tim, events, n_by_type) -> None:
    """One message of the earlier layout (wire bytes verbatim) into its list."""
    if t == "SensorSample":
        sens.append((_vector(pr.decode_sensor(data), n_by_type, t), bytes(data)))
    elif t == "CurrentCommand":
        cur.append((_vector(pr.decode_current(data), n_by_type, t), bytes(data)))
    elif t == "Timing":
        tim.append(_timing(pr.decode_timing(data)))
    elif t == "Event":
        events.append(pr.decode_event(data))


def malformed_rows(wt: str, data: bytes, n_by_type: dict, reasons) -> list:
    """A payload the recorder could not decode: why not (counted in ``reasons``, as load_run
    does), or its message if it decodes after all (another axis count than the recorder's)."""
    rows: list = []
    data = rc.upgrade(wt, data)                    # a recording of protocol 1 or 2
    try:
        _wire(wt, data, rows, rows, [], [], n_by_type) if wt in ("SensorSample", "CurrentCommand") else None
        if wt not in ("SensorSample", "CurrentCommand"):
            pr.decode_any(wt, data)
    except _Malformed as e:
        reasons[f"{wt}: {e}"] += 1
    except _DECODE_ERRORS as e:
        reasons[f"{wt}: {type(e).__name__}"] += 1
    return [r[0] for r in rows]


def axis_names(meta: dict, n: int) -> list[str]:
    """The run's axis names (RunMeta ``axis_names``), else ``x0, y0, x1, ...``."""
    names = meta.get("axis_names")
    if isinstance(names, list) and len(names) == n:
        return [str(x) for x in names]
    return [f"{'xy'[i % 2]}{i // 2}" for i in range(n)]
