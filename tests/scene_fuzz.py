"""Mutation fuzz of the shipped scenes (scenes/*.toml) through the ``ambhil`` CLI, in-process.

Every mutation is a byte string written to a file; ``analyze``, ``simulate`` and ``run`` are driven
through :func:`ambhil.bridge.cli.main.main` with stdout/stderr captured, and each outcome is classified:

``error``   exit 2, exactly one line on stderr naming the file (and, where the mutation targets a
            key, that key or the problem), no traceback
``ok``      exit 0 (the scene is valid and the command ran)
``fault``   ``simulate`` exit 1 with a FAULT line: a valid scene whose run faulted (reported, fine)
``defect``  anything else: an exception escaping ``main`` (a traceback for the user), another exit
            code, exit 0 for a scene that must be refused, a refused scene that is valid, more than
            one line, a message not naming the file or the key, a hang (CPU-time watchdog)

What each command does here (the quick tier, the default):
  analyze  ``analyze FILE --no-sweep``; the numerical analyses after ``compile_system`` are not run
           (ARPACK critical speeds cost ~15 s per valid scene on a busy 2-core machine)
  simulate ``simulate FILE --out DIR --duration 1e-3`` for real, except that the orbit PNGs are not
           drawn (matplotlib: ~1 s per node)
  run      ``run FILE --duration 1e-3 --out DIR`` for real up to the point where it would start the
           three processes; the argv it would give them is checked (run id usable in zenoh key
           expressions, recording path writable) and the ``controller`` and ``plant`` commands it
           would start are then run in-process with the same argv up to the point where they go on
           the network (everything they load, compile and check before that runs for real)
A few valid mutations (``real=``) also run ``simulate`` unstubbed (plots drawn).  ``--full`` (standalone)
runs every valid mutation unstubbed in all three commands (analyze in full, ``run`` starting its three
processes with a tiny --duration): minutes.  ``--isolate`` runs each mutation in a forked child with an
address-space limit, for code that may still exhaust memory (how the "before" counts were taken).

Expectations come from docs/scenes.md and docs/time_domain.md (the documented types and ranges),
not from plant/scene.py.  Run standalone: ``python -m tests.scene_fuzz [--full] [--list]``.
"""
from __future__ import annotations

import contextlib
import gc
import io
import os
import random
import re
import signal
import sys
import tempfile
import tomllib
import traceback
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENES = sorted((ROOT / "scenes").glob("*.toml"))
SEED = 20260510
COMMANDS = ("analyze", "simulate", "run")
TINY = "1e-3"  # s simulated by simulate and run
CPU_LIMIT_S = 60.0  # CPU seconds one command may use before it counts as a hang (quick calls use < 2 s)

# --------------------------------------------------------------------------- the documented scene format
POS, NONNEG, ANY, ANGLE, UNIT = ">0", ">=0", "any", "[0,90)", "[0,1]"
# (table, key) -> (kind, constraint, required); kinds: num int str choice bool node pair nodes hz name
SPEC = {
    ("scene", "name"): ("str", ANY, False), ("scene", "description"): ("str", ANY, False),
    ("model", "rung"): ("choice", ANY, False), ("model", "beam"): ("choice", ANY, False),
    ("model", "modal_cutoff"): ("num", POS, False),
    ("shaft", "length"): ("num", POS, True), ("shaft", "outer_diameter"): ("num", POS, True),
    ("shaft", "inner_diameter"): ("num", NONNEG, False), ("shaft", "elements"): ("int", POS, False),
    ("shaft", "youngs_modulus"): ("num", POS, False), ("shaft", "shear_modulus"): ("num", POS, False),
    ("shaft", "density"): ("num", POS, False),
    ("disc", "name"): ("str", ANY, False), ("disc", "node"): ("node", ANY, True),
    ("disc", "mass"): ("num", POS, True), ("disc", "polar_inertia"): ("num", NONNEG, True),
    ("disc", "diametral_inertia"): ("num", NONNEG, True),
    ("amb", "name"): ("str", ANY, False), ("amb", "node"): ("node", ANY, True),
    ("amb", "gap"): ("num", POS, True), ("amb", "bias_current"): ("num", POS, True),
    ("amb", "turns"): ("num", POS, True), ("amb", "pole_area"): ("num", POS, True),
    ("amb", "pole_angle"): ("num", ANGLE, False), ("amb", "misalignment"): ("pair", ANY, False),
    ("sensor", "gain"): ("num", POS, False), ("sensor", "time_constant"): ("num", NONNEG, False),
    ("amplifier", "gain"): ("num", POS, False), ("amplifier", "time_constant"): ("num", NONNEG, False),
    ("amplifier", "current_limit"): ("num", POS, False), ("amplifier", "slew_rate"): ("num", POS, False),
    ("controller", "kp"): ("num", POS, True), ("controller", "ki"): ("num", NONNEG, False),
    ("controller", "kd"): ("num", NONNEG, False), ("controller", "derivative_filter"): ("num", NONNEG, False),
    ("controller", "sample_rate"): ("num", POS, False),
    ("unbalance", "node"): ("node", ANY, True), ("unbalance", "magnitude"): ("num", NONNEG, True),
    ("unbalance", "phase"): ("num", ANY, False),
    ("speed", "range"): ("pair", ANY, False), ("speed", "points"): ("int", POS, False),
    ("damping", "mass_proportional"): ("num", NONNEG, False),
    ("damping", "stiffness_proportional"): ("num", NONNEG, False),
    ("analysis", "output_nodes"): ("nodes", ANY, False), ("analysis", "reference_criticals"): ("hz", ANY, False),
    ("analysis", "reference"): ("str", ANY, False), ("analysis", "sweep_amb"): ("name", ANY, False),
    ("simulation", "integrator"): ("choice", ANY, False), ("simulation", "step"): ("num", POS, False),
    ("simulation", "duration"): ("num", POS, False), ("simulation", "speed"): ("num", NONNEG, False),
    ("simulation", "output_nodes"): ("nodes", ANY, False),
}


