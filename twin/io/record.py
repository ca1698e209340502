"""Recording frames to HDF5 and reading them back (``twin live --record``, ``twin replay``, ``replay://``).

File layout (format ``twin-recording`` version 1; every array batch-first along the frame axis n)::

    /frames/timestamp     float64 (n,)            the source's acquisition time, s (NaN when unknown)
    /frames/sequence      int64   (n,)            sample numbers as the source gave them
    /frames/received      float64 (n,)            wall-clock time the live loop received the frame, s (UTC epoch)
    /frames/wavelengths   float64 (n, g, c)       nm, NaN where a peak is missing
    /frames/powers        float32 (n, g, c)       as reported (NaN when the source gives none)
    /frames/status        uint8   (n, g, c)       twin.PeakStatus bits
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

Durability: frames are buffered in memory and appended in chunks, and the file is flushed every
``flush_frames`` frames or ``flush_interval`` seconds, whichever comes first, and on close. The file is
written in HDF5's single-writer/multiple-reader (SWMR) mode, whose ordered metadata writes keep it readable at
any instant, so a process killed at any point leaves a file holding everything up to its last flush (at most
``flush_interval`` s of frames are lost; ``complete`` stays False). Readers open such a file in SWMR mode,
which also lets ``twin replay`` read a recording while it is being written. Truth datasets are created from
the first chunk (SWMR forbids new datasets later): truth that first appears after it is counted in
:attr:`Recorder.truth_dropped` and not stored.

ILLumiSense log files (``*.txt``, one record per line as lab loggers save the stream) are read too:
:func:`read_recording` detects them by content and :mod:`twin.io.illumisense_log` reads them (layout, header
lines, skipped lines, the vendor's own shapes in :attr:`RecordingReader.vendor`).
"""

from __future__ import annotations

import datetime as _dt
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin.calibration import Calibration
from twin.fiber import FiberModel
from twin.frames import Frame, PeakStatus, Truth
from twin.io.source import Source, SourceClosed, parse_url

__all__ = [
    "FORMAT",
    "FrameArrays",
    "Recorder",
    "RecordingReader",
    "ReplaySource",
    "TruthArrays",
    "open_recording",
    "open_replay",
]

FORMAT = "twin-recording"
VERSION = 1
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_MISSING = np.uint8(PeakStatus.MISSING)
_TRUTH_FIELDS = ("positions", "frames", "curvature", "twist", "temperature")


