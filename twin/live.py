"""The streaming loop: source → :class:`~twin.reconstruct.Reconstructor` → sinks.

One iteration takes every frame the source has ready (up to ``max_batch``), reconstructs them as one batch
(batch-first: a burst after a stall costs little more than one frame) and hands the batch to each sink. Around
that it keeps the books a live instrument needs:

- **lost samples**: forward jumps of the frames' sequence numbers (a sequence that goes backwards is counted
  as a reset — a restarted acquisition — not as loss; one absurd number amid a continuing run is one corrupt
  record: :mod:`twin.io.sequence`);
- **partly missing peaks**: a frame whose peaks are partly missing is reconstructed from the gratings whose
  remaining cores still determine the curvature (the reconstructor interpolates over the others) and flagged
  :attr:`FrameFlag.MISSING_PEAKS`; a peak outside the reconstructor's physical window around its reference
  (:meth:`~twin.reconstruct.Reconstructor.peaks_outside`: a corrupted value such as 1e300 nm, or ±inf) counts
  as missing too, and is counted in ``peaks_outside_window``. Then :attr:`FrameFlag.PARTIAL` when some
  gratings had to be dropped and :attr:`FrameFlag.UNUSABLE` when none was left (its shape is all NaN and is
  never shown as current);
- **rate**: ``rate_hz`` is the source's sampling rate measured on its own timestamps (:mod:`twin.io.rate`), so
  it reads 100 Hz for a 100 Hz source whatever the batching; when frames arrive slower than the source's
  nominal rate (or than its timestamps advance), the loop says once on stderr that the source runs behind
  real time, and counts it (``behind_events``; ``behind`` while it lasts);
- **stale data**: no usable frame for ``stale_after`` s (0.5 by default) puts the loop in state ``stale``;
  sinks keep receiving status updates (``heartbeat``) so a display can mark its last shape as old;
- **dropped connections**: drivers reconnect by themselves (:mod:`twin.io.drivers`); a source that raises
  instead (an I/O error out of ``read``) is closed and reopened through the factory given to the loop, with
  exponential backoff (0.1 s doubling to 5 s) — except :class:`~twin.io.errors.SourceFailed` (a damaged
  recording), which no reopening cures: it ends the loop (reason ``source failed``);
- **counters** from the source (framing errors, reconnects, …) are merged into the status;
- **clean stop**: Ctrl-C (SIGINT) or SIGTERM ends the loop at the next iteration; sinks are closed (the
  recorder flushes) and the source is closed, whatever happened. A second Ctrl-C interrupts at once.

Nothing a source, the reconstructor or a sink does ends the loop with an exception, except a configuration
error that makes every frame useless (frames whose shape does not match the fibre model from the start). A
sink that raises is closed and dropped, and the error is reported in the summary.

Frames move in one form: the source's ``read_batch`` (:class:`twin.io.source.Source`) gives one 1-D batch
:class:`~twin.frames.Frame` (one frame is a batch of one; the interrogator's own shape rides on it as
:attr:`Frame.vendor <twin.frames.Frame.vendor>`), the loop reconstructs it in one call — the strain computed once,
shared by the window check and the reconstruction — and hands it to every sink.

Sinks are tiny: any callable ``sink(frames, shapes, status)`` with an optional ``close()``. ``frames`` is the
batch :class:`~twin.frames.Frame` (``len``, indexing, arrays ``frames.sequence``, ``frames.timestamp``, …),
``shapes`` the batched :class:`~twin.frames.Shape` (``shapes[i]`` belongs to ``frames[i]``; None when the batch
could not be reconstructed), ``status`` a :class:`LiveStatus`. Between batches sinks get heartbeats with an empty
batch (``len(frames) == 0``) and ``shapes`` None, at least every ``heartbeat`` s and on every state change.

The counts are defined once, in :class:`Counts`, and kept in one small object, :class:`Counters`, which makes the
``Counts`` every :class:`LiveStatus` is; ``twin live``, ``twin replay`` (the loop over a file source at full
speed), the demo and the viewer and OpenIGTLink sinks all read the same books (docs/figures.md defines every
figure).

Why one module of this size: the loop, its status and counters and its summary are one state machine; split,
the counters' one meaning would be spread over files.
"""

from __future__ import annotations

import copy
import dataclasses
import enum
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol, TextIO

import numpy as np
from numba import njit

