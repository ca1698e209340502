"""Optional dependencies: which extra of ``catheter-twin`` brings which package, and one error that says so.

The sensing core installs with numpy, scipy, numba, tomli-w and pyserial only. Everything else sits behind an
extra (``pip install '.[sim]'`` from a checkout); code that needs one imports it through :func:`require` (or lets
:func:`import_optional` translate the ImportError of a module that does), so the user reads one line naming
the extra instead of a traceback.
"""

from __future__ import annotations

from importlib import import_module
from types import ModuleType

__all__ = ["EXTRAS", "MissingExtra", "import_optional", "require"]

#: top-level package → the extra that installs it
EXTRAS: dict[str, str] = {
    "mujoco": "sim",
    "meshcat": "viewer",
    "matplotlib": "viewer",
    "zmq": "viewer",
    "tornado": "viewer",
    "umsgpack": "viewer",
    "h5py": "record",
    "dask": "study",
    "distributed": "study",
    "pyarrow": "study",
    "mcap": "ros",
    "zstandard": "ros",
    "lz4": "ros",
    "foxglove": "ros",
}


class MissingExtra(ImportError):
    """An optional dependency is not installed; the message names the extra that installs it."""

    def __init__(self, package: str, extra: str, what: str | None = None):
        self.package, self.extra = package, extra
        needs = f"{what} needs" if what else "this needs"
        # the README installs from a checkout (the project is not on a package index): the hint says the same
        super().__init__(f"{needs} the '{extra}' extra ({package} is not installed): "
                         f"pip install '.[{extra}]' from a catheter-twin checkout", name=package)


def require(package: str, what: str | None = None) -> ModuleType:
    """Import ``package`` (a name in :data:`EXTRAS`, or one of its submodules) or raise :class:`MissingExtra`.

    ``what`` names the feature in the message (e.g. ``"HDF5 recording"``).
    """
    try:
        return import_module(package)
    except ModuleNotFoundError as exc:
        root = (exc.name or package).split(".")[0]
        if root in EXTRAS:
            raise MissingExtra(root, EXTRAS[root], what) from None
        raise


def import_optional(module: str, what: str | None = None) -> ModuleType:
    """Import any module; if it fails because an optional dependency is missing, raise :class:`MissingExtra`."""
    try:
        return import_module(module)
    except MissingExtra:
        raise
    except ModuleNotFoundError as exc:
        root = (exc.name or "").split(".")[0]
        if root in EXTRAS:
            raise MissingExtra(root, EXTRAS[root], what) from None
        raise
