"""Small helpers that turn user input into checked, read-only numpy arrays with clear errors."""

from __future__ import annotations

from collections.abc import Sequence

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
