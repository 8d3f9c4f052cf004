"""What every benchmark shares: the repository's paths, the standard flags, the header line
(commit, machine, load), median [min, max] over repeats, and child Python processes.

Output format, the same in every module::

    # benchmarks.NAME: <what it measures>
    # commit 1a2b3c4 | AMD EPYC, 2 CPUs | load 1.48 1.17 1.58 | OPENBLAS_NUM_THREADS=1
    <figure>: <median> [<min>, <max>] <unit> (<n> runs)      one line per figure, or
    | col | col |                                              a markdown table of medians

Children (the two processes of a loop, a recorder, a ping-pong partner) are started as
``python -c "from benchmarks.X import f; f(...)"`` in the repository root, so they import the
same ``benchmarks`` package and the installed ``ambhil``: no ``sys.path`` is patched anywhere.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Iterable

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"


def scene(name: str) -> str:
    """The path of ``scenes/<name>.toml`` (or ``name`` itself if it is a path)."""
    p = Path(name)
    if p.suffix == ".toml" or p.exists():
        return str(p.resolve())
    return str(SCENES / f"{name}.toml")


# -- the header -------------------------------------------------------------------------------

def commit() -> str:
    """The checkout's commit (short id), ``+`` if tracked files differ from it; ``?`` outside git."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "?"
    return (head or "?") + ("+" if dirty else "")


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform
    return platform.processor() or platform.machine()


def machine() -> str:
    """``CPU model, N CPUs | load 1m 5m 15m``: the load is part of every figure on a shared machine."""
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    return f"{cpu_model()}, {os.cpu_count()} CPUs | load {load}"


def header(name: str, what: str) -> None:
    """The two header lines every benchmark prints first."""
    print(f"# benchmarks.{name}: {what}")
    print(f"# commit {commit()} | {machine()} | OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}", flush=True)


def parser(doc: str, repeat: int = 5) -> argparse.ArgumentParser:
    """An argument parser whose description is the module's docstring, with the standard flag
    ``--repeat N`` (runs of each measurement; ``--runs`` is accepted as its alias)."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", "--runs", dest="repeat", type=int, default=repeat, metavar="N",
                    help=f"runs of each measurement; medians are printed (default {repeat})")
    return ap


def csv(text: str) -> list[str]:
    """A comma-separated option as a list."""
    return [x for x in text.split(",") if x]


# -- figures ----------------------------------------------------------------------------------

def spread(values: Iterable[float]) -> tuple[float, float, float]:
    """(median, min, max)."""
    v = [x for x in values if x is not None]
    return statistics.median(v), min(v), max(v)


def num(x: float, digits: int = 3) -> str:
    """``digits`` significant digits, but never an exponent for large numbers (12345, not 1.23e+04)."""
    return f"{x:.0f}" if abs(x) >= 10 ** digits else f"{x:.{digits}g}"


def figure(values: Iterable[float], unit: str = "", digits: int = 3, scale: float = 1.0) -> str:
    """``median [min, max] unit``, each value times ``scale``."""
    med, lo, hi = (num(x * scale, digits) for x in spread(values))
    return f"{med} [{lo}, {hi}]" + (f" {unit}" if unit else "")


def report(what: str, values: list[float], unit: str = "", digits: int = 3, scale: float = 1.0,
           note: str = "") -> None:
    """One result line: ``what: median [min, max] unit (n runs) note``."""
    print(f"{what}: {figure(values, unit, digits, scale)} ({len(values)} runs)"
          + (f"  {note}" if note else ""), flush=True)


def table(head: list[str], rows: list[list]) -> None:
    """A markdown table (the docs' tables are pasted from these)."""
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print("| " + " | ".join(str(x) for x in r) + " |")
    sys.stdout.flush()


def timed(fn: Callable[[], object], repeat: int, warmup: bool = True) -> list[float]:
    """Wall seconds of ``repeat`` calls of ``fn`` (after one untimed call: imports, caches, JIT)."""
    if warmup:
        fn()
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


# -- child processes --------------------------------------------------------------------------

def child_env(**extra: str) -> dict:
    return dict(os.environ, **extra)


def popen(code: str, env: dict | None = None, **kw) -> subprocess.Popen:
    """``python -c code`` in the repository root (``from benchmarks.X import ...`` works there)."""
    return subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=env or child_env(), **kw)


def run(code: str, timeout: float = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    """``python -c code`` in the repository root, to completion, output captured."""
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env or child_env(),
                          capture_output=True, text=True, timeout=timeout)


def last_json(text: str) -> dict:
    """The last line of ``text`` that is a JSON object (the children's and `ambhil --json`'s summaries)."""
    lines = [ln for ln in text.splitlines() if ln.startswith("{")]
    if not lines:
        raise RuntimeError("no JSON summary in the output")
    return json.loads(lines[-1])


def tail(text: str, n: int = 500) -> str:
    return text.strip()[-n:]
