"""The live loop's sink for the viewer: :class:`ViewerSink` (re-exported by :mod:`twin.viewer`)."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, TextIO

import numpy as np

from twin.frames import Frame, Shape
from twin.live import LatestUsable
from twin.viewer.client import ViewerError

if TYPE_CHECKING:  # pragma: no cover
    from twin.live import LiveStatus
    from twin.viewer.view import Viewer

__all__ = ["ViewerSink"]


class ViewerSink:
    """A :class:`twin.live.LiveLoop` sink drawing the latest usable shape of each batch, at most ``rate`` Hz.

    The frame's truth is drawn when the source carries one, and the interrogator's own shape when the frame
    carries one (:attr:`Frame.vendor`); the measured arrival rate, the source's rate, frames and lost frames go
    to the overlay. A frame dropped by the rate limit is kept and drawn at the next heartbeat. A stale stream
    turns the catheter grey; at the end of the run the last shape is drawn and the overlay says ``ENDED`` with
    the final frame count (the terminal's) and the run's mean arrival rate.
    Nothing raises out of the sink (the loop would drop it): errors are counted in ``errors`` (the first one
    reported on ``stream``), and a viewer whose server is gone is left alone.

    Parameters
    ----------
    viewer : Viewer
    rate : float
        Most frames drawn per second, Hz.
    close_viewer : bool
        Close the viewer when the loop closes the sink (False for ``--keep-open``).
    stream : text file
        Where the first error is reported (stderr).
    uncertainty : twin.uncertainty.Uncertainty, optional
        Draw the confidence envelope: the shape drawn (one per heartbeat, not every frame) gets its uncertainty
        propagated when it does not carry one already.
    """

    def __init__(self, viewer: Viewer, rate: float = 30.0, *, close_viewer: bool = True,
                 stream: TextIO | None = None, uncertainty=None):
        self.viewer = viewer
        self.uncertainty = uncertainty
        self.latest = LatestUsable(rate, "ViewerSink")
        self.close_viewer = close_viewer
        self.stream = stream
        self.errors = 0
        self.last_error: str | None = None
        self.frames_received = 0
        self.frames_shown = 0
        self._gave_up = False

    def __call__(self, frames: Frame, shapes: Shape | None, status: LiveStatus) -> None:
        try:
            self._handle(frames, shapes, status)
        except Exception as exc:  # the viewer must never end the live loop
            self.errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            if self.errors == 1:
                print(f"twin live: viewer: {self.last_error} (further errors counted, not shown)",
                      file=self.stream or sys.stderr)

    def _handle(self, frames, shapes, status) -> None:
        self.frames_received += len(frames)
        self.latest.offer(frames, shapes, status.flags)
        v = self.viewer
        if v.closed:
            return
        ended = status.state == "ended"
        if v.broken:  # said once (counted as an error), then left alone
            if not self._gave_up:
                self._gave_up = True
                raise ViewerError(v.broken)
            return
        taken = self.latest.take(force=ended)  # the run's last shape is drawn whatever the rate limit says
        if taken is not None:
            frame, shape = taken
            if self.uncertainty is not None and shape.covariance is None:
                shape = self.uncertainty.propagate(shape, frame)
            v.show(shape, frame.truth, force=True, vendor=frame.vendor)
            self.frames_shown += 1
        # what arrived, measured (over the last 2 s; at the end, over the run, as the terminal's summary says),
        # beside the source's own rate: a source behind real time shows as such
        arrival = status.frames / status.elapsed if ended and status.elapsed > 0 else status.arrival_hz
        v.info.update(arrival_hz=arrival, rate_hz=status.rate_hz, lost=status.lost_samples, frames=status.frames)
        detail = ""
        if status.state == "stale" and np.isfinite(status.last_valid_age):
            detail = f"no data for {status.last_valid_age:.0f} s"
        elif ended:
            detail = f"{status.frames} frames in {status.elapsed:.1f} s"
        v.set_state(status.state, detail)

    def close(self) -> None:
        if self.close_viewer:
            self.viewer.close()
