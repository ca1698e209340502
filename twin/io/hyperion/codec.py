"""Luna / Micron Optics Hyperion (si155, si255, x55) TCP: requests, responses, peaks (docs/protocols.md §3).

Ports: 51971 commands (request → one response), 51972 peak stream (the instrument pushes one frame per
acquisition). All integers little-endian.

- Request: ``<BBHI`` header (options u8, 0 u8, command length u16, argument length u32), the ASCII command
  (``#GetPeaks``), the ASCII argument (several arguments space-separated).
- Response: ``<BBHI`` header (status u8, 0 = success; response type u8; message length u16; content length
  u32), the ASCII message, the binary content.
- Peak content: ``<HHIQII`` header (header length u16 = 24 + 2·channels, version u16, reserved u32, serial
  number u64, timestamp seconds u32, timestamp nanoseconds u32), channels × int16 peak counts, then the
  float64 peak wavelengths (nm), channel 1 first.

Decisions where docs/protocols.md is silent:

- **Stream framing (port 51972)**: every pushed frame is a complete *response* (the same 8-byte header, status
  0, an empty message, the peak content). This is how Luna's public Python client reads the stream (it
  unpacks the same ``BBHI`` header, then reads ``content length`` bytes). The simulator sends an empty
  message; the decoder skips a non-empty one.
- **Channels ↔ cores**: channel ``k + 1`` is core ``k``. The instrument reports only the peaks it found, so a
  channel with fewer peaks than the others is NaN-padded at the end (status MISSING) up to the largest count,
  or up to ``n_gratings`` when the caller gives it; which grating a peak belongs to is decided downstream by
  wavelength, not here. Encoding drops NaN peaks for the same reason: a Frame with a gap in the middle of a
  core comes back compacted, which is what a real instrument would send.
- **Serial number** in the peak header counts acquisitions (Luna's stream example asserts it increments by
  one), so it carries :attr:`Frame.sequence` (a u64: one of 2**63 or more is taken as 2**63 − 1, so that frames
  stack as int64, :func:`twin.io.sequence.clamp`); timestamp = seconds + nanoseconds·1e-9.
- **Version** 1 in the peak header (only echoed). **Response type** 0 (only echoed).
- **A frame is checked whole before any of it is used** (:func:`decode_peaks`): header length against the
  content, the peak counts against the bytes that follow, and every wavelength finite and within
  :data:`WAVELENGTH_RANGE` (200–3000 nm, the Bragg wavelengths a fibre model accepts; Luna's instruments sweep
  1460–1620 nm). An instrument reports only peaks it found, so a value outside that range is not a bad peak but
  bytes that are not a wavelength: the frame is refused as a framing error. That is also how lost framing shows:
  half a frame followed by a good one makes the decoder read the good frame's headers as wavelengths (denormals
  such as 3.9e-305 nm).
- The reserved byte of both headers must be 0 and a timestamp's nanoseconds must be below 1e9: on a binary
  stream without a sync marker those checks and the wavelength range are the only way to notice lost framing.
  The peak content's rules are written once here (:func:`peak_content_fault` over a table of the peak header's
  rules, :func:`peak_header_valid` for many candidate headers at once, :func:`wavelength_fault`), and
  :func:`decode_peaks` and the stream decoder both apply them: one meaning, one error, on either path.
- A connection that closes inside a frame is one framing error (:meth:`ResponseDecoder.finish`,
  :meth:`twin.io.hyperion.stream.PeakStreamDecoder.finish`), as on the ILLumiSense stream: one meaning per
  counter across drivers.

**Resynchronisation**: the peak stream's decoder resynchronises after bad bytes, on the constraints of a frame's
fixed fields (:mod:`twin.io.hyperion.stream`). The command port's decoders (one request, one response) attempt
none: they count the first bad header or content, set ``failed`` and raise
:class:`~twin.io.errors.FramingError` — at once when the call completed nothing, otherwise from the next call,
after delivering the messages completed before the bad bytes — and refuse further data until
:meth:`ResponseDecoder.reset`: the caller closes the connection.

Why one module of this size: the codec holds both directions of one protocol (the simulator's server encodes
with it, the driver decodes), so that the two cannot drift apart.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from twin.frames import Frame, PeakStatus
from twin.io.errors import FramingError, OversizeFrameError, TruncatedFrameError
from twin.io.sequence import clamp

__all__ = [
    "COMMAND_PORT",
    "STREAM_PEAKS_PORT",
    "InstrumentState",
    "PeakHeader",
    "Request",
    "RequestDecoder",
    "Response",
    "ResponseDecoder",
    "decode_ascii",
    "decode_i32_array",
    "decode_peaks",
    "decode_peaks_header",
    "decode_request",
    "decode_response",
    "decode_u8",
    "decode_u32",
    "encode_peaks",
    "encode_request",
    "encode_response",
    "encode_stream_frame",
    "peak_content_fault",
    "peak_header_valid",
    "respond",
    "wavelength_fault",
]

PROTOCOL = "hyperion"
COMMAND_PORT = 51971
STREAM_PEAKS_PORT = 51972
_HEADER = struct.Struct("<BBHI")
_PEAK_HEADER = struct.Struct("<HHIQII")
HEADER_SIZE = _HEADER.size  # 8
PEAK_HEADER_SIZE = _PEAK_HEADER.size  # 24
DEFAULT_MAX_ARGUMENT = 1 << 20
DEFAULT_MAX_COMMAND = 0xFFFF  # the u16 field's own limit
DEFAULT_MAX_CONTENT = 1 << 24  # a full-spectrum response of 16 channels × 40k points is ~1.3 MB; ample room
#: wavelengths a peak may have, nm (the range :class:`twin.fiber.FiberModel` accepts for λ0)
WAVELENGTH_RANGE = (200.0, 3000.0)
_MISSING = np.uint8(PeakStatus.MISSING)


def _ascii(data: bytes, what: str, offset: int) -> str:
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError as exc:
        raise FramingError(
            f"{what} is not ASCII", offset=offset + exc.start, expected="ASCII text", protocol=PROTOCOL
        ) from None
    return text


# --------------------------------------------------------------------------------------------------- requests


@dataclass(frozen=True)
class Request:
    """A command sent to port 51971.

    Attributes
    ----------
    command : str
        E.g. ``"#GetPeaks"``.
    argument : str
        ASCII argument string ("" for none; several arguments space-separated).
    options : int
        Request option flags, u8 (echoed, not interpreted).
    """

    command: str
    argument: str = ""
    options: int = 0


def encode_request(command: str, argument: str = "", *, options: int = 0) -> bytes:
    """Request bytes: ``<BBHI`` header, command, argument.

    ``encode_request("#GetPeaks")`` is ``00 00 09 00 00 00 00 00`` + ``#GetPeaks``.
    """
    cmd, arg = command.encode("ascii"), argument.encode("ascii")
    if not 0 <= options <= 255 or len(cmd) > 0xFFFF or len(arg) > 0xFFFFFFFF:
        raise ValueError("request: options must fit u8, command u16 and argument u32 lengths")
    return _HEADER.pack(options, 0, len(cmd), len(arg)) + cmd + arg


def _request_header(data: bytes, offset: int, max_argument: int,
                    max_command: int = DEFAULT_MAX_COMMAND) -> tuple[int, int, int]:
    options, zero, n_cmd, n_arg = _HEADER.unpack_from(data, 0)
    if zero != 0:
        raise FramingError(
            f"reserved request byte is {zero}", offset=offset + 1, expected="0", protocol=PROTOCOL
        )
    if n_cmd == 0:
        raise FramingError(
            "request with an empty command",
            offset=offset + 2,
            expected="a command length > 0",
            protocol=PROTOCOL,
        )
    if n_cmd > max_command:
        raise OversizeFrameError(
            f"command length {n_cmd}",
            offset=offset + 2,
            expected=f"at most {max_command} bytes",
            protocol=PROTOCOL,
        )
    if n_arg > max_argument:
        raise OversizeFrameError(
            f"argument length {n_arg}",
            offset=offset + 4,
            expected=f"at most {max_argument} bytes",
            protocol=PROTOCOL,
        )
    return options, n_cmd, n_arg


def decode_request(data: bytes, *, max_argument: int = DEFAULT_MAX_ARGUMENT,
                   max_command: int = DEFAULT_MAX_COMMAND) -> Request:
    """Decode exactly one request; FramingError unless ``data`` is exactly one well-formed request."""
    data = bytes(data)
    if len(data) < HEADER_SIZE:
        raise TruncatedFrameError(
            f"request of {len(data)} bytes", offset=len(data), expected="an 8-byte header", protocol=PROTOCOL
        )
    options, n_cmd, n_arg = _request_header(data, 0, max_argument, max_command)
    total = HEADER_SIZE + n_cmd + n_arg
    if len(data) != total:
        cls = TruncatedFrameError if len(data) < total else OversizeFrameError
        raise cls(
            f"request of {len(data)} bytes",
            offset=min(len(data), total),
            expected=f"exactly {total} bytes as its header says",
            protocol=PROTOCOL,
        )
    cmd = _ascii(data[HEADER_SIZE : HEADER_SIZE + n_cmd], "command", HEADER_SIZE)
    arg = _ascii(data[HEADER_SIZE + n_cmd :], "argument", HEADER_SIZE + n_cmd)
    return Request(cmd, arg, options)


# -------------------------------------------------------------------------------------------------- responses


@dataclass(frozen=True)
class Response:
    """A response from port 51971, or one frame of the peak stream on 51972.

    Attributes
    ----------
    status : int
        0 = success; otherwise ``message`` says what failed.
    response_type : int
        u8, echoed.
    message : str
        Human-readable ASCII message ("" in stream frames).
    content : bytes
        Binary content.
    """

    status: int
    response_type: int
    message: str
    content: bytes

    @property
    def ok(self) -> bool:
        return self.status == 0


def encode_response(
    content: bytes = b"", message: str = "", *, status: int = 0, response_type: int = 0
) -> bytes:
    """Response bytes: ``<BBHI`` header, ASCII message, content."""
    msg = message.encode("ascii")
    if (
        not (0 <= status <= 255 and 0 <= response_type <= 255)
        or len(msg) > 0xFFFF
        or len(content) > 0xFFFFFFFF
    ):
        raise ValueError("response: status/type must fit u8, message u16 and content u32 lengths")
    return _HEADER.pack(status, response_type, len(msg), len(content)) + msg + bytes(content)


def encode_stream_frame(frame: Frame, **peak_kw) -> bytes:
    """One frame of the 51972 peak stream: a success response with an empty message and the peak content.

    Keyword arguments go to :func:`encode_peaks`.
    """
    return encode_response(encode_peaks(frame, **peak_kw))


def _response_header(data: bytes, offset: int, max_content: int) -> tuple[int, int, int, int]:
    status, rtype, n_msg, n_content = _HEADER.unpack_from(data, 0)
    if n_content > max_content:
        raise OversizeFrameError(
            f"content length {n_content}",
            offset=offset + 4,
            expected=f"at most {max_content} bytes",
            protocol=PROTOCOL,
        )
    return status, rtype, n_msg, n_content


def decode_response(data: bytes, *, max_content: int = DEFAULT_MAX_CONTENT) -> Response:
    """Decode exactly one response; FramingError unless ``data`` is exactly one well-formed response."""
    data = bytes(data)
    if len(data) < HEADER_SIZE:
        raise TruncatedFrameError(
            f"response of {len(data)} bytes", offset=len(data), expected="an 8-byte header", protocol=PROTOCOL
        )
    status, rtype, n_msg, n_content = _response_header(data, 0, max_content)
    total = HEADER_SIZE + n_msg + n_content
    if len(data) != total:
        cls = TruncatedFrameError if len(data) < total else OversizeFrameError
        raise cls(
            f"response of {len(data)} bytes",
            offset=min(len(data), total),
            expected=f"exactly {total} bytes as its header says",
            protocol=PROTOCOL,
        )
    msg = _ascii(data[HEADER_SIZE : HEADER_SIZE + n_msg], "message", HEADER_SIZE)
    return Response(status, rtype, msg, data[HEADER_SIZE + n_msg :])


class _Incremental:
    """Shared machinery of the command port's two decoders (length-prefixed by an 8-byte header, no resync)."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._base = 0
        self.framing_errors = 0
        self.last_error: FramingError | None = None
        self.failed = False
        self._deferred: FramingError | None = None

    @property
    def pending(self) -> int:
        """Bytes received but not yet part of a complete message."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes and the failed state (after reconnecting)."""
        self._buf.clear()
        self._base = 0
        self.failed = False
        self._deferred = None

    def _feed(self, data: bytes, body_length, decode) -> list:
        """Split the buffered stream into complete messages: ``body_length(header, stream offset)`` gives the
        bytes after the 8-byte header (raising FramingError on a bad header), ``decode(message)`` the object."""
        self._check_usable()
        buf = self._buf
        buf += data
        out: list = []
        pos = 0
        try:
            while len(buf) - pos >= HEADER_SIZE:
                end = pos + HEADER_SIZE + body_length(bytes(buf[pos : pos + HEADER_SIZE]), self._base + pos)
                if len(buf) < end:
                    break
                try:
                    out.append(decode(bytes(buf[pos:end])))
                except FramingError as exc:
                    off = None if exc.offset is None else self._base + pos + exc.offset
                    raise type(exc)(exc.what, offset=off, expected=exc.expected, protocol=PROTOCOL) from None
                pos = end
        except FramingError as exc:
            self._fail(exc)
            return self._finish(out)
        del buf[:pos]
        self._base += pos
        return out

    def finish(self) -> None:
        """Declare the end of the stream (the connection closed): bytes of an incomplete message left over are
        one framing error (nothing is counted when the decoder had already failed or holds nothing)."""
        left = len(self._buf)
        if left and not self.failed:
            self._fail(
                TruncatedFrameError(
                    f"stream ended inside a message ({left} bytes pending)",
                    offset=self._base + left,
                    expected="a complete message",
                    protocol=PROTOCOL,
                )
            )
            self._deferred = None  # nothing more will be fed; the count is what remains
        self._base += left
        self._buf.clear()

    def _fail(self, err: FramingError) -> None:
        # one loss of sync is one error: a frame found bad after the splitter already failed further on in the
        # same bytes (it comes first in the stream) replaces that error instead of adding one
        if not self.failed:
            self.framing_errors += 1
        self.last_error = err
        self.failed = True
        self._deferred = err
        self._buf.clear()

    def _check_usable(self) -> None:
        err, self._deferred = self._deferred, None
        if err is not None:
            raise err
        if self.failed:
            raise FramingError(
                "stream decoder is out of sync after an earlier error",
                offset=self._base,
                expected="reset() after reconnecting",
                protocol=PROTOCOL,
            )

    def _finish(self, out: list) -> list:
        # messages completed before the bad bytes are delivered; the error is raised now when there are
        # none, else by the next call (``failed`` is already True either way)
        if self._deferred is not None and not out:
            self._check_usable()
        return out


