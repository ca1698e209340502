"""Opening HDF5 recordings that may be damaged, quickly, and finding which of their rows can be trusted.

Why this exists. A recording written in HDF5's single-writer/multiple-reader (SWMR) mode and not closed (still
being written, or its writer was killed) can only be opened in SWMR-read mode. That mode does two things a
damaged file punishes: it skips HDF5's check that the file is as long as its superblock says (a writer may still
be extending it), so a file cut in half opens and its missing chunks read back as zeros; and it retries every
metadata read whose checksum fails (the writer might have been caught mid-write), by default 100 times with a
sleep that doubles from about a nanosecond on each attempt — hours for a file whose metadata is simply gone.

So :func:`open_hdf5` first opens the file normally (one attempt per metadata read, the length check done); only
when that fails does it open in SWMR-read mode, with the number of metadata read attempts bounded
(:data:`SWMR_READ_ATTEMPTS`, a few tens of milliseconds of retries in all), through ``H5Pset_metadata_read_attempts``
of the HDF5 library h5py is linked to (h5py does not wrap it; where that library cannot be found, HDF5's default
applies). And :func:`readable_rows` checks, from the chunk index alone, that every chunk of a dataset's leading
rows is allocated and lies wholly inside the file — the length check SWMR-read mode skipped, per chunk.
Corruption inside a chunk is caught when it is read: new recordings store a Fletcher-32 checksum per chunk.
"""

from __future__ import annotations

import ctypes
import os
import re
from pathlib import Path

__all__ = ["SWMR_READ_ATTEMPTS", "HDF5Open", "open_hdf5", "readable_rows"]

#: metadata read attempts in SWMR-read mode: the sleeps double from ~1 ns, so 26 attempts retry for ~70 ms in all
#: (HDF5's default of 100 can sleep for hours on a damaged file; 1 is the normal-mode value)
SWMR_READ_ATTEMPTS = 26

_TRUNCATED = re.compile(r"truncated file: eof = (\d+).*stored_eof = (\d+)")
_lib: ctypes.CDLL | bool | None = False  # False: not looked up yet


def _libhdf5() -> ctypes.CDLL | None:
    """The HDF5 shared library h5py uses (found among the process's mapped files), or None."""
    global _lib
    if _lib is not False:
        return _lib
    _lib = None
    try:
        with open("/proc/self/maps") as fh:
            paths = {line.split(maxsplit=5)[-1].strip() for line in fh if "libhdf5" in line}
    except OSError:
        return None
    for path in sorted(paths):
        name = os.path.basename(path)
        if name.startswith("libhdf5") and not name.startswith("libhdf5_hl") and os.path.exists(path):
            try:
                lib = ctypes.CDLL(path)  # already loaded: the same instance (same path), so the same ids
                fn = lib.H5Pset_metadata_read_attempts
            except (OSError, AttributeError):
                continue
            fn.argtypes = [ctypes.c_int64, ctypes.c_uint]
            fn.restype = ctypes.c_int
            _lib = lib
            break
    return _lib


class HDF5Open:
    """An opened HDF5 file and how it had to be opened.

    Attributes
    ----------
    file : h5py.File
    swmr : bool
        Opened in SWMR-read mode (the file was not closed by its writer, or is damaged).
    truncated : tuple of int or None
        (bytes on disk, bytes the superblock records) when HDF5 found the file shorter than it should be.
    size : int
        The file's size on disk, bytes, when opened.
    """

    def __init__(self, file, swmr: bool, truncated: tuple[int, int] | None, size: int):
        self.file, self.swmr, self.truncated, self.size = file, swmr, truncated, size


def open_hdf5(path: str | Path) -> HDF5Open:
    """Open an HDF5 file for reading, normally if possible, else in SWMR-read mode with bounded retries.

    Raises
    ------
    ValueError
        The file cannot be opened at all; one line naming the file and HDF5's reason.
    """
    import h5py

    path = Path(path)
    size = path.stat().st_size
    try:
        return HDF5Open(h5py.File(path, "r"), False, None, size)
    except Exception as exc:  # h5py raises OSError, RuntimeError, KeyError… for bad files
        first = exc
    m = _TRUNCATED.search(str(first))
    truncated = (int(m.group(1)), int(m.group(2))) if m else None
    try:
        fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
        fapl.set_libver_bounds(h5py.h5f.LIBVER_LATEST, h5py.h5f.LIBVER_LATEST)
        lib = _libhdf5()
        if lib is not None:
            lib.H5Pset_metadata_read_attempts(fapl.id, SWMR_READ_ATTEMPTS)
        fid = h5py.h5f.open(os.fsencode(path), h5py.h5f.ACC_RDONLY | h5py.h5f.ACC_SWMR_READ, fapl=fapl)
        f = h5py.File(fid)
        f.attrs.get("format")  # the root object header must be readable too
    except Exception:  # any failure here means: not openable
        why = f"truncated to {truncated[0]} of {truncated[1]} bytes" if truncated else _short(first)
        raise ValueError(f"{path}: not a readable HDF5 recording ({why})") from None
    return HDF5Open(f, True, truncated, size)


def _short(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    text = text.replace("Unable to synchronously open file ", "").replace("Unable to open file ", "")
    return text.strip("() ")


def readable_rows(ds, n: int, size: int) -> tuple[int, str | None]:
    """Leading rows of a chunked dataset whose chunks are allocated and lie inside the first ``size`` bytes.

    Parameters
    ----------
    ds : h5py.Dataset
        Chunked along axis 0 (other layouts are checked as one block).
    n : int
        Rows wanted.
    size : int
        The file's size, bytes.

    Returns
    -------
    rows : int
        How many of the first ``n`` rows can be read (``n`` when all).
    why : str or None
        What stopped it, for the damage report.
    """
    if n <= 0:
        return 0, None
    chunks = ds.chunks
    if chunks is None:
        try:
            off, nbytes = ds.id.get_offset(), ds.id.get_storage_size()
        except Exception as exc:
            return 0, f"{ds.name}: {_short(exc)}"
        if off is not None and off + nbytes > size:
            return 0, f"{ds.name}: data at bytes {off}–{off + nbytes} past the end of the file ({size} bytes)"
        return n, None
    step = chunks[0]
    tail = (0,) * (len(ds.shape) - 1)
    infos: dict[int, tuple] = {}
    try:
        ds.id.chunk_iter(lambda i: infos.__setitem__(i.chunk_offset[0], (i.byte_offset, i.size)))
    except Exception:  # a damaged index: look chunk by chunk below, as far as it goes
        infos = {}
    for start in range(0, n, step):
        info = infos.get(start)
        if info is None:
            try:
                got = ds.id.get_chunk_info_by_coord((start, *tail))
                info = (got.byte_offset, got.size)
            except Exception as exc:
                return start, f"{ds.name}: chunk index unreadable at row {start} ({_short(exc)})"
        off, nbytes = info
        if off is None:
            return start, f"{ds.name}: no data stored for rows from {start}"
        if off + nbytes > size:
            return start, f"{ds.name}: rows from {start} lie past the end of the file ({size} bytes)"
    return n, None
