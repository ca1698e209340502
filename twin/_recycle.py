"""Large output arrays on recycled memory: a buffer is handed out again once no array refers to it any more.

A fresh array of hundreds of MB (the positions and frames of a batch of 10⁴ frames) costs the kernel's zeroing of
every page on first touch — about a tenth of a batch's reconstruction time here. A caller that
reconstructs batch after batch and lets each result go (an offline pass over a recording, the bench) gets the
memory of an earlier result back instead. Reuse is safe by construction: a buffer is reused only when CPython's
reference count says that the pool alone holds it (every numpy view refers to its base buffer), and the choice is
made under a lock, so two threads never get one buffer. At most :data:`KEEP` buffers and :data:`MAX_HELD_BYTES` are held
(per reconstructor: the memory goes with it); small arrays are
left to ``np.empty`` (malloc reuses their memory anyway).
"""

from __future__ import annotations

import sys
import threading

import numpy as np

__all__ = ["KEEP", "MAX_HELD_BYTES", "MIN_BYTES", "Recycler"]

#: arrays below this size come from ``np.empty`` (malloc keeps and reuses such blocks itself)
MIN_BYTES = 1 << 22
#: buffers a :class:`Recycler` holds at most
KEEP = 4
#: bytes a :class:`Recycler` holds at most, in use or not: memory let go beyond this goes back to the system
MAX_HELD_BYTES = 1 << 30


def _alone() -> int:
    """What ``sys.getrefcount(bufs[i])`` says of an array that only the list ``bufs`` holds (2 on CPython 3.11:
    the list and the argument), measured the same way, so that an interpreter that counts otherwise does not
    make a buffer in use look free."""
    bufs = [np.empty(1)]
    return sys.getrefcount(bufs[0])


_ALONE = _alone()


class Recycler:
    """``empty(shape)``: a float64 array of ``shape``, on a held buffer no array uses any more, else new."""

    def __init__(self) -> None:
        self._buffers: list[np.ndarray] = []
        self._lock = threading.Lock()

    def empty(self, shape: tuple[int, ...]) -> np.ndarray:
        n = 1
        for d in shape:
            n *= d
        if 8 * n < MIN_BYTES:
            return np.empty(shape)
        bufs = self._buffers
        with self._lock:
            free = [i for i in range(len(bufs)) if sys.getrefcount(bufs[i]) == _ALONE]
            for i in free:
                if bufs[i].size >= n:
                    return bufs[i][:n].reshape(shape)  # the view refers to the buffer from here on: not alone
            out = np.empty(n)
            # make room, smallest unused first: at most KEEP buffers and MAX_HELD_BYTES (a large batch's memory
            # is not kept for the life of the process once the pool is full of it)
            free.sort(key=lambda i: bufs[i].size)
            drop: list[int] = []
            held = sum(b.nbytes for b in bufs)
            while free and (len(bufs) - len(drop) >= KEEP or held + out.nbytes > MAX_HELD_BYTES):
                i = free.pop(0)
                drop.append(i)
                held -= bufs[i].nbytes
            for i in sorted(drop, reverse=True):
                del bufs[i]
            if len(bufs) < KEEP and held + out.nbytes <= MAX_HELD_BYTES:
                bufs.append(out)
            return out.reshape(shape)
