"""A controller FMU as a law: FMI 2.0 or 3.0 co-simulation, through fmpy (``--law FILE.fmu``).

``FMULaw(spec, meta)`` reads the model description, extracts the FMU to a temporary folder
(removed at :meth:`FMULaw.close`, or when the law is collected), instantiates it for
co-simulation and initialises it at ``t = 0``.  Each controller period, :meth:`FMULaw.step`
sets the inputs, calls ``doStep(t, T)`` and reads the outputs: the law's ``u`` is what the FMU
computed from the sensor outputs of that sample, as for any law (controller/law.py).

Which variable is which axis (``meta.axes``, e.g. ``A-x``):

* by name: the input of axis ``A-x`` is named ``y_A_x`` or ``A_x``, its output ``u_A_x`` or
  ``A_x``; names compare without case and without ``-``, ``_``, ``.`` and spaces (so ``yAx``,
  ``Y.A.X`` and ``A-x`` name it too);
* or by the scene's table ``[controller.fmu]``: ``inputs = [...]`` and ``outputs = [...]``, one
  variable name per axis in the loop's order.

Every input must be fed (an input that no axis names is an error); outputs beyond the axes are
ignored.  Inputs and outputs are Real (FMI 2.0) / Float64 (FMI 3.0).

Parameters: each key of ``[controller.params]`` must name a parameter of the FMU (causality
``parameter``) and is set before initialisation (a number for Real / Float, an integer for
Integer / Int / Enumeration, true or false for Boolean, a string for String).  A parameter
``u_op_<axis>`` (``u_op_A_x``) the FMU has and the table does not set gets the axis's
operating-point amplifier input ``meta.u_op``.

Errors are one line naming the FMU: a file that is not an FMU (not a zip, no or a broken
modelDescription.xml), an FMU for model exchange only, no binary for this platform, a variable
that is missing (with the FMU's real inputs and outputs), a parameter it does not have; a failing
``doStep`` raises :class:`FMIError` with the status and the FMU's last log message, which the
:class:`ambhil.controller.law_runner.LawRunner` reports with the law's name and the time.
"""
from __future__ import annotations

import ctypes
import os
import re
import shutil
import weakref
from collections import deque
from pathlib import Path

import numpy as np

from .law import LawError, LawMeta

STATUS = ("OK", "Warning", "Discard", "Error", "Fatal", "Pending")
INPUT_PREFIX, OUTPUT_PREFIX = "y", "u"
REAL = {"Real", "Float64"}
INTEGER = {"Integer", "Enumeration", "Int8", "UInt8", "Int16", "UInt16", "Int32", "UInt32", "Int64", "UInt64"}


class FMIError(RuntimeError):
    """An FMI call of a running FMU returned a status other than OK (its message: the call, the
    status, the FMU's last log message)."""


def _fmpy(name: str):
    try:
        import fmpy
    except ImportError:
        raise LawError(f"law {name}: FMU laws need fmpy: pip install 'ambhil[fmu]'") from None
    return fmpy


def _norm(s: str) -> str:
    return re.sub(r"[-_.\s]", "", s).lower()


class _Log:
    """The FMU's last log messages (its logger callback writes here)."""

    def __init__(self):
        self.lines = deque(maxlen=4)

    def last(self) -> str:
        return f" (the FMU's log: {self.lines[-1]})" if self.lines else ""


# FMI 2.0's logger is variadic: fmpy's native proxy formats the message and calls one Python
# function for every FMU of the process, which finds the instance's log by its environment.
_LOGS2: dict[int, _Log] = {}
_NEXT_ENV = [1]


def _log2(env, instance, status, category, message):
    log = _LOGS2.get(env or 0)
    text = message.decode("utf-8", "replace") if message else ""
    if log is not None:
        log.lines.append(f"{STATUS[status] if 0 <= status < 6 else status}: {text}")
    else:                                   # an FMU fmpy's own callbacks made (the proxy is global)
        print(f"[{STATUS[status] if 0 <= status < 6 else status}] {text}")


