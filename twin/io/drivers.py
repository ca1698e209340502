"""Interrogator drivers: :class:`~twin.io.source.Source` implementations for ``illumisense://``,
``fispec://`` and ``hyperion://`` URLs, with reconnect, backoff and counters.

Common behaviour
----------------
- **Opening** connects at once. When nothing listens yet (connection refused or reset, a connect timeout, a
  serial device not there yet) — a lab starts the interrogator and the tool in any order — it keeps trying for
  up to ``start_wait`` s (URL option; :attr:`Driver.START_WAIT` by default: 30 s for the TCP drivers, 0 for
  serial ports, where a missing device is more likely a wrong path), with the usual backoff capped at 1 s,
  saying so on stderr once and then every 5 s. Then, or at once for an error that waiting cannot cure (an
  unknown host, a handshake the device refuses), it raises :class:`OSError` naming the URL once and the reason.
  With ``wait=1`` the driver does not wait in the constructor but keeps trying in the background of
  :meth:`read` like after a drop.
- **Reconnect policy**: after a connection drops (peer closed, reset, device gone, a protocol error that cannot
  be resynchronised), the first new attempt is immediate, then the delay doubles from 0.1 s up to 5 s
  (:class:`~twin.io.transport.Backoff`), and is reset once frames flow again. Retries go on forever unless
  ``retry_for=SECONDS`` is given, after which :meth:`read` raises :class:`~twin.io.errors.SourceFailed` (the
  live loop ends with that line and a non-zero status: giving up is not an end of the data).
  :meth:`read` never blocks longer than its timeout while disconnected; it returns None.
- **Resync timeout** (the drivers whose stream decoder resynchronises by itself: ILLumiSense, Hyperion): the
  driver reconnects when the stream stays out of sync for ``resync_timeout`` s (URL option; default
  :data:`RESYNC_TIMEOUT`, 2 s) of reading that keeps up with what arrives, with ``ConnectionLost`` ("stream out of
  sync for S s") as the reason, counted in ``disconnects`` and ``last_error`` like any drop. The clock runs only
  while reads come back shorter than asked: a reader that fell behind (away while a first reconstruction
  compiles, a starved CPU) reads the backlog first, which may hold the next intact frames, and a garbage stream
  that fills every read is skipped, not reconnected (:meth:`Driver._watch_sync`).
- **Counters** in :meth:`stats`: ``state`` (connected / disconnected / closed), ``frames``, ``framing_errors``,
  ``lost_samples`` and ``sequence_gaps`` (from the source's sample numbers), ``disconnects``, ``reconnects``
  (successful connections after the first), ``connect_failures``, ``last_error`` (text).
- :meth:`read_batch` returns every frame already received as one batch (a burst after a stall is reconstructed
  as one batch; a batch decoder's output is joined without a Python object per frame).

The protocols' drivers: :mod:`twin.io.illumisense.driver`, :mod:`twin.io.hyperion.driver`,
:mod:`twin.io.fispec.driver`.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from collections.abc import Sequence

import numpy as np

from twin.frames import Frame, PeakStatus
from twin.io.errors import FramingError, SourceFailed
from twin.io.options import Option
from twin.io.source import MAX_BATCH, Source, SourceClosed
from twin.io.transport import Backoff, ConnectionLost

__all__ = ["COMMON_OPTIONS", "MISSING", "RESYNC_OPTIONS", "RESYNC_TIMEOUT", "Driver", "split_common"]

MISSING = np.uint8(PeakStatus.MISSING)
#: default ``resync_timeout``, s (module docstring)
RESYNC_TIMEOUT = 2.0


class Driver(Source):
    """Connection management shared by the drivers (module docstring: reconnect policy and counters).

    Subclasses implement :meth:`_connect` (open the transport and do the handshake), :meth:`_pump` (wait up
    to ``timeout`` s for bytes, decode, append frames to ``self._queue``) and :meth:`_drop` (close the
    transport).

    Parameters
    ----------
    url : str
        What was opened (every error message starts with it).
    wait : bool
        Do not fail when the first connection attempt fails; keep retrying.
    retry_for : float or None
        Give up (SourceFailed) after this many seconds without a connection; None retries forever.
    backoff : Backoff, optional
        Reconnect delays.
    start_wait : float or None
        How long opening keeps trying while nothing listens yet, s (None: :attr:`START_WAIT`; 0: fail at once).
    """

    #: default ``start_wait``, s: how long opening waits for an interrogator that is not listening yet
    START_WAIT = 30.0
    #: errors that mean "not there yet" (waiting may cure them): refused, reset, timed out, no such device yet
    NOT_YET = (ConnectionError, TimeoutError, FileNotFoundError)
    #: s a stream may stay out of sync before the connection is dropped (:meth:`_watch_sync`); a resynchronising
    #: driver sets it from its ``resync_timeout`` parameter
    resync_timeout: float = RESYNC_TIMEOUT

    def __init__(self, url: str, *, wait: bool = False, retry_for: float | None = None,
                 backoff: Backoff | None = None, start_wait: float | None = None):
        self.url = url
        self.backoff = backoff or Backoff()
        self.retry_for = retry_for
        self._queue: deque[Frame] = deque()  # single frames and 1-D batch Frames
        self._connected = False
        self._closed = False
        self._ever_connected = False
        self._next_attempt = 0.0
        self._down_since: float | None = None
        self._frames_since_connect = 0
        self._out_of_sync_since: float | None = None
        self.counters = {
            "frames": 0,
            "framing_errors": 0,
            "lost_samples": 0,
            "sequence_gaps": 0,
            "disconnects": 0,
            "reconnects": 0,
            "connect_failures": 0,
        }
        self.last_error = ""
        self._last_exc: BaseException | None = None
        if not self._attempt() and not wait:
            limit = self.START_WAIT if start_wait is None else float(start_wait)
            if not limit >= 0:  # NaN too
                raise ValueError(f"{url}: start_wait must be a number of seconds >= 0, got {start_wait}")
            self._wait_at_start(limit)

    # ---------------------------------------------------------------- to implement
    def _connect(self) -> None:
        raise NotImplementedError

    def _pump(self, timeout: float) -> None:
        raise NotImplementedError

    def _drop(self) -> None:
        raise NotImplementedError

    # ---------------------------------------------------------------- machinery
    def _wait_at_start(self, limit: float) -> None:
        """Keep trying to connect for up to ``limit`` s while the errors say nothing listens yet (module
        docstring); raise OSError (the last error) when that fails or the error is of another kind."""
        t0 = time.monotonic()
        delays = Backoff(maximum=1.0)  # start-up: keep the latency after the interrogator comes up short
        said = None
        while True:
            now = time.monotonic()
            if not isinstance(self._last_exc, self.NOT_YET) or now - t0 >= limit:
                if said is None:
                    raise OSError(self.last_error)
                raise OSError(f"{self.last_error} (tried for {now - t0:.1f} s; the URL option start_wait=SECONDS "
                              "waits longer)")
            if said is None:
                print(f"{self.last_error}; nothing listening yet: trying again for up to {limit:g} s (URL option "
                      "start_wait=SECONDS) …", file=sys.stderr, flush=True)
                said = now
            elif now - said >= 5.0:
                print(f"{self.url}: still waiting ({now - t0:.0f} of {limit:g} s) …", file=sys.stderr, flush=True)
                said = now
            time.sleep(min(delays.failed(), max(0.0, t0 + limit - now)))
            if self._attempt():
                self.backoff.reset()
                print(f"{self.url}: connected after {time.monotonic() - t0:.1f} s", file=sys.stderr, flush=True)
                return

    def _error(self, exc: BaseException) -> str:
        # an OSError built with (errno, text) prints as "[Errno N] text": its text alone, so the URL shows once
        text = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        return text if text.startswith(self.url) else f"{self.url}: {text}"

    def _attempt(self) -> bool:
        """One connection attempt; True when connected."""
        try:
            self._connect()
        except (OSError, FramingError, ValueError) as exc:
            self._drop()
            self.counters["connect_failures"] += 1
            self._last_exc = exc
            self.last_error = self._error(exc)
            self._next_attempt = time.monotonic() + self.backoff.failed()
            if self._down_since is None:
                self._down_since = time.monotonic()
            return False
        if self._ever_connected:
            self.counters["reconnects"] += 1
        self._ever_connected = True
        self._connected = True
        self._down_since = None
        self._frames_since_connect = 0
        self._out_of_sync_since = None
        return True

    def _disconnect(self, exc: BaseException) -> None:
        self.last_error = self._error(exc)
        self._drop()
        self._connected = False
        self.counters["disconnects"] += 1
        self._down_since = time.monotonic()
        # immediate first retry after a connection that delivered frames; a connection that delivered nothing
        # (a server that accepts and closes, a device that never answers) counts as a failed attempt, so the
        # delays grow instead of spinning
        if self._frames_since_connect:
            self.backoff.reset()
            delay = 0.0
        else:
            delay = self.backoff.failed()
        self._next_attempt = time.monotonic() + delay

    def _watch_sync(self, n_read: int, recv_size: int, in_sync: bool) -> None:
        """The resync timeout (module docstring), after a read of ``n_read`` bytes (of ``recv_size`` asked) was
        decoded, leaving the decoder ``in_sync`` or not.

        Raises
        ------
        ConnectionLost
            The stream stayed out of sync for :attr:`resync_timeout` s of reads that kept up with it.
        """
        if not n_read:
            return
        if in_sync:
            self._out_of_sync_since = None
            return
        now = time.monotonic()
        # the clock runs only while the reader keeps up (a read shorter than asked: nothing more waited). Behind —
        # the reader was away (a first reconstruction compiling, a starved CPU) — the bytes sat unread and may hold
        # the next intact frame, and a sender held back by a full socket sent nothing new meanwhile: dropping the
        # connection would lose frames, so the clock starts again
        if n_read >= recv_size or self._out_of_sync_since is None:
            self._out_of_sync_since = now
        elif now - self._out_of_sync_since > self.resync_timeout:
            raise ConnectionLost(f"{self.url}: stream out of sync for {self.resync_timeout:g} s")

    def _push(self, frames: Sequence[Frame]) -> None:
        """Queue decoded frames: single frames, or 1-D batch Frames (a batch decoder's output, kept whole)."""
        if frames:
            n = sum(len(f) if f.batch_shape else 1 for f in frames)
            self._queue.extend(frames)
            self.counters["frames"] += n
            self._frames_since_connect += n
            if self.backoff.failures:
                self.backoff.reset()

    def _wait(self, timeout: float | None) -> None:
        """Pump until something is queued or ``timeout`` s have passed (connecting and reconnecting as needed)."""
        if self._closed:
            raise SourceClosed(f"{self.url}: closed")
        deadline = None if timeout is None else time.monotonic() + timeout
        pumped = False
        while not self._queue:
            now = time.monotonic()
            remaining = None if deadline is None else deadline - now
            if remaining is not None and remaining <= 0:
                if pumped or not self._connected:
                    break
                remaining = 0.0  # read(0): one non-blocking look at the transport
            if not self._connected:
                if self.retry_for is not None and self._down_since is not None \
                        and now - self._down_since > self.retry_for:
                    why = self.last_error.removeprefix(f"{self.url}: ")
                    raise SourceFailed(f"{self.url}: no connection for {self.retry_for:g} s ({why})")
                if now < self._next_attempt:
                    pause = self._next_attempt - now
                    time.sleep(pause if remaining is None else min(pause, remaining))
                    continue
                if not self._attempt():
                    continue
            try:
                pumped = True
                self._pump(0.5 if remaining is None else min(remaining, 0.5))
            except (ConnectionLost, OSError, FramingError) as exc:
                self._disconnect(exc)

    def _take(self, max_frames: int) -> list[Frame]:
        """Queued items holding at most ``max_frames`` frames of one (n_gratings, n_cores) (a batch cut at the
        limit leaves its rest queued; an item of another shape waits for the next call)."""
        out: list[Frame] = []
        room = max_frames
        q = self._queue
        shape = q[0].wavelengths.shape[-2:] if q else None
        while q and room > 0 and q[0].wavelengths.shape[-2:] == shape:
            item = q[0]
            n = len(item) if item.batch_shape else 1
            if n > room:
                q[0] = item[room:]
                item, n = item[:room], room
            else:
                q.popleft()
            out.append(item)
            room -= n
        return out

    def read_batch(self, max_frames: int = MAX_BATCH, timeout: float | None = None) -> Frame | None:
        """Frames received so far (up to ``max_frames``) as one batch, waiting up to ``timeout`` s for the first.

        Returns None when nothing arrived in time (also while disconnected and retrying). What the decoder made
        as batches is joined once here (no Python object per frame for a batch decoder's output).
        """
        self._wait(timeout)
        items = self._take(max_frames)
        return Frame.stack(items) if items else None

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._connected = False
            self._drop()

    @property
    def connected(self) -> bool:
        return self._connected

    def stats(self) -> dict:
        state = "closed" if self._closed else ("connected" if self._connected else "disconnected")
        return {"state": state, **self.counters, "last_error": self.last_error}


# -------------------------------------------------------------------------------------------- URL options


#: the options every driver takes (:mod:`twin.io.options`); drivers add their own
COMMON_OPTIONS = {
    "wait": Option("bool"),
    "retry_for": Option("float", low=0.0),
    "connect_timeout": Option("float", low=0.0, low_open=True, high=3600.0),
    "start_wait": Option("float", low=0.0),
}


#: the option of the drivers whose stream resynchronises (:meth:`Driver._watch_sync`)
RESYNC_OPTIONS = {"resync_timeout": Option("float", low=0.0, low_open=True)}


def split_common(opts: dict) -> dict:
    """Take the keywords of :class:`Driver` (``wait``, ``retry_for``, ``start_wait``) out of parsed options."""
    return {k: opts.pop(k) for k in ("wait", "retry_for", "start_wait") if k in opts}
