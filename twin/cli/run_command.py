"""`twin run NAME [options]`: run a scenario found through the registry (:mod:`twin.registry`).

``--viewer [--viewer-rate HZ] [--keep-open]`` (before or among the scenario's options: declared on both parsers
by :func:`add_viewer_arguments`) opens a browser view (:class:`twin.viewer.Viewer`; the URL is printed on stderr)
and hands it to the scenario as ``args.viewer`` (None without the flag), the only one of them its ``args``
keep. Scenarios draw as they go with ``viewer = getattr(args, "viewer", None)`` then ``viewer.show(shape, truth,
label=…)`` (``getattr``: the same ``run(args)`` also serves the scenario's own ``__main__``, whose parser has no
viewer). A scenario that does not draw still runs; the viewer's server stops when the scenario returns, or with
``--keep-open`` stays until Ctrl-C.

A scenario is a bounded run: Ctrl-C ends it with ``twin run: interrupted`` and exit status 130 (``twin.cli``);
Ctrl-C on a page kept open after a finished run exits with the scenario's own status.
"""

from __future__ import annotations

import argparse
import inspect
import re
import shutil
import sys
import textwrap

#: one-line help (read by `twin --help` without importing this module)
HELP = "run a scenario (an experiment of the paper, or our own)"

COMMON_HELP = ("Every scenario takes --json (one JSON object on stdout) and --report DIR (DIR/report.md with "
               "figures); the experiments take --calibration lab|true|lambda0|nominal|FILE (default lab: calibrated "
               "as a lab would, two-step then identification against the fixtures' geometry; true: the twin's true "
               "parameters) and --optics realistic|ideal. `twin run NAME --help` lists a scenario's own options.")


def add_viewer_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare ``--viewer``, ``--viewer-rate HZ`` and ``--keep-open``: on `twin run` (before NAME) and on each
    scenario's parser (among its options), so argparse reads them in both places the same way."""
    parser.add_argument("--viewer", action="store_true", help="show the run in a browser (meshcat)")
    parser.add_argument("--viewer-rate", type=float, default=None, metavar="HZ",
                        help="most frames the viewer draws per second (default 30; implies --viewer)")
    parser.add_argument("--keep-open", action="store_true",
                        help="keep the viewer serving after the run, until Ctrl-C (implies --viewer)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from twin.cli import scenarios

    known = scenarios()
    parser.epilog = COMMON_HELP
    add_viewer_arguments(parser)
    parser.add_argument("name", metavar="NAME", help="scenario: " + ", ".join(known) if known else "scenario name")
    parser.add_argument("options", nargs=argparse.REMAINDER, help="the scenario's own options (see NAME --help)")


_ROLE = re.compile(r":[\w:.-]+:`(~?)([^`]+)`")  # :mod:`x.y`, :func:`~x.y.z`
_LITERAL = re.compile(r"``(.+?)``")
_STRONG = re.compile(r"\*\*(.+?)\*\*")
_EMPHASIS = re.compile(r"(?<![\w*])\*(?=\S)(.+?)(?<=\S)\*(?![\w*])")
_ITEM = re.compile(r"^(\s*)([*-]|\d+\.)\s+")


def plain_help(doc: str, width: int | None = None) -> str:
    """A scenario's reST docstring as terminal text for ``--help``: markup dropped (````x````, ``:mod:`x```,
    ``**x**``), each paragraph and list item wrapped on its own, indented blocks kept as written."""
    if width is None:
        width = max(40, min(100, shutil.get_terminal_size().columns - 2))

    def inline(text: str) -> str:
        text = _ROLE.sub(lambda m: m.group(2).rsplit(".", 1)[-1] if m.group(1) else m.group(2), text)
        text = _LITERAL.sub(r"\1", text)
        return _EMPHASIS.sub(r"\1", _STRONG.sub(r"\1", text))

    out: list[str] = []
    for block in re.split(r"\n\s*\n", inspect.cleandoc(doc)):
        lines = block.splitlines()
        if all(line.startswith((" ", "\t")) for line in lines) and not _ITEM.match(lines[0]):
            out.append("\n".join(inline(line).rstrip() for line in lines))  # a literal block: as written
            continue
        items: list[list[str]] = []
        for line in lines:
            if _ITEM.match(line) or not items:
                items.append([line.strip()])
            else:
                items[-1].append(line.strip())
        texts = []
        for item in items:
            text = inline(" ".join(item))
            if text.endswith("::"):
                text = text[:-1]
            m = _ITEM.match(text)
            if m:
                texts.append(textwrap.fill(text, width, initial_indent="  ",
                                           subsequent_indent="  " + " " * len(m.group(0))))
            else:
                texts.append(textwrap.fill(text, width))
        out.append("\n".join(texts))
    return "\n\n".join(out)


def run(args: argparse.Namespace) -> int:
    from twin import registry
    from twin.cli import UserError, scenarios

    known = scenarios()
    if args.name not in known:
        raise UserError(f"no scenario {args.name!r}; known scenarios: {', '.join(known) or 'none installed'}")
    module = registry.load("twin.scenarios", args.name)
    parser = argparse.ArgumentParser(prog=f"twin run {args.name}", description=plain_help(module.__doc__ or ""),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    module.add_arguments(parser)
    add_viewer_arguments(parser)  # the viewer's options among the scenario's, read by the same parser
    ns = parser.parse_args(list(args.options))
    # given before NAME or among the scenario's options alike; the scenario sees only ns.viewer (a Viewer or None)
    rate = ns.viewer_rate if ns.viewer_rate is not None else args.viewer_rate
    keep = ns.keep_open or args.keep_open
    wanted = ns.viewer or args.viewer or rate is not None or keep
    del ns.viewer_rate, ns.keep_open
    if rate is not None and not rate > 0:  # NaN too
        raise ValueError(f"--viewer-rate must be a positive number of frames per second, got {rate}")
    ns.viewer = None
    if wanted:
        from twin.viewer import Viewer, ViewerConfig

        ns.viewer = Viewer(ViewerConfig(max_fps=rate if rate is not None else 30.0))
    finished = False
    try:
        status = int(module.run(ns) or 0)
        finished = True
        return status
    finally:
        if ns.viewer is not None:
            if ns.viewer.frames_shown == 0:
                print(f"twin run: scenario {args.name} drew nothing in the viewer (it does not use args.viewer)",
                      file=sys.stderr)
            if keep and finished:  # not after Ctrl-C or an error: those end the command
                from twin.viewer import keep_open

                keep_open(ns.viewer)
            ns.viewer.close()
