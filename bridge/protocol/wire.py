"""Hot-path codec for the per-period messages (SensorSample, CurrentCommand).

One call per message between ``recv()`` and ``put()``:

- ``decode_sensor(data, expect_seq, out, peer_seal)`` / ``decode_current(data, expect_seq, out,
  peer_seal)``: if ``data`` is a well-formed, all-finite message for ``len(out)`` axes whose
  sequence number is ``expect_seq``, whose sender id (bytes [-32:-16], protocol version 3) is
  ``peer_seal``'s and whose MAC (the last 16 bytes) is valid under ``peer_seal``'s key, copy
  its vector into ``out`` (a writable float64 buffer, e.g.
  :meth:`ambhil.bridge.protocol.SensorCodec.view`) and return ``(seq, step, sim_time_ns,
  publish_wall_ns)`` (sensor) or ``(seq, step, sim_time_ns, recv_wall_ns,
  publish_wall_ns)`` (current).  Otherwise return None and leave ``out`` untouched: the
  caller's validating slow path (``protocol.*Codec.unpack_into``) then classifies the
  message (foreign, auth, malformed, non-finite, duplicate, gap, wake-up).
- ``encode_sensor(vec, seq, step, sim_time_ns, publish_wall_ns, me_seal)`` /
  ``encode_current(vec, seq, step, sim_time_ns, recv_wall_ns, publish_wall_ns, me_seal)``: the
  message bytes, ending with ``me_seal``'s id and the MAC under its key, or None if ``vec``
  holds a non-finite value (never sent).

A seal is 48 bytes, peer id (16) || topic key (32) (:meth:`ambhil.bridge.protocol.auth.RunAuth.seal`,
``peer_seal``); a bare 16-byte id means that id with the all-zero key.  The MAC is keyed
BLAKE2b-128 of every byte before it (docs/protocol.md 5.3): hashlib here, _blake2b.h in C.

The functions come from the C extension ``ambhil.bridge.protocol._wire`` (built by ``pip install``) when it
is importable, else from the pure-Python twin below; ``NATIVE`` says which.  Both produce
bytes identical to :class:`ambhil.bridge.protocol.SensorCodec` / ``CurrentCodec``
(tests/test_protocol.py).  ``AMBHIL_PURE_WIRE=1`` forces the Python twin (benchmarks).

The lockstep loops' ordinary steps in C, where built: ``PlantLockstep`` and
``ControllerLockstep`` (None without the extension; the Python loops of
bridge/process/plant_lockstep.py and bridge/process/controller_node.py are their twins).  Each
is made with its fields by name (``PlantLockstep(y_mv=..., advance=..., ...)``, the field
list with each field's meaning in ``help()``); ``run()`` runs steps until one needs Python
and returns the :class:`LoopCode` saying why, the same enum as the C one (the extension
exports it as ``LOOP_DONE`` ... ``LOOP_NONFINITE``; tests/test_protocol.py checks they agree).

Why C: on the lockstep loop plant and controller share a core, and each CPython object
created per message costs several times its warm CPU time there (docs/hil.md, "Lockstep
speed").
"""
from __future__ import annotations

import enum
import hashlib
import hmac
import math
import os
import struct

import numpy as np

from ambhil.bridge.protocol.messages import ENCAP, MAC_LEN, PEER_LEN, PROTOCOL_VERSION, split_seal

_isf = math.isfinite
_equal = hmac.compare_digest
_structs: dict = {}
_seals: dict = {}
_SEALS_MAX = 64            # seals kept ready (a process uses one or two per direction)


def _get(nt: int, n: int):
    s = _structs.get((nt, n))
    if s is None:
        q = "q" * nt
        s = _structs[(nt, n)] = (struct.Struct(f"<4sH6xQQq{q}I4x{n}d{PEER_LEN}s{MAC_LEN}s"),
                                 struct.Struct(f"={n}d"),
                                 struct.Struct(f"<4sH6xQQq{q}I4x{n}d{PEER_LEN}s"))
    return s


