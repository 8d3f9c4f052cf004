"""The layering rules (docs/architecture.md), checked on every import statement of the source,
including imports inside functions: plant and controller are independent of each other, the
closed loop sits above both, the bridge above everything; inside the bridge the four rooms
import only downwards (protocol <- process <- recording <- cli); no module imports itself back
through others (no import circle); no file of the four layers is over 500 lines."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NS = "ambhil"
PACKAGES = ("plant", "controller", "loop", "bridge")
FORBIDDEN = {
    "plant": {"controller", "loop", "bridge"},
    "controller": {"plant", "loop", "bridge"},
    "loop": {"bridge"},
    "bridge": set(),
}
# the bridge's rooms, bottom to top: a room imports only the rooms before it
ROOMS = ("protocol", "process", "recording", "cli")
MAX_LINES = 500


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join([NS, *parts])


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in a file (relative ones resolved; ``from a import b``
    gives ``a.b`` when ``a.b`` is a module of the tree, else ``a``)."""
    me = module_name(path)
    pkg = me if path.name == "__init__.py" else me.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")
                base = base[:len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out += [(node.lineno, f"{mod}.{a.name}") for a in node.names] + [(node.lineno, mod)]
    return sorted(out)


def sources() -> list[Path]:
    return [f for pkg in PACKAGES for f in sorted((ROOT / pkg).rglob("*.py"))]


def layer_of(mod: str) -> tuple[str, str | None] | None:
    """(layer, bridge room or None) of a module of the tree, None outside it; old top-level names
    (``plant.x``) count as the layer too, so an import that bypasses the namespace is seen."""
    parts = mod.split(".")
    if parts[0] == NS:
        parts = parts[1:]
    if not parts or parts[0] not in PACKAGES:
        return None
    room = parts[1] if parts[0] == "bridge" and len(parts) > 1 and parts[1] in ROOMS else None
    return parts[0], room


def violations() -> list[str]:
    bad = []
    for f in sources():
        me = layer_of(module_name(f))
        for line, mod in imports(f):
            there = layer_of(mod)
            if there is None:
                continue
            where = f"{f.relative_to(ROOT)}:{line}"
            if not mod.startswith(NS + "."):
                bad.append(f"{where} imports {mod} outside the {NS} namespace")
            if there[0] in FORBIDDEN[me[0]]:
                bad.append(f"{where} imports {there[0]} ({me[0]} must not)")
            if me[0] == there[0] == "bridge" and me[1] and there[1] and \
                    ROOMS.index(there[1]) > ROOMS.index(me[1]):
                bad.append(f"{where} imports bridge/{there[1]} (bridge/{me[1]} sits below it)")
    return bad


def import_graph() -> dict[str, set[str]]:
    mods = {module_name(f): f for f in sources()}
    graph = {}
    for m, f in mods.items():
        graph[m] = {d for _, d in imports(f) if d in mods and d != m and not m.startswith(d + ".")}
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, n = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = n[0]
        n[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_layers_import_only_downwards():
    assert violations() == []


def test_no_import_circle():
    assert circles(import_graph()) == []


def test_no_file_over_500_lines():
    long = [f"{f.relative_to(ROOT)}: {n} lines" for f in sources()
            if (n := len(f.read_text().splitlines())) > MAX_LINES]
    assert long == []


def test_the_check_sees_a_violation(tmp_path):
    pkg = tmp_path / "plant"
    pkg.mkdir()
    f = pkg / "x.py"
    f.write_text("import numpy\n\ndef f():\n    from ambhil.controller.discrete import ControllerRunner\n"
                 "from . import rotor\nimport loop.scene as s\n")
    globals()["ROOT"], old = tmp_path, ROOT
    try:
        got = imports(f)
        assert (4, "ambhil.controller.discrete") in got and (5, "ambhil.plant.rotor") in got
        assert (6, "loop.scene") in got
        assert layer_of("ambhil.bridge.cli.run") == ("bridge", "cli")
    finally:
        globals()["ROOT"] = old


def test_the_check_sees_a_circle():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []
