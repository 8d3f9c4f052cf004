"""The layering rules (docs/architecture.md), checked on every import statement of the source,
including imports inside functions: plant and controller are independent of each other, the
closed loop sits above both, the bridge above everything."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("plant", "controller", "loop", "bridge")
FORBIDDEN = {
    "plant": {"controller", "loop", "bridge"},
    "controller": {"plant", "loop", "bridge"},
    "loop": {"bridge"},
    "bridge": set(),
}


def imported_packages(path: Path, package: str) -> list[tuple[int, str]]:
    """(line, top-level package) of every import in a file; relative imports resolve to ``package``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name.split(".")[0]) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            out.append((node.lineno, package if node.level else (node.module or "").split(".")[0]))
    return sorted(out)


def violations() -> list[str]:
    bad = []
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            for line, top in imported_packages(f, pkg):
                if top in FORBIDDEN[pkg]:
                    bad.append(f"{f.relative_to(ROOT)}:{line} imports {top} ({pkg} must not)")
    return bad


def test_layers_import_only_downwards():
    assert violations() == []


def test_the_check_sees_a_violation(tmp_path):
    f = tmp_path / "x.py"
    f.write_text("import numpy\n\ndef f():\n    from controller.discrete import ControllerRunner\n"
                 "from . import rotor\n")
    assert imported_packages(f, "plant") == [(1, "numpy"), (4, "controller"), (5, "plant")]
