"""A law in a process of its own: the thin client that joins a run as its controller.

    from ambhil.bridge.process.law_client import serve
    summary = serve(MyLaw, run_id="mine", connect="tcp/127.0.0.1:7447")

:func:`serve` is the controller process of ``ambhil controller`` with the user's law in place of
the scene's (docs/controllers.md, "A controller in its own process"): it declares itself, pairs
with the run's plant, waits for the plant's RunMeta and makes the law from it -- axis names,
rate, operating currents and the scene's controller, sensor and amplifier
(:func:`runner_from_meta`) -- between the same sensor and amplifier emulation as ``ambhil run``
(:class:`ambhil.controller.law_runner.LawRunner`), then answers every sample
(:func:`ambhil.bridge.process.controller_node.run_controller`: seq rules, restarts, the end of
the run).  The law needs no scene file: the plant announces everything.

The law is a class or any callable ``factory(meta) -> law`` (controller/law.py), or a name
``FILE.py:CLASS`` / ``FILE.so`` / ``FILE.fmu`` (controller/law_loader.py, relative to the
working directory).
"""
from __future__ import annotations

import math
import os
import signal
import threading
import tomllib

import numpy as np

from ambhil.controller import discrete as dc
from ambhil.controller import hardware as hw
from ambhil.controller.law import LawError
from ambhil.controller.law_loader import law_factory, resolve
from ambhil.controller.law_runner import LawRunner
from ambhil.controller.params import Amplifier, ControllerParams, Sensor
from ambhil.loop.scene_controller import LAW_TABLES, sensor_amplifier
from ambhil.bridge import protocol as pr
from ambhil.bridge.process.config import ControllerNodeConfig
from ambhil.bridge.process.controller_node import ControllerNode
from ambhil.bridge.process.events import Fault
from ambhil.bridge.process.startup import Presence


def serve(law, run_id: str, connect=None, listen=None, *, name: str | None = None,
          start_timeout: float = 30.0, sample_timeout: float = 300.0, secure: str | None = None,
          cpus: list[int] | None = None, stop=None, secret: bytes | None = None,
          insecure: bool = False) -> dict:
    """Join run ``run_id`` as its controller with ``law`` and answer the plant until the run
    ends; returns the controller's summary (``fault``: None for a clean run, else the one line
    why; ``steps``: samples answered).

    ``connect``: the plant's endpoint(s) (``tcp/HOST:PORT``; ``ambhil run --controller``'s
    ``{connect}`` gives two, the plant's and the recorder's); ``listen``: an endpoint of this
    process (default: ephemeral ones).  ``name``: how faults name the law (default its class
    or file name).  ``start_timeout``: s the plant may be absent; ``sample_timeout``: s a live
    but silent plant is waited for.  ``secure``: the certificate folder of a ``--secure`` run
    (`ambhil certs`).  ``secret``: the run's 32-byte secret (``ambhil.bridge.protocol.auth.
    read_key_file``; ``ambhil run`` puts the path of its key file in ``AMBHIL_KEY_FILE``, which
    is read when ``secret`` is None; docs/protocol.md 5.3); ``insecure``: no key, said so.
    ``cpus``: pin the process.  ``stop``: a callable or event that ends the
    run early.  SIGTERM ends it as Ctrl-C does (a fault ``interrupted``, with its summary)."""
    factory, label = _factory(law, name)
    if secure:
        from ambhil.bridge.process.security import configure
        configure(secure, "controller", run_id)
    if secret is None and os.environ.get("AMBHIL_KEY_FILE"):
        from ambhil.bridge.protocol.auth import read_key_file
        secret = read_key_file(os.environ["AMBHIL_KEY_FILE"])
    cfg = ControllerNodeConfig(run_id=run_id, connect=connect, listen=listen, cpus=cpus,
                               start_timeout=start_timeout, sample_timeout=sample_timeout,
                               secret=secret, insecure=insecure)
    presence = Presence.open(run_id, "controller", listen=listen, connect=connect, secret=secret,
                             insecure=insecure)
    old = _term_as_interrupt()
    try:
        presence.progress(f"law {label}; loading the hardware kernels")
        warm_up()
        node = LawNode(lambda info: runner_from_meta(factory, info, label), cfg, stop=stop,
                       presence=presence)
        try:
            return node.run()
        finally:
            close = getattr(node.controller, "close", None)     # the law's close(), once
            if close is not None:
                close()
    finally:
        presence.close(session_too=True)
        if old is not None:
            signal.signal(signal.SIGTERM, old)


