"""The MCAP layout of a recording (docs/hil.md, "What a recording holds"): ROS 2 conventions that
Foxglove, the mcap ros2 decoder and rerun read natively, transcoded from the wire messages.

The wire protocol (docs/protocol.md) is not changed: what goes over zenoh stays byte for byte
the same.  The recorder (and ``ambhil simulate``) write each message in a *recorded* form:

- MCAP profile ``ros2``; every channel ``message_encoding="cdr"`` with a ``ros2msg`` schema;
  fixed topic names, the run id dropped from the key expression (``/ambhil/plant/sensors``,
  ``/ambhil/controller/currents``, ``/ambhil/events``, ``/ambhil/meta``, ``/ambhil/timing``); the
  run id is in the ``ambhil.recorder`` metadata and each channel's ``key`` metadata (the zenoh key,
  :func:`channel_key`);
- every message starts with a ``std_msgs/Header`` whose stamp is the **simulation time**
  (``sim_time_ns``: step x period), and the MCAP ``log_time`` is that same simulation time, so a
  viewer's timeline is the simulated time (1 s of simulation = 1 s of timeline);
- the wall time stays available: MCAP ``publish_time`` = the wall time (CLOCK_REALTIME, ns) at
  which the message was put on the wire (SensorSample: the plant's publish; CurrentCommand: its
  arrival at the plant, or at the recorder with ``--source wire``; others: arrival at the
  recorder) and the message's own wall-time fields;
- displacement and current are **named fields**, one ``float64`` per axis, named after the axis
  with the unit as suffix (``a_x_m``, ``a_x_amp``; the mapping is in the channel metadata);
- timing is **one message per step** (``StepTiming``), not the wire's batches of 200;
- a payload that does not decode (malformed, another axis count) is kept verbatim in a
  ``Malformed`` message on ``/ambhil/malformed/<topic>`` with the reason.

The wire bytes of every recorded SensorSample / CurrentCommand are restored from the recorded
fields (:func:`wire_payloads`), as protocol version 3: the sender's peer id that ends them on the
wire is not a recorded field (RunMeta holds both, ``plant_peer_id``, ``controller_peer_id``;
:func:`peer_ids`), and **a recording keeps no MACs**: the 16 bytes of the ``mac`` that follow the
id are zero in the restored bytes (the MAC was checked when the message was received, under the
run's session key, which the file does not hold; whoever re-publishes them, ``replay
--to-controller``, seals them again with its own key).  Everything before the mac is the wire's,
byte for byte.  The MCAP topic of events is ``/ambhil/events`` whichever role's key
(``events/plant``, ``events/controller``) they travelled on (:func:`recorded_key`).
Recordings of the earlier layouts (topic = ``/`` + key with the run id; or profile ``""``, the
wire bytes verbatim, topic = key) are read as before (:func:`layout`); their messages of protocol
version 1 or 2 are upgraded to version 3 on reading (:func:`upgrade`).

This module is the layout itself: topics, schemas, the bytes of each recorded message both ways
(encode / decode, the wire bytes restored).  Around it: :class:`ambhil.bridge.recording.writer.Writer`
writes a run in it, :func:`ambhil.bridge.recording.chunks.iter_chunks` reads one chunk by chunk,
:func:`ambhil.bridge.recording.simulated_run.write_simulation` records an in-process run in it.
"""
from __future__ import annotations

import functools
import json
import re

import numpy as np

from ambhil.bridge import protocol as pr
from ambhil.bridge.protocol.cdr import _R, _W
from ambhil.bridge.protocol.auth import MAC_LEN
from ambhil.bridge.protocol.messages import ENCAP, NO_PEER, PEER_LEN, PROTOCOL_VERSION

PROFILE = "ros2"
LIBRARY = "ambhil-recorder"

# the dependencies of every recorded schema (appended as ros2msg does: a line of '=' and MSG:)
_SEP = "=" * 80 + "\n"
_HEADER = (_SEP + "MSG: std_msgs/Header\n"
           "# Standard metadata for higher-level stamped data types.\n"
           "builtin_interfaces/Time stamp\n"
           "string frame_id\n"
           + _SEP + "MSG: builtin_interfaces/Time\n"
           "int32 sec\n"
           "uint32 nanosec\n")

# recorded type of each wire type (schema names)
SENSORS, CURRENTS, EVENT, META, TIMING, MALFORMED = (
    "SensorSampleStamped", "CurrentCommandStamped", "EventStamped", "RunMetaStamped", "StepTiming",
    "Malformed")
