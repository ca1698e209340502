"""The one error type every protocol decoder in :mod:`twin.io` raises for bad bytes.

Every decoder (ILLumiSense, FiSpec, Hyperion) reports malformed, truncated or oversized input as a
:class:`FramingError` — never as ``IndexError``, ``struct.error``, ``UnicodeDecodeError`` or a bare
``ValueError`` — so a live loop needs exactly one ``except`` clause to count the error and resynchronise or
reconnect. The message names the protocol, the byte offset and what was expected there.

:class:`SourceFailed` (and :class:`RecordingDamaged`) mark the other kind of error: one that reopening the source
cannot cure, so the live loop ends on it.
"""

from __future__ import annotations

__all__ = ["FramingError", "OversizeFrameError", "RecordingDamaged", "SourceFailed", "TruncatedFrameError", "brief"]


class FramingError(ValueError):
    """Bytes that do not form a valid frame of a wire protocol.

    Parameters
    ----------
    what : str
        What was wrong, e.g. ``"grating count is not an integer"``.
    offset : int or None
        Byte offset of the offending byte or field, counted from the start of the buffer handed to the
        decoder (a payload, a reply, or — for stream decoders — the whole stream since construction).
    expected : str or None
        What a valid frame has there, e.g. ``"a decimal integer"``.
    protocol : str
        Short protocol name used as the message prefix (``"illumisense"``, ``"fispec"``, ``"hyperion"``).

    Attributes
    ----------
    what, offset, expected, protocol
        As given, for programmatic inspection (the counters of the stream decoders keep the last error).
    """

    def __init__(
        self, what: str, *, offset: int | None = None, expected: str | None = None, protocol: str = ""
    ) -> None:
        self.what = what
        self.offset = offset
        self.expected = expected
        self.protocol = protocol
        parts = [f"{protocol}: " if protocol else "", what]
        if offset is not None:
            parts.append(f" at byte {offset}")
        if expected is not None:
            parts.append(f"; expected {expected}")
        super().__init__("".join(parts))

    def __reduce__(self):
        # keep the keyword-only fields through pickling (errors cross process boundaries in sweeps)
        return (_rebuild, (type(self), self.what, self.offset, self.expected, self.protocol))


class TruncatedFrameError(FramingError):
    """The input ends before the frame does (fewer bytes than the frame declares, or no terminator)."""


class OversizeFrameError(FramingError):
    """A length field announces more bytes than the configured bound; refused before anything is allocated."""


class SourceFailed(OSError):
    """A source that can never deliver (more) frames, such as a damaged recording: the live loop ends with this
    error instead of reopening the source, which would fail the same way again."""


class RecordingDamaged(SourceFailed):
    """A recording whose file is damaged (truncated, or with chunks that fail their checksum): the frames before
    the damage can be read (``twin replay --salvage``, ``replay://FILE?salvage=1``), the rest are lost."""


def _rebuild(
    cls: type[FramingError], what: str, offset: int | None, expected: str | None, protocol: str
) -> FramingError:
    return cls(what, offset=offset, expected=expected, protocol=protocol)


def brief(exc: BaseException) -> str:
    """An exception as one short line for an error message: its first line (its type's name when it says
    nothing), at most 200 characters."""
    return (str(exc).strip() or type(exc).__name__).splitlines()[0][:200]