class RequestDecoder(_Incremental):
    """Server side of port 51971: split the incoming bytes into :class:`Request` objects.

    Raises :class:`FramingError` (and stays failed until :meth:`reset`) on a bad header: close the connection.
    A header announcing more than ``max_command`` / ``max_argument`` bytes is refused before they are buffered,
    so a partial request never holds more than 8 + ``max_command`` + ``max_argument`` bytes.
    """

    def __init__(self, *, max_argument: int = DEFAULT_MAX_ARGUMENT, max_command: int = DEFAULT_MAX_COMMAND) -> None:
        super().__init__()
        self.max_argument = max_argument
        self.max_command = max_command

    def feed(self, data: bytes) -> list[Request]:
        """Consume bytes; return the complete requests among them."""
        return self._feed(
            data,
            lambda head, offset: sum(_request_header(head, offset, self.max_argument, self.max_command)[1:]),
            lambda message: decode_request(message, max_argument=self.max_argument, max_command=self.max_command),
        )


class ResponseDecoder(_Incremental):
    """Client side of port 51971: split the incoming bytes into :class:`Response` objects (the peak stream on
    51972 has its own, resynchronising decoder: :class:`twin.io.hyperion.stream.PeakStreamDecoder`).

    Raises :class:`FramingError` (and stays failed until :meth:`reset`) on a bad header: reconnect.

    Parameters
    ----------
    max_content : int
        Largest accepted content, bytes (refused from the header, before anything is allocated).
    """

    def __init__(self, *, max_content: int = DEFAULT_MAX_CONTENT) -> None:
        super().__init__()
        self.max_content = max_content

    def feed(self, data: bytes) -> list[Response]:
        """Consume bytes; return the complete responses among them."""
        return self._feed(
            data,
            lambda head, offset: sum(_response_header(head, offset, self.max_content)[2:]),
            lambda message: decode_response(message, max_content=self.max_content),
        )