RECORDED = {"SensorSample": SENSORS, "CurrentCommand": CURRENTS, "Event": EVENT, "RunMeta": META,
            "Timing": TIMING}
WIRE_OF = {v: k for k, v in RECORDED.items()}
UNIT_SUFFIX = {SENSORS: ("m", "displacement", "m"), CURRENTS: ("amp", "coil current", "A")}

_FIXED = {
    EVENT: ("# an ambhil Event (docs/protocol.md section 3); stamp: simulation time\n"
            "std_msgs/Header header\nuint16 kind\nstring kind_name\nuint64 seq\nuint64 step\n"
            "int64 wall_ns               # sender CLOCK_REALTIME\nstring source\nstring text\n"),
    META: ("# the run's RunMeta (docs/protocol.md section 3); json: one JSON object\n"
           "std_msgs/Header header\nuint64 seq\nuint64 step\nint64 wall_ns\nstring json\n"),
    TIMING: ("# the plant's timing of one step (docs/hil.md); stamp: simulation time of the step\n"
             "std_msgs/Header header\nuint64 step\nint64 period_ns\n"
             "int64 wake_lateness_ns      # real time: publish - deadline; lockstep: 0\n"
             "int64 rtt_ns                # sample publish -> reply at the plant (0: none)\n"
             "int64 tet_ns                # controller execution time (publish - receive)\n"
             "uint8 flags                 # bit0 held, bit1 late_wake, bit2 warmup\n"
             "bool held                   # no reply at the deadline: last currents held\n"
             "bool late_wake              # the plant woke after the next deadline\n"
             "bool warmup                 # warm-up step, not in the statistics\n"),
    MALFORMED: ("# a payload that did not decode as its key's message type, verbatim\n"
                "std_msgs/Header header      # stamp: the last simulation time before it\n"
                "string reason\nuint8[] wire\n"),
}


NO_MAC = bytes(MAC_LEN)      # where a restored message's mac was (a recording keeps no MACs)
TAIL_LEN = PEER_LEN + MAC_LEN   # SensorSample / CurrentCommand end with ``peer[16] mac[16]`` (protocol 3)


def recorded_key(key: str) -> str:
    """The key a wire message is recorded under: every role's events key
    (``ambhil/<run>/events/<role>``, protocol 3) is the run's one ``ambhil/<run>/events`` (MCAP topic
    ``/ambhil/events``, as in every recording); any other key is itself."""
    parts = key.split("/")
    if len(parts) == 4 and parts[0] == "ambhil" and parts[2] == "events":
        return "/".join(parts[:3])
    return key


def topic_of(key: str) -> str:
    """The fixed MCAP topic of a key: the run id dropped (``ambhil/<run>/plant/sensors`` ->
    ``/ambhil/plant/sensors``), so one Foxglove layout or rosbag script fits every run.  The run id
    stays in the channel metadata (``key``) and in the ``ambhil.recorder`` metadata."""
    parts = key.split("/", 2)
    if len(parts) == 3 and parts[0] == "ambhil":
        return f"/ambhil/{parts[2]}"
    return "/" + key


def key_of(topic: str) -> str:
    return topic[1:] if topic.startswith("/") else topic


def channel_key(channel) -> str:
    """The zenoh key expression a recorded channel's messages travelled on (run id included):
    the channel metadata ``key`` of a recording with fixed topics, else the topic itself (the
    earlier layouts named each topic after its key)."""
    return (channel.metadata or {}).get("key") or key_of(channel.topic)


def field_names(axis_names, suffix: str) -> list[str]:
    """ROS 2 field names (``[a-z][a-z0-9_]*``) of the axes, unit suffixed: ``A-x`` -> ``a_x_m``."""
    out, seen = [], set()
    for i, a in enumerate(axis_names):
        s = re.sub(r"[^a-z0-9]+", "_", str(a).lower()).strip("_") or f"axis{i}"
        if not s[0].isalpha():
            s = f"axis_{s}"
        s = f"{s}_{suffix}"
        while s in seen:
            s = f"{s}{i}"
        seen.add(s)
        out.append(s)
    return out


def default_axis_names(n: int) -> list[str]:
    return [f"{'xy'[i % 2]}{i // 2}" for i in range(n)]