from twin import _jit_cache  # noqa: F401  (before the first cached kernel; see its docstring)
from twin.frames import Frame, Shape
from twin.io.errors import SourceFailed
from twin.io.rate import RateMeter
from twin.io.sequence import SequenceCounter, lost_before
from twin.io.source import Source, SourceClosed
from twin.io.transport import Backoff
from twin.reconstruct import Reconstructor

__all__ = [
    "Counters",
    "Counts",
    "FrameFlag",
    "LatestUsable",
    "LiveLoop",
    "LiveStatus",
    "LiveSummary",
    "PrinterSink",
    "Sink",
    "latest_usable",
    "next_due",
]


class FrameFlag(enum.IntFlag):
    """Per-frame flags of a batch (:attr:`LiveStatus.flags`)."""

    OK = 0
    MISSING_PEAKS = 1  #: some peaks missing; reconstructed from the remaining cores
    PARTIAL = 2  #: some gratings could not be solved and were interpolated over
    UNUSABLE = 4  #: no grating could be solved: no shape
    SEQUENCE_GAP = 8  #: samples were lost just before this frame


# the bits as plain ints: compiled code takes them as constants
_MISSING, _PARTIAL, _UNUSABLE, _GAP = (int(f) for f in (FrameFlag.MISSING_PEAKS, FrameFlag.PARTIAL,
                                                        FrameFlag.UNUSABLE, FrameFlag.SEQUENCE_GAP))


@njit(cache=True, nogil=True)
def _batch_books(strain, outside, valid, sequence, books):
    """The books of one batch in one compiled pass (the numpy form cost ≈ 15 µs of array calls a batch, half a
    microsecond a frame at ~28 frames a batch).

    Parameters
    ----------
    strain : ndarray (n, n_gratings, n_cores)
        NaN where a peak is missing or outside the window.
    outside : ndarray of bool (n, n_gratings, n_cores)
        Peaks present but outside the window.
    valid : ndarray of bool (n, n_gratings)
        Gratings solved.
    sequence : ndarray of int64 (n,)
    books : ndarray of int64
        The sequence counter's state, updated in place (:func:`twin.io.sequence.lost_before`).

    Returns
    -------
    flags : ndarray of uint8 (n,)
        :class:`FrameFlag` bits.
    n_outside, n_missing, n_partial, n_unusable, n_invalid, last_usable : int
        Peaks outside the window; frames with a peak missing, some / no grating solved; gratings not solved;
        index of the last frame with a grating solved (−1: none).
    gaps, resets, corrupt, lost_hi, lost_lo : int
        For :meth:`twin.io.sequence.SequenceCounter.book`.
    """
    n, g, k = strain.shape
    flags = np.zeros(n, np.uint8)
    lost, gaps, resets, corrupt, lost_hi, lost_lo = lost_before(sequence, books)
    n_outside = n_missing = n_partial = n_unusable = n_invalid = 0
    last_usable = -1
    for i in range(n):
        f = 0
        for j in range(g):
            for m in range(k):
                n_outside += outside[i, j, m]
                if f == 0 and np.isnan(strain[i, j, m]):
                    f = _MISSING
        if f:
            n_missing += 1
        solved = 0
        for j in range(g):
            solved += valid[i, j]
        n_invalid += g - solved
        if solved == 0:
            f |= _UNUSABLE
            n_unusable += 1
        else:
            last_usable = i
            if solved < g:
                f |= _PARTIAL
                n_partial += 1
        if lost[i] > 0:
            f |= _GAP
        flags[i] = f
    return (flags, n_outside, n_missing, n_partial, n_unusable, n_invalid, last_usable,
            gaps, resets, corrupt, lost_hi, lost_lo)


class Sink(Protocol):
    """What the loop feeds: ``sink(frames, shapes, status)`` with a batch Frame (empty for a heartbeat);
    ``close()`` when the loop ends (optional)."""

    def __call__(self, frames: Frame, shapes: Shape | None, status: LiveStatus) -> None: ...


