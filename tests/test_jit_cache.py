"""The project's kernels are cached under a key of every kernel source (twin/_jit_cache.py).

numba alone keys a cached function by its own file; a kernel that calls another file's kernel would keep stale
machine code when only that file changes."""

from __future__ import annotations

import os

import numpy as np

from twin import _fused, _jit_cache


def _locator(dispatcher):
    return dispatcher._cache._impl.locator


def test_a_kernel_calling_another_files_kernel_is_keyed_by_that_file():
    kernels = [v for v in vars(_fused).values() if hasattr(v, "_cache") and hasattr(v._cache, "_impl")]
    assert kernels, "twin._fused defines no cached kernel"
    locator = _locator(kernels[0])
    assert isinstance(locator, _jit_cache._ProjectStamp)
    files = {p.name for p in _jit_cache.kernel_files()}
    # _fused calls _kernels, which calls so3; the simulator's kernels call both
    assert {"_fused.py", "_kernels.py", "so3.py", "_rod_kernels.py", "frame_path.py"} <= files
    assert locator.get_source_stamp() == _jit_cache.kernel_stamp()


def test_the_stamp_changes_when_any_kernel_file_changes_and_not_otherwise(tmp_path, monkeypatch):
    # copies of the kernel files, not the checkout's: a changed stamp in the checkout would make every other
    # process of the run (tests run on parallel workers) miss the cache and recompile, or save under it
    copies = []
    for path in _jit_cache.kernel_files():
        copy = tmp_path / f"{len(copies)}_{path.name}"
        copy.write_bytes(path.read_bytes())
        copies.append(copy)
    monkeypatch.setattr(_jit_cache, "kernel_files", lambda: tuple(copies))
    before = _jit_cache.kernel_stamp()
    assert _jit_cache.kernel_stamp() == before
    so3_copy = next(c for c in copies if c.name.endswith("_so3.py"))
    st = os.stat(so3_copy)
    os.utime(so3_copy, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert _jit_cache.kernel_stamp() != before
    os.utime(so3_copy, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert _jit_cache.kernel_stamp() == before
    so3_copy.write_bytes(so3_copy.read_bytes() + b"\n")  # an edit that keeps the time: the size says it
    os.utime(so3_copy, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert _jit_cache.kernel_stamp() != before


def test_functions_outside_the_project_keep_numbas_own_locator(tmp_path, monkeypatch):
    import importlib
    import sys

    (tmp_path / "outside_kernel.py").write_text(
        "from numba import njit\n\n@njit(cache=True)\ndef twice(x):\n    return 2.0 * x\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module("outside_kernel")
    try:
        assert module.twice(np.float64(1.5)) == 3.0
        assert not isinstance(_locator(module.twice), _jit_cache._ProjectStamp)
    finally:
        sys.modules.pop("outside_kernel", None)