def _toml(obj) -> str:
    import tomli_w

    return tomli_w.dumps(obj.to_dict())


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


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
        The source's nominal rate, Hz.
    flush_frames : int
        Flush at least every this many frames.
    flush_interval : float
        Flush at least every this many seconds (checked on each append), s.
    chunk : int
        HDF5 chunk length along the frame axis.

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
        chunk: int = 256,
    ):
        import h5py

        self.path = Path(path)
        self.fiber, self.calibration = fiber, calibration
        self.flush_frames, self.flush_interval, self.chunk = int(flush_frames), float(flush_interval), int(chunk)
        try:
            self._file = h5py.File(self.path, "w", libver="latest")
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
        self._received: list[float] = []
        self._ds: dict[str, object] = {}
        self._shape: tuple[int, int] | None = None
        self._truth_shape: dict[str, tuple[int, ...]] = {}
        self._truth_s: np.ndarray | None = None
        self._last_flush = time.monotonic()
        self.frames_written = 0
        self.flushes = 0
        self.truth_dropped = 0
        self._closed = False

    # ---------------------------------------------------------------- sink interface
    def __call__(self, frames: Sequence[Frame], shapes=None, status=None) -> None:
        if frames:
            self.append(frames)
        elif time.monotonic() - self._last_flush >= self.flush_interval and self._pending:
            self.flush()

    def append(self, frames: Sequence[Frame] | Frame, received: float | None = None) -> None:
        """Buffer frames (flushing when due).

        Parameters
        ----------
        frames : Frame or sequence of Frame
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
        if isinstance(frames, Frame):
            frames = [frames]
        if not frames:
            return
        if self._shape is None:
            self._shape = frames[0].wavelengths.shape
        bad = next((f for f in frames if f.wavelengths.shape != self._shape), None)
        if bad is not None:
            good = [f for f in frames if f.wavelengths.shape == self._shape]
            self._pending.extend(good)
            self._received.extend([time.time() if received is None else received] * len(good))
            self.flush()
            raise ValueError(
                f"{self.path}: frame {bad.sequence} has {bad.wavelengths.shape[0]} gratings × "
                f"{bad.wavelengths.shape[1]} cores, the recording {self._shape[0]} × {self._shape[1]}"
            )
        self._pending.extend(frames)
        self._received.extend([time.time() if received is None else received] * len(frames))
        if len(self._pending) >= self.flush_frames or time.monotonic() - self._last_flush >= self.flush_interval:
            self.flush()

    # ---------------------------------------------------------------- datasets
    def _create(self, first: Sequence[Frame]) -> None:
        f = self._file
        g, c = self._shape
        ch = self.chunk

        def make(name: str, shape: tuple[int, ...], dtype, fill=None) -> None:
            kw = {"fillvalue": fill} if fill is not None else {}
            self._ds[name] = f.create_dataset(
                name, shape=(0, *shape), maxshape=(None, *shape), chunks=(ch, *shape), dtype=dtype, **kw
            )

        make("frames/timestamp", (), "f8", np.nan)
        make("frames/sequence", (), "i8")
        make("frames/received", (), "f8", np.nan)
        make("frames/wavelengths", (g, c), "f8", np.nan)
        make("frames/powers", (g, c), "f4", np.nan)
        make("frames/status", (g, c), "u1")
        # rows committed: written after the data of each flush (readers trust no row beyond it)
        self._ds["frames/count"] = f.create_dataset("frames/count", data=np.zeros(1, dtype=np.int64))
        truth = next((fr.truth for fr in first if fr.truth is not None), None)
        if truth is not None:
            s = np.asarray(truth.s, dtype=np.float64)
            self._truth_s = s
            f.create_dataset("truth/s", data=s)
            if truth.fixture is not None:
                f.create_dataset("truth/fixture", data=np.asarray(truth.fixture, dtype=np.float64))
            make("truth/present", (), "?")
            for name in _TRUTH_FIELDS:
                v = getattr(truth, name)
                if v is not None:
                    shp = np.shape(v)
                    self._truth_shape[name] = shp
                    make(f"truth/{name}", shp, "f4" if name == "frames" else "f8", np.nan)
        try:
            f.swmr_mode = True
        except (ValueError, RuntimeError, OSError):  # pragma: no cover - HDF5 without SWMR: flushes still apply
            pass

    def _truth_ok(self, truth: Truth | None) -> bool:
        if truth is None or self._truth_s is None:
            return False
        if np.shape(truth.s) != self._truth_s.shape or not np.array_equal(truth.s, self._truth_s):
            return False
        return all(
            getattr(truth, name) is not None and np.shape(getattr(truth, name)) == shp
            for name, shp in self._truth_shape.items()
        )

    def flush(self) -> None:
        """Append the buffered frames and flush the file to disk."""
        self._last_flush = time.monotonic()
        if not self._pending:
            return
        frames, received = self._pending, self._received
        self._pending, self._received = [], []
        if not self._ds:
            self._create(frames)
        n0, n = self.frames_written, len(frames)
        w = np.stack([fr.wavelengths for fr in frames])
        cols = {
            "frames/timestamp": np.array([fr.timestamp for fr in frames], dtype=np.float64),
            "frames/sequence": np.array([fr.sequence for fr in frames], dtype=np.int64),
            "frames/received": np.asarray(received, dtype=np.float64),
            "frames/wavelengths": w,
            "frames/powers": np.stack(
                [fr.powers if fr.powers is not None else np.full(self._shape, np.nan) for fr in frames]
            ).astype(np.float32),
            "frames/status": np.stack(
                [fr.status if fr.status is not None else np.where(np.isnan(fr.wavelengths), _MISSING, 0)
                 for fr in frames]
            ).astype(np.uint8),
        }
        if "truth/present" in self._ds:
            present = np.array([self._truth_ok(fr.truth) for fr in frames])
            self.truth_dropped += int(np.count_nonzero(~present & np.array([fr.truth is not None for fr in frames])))
            cols["truth/present"] = present
            for name, shp in self._truth_shape.items():
                dtype = np.float32 if name == "frames" else np.float64
                arr = np.full((n, *shp), np.nan, dtype=dtype)
                idx = np.flatnonzero(present)
                if idx.size:
                    arr[idx] = np.stack([getattr(frames[i].truth, name) for i in idx])
                cols[f"truth/{name}"] = arr
        else:
            self.truth_dropped += sum(fr.truth is not None for fr in frames)
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
            "frames_buffered": len(self._pending),
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


@dataclass(frozen=True, eq=False)
class FrameArrays:
    """A slice of a recording's frames as arrays (leading axis: frames).

    Attributes
    ----------
    timestamps : ndarray (n,)
        s.
    sequences : ndarray of int64 (n,)
    wavelengths : ndarray (n, g, c)
        nm, NaN where missing.
    powers : ndarray (n, g, c)
    status : ndarray of uint8 (n, g, c)
    received : ndarray (n,)
        Wall-clock receive times, s (NaN for vendor logs).
    """

    timestamps: np.ndarray
    sequences: np.ndarray
    wavelengths: np.ndarray
    powers: np.ndarray
    status: np.ndarray
    received: np.ndarray

    def __len__(self) -> int:
        return self.sequences.size


@dataclass(frozen=True, eq=False)
class TruthArrays:
    """A slice of a recording's truth (fields absent from the file are None).

    Attributes
    ----------
    s : ndarray (m,)
        m.
    present : ndarray of bool (n,)
    positions : ndarray (n, m, 3)
        m, NaN where absent.
    frames, curvature, twist, temperature
        As in :class:`~twin.frames.Truth`, with a leading frame axis.
    fixture : ndarray (k, 3) or None
    """

    s: np.ndarray
    present: np.ndarray
    positions: np.ndarray
    frames: np.ndarray | None = None
    curvature: np.ndarray | None = None
    twist: np.ndarray | None = None
    temperature: np.ndarray | None = None
    fixture: np.ndarray | None = None


class RecordingReader:
    """Read access to a recording: a twin HDF5 file (also while it is being written, or after its writer was
    killed) or an ILLumiSense log file (module docstring). Use :func:`open_recording`.

    Attributes
    ----------
    path : Path
    kind : {"twin-hdf5", "illumisense-log"}
    fiber, calibration : FiberModel, Calibration or None
        As stored (None for vendor logs and when not stored).
    source_url : str
    complete : bool
        The writer closed the file cleanly (always True for a log file).
    rate : float or None
        Nominal rate, Hz, when stored.
    errors : list of str
        Lines of a log file that were skipped, with their line numbers.
    """

    def __init__(self, path: str | Path, *, channels_as: str = "cores", n_cores: int | None = None):
        self.path = Path(path)
        try:
            with open(self.path, "rb") as fh:
                head = fh.read(8)
        except FileNotFoundError:
            raise FileNotFoundError(f"{self.path}: no such recording") from None
        self.errors: list[str] = []
        self._file = None
        self._mem: FrameArrays | None = None
        self.vendor = None  # the interrogator's own shapes (twin.io.illumisense_log.VendorArrays), logs only
        if head == _HDF5_SIGNATURE:
            self._open_hdf5()
        else:
            self._mem = _read_log(self, channels_as=channels_as, n_cores=n_cores)
            self.kind = "illumisense-log"
            self.fiber = self.calibration = None
            self.source_url = f"file://{self.path}"
            self.complete = True
            self.rate = None
            self._n = len(self._mem)

    def _open_hdf5(self) -> None:
        import h5py

        try:
            self._file = h5py.File(self.path, "r")
        except OSError:
            try:  # written in SWMR mode and not closed (still recording, or the writer was killed)
                self._file = h5py.File(self.path, "r", libver="latest", swmr=True)
            except OSError as exc:
                raise ValueError(f"{self.path}: not a readable HDF5 recording ({exc})") from None
        a = self._file.attrs
        if a.get("format") != FORMAT:
            self._file.close()
            raise ValueError(f"{self.path}: HDF5 file is not a twin recording (format attribute {a.get('format')!r})")
        self.kind = "twin-hdf5"
        self.fiber = FiberModel.from_dict(_load_toml(a["fiber_toml"]), source=f"{self.path} fiber_toml") \
            if a.get("fiber_toml") else None
        self.calibration = Calibration.from_dict(_load_toml(a["calibration_toml"]),
                                                 source=f"{self.path} calibration_toml") \
            if a.get("calibration_toml") else None
        self.source_url = str(a.get("source_url", ""))
        self.complete = bool(a.get("complete", False))
        rate = float(a.get("rate_hz", np.nan))
        self.rate = rate if np.isfinite(rate) else None
        self.refresh()

    def refresh(self) -> int:
        """Re-read how many frames are available (grows while a writer appends); returns it."""
        if self._file is None:
            return self._n
        f = self._file
        if "frames" not in f:
            self._n = 0
            return 0
        names = [f"frames/{k}" for k in ("timestamp", "sequence", "received", "wavelengths", "powers", "status")]
        if "truth/present" in f:
            names += [f"truth/{k}" for k in ("present", *_TRUTH_FIELDS) if f"truth/{k}" in f]
        for name in [*names, "frames/count"]:
            try:
                f[name].refresh()
            except (KeyError, AttributeError, ValueError, RuntimeError):  # not SWMR: nothing to refresh
                pass
        # rows every dataset has (a writer killed mid-flush may have resized some datasets but not others),
        # and no more than the committed count
        n = min(f[name].shape[0] for name in names)
        if "frames/count" in f:
            n = min(n, int(f["frames/count"][0]))
        self._n = n
        self.complete = bool(f.attrs.get("complete", False))
        return self._n

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
        return self._file is not None and "truth/present" in self._file

    def arrays(self, start: int = 0, stop: int | None = None) -> FrameArrays:
        """Frames ``start:stop`` as arrays."""
        stop = self._n if stop is None else min(stop, self._n)
        start = max(0, min(start, stop))
        if self._mem is not None:
            m = self._mem
            return FrameArrays(*(getattr(m, k)[start:stop] for k in
                                 ("timestamps", "sequences", "wavelengths", "powers", "status", "received")))
        f = self._file
        return FrameArrays(
            timestamps=f["frames/timestamp"][start:stop],
            sequences=f["frames/sequence"][start:stop],
            wavelengths=f["frames/wavelengths"][start:stop],
            powers=f["frames/powers"][start:stop].astype(np.float64),
            status=f["frames/status"][start:stop],
            received=f["frames/received"][start:stop],
        )

    def truth(self, start: int = 0, stop: int | None = None) -> TruthArrays | None:
        """Truth of frames ``start:stop``, or None when the recording has none."""
        if not self.has_truth:
            return None
        stop = self._n if stop is None else min(stop, self._n)
        start = max(0, min(start, stop))
        f = self._file
        kw = {k: f[f"truth/{k}"][start:stop] for k in _TRUTH_FIELDS if f"truth/{k}" in f}
        if "frames" in kw:
            kw["frames"] = kw["frames"].astype(np.float64)
        return TruthArrays(
            s=f["truth/s"][()],
            present=f["truth/present"][start:stop],
            fixture=f["truth/fixture"][()] if "truth/fixture" in f else None,
            **kw,
        )

    def frames(self, start: int = 0, stop: int | None = None) -> list[Frame]:
        """Frames ``start:stop`` as :class:`~twin.frames.Frame` objects (with their Truth when recorded)."""
        a = self.arrays(start, stop)
        t = self.truth(start, stop)
        out = []
        for i in range(len(a)):
            truth = None
            if t is not None and t.present[i]:
                truth = Truth(
                    s=t.s,
                    positions=t.positions[i],
                    frames=None if t.frames is None else t.frames[i],
                    curvature=None if t.curvature is None else t.curvature[i],
                    twist=None if t.twist is None else t.twist[i],
                    temperature=None if t.temperature is None else t.temperature[i],
                    fixture=t.fixture,
                )
            out.append(Frame(a.wavelengths[i], float(a.timestamps[i]), int(a.sequences[i]), a.powers[i],
                             a.status[i], truth))
        return out

    def chunks(self, size: int = 1024) -> Iterator[tuple[int, FrameArrays]]:
        """(start, arrays) for consecutive slices of ``size`` frames."""
        for start in range(0, self._n, size):
            yield start, self.arrays(start, start + size)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_recording(path: str | Path, **kw) -> RecordingReader:
    """Open a twin HDF5 recording or an ILLumiSense log file for reading (see :class:`RecordingReader`)."""
    return RecordingReader(path, **kw)


def _load_toml(text) -> dict:
    import tomllib

    if isinstance(text, bytes):
        text = text.decode("utf-8")
    return tomllib.loads(str(text))


def _read_log(reader: RecordingReader, *, channels_as: str, n_cores: int | None) -> FrameArrays:
    """Decode an ILLumiSense log file (:mod:`twin.io.illumisense_log`)."""
    from twin.io.illumisense_log import read_log

    log = read_log(reader.path, channels_as=channels_as, n_cores=n_cores)
    reader.errors.extend(log.errors)
    reader.vendor = log.vendor
    return FrameArrays(log.timestamps, log.sequences, log.wavelengths, log.powers, log.status,
                       np.full(log.sequences.size, np.nan))


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
    """

    def __init__(self, path: str | Path, *, speed: float | None = 1.0, follow: bool = False, chunk: int = 512,
                 url: str = "", channels_as: str = "cores", n_cores: int | None = None):
        self.reader = open_recording(path, channels_as=channels_as, n_cores=n_cores)
        self.url = url or f"replay://{path}"
        self.fiber = self.reader.fiber
        self.calibration = self.reader.calibration
        self.rate = self.reader.rate
        if speed is not None and not (np.isfinite(speed) and speed > 0):
            raise ValueError(f"{self.url}: speed must be a positive factor, 'recorded' or 'max'; got {speed}")
        self.speed = speed
        self.follow = follow
        self.chunk = chunk
        self._buf: list[Frame] = []
        self._times: np.ndarray = np.empty(0)
        self._next = 0  # next file row to load
        self._t_first: float | None = None  # recorded time of the first frame
        self._wall0 = 0.0
        self._delivered = 0

    def _load(self) -> bool:
        n = len(self.reader)
        if self._next >= n and self.follow:
            n = self.reader.refresh()
        if self._next >= n:
            return False
        stop = min(n, self._next + self.chunk)
        frames = self.reader.frames(self._next, stop)
        a = self.reader.arrays(self._next, stop)
        t = np.where(np.isfinite(a.timestamps), a.timestamps, a.received)
        self._buf = frames[::-1]  # pop from the end
        self._times = t[::-1].copy()
        self._next = stop
        return True

    def read(self, timeout: float | None = None) -> Frame | None:
        if self.reader is None:
            raise SourceClosed(f"{self.url}: closed")
        if not self._buf and not self._load():
            if self.follow and not self.reader.complete:
                time.sleep(min(0.05, timeout if timeout is not None else 0.05))
                return None
            raise SourceClosed(f"{self.url}: end of recording ({self._delivered} frames)")
        if self.speed is not None:
            t = float(self._times[len(self._buf) - 1])
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
        return self._buf.pop()

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
            if f is None:
                break
            out.append(f)
        return out

    def close(self) -> None:
        if self.reader is not None:
            self.reader.close()
            self.reader = None

    def stats(self) -> dict:
        return {"frames_replayed": self._delivered, "skipped_lines": len(self.reader.errors) if self.reader else 0}


def open_replay(url: str, **options) -> ReplaySource:
    """Open ``replay://FILE?speed=recorded|max|FACTOR&follow=0|1``.

    ``FILE`` is a path (``replay:///abs/path.h5`` or ``replay://relative.h5``). Default speed: as recorded.
    """
    _, rest, query = parse_url(url)
    if not rest:
        raise ValueError(f"{url!r}: expected replay://FILE")
    known = {"speed", "follow", "cores", "channels"}
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
    kw: dict = {"speed": speed, "follow": query.get("follow", "0") in ("1", "true", "yes")}
    if query.get("channels") == "single":
        kw["channels_as"] = "single"
        kw["n_cores"] = int(query.get("cores", "0") or 0) or None
    options.pop("fiber", None)  # a recording knows its fibre; the live loop takes --fiber separately
    kw.update(options)
    return ReplaySource(rest, url=url, **kw)