@dataclass(frozen=True)
class Counts:
    """The loop's counts since it started, each defined once here (docs/figures.md gives the definitions the
    reports print): :class:`Counters` keeps them, a :class:`LiveStatus` carries them (it is a ``Counts``).

    Attributes
    ----------
    frames : int
        Frames received and matching the fibre model.
    frames_complete, frames_partial, frames_unusable, frames_missing_peaks : int
        Every grating solved / some dropped / none solved / some peak missing (absent, or outside the
        physical window).
    peaks_outside_window : int
        Peaks reported but outside the reconstructor's physical window (or infinite), treated as missing.
    frames_rejected : int
        Frames whose (n_gratings, n_cores) does not match the fibre model (not reconstructed, not recorded).
    lost_samples, sequence_gaps, sequence_resets, sequence_corrupt : int
        From the frames' sequence numbers (:mod:`twin.io.sequence`).
    invalid_nodes : int
        Gratings that could not be solved, summed over frames.
    source_errors, reconstruct_errors : int
        Exceptions out of ``source.read`` and out of the reconstructor (each batch counted once).
    stale_events : int
        Transitions into ``stale``.
    """

    frames: int = 0
    frames_complete: int = 0
    frames_partial: int = 0
    frames_unusable: int = 0
    frames_missing_peaks: int = 0
    peaks_outside_window: int = 0
    frames_rejected: int = 0
    lost_samples: int = 0
    sequence_gaps: int = 0
    sequence_resets: int = 0
    sequence_corrupt: int = 0
    invalid_nodes: int = 0
    source_errors: int = 0
    reconstruct_errors: int = 0
    stale_events: int = 0


_COUNTS = tuple(f.name for f in dataclasses.fields(Counts))


class Counters:
    """The loop's book since it started, which the loop adds to: every count of :class:`Counts` (an attribute
    of that name, from its default), and its own ``reopens`` (reopenings of a source that raised, reported
    inside ``reconnects``), ``process_s`` (wall time spent in :meth:`LiveLoop.process`: window check,
    reconstruction, books, s), ``time_first`` / ``time_last`` (first and last finite source timestamps, s;
    NaN before)."""

    def __init__(self) -> None:
        self.__dict__.update({f.name: f.default for f in dataclasses.fields(Counts)})
        self.reopens = 0
        self.process_s = 0.0
        self.time_first = self.time_last = float("nan")

    def counts(self) -> Counts:
        """The counts as they are now (what a :class:`LiveStatus` carries)."""
        return Counts(**{k: self.__dict__[k] for k in _COUNTS})

    def copy(self) -> Counters:
        return copy.copy(self)

    @property
    def time_span(self) -> float | None:
        """Last minus first finite source timestamp, s (None before two)."""
        span = self.time_last - self.time_first
        return float(span) if np.isfinite(span) else None


@dataclass(frozen=True, eq=False)
class LiveStatus(Counts):
    """A snapshot of the loop's state and counters (all counts since the loop started).

    Attributes
    ----------
    state : {"starting", "live", "stale", "ended"}
        ``live``: a usable frame arrived within ``stale_after`` s; ``stale``: none did; ``starting``: within
        the first ``stale_after`` s, before any usable frame.
    connection : str or None
        The source's own state when it reports one (``connected`` / ``disconnected``).
    elapsed : float
        s since the loop started.
    frames, frames_complete, …, stale_events : int
        The loop's counts (:class:`Counts`, which a status is).
    framing_errors, reconnects, disconnects : int
        From the source's counters (plus the loop's own reopenings of a source that raised).
    last_valid_age : float
        s since the last usable frame (inf before the first).
    rate_hz : float
        The source's sampling rate over the last 2 s of its timestamps (frames received per second when it
        has none), Hz.
    arrival_hz : float
        Frames received per wall-clock second over the last 2 s, Hz.
    behind : bool
        Frames arrive slower than the source's nominal rate (or than its timestamps advance): it runs behind
        real time.
    behind_events : int
        Times the source fell behind real time.
    tip : ndarray (3,) or None
        Tip of the latest usable shape, m.
    flags : ndarray of uint8 (n,)
        :class:`FrameFlag` bits of the frames this status accompanies (empty for heartbeats).
    source : dict
        The source's ``stats()`` as last polled.
    """

    state: str = "starting"
    connection: str | None = None
    elapsed: float = 0.0
    framing_errors: int = 0
    reconnects: int = 0
    disconnects: int = 0
    last_valid_age: float = float("inf")
    rate_hz: float = 0.0
    arrival_hz: float = 0.0
    behind: bool = False
    behind_events: int = 0
    tip: np.ndarray | None = None
    flags: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    source: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        """JSON-ready counters (``tip`` in m; ``flags`` left out)."""
        out = {k: getattr(self, k) for k in self.__dataclass_fields__ if k not in ("flags", "tip", "source")}
        out["tip_m"] = None if self.tip is None else [float(x) for x in self.tip]
        out["last_valid_age"] = None if not np.isfinite(self.last_valid_age) else round(self.last_valid_age, 6)
        out["rate_hz"] = round(self.rate_hz, 3)
        out["arrival_hz"] = round(self.arrival_hz, 3)
        out["source"] = {k: v for k, v in self.source.items() if isinstance(v, int | float | str | bool | None)}
        return out


