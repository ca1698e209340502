"""Sources of frames, opened by URL (docs/architecture.md "Sources, by URL").

Every source — the simulator in-process, an interrogator over TCP or serial, a recording — is a :class:`Source`:
``read(timeout)`` returns the next :class:`~twin.frames.Frame` (or None when nothing arrived in time), and
iteration yields frames until the source ends. :func:`open_source` picks the implementation from the URL
scheme through the registry (:mod:`twin.registry`, group ``twin.sources``), importing it only then, so the
sensing core never names the simulator.
"""

from __future__ import annotations

from collections.abc import Iterator
from urllib.parse import parse_qsl, urlsplit

from twin import registry
from twin.extras import MissingExtra
from twin.fiber import FiberModel
from twin.frames import Frame

__all__ = ["Source", "SourceClosed", "open_source", "parse_url", "schemes"]


def schemes() -> dict[str, str]:
    """URL scheme → ``"module:function"`` of every registered source (group ``twin.sources``)."""
    return registry.entries("twin.sources")


class SourceClosed(EOFError):
    """The source has ended (end of a recording or scenario, or closed) and will deliver no more frames."""


class Source:
    """Base class of frame sources.

    Attributes
    ----------
    url : str
        What was opened.
    fiber : FiberModel or None
        The sensor's fibre model when the source knows it (the simulator, a recording); None for hardware.
    rate : float or None
        Nominal frame rate, Hz, when known.
    """

    url: str = ""
    fiber: FiberModel | None = None
    rate: float | None = None

    def read(self, timeout: float | None = None) -> Frame | None:
        """The next frame; None if none arrived within ``timeout`` s; raises :class:`SourceClosed` at the end."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the source (sockets, ports, simulation). Idempotent."""

    def stats(self) -> dict:
        """Counters the source keeps (framing errors, lost samples, reconnects, …)."""
        return {}

    def describe(self) -> dict:
        """What the source knows about itself, JSON-ready (a simulator: its setup and true fibre parameters)."""
        return {"url": self.url}

    def __iter__(self) -> Iterator[Frame]:
        while True:
            try:
                frame = self.read()
            except SourceClosed:
                return
            if frame is not None:
                yield frame

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def parse_url(url: str) -> tuple[str, str, dict[str, str]]:
    """Split ``scheme://rest?key=value&…`` into (scheme, rest without the query, options)."""
    try:
        parts = urlsplit(url)
    except ValueError as exc:  # urllib's own words ("Invalid IPv6 URL") name neither the URL nor the place
        raise ValueError(f"{url!r}: not a source URL ({exc}; an IPv6 host goes in brackets: [::1]:2055)") from None
    if not parts.scheme:
        raise ValueError(f"{url!r}: a source URL starts with a scheme: {', '.join(s + '://' for s in schemes())}")
    rest = url.split("://", 1)[1].split("?", 1)[0] if "://" in url else parts.path
    return parts.scheme, rest, dict(parse_qsl(parts.query, keep_blank_values=True))


def open_source(url: str, **options) -> Source:
    """Open a source of frames by URL; ``options`` override the URL's query parameters.

    ``sim://SCENARIO?key=value…`` (the simulator in-process), ``illumisense://HOST:PORT``,
    ``fispec://PORT_OR_PYSERIAL_URL``, ``hyperion://HOST``, ``replay://FILE`` (see README).
    """
    scheme = parse_url(url)[0]
    known = schemes()
    if scheme not in known:
        raise ValueError(f"{url!r}: unknown source scheme {scheme!r}; known: {', '.join(known)}")
    try:
        opener = registry.load("twin.sources", scheme)
    except MissingExtra as exc:
        raise MissingExtra(exc.package, exc.extra, f"{scheme}://") from None
    return opener(url, **options)
