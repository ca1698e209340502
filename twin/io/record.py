"""Recording frames to HDF5 and reading them back (``twin live --record``, ``twin replay``, ``replay://``).

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

Damage: a recording cut short, or with damaged bytes, is opened without waiting on HDF5's retries
(:mod:`twin.io.hdf5`) and reported: :attr:`RecordingReader.damage` says what is wrong, :attr:`len` counts the
frames readable before the first damage, :attr:`RecordingReader.frames_recorded` how many the file claims. A
damaged recording is never ``complete``.

ILLumiSense log files (``*.txt`` written by the vendor software) are read too: :func:`open_recording` detects
them by content. **Assumed columns** — nobody publishes the log format, so the reader assumes what the TCP
stream carries, one record per line, TAB-separated: date, time, sample number, channel count C, then per
channel its number, grating count G, four status integers, G peak wavelengths (nm) and G peak powers, then the
engineering-value count E and E values (docs/protocols.md §1). Lines end in CR LF or LF, a trailing TAB is
allowed, wavelength 0 is a missing peak. Lines before the first record that parses (column names, comments,
settings) are skipped as a header; a later line that does not parse, or whose channel layout differs from the
first record's, is skipped and reported with its line number. A decimal comma is accepted on a line that has
no decimal point elsewhere. Channel k is core k (``channels_as="single"`` with ``n_cores`` for a fibre whose
cores are spliced onto one channel). A log whose last line has no line end was cut: it is reported as damaged
(its last record may be incomplete).
"""

from __future__ import annotations

import datetime as _dt
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from twin.calibration import Calibration
from twin.fiber import FiberModel
from twin.frames import Frame, PeakStatus, Truth
from twin.io.errors import FramingError, RecordingDamaged
from twin.io.source import Source, SourceClosed, parse_url

__all__ = [
    "FORMAT",
    "Recorder",
    "RecordingReader",
    "ReplaySource",
    "open_recording",
    "open_replay",
]

FORMAT = "twin-recording"
VERSION = 1
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_MISSING = np.uint8(PeakStatus.MISSING)
_TRUTH_FIELDS = ("positions", "frames", "curvature", "twist", "temperature")
_FRAME_FIELDS = ("timestamp", "sequence", "received", "wavelengths", "powers", "status")
_CHUNK_BYTES = 1 << 20


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
        import h5py

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
        self._last_flush = time.monotonic()
        self.frames_written = 0
        self.flushes = 0
        self.truth_dropped = 0
        self._closed = False

    # ---------------------------------------------------------------- sink interface
    def __call__(self, frames: Sequence[Frame] | Frame, shapes=None, status=None) -> None:
        if isinstance(frames, Frame) or len(frames):
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
    def _create(self, truth: Truth | None) -> None:
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
            for name in _TRUTH_FIELDS:
                v = getattr(truth, name)
                if v is not None:
                    shp = np.shape(v)[len(truth.batch_shape):]
                    make(f"truth/{name}", shp, "f4" if name == "frames" else "f8", np.nan)
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
        if not self._ds:
            self._create(next((f.truth for f in items if f.truth is not None), None))
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
            for name in _TRUTH_FIELDS:
                if f"truth/{name}" in self._ds:
                    cols[f"truth/{name}"] = np.nan if t is None else getattr(t, name)
            self.truth_dropped += offered - int(present.sum())
        else:
            self.truth_dropped += offered
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
        }

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _software() -> str:
    from twin import __version__

    return f"twin {__version__}"


# ------------------------------------------------------------------------------------------------- reading


