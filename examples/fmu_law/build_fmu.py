"""Builds the example controller FMU (pid_law.c, a discrete PID per axis) for FMI 2.0 or 3.0
co-simulation: compiles it with a C compiler against the standard's headers that fmpy ships
(fmpy/c-code) and zips the library with its modelDescription.xml::

    python examples/fmu_law/build_fmu.py --fmi 2 --out DIR      # -> DIR/pid_law_fmi2.fmu
    python examples/fmu_law/build_fmu.py --fmi 3 --out DIR      # -> DIR/pid_law_fmi3.fmu
    ambhil simulate scenes/paper_3amb.toml --law DIR/pid_law_fmi2.fmu

Options: ``--axes`` the loop's axes (default those of scenes/paper_3amb.toml), ``--inputs`` /
``--outputs`` the variable names (default ``y_<axis>`` / ``u_<axis>``, ``-`` written ``_``, the
names the testbench matches by itself: controller/law_fmu.py), ``--cc`` the compiler (default
``$CC`` or ``cc``).  The FMU holds a binary for this machine only (``binaries/linux64`` for
FMI 2.0, ``binaries/x86_64-linux`` for 3.0 on x86-64 Linux).  Its parameters (kp, ki, kd, td,
u_op_<axis>, fail_after) are set from the scene's ``[controller.params]``; their start values are
the paper scene's PID gains.

The functions of the standard that pid_law.c does not implement are stubs returning Error,
generated from the header's function types (``fmi2FunctionTypes.h`` / ``fmi3FunctionTypes.h``) so
that each has the standard's exact signature.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import uuid
import zipfile
from pathlib import Path
from string import Template
from xml.sax.saxutils import quoteattr

HERE = Path(__file__).resolve().parent
MODEL = "pid_law"
#: the axes of scenes/paper_3amb.toml, in the loop's order
AXES = ("A-x", "A-y", "B-x", "B-y", "C-x", "C-y")
#: the parameters' start values: the PID of scenes/paper_3amb.toml (kp A/V, ki A/(V s), kd A s/V,
#: td the derivative filter's time constant, s)
START = {"kp": 5.98869, "ki": 20.0, "kd": 3.245942e-3, "td": 1.0e-4}
DESCRIPTION = {"kp": "proportional gain", "ki": "integral gain", "kd": "derivative gain",
               "td": "derivative filter time constant (s)"}
VR = {"kp": 1, "ki": 2, "kd": 3, "td": 4, "fail_after": 5}
VR_Y, VR_U, VR_UOP = 100, 200, 300


def fmi_headers() -> Path:
    """The folder of the FMI headers fmpy ships."""
    try:
        import fmpy
    except ImportError:
        raise SystemExit("build_fmu.py: needs fmpy (its FMI headers): pip install 'ambhil[fmu]'") from None
    return Path(fmpy.__file__).parent / "c-code"


def axis_name(axis: str) -> str:
    """An axis as a variable name: ``A-x`` -> ``A_x``."""
    return re.sub(r"[^0-9A-Za-z_]", "_", axis)


def model_description(fmi: int, axes, inputs, outputs, token: str) -> str:
    """The modelDescription.xml of pid_law.c for ``axes`` (template ``modelDescription_fmi<N>.xml``)."""
    rows, outs = [], []
    if fmi == 3:
        rows.append('    <Float64 name="time" valueReference="0" causality="independent" variability="continuous"/>')
        par = '    <Float64 name={n} valueReference="{vr}" causality="parameter" variability="fixed" ' \
              'start="{v!r}" description={d}/>'
        for k, v in START.items():
            rows.append(par.format(n=quoteattr(k), vr=VR[k], v=v, d=quoteattr(DESCRIPTION[k])))
        rows.append(f'    <Int32 name="fail_after" valueReference="{VR["fail_after"]}" causality="parameter" '
                    f'variability="fixed" start="0" description="doStep fails from this step on (0: never)"/>')
        for a, (ax, y, u) in enumerate(zip(axes, inputs, outputs)):
            rows.append(par.format(n=quoteattr(f"u_op_{axis_name(ax)}"), vr=VR_UOP + a, v=0.0,
                                   d=quoteattr(f"operating-point amplifier input of axis {ax}")))
            rows.append(f'    <Float64 name={quoteattr(y)} valueReference="{VR_Y + a}" causality="input" '
                        f'start="0.0" description={quoteattr(f"sensor output of axis {ax}")}/>')
            rows.append(f'    <Float64 name={quoteattr(u)} valueReference="{VR_U + a}" causality="output" '
                        f'variability="discrete" description={quoteattr(f"amplifier input of axis {ax}")}/>')
        outs = [f'    <Output valueReference="{VR_U + a}"/>' for a in range(len(axes))]
        outs += [f'    <InitialUnknown valueReference="{VR_U + a}"/>' for a in range(len(axes))]
    else:
        sv = '    <ScalarVariable name={n} valueReference="{vr}" causality="{c}" variability="{var}"{i} ' \
             'description={d}><{t}{s}/></ScalarVariable>'
        index = 0

        def add(n, vr, c, var, t, start, d, initial=""):
            nonlocal index
            index += 1
            rows.append(sv.format(n=quoteattr(n), vr=vr, c=c, var=var, t=t, d=quoteattr(d),
                                  s="" if start is None else f' start="{start!r}"',
                                  i=f' initial="{initial}"' if initial else ""))
            return index
        for k, v in START.items():
            add(k, VR[k], "parameter", "fixed", "Real", v, DESCRIPTION[k])
        add("fail_after", VR["fail_after"], "parameter", "fixed", "Integer", 0,
            "doStep fails from this step on (0: never)")
        for a, (ax, y, u) in enumerate(zip(axes, inputs, outputs)):
            add(f"u_op_{axis_name(ax)}", VR_UOP + a, "parameter", "fixed", "Real", 0.0,
                f"operating-point amplifier input of axis {ax}")
            add(y, VR_Y + a, "input", "continuous", "Real", 0.0, f"sensor output of axis {ax}")
            i = add(u, VR_U + a, "output", "discrete", "Real", None, f"amplifier input of axis {ax}",
                    initial="calculated")
            outs.append(f'      <Unknown index="{i}"/>')
    template = Template((HERE / f"modelDescription_fmi{fmi}.xml").read_text())
    return template.substitute(model=MODEL, token=token, variables="\n".join(rows), outputs="\n".join(outs))


def stubs(fmi: int, source: str) -> str:
    """C definitions returning Error (NULL, nothing) of every function of the standard's header
    that ``source`` does not define."""
    header = (fmi_headers() / f"fmi{fmi}FunctionTypes.h").read_text()
    header = re.sub(r"/\*.*?\*/|//[^\n]*", "", header, flags=re.S)
    defined = set(re.findall(rf"^[A-Za-z_][\w \t]*?\**\s*(fmi{fmi}[A-Z]\w*)\s*\(", source, flags=re.M))
    out = [f'#include "fmi{fmi}Functions.h"', ""]
    for ret, name, params in re.findall(rf"typedef\s+([\w\s*]+?)\s*(fmi{fmi}\w+)TYPE\s*\((.*?)\)\s*;", header, flags=re.S):
        if name in defined:
            continue
        ret = " ".join(ret.split())
        body = ("" if ret == "void" else f"return fmi{fmi}Error;" if ret.endswith("Status")
                else "return NULL;")
        out.append(f"{ret} {name}({' '.join(params.split())}) {{ {body} }}")
    return "\n".join(out) + "\n"


def build_fmu(out_dir: str | Path, fmi: int = 2, axes=AXES, inputs=None, outputs=None,
              cc: str | None = None, file_name: str | None = None) -> Path:
    """Compile pid_law.c for FMI ``fmi`` (2 or 3) and ``axes`` and write the FMU into ``out_dir``
    (``pid_law_fmi<N>.fmu``, or ``file_name``); ``inputs`` / ``outputs``: the variable names of
    each axis (default ``y_<axis>`` / ``u_<axis>``).  Returns the FMU's path."""
    import fmpy
    if fmi not in (2, 3):
        raise ValueError(f"--fmi must be 2 or 3, got {fmi}")
    axes = tuple(axes)
    inputs = tuple(inputs or (f"y_{axis_name(a)}" for a in axes))
    outputs = tuple(outputs or (f"u_{axis_name(a)}" for a in axes))
    if not axes or len(axes) > 99 or not len(inputs) == len(outputs) == len(axes):
        raise ValueError(f"{len(axes)} axes (1..99), {len(inputs)} input and {len(outputs)} output names: "
                         f"one of each per axis")
    names = [*inputs, *outputs, *START, "fail_after", *(f"u_op_{axis_name(a)}" for a in axes)]
    if len(set(names)) != len(names):
        raise ValueError(f"variable names repeat: {sorted(n for n in set(names) if names.count(n) > 1)}")
    cc = cc or os.environ.get("CC") or "cc"
    if shutil.which(cc) is None:
        raise FileNotFoundError(f"no C compiler {cc!r} on PATH (set --cc or $CC)")
    token = "{" + str(uuid.uuid5(uuid.NAMESPACE_URL, f"ambhil/{MODEL}/fmi{fmi}/" + ",".join(names))) + "}"
    platform = fmpy.platform if fmi == 2 else fmpy.platform_tuple
    lib = f"binaries/{platform}/{MODEL}{fmpy.sharedLibraryExtension}"
    source = (HERE / "pid_law.c").read_text()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fmu = out_dir / (file_name or f"{MODEL}_fmi{fmi}.fmu")
    with tempfile.TemporaryDirectory(prefix="pid_law_build_") as tmp:
        tmp = Path(tmp)
        (tmp / "stubs.c").write_text(stubs(fmi, source))
        so = tmp / Path(lib).name
        defs = [f"-DFMI_VERSION={fmi}", f"-DN_AXES={len(axes)}",
                *(f"-D{k.upper()}_START={v!r}" for k, v in START.items())]
        cmd = [cc, "-shared", "-fPIC", "-O2", "-ffp-contract=off", "-fvisibility=hidden", "-std=c99",
               "-Wall", f"-I{fmi_headers()}", *defs, str(HERE / "pid_law.c"), str(tmp / "stubs.c"),
               "-o", str(so)]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stderr}")
        with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("modelDescription.xml", model_description(fmi, axes, inputs, outputs, token))
            z.write(so, lib)
    return fmu


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Build the example controller FMU (pid_law.c).")
    ap.add_argument("--fmi", type=int, choices=(2, 3), default=2, help="FMI version (default 2)")
    ap.add_argument("--out", default=".", help="folder for the .fmu (default: the working directory)")
    ap.add_argument("--axes", default=",".join(AXES), help="the loop's axes, comma-separated")
    ap.add_argument("--inputs", help="input variable names, one per axis (default y_<axis>)")
    ap.add_argument("--outputs", help="output variable names, one per axis (default u_<axis>)")
    ap.add_argument("--cc", help="C compiler (default $CC or cc)")
    a = ap.parse_args(argv)
    split = lambda s: [x.strip() for x in s.split(",")] if s else None  # noqa: E731
    try:
        fmu = build_fmu(a.out, a.fmi, split(a.axes), split(a.inputs), split(a.outputs), a.cc)
    except (ValueError, RuntimeError, FileNotFoundError) as e:
        print(f"build_fmu.py: {e}", file=sys.stderr)
        return 1
    print(fmu)
    return 0


if __name__ == "__main__":
    sys.exit(main())