# --------------------------------------------------------------------------- the text of a scene
@dataclass(frozen=True)
class Site:
    table: str  # table name ("amb" for [[amb]])
    nth: int  # occurrence of that table (0-based)
    key: str
    line: int  # index into lines
    value: str  # value text (no comment)


def _split_comment(s: str) -> tuple[str, str]:
    q = None
    for i, ch in enumerate(s):
        if q:
            if ch == q:
                q = None
        elif ch in "\"'":
            q = ch
        elif ch == "#":
            return s[:i].rstrip(), s[i:]
    return s.rstrip(), ""


class Src:
    """A shipped scene as lines, with its tables and key sites located."""

    def __init__(self, path: Path):
        self.path, self.stem = path, path.stem
        self.text = path.read_text(encoding="utf-8")
        self.lines = self.text.splitlines(keepends=True)
        self.sites: list[Site] = []
        self.headers: list[tuple[str, int, int]] = []  # (table, nth, line)
        count: Counter = Counter()
        table, nth = None, 0
        for i, ln in enumerate(self.lines):
            m = re.match(r"\s*\[\[?\s*([\w.]+)\s*\]\]?", ln)
            if m:
                table = m.group(1)
                nth = count[table]
                count[table] += 1
                self.headers.append((table, nth, i))
                continue
            m = re.match(r"\s*([A-Za-z_][\w-]*)\s*=\s*(.*)$", ln)
            if m and table:
                self.sites.append(Site(table, nth, m.group(1), i, _split_comment(m.group(2))[0]))
        self.n_nodes = 1 + sum(int(s.value) for s in self.sites if s.key == "elements")

    def block(self, table: str, nth: int = 0) -> tuple[int, int]:
        """Line range [start, end) of one table (header to the next header)."""
        hs = [h for h in self.headers]
        for k, (t, n, i) in enumerate(hs):
            if t == table and n == nth:
                end = hs[k + 1][2] if k + 1 < len(hs) else len(self.lines)
                return i, end
        raise KeyError((table, nth))

    def site(self, table: str, key: str, nth: int = 0) -> Site:
        for s in self.sites:
            if (s.table, s.key, s.nth) == (table, key, nth):
                return s
        raise KeyError((table, key, nth))

    def has(self, table: str, key: str, nth: int = 0) -> bool:
        return any((s.table, s.key, s.nth) == (table, key, nth) for s in self.sites)

    def edit(self, changes: dict[int, str]) -> str:
        """Text with some lines replaced (None-free; '' deletes the line)."""
        return "".join(changes.get(i, ln) for i, ln in enumerate(self.lines))

    def value_line(self, s: Site, value: str) -> str:
        m = re.match(r"(\s*[A-Za-z_][\w-]*\s*=\s*)(.*?)(\r?\n)?$", self.lines[s.line], re.S)
        _, comment = _split_comment(m.group(2))
        return f"{m.group(1)}{value}{'   ' + comment if comment else ''}\n"

    def set_value(self, s: Site, value: str) -> str:
        return self.edit({s.line: self.value_line(s, value)})

    def drop(self, s: Site) -> str:
        return self.edit({s.line: ""})

    def rename(self, s: Site, new: str) -> str:
        return self.edit({s.line: re.sub(r"^(\s*)[A-Za-z_][\w-]*", lambda m: m.group(1) + new, self.lines[s.line], 1)})

    def insert_after(self, line: int, text: str) -> str:
        return "".join(ln + (text if i == line else "") for i, ln in enumerate(self.lines))


# --------------------------------------------------------------------------- mutations
@dataclass
class Mutation:
    id: str
    category: str
    scene: str
    data: bytes
    expect: dict  # command -> "error" | "ok" | "any"
    fragment: tuple[str, ...] = ()  # an error line must contain one of these (case-insensitive)
    extra: dict = field(default_factory=dict)  # command -> extra argv

    def expected(self, cmd: str) -> str:
        return self.expect.get(cmd, self.expect.get("*", "any"))


def _m(out: list, cat: str, src: Src, slug: str, text, expect="error", fragment=(), extra=None):
    data = text if isinstance(text, bytes) else text.encode("utf-8")
    exp = expect if isinstance(expect, dict) else {"*": expect}
    frag = (fragment,) if isinstance(fragment, str) else tuple(fragment)
    slug = re.sub(r"[^A-Za-z0-9_.=+-]", "_", slug)
    out.append(Mutation(f"{len(out):03d}-{src.stem}-{slug}", cat, src.stem, data, exp, frag, extra or {}))


def _typo(rng: random.Random, key: str) -> str:
    k = list(key)
    op = rng.choice(("swap", "drop", "double", "upper", "plural", "dash"))
    i = rng.randrange(len(k) - 1)
    if op == "swap" and k[i] != k[i + 1]:
        k[i], k[i + 1] = k[i + 1], k[i]
    elif op == "drop":
        del k[i]
    elif op == "double":
        k.insert(i, k[i])
    elif op == "upper":
        k[0] = k[0].upper()
    elif op == "dash" and "_" in key:
        return key.replace("_", "-", 1)
    else:
        k.append("s")
    return "".join(k)


NUMS = ["0", "0.0", "-0.0", "-1", "-1.0e-3", "nan", "inf", "-inf", "+inf", "1e308", "-1e308", "1e300",
        "1e30", "1e12", "1e-12", "1e-300", "5e-324", "1000000000000000000000000000000", "1" + "0" * 400, "-" + "9" * 30]
INTS = ["0", "-1", "1.5", "1.0", "9223372036854775807", "-9223372036854775808", "100000000", "1e3",
        "1000000000"]