def vector_def(rtype: str, axis_names) -> str:
    suffix, what, unit = UNIT_SUFFIX[rtype]
    head = ("# an ambhil SensorSample as recorded (docs/hil.md); stamp: simulation time (step x period)\n"
            "std_msgs/Header header\nuint64 seq\nuint64 step\n"
            "int64 publish_wall_ns       # plant CLOCK_REALTIME at publish (0: in-process simulate)\n"
            if rtype == SENSORS else
            "# an ambhil CurrentCommand as recorded (docs/hil.md); answers the SensorSample of the same seq\n"
            "std_msgs/Header header\nuint64 seq\nuint64 step\n"
            "int64 recv_wall_ns          # controller CLOCK_REALTIME when the sample arrived\n"
            "int64 publish_wall_ns       # controller CLOCK_REALTIME at publish\n")
    lines = [f"float64 {f}  # {what} of axis {a}, {unit}"
             for f, a in zip(field_names(axis_names, suffix), axis_names)]
    return head + "\n".join(lines) + "\n" + _HEADER


def schema_def(rtype: str, axis_names=None) -> str:
    if rtype in UNIT_SUFFIX:
        return vector_def(rtype, axis_names)
    return _FIXED[rtype] + _HEADER


def schema_name(rtype: str) -> str:
    return f"{pr.PACKAGE}/msg/{rtype}"


# --------------------------------------------------------------------------- fixed layouts
# Header with frame_id "": int32 sec @4, uint32 nanosec @8, uint32 len=1 @12, NUL @16, pad to 20.
_HDR = [("encap", "V4", 0), ("sec", "<i4", 4), ("nanosec", "<u4", 8), ("flen", "<u4", 12),
        ("fnul", "u1", 16)]


def _dtype(fields, size):
    names, formats, offsets = zip(*fields)
    return np.dtype({"names": list(names), "formats": list(formats), "offsets": list(offsets),
                     "itemsize": size})


@functools.lru_cache(maxsize=None)
def rec_dtype(rtype: str, n: int = 0) -> np.dtype:
    """numpy dtype of one recorded message of fixed layout (vectors of ``n`` axes, timing)."""
    if rtype == SENSORS:
        return _dtype(_HDR + [("seq", "<u8", 20), ("step", "<u8", 28), ("pub", "<i8", 36),
                              ("v", ("<f8", (n,)), 44)], 44 + 8 * n)
    if rtype == CURRENTS:
        return _dtype(_HDR + [("seq", "<u8", 20), ("step", "<u8", 28), ("recv", "<i8", 36),
                              ("pub", "<i8", 44), ("v", ("<f8", (n,)), 52)], 52 + 8 * n)
    if rtype == TIMING:
        return _dtype(_HDR + [("step", "<u8", 20), ("period", "<i8", 28), ("late", "<i8", 36),
                              ("rtt", "<i8", 44), ("tet", "<i8", 52), ("flags", "u1", 60),
                              ("held", "u1", 61), ("late_wake", "u1", 62), ("warmup", "u1", 63)], 64)
    raise ValueError(rtype)


@functools.lru_cache(maxsize=None)
def wire_dtype(wtype: str, n: int) -> np.dtype:
    """numpy dtype of a SensorSample / CurrentCommand on the wire (docs/protocol.md §3)."""
    base = [("encap", "V4", 0), ("version", "<u2", 4), ("seq", "<u8", 12), ("step", "<u8", 20),
            ("sim", "<i8", 28)]
    if wtype == "SensorSample":
        return _dtype(base + [("pub", "<i8", 36), ("count", "<u4", 44), ("v", ("<f8", (n,)), 52),
                              ("peer", f"V{PEER_LEN}", 52 + 8 * n),
                              ("mac", f"V{MAC_LEN}", 52 + 8 * n + PEER_LEN)], 52 + 8 * n + TAIL_LEN)
    return _dtype(base + [("recv", "<i8", 36), ("pub", "<i8", 44), ("count", "<u4", 52),
                          ("v", ("<f8", (n,)), 60), ("peer", f"V{PEER_LEN}", 60 + 8 * n),
                          ("mac", f"V{MAC_LEN}", 60 + 8 * n + PEER_LEN)], 60 + 8 * n + TAIL_LEN)


def peer_ids(meta: dict) -> dict[str, bytes]:
    """``{"SensorSample": plant id, "CurrentCommand": controller id}`` from a run's RunMeta info
    (:data:`NO_PEER` where it names none: ``ambhil simulate``, older recordings)."""
    out = {}
    for wt, k in (("SensorSample", "plant_peer_id"), ("CurrentCommand", "controller_peer_id")):
        try:
            b = bytes.fromhex(str((meta or {}).get(k) or ""))
        except ValueError:
            b = b""
        out[wt] = b if len(b) == PEER_LEN else NO_PEER
    return out


