"""Reading recordings back (``twin replay``, ``replay://``): twin HDF5 recordings and ILLumiSense log files.

Twin HDF5 recordings (layout, storage and durability: :mod:`twin.io.hdf5`; written by :class:`Recorder`, which
is importable from here too) are read also while being written and after their writer was killed.

Damage: a recording cut short, or with damaged bytes, is opened without waiting on HDF5's retries
(:mod:`twin.io.hdf5`) and reported: :attr:`RecordingReader.damage` says what is wrong, :attr:`len` counts the
frames readable before the first damage, :attr:`RecordingReader.frames_recorded` how many the file claims. A
damaged recording is never ``complete``. Damage to the truth or to the interrogator's own reconstruction
(``/vendor``) is reported the same way but keeps the frames: their truth or vendor blocks are absent from the
damaged row on.

The interrogator's own reconstruction (ILLumiSense sensor blocks) comes back per sensor as
:class:`~twin.frames.VendorArrays` (:meth:`RecordingReader.vendor`), from a twin recording or a
log alike, and on the single frames of ``replay://`` as :attr:`Frame.vendor <twin.frames.Frame.vendor>`.

ILLumiSense log files (``*.txt``, one record per line as lab loggers save the stream) are read too:
:func:`open_recording` detects them by content and :mod:`twin.io.illumisense.log` reads them (layout, header
lines, skipped lines, the vendor's sensor blocks). A log whose last line has no
line end was cut: it is reported as damaged, and its last record, which may be incomplete, is left out.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from twin.calibration import Calibration
from twin.fiber import FiberModel
from twin.frames import Frame, Truth, VendorArrays
from twin.io.errors import brief
from twin.io.hdf5 import (
    FORMAT,
    FRAME_FIELDS,
    TRUTH_FIELDS,
    VENDOR_FIELDS,
    Recorder,
    chunk_rows,
    open_hdf5,
    readable_rows,
)
from twin.io.reading import ReaderBase

__all__ = ["FORMAT", "Recorder", "RecordingReader", "chunk_rows", "open_recorder", "open_recording"]

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_MCAP_SIGNATURE = b"\x89MCAP0\r\n"


# ------------------------------------------------------------------------------------------------- reading


class RecordingReader(ReaderBase):
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
        The first lines of a log file that were skipped (at most
        :data:`twin.io.illumisense.log.MAX_EXAMPLES`), with their line numbers.
    skipped_lines : int
        Lines of a log file that were skipped, all of them.
    damage : list of str
        What is damaged in the file, each naming the place (dataset, rows, bytes; empty for a sound file).
        Found when opening (a file cut short, chunks past its end) and when reading (chunks failing their
        checksum); ``len`` then counts the frames before the first damage of the frame data (truth rows past
        damaged truth chunks come back absent, ``Truth.present`` False, their frames kept; vendor rows likewise,
        ``VendorArrays.present`` False).
    frames_recorded : int
        Frames the file says were written (its committed count); more than ``len`` when damaged.
    """

    def __init__(self, path: str | Path, *, channels_as: str = "cores", n_cores: int | None = None):
        self.path = Path(path)
        try:
            with open(self.path, "rb") as fh:
                if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):  # /dev/zero, a pipe: would be read forever
                    raise ValueError(f"{self.path}: not a regular file (a device or a pipe); expected a twin HDF5 "
                                     "recording or an ILLumiSense log file")
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
        self.skipped_lines = 0
        self.damage: list[str] = []
        self.notes: list[str] = []  # what reading had to assume (none for these formats; an MCAP reader's)
        # first damaged row of the frames / of their truth / of their vendor blocks
        self._first_bad = self._truth_ok = self._vendor_ok = 1 << 62
        self._file = None
        self._mem: Frame | None = None
        self._vendor_mem: tuple = ()  # a log's sensor blocks (VendorArrays per sensor)
        self._vendor_sensors = 0  # /vendor/sensor<k> groups of a twin recording
        self._truth_names: list[str] = []
        if head == _HDF5_SIGNATURE:
            self._open_hdf5()
        else:
            self._mem = self._read_log(channels_as=channels_as, n_cores=n_cores)
            self.kind = "illumisense-log"
            self.fiber = self.calibration = None
            self.source_url = f"file://{self.path}"
            self._closed_cleanly = True
            self.rate = None
            self._n = self.frames_recorded = len(self._mem)
            if last not in (b"\n", b"\r"):
                self.damage.append("the last line has no line end: the file was cut (its last record, which may "
                                   "be incomplete, is left out)")

    def _read_log(self, *, channels_as: str, n_cores: int | None) -> Frame:
        """Decode an ILLumiSense log file (:mod:`twin.io.illumisense.log`) into one batch of frames, keeping its
        skipped lines and its sensor blocks."""
        from twin.io.illumisense.log import read_log

        log = read_log(self.path, channels_as=channels_as, n_cores=n_cores)
        self.errors.extend(log.errors)
        self.skipped_lines = log.skipped_lines
        self._vendor_mem = log.vendor
        return Frame(log.wavelengths, log.timestamps, log.sequences, powers=log.powers, status=log.status)

    def _open_hdf5(self) -> None:
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
            self._names = [f"frames/{k}" for k in FRAME_FIELDS if f"frames/{k}" in f] if "frames" in f else []
            if "truth/present" in f and "truth/s" in f:
                self._truth_names = [k for k in TRUTH_FIELDS if f"truth/{k}" in f]
            while all(f"vendor/sensor{self._vendor_sensors}/{k}" in f for k in (*VENDOR_FIELDS, "spacing")):
                self._vendor_sensors += 1
            if f"vendor/sensor{self._vendor_sensors}" in f:  # a group the writer created whole, now partial
                self._damaged(0, f"vendor/sensor{self._vendor_sensors}: datasets missing", part="vendor")
            self._check_layout()
            self._n = self.frames_recorded = 0
            self.refresh()
        except Exception as exc:  # anything HDF5 raises for damaged metadata: one line
            self._file.close()
            if isinstance(exc, ValueError | OSError) and str(exc).startswith(str(self.path)):
                raise
            raise ValueError(f"{self.path}: not a readable twin recording ({brief(exc)})") from None

    def _check_layout(self) -> None:
        """Check every dataset's shape and type against the layout (:mod:`twin.io.hdf5`) before anything is read.

        A malformed frame dataset refuses the file (ValueError naming the dataset); malformed truth or vendor
        datasets are damage confined to them (issue 23 B7): the truth, or that sensor and those after it, are
        left out and the damage names the dataset, the frames are kept.
        """
        f = self._file

        def bad(name: str, want: str) -> str:
            ds = f[name]
            if not hasattr(ds, "shape") or ds.dtype.kind not in "biuf":
                return f"{name}: {getattr(ds, 'dtype', 'a group')} is not a numeric dataset"
            return f"{name}: expected shape {want}, got {ds.shape}"

        def check(name: str, ndim: int, tail: tuple, want: str) -> str | None:
            ds = f[name]
            if not hasattr(ds, "shape") or ds.dtype.kind not in "biuf" or ds.ndim != ndim or \
                    any(t is not None and t != got for t, got in zip(tail, ds.shape[1:], strict=False)):
                return bad(name, want)
            return None

        if "frames/wavelengths" in f and hasattr(f["frames/wavelengths"], "shape") and \
                f["frames/wavelengths"].ndim == 3:
            g, c = f["frames/wavelengths"].shape[1:]
        else:
            g = c = None
        for name in self._names:
            k = name.split("/")[1]
            why = check(name, 3, (g, c), "(n, gratings, cores)") if k in ("wavelengths", "powers", "status") \
                else check(name, 1, (), "(n,)")
            if why:
                raise ValueError(f"{self.path}: not a readable twin recording ({why})")
        if self._truth_names:
            s = f["truth/s"]
            m = s.shape[0] if hasattr(s, "shape") and s.ndim == 1 and s.dtype.kind == "f" else None
            tails = {"positions": (3, (m, 3), "(n, len(truth/s), 3)"), "frames": (4, (m, 3, 3), "(n, m, 3, 3)"),
                     "curvature": (3, (g, 2), "(n, gratings, 2)"), "twist": (2, (g,), "(n, gratings)"),
                     "temperature": (2, (g,), "(n, gratings)")}
            why = None if m is not None else bad("truth/s", "(m,)")
            why = why or check("truth/present", 1, (), "(n,)")
            for k in self._truth_names:
                why = why or check(f"truth/{k}", *tails[k])
            if why:
                self._damaged(0, why, part="truth")
                self._truth_names = []
        for j in range(self._vendor_sensors):
            base = f"vendor/sensor{j}"
            sp = f[f"{base}/spacing"]
            why = None
            if not hasattr(sp, "shape") or sp.shape != () or sp.dtype.kind != "f" or not float(sp[()]) > 0:
                why = f"{base}/spacing: expected a positive number, got " + (
                    f"{sp[()]!r}" if hasattr(sp, "shape") and sp.shape == () else f"shape {getattr(sp, 'shape', None)}")
            why = why or check(f"{base}/present", 1, (), "(n,)") or check(f"{base}/curvature", 2, (), "(n, G)")
            if why is None:
                gv = f[f"{base}/curvature"].shape[1]
                why = check(f"{base}/angle", 2, (gv,), "(n, G) like the curvature") or \
                    check(f"{base}/positions", 3, (None, 3), "(n, N, 3)")
            if why:  # this sensor and the later ones are left out (a sensor's index keeps its meaning)
                self._damaged(0, why, part="vendor")
                self._vendor_sensors = j
                break

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
        names += [f"vendor/sensor{j}/{k}" for j in range(self._vendor_sensors) for k in VENDOR_FIELDS]
        if len(self._names) < len(FRAME_FIELDS) or "frames/count" not in f:
            if self._names or "frames/count" in f:
                self._damaged(0, "datasets missing from /frames")
            self._n = 0
            return 0
        try:
            for name in [*names, "frames/count"]:
                if self._swmr:
                    f[name].refresh()
            count = int(f["frames/count"][0])
            held = {name: f[name].shape[0] for name in names}
            self._closed_cleanly = bool(f.attrs.get("complete", False))
        except Exception as exc:
            if self._n and not self._closed_cleanly:  # a writer caught mid-flush: try again later
                return self._n
            raise ValueError(f"{self.path}: not a readable twin recording ({brief(exc)})") from None
        if count < 0:
            self._damaged(0, f"frames/count is {count}")
            count = 0
        self.frames_recorded = count
        # rows every dataset has (a writer killed mid-flush may have resized some datasets but not others),
        # no more than the committed count, and only those whose chunks are inside the file. In a file closed
        # cleanly a short dataset is damage from its last row on: of the frames, or only of their truth or
        # vendor blocks (the frames kept)
        n = min(count, *(held[name] for name in self._names))
        ok_rows = {None: n, "truth": n, "vendor": n}  # rows readable: frames, truth, vendor blocks
        for name, rows in held.items():
            part = name.split("/")[0] if name.startswith(("truth/", "vendor/")) else None
            if rows < count and self._closed_cleanly:
                self._damaged(rows, f"{name} holds {rows} rows, frames/count says {count}", part=part)
            if part is not None and not self._closed_cleanly:
                n = min(n, rows)  # a writer mid-flush: wait for the truth and vendor rows too
            ok_rows[part] = min(ok_rows[part], rows)
        ok_rows = {p: min(v, n) for p, v in ok_rows.items()}
        size = _size(self.path)
        for name in names:
            part = name.split("/")[0] if name.startswith(("truth/", "vendor/")) else None
            want = ok_rows[part]
            ok, why = readable_rows(f[name], want, size)
            if ok < want and _size(self.path) > size:  # a writer's flush landed meanwhile
                size = _size(self.path)
                ok, why = readable_rows(f[name], want, size)
            if ok < want:
                self._damaged(ok, why, part=part)
                ok_rows = {p: min(v, ok) for p, v in ok_rows.items()} if part is None else {**ok_rows, part: ok}
        self._n = min(n, ok_rows[None], self._first_bad)
        return self._n

    def _damaged(self, row: int, why: str, part: str | None = None) -> None:
        """Note damage from ``row`` on: of the frames, or (``part`` "truth" or "vendor") only of their truth or
        vendor blocks, which are then absent from that row on while the frames stay readable."""
        if part == "truth":
            self._truth_ok = min(row, self._truth_ok)
        elif part == "vendor":
            self._vendor_ok = min(row, self._vendor_ok)
        else:
            self._first_bad = min(row, self._first_bad)
            self._n = min(getattr(self, "_n", 0), self._first_bad)
        if why not in self.damage:
            self.damage.append(why)

    def damage_line(self) -> str:
        """One line for a damaged file: the file, frames readable of how many, the first damage, what to do."""
        return (f"{self.path}: damaged recording: {self._n} of {self.frames_recorded} frames readable "
                f"({self.damage[0] if self.damage else 'no damage'}); --salvage (replay://FILE?salvage=1) uses "
                "the readable frames")

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

    def _read(self, names: Sequence[str], start: int, stop: int, part: str | None = None
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
                    self._damaged(row, f"{name} rows {row}–{nxt - 1} unreadable ({brief(exc)})", part)
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
        end = max(start, min(stop, self._truth_ok))
        cols, end = self._read(fields, start, end, part="truth")
        self._pad(cols, stop - start)
        kw = {k: cols[f"truth/{k}"] for k in names}
        if "frames" in kw:
            kw["frames"] = kw["frames"].astype(np.float64)
        return Truth(s=f["truth/s"][()], present=cols["truth/present"],
                     fixture=f["truth/fixture"][()] if "truth/fixture" in f else None, **kw), stop

    def _pad(self, cols: dict[str, np.ndarray], m: int) -> None:
        """Pad columns cut at damage to ``m`` rows: absent (``present`` False), NaN."""
        for name, v in cols.items():
            if len(v) < m:
                ds = self._file[name]
                fill = False if name.endswith("/present") else np.nan
                cols[name] = np.concatenate([v, np.full((m - len(v), *ds.shape[1:]), fill, dtype=ds.dtype)])

    @property
    def has_vendor(self) -> bool:
        """The recording holds the interrogator's own reconstruction (sensor blocks)."""
        return bool(self._vendor_mem) or self._vendor_sensors > 0

    def vendor(self, start: int = 0, stop: int | None = None) -> tuple:
        """The interrogator's own reconstruction of frames ``start:stop``, one
        :class:`~twin.frames.VendorArrays` per sensor (rows from 0 = frame ``start``; empty
        when the recording has none). Rows past damaged vendor chunks come back absent."""
        start, stop = self._span(start, stop)
        if self._mem is not None:
            return tuple(a[start:stop] for a in self._vendor_mem)
        if not self._vendor_sensors:
            return ()
        f = self._file
        names = [f"vendor/sensor{j}/{k}" for j in range(self._vendor_sensors) for k in VENDOR_FIELDS]
        end = max(start, min(stop, self._vendor_ok))
        cols, _ = self._read(names, start, end, part="vendor")
        self._pad(cols, stop - start)
        return tuple(VendorArrays(*(cols[f"vendor/sensor{j}/{k}"] for k in ("curvature", "angle", "positions")),
                                  present=cols[f"vendor/sensor{j}/present"],
                                  spacing=float(f[f"vendor/sensor{j}/spacing"][()]))
                     for j in range(self._vendor_sensors))

    def received(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Wall-clock receive times of frames ``start:stop``, s (NaN for vendor logs)."""
        start, stop = self._span(start, stop)
        if self._mem is not None:
            return np.full(stop - start, np.nan)
        return self._read(["frames/received"], start, stop)[0]["frames/received"]

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _text(v) -> str:
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


def _number(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def open_recording(path: str | Path, **kw) -> RecordingReader:
    """Open a twin HDF5 recording, a twin MCAP recording (:class:`twin.io.rosbag.McapRecording`, the same
    interface) or an ILLumiSense log file for reading (see :class:`RecordingReader`); the kind is told by the
    file's first bytes."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError:
        head = b""  # RecordingReader says what is wrong, in its words
    if head == _MCAP_SIGNATURE:
        from twin.io.rosbag import McapRecording

        return McapRecording(path)
    return RecordingReader(path, **kw)


def open_recorder(path: str | Path, **kw):
    """A recorder for ``path`` chosen by its extension: ``.mcap`` a rosbag2-compatible MCAP file
    (:class:`twin.io.rosbag.McapRecorder`), anything else twin HDF5 (:class:`Recorder`). Keywords: ``fiber``,
    ``calibration``, ``source_url``, ``rate``."""
    if Path(path).suffix.lower() == ".mcap":
        from twin.io.rosbag import McapRecorder

        return McapRecorder(path, **kw)
    return Recorder(path, **kw)


def _load_toml(text) -> dict:
    import tomllib

    if isinstance(text, bytes):
        text = text.decode("utf-8")
    return tomllib.loads(str(text))
