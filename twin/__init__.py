"""twin: fibre-optic (multi-core FBG) shape sensing of catheters.

Peak wavelengths → strain → curvature → 3D centreline, with calibration and parameter identification.
Needs only numpy, scipy and numba; the MuJoCo twin lives in the ``models`` and ``sim_interrogator`` packages.

The names below are imported on first use (PEP 562), so that importing a submodule — the ``twin`` command's
entry point above all — does not first load numpy, scipy and numba: the command line starts at once, and a
Ctrl-C in its first second meets its handler instead of an import (one line, exit 130, no traceback).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from twin import strain
    from twin.calibration import Calibration, CalibrationError
    from twin.fiber import FiberModel
    from twin.frames import Frame, PeakStatus, Shape, Truth
    from twin.reconstruct import Reconstructor

__all__ = [
    "Calibration",
    "CalibrationError",
    "FiberModel",
    "Frame",
    "PeakStatus",
    "Reconstructor",
    "Shape",
    "Truth",
    "strain",
]
__version__ = "0.1.0"

_HOME = {
    "Calibration": "twin.calibration",
    "CalibrationError": "twin.calibration",
    "FiberModel": "twin.fiber",
    "Frame": "twin.frames",
    "PeakStatus": "twin.frames",
    "Reconstructor": "twin.reconstruct",
    "Shape": "twin.frames",
    "Truth": "twin.frames",
}


def __getattr__(name: str):
    if name.startswith("__"):
        raise AttributeError(f"module 'twin' has no attribute {name!r}")
    if name in _HOME:
        value = getattr(importlib.import_module(_HOME[name]), name)
    else:
        try:  # a submodule, as ``import twin`` used to load some eagerly (twin.strain, twin.fiber, …)
            value = importlib.import_module(f"twin.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"twin.{name}":
                raise
            raise AttributeError(f"module 'twin' has no attribute {name!r}") from None
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