@dataclass(frozen=True, eq=False)
class LiveSummary:
    """How a run went.

    Attributes
    ----------
    status : LiveStatus
        The final counters (state ``ended``).
    duration : float
        s.
    reason : str
        Why the loop ended: ``duration``, ``frames``, ``source ended``, ``source failed``, ``interrupted``,
        ``stopped``.
    sink_errors : tuple of str
        Sinks that raised (and were dropped), with the error.
    counters : Counters or None
        The loop's books at the end (a copy).
    """

    status: LiveStatus
    duration: float
    reason: str
    sink_errors: tuple[str, ...] = ()
    counters: Counters | None = None

    @property
    def frames_per_s(self) -> float:
        """Frames received per wall-clock second of the run, Hz (docs/figures.md: the run's arrival rate)."""
        return self.status.frames / self.duration if self.duration > 0 else 0.0

    @property
    def processing_frames_per_s(self) -> float | None:
        """Frames reconstructed per second spent in the loop's processing (window check, reconstruction and
        books; first-call compilation included), Hz: the throughput, not the arrival rate, nor `twin bench`'s
        ``reconstruct_frames_per_s`` (the reconstruction alone, compiled, best window). None before any."""
        c = self.counters
        if c is None or c.process_s <= 0 or not self.status.frames:
            return None
        return self.status.frames / c.process_s

    def as_dict(self) -> dict:
        rfs = self.processing_frames_per_s
        span = None if self.counters is None else self.counters.time_span
        return {
            "reason": self.reason,
            "duration": round(self.duration, 6),
            "frames_per_s": round(self.frames_per_s, 3),
            "processing_frames_per_s": None if rfs is None else round(rfs, 1),
            "time_span": None if span is None else round(span, 6),
            **self.status.as_dict(),
            "sink_errors": list(self.sink_errors),
        }


# what a source may raise besides SourceClosed; anything else (a bug in a source) is reported the same way,
# because the live loop must outlive its source
_SOURCE_ERRORS = (Exception,)


