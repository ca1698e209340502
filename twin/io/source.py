"""Sources of frames, opened by URL (docs/architecture.md "Sources, by URL").

Every source — the simulator in-process, an interrogator over TCP or serial, a recording, the synthetic arc —
satisfies one protocol, :class:`Source`: ``read_batch(max_frames, timeout)`` returns the frames that are ready
as ONE 1-D batch :class:`~twin.frames.Frame` (a single frame is a batch of one; None when nothing arrived in
time) and raises :class:`SourceClosed` at the end. A batch has one (n_gratings, n_cores); a source whose frames
change shape ends the batch there. An error met after some frames were gathered is kept by the source and raised
by its next call, so nothing received is dropped. That is the whole contract the live loop relies on
(:class:`twin.live.LiveLoop`); ``stats``, ``describe`` and ``close`` complete it.

Implementations may subclass :class:`Source` to inherit ``read`` (one frame, for scripts), iteration and the
context manager, or just match it (``typing.Protocol``: tests/test_layering.py checks every registered source);
:class:`FrameByFrame` is the base for sources that make one frame at a time (the simulator).

:func:`open_source` picks the implementation from the URL scheme through the registry (:mod:`twin.registry`,
group ``twin.sources``), importing it only then, so the sensing core never names the simulator.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Protocol, runtime_checkable
from urllib.parse import parse_qsl, urlsplit

from twin import registry
from twin.extras import MissingExtra
from twin.fiber import FiberModel
from twin.frames import Frame

__all__ = ["MAX_BATCH", "FrameByFrame", "Source", "SourceClosed", "open_source", "parse_url", "schemes"]

#: frames one ``read_batch`` returns at most unless asked otherwise (an unpaced generator makes no more)
MAX_BATCH = 1024


def schemes() -> dict[str, str]:
    """URL scheme → ``"module:function"`` of every registered source (group ``twin.sources``)."""
    return registry.entries("twin.sources")


class SourceClosed(EOFError):
    """The source has ended (end of a recording or scenario, or closed) and will deliver no more frames."""


@runtime_checkable
class Source(Protocol):
    """What every source of frames is (module docstring).

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

    def read_batch(self, max_frames: int = MAX_BATCH, timeout: float | None = None) -> Frame | None:
        """The frames ready now, up to ``max_frames``, as one 1-D batch, waiting up to ``timeout`` s (None:
        forever) for the first; None if none arrived in time; :class:`SourceClosed` at the end."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the source (sockets, ports, simulation). Idempotent."""

    def stats(self) -> dict:
        """Counters the source keeps (framing errors, lost samples, reconnects, …)."""
        return {}

    def describe(self) -> dict:
        """What the source knows about itself, JSON-ready (a simulator: its setup and true fibre parameters)."""
        return {"url": self.url}

    # ------------------------------------------------------------ inherited by subclasses, not part of the protocol
    def read(self, timeout: float | None = None) -> Frame | None:
        """The next single frame (a script's convenience on top of :meth:`read_batch`); None if none arrived
        within ``timeout`` s."""
        batch = self.read_batch(1, timeout)
        return None if batch is None else batch[0]

    def __iter__(self) -> Iterator[Frame]:
        """Single frames until the source ends."""
        while True:
            try:
                batch = self.read_batch(MAX_BATCH, None)
            except SourceClosed:
                return
            if batch is not None:
                yield from batch

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class FrameByFrame(Source):
    """Base of sources that make one frame at a time: implement :meth:`next_frame`; :meth:`read_batch` gathers
    the frames that are ready (``next_frame(0)`` until it returns None) into one batch, keeps an error met after
    the first frame and raises it on the next call."""

    _pending_error: BaseException | None = None
    _held: Frame | None = None  # a frame of another shape than the batch it followed: it opens the next one

    def next_frame(self, timeout: float | None) -> Frame | None:
        """One single frame, waiting up to ``timeout`` s; None if none is ready; SourceClosed at the end."""
        raise NotImplementedError

    def read_batch(self, max_frames: int = MAX_BATCH, timeout: float | None = None) -> Frame | None:
        if self._pending_error is not None:
            err, self._pending_error = self._pending_error, None
            raise err
        first, self._held = self._held, None
        if first is None:
            first = self.next_frame(timeout)
            if first is None:
                return None
        out = [first]
        shape = first.wavelengths.shape
        while len(out) < max_frames:
            try:
                nxt = self.next_frame(0.0)
            except Exception as exc:  # delivered with the next call: nothing gathered is dropped
                self._pending_error = exc
                break
            if nxt is None:
                break
            if nxt.wavelengths.shape != shape:
                self._held = nxt
                break
            out.append(nxt)
        return Frame.stack(out)

    def read(self, timeout: float | None = None) -> Frame | None:
        """The next single frame as made (no batch of one built and indexed)."""
        if self._pending_error is None and self._held is None:
            return self.next_frame(timeout)
        return super().read(timeout)


def parse_url(url: str) -> tuple[str, str, dict[str, str]]:
    """Split ``scheme://rest?key=value&…`` into (scheme, rest without the query, options)."""
    try:
        parts = urlsplit(url)
    except ValueError as exc:  # urllib's own words ("Invalid IPv6 URL") name neither the URL nor the place
        raise ValueError(f"{url!r}: not a source URL ({exc}; an IPv6 host goes in brackets: [::1]:2055)") from None
    if not parts.scheme:
        raise ValueError(f"{url!r}: a source URL starts with a scheme: {', '.join(s + '://' for s in schemes())}")
    rest = url.split("://", 1)[1].split("?", 1)[0] if "://" in url else parts.path
    pairs = parse_qsl(parts.query, keep_blank_values=True)
    query = dict(pairs)
    if len(query) < len(pairs):  # the last one would win unsaid: say which is meant
        twice = next(k for i, (k, _) in enumerate(pairs) if k in dict(pairs[:i]))
        raise ValueError(f"{url!r}: option {twice!r} given more than once")
    return parts.scheme, rest, query


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
