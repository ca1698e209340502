"""``replay://FILE``: a recording's frames as a source (:class:`ReplaySource`), paced as recorded or as fast as
read, with their truth and their sensor blocks (:attr:`Frame.vendor <twin.frames.Frame.vendor>`) when recorded.
``twin replay`` is the live loop over this source at full speed (:mod:`twin.replay_summary`).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from twin.frames import Frame
from twin.io.errors import RecordingDamaged
from twin.io.options import Option, parse_options
from twin.io.record import open_recording
from twin.io.source import MAX_BATCH, Source, SourceClosed, parse_url

__all__ = ["ReplaySource", "open_replay"]


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
        Frames read from the file at a time (a batch never spans two chunks).
    salvage : bool
        A damaged recording: replay the frames before the damage and end normally. Without it, a recording
        found damaged when opened raises :class:`~twin.io.errors.RecordingDamaged` at once, and damage found
        while reading raises it after the frames before it were delivered — a permanent error, which the live
        loop does not retry.

    Attributes
    ----------
    info : dict
        What the file is (``kind``, ``complete``, ``damaged``, ``damage``, ``frames_recorded``, ``source_url``,
        ``skipped_lines``, ``notes``), kept up to date while reading and after :meth:`close`.
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
        self._batch: Frame | None = None  # the loaded chunk, with its truth and sensor blocks
        self._i = 0
        self._times: np.ndarray = np.empty(0)
        self._next = 0  # next file row to load
        self._t_first: float | None = None  # recorded time of the first frame
        self._wall0 = 0.0
        self._delivered = 0
        self.info: dict = {}
        self._update_info()

    def _update_info(self) -> None:
        r = self.reader
        self.info = {"file": str(r.path), "kind": r.kind, "complete": r.complete, "damaged": r.damaged,
                     "damage": list(r.damage), "frames_recorded": r.frames_recorded, "source_url": r.source_url,
                     "skipped_lines": r.skipped_lines, "skipped": list(r.errors[:1]),
                     "damage_line": r.damage_line() if r.damaged else "", "notes": list(r.notes)}

    def _load(self) -> bool:
        n = len(self.reader)
        if self._next >= n and self.follow and not self.reader.damaged:
            n = self.reader.refresh()
        if self._next >= n:
            return False
        try:
            stop = min(n, self._next + self.chunk)
            batch = self.reader.frames(self._next, stop)
            received = self.reader.received(self._next, self._next + len(batch))
            vendor = self.reader.vendor(self._next, self._next + len(batch))
        except Exception as exc:  # reopening would replay the same bytes: never transient
            raise RecordingDamaged(f"{self.reader.path}: unreadable at frame {self._next} ({exc})") from None
        finally:
            self._update_info()
        if len(batch) == 0:
            return False
        if vendor:
            batch = dataclasses.replace(batch, vendor=tuple(vendor))
        m = min(len(batch), len(received))
        self._batch, self._i = batch, 0
        self._times = np.where(np.isfinite(batch.timestamp[:m]), batch.timestamp[:m], received[:m])
        self._next += len(batch)
        return True

    def _pending(self) -> int:
        return 0 if self._batch is None else len(self._batch) - self._i

    def _due(self, k: int, timeout: float | None) -> int:
        """How many of the next ``k`` loaded frames are due, after waiting up to ``timeout`` s for the first."""
        if self.speed is None:
            return k
        t = self._times[self._i : self._i + k]
        if t.size and np.isfinite(t[0]):
            if self._t_first is None:
                self._t_first, self._wall0 = float(t[0]), time.monotonic()
            wait = self._wall0 + (t[0] - self._t_first) / self.speed - time.monotonic()
            if wait > 0:
                if timeout is not None and timeout < wait:
                    time.sleep(max(0.0, timeout))
                    return 0
                time.sleep(wait)
        if self._t_first is None or t.size < k:
            return max(1, min(k, t.size))
        due = ~np.isfinite(t) | (self._wall0 + (t - self._t_first) / self.speed <= time.monotonic())
        due[0] = True
        return k if due.all() else int(np.argmin(due))

    def read_batch(self, max_frames: int = MAX_BATCH, timeout: float | None = None) -> Frame | None:
        if self.reader is None:
            raise SourceClosed(f"{self.url}: closed")
        if not self._pending() and not self._load():
            if self.reader.damaged and not self.salvage:
                raise RecordingDamaged(self.reader.damage_line())
            if self.follow and not self.reader.complete and not self.reader.damaged:
                time.sleep(min(0.05, timeout if timeout is not None else 0.05))
                return None
            raise SourceClosed(f"{self.url}: end of recording ({self._delivered} frames)")
        n = self._due(min(max_frames, self._pending()), timeout)
        if n == 0:
            return None
        out = self._batch[self._i : self._i + n]
        self._i += n
        self._delivered += n
        return out

    def close(self) -> None:
        if self.reader is not None:
            self._update_info()
            self.reader.close()
            self.reader = None

    def stats(self) -> dict:
        return {"frames_replayed": self._delivered, "skipped_lines": self.info.get("skipped_lines", 0),
                "damaged": bool(self.info.get("damaged"))}

    def describe(self) -> dict:
        return {"url": self.url, **self.info}


#: the options of ``replay://`` (:mod:`twin.io.options`)
REPLAY_OPTIONS = {
    "speed": Option("float", default=1.0, low=0.0, low_open=True, words={"recorded": 1.0, "max": None}),
    "follow": Option("bool"),
    "salvage": Option("bool"),
    "channels": Option("str", choices=("cores", "single")),
    "cores": Option("int", low=1, high=64),
}


def open_replay(url: str, **options) -> ReplaySource:
    """Open ``replay://FILE?speed=recorded|max|FACTOR&follow=0|1&salvage=0|1&channels=cores|single&cores=N``.

    ``FILE`` is a path (``replay:///abs/path.h5`` or ``replay://relative.h5``). Default speed: as recorded.
    """
    _, rest, query = parse_url(url)
    if not rest:
        raise ValueError(f"{url!r}: expected replay://FILE")
    kw = parse_options(url, query, REPLAY_OPTIONS)  # speed: 1.0 when absent, None for "max"
    channels = kw.pop("channels", "cores")
    n_cores = kw.pop("cores", None)
    if channels == "single":
        kw["channels_as"], kw["n_cores"] = "single", n_cores
    options.pop("fiber", None)  # a recording knows its fibre; the live loop takes --fiber separately
    kw.update(options)
    return ReplaySource(rest, url=url, **kw)
