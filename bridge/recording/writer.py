"""Writing a run in the recorded layout (:mod:`ambhil.bridge.recording.layout`): the wire
payloads of each key transcoded into their recorded messages, channels and schemas registered on
first use.  One payload at a time (:meth:`Writer.put`), a plant's RecordBatch a block at a time
(:meth:`Writer.put_many`, :meth:`Writer.put_block`: numpy, one bulk add per block), or whole arrays
(:meth:`Writer.put_vectors`, ``ambhil simulate``).  A payload that does not decode goes verbatim,
with the reason, to the key's ``malformed`` channel."""
from __future__ import annotations

import json
import math
import struct

import numpy as np

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol.messages import ENCAP, PROTOCOL_VERSION
from ambhil.bridge.recording.layout import (
    ENCAP_V4, EVENT, MALFORMED, META, RECORDED, TAIL_LEN, TIMING, UNIT_SUFFIX, default_axis_names,
    encode_event, encode_malformed, encode_meta, field_names, recorded_key, schema_def, schema_name,
    timing_rows, topic_of, vector_rows, wire_dtype)
from ambhil.bridge.recording.mcap_bulk import add_messages

_isfinite = math.isfinite


class Writer:
    """Writes a run's messages in the recorded layout on an ``mcap.writer.Writer`` (already
    started with :data:`ambhil.bridge.recording.layout.PROFILE`): channels registered on first
    use, per key.

    :meth:`put` takes one wire payload of a key (``wall_ns``: its publish / arrival wall time);
    :meth:`put_vectors` / :meth:`put_timing` take arrays (``ambhil simulate``).  ``axis_names``:
    the run's axis order (else RunMeta's ``axis_names`` once it was put, else ``x0, y0, ...``)."""

    def __init__(self, mcap_writer, run_id: str, axis_names=None):
        self.w = mcap_writer
        self.K = pr.keys(run_id)
        self.axis_names = list(axis_names) if axis_names else None
        self.schemas: dict[tuple, int] = {}
        self.channels: dict[str, tuple] = {}     # key -> (channel id, rtype, n)
        self.per_key: dict[str, int] = {}
        self.n = 0
        self.last_sim = 0
        self.n_axes: int | None = len(self.axis_names) if self.axis_names else None
        self._codecs: dict = {}

    def _schema(self, rtype, names=None) -> int:
        k = (rtype, tuple(names or ()))
        sid = self.schemas.get(k)
        if sid is None:
            sid = self.schemas[k] = self.w.register_schema(schema_name(rtype), "ros2msg",
                                                           schema_def(rtype, names).encode())
        return sid

    def _channel(self, key: str, rtype: str, n: int = 0):
        ch = self.channels.get(key)
        if ch is None:
            md = {"type": rtype, "key": key}
            names = None
            if rtype in UNIT_SUFFIX:
                names = (self.axis_names if self.axis_names and len(self.axis_names) == n
                         else default_axis_names(n))
                suffix, what, unit = UNIT_SUFFIX[rtype]
                md.update(axis_names=json.dumps(names), fields=json.dumps(field_names(names, suffix)),
                          unit=unit, quantity=what)
            if rtype == MALFORMED:
                md["wire_key"] = key.replace("/malformed/", "/", 1)
            cid = self.w.register_channel(topic_of(key), "cdr", self._schema(rtype, names), md)
            ch = self.channels[key] = (cid, rtype, n)
            self.per_key[key] = 0
        return ch

    def _add(self, key, rtype, data, sim_ns, wall_ns, seq, n=0):
        cid = self._channel(key, rtype, n)[0]
        self.w.add_message(cid, max(int(sim_ns), 0), data, max(int(wall_ns), 0), int(seq) & 0xFFFFFFFF)
        self.per_key[key] += 1
        self.n += 1

    def malformed(self, key: str, data: bytes, reason: str, wall_ns: int) -> None:
        parts = key.split("/", 2)
        mkey = f"{parts[0]}/{parts[1]}/malformed/{parts[2]}" if len(parts) == 3 else key + "/malformed"
        self._add(mkey, MALFORMED, encode_malformed(self.last_sim, reason, bytes(data)), self.last_sim,
                  wall_ns, 0)

    def put(self, key: str, data, wall_ns: int, wtype: str | None = None) -> str | None:
        """One wire payload of ``key`` (its wire type: ``wtype`` or from the key).  Returns the
        wire type stored, or None if it went to the malformed channel.  Events of every role's
        key go to the run's one events channel (:func:`ambhil.bridge.recording.layout.recorded_key`)."""
        wtype = wtype or pr.message_type_for_key(key)
        key = recorded_key(key)
        try:
            if wtype in ("SensorSample", "CurrentCommand"):
                self._put_vector(key, wtype, data, wall_ns)
            elif wtype == "Event":
                ev = pr.decode_event(data)
                self._add(key, EVENT, encode_event(ev), ev.sim_time_ns, wall_ns, ev.seq)
            elif wtype == "RunMeta":
                m = pr.decode_meta(data)
                names = m.info.get("axis_names")
                if self.axis_names is None and isinstance(names, list) and names:
                    self.axis_names = [str(x) for x in names]
                    if self.n_axes is None:
                        self.n_axes = len(self.axis_names)
                self._add(key, META, encode_meta(m), m.sim_time_ns, wall_ns, m.seq)
            elif wtype == "Timing":
                self.put_timing(key, pr.decode_timing(data), wall_ns)
            else:
                self.malformed(key, data, "unknown key", wall_ns)
                return None
        except (ValueError, OverflowError, TypeError) as e:     # ProtocolError is a ValueError
            self.malformed(key, data, str(e) if isinstance(e, pr.ProtocolError) else f"{type(e).__name__}: {e}",
                           wall_ns)
            return None
        return wtype

    def _vec(self, key, wtype, n):
        """(channel id, wire struct, recorded struct, count index, codec) of a vector key.  The
        wire struct ends with the id and the mac (one field: neither is recorded, nor checked
        here: the recorder took only authenticated messages)."""
        c = self._codecs.get((key, wtype))
        if c is None:
            sens = wtype == "SensorSample"
            codec = (pr.SensorCodec if sens else pr.CurrentCodec)(n)
            c = self._codecs[(key, wtype)] = (
                self._channel(key, RECORDED[wtype], n)[0],
                struct.Struct(f"<4sH6xQQq{'q' if sens else 'qq'}I4x{n}d{TAIL_LEN}s"),
                struct.Struct(f"<4siIIB3xQQq{'' if sens else 'q'}{n}d"), 6 if sens else 7, codec)
        return c

    def _put_vector(self, key, wtype, data, wall_ns) -> None:
        n = self.n_axes
        if n is None:
            m = (pr.decode_sensor if wtype == "SensorSample" else pr.decode_current)(data)
            n = self.n_axes = len(m.displacement if wtype == "SensorSample" else m.current)
        cid, full, rec, ci, codec = self._vec(key, wtype, n)
        if len(data) != full.size:
            codec._decode(data)                    # raises the ProtocolError that says why
        h = full.unpack(data)
        if h[0] != ENCAP or h[1] != PROTOCOL_VERSION or h[ci] != n or not all(map(_isfinite, h[ci + 1:-1])):
            codec._decode(data)
        sim = h[4]
        self.w.add_message(cid, sim if sim > 0 else 0,
                           rec.pack(ENCAP, sim // 1_000_000_000, sim % 1_000_000_000, 1, 0, *h[2:4], *h[5:ci], *h[ci + 1:-1]),
                           wall_ns if wall_ns > 0 else 0, h[2] & 0xFFFFFFFF)
        self.last_sim = sim
        self.per_key[key] += 1
        self.n += 1

    def put_many(self, key: str, wtype: str, datas: list, walls: list) -> None:
        """Several wire payloads of one vector key (the plant's RecordBatch), transcoded at once:
        the well-formed ones of the expected size with numpy, the others one by one (:meth:`put`)."""
        if not datas:
            return
        n = self._axes(key, wtype, datas[0], walls[0])
        if n is not True:                            # the first was put to learn the axis count
            datas, walls = datas[1:], walls[1:]
            if n is None or not datas:
                for d, wl in zip(datas, walls):
                    self.put(key, d, wl, wtype)
                return
        n = self.n_axes
        size = self._vec(key, wtype, n)[1].size
        same = [len(d) == size for d in datas]
        idx = [i for i, ok in enumerate(same) if ok]
        bad = [i for i, ok in enumerate(same) if not ok]
        if idx:
            a = np.frombuffer(b"".join(datas[i] for i in idx), wire_dtype(wtype, n))
            bad += [idx[i] for i in self._put_rows(key, wtype, n, a, np.asarray(walls, np.int64)[idx])]
        for i in sorted(bad):                        # malformed: reasons, one by one
            self.put(key, datas[i], walls[i], wtype)

    def put_block(self, key: str, wtype: str, data, offset: int, count: int, size: int, walls) -> None:
        """``count`` wire payloads of one vector key lying back to back in ``data`` from
        ``offset``, each ``size`` bytes (a RecordBatch's common case), with their arrival /
        publish wall times: as :meth:`put_many`, without a bytes object per payload."""
        if count <= 0:
            return
        n = self.n_axes
        if n is None or size != self._vec(key, wtype, n)[1].size:
            self.put_many(key, wtype, [bytes(data[offset + i * size:offset + (i + 1) * size])
                                       for i in range(count)], list(np.asarray(walls).tolist()))
            return
        a = np.frombuffer(data, wire_dtype(wtype, n), count, offset)
        walls = np.asarray(walls, np.int64)
        for i in self._put_rows(key, wtype, n, a, walls):
            self.put(key, a[i].tobytes(), int(walls[i]), wtype)

    def _axes(self, key, wtype, first, wall):
        """The run's axis count, learnt from the first payload if not known yet (which is then
        put on its own: returns the count, or None if it could not be learnt); True if known."""
        if self.n_axes is not None:
            return True
        self.put(key, first, wall, wtype)
        return self.n_axes

    def _put_rows(self, key, wtype, n, a, walls) -> list[int]:
        """Wire rows ``a`` (structured, :func:`wire_dtype`) into the recorded channel: the
        well-formed ones in one bulk add; returns the indices of the others (in order)."""
        cid = self._vec(key, wtype, n)[0]
        ok = ((a["encap"] == ENCAP_V4) & (a["version"] == PROTOCOL_VERSION) & (a["count"] == n)
              & np.isfinite(a["v"]).all(axis=1))
        if not ok.all():
            bad = np.flatnonzero(~ok).tolist()
            a, walls = a[ok], walls[ok]
        else:
            bad = []
        if len(a):
            sim = a["sim"]
            rows = vector_rows(RECORDED[wtype], a["seq"], a["step"], sim, a["v"], pub=a["pub"],
                               recv=a["recv"] if wtype == "CurrentCommand" else None)
            add_messages(self.w, cid, np.maximum(sim, 0), rows, np.maximum(walls, 0),
                         a["seq"] & np.uint64(0xFFFFFFFF))
            self.last_sim = int(sim[-1])
            self.per_key[key] += len(a)
            self.n += len(a)
        return bad

    def put_timing(self, key: str, t: pr.Timing, wall_ns) -> None:
        rows = timing_rows(t)
        N = len(rows)
        cid = self._channel(key, TIMING)[0]
        steps = t.step + np.arange(N, dtype=np.int64)
        wall = np.broadcast_to(np.maximum(np.asarray(wall_ns, np.int64), 0), (N,))
        add_messages(self.w, cid, np.maximum(steps * t.period_ns, 0), rows, wall, steps & 0xFFFFFFFF)
        self.per_key[key] += N
        self.n += N

    def put_vectors(self, key: str, wtype: str, seq, step, sim_ns, v, wall_ns, pub=None, recv=None) -> None:
        """N recorded SensorSample / CurrentCommand rows at once (``ambhil simulate``)."""
        rtype = RECORDED[wtype]
        v = np.asarray(v, np.float64)
        rows = vector_rows(rtype, seq, step, sim_ns, v, pub=pub, recv=recv)
        N = len(rows)
        cid = self._channel(key, rtype, v.shape[1])[0]
        sim = np.maximum(np.broadcast_to(np.asarray(sim_ns, np.int64), (N,)), 0)
        wall = np.maximum(np.broadcast_to(np.asarray(wall_ns, np.int64), (N,)), 0)
        add_messages(self.w, cid, sim, rows, wall,
                     np.broadcast_to(np.asarray(seq, np.uint64), (N,)) & np.uint64(0xFFFFFFFF))
        self.per_key[key] += N
        self.n += N
        if N:
            self.last_sim = int(sim[-1])
