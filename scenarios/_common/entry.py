"""The command-line glue of every scenario: options from the parameters dataclass, ``--json``, ``--report DIR``,
progress on stderr.

A scenario module provides

* ``Params``: a frozen dataclass (SI units). A field becomes an option when its metadata says so,
  ``field(default=0.05, metadata=option("distance out of the sheath", flag="--protrusion-mm", scale=1e-3))``:
  the flag defaults to ``--`` + the field's name with dashes, the option's value times ``scale`` is the field's
  value (mm → m above; :data:`DEG` for degrees), ``choices`` restricts it; bools become ``--flag/--no-flag``;
  tuples of names are given comma-separated. The help shows the default in the option's unit;
* ``run_experiment(params, progress=None[, viewer=None])`` returning a result with ``to_dict()`` (or a dict,
  whose keys starting with ``_`` are for the report only and left out of ``--json``);
* ``text_report(result) -> str`` and ``write_report(result, directory) -> path``.

and wires itself with three lines::

    def add_arguments(parser): entry.add_arguments(parser, Params)
    def run(args): return entry.run("NAME", sys.modules[__name__], args)
    if __name__ == "__main__": entry.main(sys.modules[__name__])

``entry.run`` turns the options into ``Params`` (or calls the module's own ``params_from_args(args)`` when it
has one, for checks across options), runs with progress on stderr, writes ``--report``, and prints one JSON
object (``--json``) or the text report. A catheter that does not settle is one line on stderr and exit status 1.

Conventions the experiments share: ``optics: str = field(default="realistic", metadata=option(…,
choices=OPTICS))`` turned into an ``OpticsConfig`` by :func:`scenarios._common.optics_presets.optics_config`;
``calibration: str = field(default="lab", …)`` resolved by :func:`scenarios._common.calibration.calibration_for`,
whose ``to_dict()`` goes into the JSON under ``calibration`` and whose ``label`` goes to
``scenarios.report.Report(directory, title, label)``, which stamps it on every figure.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import math
import sys
import types
from collections.abc import Mapping

from twin import jsonout

__all__ = ["DEG", "add_arguments", "command_line", "main", "option", "params_from_args", "run", "say"]

#: ``scale`` for an option given in degrees and held in radians.
DEG = math.pi / 180.0


def option(help: str, *, flag: str | None = None, scale: float = 1.0, choices=None, metavar: str | None = None
           ) -> Mapping:
    """Field metadata making a ``Params`` field a command-line option (see the module docstring)."""
    return types.MappingProxyType({"cli": {"help": help, "flag": flag, "scale": float(scale), "choices": choices,
                                           "metavar": metavar}})


def say(message: str) -> None:
    """Progress: one line on stderr, flushed."""
    print(message, file=sys.stderr, flush=True)


def _options(params_cls):
    for f in dataclasses.fields(params_cls):
        meta = f.metadata.get("cli")
        if meta is not None:
            flag = meta["flag"] or "--" + f.name.replace("_", "-")
            yield f, meta, flag, flag.lstrip("-").replace("-", "_")


def _shown(value, scale: float):
    return float(f"{value / scale:.12g}") if scale != 1.0 else value


def add_arguments(parser: argparse.ArgumentParser, params_cls, *, json_report: bool = True) -> None:
    """One option per ``Params`` field with :func:`option` metadata, then ``--json`` and ``--report DIR``."""
    for f, meta, flag, dest in _options(params_cls):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if isinstance(default, bool):
            parser.add_argument(flag, dest=dest, action=argparse.BooleanOptionalAction, default=default,
                                help=f"{meta['help']} (default {'on' if default else 'off'})")
            continue
        if isinstance(default, tuple):
            parser.add_argument(flag, dest=dest, default=",".join(default), metavar=meta["metavar"] or "A,B,…",
                                help=f"{meta['help']}, comma-separated (default {','.join(default)})")
            continue
        kind = float if isinstance(default, float) or meta["scale"] != 1.0 else type(default)
        kind = str if default is None else kind
        shown = None if default is None else _shown(default, meta["scale"])
        parser.add_argument(flag, dest=dest, type=kind, default=shown, choices=meta["choices"],
                            metavar=meta["metavar"], help=f"{meta['help']} (default {shown})")
    if json_report:
        parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
        parser.add_argument("--report", metavar="DIR", help="write DIR/report.md with PNG figures")


def params_from_args(params_cls, args: argparse.Namespace, **extra):
    """``Params`` from parsed options (values times their ``scale``); ``extra`` overrides fields."""
    values = {}
    for f, meta, _, dest in _options(params_cls):
        v = getattr(args, dest)
        default = f.default if f.default is not dataclasses.MISSING else None
        if isinstance(default, tuple):
            v = tuple(x.strip() for x in str(v).split(",") if x.strip())
        elif v is not None and meta["scale"] != 1.0:
            v = float(v) * meta["scale"]
        values[f.name] = v
    values.update(extra)
    return params_cls(**values)


def command_line(params) -> list[str]:
    """The options that give ``params`` (a ``Params``) from the defaults, one ``"--flag value"`` string each, in
    the option's unit (value / ``scale``): the reproduction line of a report. Fields without :func:`option`
    metadata are the module's to add."""
    out = []
    for f, meta, flag, _ in _options(type(params)):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        value = getattr(params, f.name)
        if isinstance(value, float) and isinstance(default, float):
            if math.isclose(value, default, rel_tol=1e-9):
                continue
        elif value == default:
            continue
        if isinstance(value, bool):
            out.append(flag if value else "--no-" + flag.removeprefix("--"))
        elif isinstance(value, tuple):
            out.append(f"{flag} {','.join(map(str, value))}")
        else:
            shown = _shown(value, meta["scale"])
            out.append(f"{flag} {shown:.12g}" if isinstance(shown, float) else f"{flag} {shown}")
    return out


def run(name: str, module, args: argparse.Namespace) -> int:
    """``twin run NAME`` for ``module`` (see the module docstring)."""
    from models.fixtures import SettleError

    params = module.params_from_args(args) if hasattr(module, "params_from_args") else \
        params_from_args(module.Params, args)
    kwargs = {"progress": say}
    if "viewer" in inspect.signature(module.run_experiment).parameters:
        kwargs["viewer"] = getattr(args, "viewer", None)
    try:
        result = module.run_experiment(params, **kwargs)
    except SettleError as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 1
    if getattr(args, "report", None):
        say(f"report: {module.write_report(result, args.report)}")
    if getattr(args, "json", False):
        out = {k: v for k, v in result.items() if not k.startswith("_")} if isinstance(result, dict) else \
            result.to_dict()
        print(jsonout.dumps(out, indent=2))
    else:
        print(module.text_report(result))
    return 0


def main(module) -> None:
    """``python -m scenarios.NAME``: the module's own parser, then :func:`run`; exits with its status."""
    spec = getattr(module, "__spec__", None)
    name = (spec.name if spec else module.__name__).rpartition(".")[2].replace("_", "-")
    parser = argparse.ArgumentParser(prog=name, description=module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    module.add_arguments(parser)
    sys.exit(module.run(parser.parse_args()))