_LOGGER2 = None


def _callbacks2(log: _Log):
    """An fmi2CallbackFunctions whose logger fills ``log``."""
    global _LOGGER2
    from fmpy import calloc, free
    from fmpy import fmi2
    if _LOGGER2 is None:
        _LOGGER2 = fmi2.fmi2CallbackLoggerTYPE(_log2)
    cb = fmi2.fmi2CallbackFunctions()
    cb.logger = _LOGGER2
    cb.allocateMemory = fmi2.fmi2CallbackAllocateMemoryTYPE(calloc)
    cb.freeMemory = fmi2.fmi2CallbackFreeMemoryTYPE(free)
    env = _NEXT_ENV[0]
    _NEXT_ENV[0] += 1
    cb.componentEnvironment = env
    _LOGS2[env] = log
    try:
        from fmpy.logging import addLoggerProxy
        addLoggerProxy(ctypes.byref(cb))
    except Exception:                       # no proxy: messages arrive unformatted
        pass
    return cb, env


class FMULaw:
    """A co-simulation FMU stepped once per controller period (module docstring)."""

    def __init__(self, spec: str, meta: LawMeta):
        self.name = name = Path(spec).name
        self.meta = meta
        fmpy = _fmpy(name)
        md = _model_description(fmpy, spec, name)
        if md.fmiVersion not in ("2.0",) and not str(md.fmiVersion).startswith("3."):
            raise LawError(f"law {name}: FMI {md.fmiVersion} is not supported (FMI 2.0 or 3.0 co-simulation)")
        if md.coSimulation is None:
            kinds = " and ".join(k for k, v in (("model exchange", md.modelExchange),
                                                ("scheduled execution", getattr(md, "scheduledExecution", None)))
                                 if v is not None) or "no interface"
            raise LawError(f"law {name}: an FMU for {kinds} only; a controller FMU must support co-simulation")
        self.fmi = 2 if md.fmiVersion == "2.0" else 3
        variables = {v.name: v for v in md.modelVariables}
        ins = [v for v in md.modelVariables if v.causality == "input"]
        outs = [v for v in md.modelVariables if v.causality == "output"]
        vin, vout = _mapping(name, meta, ins, outs, variables)
        self._params = _parameters(name, meta, variables, self.fmi)
        n = meta.n_axes
        self._vr_in = (ctypes.c_uint * n)(*(v.valueReference for v in vin))
        self._vr_out = (ctypes.c_uint * n)(*(v.valueReference for v in vout))
        self._yc = (ctypes.c_double * n)()
        self._uc = (ctypes.c_double * n)()
        self._y = np.ctypeslib.as_array(self._yc)
        self.u = np.ctypeslib.as_array(self._uc)
        self.period = float(meta.period)
        self._log = _Log()
        self._state = state = {"fmu": None, "dir": None, "env": None, "started": False}
        self._finalizer = weakref.finalize(self, _release, state)
        try:
            try:
                state["dir"] = fmpy.extract(spec)
            except Exception as e:
                raise LawError(f"law {name}: cannot extract the FMU: {_line(e)}") from None
            self._fmu = fmu = self._instantiate(fmpy, md, state)
            c = fmu.component
            if self.fmi == 2:
                self._set, self._get, self._do = fmu.fmi2SetReal, fmu.fmi2GetReal, fmu.fmi2DoStep
                self._set_args, self._get_args = (c, self._vr_in, n, self._yc), (c, self._vr_out, n, self._uc)
                self._do_args = (1,)        # noSetFMUStatePriorToCurrentPoint
            else:
                self._set, self._get, self._do = fmu.fmi3SetFloat64, fmu.fmi3GetFloat64, fmu.fmi3DoStep
                self._set_args = (c, self._vr_in, n, self._yc, n)
                self._get_args = (c, self._vr_out, n, self._uc, n)
                # eventHandlingNeeded, terminateSimulation, earlyReturn, lastSuccessfulTime
                self._flags = (ctypes.c_bool(), ctypes.c_bool(), ctypes.c_bool(), ctypes.c_double())
                self._do_args = (True, *(ctypes.byref(f) for f in self._flags))
            self._initialise()
        except BaseException:
            self._finalizer()               # nothing left behind: instance freed, folder removed
            raise
        self._fresh = True

    # -- life cycle -------------------------------------------------------------------------

    def _instantiate(self, fmpy, md, state):
        cs = md.coSimulation
        args = dict(guid=md.guid, modelIdentifier=cs.modelIdentifier, unzipDirectory=state["dir"],
                    instanceName=Path(self.name).stem)
        plat = fmpy.platform if self.fmi == 2 else fmpy.platform_tuple
        lib = f"binaries/{plat}/{cs.modelIdentifier}{fmpy.sharedLibraryExtension}"
        if not (Path(state["dir"]) / lib).is_file():
            raise LawError(f"law {self.name}: no binary for this platform ({lib}); the FMU has "
                           f"{', '.join(_platforms(state['dir'])) or 'none'}")
        cwd = os.getcwd()                   # fmpy changes into the binary's folder while loading it
        try:
            if self.fmi == 2:
                from fmpy.fmi2 import FMU2Slave
                fmu = FMU2Slave(**args)
                state["fmu"] = fmu
                cb, state["env"] = _callbacks2(self._log)
                fmu.instantiate(callbacks=cb, loggingOn=False)
            else:
                from fmpy.fmi3 import FMU3Slave
                fmu = FMU3Slave(**args)
                state["fmu"] = fmu
                log = self._log

                def log3(env, status, category, message):
                    log.lines.append(f"{STATUS[status] if 0 <= status < 6 else status}: "
                                     f"{message.decode('utf-8', 'replace') if message else ''}")
                fmu.instantiate(loggingOn=False, logMessage=log3)
        except LawError:
            raise
        except Exception as e:
            raise LawError(f"law {self.name}: cannot instantiate the FMU for co-simulation: "
                           f"{_line(e)}{self._log.last()}") from None
        finally:
            os.chdir(cwd)
        return fmu

    def _initialise(self) -> None:
        """Parameters, then initialisation at t = 0 (FMI 2.0: setupExperiment first)."""
        fmu = self._fmu
        try:
            if self.fmi == 2:
                fmu.setupExperiment(startTime=0.0)
            for setter, vr, value in self._params:
                getattr(fmu, setter)([vr], [value])
            if self.fmi == 2:
                fmu.enterInitializationMode()
                fmu.exitInitializationMode()
            else:
                fmu.enterInitializationMode(startTime=0.0)
                fmu.exitInitializationMode()
        except Exception as e:
            raise LawError(f"law {self.name}: initialisation failed: {_line(e)}{self._log.last()}") from None
        self._state["started"] = True

    def reset(self) -> None:
        """Back to the state after initialisation (fmiReset, parameters, initialisation again)."""
        if self._fresh:
            return
        if self._fmu.component is None:
            raise FMIError("reset after close()")
        try:
            self._fmu.reset()
        except Exception as e:
            raise FMIError(f"fmi{self.fmi}Reset failed: {_line(e)}{self._log.last()}") from None
        self._state["started"] = False
        self._initialise()
        self._fresh = True

    def close(self) -> None:
        """Terminate, free the instance, remove the extracted FMU (idempotent)."""
        self._finalizer()

    # -- the loop ---------------------------------------------------------------------------

    def step(self, t: float, y: np.ndarray) -> np.ndarray:
        self._fresh = False
        if self._fmu.component is None:
            raise FMIError("step after close()")
        self._y[:] = y
        try:
            self._status(self._set, self._set(*self._set_args))
            self._status(self._do, self._do(self._fmu.component, t, self.period, *self._do_args))
            if self.fmi == 3 and self._flags[1].value:
                raise FMIError(f"fmi3DoStep asked to terminate the simulation{self._log.last()}")
            self._status(self._get, self._get(*self._get_args))
        except FMIError:
            raise
        except Exception as e:              # fmpy raises on Discard, Error, Fatal
            status = getattr(e, "status", None)
            what = getattr(e, "function", None) or "an FMI call"
            raise FMIError(f"{what} returned {self._label(status)}{self._log.last()}"
                           if status is not None else f"{what} failed: {_line(e)}") from None
        return self.u

    def _status(self, call, status) -> None:
        if status:                          # Warning (fmpy raises on worse)
            raise FMIError(f"{call.__name__} returned {self._label(status)}{self._log.last()}")

    def _label(self, status) -> str:
        return f"fmi{self.fmi}{STATUS[status]}" if isinstance(status, int) and 0 <= status < 6 else str(status)


