"""The Hyperion peak stream (port 51972): :class:`PeakStreamDecoder`, framing with resynchronisation.

Every frame on the stream is a response (``<BBHI`` header: status 0, type, message length, content length) whose
content is peak data (``<HHIQII`` peak header, the channels' int16 peak counts, float64 wavelengths);
:mod:`twin.io.hyperion.codec` and docs/protocols.md §3. The stream has no sync marker, but a frame's start is
tightly constrained, so bad bytes (garbage, a frame cut short by the sender) need not cost the connection:

- **Checked as it arrives.** A frame is checked field by field as its bytes come in: status 0, content length
  within ``max_content``, the message ASCII, then the peak content by the codec's own rules, judged on the bytes
  received so far (:func:`~twin.io.hyperion.codec.peak_content_fault`: the peak header's length 24 + 2·channels
  within the content, reserved 0 and nanoseconds below 1e9, every peak count ≥ 0 and ≤ ``n_gratings`` when given,
  the content length equal to the peak header plus 8 bytes a peak; :func:`~twin.io.hyperion.codec.wavelength_fault`:
  each wavelength received within ``WAVELENGTH_RANGE``). A frame with a good response header is refused exactly when
  :func:`~twin.io.hyperion.codec.decode_peaks` refuses its content, with the same error; error offsets count from
  the start of the stream. A corrupt header announcing 16 MiB is refuted by the bytes that follow it, not waited
  for; a frame cut short is refuted when the next frame's header lands where its wavelengths should be (its bytes
  read as float64 are denormals).
- **Hunt.** On a bad byte the decoder counts one framing error (one per loss of sync, however long the garbage)
  and hunts from the byte after the refuted frame's start: a candidate start has status 0, an empty message (the
  stream's frames carry none), a content length within bounds that leaves room for whole peaks, and a peak header
  that passes the codec's rules (:func:`~twin.io.hyperion.codec.peak_header_valid`) — one vectorised pass over the
  buffer, then each candidate checked as above. The first
  candidate that decodes whole puts the decoder back in sync; the frame is delivered. Skipped bytes are counted
  in ``bytes_discarded``.
- **Bounded.** In sync the buffer holds at most one frame (8 + 65535 + ``max_content`` bytes) and one feed's bytes;
  hunting, it keeps only the last 31 bytes (a candidate's fixed fields not yet complete). Each byte is scanned a
  bounded number of times per candidate that covers it, and candidates are refuted on their first bad field.

A connection that ends inside a frame is one framing error (:meth:`PeakStreamDecoder.finish`), as on ILLumiSense.
"""

from __future__ import annotations

import struct
from collections import deque

import numpy as np

from twin.frames import Frame
from twin.io.errors import FramingError, OversizeFrameError
from twin.io.hyperion.codec import (
    DEFAULT_MAX_CONTENT,
    HEADER_SIZE,
    PEAK_HEADER_SIZE,
    PROTOCOL,
    _header_and_counts,
    _peaks_frame,
    peak_content_fault,
    peak_header_valid,
    wavelength_fault,
)

__all__ = ["PeakStreamDecoder"]

_FIXED = HEADER_SIZE + PEAK_HEADER_SIZE  # 32: the response header and the peak header, a frame's fixed fields
_RESPONSE = struct.Struct("<BBHI")
_LENGTH = struct.Struct("<H")  # the peak header's first field: its length


def _u(a: np.ndarray, k: int, n: int, width: int) -> np.ndarray:
    """Little-endian unsigned integers of ``width`` (≤ 4) bytes at offsets k … k + n − 1 of the byte array ``a``,
    as int64."""
    out = np.zeros(n, np.int64)
    for b in range(width):
        out |= a[k + b : k + b + n].astype(np.int64) << (8 * b)
    return out


