"""The one JSON writer behind every ``--json``: strict JSON, never NaN or Infinity.

Python's :func:`json.dumps` writes ``NaN`` and ``Infinity`` for non-finite floats, which no JSON parser has to
accept. Every command prints its result through :func:`dumps`, which maps a non-finite float to ``null`` (the
value is unknown or undefined: an error against a missing truth, a tip that could not be reconstructed) and
turns numpy scalars and arrays into plain numbers and lists on the way.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping

import numpy as np

__all__ = ["dumps", "finite"]


def finite(obj):
    """``obj`` with every non-finite float replaced by None, numpy scalars and arrays made plain (recursive)."""
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, float | np.floating):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, np.ndarray):
        return finite(obj.tolist())
    if isinstance(obj, Mapping):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite(v) for v in obj]
    return obj


def dumps(obj, **kw) -> str:
    """:func:`json.dumps` of :func:`finite` ``(obj)``; refuses (ValueError) anything non-finite it missed."""
    return json.dumps(finite(obj), allow_nan=False, **kw)
