"""The streaming loop: source → :class:`~twin.reconstruct.Reconstructor` → sinks.

One iteration takes every frame the source has ready (up to ``max_batch``), reconstructs them as one batch
(batch-first: a burst after a stall costs little more than one frame) and hands the batch to each sink. Around
that it keeps the books a live instrument needs:

- **lost samples**: forward jumps of the frames' sequence numbers (a sequence that goes backwards is counted
  as a reset — a restarted acquisition — not as loss);
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

Sinks are tiny: any callable ``sink(frames, shapes, status)`` with an optional ``close()``. ``frames`` is the
list of frames of the batch, or one 1-D batch :class:`~twin.frames.Frame` when the source decodes in batches
(the ILLumiSense driver: same ``len``, indexing and iteration), ``shapes`` the batched
:class:`~twin.frames.Shape` (``shapes[i]`` belongs to ``frames[i]``; None when the batch could not be
reconstructed), ``status`` a :class:`LiveStatus`. Between batches sinks get ``sink([], None, status)``
heartbeats (at least every ``heartbeat`` s and on every state change).

Why one module of this size: the loop, its status and counters and its summary are one state machine; split,
the counters' one meaning would be spread over files.
"""

from __future__ import annotations

import enum
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol, TextIO

import numpy as np

from twin.frames import Frame, Shape
from twin.io.errors import SourceFailed
from twin.io.rate import RateMeter
from twin.io.sequence import SequenceCounter
from twin.io.source import Source, SourceClosed
from twin.io.transport import Backoff
from twin.reconstruct import Reconstructor

__all__ = [
    "CallbackSink",
    "FrameFlag",
    "LiveLoop",
    "LiveStatus",
    "LiveSummary",
    "PrinterSink",
    "Sink",
    "batch_timestamps",
    "join_batches",
    "read_batch",
]


class FrameFlag(enum.IntFlag):
    """Per-frame flags of a batch (:attr:`LiveStatus.flags`)."""

    OK = 0
    MISSING_PEAKS = 1  #: some peaks missing; reconstructed from the remaining cores
    PARTIAL = 2  #: some gratings could not be solved and were interpolated over
    UNUSABLE = 4  #: no grating could be solved: no shape
    SEQUENCE_GAP = 8  #: samples were lost just before this frame


_MISSING, _PARTIAL, _UNUSABLE, _GAP = (np.uint8(f) for f in (1, 2, 4, 8))


class Sink(Protocol):
    """What the loop feeds: ``sink(frames, shapes, status)``; ``close()`` when the loop ends (optional)."""

    def __call__(self, frames: Sequence[Frame], shapes: Shape | None, status: LiveStatus) -> None: ...