NONFINITE = ("nan", "inf", "-inf", "+inf")
WRONG_TYPES = ['"12"', '"abc"', "true", "false", "[1.0, 2.0]", "[]", "{ a = 1 }", "1979-05-27", "07:32:00",
               "1979-05-27T07:32:00Z", '"""multi\nline"""', "[[1, 2], [3]]"]


def _num_expect(kind: str, cons: str, value: str, key: str) -> str:
    """Documented outcome of a numeric value ("error" or "any") for a key of this kind/constraint."""
    v = tomllib.loads(f"v = {value}")["v"]
    if kind == "int":
        if not isinstance(v, int):
            return "error"
        return "error" if (v < 1 and cons == POS) or v < 0 else "any"
    try:
        fv = float(v)
    except OverflowError:  # an integer beyond the float range
        fv = float("inf") if v > 0 else float("-inf")
    if fv != fv or fv in (float("inf"), float("-inf")):
        return "any" if (key == "current_limit" and fv > 0) else "error"
    if cons == POS and not fv > 0 or cons == NONNEG and fv < 0:
        return "error"
    if cons == ANGLE and not 0 <= fv < 90:
        return "error"
    return "any"


def generate(seed: int = SEED) -> list[Mutation]:
    rng = random.Random(seed)
    srcs = [Src(p) for p in SCENES]
    by = {s.stem: s for s in srcs}
    base = by.get("paper_2amb", srcs[0])
    three = by.get("paper_3amb", srcs[-1])
    out: list[Mutation] = []
    pick = lambda: rng.choice(srcs)

    # ---- baselines: the shipped scenes themselves
    for s in srcs:
        _m(out, "baseline", s, "as-shipped", s.text, "ok")

    # ---- missing keys (every required key once, a few optional ones)
    req = [(t, k) for (t, k), v in SPEC.items() if v[2]]
    for t, k in req:
        # a scene that has the key (kp is required by the built-in law only: a scene of
        # another [controller] kind has none)
        s = rng.choice([x for x in srcs if any((y.table, y.key) == (t, k) for y in x.sites)])
        site = next(x for x in s.sites if (x.table, x.key) == (t, k))
        _m(out, "missing key", s, f"no-{t}.{k}", s.drop(site), "error", k)
    optional = [x for x in base.sites if not SPEC.get((x.table, x.key), ("", "", True))[2]]
    for site in rng.sample(optional, 6):
        _m(out, "missing key", base, f"no-{site.table}.{site.key}", base.drop(site), "any")

    # ---- misspelled keys
    for s, site in rng.sample([(s, x) for s in srcs for x in s.sites], 30):
        new = _typo(rng, site.key)
        if new == site.key:
            new = site.key + "_"
        _m(out, "misspelled key", s, f"typo-{site.table}.{new}", s.rename(site, new), "error", (new, site.key))
    for t_old, t_new in (("controller", "controler"), ("simulation", "simulaton"), ("amb", "ambs")):
        s = pick()
        i = s.block(t_old)[0]
        _m(out, "misspelled key", s, f"table-{t_new}", s.edit({i: s.lines[i].replace(t_old, t_new, 1)}),
           "error", (t_new, t_old))

    # ---- wrong types
    typed = [(s, x) for s in srcs for x in s.sites if (x.table, x.key) in SPEC]
    for s, site in rng.sample(typed, 40):
        kind = SPEC[(site.table, site.key)][0]
        choices = [w for w in WRONG_TYPES if not (kind in ("str", "choice", "name") and w.startswith('"'))
                   and not (kind in ("pair", "nodes", "hz") and w == "[]")
                   and not (kind == "pair" and w == "[1.0, 2.0]")]
        w = rng.choice(choices)
        exp = "any" if kind == "hz" and w == "[1.0, 2.0]" else "error"  # two frequencies in Hz: valid
        _m(out, "wrong type", s, f"type-{site.table}.{site.key}", s.set_value(site, w), exp, site.key)

    # ---- zero / negative / NaN / inf / huge / tiny values
    numeric = [(t, k) for (t, k), v in SPEC.items() if v[0] in ("num", "int")]
    for t, k in numeric:
        kind, cons, _ = SPEC[(t, k)]
        holders = [s for s in srcs if s.has(t, k)]
        if not holders:
            continue
        pool = INTS if kind == "int" else NUMS
        vals = rng.sample([v for v in pool if v not in NONFINITE], 2) + [rng.choice(NONFINITE) if kind == "num"
                                                                        else rng.choice(["1e3", "1.5"])]
        for v in vals:
            s = rng.choice(holders)
            site = s.site(t, k)
            slug = v if len(v) <= 10 else f"{v[:3]}_{len(v.lstrip('-'))}digits"
            _m(out, "extreme value", s, f"{t}.{k}={slug}", s.set_value(site, v), _num_expect(kind, cons, v, k), k)
    # the keys that set the size of the problem, at sizes that would exhaust memory or time
    for t, k, v in (("shaft", "elements", "100000000"), ("shaft", "elements", "2000000"),
                    ("speed", "points", "10000000000"), ("controller", "delay_samples", "1000000000000"),
                    ("simulation", "record_every", "9223372036854775807"),
                    ("simulation", "newton_iterations", "1000000000000"),
                    ("controller", "sample_rate", "1e300"), ("controller", "sample_rate", "1e-300"),
                    ("simulation", "duration", "1e300"), ("analysis", "frequency_max", "1e300"),
                    ("model", "modal_cutoff", "1e-300")):
        s = base
        text = s.set_value(s.site(t, k), v) if s.has(t, k) else s.insert_after(s.block(t)[0], f"{k} = {v}\n")
        _m(out, "extreme value", s, f"size-{t}.{k}={v[:8]}", text, "any", k)
    for v in ("1e300", "1e-300", "1e30"):  # every AMB parameter at once (a scale error)
        s = pick()
        text = s.edit({x.line: s.value_line(x, v) for x in s.sites
                       if x.table == "amb" and x.key in ("turns", "pole_area", "bias_current")})
        _m(out, "extreme value", s, f"amb-scale-{v}", text, "any", ("turns", "pole_area", "bias_current"))

    # ---- nodes and stations
    n = base.n_nodes
    for t in ("disc", "amb", "unbalance"):
        for v in ("0", "-1", str(n + 1), "1000000", "9223372036854775807"):
            s = pick()
            _m(out, "out-of-range node", s, f"{t}.node={v}", s.set_value(s.site(t, "node"), v), "error", "node")
    for t, key, v in (("amb", "position", "-0.1"), ("amb", "position", "1.6"), ("disc", "position", "0.333"),
                      ("unbalance", "position", "1e300"), ("amb", "sensor_node", "0"),
                      ("amb", "sensor_node", str(n + 1)), ("amb", "sensor_position", "-1.0")):
        s = pick()
        node_site = s.site(t, "node")
        ln = f"{key} = {v}\n"  # position replaces node; a sensor station is added beside it
        text = s.edit({node_site.line: ln if key == "position" else s.lines[node_site.line] + ln})
        _m(out, "out-of-range node", s, f"{t}.{key}={v}", text, "error", key)
    for t, v in (("analysis", "[0, 21]"), ("analysis", f"[21, {n + 1}]"), ("simulation", "[-5]"),
                 ("simulation", "[21, 1000000000000]")):
        s = base
        _m(out, "out-of-range node", s, f"{t}.output_nodes={v}", s.set_value(s.site(t, "output_nodes"), v),
           "error", "output_nodes")
    s = three
    if s.has("analysis", "sweep_amb"):
        _m(out, "out-of-range node", s, "sweep_amb=Q", s.set_value(s.site("analysis", "sweep_amb"), '"Q"'),
           "error", "sweep_amb")

    # ---- duplicated stations
    s = three
    a0, a1 = s.block("amb", 0)
    amb_a = "".join(s.lines[a0:a1])
    last = s.block("amb", 2)[1] - 1
    _m(out, "duplicated station", s, "amb-dup-verbatim", s.insert_after(last, "\n" + amb_a), "error", ("name", "node"))
    _m(out, "duplicated station", s, "amb-dup-same-node",
       s.insert_after(last, "\n" + amb_a.replace('name = "A"', 'name = "D"')), "error", "node")
    _m(out, "duplicated station", s, "amb-dup-same-name",
       s.insert_after(last, "\n" + amb_a.replace("node = 21", "node = 12")), "error", "name")
    d0, d1 = s.block("disc", 0)
    _m(out, "duplicated station", s, "disc-dup", s.insert_after(d1 - 1, "".join(s.lines[d0:d1])), "any")
    u0, u1 = base.block("unbalance", 0)
    _m(out, "duplicated station", base, "unbalance-dup", base.insert_after(u1 - 1, "".join(base.lines[u0:u1])), "any")
    _m(out, "duplicated station", base, "amb-on-disc-node", base.set_value(base.site("amb", "node", 1), "48"), "any")
    _m(out, "duplicated station", base, "output-nodes-dup",
       base.set_value(base.site("analysis", "output_nodes"), "[21, 21, 30, 30]"), "any")
    _m(out, "duplicated station", base, "sim-output-nodes-dup",
       base.set_value(base.site("simulation", "output_nodes"), "[57, 57]"), "any")
    _m(out, "duplicated station", base, "axial-on-amb-node",
       base.text + '\n[axial_amb]\nnode = 21\ngap = 5e-4\nbias_current = 2.0\nturns = 100\npole_area = 1e-3\n', "any")
    _m(out, "duplicated station", base, "two-axial-tables",
       base.text + '\n[axial_amb]\nnode = 1\ngap = 5e-4\nbias_current = 2.0\nturns = 100\npole_area = 1e-3\n' * 2,
       "error")

    # ---- bad encodings
    b = base.text.encode("utf-8")
    lines = base.text.splitlines(keepends=True)
    k = rng.randrange(5, len(lines) - 5)
    latin = "".join(lines[:k]) + "# caf\xe9 r\xf6tor\n" + "".join(lines[k:])
    _m(out, "encoding", base, "latin1-comment", latin.encode("latin-1"), "error", "byte")
    _m(out, "encoding", base, "latin1-string",
       base.text.replace("two isotropic", "zwei L\xe4ger", 1).encode("latin-1"), "error", "byte")
    _m(out, "encoding", base, "cp1252-quotes",
       base.text.replace('"paper_2amb"', '\u201cpaper_2amb\u201d', 1).encode("cp1252"), "error", "byte")
    for j in range(4):
        pos = rng.randrange(len(b))
        _m(out, "encoding", base, f"byte-ff-at-{pos}", b[:pos] + b"\xff" + b[pos:], "error", "byte")
    _m(out, "encoding", base, "overlong-slash", b.replace(b"# Su et al.", b"# Su \xc0\xaf et al.", 1), "error", "byte")
    _m(out, "encoding", base, "surrogate", b.replace(b"# Su et al.", b"# Su \xed\xa0\x80 et al.", 1), "error", "byte")
    _m(out, "encoding", base, "truncated-utf8-seq", b + "\u00e9".encode()[:1], "error", "byte")
    _m(out, "encoding", base, "utf8-bom", b"\xef\xbb\xbf" + b, "any", "byte")
    _m(out, "encoding", base, "utf16-le-bom", base.text.encode("utf-16"), "error", ("utf-16", "byte"))
    _m(out, "encoding", base, "utf16-be-bom", b"\xfe\xff" + base.text.encode("utf-16-be"), "error", ("utf-16", "byte"))
    _m(out, "encoding", base, "utf16-le-nobom", base.text.encode("utf-16-le"), "error")
    _m(out, "encoding", base, "utf32-bom", base.text.encode("utf-32"), "error", ("utf-32", "utf-16", "byte"))
    _m(out, "encoding", base, "nul-byte", b.replace(b"[controller]", b"[contr\x00oller]", 1), "error")
    _m(out, "encoding", base, "random-bytes", bytes(rng.randrange(256) for _ in range(4096)), "error")

    # ---- TOML syntax errors
    c = base.block("controller")[0]
    kp = base.site("controller", "kp")
    syn = [
        ("header-unclosed", base.edit({c: "[controller\n"})),
        ("aot-unclosed", base.edit({base.block("amb", 0)[0]: "[[amb]\n"})),
        ("string-unterminated", base.edit({base.site("scene", "name").line: 'name = "paper_2amb\n'})),
        ("value-missing", base.edit({kp.line: "kp =\n"})),
        ("equals-missing", base.edit({kp.line: "kp 5.98869\n"})),
        ("key-duplicated", base.insert_after(kp.line, "kp = 1.0\n")),
        ("table-duplicated", base.text + "\n[controller]\nkp = 1.0\n"),
        ("garbage-line", base.insert_after(kp.line, "!!! what\n")),
        ("bad-escape", base.edit({base.site("scene", "description").line: 'description = "a\\qb"\n'})),
        ("multiline-unterminated", base.edit({base.site("scene", "description").line: 'description = """abc\n'})),
        ("number-two-dots", base.set_value(kp, "1.2.3")),
        ("number-bad-underscore", base.set_value(kp, "1__0")),
        ("hex-float", base.set_value(kp, "0x1.8p3")),
        ("bad-date", base.set_value(kp, "1979-02-30")),
        ("array-unclosed", base.set_value(base.site("analysis", "output_nodes"), "[21, 30")),
        ("inline-table-newline", base.set_value(kp, "{ a = 1,\n b = 2 }")),
        ("redefine-aot-as-value", base.text + "\namb = 5\n"),
        ("dotted-key-in-table", base.insert_after(kp.line, "controller.kp = 5.0\n")),
        ("top-level-scalar-table", "controller = 5\n" + base.text.replace("[controller]", "[controllerX]", 1)),
        ("aot-instead-of-table", base.edit({c: "[[controller]]\n"})),
        ("table-instead-of-aot", base.text.replace("[[unbalance]]", "[unbalance]", 1)),
        ("empty-table", base.edit({i: "" for i in range(c + 1, base.block("controller")[1]) })),
        ("empty-file", ""),
        ("only-comments", "# nothing here\n# at all\n"),
        ("unknown-table", base.text + "\n[extra]\nx = 1\n"),
        ("crlf", base.text.replace("\n", "\r\n")),
        ("lone-cr", base.text.replace("\n", "\r", 3)),
    ]
    valid_syntax = {"crlf", "empty-table"}
    for slug, text in syn:
        exp = "any" if slug == "crlf" else "error"
        frag = "kp" if slug == "empty-table" else ()
        _m(out, "syntax", base, slug, text, exp, frag)
    for j in range(8):  # truncated files (a cut at a line end may leave a valid scene)
        s = pick()
        cut = rng.randrange(1, len(s.text) - 1)
        _m(out, "syntax", s, f"truncated-at-{cut}", s.text[:cut], "any")
    for slug in ("no-controller", "no-amb", "no-shaft"):
        s = pick()
        tname = slug[3:]
        drop = {}
        for t, nth, i in s.headers:
            if t == tname:
                a, e = s.block(t, nth)
                drop.update({x: "" for x in range(a, e)})
        _m(out, "missing key", s, slug, s.edit(drop), "error", tname)

    # ---- absurd nesting
    o = base.site("analysis", "output_nodes")
    for depth in (5000, 6500):  # deep, and still under the 16 KiB file limit
        _m(out, "nesting", base, f"array-depth-{depth}", base.set_value(o, "[" * depth + "]" * depth), "error",
           ("nest", "deep"))
    _m(out, "nesting", base, "array-depth-100000-over-16KiB", base.set_value(o, "[" * 100000 + "]" * 100000),
       "error", ("larger than",))
    _m(out, "nesting", base, "inline-table-depth-3000",
       base.set_value(o, "{a=" * 3000 + "1" + "}" * 3000), "error", ("nest", "deep"))
    _m(out, "nesting", base, "array-depth-300", base.set_value(o, "[" * 300 + "21" + "]" * 300), "error",
       "output_nodes")
    _m(out, "nesting", base, "dotted-header-depth-5000", base.text + "\n[" + ".".join(["a"] * 5000) + "]\nx = 1\n",
       "error")
    m_ = base.site("amb", "gap")
    _m(out, "nesting", base, "pair-nested", base.set_value(m_, "[[1e-4, 1e-4]]"), "error", "gap")

    # ---- huge files
    big_comment = "# " + "x" * 120 + "\n"
    _m(out, "huge", base, "comments-3MiB", base.text + big_comment * (3 * 2 ** 20 // len(big_comment)), "any")
    _m(out, "huge", base, "comments-40MiB", base.text + big_comment * (40 * 2 ** 20 // len(big_comment)), "any")
    _m(out, "huge", base, "description-900KiB",
       base.set_value(base.site("scene", "description"), '"' + "d" * (900 * 2 ** 10) + '"'), "any")
    _m(out, "huge", base, "unbalance-tables-5000",
       base.text + "".join(f"\n[[unbalance]]\nnode = {2 + j % 60}\nmagnitude = 1e-9\n" for j in range(5000)), "any")
    _m(out, "huge", base, "output-nodes-200k",
       base.set_value(base.site("simulation", "output_nodes"), "[" + ", ".join(["21"] * 200000) + "]"), "any")
    _m(out, "huge", base, "key-name-900KiB", base.insert_after(kp.line, "k" * (900 * 2 ** 10) + " = 1\n"), "error")
    _m(out, "huge", base, "table-name-900KiB", base.text + "\n[" + "t" * (900 * 2 ** 10) + "]\n", "error")
    _m(out, "huge", base, "name-100k", base.set_value(base.site("scene", "name"), '"' + "n" * 100000 + '"'), "any",
       "name")
    for v in ('"a/b"', '"run*1"', '""', '"two words"', '"x#y"', '"../../escape"'):
        _m(out, "name", base, f"name={v[:8]}", base.set_value(base.site("scene", "name"), v), "any", "name")

    # ---- scene-level consistency
    st = base.site("simulation", "step")
    for v in ("3e-5", "2e-4", "7e-5"):
        _m(out, "consistency", base, f"step={v}", base.set_value(st, v),
           {"analyze": "ok", "simulate": "error", "run": "error"}, "step")
        _m(out, "consistency", base, f"step={v}+--h", base.set_value(st, v),
           {"analyze": "ok", "simulate": "ok", "run": "error"}, "step", extra={"simulate": ["--h", "1e-4"]})
    _m(out, "consistency", base, "step=5e-5", base.set_value(st, "5e-5"), "ok")
    ig = base.site("simulation", "integrator")
    _m(out, "consistency", base, "zoh+nonlinear", base.insert_after(ig.line, 'force_law = "nonlinear"\n')
       .replace(f"integrator = {ig.value}", 'integrator = "zoh"'), "error", "integrator")
    _m(out, "consistency", base, "zoh+run_up", base.insert_after(ig.line, "run_up = [0.0, 100.0]\n")
       .replace(f"integrator = {ig.value}", 'integrator = "zoh"'), "error", "integrator")
    _m(out, "consistency", base, "kd-without-filter", base.drop(base.site("controller", "derivative_filter")),
       "error", "derivative_filter")
    _m(out, "consistency", base, "range-reversed", base.set_value(base.site("speed", "range"), "[4000.0, 0.0]"),
       "error", "range")
    _m(out, "consistency", base, "inner-ge-outer",
       base.insert_after(base.site("shaft", "length").line, "inner_diameter = 0.2\n"), "error", "inner_diameter")
    _m(out, "consistency", base, "current-limit-too-low",
       by.get("paper_3amb_misaligned", base).text.replace("current_limit = 4.0", "current_limit = 1.0"),
       "error", "current_limit")
    mis = by.get("paper_3amb_misaligned")
    if mis is not None:
        _m(out, "consistency", mis, "misalignment-ge-gap",
           mis.set_value(mis.site("amb", "misalignment", 1), "[0.0, 1.5e-4]"), "error", "misalignment")
    _m(out, "consistency", base, "run_up-negative", base.insert_after(ig.line, "run_up = [-1.0, 100.0]\n"),
       "error", "run_up")
    _m(out, "consistency", base, "rho_inf=2", base.insert_after(ig.line, "rho_inf = 2.0\n"), "error", "rho_inf")
    _m(out, "consistency", base, "speed-value-and-range", base.insert_after(base.site("speed", "range").line,
                                                                            "value = 10.0\n"), "error", "value")
    _m(out, "consistency", base, "delay-5", base.insert_after(kp.line, "delay_samples = 5\n"), "any")
    return out


# --------------------------------------------------------------------------- driving the CLI
class Hang(BaseException):
    """The CPU-time watchdog fired."""


class _Spawned(BaseException):
    """`run` reached the point where it starts its processes."""


class _Live(BaseException):
    """A `plant` / `controller` command reached the point where it goes on the network."""


@dataclass
class Call:
    code: object  # int, or "spawned" / "live" for the stubbed stages
    out: str
    err: str
    exc: str | None = None  # an exception that escaped main (type: message)
    tb: str = ""


@contextlib.contextmanager
def _watchdog(seconds: float):
    """Raise Hang in the main thread after `seconds` of this process's CPU time (not wall time:
    a busy machine slows a call down without making it look hung)."""
    def fire(signum, frame):
        raise Hang(f"more than {seconds:g} s of CPU time")
    old = signal.signal(signal.SIGPROF, fire)
    signal.setitimer(signal.ITIMER_PROF, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, old)


def call(argv: list[str], cpu_limit: float = CPU_LIMIT_S) -> Call:
    """Run ``ambhil.bridge.cli.main.main(argv)`` in-process with stdout/stderr captured."""
    from ambhil.bridge.cli import main as cli
    out, err = io.StringIO(), io.StringIO()
    res = Call(None, "", "")
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
            warnings.catch_warnings(record=True) as warned:
        warnings.simplefilter("always")
        try:
            with _watchdog(cpu_limit):
                res.code = cli.main(argv)
        except SystemExit as e:
            res.code = e.code if isinstance(e.code, int) else (2 if e.code else 0)
            if e.code not in (None, 0) and not isinstance(e.code, int):
                print(e.code, file=sys.stderr)
        except _Spawned:
            res.code = "spawned"
        except _Live:
            res.code = "live"
        except Hang as e:
            res.exc = f"hang: {e}"
        except BaseException as e:  # what would reach the user as a traceback
            res.exc = f"{type(e).__name__}: {str(e)[:200]}"
            res.tb = traceback.format_exc()
    for w in warned:  # Python prints these on stderr
        err.write(warnings.formatwarning(w.message, w.category, w.filename, w.lineno))
    res.out, res.err = out.getvalue(), err.getvalue()
    return res


class Stubs:
    """The quick tier's stand-ins (see the module docstring); a context manager."""

    def __init__(self):
        self.spawned: list[list[str]] = []

    def __enter__(self):
        import ambhil.bridge.process.controller_node as cn
        import ambhil.bridge.process.plant_node as pn
        import ambhil.bridge.cli.run as br
        import ambhil.loop.report as an
        import ambhil.loop.orbit_plots as ps
        from ambhil.loop.system import compile_system
        self._saved = []
        stubs = self

        def patch(obj, name, value):
            self._saved.append((obj, name, getattr(obj, name)))
            setattr(obj, name, value)

        class Child:  # bridge.cli.run.Child: records what `run` would start, stops at the plant
            class p:                  # a process that already ended (run stops the others)
                @staticmethod
                def poll():
                    return 0

            def __init__(self, name, argv, echo, external=False, env=None):
                stubs.spawned.append(list(argv))
                if argv[0] == "plant":  # the last of the three: stop here
                    raise _Spawned()

        def live(*a, **k):
            raise _Live()
        patch(br, "Child", Child)
        patch(pn, "run_plant", live)
        patch(cn, "run_controller", live)

        def run_scene(scene, out, sweep=True, campbell_points=41, progress=None):
            compile_system(scene)
            raise _Live()
        patch(an, "run_scene", run_scene)
        patch(ps, "plot_orbits", lambda res, out_dir, nodes=None, gaps=None, clearances=None: [])
        # the sampled-loop checks before simulate/run are numerics, not input handling (tested in
        # test_timing_study/test_loop_stability); seconds per scene on the full rung
        import ambhil.loop.numerics as nm
        import ambhil.loop.timing_study as ts
        patch(ts, "precheck", lambda *a, **k: ts.Precheck(True, None))
        patch(nm, "numerics_warning", lambda *a, **k: None)
        return self

    def __exit__(self, *exc):
        for obj, name, value in reversed(self._saved):
            setattr(obj, name, value)


def _error_defect(m: Mutation, path: Path, err: str) -> str | None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if "Traceback" in err:
        return "traceback on stderr"
    if len(lines) != 1:
        return f"{len(lines)} lines on stderr: {' | '.join(lines)[:1500]}"
    line = lines[0]
    if path.name not in line:
        return f"error does not name the file: {line[:300]}"
    if len(line) > 400:
        return f"error line of {len(line)} characters: {line[:200]}..."
    if m.fragment and not any(f.lower() in line.lower() for f in m.fragment):
        return f"error does not name {' / '.join(m.fragment)}: {line[:300]}"
    return None


def _run_probe(m: Mutation, path: Path, tmp: Path, stubs: Stubs) -> tuple[str, str]:
    """`run` was stopped at its spawn: check what it would start."""
    from ambhil.bridge import protocol as pr
    argvs = {a[0]: a for a in stubs.spawned}
    rec = argvs.get("record")
    if rec is None or "controller" not in argvs:
        return "defect", f"run reached the plant spawn without the others: {sorted(argvs)}"
    rid = rec[rec.index("--run-id") + 1]
    try:
        pr.keys(rid)
    except ValueError as e:
        return "defect", f"run would start its processes with an unusable run id: {e}"[:300]
    mcap = Path(rec[rec.index("--out") + 1]) / f"{rid}.mcap"  # record --out is the folder
    if len(mcap.name.encode()) > 255 or mcap.parent.resolve() != (tmp / "rec").resolve():
        return "defect", f"run would record to an unwritable path {str(mcap)[:120]}"
    for child in ("controller", "plant"):
        stubs.spawned.clear()
        argv = list(argvs[child])
        if "--key-file" in argv:    # the run's key file went with the run: a key of our own
            from ambhil.bridge.protocol.auth import write_key_file
            key = tmp / "probe.key"
            if not key.exists():
                write_key_file(str(key))
            argv[argv.index("--key-file") + 1] = str(key)
        r = call(argv)
        if r.code == "live":
            continue
        why = r.exc or (r.err.strip().splitlines() or [f"exit {r.code}"])[-1]
        return "defect", f"run would start processes for a scene its {child} refuses: {why[:250]}"
    return "ok", ""


def classify(m: Mutation, cmd: str, path: Path, r: Call, tmp: Path, stubs: Stubs) -> tuple[str, str]:
    exp = m.expected(cmd)
    if r.exc:
        return "defect", r.exc
    if r.code == 2:
        why = _error_defect(m, path, r.err)
        if why:
            return "defect", why
        if exp == "ok":
            return "defect", f"valid scene refused: {r.err.strip()[:300]}"
        return "error", ""
    if "Traceback" in r.err:
        return "defect", "traceback on stderr"
    if exp == "error" and r.code in (0, 1, "spawned", "live"):
        return "defect", f"bad scene accepted (exit {r.code})"
    if cmd == "run" and r.code == "spawned":
        return _run_probe(m, path, tmp, stubs)
    if cmd == "analyze" and r.code == "live" or r.code == 0:
        return "ok", ""
    if cmd == "simulate" and r.code == 1 and ("FAULT" in r.out or "NOT STEADY" in r.out):
        return "fault", ""  # a scene whose loop faults or grows says so and exits 1
    return "defect", f"exit code {r.code}: {(r.err.strip().splitlines() or [''])[-1][:200]}"


def argv_for(cmd: str, path: Path, tmp: Path, m: Mutation, real: bool = False) -> list[str]:
    a = {"analyze": ["analyze", str(path), "--no-sweep"],
         "simulate": ["simulate", str(path), "--out", str(tmp / "sim"), "--duration", TINY],
         "run": ["run", str(path), "--duration", TINY, "--out", str(tmp / "rec")]}[cmd]
    if real and cmd == "run":  # time out only on a peer that is gone, not on a busy machine
        a += ["--start-timeout", "600", "--reply-timeout", "600000"]
    return a + list(m.extra.get(cmd, []))


@dataclass
class Outcome:
    mutation: Mutation
    command: str
    category: str
    detail: str


def _one(m: Mutation, path: Path, tmp: Path, full: bool, real: tuple[str, ...]) -> list[tuple[str, str, str]]:
    rows = []
    for cmd in COMMANDS:
        with Stubs() as stubs:
            r = call(argv_for(cmd, path, tmp, m))
            cat, why = classify(m, cmd, path, r, tmp, stubs)
        if cat == "defect" and " lines on stderr: " in why:
            # warnings are process-wide: a finalizer of an earlier call's object (collected
            # during this call) or another thread can warn inside this call's capture.  What
            # the call itself prints repeats; collect first and run it once more.
            gc.collect()
            with Stubs() as stubs:
                r = call(argv_for(cmd, path, tmp, m))
                cat, why = classify(m, cmd, path, r, tmp, stubs)
        rows.append((cmd, cat, why))
    if full or any(m.id.endswith(x) for x in real):
        for cmd, cat, _ in list(rows):  # unstubbed, where the scene is valid for the command
            if cat not in ("ok", "fault") or not full and cmd != "simulate":
                continue
            r = call(argv_for(cmd, path, tmp, m, real=True), cpu_limit=600.0)
            cat, why = classify(m, cmd, path, r, tmp, Stubs())
            rows.append((cmd + " (real)", cat, why))
    return rows


def _isolated(m: Mutation, path: Path, tmp: Path, full: bool, real: tuple[str, ...],
              mem_limit: int) -> list[tuple[str, str, str]]:
    """_one in a forked child with an address-space limit: a mutation that exhausts memory or
    kills the interpreter becomes a defect instead of ending the fuzz."""
    import pickle
    import resource
    rfd, wfd = os.pipe()
    pid = os.fork()
    if pid == 0:  # child
        os.close(rfd)
        try:
            resource.setrlimit(resource.RLIMIT_AS, (mem_limit, mem_limit))
            data = pickle.dumps(_one(m, path, tmp, full, real))
        except BaseException as e:
            data = pickle.dumps([(c, "defect", f"fuzz child failed: {type(e).__name__}") for c in COMMANDS])
        with os.fdopen(wfd, "wb") as f:
            f.write(data)
        os._exit(0)
    os.close(wfd)
    with os.fdopen(rfd, "rb") as f:
        data = f.read()
    _, status = os.waitpid(pid, 0)
    if data:
        return pickle.loads(data)
    how = f"signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status) else f"exit {os.WEXITSTATUS(status)}"
    return [(c, "defect", f"the process died ({how})") for c in COMMANDS]


def run_fuzz(muts: list[Mutation], tmp: Path, *, full: bool = False, real: tuple[str, ...] = (),
             isolate: bool = False, mem_limit: int = 6 << 30, progress=None) -> list[Outcome]:
    """Drive every mutation through the three commands (quick tier); ``real``: mutation id
    suffixes whose valid scenes also run ``simulate`` and ``run`` unstubbed; ``full``: every valid
    mutation runs all three unstubbed; ``isolate``: each mutation in a forked, memory-limited child."""
    os.environ.pop("AMBHIL_DEBUG", None)
    results = []
    tmp.mkdir(parents=True, exist_ok=True)
    if isolate:  # import and load the kernels once, before the forks
        _one(muts[0], SCENES[0], tmp, False, ())
    for k, m in enumerate(muts):
        path = tmp / f"{m.id}.toml"
        path.write_bytes(m.data)
        rows = _isolated(m, path, tmp, full, real, mem_limit) if isolate else _one(m, path, tmp, full, real)
        results += [Outcome(m, cmd, cat, why) for cmd, cat, why in rows]
        path.unlink()
        if progress:
            progress(k, m, results[-len(rows):])
    return results


def summary(results: list[Outcome]) -> str:
    cats = ("error", "ok", "fault", "defect")
    cmds = list(dict.fromkeys(o.command for o in results))
    muts = len({o.mutation.id for o in results})
    lines = [f"scene fuzz: {muts} mutations of {len(SCENES)} shipped scenes, {len(results)} command runs (seed {SEED})",
             f"  {'command':16s}" + "".join(f"{c:>8s}" for c in cats)]
    for c in cmds:
        cnt = Counter(o.category for o in results if o.command == c)
        lines.append(f"  {c:16s}" + "".join(f"{cnt[x]:8d}" for x in cats))
    tot = Counter(o.category for o in results)
    lines.append(f"  {'all':16s}" + "".join(f"{tot[x]:8d}" for x in cats))
    bycat = Counter()
    for o in results:
        if o.category == "defect":
            bycat[o.mutation.category] += 1
    if bycat:
        lines.append("  defects by mutation class: " + ", ".join(f"{k} {v}" for k, v in sorted(bycat.items())))
    per = Counter(o.mutation.category for o in results if o.command == "analyze")
    lines.append("  mutations by class: " + ", ".join(f"{k} {v}" for k, v in sorted(per.items())))
    for o in results:
        if o.category == "defect":
            lines.append(f"  DEFECT {o.mutation.id} [{o.command}]: {o.detail}")
    return "\n".join(lines)


def main(argv=None) -> int:
    import argparse
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="run every valid mutation unstubbed")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--only", help="run only mutations whose id contains this")
    ap.add_argument("--isolate", action="store_true", help="each mutation in a forked, memory-limited child")
    a = ap.parse_args(argv)
    muts = generate()
    if a.only:
        muts = [m for m in muts if a.only in m.id]
    if a.list:
        for m in muts:
            print(f"{m.id:50s} {m.category:20s} {len(m.data):9d} B expect {m.expect}")
        return 0
    with tempfile.TemporaryDirectory() as d:
        def prog(k, m, res):
            bad = [o for o in res if o.category == "defect"]
            print(f"[{k + 1}/{len(muts)}] {m.id}: " + ", ".join(f"{o.command} {o.category}" for o in res)
                  + "".join(f"\n      {o.command}: {o.detail}" for o in bad), file=sys.__stderr__, flush=True)
        res = run_fuzz(muts, Path(d), full=a.full, isolate=a.isolate, progress=prog)
    print(summary(res))
    return 1 if any(o.category == "defect" for o in res) else 0


if __name__ == "__main__":
    sys.exit(main())
