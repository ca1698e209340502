"""numba's on-disk cache for the project's kernels, keyed by every kernel source they may call.

numba keys a cached function by the modification time and size of its own file only, so a kernel that calls
or inlines a kernel of another file keeps its old machine code when only that other file changes (numba's
documentation, "Notes on caching": changes in other files are not detected). Several of ours read buffers
through raw addresses (:mod:`twin._numba_entry`), where stale code reads the wrong memory instead of failing.

Importing this module before a module's first ``@njit(cache=True)`` puts two cache locators ahead of numba's
own: for a function defined in one of the project's packages (twin, models, sim_interrogator) they key the
cache by the time and size of every file of those packages that imports numba — any kernel a cached kernel
can call is in one of them — and store it where numba would. Editing one kernel file therefore recompiles
every project kernel on next use (tens of seconds, once); an installed release never does.

twin/io's kernels (sequence numbers, rates, the ILLumiSense scan) call no other file's kernels, and twin/io
imports nothing from the rest of twin, so they keep numba's own locator.
"""

from __future__ import annotations

import functools
import os
import re
from pathlib import Path

from numba.core import caching

__all__ = ["kernel_files", "kernel_stamp"]

_BASE = Path(__file__).resolve().parent.parent
_PACKAGES = tuple(_BASE / name for name in ("twin", "models", "sim_interrogator"))
_IMPORTS_NUMBA = re.compile(rb"^\s*(?:import|from)\s+numba\b", re.MULTILINE)


def _in_project(py_file: str) -> bool:
    path = Path(py_file).resolve()
    return any(path.is_relative_to(package) for package in _PACKAGES)


@functools.cache
def kernel_files() -> tuple[Path, ...]:
    """Every source file of the project's packages that imports numba (read once per process)."""
    found = []
    for package in _PACKAGES:
        for path in sorted(package.rglob("*.py")):
            try:
                if _IMPORTS_NUMBA.search(path.read_bytes()):
                    found.append(path)
            except OSError:  # unreadable: it cannot hold a kernel that was compiled either
                continue
    return tuple(found)


def kernel_stamp() -> tuple:
    """(path, mtime ns, size) of every :func:`kernel_files` entry: the key of every project kernel's cache."""
    stamp = []
    for path in kernel_files():
        try:
            st = os.stat(path)
        except OSError:
            stamp.append((str(path), None, None))
        else:
            stamp.append((str(path), st.st_mtime_ns, st.st_size))
    return tuple(stamp)


class _ProjectStamp:
    """Mixin for numba's source-file locators: only the project's files, keyed by :func:`kernel_stamp`."""

    @classmethod
    def from_function(cls, py_func, py_file):
        if not _in_project(py_file):
            return None
        return super().from_function(py_func, py_file)

    def get_source_stamp(self):
        return kernel_stamp()


class _UserProvided(_ProjectStamp, caching.UserProvidedCacheLocator):
    pass


class _InTree(_ProjectStamp, caching.InTreeCacheLocator):
    pass


class _UserWide(_ProjectStamp, caching.UserWideCacheLocator):
    pass


def _install() -> None:
    locators = caching.CacheImpl._locator_classes
    if _InTree not in locators:
        # numba's order (a user's NUMBA_CACHE_DIR, beside the source, the user-wide directory), ahead of numba's
        locators[:0] = [_UserProvided, _InTree, _UserWide]


_install()
