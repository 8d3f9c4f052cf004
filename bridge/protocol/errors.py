"""Validation errors of the wire protocol: one class per stable reason code
(docs/protocol.md, section 4)."""
from __future__ import annotations

from ambhil.bridge.protocol.messages import ENCAP, PROTOCOL_VERSION

class ProtocolError(ValueError):
    """A message failed validation.  ``reason`` is a short stable code."""
    reason = "protocol"

    def __init__(self, detail: str = ""):
        super().__init__(f"{self.reason}: {detail}" if detail else self.reason)
        self.detail = detail


class TruncatedError(ProtocolError):
    reason = "truncated"


class EncapsulationError(ProtocolError):
    reason = "encapsulation"


class VersionError(ProtocolError):
    reason = "version"


class LengthError(ProtocolError):
    reason = "length"


class OversizeError(ProtocolError):
    reason = "oversize"


class AxisCountError(ProtocolError):
    reason = "axes"


class NonFiniteError(ProtocolError):
    reason = "nonfinite"


class StringError(ProtocolError):
    reason = "string"


class SequenceError(ProtocolError):
    reason = "sequence"


class ForeignError(ProtocolError):
    """Sent by a process the receiver is not paired with (a SensorSample / CurrentCommand that
    does not end with the paired peer id, docs/protocol.md section 5.1)."""
    reason = "peer"


class AuthError(ProtocolError):
    """A message whose MAC is wrong or missing: not sent by a holder of the run's key (for the
    paired peer's id, docs/protocol.md section 5.3).  Not :class:`ambhil.bridge.protocol.auth.AuthError`
    (an unusable key file)."""
    reason = "auth"


REASONS = tuple(c.reason for c in (TruncatedError, EncapsulationError, VersionError, LengthError,
                                   OversizeError, AxisCountError, NonFiniteError, StringError,
                                   SequenceError, ForeignError, AuthError))


def check_header(data, min_len: int) -> None:
    """Raise the reason a message shorter than ``min_len`` or with a foreign header fails."""
    if len(data) < min_len:
        raise TruncatedError(f"{len(data)} bytes < minimum {min_len}")
    if data[:4] != ENCAP:
        raise EncapsulationError(f"header {bytes(data[:4]).hex()} != 00010000 (CDR little endian)")
    v = data[4] | (data[5] << 8)
    if v != PROTOCOL_VERSION:
        raise VersionError(f"version {v} != {PROTOCOL_VERSION}")