# ---------------------------------------------------------------------------------------------- peak content


@dataclass(frozen=True)
class PeakHeader:
    """The 24-byte header of peak content.

    Attributes
    ----------
    header_length : int
        24 + 2·channels, bytes (the offset of the wavelengths).
    version : int
    reserved : int
    serial_number : int
        Acquisition counter (→ :attr:`Frame.sequence`).
    timestamp_s, timestamp_ns : int
        Acquisition time, whole seconds and nanoseconds.
    """

    header_length: int
    version: int
    reserved: int
    serial_number: int
    timestamp_s: int
    timestamp_ns: int

    @property
    def n_channels(self) -> int:
        return (self.header_length - PEAK_HEADER_SIZE) // 2

    @property
    def timestamp(self) -> float:
        """Seconds, float."""
        return self.timestamp_s + self.timestamp_ns * 1e-9


class _HeaderFields(NamedTuple):
    """What the peak header's rules judge: ints for one header, int64 arrays for every candidate start of a
    buffer (the stream decoder's hunt)."""

    header_length: Any
    reserved: Any
    timestamp_ns: Any
    content_length: Any  # bytes of the peak content, header included (the response's content length)
    max_channels: int


@dataclass(frozen=True)
class _HeaderRule:
    """One validity rule of the peak header: the field it judges (an attribute of :class:`_HeaderFields`), the
    field as errors name it, its byte offset in the peak content, the test (elementwise), and what a valid header
    holds there (a format string over the fields)."""

    name: str
    label: str
    offset: int
    holds: Callable[[_HeaderFields], Any]
    expected: str
    error: type[FramingError] = FramingError