class LiveLoop:
    """Source → reconstructor → sinks, with the bookkeeping of the module docstring.

    Parameters
    ----------
    source : Source or callable returning a Source
        A factory lets the loop reopen a source that raised (it is called once at :meth:`run`).
    reconstructor : Reconstructor
        Its fibre model fixes the (n_gratings, n_cores) frames must have.
    sinks : sequence of Sink
    stale_after : float
        s without a usable frame before the state becomes ``stale``.
    max_batch : int
        Most frames reconstructed in one call.
    poll : float
        Longest wait for frames in one iteration, s (bounds the latency of stopping and of heartbeats).
    heartbeat : float
        Sinks get a status at least this often, s.
    rate_window : float
        Window of the rate readout and of the behind-real-time check, s (:class:`~twin.io.rate.RateMeter`).
    realtime : bool
        The source is a stream in real time (the default): say when it falls behind. False for a file read at
        full speed (``twin replay``), where behind-real-time means nothing.
    name : str
        What the loop's messages start with (the command).
    quiet : bool
        Do not say on stderr what happens as it happens (source failures, a dropped sink, falling behind): for a
        caller that reports everything from the summary (``twin replay``).
    """

    def __init__(self, source: Source | Callable[[], Source], reconstructor: Reconstructor,
                 sinks: Sequence[Sink] = (), *, stale_after: float = 0.5, max_batch: int = 256,
                 poll: float = 0.05, heartbeat: float = 0.1, rate_window: float = 2.0, realtime: bool = True,
                 name: str = "twin live", quiet: bool = False):
        self._factory = source if callable(source) and not isinstance(source, Source) else None
        self.source: Source | None = None if self._factory else source
        self.rec = reconstructor
        self.sinks = list(sinks)
        self.stale_after, self.max_batch = float(stale_after), int(max_batch)
        self.poll, self.heartbeat = float(poll), float(heartbeat)
        self.rate_window = float(rate_window)
        self.realtime = bool(realtime)
        self.name = name
        self.quiet = bool(quiet)
        self._shape = (reconstructor.fiber.n_gratings, reconstructor.fiber.n_cores)
        self._empty = Frame(np.empty((0, *self._shape)))  # what heartbeats carry
        self._stop = threading.Event()
        self._stop_reason = "stopped"
        self.sink_errors: list[str] = []
        self._reset_counters()

    def _reset_counters(self) -> None:
        self.c = Counters()
        self._sequence = SequenceCounter()
        self._matched_any = False
        self._tip: np.ndarray | None = None
        self._t0 = time.monotonic()
        self._last_valid: float | None = None
        self._state = "starting"
        self._source_stats: dict = {}
        self._stats_at = -1.0
        self._meter = RateMeter(window=self.rate_window)

    # ---------------------------------------------------------------- the hot path
    def process(self, frames: Frame) -> tuple[Frame, Shape | None, np.ndarray]:
        """Check, reconstruct and count one batch.

        Parameters
        ----------
        frames : Frame
            A 1-D batch (what a source's ``read_batch`` gives; no Python object per frame on the hot path).

        Returns
        -------
        frames : Frame
            The batch when it matches the fibre model, else an empty batch (its frames counted in
            ``frames_rejected``).
        shapes : Shape or None
            Batched reconstruction (None when nothing matched or the reconstructor raised).
        flags : ndarray of uint8 (n,)
            :class:`FrameFlag` bits per frame.

        Raises
        ------
        ValueError
            When no frame has matched the fibre model yet and this batch does not either: a configuration
            error (wrong ``--fiber``), not a transient.
        """
        w = frames.wavelengths
        shape = w.shape  # (n, n_gratings, n_cores): read once, not through the Frame's properties
        if len(shape) != 3:
            raise ValueError(f"LiveLoop.process: expected a 1-D batch Frame, got batch shape {frames.batch_shape}")
        n = shape[0]
        if shape[1:] != self._shape:
            self._reject(n, shape[1:])
            return self._empty, None, np.zeros(0, np.uint8)
        if n == 0:
            return frames, None, np.zeros(0, np.uint8)
        t0 = time.perf_counter()
        self._matched_any = True
        c = self.c
        rec = self.rec
        e, outside = rec.strain(w)  # once: the window check and the reconstruction
        try:
            shapes = rec.from_strain(e)
            valid = shapes.valid
        except Exception as exc:  # the frames still reach the sinks (the recorder keeps them)
            if not c.reconstruct_errors:
                self._say(f"reconstruction failed: {exc}")
            c.reconstruct_errors += 1
            shapes = None
            valid = np.zeros((n, self._shape[0]), bool)  # no grating solved: every frame unusable
        counter = self._sequence
        (flags, n_outside, n_missing, n_partial, n_unusable, n_invalid, last_usable,
         *books) = _batch_books(e, outside, valid, frames.sequence, counter.state)
        counter.book(*books)
        c.sequence_gaps = counter.sequence_gaps
        c.lost_samples = counter.lost_samples
        c.sequence_resets = counter.sequence_resets
        c.sequence_corrupt = counter.sequence_corrupt
        c.peaks_outside_window += n_outside
        c.frames += n
        c.frames_missing_peaks += n_missing
        c.frames_partial += n_partial
        c.frames_unusable += n_unusable
        c.frames_complete += n - n_partial - n_unusable
        c.invalid_nodes += n_invalid
        self._count_span(frames.timestamp)
        if last_usable >= 0:
            self._last_valid = time.monotonic()
            self._tip = shapes.positions[last_usable, -1].copy()
        c.process_s += time.perf_counter() - t0
        return frames, shapes, flags

    def _count_span(self, timestamps: np.ndarray) -> None:
        """First and last finite source timestamps (the ends of a batch are enough when they are finite)."""
        first, last = float(timestamps[0]), float(timestamps[-1])
        if not (math.isfinite(first) and math.isfinite(last)):
            ts = timestamps[np.isfinite(timestamps)]
            if not ts.size:
                return
            first, last = float(ts[0]), float(ts[-1])
        c = self.c
        if math.isnan(c.time_first):
            c.time_first = first
        c.time_last = last

    def _reject(self, n: int, bad: tuple) -> None:
        """Count n frames of another (n_gratings, n_cores) than the fibre model's; a configuration error when
        nothing has ever matched."""
        self.c.frames_rejected += n
        if not self._matched_any:
            shape = self._shape
            url = getattr(self.source, "url", "")  # the place: which source sent them
            raise ValueError(
                f"{url + ': ' if url else ''}frames have {bad[0]} gratings × {bad[1]} cores but the fibre model has "
                f"{shape[0]} × {shape[1]}; give the sensor's fibre model (--fiber FILE)"
            )

    # ---------------------------------------------------------------- status
    def status(self, flags: np.ndarray | None = None) -> LiveStatus:
        now = time.monotonic()
        if self.source is not None and now - self._stats_at > 0.1:
            try:
                self._source_stats = dict(self.source.stats())
            except Exception:  # a faulty stats() must not end the loop
                self._source_stats = {}
            self._stats_at = now
        s = self._source_stats
        age = float("inf") if self._last_valid is None else now - self._last_valid
        meter = self._meter
        return LiveStatus(
            state=self._state,
            connection=s.get("state") if isinstance(s.get("state"), str) else None,
            elapsed=now - self._t0,
            **vars(self.c.counts()),
            framing_errors=int(s.get("framing_errors", 0)),
            reconnects=int(s.get("reconnects", 0)) + self.c.reopens,
            disconnects=int(s.get("disconnects", 0)),
            last_valid_age=age,
            rate_hz=meter.rate,
            arrival_hz=meter.arrival_rate,
            behind=meter.behind,
            behind_events=meter.behind_events,
            tip=self._tip,
            flags=np.zeros(0, np.uint8) if flags is None else flags,
            source=s,
        )

    def _update_state(self) -> bool:
        """Recompute the state; True when it changed."""
        now = time.monotonic()
        if self._last_valid is not None and now - self._last_valid <= self.stale_after:
            new = "live"
        elif self._last_valid is None and now - self._t0 <= self.stale_after:
            new = "starting"
        else:
            new = "stale"
        changed = new != self._state
        if changed and new == "stale":
            self.c.stale_events += 1
        self._state = new
        return changed

    # ---------------------------------------------------------------- running
    def stop(self, reason: str = "stopped") -> None:
        """Ask the loop to end at its next iteration (thread-safe)."""
        self._stop_reason = reason
        self._stop.set()

    def _emit(self, frames, shapes, status) -> None:
        for sink in list(self.sinks):
            try:
                sink(frames, shapes, status)
            except Exception as exc:  # a faulty sink must not end the loop
                self.sink_errors.append(f"{type(sink).__name__}: {exc}")
                self._say(f"sink {type(sink).__name__} failed and was removed: {exc}")
                self.sinks.remove(sink)
                _close(sink)

    def _open(self) -> None:
        if self._factory is not None:
            self.source = self._factory()

    def run(self, duration: float | None = None, max_frames: int | None = None,
            handle_signals: bool = True) -> LiveSummary:
        """Run until ``duration`` s, ``max_frames`` frames, the source's end, :meth:`stop` or Ctrl-C.

        The first opening of a source factory may raise (a wrong URL is the caller's error); after that
        nothing the source does raises out of here.
        """
        self._reset_counters()
        self._stop.clear()
        self._open()
        self._meter.nominal = _nominal_rate(self.source)
        restore = self._install_signals() if handle_signals else None
        backoff = Backoff()
        reopen_at = None
        last_emit = 0.0
        reason = "stopped"
        try:
            while True:
                if self._stop.is_set():
                    reason = self._stop_reason
                    break
                now = time.monotonic()
                if duration is not None and now - self._t0 >= duration:
                    reason = "duration"
                    break
                if max_frames is not None and self.c.frames >= max_frames:
                    reason = "frames"
                    break
                wait = self.poll
                if duration is not None:
                    wait = max(0.0, min(wait, self._t0 + duration - now))
                frames: Frame | None = None
                if self.source is None:
                    if reopen_at is not None and now >= reopen_at:
                        try:
                            self._open()
                            self.c.reopens += 1
                            reopen_at = None
                        except _SOURCE_ERRORS:
                            reopen_at = time.monotonic() + backoff.failed()
                    if self.source is None:
                        time.sleep(wait)
                else:
                    limit = self.max_batch if max_frames is None else max(1, min(
                        self.max_batch, max_frames - self.c.frames))
                    try:
                        frames = self.source.read_batch(limit, wait)
                    except SourceClosed:
                        reason = "source ended"
                        break
                    except SourceFailed as exc:  # reopening cannot cure it (a damaged recording)
                        self.c.source_errors += 1
                        self._source_stats = {**self._source_stats, "last_error": str(exc)}
                        self._say(f"source failed: {exc}")
                        reason = "source failed"
                        break
                    except _SOURCE_ERRORS as exc:
                        self.c.source_errors += 1
                        self._source_stats = {**self._source_stats, "last_error": str(exc)}
                        if self._factory is None:
                            self._say(f"source failed: {exc}")
                            reason = "source failed"
                            break
                        _close(self.source)
                        self.source = None
                        reopen_at = time.monotonic() + backoff.failed()
                if frames:
                    good, shapes, flags = self.process(frames)
                    t = time.monotonic()
                    if len(good) and self._meter.add(good.timestamp, t) and self.realtime:
                        self._say_behind()
                    if self.c.frames and backoff.failures:
                        backoff.reset()
                    changed = self._update_state()
                    if (len(good) or changed) and self.sinks:  # a status only for someone to read it
                        self._emit(good, shapes, self.status(flags))
                        last_emit = t
                else:
                    changed = self._update_state()
                    t = time.monotonic()
                    if changed or t - last_emit >= self.heartbeat:
                        self._emit(self._empty, None, self.status())
                        last_emit = t
        except KeyboardInterrupt:
            reason = "interrupted"
        finally:
            if restore is not None:
                restore()
            self._state = "ended"
            final = self.status()
            for sink in self.sinks:
                try:
                    sink(self._empty, None, final)
                except Exception as exc:
                    self.sink_errors.append(f"{type(sink).__name__}: {exc}")
                err = _close(sink)
                if err:
                    self.sink_errors.append(f"{type(sink).__name__}.close: {err}")
            if self.source is not None:
                try:
                    self._source_stats = dict(self.source.stats())
                except Exception:
                    pass
                _close(self.source)
            final = self.status()
        return LiveSummary(final, time.monotonic() - self._t0, reason, tuple(self.sink_errors),
                           self.c.copy())

    def _say_behind(self) -> None:
        m = self._meter
        if m.behind_events != 1:
            return  # said once; later episodes are counted
        expected = m.expected_rate or 0.0
        why = "its nominal rate" if m.nominal is not None else "its timestamps advance"
        self._say(f"frames arrive at {m.arrival_rate:.0f} Hz, slower than {why} ({expected:.0f} Hz): the source runs "
                  "behind real time (said once; counted in behind_events)")

    def _say(self, text: str) -> None:
        if not self.quiet:
            print(f"{self.name}: {text}", file=sys.stderr, flush=True)

    def _install_signals(self) -> Callable[[], None] | None:
        if threading.current_thread() is not threading.main_thread():
            return None
        previous = {}

        def handler(signum, _frame):
            self.stop("interrupted" if signum == signal.SIGINT else "terminated")
            # a second Ctrl-C interrupts at once
            signal.signal(signal.SIGINT, signal.default_int_handler)

        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                previous[sig] = signal.signal(sig, handler)
            except (ValueError, OSError):  # pragma: no cover - not the main interpreter
                pass

        def restore() -> None:
            for sig, h in previous.items():
                signal.signal(sig, h)

        return restore