@dataclass(frozen=True, eq=False)
class LiveStatus:
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
    frames : int
        Frames received and matching the fibre model.
    frames_complete, frames_partial, frames_unusable, frames_missing_peaks : int
        Every grating solved / some dropped / none solved / some peak missing (absent, or outside the
        physical window).
    peaks_outside_window : int
        Peaks reported but outside the reconstructor's physical window (or infinite), treated as missing.
    frames_rejected : int
        Frames whose (n_gratings, n_cores) does not match the fibre model (not reconstructed, not recorded).
    lost_samples, sequence_gaps, sequence_resets : int
        From the frames' sequence numbers.
    invalid_nodes : int
        Gratings that could not be solved, summed over frames.
    framing_errors, reconnects, disconnects : int
        From the source's counters (plus the loop's own reopenings of a source that raised).
    source_errors, reconstruct_errors : int
        Exceptions out of ``source.read`` and out of the reconstructor (each batch counted once).
    stale_events : int
        Transitions into ``stale``.
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
    invalid_nodes: int = 0
    framing_errors: int = 0
    reconnects: int = 0
    disconnects: int = 0
    source_errors: int = 0
    reconstruct_errors: int = 0
    stale_events: int = 0
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
    """

    status: LiveStatus
    duration: float
    reason: str
    sink_errors: tuple[str, ...] = ()

    @property
    def frames_per_s(self) -> float:
        return self.status.frames / self.duration if self.duration > 0 else 0.0

    def as_dict(self) -> dict:
        return {
            "reason": self.reason,
            "duration": round(self.duration, 6),
            "frames_per_s": round(self.frames_per_s, 3),
            **self.status.as_dict(),
            "sink_errors": list(self.sink_errors),
        }


def read_batch(source: Source, max_frames: int, timeout: float | None) -> list[Frame] | Frame:
    """Every frame the source has ready, up to ``max_frames``, waiting up to ``timeout`` s for the first.

    Uses the source's ``read_batches`` when it has one (a driver whose decoder makes batch Frames): when every
    item is a 1-D batch of one shape, the result is ONE batch Frame (no Python object per frame), otherwise
    the list of single frames. Else the source's ``read_many`` (the drivers, synthetic and replay sources
    have one), else ``read(timeout)`` followed by ``read(0)`` until nothing is ready. An exception
    (SourceClosed included) is raised only when no frame was read before it; otherwise the frames are
    returned and the exception is kept on the source (``_twin_deferred``) and raised by the next call, so
    nothing received is dropped.
    """
    deferred = getattr(source, "_twin_deferred", None)
    if deferred is not None:
        source._twin_deferred = None
        raise deferred
    batches = getattr(source, "read_batches", None)
    if batches is not None:
        return join_batches(batches(max_frames, timeout))
    many = getattr(source, "read_many", None)
    if many is not None:
        return many(max_frames, timeout)
    first = source.read(timeout)
    if first is None:
        return []
    out = [first]
    while len(out) < max_frames:
        try:
            nxt = source.read(0.0)
        except Exception as exc:
            source._twin_deferred = exc
            break
        if nxt is None:
            break
        out.append(nxt)
    return out


def join_batches(items: Sequence[Frame]) -> list[Frame] | Frame:
    """Single frames and 1-D batch Frames (in order) as what :meth:`LiveLoop.process` takes: one batch Frame
    when every item is a batch of one (n_gratings, n_cores) without truth, else the list of single frames."""
    if items and all(f.batch_shape and f.truth is None for f in items) and \
            len({f.wavelengths.shape[1:] for f in items}) == 1:
        if len(items) == 1:
            return items[0]
        return Frame.stack(items)
    return [g for f in items for g in (f if f.batch_shape else (f,))]


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
    """

    def __init__(self, source: Source | Callable[[], Source], reconstructor: Reconstructor,
                 sinks: Sequence[Sink] = (), *, stale_after: float = 0.5, max_batch: int = 256,
                 poll: float = 0.05, heartbeat: float = 0.1, rate_window: float = 2.0):
        self._factory = source if callable(source) and not isinstance(source, Source) else None
        self.source: Source | None = None if self._factory else source
        self.rec = reconstructor
        self.sinks = list(sinks)
        self.stale_after, self.max_batch = float(stale_after), int(max_batch)
        self.poll, self.heartbeat = float(poll), float(heartbeat)
        self.rate_window = float(rate_window)
        self._shape = (reconstructor.fiber.n_gratings, reconstructor.fiber.n_cores)
        self._stop = threading.Event()
        self._stop_reason = "stopped"
        self.sink_errors: list[str] = []
        self._reset_counters()

    def _reset_counters(self) -> None:
        self.c = dict.fromkeys(
            ("frames", "frames_complete", "frames_partial", "frames_unusable", "frames_missing_peaks",
             "peaks_outside_window", "frames_rejected", "lost_samples", "sequence_gaps", "sequence_resets",
             "invalid_nodes", "source_errors", "reconstruct_errors", "stale_events", "reopens"), 0)
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
    def process(self, frames: Sequence[Frame] | Frame) -> tuple[list[Frame] | Frame, Shape | None, np.ndarray]:
        """Check, reconstruct and count one batch.

        Parameters
        ----------
        frames : list of Frame, or Frame
            Single frames, or one 1-D batch Frame (what :func:`read_batch` gives for a driver that decodes in
            batches: no Python object per frame on the hot path).

        Returns
        -------
        frames : list of Frame, or Frame
            The frames that match the fibre model (the others are counted in ``frames_rejected``): a list for
            a list, the batch (or an empty list) for a batch.
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
        shape = self._shape
        if isinstance(frames, Frame):
            if len(frames.batch_shape) != 1:
                raise ValueError(f"LiveLoop.process: expected a 1-D batch Frame, got batch shape {frames.batch_shape}")
            n = len(frames)
            if frames.wavelengths.shape[1:] == shape:
                good, w, seq = frames, frames.wavelengths, frames.sequence
            else:
                good, w, seq = [], None, None
                self._reject(n, frames.wavelengths.shape[1:])
                n = 0
        else:
            good = [f for f in frames if f.wavelengths.shape == shape]
            if len(good) < len(frames):
                self._reject(len(frames) - len(good), frames[0].wavelengths.shape, any_good=bool(good))
            n = len(good)
            if n:
                w = np.stack([f.wavelengths for f in good]) if n > 1 else good[0].wavelengths[None]
                seq = [f.sequence for f in good]
        if n == 0:
            return [] if isinstance(good, Frame) else good, None, np.zeros(0, np.uint8)
        self._matched_any = True
        shapes, flags = self.process_arrays(w, seq)
        return good, shapes, flags

    def process_arrays(self, w: np.ndarray, sequence) -> tuple[Shape | None, np.ndarray]:
        """Reconstruct and count a batch given as arrays (the books of :meth:`process`; ``twin replay`` keeps
        its books here too, so both count alike).

        Parameters
        ----------
        w : ndarray, shape (n, n_gratings, n_cores)
            Wavelengths, nm, matching the fibre model (n >= 1).
        sequence : array_like of int, shape (n,)
            The frames' sequence numbers.

        Returns
        -------
        shapes : Shape or None
            Batched reconstruction (None when the reconstructor raised).
        flags : ndarray of uint8 (n,)
            :class:`FrameFlag` bits per frame.
        """
        n = len(w)
        shape = self._shape
        # the strain once, for the window check, the flags and the reconstruction (NaN where missing or outside)
        e, outside = self.rec.strain(w)
        n_outside = int(np.count_nonzero(outside))
        flags = np.isnan(e.reshape(n, -1)).any(axis=1).astype(np.uint8)  # MISSING_PEAKS = 1
        # counted before the sequence counter adds its own flag to the same array
        n_missing = int(np.count_nonzero(flags))
        self._count_sequence(sequence, flags)
        try:
            shapes = self.rec.from_strain(e)
        except Exception as exc:  # the frames still reach the sinks (the recorder keeps them)
            if not self.c["reconstruct_errors"]:
                print(f"twin live: reconstruction failed: {exc}", file=sys.stderr)
            self.c["reconstruct_errors"] += 1
            shapes = None
        g = shape[0]
        c = self.c
        c["peaks_outside_window"] += n_outside
        if shapes is None:
            n_valid = np.zeros(n, np.int64)
        else:
            n_valid = shapes.valid.sum(axis=-1)
        unusable = n_valid == 0
        partial = (n_valid < g) & ~unusable
        flags |= (partial * _PARTIAL) | (unusable * _UNUSABLE)
        n_partial, n_unusable = int(partial.sum()), int(unusable.sum())
        c["frames"] += n
        c["frames_missing_peaks"] += n_missing
        c["frames_partial"] += n_partial
        c["frames_unusable"] += n_unusable
        c["frames_complete"] += n - n_partial - n_unusable
        c["invalid_nodes"] += g * n - int(n_valid.sum())
        if n_unusable < n:
            self._last_valid = time.monotonic()
            last = n - 1 if not unusable[-1] else int(np.flatnonzero(~unusable)[-1])
            self._tip = shapes.positions[last, -1].copy()
        return shapes, flags

    def _reject(self, n: int, bad: tuple, any_good: bool = False) -> None:
        """Count n frames of another (n_gratings, n_cores) than the fibre model's; a configuration error when
        nothing has ever matched."""
        self.c["frames_rejected"] += n
        if not any_good and not self._matched_any:
            shape = self._shape
            raise ValueError(
                f"frames have {bad[0]} gratings × {bad[1]} cores but the fibre model has {shape[0]} × "
                f"{shape[1]}; give the sensor's fibre model (--fiber FILE)"
            )

    def _count_sequence(self, seq, flags: np.ndarray) -> None:
        """Count gaps and resets of the sequence numbers; flag the frames that follow a gap."""
        counter = self._sequence
        flags[counter.count_many(seq) > 0] |= _GAP  # one batch call (a call per frame cost ~10 µs each)
        self.c["sequence_gaps"] = counter.sequence_gaps
        self.c["lost_samples"] = counter.lost_samples
        self.c["sequence_resets"] = counter.sequence_resets

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
            **{k: v for k, v in self.c.items() if k != "reopens"},
            framing_errors=int(s.get("framing_errors", 0)),
            reconnects=int(s.get("reconnects", 0)) + self.c["reopens"],
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
            self.c["stale_events"] += 1
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
                print(f"twin live: sink {type(sink).__name__} failed and was removed: {exc}", file=sys.stderr)
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
                if max_frames is not None and self.c["frames"] >= max_frames:
                    reason = "frames"
                    break
                wait = self.poll
                if duration is not None:
                    wait = max(0.0, min(wait, self._t0 + duration - now))
                frames: list[Frame] | Frame = []
                if self.source is None:
                    if reopen_at is not None and now >= reopen_at:
                        try:
                            self._open()
                            self.c["reopens"] += 1
                            reopen_at = None
                        except _SOURCE_ERRORS:
                            reopen_at = time.monotonic() + backoff.failed()
                    if self.source is None:
                        time.sleep(wait)
                else:
                    limit = self.max_batch if max_frames is None else max(1, min(
                        self.max_batch, max_frames - self.c["frames"]))
                    try:
                        frames = read_batch(self.source, limit, wait)
                    except SourceClosed:
                        reason = "source ended"
                        break
                    except SourceFailed as exc:  # reopening cannot cure it (a damaged recording)
                        self.c["source_errors"] += 1
                        self._source_stats = {**self._source_stats, "last_error": str(exc)}
                        print(f"twin live: source failed: {exc}", file=sys.stderr)
                        reason = "source failed"
                        break
                    except _SOURCE_ERRORS as exc:
                        self.c["source_errors"] += 1
                        self._source_stats = {**self._source_stats, "last_error": str(exc)}
                        if self._factory is None:
                            print(f"twin live: source failed: {exc}", file=sys.stderr)
                            reason = "source failed"
                            break
                        _close(self.source)
                        self.source = None
                        reopen_at = time.monotonic() + backoff.failed()
                if frames:
                    good, shapes, flags = self.process(frames)
                    t = time.monotonic()
                    if good and self._meter.add(batch_timestamps(good), t):
                        self._say_behind()
                    if self.c["frames"] and backoff.failures:
                        backoff.reset()
                    changed = self._update_state()
                    if good or changed:
                        self._emit(good, shapes, self.status(flags))
                        last_emit = t
                else:
                    changed = self._update_state()
                    t = time.monotonic()
                    if changed or t - last_emit >= self.heartbeat:
                        self._emit([], None, self.status())
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
                    sink([], None, final)
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
        return LiveSummary(final, time.monotonic() - self._t0, reason, tuple(self.sink_errors))

    def _say_behind(self) -> None:
        m = self._meter
        if m.behind_events != 1:
            return  # said once; later episodes are counted
        expected = m.expected_rate or 0.0
        why = "its nominal rate" if m.nominal is not None else "its timestamps advance"
        print(f"twin live: frames arrive at {m.arrival_rate:.0f} Hz, slower than {why} ({expected:.0f} Hz): the "
              "source runs behind real time (said once; counted in behind_events)", file=sys.stderr, flush=True)

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


def batch_timestamps(frames: Sequence[Frame] | Frame) -> np.ndarray:
    """Timestamps of a list of frames or of a batch Frame, s, shape (n,)."""
    if isinstance(frames, Frame):
        return np.asarray(frames.timestamp, dtype=np.float64)
    return np.fromiter((f.timestamp for f in frames), float, len(frames))


def _nominal_rate(source) -> float | None:
    rate = getattr(source, "rate", None)
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


class PrinterSink:
    """Prints one status line at most ``rate`` times per second (and on every state change).

    Parameters
    ----------
    stream : text file
        Where to print (default stdout).
    rate : float
        Lines per second, Hz.
    """

    def __init__(self, stream: TextIO | None = None, rate: float = 1.0):
        self.stream = stream or sys.stdout
        self.period = 1.0 / rate if rate > 0 else float("inf")
        self._last = -float("inf")
        self._state = None

    def __call__(self, frames, shapes, status: LiveStatus) -> None:
        now = time.monotonic()
        if status.state == "ended" or (status.state == self._state and now - self._last < self.period):
            return
        self._last, self._state = now, status.state
        print(format_status(status), file=self.stream, flush=True)


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


class CallbackSink:
    """Calls ``fn(frame, shape, status)`` with the latest frame of each batch (and its single Shape)."""

    def __init__(self, fn: Callable[[Frame, Shape, LiveStatus], None]):
        self.fn = fn

    def __call__(self, frames, shapes, status) -> None:
        if frames and shapes is not None:
            self.fn(frames[-1], shapes[len(frames) - 1], status)
