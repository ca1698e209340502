"""Interrogator I/O: protocol codecs (encode and decode), transports, drivers, recording and replay, and
:func:`open_source`, which opens any source of frames by URL."""

from twin.io.errors import FramingError
from twin.io.source import Source, SourceClosed, open_source

__all__ = ["FramingError", "Source", "SourceClosed", "open_source"]