def _nominal_rate(source) -> float | None:
    rate = source.rate
    try:
        rate = float(rate) if rate is not None else None
    except (TypeError, ValueError):
        return None
    return rate if rate is not None and np.isfinite(rate) and rate > 0 else None


def _close(obj) -> str | None:
    close = getattr(obj, "close", None)
    if close is None:
        return None
    try:
        close()
    except Exception as exc:  # report, never raise out of cleanup
        return str(exc)
    return None


# ------------------------------------------------------------------------------------------------- sinks


# ------------------------------------------------------------------------------------------------ display sinks' rate
def latest_usable(shapes: Shape, flags: np.ndarray, n: int) -> int | None:
    """Index of the last frame of a batch whose shape can be drawn (not flagged unusable, finite points)."""
    flags = np.asarray(flags)
    finite = np.all(np.isfinite(shapes.positions.reshape(len(shapes.positions), -1)), axis=1)[:n]
    ok = finite.copy()
    m = min(len(flags), n)
    ok[:m] &= (flags[:m] & int(FrameFlag.UNUSABLE)) == 0
    idx = np.flatnonzero(ok)
    return int(idx[-1]) if idx.size else None


def next_due(due: float, now: float, period: float) -> float:
    """The rate limiter's next slot: one period after the last slot (keeps the average rate at 1/period when
    frames come in batches); a limiter that fell behind restarts from now rather than drawing a burst."""
    return max(due + period, now) if np.isfinite(due) else now + period


