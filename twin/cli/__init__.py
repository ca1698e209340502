"""The `twin` command line.

Each sub-command lives in its own module exposing ``add_arguments(parser)`` and ``run(args) -> int``; this file
only routes. Every command — the core's and those of the packages above it (the demo, ``serve``, ``study``) — is
an entry point of the ``twin.commands`` group (:mod:`twin.registry`), and every ``twin run NAME`` one of
``twin.scenarios``. Modules are imported when their command runs (the help of the others is read from their
source), so `twin --help` is quick and the sensing core never imports the simulator.
A command that needs an optional dependency which is not installed says which extra installs it.

User mistakes (bad files, wrong options, unreachable sources) print one line on stderr and exit with status 2;
set TWIN_DEBUG=1 to see the traceback instead.

Ctrl-C, one rule for every command (README, "Exit status"): it always ends the command cleanly — a run that has
a summary prints it — and the exit status is 130 when it cut a bounded run short (``--duration``/``--frames``,
``twin run``, ``twin study``, ``twin calibrate``, the demo's run, any command computing a result) and 0 when it
stopped an open-ended one (``twin live``/``twin serve`` without a bound, a viewer's page kept open after its run):
:func:`interrupted_status`. A Ctrl-C that no command catches prints ``twin COMMAND: interrupted`` and exits with
130, whenever it comes: this module imports almost nothing at load time (the registry, the extras and every
command are imported inside :func:`main`'s handler, and ``twin`` itself loads its names lazily), so the handler
is in place within a few tens of milliseconds of start-up.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    from twin.extras import MissingExtra


#: exit status when Ctrl-C cut a bounded run short (128 + SIGINT, what a shell reports for a Ctrl-C)
EXIT_INTERRUPTED = 130


def interrupted_status(interrupted: bool, bounded: bool) -> int:
    """The exit status after a run that may have been ended by Ctrl-C (see the module docstring).

    Parameters
    ----------
    interrupted : bool
        Ctrl-C ended the run.
    bounded : bool
        The run had an end of its own (a duration, a frame count, a task list): Ctrl-C cut it short.

    Returns
    -------
    int
        :data:`EXIT_INTERRUPTED` (130) for a bounded run cut short, else 0.
    """
    return EXIT_INTERRUPTED if interrupted and bounded else 0


class UserError(Exception):
    """An error caused by the user's input; reported as one line, no traceback."""


def commands() -> dict[str, str]:
    """Every command (the core's and those of the packages above it): name → module, from the registry."""
    from twin import registry

    return registry.entries("twin.commands")


def scenarios() -> dict[str, str]:
    """Every registered scenario (``twin run NAME``): name → module."""
    from twin import registry

    return registry.entries("twin.scenarios")


def _command_module(name: str):
    from twin import registry

    return registry.load("twin.commands", name)


def missing_extra(exc: ImportError) -> MissingExtra | None:
    """The :class:`MissingExtra` behind an ImportError, or None when it is not a missing optional package."""
    from twin.extras import EXTRAS, MissingExtra

    if isinstance(exc, MissingExtra):
        return exc
    root = (getattr(exc, "name", None) or "").split(".")[0]
    return MissingExtra(root, EXTRAS[root]) if isinstance(exc, ModuleNotFoundError) and root in EXTRAS else None


def build_parser(described: str | None = None) -> argparse.ArgumentParser:
    """The router's parser. Each command's one-line help is read from its module's source (no import); with
    ``described`` only that command's is read (the list of all of them shows only when no command is given)."""
    from twin import registry

    parser = argparse.ArgumentParser(
        prog="twin",
        description="Fibre-optic shape sensing of catheters, with a MuJoCo physics twin.",
    )
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in commands():
        help_text = registry.summary("twin.commands", name) if described in (None, name) else None
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_command=name)
    return parser


def _version() -> str:
    from twin import __version__

    return f"twin {__version__}"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    try:
        known = command in commands()
        parser = build_parser(command if known else None)
        # Only the chosen command's module is imported and asked for its arguments.
        if known:
            sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
            _command_module(command).add_arguments(sub.choices[command])
        args = parser.parse_args(argv)
        if not getattr(args, "_command", None):
            parser.print_help()
            return 0
        module = _command_module(args._command)
        from twin import compile_notice

        compile_notice.install(args._command)  # a cold kernel cache: one line on a terminal, not a silent wait
        return int(module.run(args) or 0)
    except KeyboardInterrupt:
        print(f"twin{' ' + command if command else ''}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except ImportError as exc:
        extra = missing_extra(exc)
        if extra is None or os.environ.get("TWIN_DEBUG"):
            raise
        print(f"twin {command}: error: {extra}", file=sys.stderr)
        return 2
    except (UserError, ValueError, OSError, KeyError) as exc:
        if os.environ.get("TWIN_DEBUG"):
            raise
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"twin {command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
