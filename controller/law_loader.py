"""Which law a name means, and the factory that makes it (controller/law.py).

    "FILE.py:CLASS"   a Python class: ``CLASS(meta)``, ``step(t, y) -> u``, optional ``reset()``
    "FILE.so"         a shared library of the C ABI (include/ambhil_law.h; controller/law_c.py)
    "FILE.fmu"        an FMU, FMI 2.0 or 3.0 co-simulation (controller/law_fmu.py)

Relative paths are taken from ``base_dir`` (the scene's folder for ``[controller] law``, the
working directory for ``--law``).  Errors are one line naming the law.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from .law import LawError

LIBRARY_SUFFIXES = (".so", ".dylib", ".dll")


def resolve(spec: str, base_dir: str | Path = ".") -> str:
    """``spec`` with its file made absolute (relative to ``base_dir``); the file must exist."""
    spec = str(spec).strip()
    path, sep, cls = spec.rpartition(":") if spec.count(":") and not _is_drive(spec) else (spec, "", "")
    if not sep:
        path = spec
    p = Path(path).expanduser()
    if not p.is_absolute():
        p = Path(base_dir) / p
    kind = law_kind(spec)
    if kind == "python" and not cls:
        raise LawError(f"law {spec}: a Python law is named FILE.py:CLASS (the class to make)")
    if not p.is_file():
        raise LawError(f"law {spec}: no such file {p}")
    return f"{p.resolve()}{sep}{cls}" if sep else str(p.resolve())


def _is_drive(spec: str) -> bool:
    return len(spec) > 2 and spec[1] == ":" and spec[2] in "\\/"


def law_kind(spec: str) -> str:
    """``python``, ``c`` or ``fmu`` from the name; anything else is a :class:`LawError`."""
    path = spec.rsplit(":", 1)[0] if ".py:" in spec else spec
    suffix = Path(path).suffix.lower()
    if suffix == ".py":
        return "python"
    if suffix in LIBRARY_SUFFIXES:
        return "c"
    if suffix == ".fmu":
        return "fmu"
    raise LawError(f"law {spec}: not a law (FILE.py:CLASS, a shared library {'/'.join(LIBRARY_SUFFIXES)} "
                   f"of include/ambhil_law.h, or an FMU .fmu)")


def law_factory(spec: str):
    """``(factory, name)`` for an absolute ``spec`` (:func:`resolve`): ``factory(meta) -> law``."""
    kind = law_kind(spec)
    name = Path(spec.rsplit(":", 1)[0] if kind == "python" else spec).name
    if kind == "python":
        path, cls = spec.rsplit(":", 1)
        return python_class(path, cls), f"{name}:{cls}"
    if kind == "c":
        from .law_c import CLaw
        return (lambda meta: CLaw(spec, meta)), name
    from .law_fmu import FMULaw
    return (lambda meta: FMULaw(spec, meta)), name


def python_class(path: str, cls: str):
    """The class ``cls`` of the Python file ``path`` (imported as a module of its own name;
    its folder is importable while it loads, for its helpers)."""
    p = Path(path)
    mod_name = f"ambhil_law_{p.stem}"
    spec = importlib.util.spec_from_file_location(mod_name, p)
    if spec is None or spec.loader is None:
        raise LawError(f"law {p.name}:{cls}: cannot import {p}")
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(p.parent))
    try:
        spec.loader.exec_module(module)
    except Exception as e:
        raise LawError(f"law {p.name}:{cls}: importing {p.name} raised {type(e).__name__}: "
                       f"{str(e).strip().splitlines()[0][:300] if str(e).strip() else ''}") from None
    finally:
        sys.path.remove(str(p.parent))
    obj = getattr(module, cls, None)
    if obj is None:
        raise LawError(f"law {p.name}:{cls}: {p.name} has no {cls!r}")
    if not callable(getattr(obj, "step", None)) and not callable(obj):
        raise LawError(f"law {p.name}:{cls}: {cls} has no step(t, y)")
    return obj
