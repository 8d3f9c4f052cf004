"""The `ambhil` command line: analyses, simulation and the HIL processes."""
from __future__ import annotations

import argparse
import sys

from loop.scene import INPUT_ERRORS


def _analyze(args) -> int:
    from loop import report
    from .progress import Progress
    return report.main(args.scenes, args.out, sweep=not args.no_sweep, progress=Progress)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ambhil", description="HIL testbench for flexible rotors on active magnetic bearings")
    sub = p.add_subparsers(dest="command", required=True)
    a = sub.add_parser("analyze", help="critical speeds, stability, sensitivity, unbalance response, support sweep")
    a.add_argument("scenes", nargs="+", help="scene TOML file(s)")
    a.add_argument("--out", help="folder for PNG plots and report.txt")
    a.add_argument("--no-sweep", action="store_true", help="skip the support-position sweep")
    a.set_defaults(func=_analyze)
    for mod in ("commands_time", "commands_hil"):
        try:
            m = __import__(f"bridge.{mod}", fromlist=["add_parsers"])
        except ImportError as e:
            if e.name != f"bridge.{mod}":
                raise
            continue
        m.add_parsers(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except INPUT_ERRORS as e:
        print(f"ambhil: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("ambhil: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
