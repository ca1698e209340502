"""One registry for what lives above the sensing core: source URL schemes, scenarios and commands.

The core (``twin``) never names the simulator's modules. Packages register their parts as Python entry points
in ``pyproject.toml``, and the core finds them here:

``twin.sources``
    URL scheme → ``"module:function"``; the function takes the URL and keyword options and returns a
    :class:`twin.io.source.Source`.
``twin.scenarios``
    scenario name (``twin run NAME``) → ``"module"``; the module exposes ``add_arguments(parser)`` and
    ``run(args) -> int``.
``twin.commands``
    command name (``twin NAME``) → ``"module"``, with the same two functions.
``twin.bench``
    section of ``twin bench`` → ``"module:function"``; the function takes ``quick: bool`` and returns a flat dict
    of figures.

Entry points are read from the installed package metadata, so a new entry needs ``pip install -e .`` again.
Tests may add entries for the life of the process with :func:`register`.
"""

from __future__ import annotations

from importlib.metadata import entry_points

__all__ = ["GROUPS", "entries", "load", "register"]

GROUPS = ("twin.sources", "twin.scenarios", "twin.commands", "twin.bench")

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
