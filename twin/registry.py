"""The one registry of the project's parts: source URL schemes, simulated setups, scenarios, commands, bench sections.

The core (``twin``) never names the simulator's modules. Packages register their parts as Python entry points
in ``pyproject.toml``, and the core finds them here:

``twin.sources``
    URL scheme → ``"module:function"``; the function takes the URL and keyword options and returns a
    :class:`twin.io.source.Source`.
``twin.scenarios``
    scenario name (``twin run NAME``) → ``"module"``; the module exposes ``add_arguments(parser)`` and
    ``run(args) -> int``.
``twin.commands``
    command name (``twin NAME``) → ``"module"``, with the same two functions and a one-line ``HELP`` (a string,
    or a dict command name → string when one module serves several commands), which :func:`summary` reads
    without importing the module (so `twin --help` imports no command).
``twin.sim_setups``
    simulated setup name (``sim://NAME``) → ``"module:Class"``, a :class:`sim_interrogator.setups.Setup`
    subclass.
``twin.bench``
    section of ``twin bench`` → ``"module:function"``; the function takes ``quick: bool`` and returns a flat dict
    of figures.

Entry points are read from the installed package metadata, so a new entry needs ``pip install -e .`` again.
Tests may add entries for the life of the process with :func:`register`.
"""

from __future__ import annotations

import ast
import importlib.util
from importlib.metadata import entry_points

__all__ = ["GROUPS", "entries", "load", "register", "summary", "unregister"]

GROUPS = ("twin.sources", "twin.scenarios", "twin.commands", "twin.bench", "twin.sim_setups")

_extra: dict[str, dict[str, str]] = {group: {} for group in GROUPS}


def entries(group: str) -> dict[str, str]:
    """Name → target (``"module"`` or ``"module:attribute"``) of every entry registered in ``group``."""
    if group not in GROUPS:
        raise ValueError(f"unknown registry group {group!r}; known: {', '.join(GROUPS)}")
    found = {ep.name: ep.value for ep in entry_points(group=group)}
    found.update(_extra[group])
    return dict(sorted(found.items()))


def register(group: str, name: str, target: str) -> None:
    """Add (or replace) an entry for this process only, e.g. a scenario defined by a test."""
    if group not in GROUPS:
        raise ValueError(f"unknown registry group {group!r}; known: {', '.join(GROUPS)}")
    _extra[group][name] = target


def unregister(group: str, name: str) -> None:
    """Remove an entry added with :func:`register` (no error if there is none)."""
    _extra[group].pop(name, None)


def load(group: str, name: str):
    """Import the module (and attribute) an entry names.

    Raises
    ------
    KeyError
        No entry of that name in ``group``.
    twin.extras.MissingExtra
        The entry's module needs an optional dependency that is not installed.
    """
    known = entries(group)
    if name not in known:
        raise KeyError(name)
    module, _, attribute = known[name].partition(":")
    from twin.extras import import_optional

    mod = import_optional(module)
    return getattr(mod, attribute) if attribute else mod


def summary(group: str, name: str) -> str:
    """The entry's one-line ``HELP``, read from its module's source without importing it ("" when it has none).

    ``HELP`` is a module-level string, or a dict entry name → string for a module that serves several entries.
    Reading the source keeps `twin --help` from importing every command (and the optional packages they need).
    """
    module = entries(group)[name].partition(":")[0]
    try:
        spec = importlib.util.find_spec(module)
    except ImportError:  # a parent package that needs a missing optional dependency
        return ""
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return ""
    with open(spec.origin, encoding="utf-8") as f:
        tree = ast.parse(f.read(), spec.origin)
    for node in tree.body:
        target = node.target if isinstance(node, ast.AnnAssign) else (
            node.targets[0] if isinstance(node, ast.Assign) and len(node.targets) == 1 else None)
        if isinstance(target, ast.Name) and target.id == "HELP" and node.value is not None:
            value = ast.literal_eval(node.value)
            return value.get(name, "") if isinstance(value, dict) else str(value)
    return ""
