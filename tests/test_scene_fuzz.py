"""Mutation fuzz of the shipped scenes through `ambhil analyze / simulate / run` (issue 10 item 5).

The fuzz itself (mutations, how each command is driven, how an outcome is classified) is
tests/scene_fuzz.py; ``python -m tests.scene_fuzz --full`` runs every valid mutation unstubbed.
"""
from __future__ import annotations

import hashlib
from collections import Counter

import pytest

import scene_fuzz as F

# valid mutations that also run `simulate` unstubbed (orbit plots drawn)
REAL = ("utf8-bom", "step=3e-5+--h")


def test_mutations_are_deterministic_and_cover_every_class():
    a, b = F.generate(), F.generate()
    assert [(m.id, hashlib.sha1(m.data).hexdigest()) for m in a] == \
        [(m.id, hashlib.sha1(m.data).hexdigest()) for m in b]
    assert len(a) >= 200 and len({m.id for m in a}) == len(a)
    classes = Counter(m.category for m in a)
    for c in ("missing key", "misspelled key", "wrong type", "extreme value", "out-of-range node",
              "duplicated station", "encoding", "syntax", "nesting", "huge", "consistency"):
        assert classes[c] >= 5, c
    ids = " ".join(m.id for m in a)
    for must in ("array-depth-5000", "latin1-comment", "utf8-bom", "utf16-le-bom", "comments-40MiB",
                 "=nan", "=0", "=-1", "amb-dup-same-node", "truncated-at-", "step=3e-5+--h"):
        assert must in ids, must
    assert max(len(m.data) for m in a) > 40 << 20
    assert {m.scene for m in a} == {p.stem for p in F.SCENES}


def _mut(**kw):
    d = dict(id="x", category="test", scene="s", data=b"", expect={"*": "error"}, fragment=("gap",))
    d.update(kw)
    return F.Mutation(**d)


@pytest.mark.parametrize("code,err,exc,expect,verdict", [
    (2, "ambhil: /t/x.toml: [[amb]] #1 'A' key 'gap': must be > 0, got 0\n", None, "error", "error"),
    (2, "ambhil: /t/x.toml: [[amb]] #1 'A' key 'gap': must be > 0\n", None, "ok", "defect"),  # valid refused
    (0, "", None, "error", "defect"),  # bad scene accepted
    (0, "", None, "any", "ok"),
    (None, "", "ValueError: boom", "any", "defect"),  # an exception escaping main = a traceback
    (2, "Traceback (most recent call last):\nambhil: /t/x.toml: key 'gap'\n", None, "error", "defect"),
    (2, "ambhil: /t/x.toml: key 'gap': bad\nambhil: and more\n", None, "error", "defect"),  # two lines
    (2, "ambhil: error: float division by zero 'gap'\n", None, "error", "defect"),  # no file name
    (2, "ambhil: /t/x.toml: key 'turns': bad\n", None, "error", "defect"),  # not the key at fault
    (2, "ambhil: /t/x.toml: 'gap' " + "x" * 500 + "\n", None, "error", "defect"),  # not one readable line
    (3, "", None, "any", "defect"),
])
def test_classifier_can_fail(tmp_path, code, err, exc, expect, verdict):
    m = _mut(expect={"*": expect})
    got, _ = F.classify(m, "analyze", tmp_path / "x.toml", F.Call(code, "", err, exc), tmp_path, F.Stubs())
    assert got == verdict


def test_watchdog_turns_a_hang_into_a_defect(monkeypatch, tmp_path):
    import ambhil.loop.report as an
    def spin(path):
        while True:
            pass
    monkeypatch.setattr(an, "load_scene", spin)
    r = F.call(["analyze", str(tmp_path / "x.toml"), "--no-sweep"], cpu_limit=0.5)  # CPU time, not wall
    assert r.exc and r.exc.startswith("hang")
    assert F.classify(_mut(), "analyze", tmp_path / "x.toml", r, tmp_path, F.Stubs())[0] == "defect"


def test_scene_fuzz(tmp_path, capsys):
    res = F.run_fuzz(F.generate(), tmp_path, real=REAL)
    text = F.summary(res)
    with capsys.disabled():
        print("\n" + text)
    assert not [o for o in res if o.category == "defect"], text
    by = Counter((o.command, o.category) for o in res)
    for cmd in F.COMMANDS:  # every command refused the bad scenes and ran the good ones
        assert by[cmd, "error"] >= 200 and by[cmd, "ok"] + by[cmd, "fault"] >= 10, text
    assert by["simulate (real)", "ok"] == len(REAL), text