#: The peak header's validity rules, in the order they are checked: the one definition that
#: :func:`decode_peaks_header`, the stream decoder's field-by-field check and its vectorised hunt
#: (:mod:`twin.io.hyperion.stream`) all apply. With no sync marker on the stream, these fields are how lost
#: framing shows (docs/protocols.md §3.4).
_PEAK_HEADER_RULES = (
    _HeaderRule("header_length", "peak header length", 0,
                lambda f: (f.header_length >= PEAK_HEADER_SIZE) & (f.header_length % 2 == 0)
                & (f.header_length <= PEAK_HEADER_SIZE + 2 * f.max_channels),
                "24 + 2·channels with at most {max_channels} channels"),
    _HeaderRule("header_length", "peak header length", 0, lambda f: f.header_length <= f.content_length,
                "at most the {content_length}-byte content", TruncatedFrameError),
    _HeaderRule("reserved", "peak header reserved field", 4, lambda f: f.reserved == 0, "0"),
    _HeaderRule("timestamp_ns", "timestamp nanoseconds", 20, lambda f: f.timestamp_ns < 1_000_000_000,
                "below 1e9"),
)


def peak_header_valid(header_length: int | np.ndarray, reserved: int | np.ndarray, timestamp_ns: int | np.ndarray,
                      content_length: int | np.ndarray, *, max_channels: int = 128) -> bool | np.ndarray:
    """Whether peak headers pass every rule of :data:`_PEAK_HEADER_RULES`, elementwise.

    Parameters
    ----------
    header_length, reserved, timestamp_ns : int or ndarray of int64
        The header's fields (arrays: one element per candidate header).
    content_length : int or ndarray of int64
        Bytes of the peak content the header starts, header included.
    max_channels : int
        Most channels a header may announce.

    Returns
    -------
    bool or ndarray of bool
    """
    f = _HeaderFields(header_length, reserved, timestamp_ns, content_length, max_channels)
    ok = True
    for rule in _PEAK_HEADER_RULES:
        ok = ok & rule.holds(f)
    return ok


