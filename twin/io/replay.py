"""What a recording holds: reconstruct every frame in batches and summarise (the library behind ``twin replay``).

:func:`summarize` reads a twin HDF5 recording or an ILLumiSense log (:mod:`twin.io.record`), reconstructs every
readable frame and returns a :class:`ReplaySummary`: frames, time span, lost samples and resets, complete /
partial / unusable frames, frames with missing peaks, peaks outside their window, invalid nodes — counted by
the live loop's own books (:meth:`twin.live.LiveLoop.process_arrays`), so `twin replay` and `twin live` count
alike —, reconstruction speed, the damage of a damaged file, when the recording holds the simulator's truth the
shape error against it (:func:`twin.metrics.shape_error` after a registration, on at most ``max_compare``
frames spread evenly), and when it holds the interrogator's own shape the distance to it.

:class:`ReplaySource` (``replay://FILE``) delivers the recorded frames one by one, with their truth and their
sensor blocks (:attr:`Frame.vendor <twin.frames.Frame.vendor>`) when recorded.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from twin.calibration import Calibration
from twin.fiber import FiberModel
from twin.frames import Frame
from twin.io.errors import RecordingDamaged
from twin.io.illumisense.vendor import VendorDistance, frame_vendor
from twin.io.record import open_recording
from twin.io.source import Source, SourceClosed, parse_url
from twin.live import LiveLoop
from twin.metrics import shape_error
from twin.reconstruct import Reconstructor

__all__ = ["ReplaySource", "ReplaySummary", "TruthErrors", "open_replay", "summarize"]


@dataclass(frozen=True)
class TruthErrors:
    """Shape error against the recorded truth, mm (over ``frames_compared`` complete frames)."""

    frames_compared: int
    register: str
    mean_error_mm: float
    max_error_mm: float
    rms_error_mm: float
    tip_error_mm_mean: float
    tip_error_mm_max: float


@dataclass(frozen=True)
class ReplaySummary:
    """The summary of one recording (JSON-ready through :meth:`as_dict`; None where unknown, never NaN).

    Attributes
    ----------
    file, kind, source_url, fiber : str
        The file, ``twin-hdf5`` or ``illumisense-log``, where its frames came from, the fibre model's name.
    complete : bool
        Closed cleanly by its writer and not damaged.
    damaged : bool
    damage : tuple of str
        What is damaged, each naming the place.
    frames : int
        Frames read and reconstructed (those before the first damage).
    frames_recorded : int
        Frames the file says it holds.
    time_span : float or None
        Last minus first finite timestamp, s.
    rate_hz : float or None
    lost_samples, sequence_gaps, sequence_resets : int
    frames_complete, frames_partial, frames_unusable, frames_missing_peaks, invalid_nodes : int
        As :class:`twin.live.LiveStatus` counts them.
    peaks_outside_window : int
        Peaks outside the reconstructor's physical window (or infinite), treated as missing.
    reconstruct_frames_per_s : float or None
    skipped_lines : int
        Log lines that did not parse.
    truth : TruthErrors or None
    vendor : dict
        When the recording (a twin recording or a log) carries the interrogator's own shape (sensor 0):
        ``vendor_frames_compared``, ``vendor_distance_max_mm``, ``vendor_distance_mean_mm`` (ours against it
        after a rigid registration, :class:`twin.io.illumisense.vendor.VendorDistance`, on the same frames as
        the truth); empty otherwise.
    notes : tuple of str
    """

    file: str
    kind: str
    complete: bool
    damaged: bool
    source_url: str
    fiber: str
    frames: int
    frames_recorded: int
    time_span: float | None
    rate_hz: float | None
    lost_samples: int
    sequence_gaps: int
    sequence_resets: int
    frames_complete: int
    frames_partial: int
    frames_unusable: int
    frames_missing_peaks: int
    invalid_nodes: int
    peaks_outside_window: int
    reconstruct_frames_per_s: float | None
    skipped_lines: int
    damage: tuple[str, ...] = ()
    truth: TruthErrors | None = None
    vendor: dict = field(default_factory=dict)
    notes: tuple[str, ...] = field(default_factory=tuple)

    def as_dict(self) -> dict:
        out = asdict(self)
        out["damage"], out["notes"] = list(self.damage), list(self.notes)
        out.update(out.pop("vendor"))
        if self.truth is None:
            del out["truth"]
        return out


def summarize(path: str | Path, *, fiber: FiberModel | None = None, calibration: Calibration | None = None,
              method: str = "material", register: str = "kabsch", max_compare: int = 1000,
              channels_as: str = "cores", n_cores: int | None = None, batch: int = 2048,
              salvage: bool = False) -> ReplaySummary:
    """Reconstruct a recording and summarise it.

    Parameters
    ----------
    path : str or Path
        A twin HDF5 recording or an ILLumiSense log.
    fiber, calibration : optional
        Default: the ones stored in the recording (else the reference fibre, said in the notes).
    method, register, max_compare :
        Reconstruction method; registration before comparing with the truth; most frames compared.
    channels_as, n_cores :
        Log files: channel layout (:mod:`twin.io.record`).
    batch : int
        Frames reconstructed per call.
    salvage : bool
        A damaged recording is summarised from its readable frames instead of raising.

    Raises
    ------
    RecordingDamaged
        The file is damaged and ``salvage`` is False (one line: readable frames of how many, the damage).
    ValueError
        Unreadable file, or frames that do not fit the fibre model.
    """
    path = Path(path)
    with open_recording(path, channels_as=channels_as, n_cores=n_cores) as reader:
        if reader.damaged and not salvage:
            raise RecordingDamaged(reader.damage_line())
        notes = []
        if fiber is None:
            fiber = reader.fiber
        if fiber is None:
            fiber = FiberModel.paper()
            notes.append("no fibre model in the recording: using the reference fibre (FiberModel.paper())")
        if calibration is None:
            calibration = reader.calibration
        if len(reader) and reader.shape != (fiber.n_gratings, fiber.n_cores):
            g, c = reader.shape
            raise ValueError(f"{path}: frames have {g} gratings × {c} cores but the fibre model has "
                             f"{fiber.n_gratings} × {fiber.n_cores}; give the sensor's model with --fiber")
        rec = Reconstructor(fiber, calibration, method=method)
        books = LiveLoop(None, rec)  # never run: its books only
        stride = max(1, math.ceil(len(reader) / max(1, max_compare)))
        g = fiber.n_gratings
        n = 0
        t_first = t_last = math.nan
        errors: dict[str, list[np.ndarray]] = {"mean": [], "max": [], "rms": [], "tip": []}
        truth_note = None
        vendor = VendorDistance(rate=None)
        t_rec = 0.0
        for start, frames in reader.chunks(batch, truth=False):
            m = len(frames)
            n += m
            t0 = time.perf_counter()
            shapes, _ = books.process_arrays(frames.wavelengths, frames.sequence)
            t_rec += time.perf_counter() - t0
            ts = frames.timestamp[np.isfinite(frames.timestamp)]
            if ts.size:
                t_first = ts[0] if math.isnan(t_first) else t_first
                t_last = ts[-1]
            if shapes is None:
                continue
            n_valid = np.count_nonzero(shapes.valid, axis=-1)
            compare = (np.arange(start, start + m) % stride == 0) & (n_valid == g)
            if reader.has_vendor:
                vendor.add_chunk(reader.vendor(start, start + m)[0], shapes, compare)
            if reader.has_truth and truth_note is None:
                truth = reader.truth(start, start + m, fields=("positions",))
                sel = np.flatnonzero(compare[: len(truth)] & truth.all_present)
                if sel.size:
                    try:
                        e = shape_error(shapes.positions[sel], truth.positions[sel], s=rec.s, truth_s=truth.s,
                                        register=register)
                    except ValueError as exc:
                        truth_note = f"truth comparison skipped: {exc}"
                    else:
                        for k in errors:
                            errors[k].append(np.atleast_1d(getattr(e, k)))
        if reader.damaged and not salvage:  # found while reading (a chunk failing its checksum)
            raise RecordingDamaged(reader.damage_line())
        truth_errors = None
        if reader.has_truth:
            if errors["mean"]:
                e = {k: np.concatenate(v) for k, v in errors.items()}
                truth_errors = TruthErrors(
                    frames_compared=int(e["mean"].size),
                    register=register,
                    mean_error_mm=round(float(e["mean"].mean()) * 1e3, 4),
                    max_error_mm=round(float(e["max"].max()) * 1e3, 4),
                    rms_error_mm=round(float(np.sqrt(np.mean(e["rms"] ** 2))) * 1e3, 4),
                    tip_error_mm_mean=round(float(e["tip"].mean()) * 1e3, 4),
                    tip_error_mm_max=round(float(e["tip"].max()) * 1e3, 4),
                )
            else:
                notes.append(truth_note or "truth present but no complete frame to compare")
        if reader.errors:
            notes.append(f"{len(reader.errors)} line(s) skipped, first: {reader.errors[0]}")
        notes.extend(getattr(reader, "notes", ()))  # what a reader had to assume (an MCAP recording's)
        if books.c["reconstruct_errors"]:
            notes.append(f"reconstruction failed on {books.c['reconstruct_errors']} batch(es): their frames are "
                         "counted unusable")
        if not reader.complete and not reader.damaged:
            notes.append("the recording was not closed cleanly (killed writer, or still being written)")
        span = None if math.isnan(t_first) else float(t_last - t_first)
        return ReplaySummary(
            file=str(path),
            kind=reader.kind,
            complete=reader.complete,
            damaged=reader.damaged,
            source_url=reader.source_url,
            fiber=fiber.name,
            frames=n,
            frames_recorded=max(n, reader.frames_recorded),
            time_span=None if span is None or not math.isfinite(span) else round(span, 6),
            rate_hz=round((n - 1) / span, 3) if span is not None and math.isfinite(span) and span > 0 and n >= 2
            else None,
            **{k: books.c[k] for k in ("lost_samples", "sequence_gaps", "sequence_resets", "frames_complete",
                                       "frames_partial", "frames_unusable", "frames_missing_peaks", "invalid_nodes",
                                       "peaks_outside_window")},
            reconstruct_frames_per_s=round(n / t_rec, 1) if t_rec > 0 else None,
            skipped_lines=len(reader.errors),
            damage=tuple(reader.damage),
            truth=truth_errors,
            vendor=vendor.as_dict(),
            notes=tuple(notes),
        )


# -------------------------------------------------------------------------------------------------- replay


class ReplaySource(Source):
    """``replay://FILE?speed=…``: a recording's frames, paced as recorded or as fast as read, with their truth
    and their sensor blocks (:attr:`Frame.vendor <twin.frames.Frame.vendor>`) when recorded.

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
            raise RecordingDamaged(self.reader.damage_line())
        self.fiber = self.reader.fiber
        self.calibration = self.reader.calibration
        self.rate = self.reader.rate
        self.speed = speed
        self.follow = follow
        self.chunk = chunk
        self._batch: Frame | None = None
        self._vendor: tuple = ()  # the batch's sensor blocks (VendorArrays per sensor)
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
            self._vendor = self.reader.vendor(self._next, self._next + len(batch))
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
                raise RecordingDamaged(self.reader.damage_line())
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
        frame = self._batch[self._i - 1]
        if self._vendor:
            blocks = frame_vendor(self._vendor, self._i - 1)
            if blocks is not None:
                frame = dataclasses.replace(frame, vendor=blocks)
        return frame

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
