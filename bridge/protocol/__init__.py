"""ambhil wire protocol: CDR (XCDR1, little endian) encodings of ros2msg types.

The payload on the wire is exactly the serialised message.  The recorder writes each
one to MCAP in a stamped form (bridge/recording/layout.py: profile ros2, std_msgs/Header in simulation
time, named fields) that Foxglove and rerun read natively, and from which the wire bytes are
restored exactly.  See docs/protocol.md for the byte layouts, key expressions and the behaviour
on bad input.

Every message starts with the same 32-byte prefix (offsets relative to the
start of the CDR body, i.e. after the 4-byte encapsulation header
``00 01 00 00``)::

    0  uint16 version      (Event: offset 2 holds uint16 kind)
    8  uint64 seq
    16 uint64 step
    24 int64  sim_time_ns

This module is the one name space of the protocol (``from bridge import protocol as pr``);
the parts live in one module per concept:

- :mod:`ambhil.bridge.protocol.messages`: constants, ros2msg schemas, flag bits, event kinds, message types;
- :mod:`ambhil.bridge.protocol.errors`: the validation errors (one per reason code);
- :mod:`ambhil.bridge.protocol.auth`: the run's keys and MACs (seals of the loop codecs,
  attachments of the other messages, pairing proofs);
- :mod:`ambhil.bridge.protocol.keys`: key expressions of a run;
- :mod:`ambhil.bridge.protocol.vector_codec`: SensorSample / CurrentCommand codecs (the loops' validating
  slow path; the fast path is :mod:`ambhil.bridge.protocol.wire`, one C call per message, same bytes);
- :mod:`ambhil.bridge.protocol.cdr`: the generic CDR writer/reader and the Event / RunMeta / Timing codecs.
"""
from __future__ import annotations

from ambhil.bridge.protocol.cdr import (decode_event, decode_meta, decode_timing, encode_event, encode_meta,  # noqa: F401
                  encode_timing)
from ambhil.bridge.protocol.keys import (EVENT_ROLES, TOPIC_TYPES, Keys, event_key, keys,  # noqa: F401
                                       message_type_for_key, pair_key, topic_of)
from ambhil.bridge.protocol.messages import (DEFAULT_MAX_AXES, DEFAULT_MAX_BATCH, DEFAULT_MAX_TEXT, ENCAP,  # noqa: F401
                       ENCAP_LEN, EVENT_KIND_OFFSET, FLAG_HELD, FLAG_LATE_WAKE, FLAG_WARMUP,
                       MAC_LEN, MSG_DEFS, NO_KEY, NO_PEER, PACKAGE, PEER_LEN, PROTOCOL_VERSION,
                       SEAL_LEN, SEQ_OFFSET, SIM_TIME_OFFSET, STEP_OFFSET, CurrentCommand, Event,
                       EventKind, RunMeta, SensorSample, Timing, schema_name, split_seal)
from ambhil.bridge.protocol.errors import (REASONS, AuthError, AxisCountError, EncapsulationError, ForeignError,  # noqa: F401
                              LengthError, NonFiniteError, OversizeError, ProtocolError,
                              SequenceError, StringError, TruncatedError, VersionError,
                              check_header)
from ambhil.bridge.protocol.vector_codec import (CurrentCodec, SensorCodec, decode_current, decode_sensor,  # noqa: F401
                           encode_current, encode_sensor, reseal)


def decode_any(key_or_type: str, data):
    """Decode by key expression (``ambhil/<run>/plant/sensors``) or type name."""
    t = key_or_type if key_or_type in MSG_DEFS else message_type_for_key(key_or_type)
    if t == "SensorSample":
        return decode_sensor(data)
    if t == "CurrentCommand":
        return decode_current(data)
    if t == "Event":
        return decode_event(data)
    if t == "RunMeta":
        return decode_meta(data)
    if t == "Timing":
        return decode_timing(data)
    raise ValueError(f"no message type for {key_or_type!r}")