def runner_from_meta(factory, info: dict, name: str = "law", base_dir: str = ".") -> LawRunner:
    """The :class:`LawRunner` of ``factory`` for the run a plant announced: ``info`` is RunMeta's
    JSON object (docs/protocol.md §5.2: ``axis_names``, ``controller`` with its ``continuous``
    gains and hardware, ``i_op``, ``rate_hz``; ``scene_toml`` adds the amplifier's slew limit and
    the ``[controller]`` table as written, the law's ``meta.controller`` / ``meta.params``).
    The same runner as ``ambhil run --law`` makes from the scene."""
    c = info.get("controller")
    if not isinstance(c, dict) or not isinstance(c.get("continuous"), dict):
        raise LawError(f"law {name}: RunMeta has no controller.continuous (the scene's gains and "
                       f"hardware; an ambhil plant publishes them): cannot make the law")
    k = c["continuous"]
    axes = info.get("axis_names")
    i_op = c.get("i_op")
    if not isinstance(axes, list) or not isinstance(i_op, list) or len(axes) != len(i_op):
        raise LawError(f"law {name}: RunMeta axis_names {axes!r} do not match controller.i_op {i_op!r}")
    doc = _scene_doc(info, name)
    table = dict(doc.get("controller", {}))
    params = table.pop("params", {})
    lim = k.get("current_limit")
    try:
        slew = sensor_amplifier(doc, "RunMeta scene_toml", ())[1].slew_rate if doc else math.inf
        cfg = ControllerParams(
            kp=float(k["kp"]), ki=float(k["ki"]), kd=float(k["kd"]),
            derivative_filter=float(k["derivative_filter_s"]), sample_rate=float(c["rate_hz"]),
            discretisation=str(c["discretisation"]), delay_samples=int(c["delay_samples"]),
            anti_windup=bool(c["anti_windup"]),
            sensor=Sensor(float(k["sensor_gain"]), float(k["sensor_time_constant_s"])),
            amplifier=Amplifier(float(k["amplifier_gain"]), float(k["amplifier_time_constant_s"]),
                                math.inf if lim is None else float(lim), slew),
            kind=str(table.get("kind", "pid")), table=table,
            law_params=params if isinstance(params, dict) else {},
            lti={t: table[t] for t in LAW_TABLES if t in table})
    except (KeyError, TypeError, ValueError) as e:
        raise LawError(f"law {name}: RunMeta controller is incomplete: {type(e).__name__}: {e}") from None
    return LawRunner(factory, cfg, np.array(i_op, float), cfg.sample_rate, cfg.discretisation,
                     axes=[str(a) for a in axes], name=name, base_dir=base_dir)


def warm_up() -> None:
    """Load (or compile, the first time) the sensor and amplifier kernels before the run: the
    first sample is answered at once."""
    p = hw.hardware_params(dc.discretise(ControllerParams(kp=1.0)), math.inf, 1e-4)
    h, y, u = hw.initial_state(p, np.zeros(1)), np.zeros(1), np.zeros(1)
    hw.sensor_step(p, h, y, u)
    hw.amplifier_step(p, h, u, y)


class LawNode(ControllerNode):
    """The controller process (:class:`ControllerNode`) whose step object is made once paired,
    from the paired plant's RunMeta: ``make(info) -> step object``.  The plant publishes RunMeta
    after pairing, before its first sample; the samples wait in the subscription meanwhile."""

    def __init__(self, make, cfg: ControllerNodeConfig, **kw):
        super().__init__(_Unmade(), cfg, **kw)
        self.make = make
        self.info = None

    def _start(self):
        super()._start()        # pairs by the plant's RunMeta (sealed for this controller)
        self.info = info = self.meta
        n = info.get("n_axes")
        if not isinstance(n, int) or not 0 < n <= pr.DEFAULT_MAX_AXES:
            raise Fault(f"RunMeta n_axes {n!r} is not a number of axes")
        try:
            self.controller = runner = self.make(info)
        except LawError as e:                   # the law could not be made: the run's fault
            raise Fault(str(e)) from None
        n = self.n = int(runner.n_axes)
        self.sc, self.cc = pr.SensorCodec(n), pr.CurrentCodec(n)
        self.sc.peer, self.cc.me = self.peer, self.me
        runner.reset()
        self.presence.progress(f"RunMeta: {n} axes at {runner.sample_rate:g} Hz, mode "
                               f"{info.get('mode')}, {info.get('n_steps')} steps; law made")


class _Unmade:
    """The step object before RunMeta: no axes yet, nothing to reset."""
    n_axes = 1

    def reset(self):
        pass


def _factory(law, name):
    if isinstance(law, (str, os.PathLike)):
        factory, label = law_factory(resolve(str(law), os.getcwd()))
        return factory, name or label
    if not callable(law):
        raise LawError(f"law {law!r}: not a law (a class, a factory(meta), or FILE.py:CLASS, "
                       f"FILE.so, FILE.fmu)")
    return law, name or getattr(law, "__name__", type(law).__name__)


def _scene_doc(info: dict, name: str) -> dict:
    text = info.get("scene_toml")
    if not text:
        return {}
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise LawError(f"law {name}: RunMeta scene_toml is not TOML: {e}") from None


def _term_as_interrupt():
    """SIGTERM as Ctrl-C (the node ends with its summary); the previous handler, or None off
    the main thread."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def _term(signum, frame):
        raise KeyboardInterrupt
    return signal.signal(signal.SIGTERM, _term)
