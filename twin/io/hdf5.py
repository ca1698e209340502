"""The twin HDF5 recording: its layout, the writer (:class:`Recorder`, ``twin live --record``), and opening files
that may be damaged (the reader is :class:`twin.io.record.RecordingReader`).

File layout (format ``twin-recording`` version 1; every array batch-first along the frame axis n)::

    /frames/timestamp     float64 (n,)            the source's acquisition time, s (NaN when unknown)
    /frames/sequence      int64   (n,)            sample numbers as the source gave them
    /frames/received      float64 (n,)            wall-clock time the live loop received the frame, s (UTC epoch)
    /frames/wavelengths   float64 (n, g, c)       nm, NaN where a peak is missing
    /frames/powers        float32 (n, g, c)       as reported (NaN when the source gives none)
    /frames/status        uint8   (n, g, c)       twin.PeakStatus bits
    /frames/count         int64   (1,)            rows committed (written after each flush's data)
    /truth/present        bool    (n,)            frame carried a Truth           (only when the source is
    /truth/positions      float64 (n, m, 3)       m                                 the simulator, or any
    /truth/frames         float32 (n, m, 3, 3)    material frames, if given         source whose first
    /truth/curvature      float64 (n, g, 2)       1/m, if given                     frames carry truth)
    /truth/twist          float64 (n, g)          rad/m, if given
    /truth/temperature    float64 (n, g)          K, if given
    /truth/s              float64 (m,)            arc length of the truth samples, m
    /truth/fixture        float64 (k, 3)          the fixture's centreline of the first frame, m, if given
    /vendor/sensor<k>/present    bool    (n,)       the frame carried sensor block k   (only when the first
    /vendor/sensor<k>/curvature  float64 (n, G)     |κ| at its G gratings, 1/m           chunk's frames carry
    /vendor/sensor<k>/angle      float64 (n, G)     bending direction, rad               the interrogator's
    /vendor/sensor<k>/positions  float64 (n, N, 3)  shape points, m, vendor frame        reconstruction,
    /vendor/sensor<k>/spacing    float64 ()         arc length between the points, m     Frame.vendor)
    attributes of /: format, version, fiber_toml, calibration_toml, source_url, created_utc, software,
                     frames (count written so far), complete (False until closed cleanly), rate_hz

Storage: every per-frame dataset is chunked along the frame axis, compressed (byte shuffle + gzip level 1)
and checksummed per chunk (Fletcher-32), so a few frames take kilobytes (the fill of a half-empty chunk
compresses to nothing) and a damaged chunk is detected when read instead of returning garbage. The chunk length
follows the frame rate: about one flush interval of frames (16 to 1024 rows, 64 when the rate is unknown), and
at most ~1 MiB per chunk uncompressed.

Durability: frames are buffered in memory and appended in chunks, and the file is flushed every
``flush_frames`` frames or ``flush_interval`` seconds, whichever comes first, and on close. The file is
written in HDF5's single-writer/multiple-reader (SWMR) mode, whose ordered metadata writes keep it readable at
any instant, so a process killed at any point leaves a file holding everything up to its last flush (at most
``flush_interval`` s of frames are lost; ``complete`` stays False). Readers open such a file in SWMR mode,
which also lets ``twin replay`` read a recording while it is being written. Truth datasets are created from
the first chunk (SWMR forbids new datasets later): truth that first appears after it is counted in
:attr:`Recorder.truth_dropped` and not stored.

The interrogator's own reconstruction (ILLumiSense sensor blocks, :attr:`Frame.vendor`, SI) is stored the same
way, one group per sensor k = 0, 1, … with the layout — G gratings, N shape points, their spacing — of the
sensor's first block in the first chunk: fixed per recording, so the arrays stay rectangular and chunked like
the rest. A block of another G, N or spacing, a sensor beyond those of the first chunk, or blocks that first
appear after it are not stored (``present`` False there) and counted in :attr:`Recorder.vendor_dropped`.
Damage to vendor chunks is treated like damage to truth chunks: reported, and the rows from there on come back
without their vendor blocks, the frames kept.

Opening damaged files quickly, and finding which of their rows can be trusted. A recording written in SWMR
mode and not closed (still being written, or its writer was killed) can only be opened in SWMR-read mode. That
mode does two things a damaged file punishes: it skips HDF5's check that the file is as long as its superblock
says (a writer may still be extending it), so a file cut in half opens and its missing chunks read back as
zeros; and it retries every metadata read whose checksum fails (the writer might have been caught mid-write), by
default 100 times with a sleep that doubles from about a nanosecond on each attempt — hours for a file whose
metadata is simply gone.

So :func:`open_hdf5` first opens the file normally (one attempt per metadata read, the length check done); only
when that fails does it open in SWMR-read mode, with the metadata read attempts bounded
(:data:`SWMR_READ_ATTEMPTS`, a few tens of milliseconds of retries in all) through
``H5Pset_metadata_read_attempts`` of the HDF5 library h5py is linked to (h5py does not wrap it; where that
library cannot be found, HDF5's default applies). And :func:`readable_rows` checks, from the chunk index alone,
that every chunk of a dataset's leading rows is allocated and lies wholly inside the file — the length check
SWMR-read mode skipped, per chunk. Corruption inside a chunk is caught when it is read: recordings store a
Fletcher-32 checksum per chunk.
"""

