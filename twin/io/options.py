"""The one parser of source URL options (``scheme://…?key=value&…``), used by every opener.

An opener declares its options as :class:`Option` fields — a type, a default, a range — and :func:`parse_options`
turns the URL's query into typed values or one line naming the URL and the key:

- an unknown key: ``'replay://a.h5?sped=2': unknown option 'sped'; known: channels, cores, …``;
- a bad boolean: booleans read ``1/0``, ``true/false``, ``yes/no``, ``on/off`` (any case) the same everywhere,
  anything else is an error (so ``salvage=on`` means true for every opener, never silently false);
- a bad number, NaN or ±inf, or a number outside its range: ``'synthetic://?rate=-1': option rate=-1: expected
  a number in (0, 1e+06]``;
- a word outside its choices, a malformed list.

Options given in code (``open_source(url, fiber=…, wait=True)``) bypass the query and are the caller's to check.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

__all__ = ["Option", "parse_bool", "parse_options"]

_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")


def parse_bool(text: str) -> bool:
    """``1/true/yes/on`` → True, ``0/false/no/off`` → False (any case); anything else raises ValueError."""
    v = text.strip().lower()
    if v in _TRUE:
        return True
    if v in _FALSE:
        return False
    raise ValueError(f"expected a boolean ({'/'.join(_TRUE)} or {'/'.join(_FALSE)})")


@dataclass(frozen=True)
class Option:
    """One URL option.

    Attributes
    ----------
    kind : {"bool", "int", "float", "str", "ints"}
        ``ints`` is a comma-separated list of integers.
    default : object
        The value when the key is absent (returned as is; ``None`` leaves the opener's own default).
    low, high : float or None
        Inclusive range of a number (of each number of ``ints``); None: unbounded on that side.
    low_open : bool
        ``low`` itself is excluded (a positive rate: ``low=0, low_open=True``).
    choices : tuple of str or None
        The words a ``str`` option may take.
    words : mapping of str to object, optional
        Words a number option also takes, with their values (``speed=max`` → None).
    """

    kind: str = "str"
    default: Any = None
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    choices: tuple[str, ...] | None = None
    words: Mapping[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("bool", "int", "float", "str", "ints"):
            raise ValueError(f"Option: unknown kind {self.kind!r}")

    def expected(self) -> str:
        """What a valid value looks like, for the error message."""
        if self.kind == "bool":
            return "a boolean (1/0, true/false, yes/no, on/off)"
        if self.kind == "str":
            return "one of " + ", ".join(self.choices) if self.choices else "text"
        what = {"int": "an integer", "float": "a number", "ints": "comma-separated integers"}[self.kind]
        if self.low is not None or self.high is not None:
            lo = "-inf" if self.low is None else f"{self.low:g}"
            hi = "inf" if self.high is None else f"{self.high:g}"
            left = "(" if self.low_open or self.low is None else "["
            right = "]" if self.high is not None else ")"
            what += f" in {left}{lo}, {hi}{right}"
        if self.words:
            what += " or " + ", ".join(self.words)
        return what

    def parse(self, text: str) -> Any:
        """The typed value of ``text``; ValueError when it is not one."""
        if self.kind == "bool":
            return parse_bool(text)
        if self.kind == "str":
            if self.choices is not None and text not in self.choices:
                raise ValueError(text)
            return text
        if self.words and text in self.words:
            return self.words[text]
        if self.kind == "ints":
            values = [int(x) for x in text.split(",") if x.strip()]
            if not values:
                raise ValueError(text)
            for v in values:
                self._check_range(v)
            return values
        value = int(text) if self.kind == "int" else float(text)
        if not math.isfinite(value):
            raise ValueError(text)
        self._check_range(value)
        return value

    def _check_range(self, value: float) -> None:
        if self.low is not None and (value < self.low or (self.low_open and value == self.low)):
            raise ValueError(value)
        if self.high is not None and value > self.high:
            raise ValueError(value)


def parse_options(url: str, query: Mapping[str, str], spec: Mapping[str, Option], *,
                  extra: bool = False) -> dict[str, Any]:
    """Typed options of a source URL.

    Parameters
    ----------
    url : str
        The URL (every error names it).
    query : mapping
        Its query, key → text (:func:`twin.io.source.parse_url`).
    spec : mapping of str to Option
        The opener's options.
    extra : bool
        Keys not in ``spec`` are returned untouched under ``"_extra"`` (a dict) instead of being an error (the
        simulator hands them to its setup, which checks them).

    Returns
    -------
    dict
        Every option of ``spec`` whose key was given or whose default is not None, typed.

    Raises
    ------
    ValueError
        One line naming the URL and the key: an unknown key, or a value that is not what the option takes.
    """
    unknown = sorted(set(query) - set(spec))
    if unknown and not extra:
        raise ValueError(f"{url!r}: unknown option{'s' if len(unknown) > 1 else ''} "
                         f"{', '.join(map(repr, unknown))}; known: {', '.join(sorted(spec))}")
    out: dict[str, Any] = {k: o.default for k, o in spec.items() if o.default is not None}
    for key, text in query.items():
        option = spec.get(key)
        if option is None:
            continue
        try:
            out[key] = option.parse(text)
        except (ValueError, OverflowError):
            raise ValueError(f"{url!r}: option {key}={text!r}: expected {option.expected()}") from None
    if extra:
        out["_extra"] = {k: query[k] for k in unknown}
    return out
