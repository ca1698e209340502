"""The `twin` command line.

Each sub-command lives in its own module exposing ``add_arguments(parser)`` and ``run(args) -> int``; this file
only routes. Modules are imported when their command runs, so `twin --help` is quick and the sensing core never
imports the simulator. Scenarios (`twin run NAME`) are found through :data:`SCENARIOS`.

User mistakes (bad files, wrong options, unreachable sources) print one line on stderr and exit with status 2;
set TWIN_DEBUG=1 to see the traceback instead.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

#: command → (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("scenarios.demo", "the main job: reconstruct shapes from (simulated) interrogator data and compare"),
    "run": ("twin.scenario_cli", "run a scenario (an experiment of the paper, or our own)"),
    "bench": ("twin.bench", "measure reconstruction (and simulation, streaming) speed"),
    "live": ("twin.live_cli", "reconstruct shapes live from an interrogator, the simulator or a recording (URL)"),
    "replay": ("twin.replay_cli", "reconstruct a recording (twin HDF5 or ILLumiSense log) and summarise it"),
    "serve": ("sim_interrogator.serve", "serve a simulated interrogator over illumisense, fispec or hyperion"),
    "calibrate": ("twin.calibrate_cli", "two-step calibration (straight, then an in-plane bend) from a source"),
    "identify": ("twin.identify_cli", "identify Δθ and g = r·S_ε from recordings of shapes of known geometry"),
    "jig-calibrate": ("twin.jig_cli", "fit a calibration from jig poses (grooves of known curvature)"),
    "jig-validate": ("twin.jig_cli", "curvature and bend-direction errors of a calibration on jig poses"),
}

#: scenario name → module (each exposes add_arguments(parser) and run(args) -> int)
SCENARIOS: dict[str, str] = {
    "library": "scenarios.library",
    "static-shapes": "scenarios.static_shapes",
    "paper-ablation": "scenarios.paper_ablation",
    "temperature-bath": "scenarios.temperature_bath",
    "rotation": "scenarios.rotation",
    "repeatability": "scenarios.repeatability",
    "tendon": "scenarios.tendon",
    "sheath-motion": "scenarios.sheath_motion",
    "jig": "scenarios.jig",
}


class UserError(Exception):
    """An error caused by the user's input; reported as one line, no traceback."""


def _command_module(name: str):
    return importlib.import_module(COMMANDS[name][0])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="twin",
        description="Fibre-optic shape sensing of catheters, with a MuJoCo physics twin.",
    )
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_command=name)
    return parser


def _version() -> str:
    from twin import __version__

    return f"twin {__version__}"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    # Only the chosen command's module is imported and asked for its arguments.
    command = next((a for a in argv if not a.startswith("-")), None)
    if command in COMMANDS:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        _command_module(command).add_arguments(sub.choices[command])
    args = parser.parse_args(argv)
    if not getattr(args, "_command", None):
        parser.print_help()
        return 0
    try:
        return int(_command_module(args._command).run(args) or 0)
    except KeyboardInterrupt:
        print("twin: interrupted", file=sys.stderr)
        return 130
    except (UserError, ValueError, OSError, KeyError) as exc:
        if os.environ.get("TWIN_DEBUG"):
            raise
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"twin {args._command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
