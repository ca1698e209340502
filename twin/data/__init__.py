"""Data sets installed with the package (package data, so they are there after a plain ``pip install .``).

``jig/SENSOR/``: a real jig table per sensor — ``poses.csv`` (the table), ``needle.toml`` (its fibre model),
``calibration.toml`` (its jig calibration) and ``SOURCE.md`` (provenance and licence). ``amiro`` is JHU AMIRo's
needle_3CH_4AA_v2, ``amiro-3aa`` its needle_3CH_3AA (docs/jig.md). Every directory under ``jig/`` is installed
(pyproject's package data takes ``jig/*/*``), so another sensor is added by adding its directory.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["JIG", "jig_dir", "jig_sensors"]

#: the jig tables' directory
JIG = Path(__file__).resolve().parent / "jig"


def jig_sensors() -> list[str]:
    """Names of the installed jig tables (the directories under :data:`JIG`)."""
    return sorted(p.name for p in JIG.iterdir() if p.is_dir() and not p.name.startswith(("_", "."))) \
        if JIG.is_dir() else []


def jig_dir(sensor: str) -> Path:
    """The directory of ``sensor``'s jig table.

    Raises
    ------
    FileNotFoundError
        When no such table is installed, naming the known ones.
    """
    path = JIG / sensor
    if not path.is_dir():
        known = ", ".join(jig_sensors()) or "none"
        raise FileNotFoundError(f"no jig table {sensor!r} installed in {JIG} (known: {known})")
    return path
