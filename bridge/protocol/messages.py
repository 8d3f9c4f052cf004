"""ambhil message definitions: protocol constants, the ros2msg schemas, flag bits and event
kinds, and the Python types the codecs produce (docs/protocol.md, section 3).

The byte layouts live in the codecs: :mod:`ambhil.bridge.protocol.vector_codec` (SensorSample,
CurrentCommand) and :mod:`ambhil.bridge.protocol.cdr` (Event, RunMeta, Timing)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ambhil.bridge.protocol import auth

PROTOCOL_VERSION = 3                 # 3: a MAC ends SensorSample / CurrentCommand (docs/protocol.md 5.3)
ENCAP = b"\x00\x01\x00\x00"          # CDR_LE encapsulation, options 0
ENCAP_LEN = 4
DEFAULT_MAX_AXES = 64                # largest accepted axis count
DEFAULT_MAX_TEXT = 64 * 1024         # largest accepted string (bytes, without NUL)
DEFAULT_MAX_BATCH = 100_000          # largest accepted Timing batch
SIM_TIME_OFFSET = ENCAP_LEN + 24     # absolute offset of int64 sim_time_ns in every message
SEQ_OFFSET = ENCAP_LEN + 8           # absolute offset of uint64 seq in every message
STEP_OFFSET = ENCAP_LEN + 16
EVENT_KIND_OFFSET = ENCAP_LEN + 2    # absolute offset of uint16 kind in Event
PEER_LEN = 16                        # bytes of a peer id (bridge/process/pairing.py)
NO_PEER = bytes(PEER_LEN)            # the id of a sender that has none (in-process, tests)
MAC_LEN = 16                         # bytes of a MAC: keyed BLAKE2b-128 (auth.py)
SEAL_KEY_LEN = 32                    # bytes of a topic key
SEAL_LEN = PEER_LEN + SEAL_KEY_LEN   # a codec's seal: peer id || topic key (auth.RunAuth.seal)
NO_KEY = bytes(SEAL_KEY_LEN)         # the key of a seal given as a bare 16-byte id
assert (MAC_LEN, SEAL_LEN, PEER_LEN) == (auth.MAC_LEN, auth.SEAL_LEN, auth.ID_LEN)

PACKAGE = "ambhil_msgs"

MSG_DEFS: dict[str, str] = {
    "SensorSample": (
        "# plant -> controller, one per controller period\n"
        "uint16 version\nuint64 seq\nuint64 step\nint64 sim_time_ns\nint64 publish_wall_ns\n"
        "float64[] displacement\n"
        "uint8[16] peer              # the sending plant's peer id (docs/protocol.md 5.1)\n"
        "uint8[16] mac               # keyed BLAKE2b-128 of every byte before it (docs/protocol.md 5.3)\n"),
    "CurrentCommand": (
        "# controller -> plant, answers the SensorSample with the same seq\n"
        "uint16 version\nuint64 seq\nuint64 step\nint64 sim_time_ns\n"
        "int64 recv_wall_ns\nint64 publish_wall_ns\nfloat64[] current\n"
        "uint8[16] peer              # the sending controller's peer id (docs/protocol.md 5.1)\n"
        "uint8[16] mac               # keyed BLAKE2b-128 of every byte before it (docs/protocol.md 5.3)\n"),
    "Event": (
        "uint16 version\nuint16 kind\nuint64 seq\nuint64 step\nint64 sim_time_ns\n"
        "int64 wall_ns\nstring source\nstring text\n"),
    "RunMeta": (
        "uint16 version\nuint64 seq\nuint64 step\nint64 sim_time_ns\nint64 wall_ns\n"
        "string json\n"),
    "Timing": (
        "# plant-side timing for steps step..step+n-1 (one batch)\n"
        "uint16 version\nuint64 seq\nuint64 step\nint64 sim_time_ns\nint64 period_ns\n"
        "uint64 overruns\nint64[] wake_lateness_ns\nint64[] rtt_ns\nint64[] tet_ns\n"
        "uint8[] flags\n"),
}


def schema_name(msg_type: str) -> str:
    return f"{PACKAGE}/msg/{msg_type}"


def split_seal(value, what: str = "seal") -> tuple[bytes, bytes]:
    """``(peer id, topic key)`` of a codec's seal: 48 bytes = id || key, or a bare 16-byte id,
    which means that id with the all-zero key (:data:`NO_KEY`: tests, in-process runs).
    ValueError naming ``what`` for any other length."""
    b = bytes(value)
    if len(b) == SEAL_LEN:
        return b[:PEER_LEN], b[PEER_LEN:]
    if len(b) == PEER_LEN:
        return b, NO_KEY
    raise ValueError(f"{what}: a peer id is {PEER_LEN} bytes and a seal {SEAL_LEN} (id + key), "
                     f"got {len(b)}")


# Timing.flags bits
FLAG_HELD = 1          # no valid reply at the deadline: last currents held (overrun)
FLAG_LATE_WAKE = 2     # plant woke after the next deadline (overrun)
FLAG_WARMUP = 4        # step belongs to the warm-up, excluded from statistics


class EventKind:
    """Event.kind codes (uint16).  Names are stable; codes never reused."""
    INFO = 0
    RUN_START = 1
    RUN_END = 2
    FAULT = 3
    REJECTED = 4        # malformed message dropped (text = reason code + detail)
    DUPLICATE = 5       # seq already seen / stale reply
    GAP = 6             # seq jumped (missing messages)
    OVERRUN = 7         # deadline missed, last currents held
    PEER_LOST = 8       # liveliness DELETE of a peer
    TIMEOUT = 9         # no message within the watchdog timeout
    WARNING = 10        # non-fatal condition (e.g. plant Newton iteration not converged)
    FAULT_INJECTED = 11  # a scheduled fault starts or ends (text: JSON {kind, axis, params, phase})
    NAMES = {0: "INFO", 1: "RUN_START", 2: "RUN_END", 3: "FAULT", 4: "REJECTED",
             5: "DUPLICATE", 6: "GAP", 7: "OVERRUN", 8: "PEER_LOST", 9: "TIMEOUT",
             10: "WARNING", 11: "FAULT_INJECTED"}



# --------------------------------------------------------------------------- types
class SensorSample(NamedTuple):
    seq: int
    step: int
    sim_time_ns: int
    publish_wall_ns: int
    displacement: np.ndarray
    peer: bytes = NO_PEER          # the sender's peer id (docs/protocol.md 5.1)
    mac: bytes = bytes(MAC_LEN)    # its MAC (docs/protocol.md 5.3)


class CurrentCommand(NamedTuple):
    seq: int
    step: int
    sim_time_ns: int
    recv_wall_ns: int
    publish_wall_ns: int
    current: np.ndarray
    peer: bytes = NO_PEER
    mac: bytes = bytes(MAC_LEN)


@dataclass
class Event:
    kind: int
    text: str = ""
    source: str = ""
    seq: int = 0
    step: int = 0
    sim_time_ns: int = 0
    wall_ns: int = 0

    @property
    def kind_name(self) -> str:
        return EventKind.NAMES.get(self.kind, f"KIND{self.kind}")


@dataclass
class RunMeta:
    info: dict
    seq: int = 0
    step: int = 0
    sim_time_ns: int = 0
    wall_ns: int = 0


@dataclass
class Timing:
    step: int
    sim_time_ns: int
    period_ns: int
    overruns: int
    wake_lateness_ns: np.ndarray
    rtt_ns: np.ndarray
    tet_ns: np.ndarray
    flags: np.ndarray
    seq: int = 0