class RecordingReader:
    """Read access to a recording: a twin HDF5 file (also while it is being written, after its writer was
    killed, or damaged) or an ILLumiSense log file (module docstring). Use :func:`open_recording`.

    Attributes
    ----------
    path : Path
    kind : {"twin-hdf5", "illumisense-log"}
    fiber, calibration : FiberModel, Calibration or None
        As stored (None for vendor logs and when not stored).
    source_url : str
    complete : bool
        The writer closed the file cleanly and nothing is damaged (a log: it ends with a line end).
    rate : float or None
        Nominal rate, Hz, when stored.
    errors : list of str
        Lines of a log file that were skipped, with their line numbers.
    damage : list of str
        What is damaged in the file, each naming the place (dataset, rows, bytes; empty for a sound file).
        Found when opening (a file cut short, chunks past its end) and when reading (chunks failing their
        checksum); ``len`` then counts the frames before the first damage of the frame data (truth rows past
        damaged truth chunks come back absent, ``Truth.present`` False, their frames kept).
    frames_recorded : int
        Frames the file says were written (its committed count); more than ``len`` when damaged.
    """

    def __init__(self, path: str | Path, *, channels_as: str = "cores", n_cores: int | None = None):
        self.path = Path(path)
        try:
            with open(self.path, "rb") as fh:
                head = fh.read(8)
                fh.seek(0, 2)
                size = fh.tell()
                if size:
                    fh.seek(size - 1)
                last = fh.read(1)
        except FileNotFoundError:
            raise FileNotFoundError(f"{self.path}: no such recording") from None
        except IsADirectoryError:
            raise IsADirectoryError(f"{self.path}: is a directory, not a recording") from None
        self.errors: list[str] = []
        self.damage: list[str] = []
        self._file = None
        self._mem: Frame | None = None
        self._truth_names: list[str] = []
        if head == _HDF5_SIGNATURE:
            self._open_hdf5()
        else:
            self._mem = _read_log(self.path, self.errors, channels_as=channels_as, n_cores=n_cores)
            self.kind = "illumisense-log"
            self.fiber = self.calibration = None
            self.source_url = f"file://{self.path}"
            self._closed_cleanly = True
            self.rate = None
            self._n = self.frames_recorded = len(self._mem)
            if last not in (b"\n", b"\r"):
                self.damage.append("the last line has no line end: the file was cut (its last record may be "
                                   "incomplete)")

    @property
    def complete(self) -> bool:
        return self._closed_cleanly and not self.damage

    @property
    def damaged(self) -> bool:
        return bool(self.damage)

    def _open_hdf5(self) -> None:
        from twin.io.hdf5 import open_hdf5

        opened = open_hdf5(self.path)
        self._file, self._swmr = opened.file, opened.swmr
        if opened.truncated:
            self.damage.append(f"the file is cut short: {opened.truncated[0]} of {opened.truncated[1]} bytes")
        try:
            a = self._file.attrs
            fmt = a.get("format")
            if isinstance(fmt, bytes):
                fmt = fmt.decode("utf-8", "replace")
            if fmt is None and self.damage:
                raise ValueError(f"{self.path}: not a readable twin recording ({self.damage[0]})")
            if fmt != FORMAT:
                raise ValueError(f"{self.path}: HDF5 file is not a twin recording (format attribute {fmt!r})")
            self.kind = "twin-hdf5"
            self.fiber = self._attr_model(a, "fiber_toml", FiberModel)
            self.calibration = self._attr_model(a, "calibration_toml", Calibration)
            self.source_url = _text(a.get("source_url", ""))
            self._closed_cleanly = bool(a.get("complete", False))
            rate = _number(a.get("rate_hz", np.nan))
            self.rate = rate if np.isfinite(rate) and rate > 0 else None
            f = self._file
            self._names = [f"frames/{k}" for k in _FRAME_FIELDS if f"frames/{k}" in f] if "frames" in f else []
            if "truth/present" in f and "truth/s" in f:
                self._truth_names = [k for k in _TRUTH_FIELDS if f"truth/{k}" in f]
            self._n = self.frames_recorded = 0
            self.refresh()
        except Exception as exc:  # anything HDF5 raises for damaged metadata: one line
            self._file.close()
            if isinstance(exc, ValueError | OSError) and str(exc).startswith(str(self.path)):
                raise
            raise ValueError(f"{self.path}: not a readable twin recording ({_brief(exc)})") from None

    def _attr_model(self, attrs, name: str, cls):
        text = attrs.get(name)
        if not text:
            return None
        where = f"{self.path}: attribute {name}"
        try:
            return cls.from_dict(_load_toml(text), source=where)
        except Exception as exc:  # TOML errors, wrong types: one line naming the place
            msg = str(exc)
            raise ValueError(msg if msg.startswith(str(self.path)) else f"{where}: {msg}") from None

    def refresh(self) -> int:
        """Re-read how many frames are available (grows while a writer appends); returns it."""
        if self._file is None:
            return self._n
        f = self._file
        names = self._names + ([f"truth/{k}" for k in ("present", *self._truth_names)] if self.has_truth else [])
        if len(self._names) < len(_FRAME_FIELDS) or "frames/count" not in f:
            if self._names or "frames/count" in f:
                self._damaged(0, "datasets missing from /frames")
            self._n = 0
            return 0
        try:
            for name in [*names, "frames/count"]:
                if self._swmr:
                    f[name].refresh()
            count = int(f["frames/count"][0])
            rows = min(f[name].shape[0] for name in names)
            self._closed_cleanly = bool(f.attrs.get("complete", False))
        except Exception as exc:
            if self._n and not self._closed_cleanly:  # a writer caught mid-flush: try again later
                return self._n
            raise ValueError(f"{self.path}: not a readable twin recording ({_brief(exc)})") from None
        if count < 0 or (count > rows and self._closed_cleanly):
            self._damaged(0, f"frames/count is {count} but the datasets hold {rows} rows")
            count = max(0, min(count, rows))
        self.frames_recorded = count
        # rows every dataset has (a writer killed mid-flush may have resized some datasets but not others),
        # no more than the committed count, and only those whose chunks are inside the file
        n = min(rows, count)
        from twin.io.hdf5 import readable_rows

        size = _size(self.path)
        truth_ok = n
        for name in names:
            is_truth = name.startswith("truth/")
            want = truth_ok if is_truth else n
            ok, why = readable_rows(f[name], want, size)
            if ok < want and _size(self.path) > size:  # a writer's flush landed meanwhile
                size = _size(self.path)
                ok, why = readable_rows(f[name], want, size)
            if ok < want:
                self._damaged(ok, why, truth=is_truth)
                if is_truth:
                    truth_ok = ok
                else:
                    n = truth_ok = ok
        self._n = n if not self.damage else min(n, self._n_limit())
        return self._n

    def _n_limit(self) -> int:
        return getattr(self, "_first_bad", 1 << 62)

    def _damaged(self, row: int, why: str, truth: bool = False) -> None:
        """Note damage from ``row`` on: of the frames, or (``truth``) only of their truth, which is then absent
        from that row on while the frames stay readable."""
        if truth:
            self._truth_ok = min(row, getattr(self, "_truth_ok", 1 << 62))
        else:
            self._first_bad = min(row, self._n_limit())
            self._n = min(getattr(self, "_n", 0), self._first_bad)
        if why not in self.damage:
            self.damage.append(why)

    def __len__(self) -> int:
        return self._n

    @property
    def shape(self) -> tuple[int, int] | None:
        """(n_gratings, n_cores) of the frames, or None for an empty recording."""
        if self._mem is not None:
            return self._mem.wavelengths.shape[1:]
        if self._file is None or "frames/wavelengths" not in self._file:
            return None
        return tuple(self._file["frames/wavelengths"].shape[1:])

    @property
    def has_truth(self) -> bool:
        return bool(self._truth_names)

    def _span(self, start: int, stop: int | None) -> tuple[int, int]:
        stop = self._n if stop is None else min(stop, self._n)
        return max(0, min(start, stop)), stop

    def _read(self, names: Sequence[str], start: int, stop: int, truth: bool = False
              ) -> tuple[dict[str, np.ndarray], int]:
        """Rows start:stop of datasets; on a read error, the rows before the first bad chunk (damage noted)."""
        out: dict[str, np.ndarray] = {}
        end = stop
        for name in names:
            ds = self._file[name]
            try:
                out[name] = ds[start:end]
                continue
            except Exception:  # find the first chunk that fails (checksum, decompression)
                pass
            step = ds.chunks[0] if ds.chunks else end - start
            row = start
            parts = []
            while row < end:
                nxt = min(end, (row // step + 1) * step)
                try:
                    parts.append(ds[row:nxt])
                except Exception as exc:
                    self._damaged(row, f"{name} rows {row}–{nxt - 1} unreadable ({_brief(exc)})", truth)
                    break
                row = nxt
            end = row
            out[name] = np.concatenate(parts) if parts else ds[0:0]
        return {k: v[: end - start] for k, v in out.items()}, end

    def frames(self, start: int = 0, stop: int | None = None, *, truth: bool = True) -> Frame:
        """Frames ``start:stop`` as one batch :class:`~twin.frames.Frame` (with their truth when recorded and
        ``truth``). Fewer rows come back when a chunk turns out to be damaged (:attr:`damage`)."""
        start, stop = self._span(start, stop)
        if self._mem is not None:
            return self._mem[start:stop]
        cols, stop = self._read([f"frames/{k}" for k in ("timestamp", "sequence", "wavelengths", "powers",
                                                          "status")], start, stop)
        t = None
        if truth and self.has_truth:
            t, stop = self._truth(start, stop, self._truth_names)
            cols = {k: v[: stop - start] for k, v in cols.items()}
        return Frame(cols["frames/wavelengths"], cols["frames/timestamp"], cols["frames/sequence"],
                     cols["frames/powers"].astype(np.float64), cols["frames/status"],
                     None if t is None else t[: stop - start])

    def truth(self, start: int = 0, stop: int | None = None, fields: Sequence[str] | None = None) -> Truth | None:
        """Truth of frames ``start:stop`` as a batched :class:`~twin.frames.Truth` (only ``fields`` when given;
        positions always), or None when the recording has none."""
        if not self.has_truth:
            return None
        start, stop = self._span(start, stop)
        names = [k for k in self._truth_names if fields is None or k in fields or k == "positions"]
        return self._truth(start, stop, names)[0]

    def _truth(self, start: int, stop: int, names: Sequence[str]) -> tuple[Truth, int]:
        """Truth of rows start:stop; rows past damaged truth chunks come back absent (``present`` False)."""
        f = self._file
        fields = ["truth/present", *(f"truth/{k}" for k in names)]
        end = max(start, min(stop, getattr(self, "_truth_ok", stop)))
        cols, end = self._read(fields, start, end, truth=True)
        m = stop - start
        for name in fields:  # pad damaged rows: absent, NaN
            ds, v = f[name], cols[name]
            if len(v) < m:
                pad = np.full((m - len(v), *ds.shape[1:]), False if name == "truth/present" else np.nan,
                              dtype=ds.dtype)
                cols[name] = np.concatenate([v, pad])
        kw = {k: cols[f"truth/{k}"] for k in names}
        if "frames" in kw:
            kw["frames"] = kw["frames"].astype(np.float64)
        return Truth(s=f["truth/s"][()], present=cols["truth/present"],
                     fixture=f["truth/fixture"][()] if "truth/fixture" in f else None, **kw), stop

    def received(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Wall-clock receive times of frames ``start:stop``, s (NaN for vendor logs)."""
        start, stop = self._span(start, stop)
        if self._mem is not None:
            return np.full(stop - start, np.nan)
        return self._read(["frames/received"], start, stop)[0]["frames/received"]

    def chunks(self, size: int = 1024, *, truth: bool = True) -> Iterator[tuple[int, Frame]]:
        """(start, batch) for consecutive slices of ``size`` frames (ending early at damage)."""
        start = 0
        while start < self._n:
            batch = self.frames(start, start + size, truth=truth)
            if len(batch) == 0:
                return
            yield start, batch
            start += len(batch)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _brief(exc: BaseException) -> str:
    return (str(exc).strip() or type(exc).__name__).splitlines()[0][:200]


def _text(v) -> str:
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


def _number(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def open_recording(path: str | Path, **kw) -> RecordingReader:
    """Open a twin HDF5 recording or an ILLumiSense log file for reading (see :class:`RecordingReader`)."""
    return RecordingReader(path, **kw)


def _load_toml(text) -> dict:
    import tomllib

    if isinstance(text, bytes):
        text = text.decode("utf-8")
    return tomllib.loads(str(text))


def _read_log(path: Path, errors: list[str], *, channels_as: str, n_cores: int | None,
              max_header_lines: int = 1000) -> Frame:
    """Decode an ILLumiSense log file (module docstring for the assumed columns)."""
    from twin.io.illumisense import decode_record

    data = path.read_bytes()
    lines = data.splitlines()
    frames: list[Frame] = []
    shape = None
    header_lines = 0
    for no, raw in enumerate(lines, start=1):
        line = raw.rstrip(b"\r")
        if not line.strip():
            continue
        frame = None
        err: FramingError | None = None
        for candidate in (line, line.replace(b",", b".") if b"," in line else None):
            if candidate is None:
                continue
            try:
                frame = decode_record(candidate + b"\r\n", channels_as=channels_as, n_cores=n_cores).frame
                break
            except FramingError as exc:
                err = err or exc
        if frame is None:
            if shape is None:
                header_lines += 1
                if header_lines > max_header_lines:
                    break
                continue
            errors.append(f"line {no}: {err}")
            continue
        if shape is None:
            shape = frame.wavelengths.shape
        elif frame.wavelengths.shape != shape:
            errors.append(f"line {no}: {frame.wavelengths.shape[0]} gratings × {frame.wavelengths.shape[1]} "
                          f"channels, the first record has {shape[0]} × {shape[1]}")
            continue
        frames.append(frame)
    if not frames:
        raise ValueError(f"{path}: neither a twin HDF5 recording nor an ILLumiSense log (no line is a "
                         "TAB-separated record: date, time, sample, C, channels…, E, values…)")
    return Frame.stack(frames)


# -------------------------------------------------------------------------------------------------- replay


class ReplaySource(Source):
    """``replay://FILE?speed=…``: a recording's frames, paced as recorded or as fast as read.

    Parameters
    ----------
    path : str or Path
        A twin HDF5 recording or an ILLumiSense log file.
    speed : float or None
        None: as fast as read. Otherwise the recorded time axis is replayed ``speed`` times faster (1 = as
        recorded), paced by the frames' timestamps (their receive times when timestamps are missing).
    follow : bool
        At the end of a recording that is still being written, wait for more frames instead of ending.
    chunk : int
        Frames read from the file at a time.
    salvage : bool
        A damaged recording: replay the frames before the damage and end normally. Without it, a recording
        found damaged when opened raises :class:`~twin.io.errors.RecordingDamaged` at once, and damage found
        while reading raises it after the frames before it were delivered — a permanent error, which the live
        loop does not retry.
    """

    def __init__(self, path: str | Path, *, speed: float | None = 1.0, follow: bool = False, chunk: int = 512,
                 url: str = "", channels_as: str = "cores", n_cores: int | None = None, salvage: bool = False):
        self.url = url or f"replay://{path}"
        if speed is not None and not (np.isfinite(speed) and speed > 0):
            raise ValueError(f"{self.url}: speed must be a positive factor, 'recorded' or 'max'; got {speed}")
        self.reader = open_recording(path, channels_as=channels_as, n_cores=n_cores)
        self.salvage = bool(salvage)
        if self.reader.damaged and not self.salvage:
            self.reader.close()
            raise RecordingDamaged(_damage_line(self.reader))
        self.fiber = self.reader.fiber
        self.calibration = self.reader.calibration
        self.rate = self.reader.rate
        self.speed = speed
        self.follow = follow
        self.chunk = chunk
        self._batch: Frame | None = None
        self._i = 0
        self._times: np.ndarray = np.empty(0)
        self._next = 0  # next file row to load
        self._t_first: float | None = None  # recorded time of the first frame
        self._wall0 = 0.0
        self._delivered = 0

    def _load(self) -> bool:
        n = len(self.reader)
        if self._next >= n and self.follow and not self.reader.damaged:
            n = self.reader.refresh()
        if self._next >= n:
            return False
        try:
            batch = self.reader.frames(self._next, min(n, self._next + self.chunk))
            received = self.reader.received(self._next, self._next + len(batch))
        except Exception as exc:  # reopening would replay the same bytes: never transient
            raise RecordingDamaged(f"{self.reader.path}: unreadable at frame {self._next} ({exc})") from None
        if len(batch) == 0:
            return False
        m = min(len(batch), len(received))
        self._batch, self._i = batch, 0
        self._times = np.where(np.isfinite(batch.timestamp[:m]), batch.timestamp[:m], received[:m])
        self._next += len(batch)
        return True

    def _pending(self) -> int:
        return 0 if self._batch is None else len(self._batch) - self._i

    def read(self, timeout: float | None = None) -> Frame | None:
        if self.reader is None:
            raise SourceClosed(f"{self.url}: closed")
        if not self._pending() and not self._load():
            if self.reader.damaged and not self.salvage:
                raise RecordingDamaged(_damage_line(self.reader))
            if self.follow and not self.reader.complete and not self.reader.damaged:
                time.sleep(min(0.05, timeout if timeout is not None else 0.05))
                return None
            raise SourceClosed(f"{self.url}: end of recording ({self._delivered} frames)")
        if self.speed is not None and self._i < len(self._times):
            t = float(self._times[self._i])
            if np.isfinite(t):
                if self._t_first is None:
                    self._t_first, self._wall0 = t, time.monotonic()
                wait = self._wall0 + (t - self._t_first) / self.speed - time.monotonic()
                if wait > 0:
                    if timeout is not None and timeout < wait:
                        time.sleep(max(0.0, timeout))
                        return None
                    time.sleep(wait)
        self._delivered += 1
        self._i += 1
        return self._batch[self._i - 1]

    def read_many(self, max_frames: int = 1 << 30, timeout: float | None = None) -> list[Frame]:
        """Frames that are due now, up to ``max_frames`` (waiting up to ``timeout`` s for the first)."""
        first = self.read(timeout)
        if first is None:
            return []
        out = [first]
        while len(out) < max_frames:
            try:
                f = self.read(0.0)
            except SourceClosed:
                break
            except RecordingDamaged as exc:  # deliver what was read; the error comes with the next call
                self._twin_deferred = exc
                break
            if f is None:
                break
            out.append(f)
        return out

    def close(self) -> None:
        if self.reader is not None:
            self.reader.close()
            self.reader = None

    def stats(self) -> dict:
        r = self.reader
        return {"frames_replayed": self._delivered, "skipped_lines": len(r.errors) if r else 0,
                "damaged": bool(r.damage) if r else False}


def _damage_line(reader: RecordingReader) -> str:
    """One line: the file, how many frames are readable of how many, the first damage, what to do."""
    first = reader.damage[0]
    return (f"{reader.path}: damaged recording: {len(reader)} of {reader.frames_recorded} frames readable "
            f"({first}); --salvage (replay://FILE?salvage=1) uses the readable frames")


def open_replay(url: str, **options) -> ReplaySource:
    """Open ``replay://FILE?speed=recorded|max|FACTOR&follow=0|1&salvage=0|1``.

    ``FILE`` is a path (``replay:///abs/path.h5`` or ``replay://relative.h5``). Default speed: as recorded.
    """
    _, rest, query = parse_url(url)
    if not rest:
        raise ValueError(f"{url!r}: expected replay://FILE")
    known = {"speed", "follow", "cores", "channels", "salvage"}
    unknown = sorted(set(query) - known)
    if unknown:
        raise ValueError(f"{url!r}: unknown option(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    sp = query.get("speed", "recorded")
    if sp == "recorded":
        speed: float | None = 1.0
    elif sp == "max":
        speed = None
    else:
        try:
            speed = float(sp)
        except ValueError:
            raise ValueError(f"{url!r}: speed must be 'recorded', 'max' or a factor, got {sp!r}") from None
    yes = ("1", "true", "yes")
    kw: dict = {"speed": speed, "follow": query.get("follow", "0") in yes, "salvage": query.get("salvage", "0") in yes}
    if query.get("channels") == "single":
        kw["channels_as"] = "single"
        kw["n_cores"] = int(query.get("cores", "0") or 0) or None
    options.pop("fiber", None)  # a recording knows its fibre; the live loop takes --fiber separately
    kw.update(options)
    return ReplaySource(rest, url=url, **kw)