class LatestUsable:
    """The rate limit every live display sink shares (the viewer's, OpenIGTLink's, Foxglove's).

    Each batch offers its latest usable frame (:func:`latest_usable`), which replaces one still held; :meth:`take`
    hands the held frame over when its slot is due (:func:`next_due`, at most ``rate`` a second), or at once with
    ``force``. A frame held back by the rate is thus shown at the next call (a heartbeat), never lost.

    Parameters
    ----------
    rate : float
        Most frames handed over per second, Hz.
    who : str
        The sink, for the error on a rate that is not positive.
    """

    def __init__(self, rate: float, who: str):
        if not rate > 0:
            raise ValueError(f"{who}: rate must be positive, got {rate}")
        self.period = 1.0 / rate
        self.held: tuple[Frame, Shape] | None = None
        self.due = -float("inf")

    def offer(self, frames: Frame, shapes: Shape | None, flags: np.ndarray) -> None:
        """Hold the batch's latest usable frame and its shape (a batch with none leaves the held one)."""
        if len(frames) and shapes is not None:
            i = latest_usable(shapes, flags, len(frames))
            if i is not None:
                self.held = (frames[i], shapes[i])

    def take(self, *, force: bool = False) -> tuple[Frame, Shape] | None:
        """The held frame and shape when their slot is due (or ``force``), else None; taking books the next slot."""
        if self.held is None:
            return None
        now = time.monotonic()
        if not (force or now >= self.due):
            return None
        held, self.held = self.held, None
        self.due = next_due(self.due, now, self.period)
        return held


