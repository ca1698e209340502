"""What every recording reader shares (:class:`twin.io.record.RecordingReader` for HDF5 recordings and logs,
:class:`twin.io.rosbag.McapRecording`): its state as a file (complete, damaged), spans of rows, consecutive
batches, and use as a context manager. A reader sets ``_n`` (frames readable), ``_closed_cleanly`` and
``damage`` and provides ``frames(start, stop, truth=…)`` and ``close()``.
"""

from __future__ import annotations

from collections.abc import Iterator

from twin.frames import Frame

__all__ = ["ReaderBase"]


class ReaderBase:
    """The part of the recording-reader interface that is the same for every format (module docstring)."""

    _n: int
    _closed_cleanly: bool
    damage: list[str]
    skipped_lines: int = 0  #: lines of a log file skipped (its first few named in ``errors``)

    @property
    def complete(self) -> bool:
        """The writer closed the file cleanly and nothing is damaged."""
        return self._closed_cleanly and not self.damage

    @property
    def damaged(self) -> bool:
        return bool(self.damage)

    def __len__(self) -> int:
        return self._n

    def _span(self, start: int, stop: int | None) -> tuple[int, int]:
        """Rows ``start:stop`` clipped to the readable frames."""
        stop = self._n if stop is None else min(stop, self._n)
        return max(0, min(start, stop)), stop

    def frames(self, start: int = 0, stop: int | None = None, *, truth: bool = True) -> Frame:
        raise NotImplementedError

    def chunks(self, size: int = 1024, *, truth: bool = True) -> Iterator[tuple[int, Frame]]:
        """(start, batch) for consecutive slices of ``size`` frames (ending early at damage found while reading)."""
        start = 0
        while start < self._n:
            batch = self.frames(start, start + size, truth=truth)
            if len(batch) == 0:
                return
            yield start, batch
            start += len(batch)

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