from __future__ import annotations

import ctypes
import datetime as _dt
import os
import re
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from twin.calibration import Calibration
from twin.extras import require
from twin.fiber import FiberModel
from twin.frames import Frame, Truth, VendorArrays, vendor_rows

__all__ = ["FORMAT", "FRAME_FIELDS", "SWMR_READ_ATTEMPTS", "TRUTH_FIELDS", "VENDOR_FIELDS", "VERSION", "HDF5Open",
           "Recorder", "chunk_rows", "open_hdf5", "readable_rows"]

FORMAT = "twin-recording"
VERSION = 1
TRUTH_FIELDS = ("positions", "frames", "curvature", "twist", "temperature")
FRAME_FIELDS = ("timestamp", "sequence", "received", "wavelengths", "powers", "status")
#: per-frame datasets of each /vendor/sensor<k> group (with ``spacing``, a scalar)
VENDOR_FIELDS = ("present", "curvature", "angle", "positions")
_CHUNK_BYTES = 1 << 20

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
    h5py = require("h5py", "reading HDF5 recordings")

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


# ------------------------------------------------------------------------------------------------- writing


def _toml(obj) -> str:
    import tomli_w

    return tomli_w.dumps(obj.to_dict())


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def chunk_rows(rate: float | None, flush_interval: float, row_bytes: int) -> int:
    """Chunk length along the frame axis: about one flush interval of frames, a power of two in [16, 1024]
    (64 when the rate is unknown), and at most ~1 MiB of uncompressed data per chunk."""
    want = rate * flush_interval if rate and np.isfinite(rate) and rate > 0 else 64.0
    rows = int(2 ** np.clip(np.round(np.log2(max(want, 1.0))), 4, 10))
    return max(1, min(rows, _CHUNK_BYTES // max(1, row_bytes)))


# ------------------------------------------------------------------------------------------------- writing


class Recorder:
    """Appends frames to an HDF5 recording in chunks, flushing regularly (layout in the module docstring).

    Also a live-loop sink: ``recorder(frames, shapes, status)`` appends ``frames``.

    Parameters
    ----------
    path : str or Path
        File to create (an existing file is replaced).
    fiber : FiberModel, optional
        The fibre model used, stored as TOML text.
    calibration : Calibration, optional
        The calibration used, stored as TOML text.
    source_url : str
        Where the frames come from.
    rate : float, optional
        The source's nominal rate, Hz (also sizes the chunks).
    flush_frames : int
        Flush at least every this many frames.
    flush_interval : float
        Flush at least every this many seconds (checked on each append), s.
    chunk : int, optional
        HDF5 chunk length along the frame axis (default: :func:`chunk_rows`).
    compression : int
        gzip level (0 for none; 1 is fast and already removes the fill of half-empty chunks).

    Attributes
    ----------
    frames_written : int
        Frames on disk as of the last flush.
    truth_dropped : int
        Frames whose truth could not be stored (truth absent from the first chunk, or a truth of another
        shape).
    vendor_dropped : int
        Sensor blocks (:attr:`Frame.vendor`) that could not be stored (module docstring).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        fiber: FiberModel | None = None,
        calibration: Calibration | None = None,
        source_url: str = "",
        rate: float | None = None,
        flush_frames: int = 1000,
        flush_interval: float = 0.5,
        chunk: int | None = None,
        compression: int = 1,
    ):
        h5py = require("h5py", "HDF5 recording")

        self.path = Path(path)
        self.fiber, self.calibration, self.rate = fiber, calibration, rate
        self.flush_frames, self.flush_interval = int(flush_frames), float(flush_interval)
        self.chunk = None if chunk is None else int(chunk)
        self.compression = int(compression)
        try:
            # a chunk cache larger than a chunk, so that a flush of part of a chunk does not recompress it twice
            self._file = h5py.File(self.path, "w", libver="latest", rdcc_nbytes=4 * _CHUNK_BYTES)
        except OSError as exc:
            raise OSError(f"{self.path}: cannot create the recording ({exc})") from None
        a = self._file.attrs
        a["format"] = FORMAT
        a["version"] = VERSION
        a["fiber_toml"] = _toml(fiber) if fiber is not None else ""
        a["calibration_toml"] = _toml(calibration) if calibration is not None else ""
        a["source_url"] = source_url
        a["created_utc"] = _utc_now()
        a["software"] = _software()
        a["rate_hz"] = float(rate) if rate else float("nan")
        a["frames"] = 0
        a["complete"] = False
        self._pending: list[Frame] = []
        self._received: list[tuple[int, float]] = []
        self._n_pending = 0
        self._ds: dict[str, object] = {}
        self._shape: tuple[int, int] | None = None
        self._truth_ref: Truth | None = None
        self._vendor_ref: list = []  # (G, N, spacing) of each sensor's first block in the first flush
        self._last_flush = time.monotonic()
        self.frames_written = 0
        self.flushes = 0
        self.truth_dropped = 0
        self.vendor_dropped = 0
        self._closed = False

    # ---------------------------------------------------------------- sink interface
    def __call__(self, frames: Frame, shapes=None, status=None) -> None:
        """The live-loop sink: append a batch (an empty one is a heartbeat: flush when due)."""
        if len(frames):
            self.append(frames)
        elif time.monotonic() - self._last_flush >= self.flush_interval and self._pending:
            self.flush()

    def append(self, frames: Sequence[Frame] | Frame, received: float | None = None) -> None:
        """Buffer frames (flushing when due).

        Parameters
        ----------
        frames : Frame (one or a 1-D batch) or sequence of Frame
            All with the same (n_gratings, n_cores) as the first frame ever appended.
        received : float, optional
            Wall-clock receive time of the batch, s (default now).

        Raises
        ------
        ValueError
            A frame of another shape (what was buffered is flushed first).
        """
        if self._closed:
            raise ValueError(f"{self.path}: recorder is closed")
        items = [frames] if isinstance(frames, Frame) else list(frames)
        if not items:
            return
        if self._shape is None:
            self._shape = items[0].wavelengths.shape[-2:]
        t = time.time() if received is None else float(received)
        bad = next((f for f in items if f.wavelengths.shape[-2:] != self._shape), None)
        if bad is not None:
            good = [f for f in items if f.wavelengths.shape[-2:] == self._shape]
            self._buffer(good, t)
            self.flush()
            g, c = bad.wavelengths.shape[-2:]
            raise ValueError(f"{self.path}: frame {bad.sequence} has {g} gratings × {c} cores, the recording "
                             f"{self._shape[0]} × {self._shape[1]}")
        self._buffer(items, t)
        if self._n_pending >= self.flush_frames or time.monotonic() - self._last_flush >= self.flush_interval:
            self.flush()

    def _buffer(self, items: list[Frame], t: float) -> None:
        for f in items:
            k = len(f) if f.batch_shape else 1
            if k:
                self._pending.append(f)
                self._received.append((k, t))
                self._n_pending += k

    # ---------------------------------------------------------------- datasets
    def _create(self, truth: Truth | None, vendor: Sequence) -> None:
        f = self._file
        g, c = self._shape

        def make(name: str, shape: tuple[int, ...], dtype, fill=None) -> None:
            kw = {"fillvalue": fill} if fill is not None else {}
            if self.compression > 0:
                kw.update(compression="gzip", compression_opts=self.compression, shuffle=True)
            row_bytes = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
            ch = self.chunk or chunk_rows(self.rate, self.flush_interval, row_bytes)
            self._ds[name] = f.create_dataset(name, shape=(0, *shape), maxshape=(None, *shape),
                                              chunks=(ch, *shape), dtype=dtype, fletcher32=True, **kw)

        make("frames/timestamp", (), "f8", np.nan)
        make("frames/sequence", (), "i8")
        make("frames/received", (), "f8", np.nan)
        make("frames/wavelengths", (g, c), "f8", np.nan)
        make("frames/powers", (g, c), "f4", np.nan)
        make("frames/status", (g, c), "u1")
        # rows committed: written after the data of each flush (readers trust no row beyond it)
        self._ds["frames/count"] = f.create_dataset("frames/count", data=np.zeros(1, dtype=np.int64))
        if truth is not None:
            self._truth_ref = truth
            f.create_dataset("truth/s", data=np.asarray(truth.s, dtype=np.float64))
            if truth.fixture is not None:
                f.create_dataset("truth/fixture", data=np.asarray(truth.fixture, dtype=np.float64))
            make("truth/present", (), "?")
            for name in TRUTH_FIELDS:
                v = getattr(truth, name)
                if v is not None:
                    shp = np.shape(v)[len(truth.batch_shape):]
                    make(f"truth/{name}", shp, "f4" if name == "frames" else "f8", np.nan)
        self._vendor_ref = list(vendor)
        for k, (g, m, spacing) in enumerate(self._vendor_ref):
            f.create_dataset(f"vendor/sensor{k}/spacing", data=np.float64(spacing))
            make(f"vendor/sensor{k}/present", (), "?")
            make(f"vendor/sensor{k}/curvature", (g,), "f8", np.nan)
            make(f"vendor/sensor{k}/angle", (g,), "f8", np.nan)
            make(f"vendor/sensor{k}/positions", (m, 3), "f8", np.nan)
        try:
            f.swmr_mode = True
        except (ValueError, RuntimeError, OSError):  # pragma: no cover - HDF5 without SWMR: flushes still apply
            pass

    def flush(self) -> None:
        """Append the buffered frames and flush the file to disk."""
        self._last_flush = time.monotonic()
        if not self._pending:
            return
        items, received = self._pending, self._received
        self._pending, self._received, self._n_pending = [], [], 0
        # each item's sensor blocks as rows per sensor (single frames and batches alike)
        vendors = [vendor_rows(f) for f in items]
        counts = [len(f) if f.batch_shape else 1 for f in items]
        if not self._ds:
            first: dict[int, tuple] = {}
            for rows in vendors:
                for k, a in enumerate(rows):
                    if a.present.any():
                        first.setdefault(k, a.layout)
            self._create(next((f.truth for f in items if f.truth is not None), None),
                         [first[k] for k in range(len(first))])
        offered = sum(int(np.count_nonzero(f.truth.all_present)) for f in items if f.truth is not None)
        batch = Frame.stack(items, truth_like=self._truth_ref)
        n0, n = self.frames_written, len(batch)
        cols = {
            "frames/timestamp": batch.timestamp,
            "frames/sequence": batch.sequence,
            "frames/received": np.repeat([t for _, t in received], [k for k, _ in received]),
            "frames/wavelengths": batch.wavelengths,
            "frames/powers": np.full(batch.wavelengths.shape, np.nan, np.float32) if batch.powers is None
            else batch.powers.astype(np.float32),
            "frames/status": batch.status_or_missing,
        }
        if self._truth_ref is not None:
            t = batch.truth
            present = np.zeros(n, bool) if t is None else np.asarray(t.all_present)
            cols["truth/present"] = present
            for name in TRUTH_FIELDS:
                if f"truth/{name}" in self._ds:
                    cols[f"truth/{name}"] = np.nan if t is None else getattr(t, name)
            self.truth_dropped += offered - int(present.sum())
        else:
            self.truth_dropped += offered
        cols.update(self._vendor_columns(vendors, counts))
        for name, data in cols.items():
            ds = self._ds[name]
            ds.resize(n0 + n, axis=0)
            ds[n0 : n0 + n] = data
        self.frames_written = n0 + n
        # the count is written after the data: a reader trusts at most this many rows
        self._ds["frames/count"][0] = self.frames_written
        self._file.attrs["frames"] = self.frames_written
        self._file.flush()
        self.flushes += 1

    def _vendor_columns(self, vendors: list, counts: list[int]) -> dict[str, np.ndarray]:
        """The /vendor rows of one flush, from each item's blocks (:func:`~twin.frames.vendor_rows`) in the
        recording's layout per sensor; counts the blocks dropped (another layout, or a sensor beyond those)."""
        offered = sum(int(a.present.sum()) for rows in vendors for a in rows)
        if not offered and not self._vendor_ref:
            return {}
        cols: dict[str, np.ndarray] = {}
        stored = 0
        for k, layout in enumerate(self._vendor_ref):
            a = VendorArrays.concat([rows[k] if len(rows) > k else None for rows in vendors], counts, layout=layout)
            stored += int(a.present.sum())
            for name in VENDOR_FIELDS:
                cols[f"vendor/sensor{k}/{name}"] = getattr(a, name)
        self.vendor_dropped += offered - stored
        return cols

    def close(self) -> None:
        """Flush everything, mark the recording complete and close the file. Idempotent."""
        if self._closed:
            return
        try:
            self.flush()
            self._file.attrs["complete"] = True
            self._file.flush()
        finally:
            self._closed = True
            self._file.close()

    def stats(self) -> dict:
        return {
            "frames_written": self.frames_written,
            "frames_buffered": self._n_pending,
            "flushes": self.flushes,
            "truth_dropped": self.truth_dropped,
            "vendor_dropped": self.vendor_dropped,
        }

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _software() -> str:
    from twin import __version__

    return f"twin {__version__}"
