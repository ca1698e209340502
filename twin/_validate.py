"""Small helpers that turn user input into checked, read-only numpy arrays with clear errors."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np


def frozen(a: np.ndarray) -> np.ndarray:
    """Return ``a`` with its write flag cleared (models and results are immutable)."""
    a.setflags(write=False)
    return a


def real_array(
    value,
    name: str,
    *,
    shape: Sequence[int | None] | None = None,
    finite: bool = True,
    unit: str = "",
    owner: str = "",
) -> np.ndarray:
    """Convert ``value`` to a float64 array and check its shape and finiteness.

    ``shape`` entries of ``None`` accept any length. Errors name the field, what was wrong and what was
    expected, e.g. ``FiberModel.core_radii: expected shape (4,), got (3,)``.
    """
    where = f"{owner}.{name}" if owner else name
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: expected numbers{f' in {unit}' if unit else ''}, got {value!r}") from exc
    if shape is not None:
        ok = a.ndim == len(shape) and all(e is None or e == n for e, n in zip(shape, a.shape, strict=True))
        if not ok:
            want = "(" + ", ".join("n" if e is None else str(e) for e in shape) + ("," if len(shape) == 1 else "")
            raise ValueError(f"{where}: expected shape {want}), got {a.shape}")
    if finite and not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        idx = tuple(int(i) for i in bad)
        raise ValueError(f"{where}: expected finite numbers, got {a[idx]} at index {idx if len(idx) > 1 else idx[0]}")
    return a


#: Bragg wavelengths a fibre model or a calibration may hold, nm (anything else is in another unit: µm, m)
BRAGG_NM = (200.0, 3000.0)


def check_bragg_nm(lam: np.ndarray, where: str) -> None:
    """One ValueError naming ``where`` (e.g. ``FiberModel.lambda0``), the grating and the core when a wavelength
    of ``lam`` (n_gratings, n_cores) lies outside :data:`BRAGG_NM`."""
    out = (lam < BRAGG_NM[0]) | (lam > BRAGG_NM[1])
    if np.any(out):
        g, c = (int(i) for i in np.argwhere(out)[0])
        raise ValueError(f"{where}: grating {g} core {c} has {lam[g, c]} nm; expected a Bragg wavelength in nm "
                         f"({BRAGG_NM[0]:g}–{BRAGG_NM[1]:g})")


def _toml_kind(value) -> str:
    """How a value read from TOML (or given to ``from_dict``) reads in an error message."""
    import datetime

    if isinstance(value, bool | np.bool_):
        return f"a boolean ({str(value).lower()})"
    if isinstance(value, str):
        return f"text ({value[:40]!r})"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, datetime.date | datetime.time):
        return f"a date/time ({value})"
    if isinstance(value, list | tuple | np.ndarray):
        return f"a list ({str(list(value))[:40]})"
    return f"{type(value).__name__} ({str(value)[:40]})"


def _is_number(value) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool | np.bool_)


def _numbers(value, depth: int) -> bool:
    """Whether ``value`` is a list nested ``depth`` deep whose leaves are all numbers (not booleans)."""
    if isinstance(value, np.ndarray):
        return value.ndim == depth and (value.dtype.kind in "iuf")
    if depth == 0:
        return _is_number(value)
    return isinstance(value, list | tuple) and all(_numbers(v, depth - 1) for v in value)


def check_field_types(data, kinds: dict[str, str], where: str = "") -> None:
    """Check the types of a mapping read from a file before any is converted: one ValueError naming the field.

    ``kinds`` maps a field to ``number``, ``integer``, ``text``, ``numbers`` (a list of numbers), ``rows`` (a
    list of lists of numbers), ``number or numbers``, ``table``; fields not in ``data`` are skipped. Booleans,
    dates and tables are never numbers (TOML's ``true`` is not 1.0).
    """
    tests = {
        "number": lambda v: _is_number(v),
        "integer": lambda v: isinstance(v, int | np.integer) and not isinstance(v, bool | np.bool_),
        "text": lambda v: isinstance(v, str),
        "numbers": lambda v: _numbers(v, 1),
        "rows": lambda v: _numbers(v, 2),
        "matrices": lambda v: _numbers(v, 3),
        "number or numbers": lambda v: _is_number(v) or _numbers(v, 1),
        "table": lambda v: isinstance(v, dict),
    }
    names = {"numbers": "a list of numbers", "rows": "a list of rows of numbers", "table": "a table",
             "matrices": "a list of matrices of numbers",
             "number or numbers": "a number or a list of numbers", "integer": "an integer", "text": "text",
             "number": "a number"}
    for field, kind in kinds.items():
        if field in data and data[field] is not None and not tests[kind](data[field]):
            raise ValueError(f"{where}{field}: expected {names[kind]}, got {_toml_kind(data[field])}")
        if field in data and kind != "integer" and (big := _beyond_float(data[field])) is not None:
            raise ValueError(f"{where}{field}: {'-' if big < 0 else ''}an integer of {len(str(abs(big)))} digits is "
                             "beyond any float (±1.8e308)")


def _beyond_float(value) -> int | None:
    """The first Python int in ``value`` (a number or nested lists of them) that float64 cannot hold, or None
    (TOML integers are unbounded; converting one raises OverflowError, not the ValueError the readers report)."""
    if isinstance(value, int) and not isinstance(value, bool):
        return value if abs(value) >= 1 << 1024 else None
    if isinstance(value, list | tuple):
        for v in value:
            if (big := _beyond_float(v)) is not None:
                return big
    return None


def check_table(data, cls, what: str, where: str = "") -> None:
    """``data`` is a mapping whose keys are all fields of the dataclass ``cls``, else one ValueError naming
    ``where`` (a file, with ": ") and the unknown fields; ``what`` names the table ("fibre", "calibration")."""
    if not isinstance(data, Mapping):
        raise ValueError(f"{where}expected a table of {what} fields, got {type(data).__name__}")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"{where}unknown field(s) {', '.join(unknown)}; known fields: {', '.join(sorted(known))}")