def _release(state: dict) -> None:
    """Terminate and free an instance, remove its folder (the law's finalizer: no reference to it)."""
    fmu = state.get("fmu")
    if fmu is not None and fmu.component:
        try:
            if state.get("started"):
                fmu.terminate()
        except Exception:
            pass
        try:
            fmu.freeInstance()
        except Exception:
            pass
        fmu.component = None
    if state.get("env") is not None:
        _LOGS2.pop(state["env"], None)
    if state.get("dir"):
        shutil.rmtree(state["dir"], ignore_errors=True)


def _model_description(fmpy, spec: str, name: str):
    import zipfile
    try:
        return fmpy.read_model_description(spec, validate=True)
    except zipfile.BadZipFile:
        raise LawError(f"law {name}: not an FMU (not a zip archive)") from None
    except KeyError:
        raise LawError(f"law {name}: not an FMU (no modelDescription.xml in the archive)") from None
    except Exception as e:
        problems = getattr(e, "problems", None)
        what = problems[0] if problems else _line(e)
        raise LawError(f"law {name}: a broken modelDescription.xml: {what}") from None


def _platforms(folder) -> list[str]:
    return sorted(p.name for p in (Path(folder) / "binaries").glob("*") if p.is_dir())


def _mapping(name: str, meta: LawMeta, ins, outs, variables):
    """The FMU's input and output variable of each axis, in the loop's order."""
    table = meta.controller.get("fmu") or {}
    if not isinstance(table, dict):
        raise LawError(f"law {name}: [controller] key 'fmu' must be a table (inputs, outputs), got {table!r}")
    extra = sorted(set(table) - {"inputs", "outputs"})
    if extra:
        raise LawError(f"law {name}: [controller.fmu] has unknown key {extra[0]!r} (inputs, outputs)")
    real = lambda vs: ", ".join(v.name for v in vs) or "none"  # noqa: E731
    found = {}
    for kind, vs, prefix in (("inputs", ins, INPUT_PREFIX), ("outputs", outs, OUTPUT_PREFIX)):
        names = table.get(kind)
        if names is not None:
            if (not isinstance(names, list) or len(names) != meta.n_axes
                    or not all(isinstance(s, str) for s in names)):
                raise LawError(f"law {name}: [controller.fmu] {kind} must be {meta.n_axes} variable names "
                               f"(one per axis: {', '.join(meta.axes)}), got {names!r}")
            by_name = {v.name: v for v in vs}
            picked = []
            for axis, s in zip(meta.axes, names):
                if s not in by_name:
                    what = (f"is {_a(variables[s].causality)}, not an {kind[:-1]}" if s in variables
                            else "does not exist")
                    raise LawError(f"law {name}: [controller.fmu] {kind}: the FMU's variable {s!r} (axis {axis}) "
                                   f"{what}; its inputs: {real(ins)}; its outputs: {real(outs)}")
                picked.append(by_name[s])
        else:
            picked = []
            for axis in meta.axes:
                want = {_norm(axis), prefix + _norm(axis)}
                hits = [v for v in vs if _norm(v.name) in want]
                if len(hits) != 1:
                    k = axis_var(axis)
                    said = (f"no {kind[:-1]} {prefix}_{k} or {k}" if not hits else
                            f"{len(hits)} {kind} ({', '.join(v.name for v in hits)})")
                    raise LawError(f"law {name}: {said} for axis {axis}; its inputs: {real(ins)}; "
                                   f"its outputs: {real(outs)} (or name them in [controller.fmu] {kind})")
                picked.append(hits[0])
        if len({v.valueReference for v in picked}) != len(picked):
            raise LawError(f"law {name}: two axes name the same {kind[:-1]} of the FMU")
        for v in picked:
            if v.type not in REAL:
                raise LawError(f"law {name}: the FMU's {kind[:-1]} {v.name!r} is {v.type}, not Real/Float64")
            if getattr(v, "dimensions", None):
                raise LawError(f"law {name}: the FMU's {kind[:-1]} {v.name!r} is an array; "
                               f"one scalar variable per axis is needed")
        found[kind] = picked
    unfed = [v.name for v in ins if v not in found["inputs"]]
    if unfed:
        raise LawError(f"law {name}: the FMU's input {unfed[0]!r} is fed by no axis "
                       f"(axes: {', '.join(meta.axes)}); name each input in [controller.fmu] inputs")
    return found["inputs"], found["outputs"]