def peak_content_fault(data: bytes | bytearray, start: int = 0, content_length: int | None = None, *,
                       max_channels: int = 128, n_gratings: int | None = None,
                       origin: int = 0) -> FramingError | None:
    """The first rule that the header and peak counts of peak content break, judged on the bytes received.

    One definition of the rules for :func:`decode_peaks_header` (content whole) and the stream decoder (content
    still arriving, :mod:`twin.io.hyperion.stream`). Checked in order: the content holds a 24-byte header,
    :data:`_PEAK_HEADER_RULES`, every peak count in 0 … ``n_gratings`` (0 … 32767 without it), and the content
    length equal to the header plus 8 bytes a peak. A rule whose field has not arrived yet is not judged.

    Parameters
    ----------
    data : bytes-like
        Holds the peak content from ``data[start]`` on: all of it, or its first bytes.
    start : int
        Where the content starts in ``data``.
    content_length : int, optional
        Bytes of the whole content (default: all of ``data`` from ``start``).
    max_channels : int
        Most channels a header may announce.
    n_gratings : int, optional
        Most peaks a channel may report.
    origin : int
        Offset of ``data[0]`` in the caller's stream (added to the error's offset).

    Returns
    -------
    FramingError or None
        The error (its offset counted from ``data[0]`` plus ``origin``), or None when every field received is
        valid (complete once ``data`` holds the header length's bytes from ``start``).
    """
    have = len(data) - start
    n = have if content_length is None else int(content_length)
    at = origin + start
    if n < PEAK_HEADER_SIZE:
        return TruncatedFrameError(f"peak content of {n} bytes", offset=at + n, expected="a 24-byte peak header",
                                   protocol=PROTOCOL)
    if have < PEAK_HEADER_SIZE:
        return None
    hl, _, reserved, _, _, ns = _PEAK_HEADER.unpack_from(data, start)
    f = _HeaderFields(hl, reserved, ns, n, max_channels)
    for rule in _PEAK_HEADER_RULES:
        if not rule.holds(f):
            return rule.error(f"{rule.label} {getattr(f, rule.name)}", offset=at + rule.offset,
                              expected=rule.expected.format(**f._asdict()), protocol=PROTOCOL)
    if have < hl:
        return None
    counts = np.frombuffer(data, "<i2", (hl - PEAK_HEADER_SIZE) // 2, start + PEAK_HEADER_SIZE)
    g = n_gratings
    if counts.size and (counts.min() < 0 or (g is not None and counts.max() > g)):
        k = int(np.argmax((counts < 0) | (g is not None and counts > g)))
        what = (f"channel {k + 1} reports {counts[k]} peaks, more than n_gratings = {g}" if counts[k] >= 0
                else f"channel {k + 1} peak count {counts[k]}")
        return FramingError(what, offset=at + PEAK_HEADER_SIZE + 2 * k,
                            expected=f"a count in 0 … {32767 if g is None else g}", protocol=PROTOCOL)
    n_bytes = 8 * int(counts.sum(dtype=np.int64))
    if n - hl != n_bytes:
        return (TruncatedFrameError if n - hl < n_bytes else OversizeFrameError)(
            f"{n - hl} bytes of wavelengths for {n_bytes // 8} peaks",
            offset=at + min(n, hl + n_bytes),
            expected=f"exactly {n_bytes} bytes (8 per peak)",
            protocol=PROTOCOL,
        )
    return None


def wavelength_fault(data: bytes | bytearray, start: int, count: int, *, first: int = 0,
                     origin: int = 0) -> FramingError | None:
    """The first of ``count`` float64 peaks at ``data[start]`` that is not a wavelength: not finite, or outside
    :data:`WAVELENGTH_RANGE` (the frame is refused whole: lost framing or corrupt data); None when all are.

    ``first`` is the index of the first of them in the frame; the error's offset is counted from ``data[0]``
    plus ``origin``.
    """
    values = np.frombuffer(data, "<f8", count, start)
    lo, hi = WAVELENGTH_RANGE
    bad = ~((values >= lo) & (values <= hi))  # NaN too
    if not bad.any():
        return None
    i = int(np.argmax(bad))
    return FramingError(
        f"peak {first + i} of the frame is {values[i]!r} nm",
        offset=origin + start + 8 * i,
        expected=f"a wavelength in {lo:g}–{hi:g} nm (the whole frame is refused: lost framing or corrupt data)",
        protocol=PROTOCOL,
    )


def decode_peaks_header(content: bytes, *, max_channels: int = 128,
                        n_gratings: int | None = None) -> tuple[PeakHeader, np.ndarray]:
    """The header and the per-channel peak counts of peak content.

    Raises
    ------
    FramingError
        The first rule of :func:`peak_content_fault` that the content breaks (a channel reporting more than
        ``n_gratings`` peaks included, when given).
    """
    err = peak_content_fault(content, max_channels=max_channels, n_gratings=n_gratings)
    if err is not None:
        raise err
    return _header_and_counts(content)


def _header_and_counts(content: bytes) -> tuple[PeakHeader, np.ndarray]:
    """The header and the peak counts (int64) of peak content, unchecked."""
    h = PeakHeader(*_PEAK_HEADER.unpack_from(content, 0))
    return h, np.frombuffer(content, dtype="<i2", count=h.n_channels, offset=PEAK_HEADER_SIZE).astype(np.int64)


def decode_peaks(content: bytes, *, n_gratings: int | None = None, max_channels: int = 128) -> Frame:
    """Peak content (a ``#GetPeaks`` reply, or one stream frame's content) → :class:`Frame`.

    Parameters
    ----------
    content : bytes
        The response content.
    n_gratings : int, optional
        Rows of the frame; default the largest peak count. Channels with fewer peaks are NaN-padded (MISSING).
    max_channels : int
        Bound on the channel count read from the header.

    Returns
    -------
    Frame
        Wavelengths (n_gratings, n_channels) nm, status, sequence = serial number, timestamp s.

    Raises
    ------
    FramingError
        Inconsistent header, counts or length; a channel with more peaks than ``n_gratings``; a wavelength that
        is not finite or outside :data:`WAVELENGTH_RANGE` (the bytes are not peak data).
    """
    if n_gratings is not None and n_gratings < 0:
        raise ValueError(f"n_gratings: expected >= 0, got {n_gratings}")
    content = bytes(content)
    h, counts = decode_peaks_header(content, max_channels=max_channels, n_gratings=n_gratings)
    err = wavelength_fault(content, h.header_length, int(counts.sum()))
    if err is not None:
        raise err
    return _peaks_frame(content, h, counts, n_gratings)


def _peaks_frame(content: bytes, h: PeakHeader, counts: np.ndarray, n_gratings: int | None) -> Frame:
    """Peak content that passed every check (:func:`peak_content_fault`, :func:`wavelength_fault`) → Frame."""
    n_ch = counts.size
    g = int(counts.max(initial=0)) if n_gratings is None else int(n_gratings)
    values = np.frombuffer(content, dtype="<f8", offset=h.header_length)
    lam = np.full((n_ch, g), np.nan)
    # row of each value = its channel, column = its index within the channel; one scatter, no loop
    ch = np.repeat(np.arange(n_ch), counts)
    col = np.arange(values.size) - np.repeat(np.cumsum(counts) - counts, counts)
    lam[ch, col] = values
    st = np.where(np.arange(g)[None, :] < counts[:, None], np.uint8(0), _MISSING).astype(np.uint8)
    return Frame(
        wavelengths=np.ascontiguousarray(lam.T),
        timestamp=h.timestamp,
        sequence=clamp(h.serial_number),  # a u64 beyond int64 → 2**63 − 1 (twin.io.sequence)
        status=np.ascontiguousarray(st.T),
    )


def encode_peaks(frame: Frame, *, serial_number: int | None = None, version: int = 1) -> bytes:
    """:class:`Frame` → peak content; NaN (or non-positive) peaks are left out, each core is one channel.

    Parameters
    ----------
    frame : Frame
        Wavelengths nm, one column per channel; timestamp s (NaN → 0); sequence → serial number.
    serial_number : int, optional
        Override for the header's serial number (default ``frame.sequence``, or 0 when it is negative).
    version : int
        Header version field.
    """
    w = frame.wavelengths
    n_ch = w.shape[1]
    present = np.isfinite(w) & (w > 0)
    counts = present.sum(axis=0)
    values = w.T[present.T]  # channel-major, in grating order
    sn = serial_number if serial_number is not None else max(frame.sequence, 0)
    ts = frame.timestamp if np.isfinite(frame.timestamp) and frame.timestamp >= 0 else 0.0
    sec = int(ts)
    ns = round((ts - sec) * 1e9)  # split first: ts·1e9 as one float would lose ~0.5 µs at today's epoch
    if ns >= 1_000_000_000:
        sec, ns = sec + 1, ns - 1_000_000_000
    if (
        sec > 0xFFFFFFFF
        or not 0 <= sn < 2**64
        or n_ch > (0xFFFF - PEAK_HEADER_SIZE) // 2
        or counts.max(initial=0) > 0x7FFF
    ):
        raise ValueError("peaks: timestamp, serial number, channel or peak count does not fit its field")
    head = _PEAK_HEADER.pack(PEAK_HEADER_SIZE + 2 * n_ch, version, 0, sn, sec, ns)
    return head + counts.astype("<i2").tobytes() + values.astype("<f8").tobytes()


# --------------------------------------------------------------------------------- start-up command replies


def _exact(content: bytes, n: int, what: str) -> bytes:
    if len(content) != n:
        cls = TruncatedFrameError if len(content) < n else OversizeFrameError
        raise cls(
            f"{what} content of {len(content)} bytes",
            offset=min(len(content), n),
            expected=f"exactly {n} bytes",
            protocol=PROTOCOL,
        )
    return content


def decode_u32(content: bytes) -> int:
    """Content of ``#GetDutChannelCount``, ``#GetMaximumPeakCountPerDutChannel``, ``#GetLaserScanSpeed``."""
    return int.from_bytes(_exact(content, 4, "u32"), "little")


def decode_u8(content: bytes) -> int:
    """Content of ``#isready`` (non-zero = ready)."""
    return _exact(content, 1, "u8")[0]


def decode_i32_array(content: bytes) -> np.ndarray:
    """Content of ``#GetAvailableLaserScanSpeeds``: int32 array."""
    if len(content) % 4:
        raise FramingError(
            f"int32 array content of {len(content)} bytes",
            offset=len(content) - len(content) % 4,
            expected="a multiple of 4 bytes",
            protocol=PROTOCOL,
        )
    return np.frombuffer(content, dtype="<i4").astype(np.int64)


def decode_ascii(content: bytes) -> str:
    """Content of ``#GetSerialNumber``, ``#GetFirmwareVersion``, ``#GetFPGAVersion``, ``#GetInstrumentName``
    (ASCII)."""
    return _ascii(bytes(content), "content", 0)


@dataclass
class InstrumentState:
    """What the simulated instrument answers to the start-up commands (mutable: ``#SetLaserScanSpeed``)."""

    serial_number: str = "SIM0001"
    firmware_version: str = "2.4.0.0"
    fpga_version: str = "1.0.0"
    instrument_name: str = "catheter-twin simulated si155"
    channel_count: int = 4
    max_peaks_per_channel: int = 64
    laser_scan_speed: int = 1000
    available_scan_speeds: Sequence[int] = field(default_factory=lambda: (1, 2, 5, 10, 100, 1000, 2000, 5000))
    ready: bool = True


def respond(request: Request, state: InstrumentState, *, frame: Frame | None = None) -> bytes:
    """Server side of port 51971: the response bytes to ``request``.

    Handles ``#GetPeaks`` (needs ``frame``), ``#GetDutChannelCount``, ``#GetMaximumPeakCountPerDutChannel``,
    ``#isready``, ``#GetSerialNumber``, ``#GetFirmwareVersion``, ``#GetFPGAVersion``, ``#GetInstrumentName``,
    ``#GetLaserScanSpeed``, ``#GetAvailableLaserScanSpeeds`` and ``#SetLaserScanSpeed <n>``; command names are
    matched case-insensitively (Luna's own client spells ``#isready`` in lower case). Anything else, or a bad
    argument, gets a non-zero status with a message (status 1: unknown command, 2: bad argument, 3: no data).
    """
    cmd = request.command.lower()
    s = state
    ascii_replies = {
        "#getserialnumber": s.serial_number,
        "#getfirmwareversion": s.firmware_version,
        "#getfpgaversion": s.fpga_version,
        "#getinstrumentname": s.instrument_name,
    }
    if cmd in ascii_replies:
        return encode_response(ascii_replies[cmd].encode("ascii"))
    if cmd == "#getpeaks":
        if frame is None:
            return encode_response(message="No peak data available", status=3)
        return encode_response(encode_peaks(frame))
    if cmd == "#getdutchannelcount":
        return encode_response(struct.pack("<I", s.channel_count))
    if cmd == "#getmaximumpeakcountperdutchannel":
        return encode_response(struct.pack("<I", s.max_peaks_per_channel))
    if cmd == "#isready":
        return encode_response(struct.pack("<B", 1 if s.ready else 0))
    if cmd == "#getlaserscanspeed":
        return encode_response(struct.pack("<I", s.laser_scan_speed))
    if cmd == "#getavailablelaserscanspeeds":
        return encode_response(np.asarray(s.available_scan_speeds, dtype="<i4").tobytes())
    if cmd == "#setlaserscanspeed":
        arg = request.argument.strip()
        # bounded before int(): Python refuses to convert more than 4300 digits (and a speed has at most 6)
        if not (len(arg) <= 9 and arg.isascii() and arg.isdigit()) or int(arg) not in s.available_scan_speeds:
            return encode_response(message=f"Invalid laser scan speed {arg[:20]!r}", status=2)
        s.laser_scan_speed = int(arg)
        return encode_response(message=f"Laser scan speed set to {s.laser_scan_speed} Hz")
    return encode_response(message=f"Unknown command {request.command[:40]!r}", status=1)