def upgrade(wtype: str, data, peer: bytes = NO_PEER) -> bytes:
    """A wire message of protocol version 1 or 2 (the earlier recorded layout and the Malformed
    messages keep them verbatim) as version 3: the version field set to 3 and, for SensorSample /
    CurrentCommand, what version 3 has more appended: version 1 ended with the vector (the
    sender's ``peer`` id and a zero mac appended), version 2 with the id (a zero mac appended;
    a recording keeps no MACs).  Anything else is returned unchanged (and validated by its
    decoder)."""
    data = bytes(data)
    if len(data) >= 6 and data[:4] == ENCAP and data[4:6] in (b"\x01\x00", b"\x02\x00"):
        old = data[4]
        data = data[:4] + PROTOCOL_VERSION.to_bytes(2, "little") + data[6:]
        if wtype in ("SensorSample", "CurrentCommand"):
            data += (peer + NO_MAC) if old == 1 else NO_MAC
    return data


ENCAP_V4 = np.frombuffer(ENCAP, "V4")[0]     # the CDR encapsulation as one numpy void (a field's value)


def _stamp(arr, sim_ns):
    sim_ns = np.asarray(sim_ns, np.int64)
    arr["encap"] = ENCAP_V4
    arr["sec"] = sim_ns // 1_000_000_000
    arr["nanosec"] = sim_ns % 1_000_000_000
    arr["flen"] = 1


def stamp_ns(sec, nanosec):
    return np.asarray(sec, np.int64) * 1_000_000_000 + np.asarray(nanosec, np.int64)


def _split(buf: bytes, size: int, count: int) -> list[bytes]:
    return [buf[i:i + size] for i in range(0, size * count, size)]


def vector_rows(rtype: str, seq, step, sim_ns, v, pub=None, recv=None) -> np.ndarray:
    """Recorded SensorSampleStamped / CurrentCommandStamped rows of N samples (vectorised): a
    structured array whose rows' bytes are the CDR payloads."""
    v = np.asarray(v, np.float64)
    N, n = v.shape
    a = np.zeros(N, rec_dtype(rtype, n))
    _stamp(a, sim_ns)
    a["seq"], a["step"], a["v"] = seq, step, v
    a["pub"] = 0 if pub is None else pub
    if rtype == CURRENTS:
        a["recv"] = 0 if recv is None else recv
    return a


def encode_vectors(rtype: str, seq, step, sim_ns, v, pub=None, recv=None) -> list[bytes]:
    """Recorded SensorSampleStamped / CurrentCommandStamped payloads of N rows (vectorised)."""
    a = vector_rows(rtype, seq, step, sim_ns, v, pub, recv)
    return _split(a.tobytes(), a.dtype.itemsize, len(a))


def timing_rows(t: pr.Timing) -> np.ndarray:
    """StepTiming rows, one per step of a wire Timing batch (their bytes are the payloads)."""
    N = len(t.rtt_ns)
    a = np.zeros(N, rec_dtype(TIMING))
    steps = t.step + np.arange(N, dtype=np.int64)
    _stamp(a, steps * t.period_ns)
    a["step"], a["period"] = steps, t.period_ns
    a["late"], a["rtt"], a["tet"], a["flags"] = t.wake_lateness_ns, t.rtt_ns, t.tet_ns, t.flags
    f = np.asarray(t.flags, np.uint8)
    a["held"], a["late_wake"], a["warmup"] = (f & pr.FLAG_HELD) > 0, (f & pr.FLAG_LATE_WAKE) > 0, (f & pr.FLAG_WARMUP) > 0
    return a


def encode_timing_steps(t: pr.Timing) -> list[bytes]:
    """One StepTiming payload per step of a wire Timing batch."""
    a = timing_rows(t)
    return _split(a.tobytes(), a.dtype.itemsize, len(a))


