"""`twin run NAME [options]`: run a scenario found through the registry in :mod:`twin.cli`."""

from __future__ import annotations

import argparse
import importlib


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from twin.cli import SCENARIOS

    parser.add_argument("name", metavar="NAME", help="scenario: " + ", ".join(sorted(SCENARIOS)) if SCENARIOS
                        else "scenario name")
    parser.add_argument("options", nargs=argparse.REMAINDER, help="the scenario's own options (see NAME --help)")


def run(args: argparse.Namespace) -> int:
    from twin.cli import SCENARIOS, UserError

    if args.name not in SCENARIOS:
        known = ", ".join(sorted(SCENARIOS)) or "none installed"
        raise UserError(f"no scenario {args.name!r}; known scenarios: {known}")
    module = importlib.import_module(SCENARIOS[args.name])
    parser = argparse.ArgumentParser(prog=f"twin run {args.name}", description=module.__doc__)
    module.add_arguments(parser)
    return int(module.run(parser.parse_args(args.options)) or 0)
