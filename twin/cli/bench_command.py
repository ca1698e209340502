"""`twin bench [--json] [--out FILE] [--compare FILE] [--quick] [--sections LIST] [--cpu N]`: speed figures.

The measurements are :mod:`twin.bench`'s; ``--json`` prints one JSON object, ``--out FILE`` writes it and
``--compare FILE`` shows the change against an earlier run.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from twin import jsonout
from twin.bench import measure_in_child, report, sections

#: one-line help (read by `twin --help` without importing this module)
HELP = "measure reconstruction (and simulation, streaming) speed"

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the report")
    parser.add_argument("--out", type=Path, help="also write the JSON to this file")
    parser.add_argument("--compare", type=Path, help="compare with an earlier `twin bench --json` file")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (a rough figure in seconds)")
    known = ",".join(sections())
    parser.add_argument("--sections", default=known, help=f"comma-separated sections to run (default: {known})")
    parser.add_argument("--cpu", type=int, default=None, help="CPU to pin the measurement to (default: the last)")


def run(args: argparse.Namespace) -> int:
    known = sections()
    chosen = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = sorted(set(chosen) - set(known))
    if unknown:
        raise ValueError(f"unknown section(s) {', '.join(unknown)}; known: {', '.join(known)}")
    previous = None
    if args.compare:
        try:
            previous = json.loads(args.compare.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{args.compare}: not a JSON benchmark file ({exc})") from None
    result = measure_in_child(chosen, quick=args.quick, cpu=args.cpu)
    text = jsonout.dumps(result, indent=2)
    if args.out:
        args.out.write_text(text + "\n")
    if args.json:
        print(text)
    else:
        print(report(result, previous))
    return 0
