"""How fast a stream of frames runs: its own sampling rate, read from the frames' timestamps, and whether it keeps
up with real time. Shared by the live loop (:mod:`twin.live`) and the simulated interrogators' frame pump.

Counting frames per wall-clock second makes a jumpy readout: frames come in batches (network packets, the loop's
polls, a simulator that steps in chunks), and a window that ends just after a burst counts frames sampled over a
longer time than the window. The sampling rate is therefore measured on the source's clock: over the frames whose
timestamps lie within the last ``window`` s of the newest one, ``rate = (n − 1) / (t_newest − t_oldest)``, which
is the source's rate whatever the delivery jitter. Timestamps that are missing (NaN) or go backwards (a restarted
source, a reconnect to another one) restart the window; without usable timestamps the rate is frames received per
wall-clock second over the window.

A source runs *behind real time* when frames arrive (per wall-clock second, over ``window`` s) slower than
``slow`` × the rate they should come at: the source's nominal rate when it declares one, else its sampling rate
from the timestamps (a simulator that stamps frames with simulated time and steps slower than the clock).
Entering that state needs it to last ``hold`` s; leaving it needs the arrival rate back above
(1 + slow)/2 of the expected one, so a rate hovering at the threshold does not flap.
"""

from __future__ import annotations

import math
import time
from collections import deque

import numpy as np
from numba import njit

__all__ = ["RateMeter"]


class RateMeter:
    """Sampling rate of a stream from its timestamps, and whether it runs behind real time (module docstring).

    Parameters
    ----------
    nominal : float or None
        The rate the source says it runs at, Hz (None: judge by the timestamps).
    window : float
        Length of the measuring windows, s (of source time for the rate, of wall time for the arrival rate).
    slow : float
        Fraction of the expected rate below which the stream is behind real time.
    hold : float
        How long the stream must stay slow before it counts as behind, s.

    Attributes
    ----------
    behind : bool
        Whether the stream is behind real time now.
    behind_events : int
        Times it fell behind.
    """

    def __init__(self, nominal: float | None = None, *, window: float = 2.0, slow: float = 0.9, hold: float = 0.5):
        if nominal is not None and not (np.isfinite(nominal) and nominal > 0):
            nominal = None
        if not (window > 0 and 0 < slow < 1 and hold >= 0):
            raise ValueError(f"RateMeter: expected window > 0 s, 0 < slow < 1, hold >= 0 s; got {window}, {slow}, "
                             f"{hold}")
        self.nominal = None if nominal is None else float(nominal)
        self.window, self.slow, self.hold = float(window), float(slow), float(hold)
        # per batch: first and last timestamp, frames, and (batches of more than one frame) the timestamps, to count
        # those of a batch that straddles the window's start
        self._stamped: deque[tuple[float, float, int, np.ndarray | None]] = deque()
        self._stamped_n = 0
        self._arrived: deque[tuple[float, int]] = deque()  # (wall time, frames) per batch
        self._arrived_n = 0
        self._start: float | None = None
        self._slow_since: float | None = None
        self.behind = False
        self.behind_events = 0

    def add(self, timestamps, now: float | None = None) -> bool:
        """Count a batch of frames with their timestamps (s; NaN when unknown), received at ``now`` (monotonic s).

        Returns True when the stream has just fallen behind real time.
        """
        ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        n = ts.size
        if n == 0:
            return False
        now = time.monotonic() if now is None else float(now)
        if self._start is None:
            self._start = now
        # the source's clock (one frame, the common live case, without array calls)
        stamped = self._stamped
        first, last = float(ts[0]), float(ts[-1])
        if n == 1:
            usable = math.isfinite(first)
        else:
            usable = _finite_and_ordered(ts)
        if not usable or (stamped and first < stamped[-1][1]):
            stamped.clear()
            self._stamped_n = 0
        if usable:
            # a copy: a view would keep its batch's whole buffer alive for the window
            stamped.append((first, last, n, ts.copy() if n > 1 else None))
            self._stamped_n += n
            while len(stamped) > 1 and stamped[0][1] < last - self.window:
                self._stamped_n -= stamped.popleft()[2]
        # the wall clock
        arrived = self._arrived
        arrived.append((now, n))
        self._arrived_n += n
        # keep one batch at or before the window's start as the anchor the time is measured from
        while len(arrived) > 1 and arrived[1][0] <= now - self.window:
            self._arrived_n -= arrived.popleft()[1]
        return self._judge(now)

    @property
    def stamped_rate(self) -> float | None:
        """Frames per second of the source's clock over the window, Hz (None without usable timestamps): over the
        frames within the last ``window`` s of the newest, also those of a batch that straddles the window's start
        (a file read at full speed comes in batches longer than the window)."""
        s = self._stamped
        if self._stamped_n < 2:
            return None
        newest = s[-1][1]
        oldest, _, _, times = s[0]
        skip = 0
        if oldest < newest - self.window:  # the oldest batch reaches back past the window (never a single frame)
            skip = int(np.searchsorted(times, newest - self.window, side="left"))
            oldest = float(times[skip])
        n = self._stamped_n - skip
        span = newest - oldest
        return (n - 1) / span if n >= 2 and span > 0 else None

    @property
    def arrival_rate(self) -> float:
        """Frames received per wall-clock second over about the window, Hz: the frames of the batches after the
        oldest one kept, over the time since that one arrived (a backlog delivered at once does not count as a
        fast stream)."""
        a = self._arrived
        if len(a) < 2:
            return 0.0
        span = a[-1][0] - a[0][0]
        return (self._arrived_n - a[0][1]) / span if span > 0 else 0.0

    @property
    def rate(self) -> float:
        """The stream's sampling rate, Hz: :attr:`stamped_rate`, else :attr:`arrival_rate`."""
        r = self.stamped_rate
        return self.arrival_rate if r is None else r

    @property
    def expected_rate(self) -> float | None:
        """What the arrival rate should be, Hz: the nominal rate, else the stamped rate."""
        return self.nominal if self.nominal is not None else self.stamped_rate

    def _judge(self, now: float) -> bool:
        expected = self.expected_rate
        if expected is None or now - self._start < self.window:
            return False  # not enough wall time seen to tell
        ratio = self.arrival_rate / expected
        if ratio >= 0.5 * (1.0 + self.slow):
            self._slow_since = None
            self.behind = False
            return False
        if ratio >= self.slow:
            return False
        if self._slow_since is None:
            self._slow_since = now
        if not self.behind and now - self._slow_since >= self.hold:
            self.behind = True
            self.behind_events += 1
            return True
        return False


@njit(cache=True, nogil=True)
def _finite_and_ordered(ts) -> bool:
    """All timestamps finite and none before its predecessor (one compiled pass: the numpy form cost ≈ 2.5 µs of
    array calls a batch in the live loop)."""
    for i in range(ts.size):
        if not np.isfinite(ts[i]) or (i and ts[i] < ts[i - 1]):
            return False
    return True