class PrinterSink:
    """Prints one status line at most ``rate`` times per second (and on every state change).

    Parameters
    ----------
    stream : text file
        Where to print (default stdout).
    rate : float
        Lines per second, Hz.
    extras : sequence of callables returning str or None
        More figures for the line (the error against a truth or the interrogator's own shape:
        :meth:`twin.reference_errors.TruthError.status_text`); None leaves them out.
    """

    def __init__(self, stream: TextIO | None = None, rate: float = 1.0,
                 extras: Sequence[Callable[[], str | None]] = ()):
        self.stream = stream or sys.stdout
        self.period = 1.0 / rate if rate > 0 else float("inf")
        self.extras = tuple(extras)
        self._last = -float("inf")
        self._state = None

    def __call__(self, frames, shapes, status: LiveStatus) -> None:
        now = time.monotonic()
        if status.state == "ended" or (status.state == self._state and now - self._last < self.period):
            return
        self._last, self._state = now, status.state
        line = format_status(status)
        more = [t for t in (f() for f in self.extras) if t]
        if more:
            line += "  " + "  ".join(more)
        print(line, file=self.stream, flush=True)


def format_status(s: LiveStatus) -> str:
    """One human line: state, counters, tip in mm."""
    conn = f" ({s.connection})" if s.connection and s.connection != "connected" else ""
    tip = "—" if s.tip is None else "(" + ", ".join(f"{1e3 * x:7.2f}" for x in s.tip) + ") mm"
    if s.state == "stale" and s.tip is not None:
        tip += f" [stale {s.last_valid_age:.1f} s]"
    rate = f"{s.rate_hz:.0f} Hz" + (f", arriving at {s.arrival_hz:.0f} Hz: behind real time" if s.behind else "")
    return (
        f"{s.elapsed:7.1f} s  {s.state:8s}{conn}  frames {s.frames} ({rate})  lost {s.lost_samples}  "
        f"framing errors {s.framing_errors}  reconnects {s.reconnects}  partial {s.frames_partial}  "
        f"unusable {s.frames_unusable}  invalid nodes {s.invalid_nodes}  tip {tip}"
    )