def _header(w: _W, sim_ns: int) -> None:
    w.put("i", sim_ns // 1_000_000_000)
    w.put("I", sim_ns % 1_000_000_000)
    w.string("", 1)


def encode_event(ev: pr.Event) -> bytes:
    w = _W()
    _header(w, ev.sim_time_ns)
    w.put("H", ev.kind)
    w.string(ev.kind_name, pr.DEFAULT_MAX_TEXT)
    w.put("Q", ev.seq)
    w.put("Q", ev.step)
    w.put("q", ev.wall_ns)
    w.string(ev.source, pr.DEFAULT_MAX_TEXT)
    w.string(ev.text, pr.DEFAULT_MAX_TEXT)
    return bytes(w.b)


def encode_meta(m: pr.RunMeta) -> bytes:
    w = _W()
    _header(w, m.sim_time_ns)
    w.put("Q", m.seq)
    w.put("Q", m.step)
    w.put("q", m.wall_ns)
    w.string(json.dumps(m.info, sort_keys=True, separators=(",", ":")), 1 << 30)
    return bytes(w.b)


def encode_malformed(sim_ns: int, reason: str, data: bytes) -> bytes:
    w = _W()
    _header(w, sim_ns)
    w.string(reason, pr.DEFAULT_MAX_TEXT)
    w.put("I", len(data))
    w.b += data
    return bytes(w.b)


def _read_header(r: _R) -> int:
    sec, = r.get("i")
    nsec, = r.get("I")
    r.string(1 << 20)
    return sec * 1_000_000_000 + nsec


def decode_event(data) -> pr.Event:
    r = _R(data)
    sim = _read_header(r)
    kind, = r.get("H")
    r.string(pr.DEFAULT_MAX_TEXT)
    (seq,), (step,), (wall,) = r.get("Q"), r.get("Q"), r.get("q")
    src = r.string(pr.DEFAULT_MAX_TEXT)
    text = r.string(pr.DEFAULT_MAX_TEXT)
    return pr.Event(kind, text, src, seq, step, sim, wall)


def decode_meta(data) -> pr.RunMeta:
    r = _R(data)
    sim = _read_header(r)
    (seq,), (step,), (wall,) = r.get("Q"), r.get("Q"), r.get("q")
    return pr.RunMeta(json.loads(r.string(1 << 30)), seq, step, sim, wall)


def decode_malformed(data) -> tuple[int, str, bytes]:
    r = _R(data)
    sim = _read_header(r)
    reason = r.string(pr.DEFAULT_MAX_TEXT)
    n, = r.get("I")
    return sim, reason, bytes(r.d[r.p:r.p + n])


def decode_vectors(rtype: str, n: int, datas) -> np.ndarray:
    """Structured array (``rec_dtype``) of recorded vector / timing payloads of one channel."""
    dt = rec_dtype(rtype, n)
    buf = b"".join(datas)
    if len(buf) != dt.itemsize * len(datas):
        raise ValueError(f"{rtype}: payload sizes differ from {dt.itemsize} bytes")
    return np.frombuffer(buf, dt)


def wire_payloads(rtype: str, a: np.ndarray, peer: bytes = NO_PEER) -> list[bytes]:
    """The wire bytes (docs/protocol.md §3) of recorded SensorSample / CurrentCommand rows, sent
    by ``peer`` (:func:`peer_ids`): exact up to the mac, which is zero (the module docstring)."""
    wt = WIRE_OF[rtype]
    n = a.dtype["v"].shape[0] if a.dtype["v"].shape else 1
    w = np.zeros(len(a), wire_dtype(wt, n))
    w["encap"] = ENCAP_V4
    w["version"] = PROTOCOL_VERSION
    w["seq"], w["step"], w["sim"] = a["seq"], a["step"], stamp_ns(a["sec"], a["nanosec"])
    w["pub"], w["count"], w["v"] = a["pub"], n, a["v"]
    w["peer"] = np.frombuffer(peer, f"V{PEER_LEN}")[0]       # "mac" stays zero
    if wt == "CurrentCommand":
        w["recv"] = a["recv"]
    return _split(w.tobytes(), w.dtype.itemsize, len(a))


def layout(schema) -> str | None:
    """The recorded type of a channel's schema (``SensorSampleStamped``, ...), ``"wire:<Type>"`` for a
    channel of the earlier layout (wire bytes verbatim), None for anything else."""
    if schema is None or not schema.name.startswith(f"{pr.PACKAGE}/msg/"):
        return None
    t = schema.name.rsplit("/", 1)[1]
    if t in WIRE_OF or t == MALFORMED:
        return t
    if t in pr.MSG_DEFS:
        return f"wire:{t}"
    return None


def axes_of(channel) -> list[str] | None:
    try:
        return json.loads(channel.metadata.get("axis_names", "null"))
    except ValueError:
        return None


def wire_of(schema, data, peer: bytes = NO_PEER) -> bytes | None:
    """The wire bytes of one recorded SensorSample / CurrentCommand message, sent by ``peer``
    (the payload itself for the earlier layout, versions 1 and 2 upgraded; the verbatim payload of
    a Malformed one); None for other types."""
    lay = layout(schema)
    if lay in (SENSORS, CURRENTS):
        n = (len(data) - (44 if lay == SENSORS else 52)) // 8
        return wire_payloads(lay, decode_vectors(lay, n, [data]), peer)[0]
    if lay == MALFORMED:
        return decode_malformed(data)[2]
    if lay is not None and lay.startswith("wire:"):
        return upgrade(lay[5:], data, peer)
    return None