class PeakStreamDecoder:
    """Split the peak stream into frames, resynchronising after bad bytes (module docstring).

    Parameters
    ----------
    max_content : int
        Largest accepted content, bytes.
    n_gratings : int, optional
        Rows of each frame (:func:`~twin.io.hyperion.codec.decode_peaks`); a channel reporting more peaks is bad.
    max_channels : int
        Most channels a peak header may announce.

    Attributes
    ----------
    framing_errors : int
        Losses of sync (each counted once, however many bytes were skipped), and connections that ended inside a
        frame.
    bytes_discarded : int
        Bytes skipped while hunting, or left over from a frame the connection cut short.
    last_error : FramingError or None
        What broke the sync last, with its offset in the stream.
    in_sync : bool
        False between a framing error and the next good frame.
    """

    def __init__(self, *, max_content: int = DEFAULT_MAX_CONTENT, n_gratings: int | None = None,
                 max_channels: int = 128) -> None:
        self.max_content = int(max_content)
        self.n_gratings = n_gratings
        self.max_channels = int(max_channels)
        self.framing_errors = 0
        self.bytes_discarded = 0
        self.last_error: FramingError | None = None
        self.in_sync = True
        self._buf = bytearray()
        self._base = 0  # stream offset of _buf[0]
        self._checked = (-1, 0)  # (frame start, wavelength bytes already found in range): each checked once

    @property
    def pending(self) -> int:
        """Bytes received but not yet delivered or discarded."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        """Consume stream bytes; return the frames completed by them, in order."""
        buf = self._buf
        buf += data
        out: list[Frame] = []
        pos = 0
        cands: deque[int] = deque()
        while pos < len(buf):
            if not self.in_sync:
                if not cands:
                    cands = deque(self._candidates(pos))
                    if not cands:  # keep only what may still be the start of a candidate
                        keep = max(pos, len(buf) - (_FIXED - 1))
                        self.bytes_discarded += keep - pos
                        pos = keep
                        break
                p = cands.popleft()
                self.bytes_discarded += p - pos
                pos = p
            end, err = self._check(pos)
            if err is not None:
                if self.in_sync:
                    self.framing_errors += 1
                    self.last_error = err
                    self.in_sync = False
                    cands.clear()
                self.bytes_discarded += 1
                pos += 1
                continue
            if end is None:  # a frame (or candidate) waiting for the rest of its bytes
                break
            out.append(self._decode(pos, end))
            self.in_sync = True
            cands.clear()
            pos = end
        del buf[:pos]
        self._base += pos
        return out

    def finish(self) -> None:
        """The connection ended: bytes of an unfinished frame are one framing error (none when the decoder was
        already hunting: that loss was counted); the decoder starts the next connection empty and in sync."""
        left = len(self._buf)
        if left and self.in_sync:
            self.framing_errors += 1
            self.last_error = FramingError(f"stream ended inside a frame ({left} bytes pending)",
                                           offset=self._base + left, expected="a complete frame", protocol=PROTOCOL)
        self.bytes_discarded += left
        self._base += left
        self._buf.clear()
        self.in_sync = True
        self._checked = (-1, 0)

    # ------------------------------------------------------------------------------------------------ internals
    def _error(self, cls, what: str, offset: int, expected: str) -> tuple[None, FramingError]:
        return None, cls(what, offset=self._base + offset, expected=expected, protocol=PROTOCOL)

    def _check(self, p: int) -> tuple[int | None, FramingError | None]:
        """Check the frame starting at ``p`` on the bytes received: (end, None) when complete and good, (None,
        None) when good so far but incomplete, (None, error) when refuted."""
        buf = self._buf
        have = len(buf) - p
        if have < HEADER_SIZE:
            return None, None
        status, _, n_msg, n_content = _RESPONSE.unpack_from(buf, p)
        if status != 0:
            return self._error(FramingError, f"stream frame with status {status}", p, "status 0")
        if n_content > self.max_content:
            return self._error(OversizeFrameError, f"content length {n_content}", p + 4,
                               f"at most {self.max_content} bytes")
        c0 = p + HEADER_SIZE + n_msg  # where the content starts
        end = c0 + n_content
        if not buf[p + HEADER_SIZE : min(c0, len(buf))].isascii():
            return self._error(FramingError, "message is not ASCII", p + HEADER_SIZE, "ASCII text")
        # the peak header and counts: the codec's rules, judged on the bytes received so far
        err = peak_content_fault(buf, c0, n_content, max_channels=self.max_channels, n_gratings=self.n_gratings,
                                 origin=self._base)
        if err is not None:
            return None, err
        if len(buf) < c0 + PEAK_HEADER_SIZE:
            return None, None
        hl = _LENGTH.unpack_from(buf, c0)[0]
        if len(buf) < c0 + hl:  # the counts not all here yet
            return None, None
        # the wavelengths received so far, each checked once however the frame's bytes are split into feeds
        w0 = c0 + hl
        done = self._checked[1] if self._checked[0] == self._base + p else 0
        upto = min(len(buf), end) - w0
        upto -= upto % 8
        if upto > done:
            err = wavelength_fault(buf, w0 + done, (upto - done) // 8, first=done // 8, origin=self._base)
            if err is not None:
                return None, err
            self._checked = (self._base + p, upto)
        return (end if len(buf) >= end else None), None

    def _decode(self, p: int, end: int) -> Frame:
        # _check has judged the whole frame by the codec's rules (header, counts, every wavelength): the content is
        # built into a Frame without judging it a second time
        n_msg = _RESPONSE.unpack_from(self._buf, p)[2]
        self._checked = (-1, 0)
        content = bytes(self._buf[p + HEADER_SIZE + n_msg : end])
        return _peaks_frame(content, *_header_and_counts(content), self.n_gratings)

    def _candidates(self, pos: int) -> list[int]:
        """Offsets ≥ ``pos`` whose fixed fields could start a stream frame (module docstring), in order; one
        vectorised pass (a flood of zero bytes costs no Python step a byte)."""
        a = np.frombuffer(self._buf, np.uint8)[pos:]
        n = a.size - (_FIXED - 1)
        if n <= 0:
            return []
        n_content, hl = _u(a, 4, n, 4), _u(a, 8, n, 2)
        rest = n_content - hl
        # the response header's fields (status 0, no message, content within bounds), the codec's peak header
        # rules, and room for a whole number of peaks after the header
        good = ((a[:n] == 0) & (a[2 : 2 + n] == 0) & (a[3 : 3 + n] == 0) & (n_content <= self.max_content)
                & peak_header_valid(hl, _u(a, 12, n, 4), _u(a, 28, n, 4), n_content, max_channels=self.max_channels)
                & (rest % 8 == 0))
        return (np.flatnonzero(good) + pos).tolist()