def axis_var(axis: str) -> str:
    """An axis as a variable name: ``A-x`` -> ``A_x``."""
    return re.sub(r"[^0-9A-Za-z_]", "_", axis)


def _parameters(name: str, meta: LawMeta, variables, fmi: int) -> list[tuple[str, int, object]]:
    """``(setter, value reference, value)`` of every parameter to set: [controller.params], and
    ``u_op_<axis>`` from the operating point where the FMU has it (fmpy's setters: ``setReal``,
    ``setInteger`` for FMI 2.0; ``setFloat64``, ``setInt32``, ... for 3.0, whose enumerations are Int64)."""
    params = dict(meta.params)
    for axis, u in zip(meta.axes, meta.u_op):
        k = f"u_op_{axis_var(axis)}"
        v = variables.get(k)
        if k not in params and v is not None and v.causality == "parameter" and v.type in REAL:
            params[k] = float(u)
    out = []
    for key, value in params.items():
        v = variables.get(key)
        if v is None or v.causality != "parameter":
            known = ", ".join(n for n, x in variables.items() if x.causality == "parameter") or "none"
            what = f"is {_a(v.causality)}" if v is not None else "is not a variable of the FMU"
            raise LawError(f"law {name}: [controller.params] key {key!r} {what}, not a parameter "
                           f"(the FMU's parameters: {known})")
        t = v.type
        if t in REAL or t == "Float32":
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            setter, value = ("setReal" if fmi == 2 else f"set{t}"), (float(value) if ok else value)
        elif t in INTEGER:
            ok = isinstance(value, int) and not isinstance(value, bool)
            setter = "setInteger" if fmi == 2 else "setInt64" if t == "Enumeration" else f"set{t}"
        elif t == "Boolean":
            ok, setter = isinstance(value, bool), "setBoolean"
        elif t == "String":
            ok, setter = isinstance(value, str), "setString"
        else:
            raise LawError(f"law {name}: [controller.params] key {key!r}: parameters of type {t} are not supported")
        if not ok:
            raise LawError(f"law {name}: [controller.params] {key} = {value!r}: the FMU's parameter is {t}")
        out.append((setter, v.valueReference, value))
    return out


def _a(word: str) -> str:
    return f"{'an' if word[:1] in 'aeiou' else 'a'} {word}"


def _line(e: BaseException) -> str:
    s = str(e).strip().splitlines()
    return s[0][:300] if s else type(e).__name__
