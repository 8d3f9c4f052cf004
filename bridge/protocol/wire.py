"""Hot-path codec for the per-period messages (SensorSample, CurrentCommand).

One call per message between ``recv()`` and ``put()``:

- ``decode_sensor(data, expect_seq, out, peer)`` / ``decode_current(data, expect_seq, out,
  peer)``: if ``data`` is a well-formed, all-finite message for ``len(out)`` axes whose
  sequence number is ``expect_seq`` and whose sender id (the last 16 bytes, protocol
  version 2) is ``peer``, copy its vector into ``out`` (a writable float64 buffer, e.g.
  :meth:`ambhil.bridge.protocol.SensorCodec.view`) and return ``(seq, step, sim_time_ns,
  publish_wall_ns)`` (sensor) or ``(seq, step, sim_time_ns, recv_wall_ns,
  publish_wall_ns)`` (current).  Otherwise return None and leave ``out`` untouched: the
  caller's validating slow path (``protocol.*Codec.unpack_into``) then classifies the
  message (foreign, malformed, non-finite, duplicate, gap, wake-up).
- ``encode_sensor(vec, seq, step, sim_time_ns, publish_wall_ns, me)`` /
  ``encode_current(vec, seq, step, sim_time_ns, recv_wall_ns, publish_wall_ns, me)``: the
  message bytes, ending with the sender id ``me`` (16 bytes), or None if ``vec`` holds a non-finite value (never sent).

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
import math
import os
import struct

import numpy as np

from ambhil.bridge.protocol.messages import ENCAP, PEER_LEN, PROTOCOL_VERSION

_isf = math.isfinite
_structs: dict = {}


def _get(nt: int, n: int):
    s = _structs.get((nt, n))
    if s is None:
        q = "q" * nt
        s = _structs[(nt, n)] = (struct.Struct(f"<4sH6xQQq{q}I4x{n}d{PEER_LEN}s"),
                                 struct.Struct(f"={n}d"))
    return s


def _py_decode(nt: int):
    ci = 5 + nt

    def decode(data, expect_seq, out, peer):
        if len(peer) != PEER_LEN:
            raise TypeError(f"decode(): peer must be {PEER_LEN} bytes")
        n = out.nbytes // 8 if isinstance(out, memoryview) else memoryview(out).nbytes // 8
        full, vec = _get(nt, n)
        if len(data) != full.size:
            return None
        h = full.unpack(data)
        if (h[2] != expect_seq or h[0] != ENCAP or h[1] != PROTOCOL_VERSION or h[ci] != n
                or h[-1] != peer):
            return None
        v = h[ci + 1:-1]
        s = sum(v)                     # a finite sum <=> all finite (else check each)
        if s - s != 0.0 and not all(map(_isf, v)):
            return None
        vec.pack_into(out, 0, *v)
        return h[2:ci]
    return decode


def _py_encode(nt: int):
    def encode(vec, seq, step, sim_time_ns, *rest):
        if len(rest) != nt + 1:
            raise TypeError(f"encode takes {5 + nt} arguments ({4 + len(rest)} given)")
        times, me = rest[:nt], rest[nt]
        if not isinstance(me, bytes) or len(me) != PEER_LEN:
            raise ValueError(f"encode(): the sender id must be {PEER_LEN} bytes")
        mv = vec if isinstance(vec, memoryview) else memoryview(vec)
        full, vs = _get(nt, mv.nbytes // 8)
        v = vs.unpack(mv)
        s = sum(v)
        if s - s != 0.0 and not all(map(_isf, v)):
            return None
        return full.pack(ENCAP, PROTOCOL_VERSION, seq, step, sim_time_ns, *times, len(v), *v, me)
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
