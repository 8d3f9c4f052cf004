"""The docs point at things that exist: every relative markdown link (and its #anchor, by
GitHub's heading rules), every repository file path written in the text, every benchmark and
docs tool a command names, and no doc names a notes file that is not in the repository.

Checked: README.md, docs/*.md, benchmarks/README.md, docs/tools/README.md.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
        ROOT / "benchmarks" / "README.md", ROOT / "docs" / "tools" / "README.md"]
DOCS = [d for d in DOCS if d.exists()]
TOP = ("plant", "controller", "loop", "bridge", "benchmarks", "tests", "docs", "scenes", "examples")
# outside the repository, named in plain text as such (the project's shared reference notes)
OUTSIDE = ("shared/reference/",)
# files a doc shows as an example of the user's own (an error message about a broken scene)
EXAMPLES = {"scenes/bad.toml"}


def _rel(p: Path) -> str:
    return str(p.relative_to(ROOT))


def _prose(text: str) -> str:
    """The text without fenced code blocks (their lines are commands and code, not prose)."""
    out, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            out.append("")
            continue
        out.append("" if fenced else line)
    return "\n".join(out)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: the rendered text lowercased, punctuation other than
    ``-`` and ``_`` dropped, each space a ``-``."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)      # a link: its text
    text = text.replace("`", "").replace("*", "")
    text = re.sub(r"<[^>]+>", "", text).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a markdown file (repeated headings get -1, -2, ... as on GitHub)."""
    seen: dict[str, int] = {}
    out = set()
    for line in _prose(path.read_text()).splitlines():
        m = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        s = slug(m.group(1))
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return out


def links(path: Path):
    """(line number, target) of every relative markdown link ``[text](target)``."""
    for k, line in enumerate(_prose(path.read_text()).splitlines(), 1):
        for m in re.finditer(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)", line):
            t = m.group(1)
            if not re.match(r"[a-z][a-z0-9+.-]*:", t):          # http:, https:, mailto: ...
                yield k, t


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_relative_links_point_to_files_and_headings_that_exist(doc):
    bad = []
    for k, target in links(doc):
        file, _, anchor = target.partition("#")
        dest = (doc.parent / file).resolve() if file else doc
        if not dest.exists():
            bad.append(f"{_rel(doc)}:{k}: {target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{_rel(doc)}:{k}: {target}: no heading with that anchor in {_rel(dest)}")
    assert not bad, "\n".join(bad)


_PATH = re.compile(r"(?<![\w./-])(?:\.\./|\./)?((?:%s)/[\w./-]*[\w])" % "|".join(TOP))


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_repository_paths_in_the_text_exist(doc):
    """``bridge/process/deadline.py``, ``scenes/paper_3amb.toml``, ``docs/hil.md``: a path written
    in a doc (from the repository root, or from the doc's folder) names a file or folder that is
    there; so does a module written with a name of it (``plant/step.bound_kernel``: plant/step.py).
    Only paths whose last part has a dot are checked: ``plant/sensors`` is a zenoh key."""
    bad = []
    for k, line in enumerate(doc.read_text().splitlines(), 1):
        for m in _PATH.finditer(line):
            p = m.group(1).rstrip(".")
            folder, _, last = p.rpartition("/")
            if "." not in last or any(ch in p for ch in "*<>") or "/target/" in p or p in EXAMPLES:
                continue
            stem = f"{folder}/{last.split('.')[0]}"
            if not any((base / q).exists() for base in (ROOT, doc.parent) for q in (p, stem + ".py", stem)):
                bad.append(f"{_rel(doc)}:{k}: {p}")
    assert not bad, "paths that do not exist:\n" + "\n".join(bad)


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_named_benchmarks_and_docs_tools_exist(doc):
    """``python -m benchmarks.X`` / ``docs.tools.X`` and ``benchmarks/X.py`` name modules that exist."""
    text = doc.read_text()
    bad = []
    for m in re.finditer(r"-m\s+((?:benchmarks|docs\.tools)\.[a-z_][a-z0-9_]*)\b", text):   # not NAME
        if not (ROOT / (m.group(1).replace(".", "/") + ".py")).exists():
            bad.append(m.group(1))
    for m in re.finditer(r"(?<![\w/])(benchmarks/\w+\.py)", text):
        if not (ROOT / m.group(1)).exists():
            bad.append(m.group(1))
    assert not bad, f"{_rel(doc)} names benchmarks that do not exist: {sorted(set(bad))}"


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_no_notes_outside_the_repository_named_as_if_they_were_in_it(doc):
    """A bare ``something.md`` is a doc of this repository; the project's reference notes, which are
    not in it, are named with their folder (``shared/reference/tooling.md``)."""
    names = {p.name for p in DOCS} | {p.name for p in ROOT.rglob("*.md") if ".venv" not in p.parts}
    bad = []
    for k, line in enumerate(doc.read_text().splitlines(), 1):
        for m in re.finditer(r"(?<![\w.-])([\w./-]*?)([\w-]+\.md)\b", line):
            folder, name = m.group(1), m.group(2)
            if any(o in folder for o in OUTSIDE) or folder.startswith(("http", "/")):
                continue
            if folder:
                ok = (ROOT / folder / name).exists() or (doc.parent / folder / name).exists()
            else:
                ok = name in names
            if not ok:
                bad.append(f"{_rel(doc)}:{k}: {folder}{name}")
    assert not bad, "notes that are not in the repository:\n" + "\n".join(bad)