def _seal(value, what: str):
    """``(id, keyed hasher)`` of a seal (16 or 48 bytes), kept ready like the C one's state
    after the key block; TypeError naming ``what`` for anything else."""
    r = _seals.get(value)
    if r is None:
        if not isinstance(value, bytes):
            raise TypeError(f"{what} must be bytes (a 16-byte peer id or a 48-byte seal)")
        try:
            pid, key = split_seal(value, what)
        except ValueError as e:
            raise TypeError(str(e)) from None
        if len(_seals) >= _SEALS_MAX:
            _seals.clear()
        r = _seals[value] = (pid, hashlib.blake2b(key=key, digest_size=MAC_LEN))
    return r


def _py_decode(nt: int):
    ci = 5 + nt

    def decode(data, expect_seq, out, peer_seal):
        pid, h0 = _seal(peer_seal, "decode(): peer_seal")
        n = out.nbytes // 8 if isinstance(out, memoryview) else memoryview(out).nbytes // 8
        full, vec, _ = _get(nt, n)
        if len(data) != full.size:
            return None
        h = full.unpack(data)
        if (h[2] != expect_seq or h[0] != ENCAP or h[1] != PROTOCOL_VERSION or h[ci] != n
                or h[-2] != pid):
            return None
        v = h[ci + 1:-2]
        s = sum(v)                     # a finite sum <=> all finite (else check each)
        if s - s != 0.0 and not all(map(_isf, v)):
            return None
        m = h0.copy()
        m.update(data[:-MAC_LEN])
        if not _equal(m.digest(), h[-1]):
            return None
        vec.pack_into(out, 0, *v)
        return h[2:ci]
    return decode


def _py_encode(nt: int):
    def encode(vec, seq, step, sim_time_ns, *rest):
        if len(rest) != nt + 1:
            raise TypeError(f"encode takes {5 + nt} arguments ({4 + len(rest)} given)")
        times, me_seal = rest[:nt], rest[nt]
        pid, h0 = _seal(me_seal, "encode(): me_seal")
        mv = vec if isinstance(vec, memoryview) else memoryview(vec)
        _, vs, body = _get(nt, mv.nbytes // 8)
        v = vs.unpack(mv)
        s = sum(v)
        if s - s != 0.0 and not all(map(_isf, v)):
            return None
        b = body.pack(ENCAP, PROTOCOL_VERSION, seq, step, sim_time_ns, *times, len(v), *v, pid)
        m = h0.copy()
        m.update(b)
        return b + m.digest()
    return encode


py_decode_sensor, py_decode_current = _py_decode(1), _py_decode(2)
py_encode_sensor, py_encode_current = _py_encode(1), _py_encode(2)


class LoopCode(enum.IntEnum):
    """Why a C lockstep loop's ``run()`` handed the loop back to Python (``enum LoopCode`` of
    _lockstep.h, whose names carry a ``LOOP_`` prefix there)."""
    DONE = 0        # all steps done
    SLOW = 1        # the message in hand is not the fast-path one: the loop's slow path takes it
    FLUSH = 2       # (plant) a step done, a Timing or RecordBatch flush is due
    CHECK = 3       # the step object returned another output object (or a plant status is set)
    RAISED = 4      # the step object raised
    NONFINITE = 5   # the output to send is not finite (nothing was sent)


NATIVE = False
decode_sensor, decode_current = py_decode_sensor, py_decode_current
encode_sensor, encode_current = py_encode_sensor, py_encode_current
PlantLockstep = ControllerLockstep = None
_wire = None
if os.environ.get("AMBHIL_PURE_WIRE", "") in ("", "0"):
    try:
        from ambhil.bridge.protocol import _wire
    except ImportError:          # extension not built: the Python twin is used
        _wire = None
    if _wire is not None:
        NATIVE = True
        decode_sensor, decode_current = _wire.decode_sensor, _wire.decode_current
        encode_sensor, encode_current = _wire.encode_sensor, _wire.encode_current
        PlantLockstep, ControllerLockstep = _wire.PlantLockstep, _wire.ControllerLockstep


def output_view(codec, a):
    """``(memoryview, key)`` for a step object's output vector: ``key`` is ``a`` itself when
    the view aliases it (a float64 C-contiguous array, typically a buffer the step object
    reuses), so the view can be reused while the object returns the same array; else None."""
    mv = codec.view(a)
    alias = isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous
    return mv, (a if alias else None)
