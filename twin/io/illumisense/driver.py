"""The ILLumiSense driver: :class:`IllumisenseSource`.

``illumisense://HOST[:PORT]`` (port 2055): the ILLumiSense TCP stream (docs/protocols.md §1). The stream decoder
resynchronises by itself after bad bytes; the driver reconnects only when the peer closes, or when the stream stays
out of sync for ``resync_timeout`` s (default 2) of reading that keeps up with what arrives (a reader that fell
behind reads what waits first: time spent away from the socket never drops a connection holding unread records; a
garbage stream that fills every read is skipped, not reconnected). The channel layout is decided by a consensus of
the first records (records of another layout are counted in ``odd_records``; held records are released after
``layout_wait`` s at the latest). Options: ``channels=cores|single`` with ``cores=N`` for a fibre whose cores are
spliced onto one channel, ``max_payload`` (bytes), ``layout_wait`` (s, default 0.25).

Common behaviour (opening, reconnect policy, counters): :mod:`twin.io.drivers`.
"""

from __future__ import annotations

import time

from twin.io.drivers import COMMON_OPTIONS, RESYNC_OPTIONS, RESYNC_TIMEOUT, Driver, split_common
from twin.io.illumisense import codec
from twin.io.illumisense.stream import StreamDecoder
from twin.io.options import Option, parse_options
from twin.io.source import parse_url
from twin.io.transport import TcpClient, parse_host_port

__all__ = ["IllumisenseSource", "open_illumisense"]


class IllumisenseSource(Driver):
    """``illumisense://HOST[:PORT]``: the FBGS ILLumiSense TCP stream (module docstring).

    Parameters
    ----------
    host, port
        The ILLumiSense (or ``twin serve illumisense``) endpoint.
    channels_as, n_cores, max_payload
        Passed to :class:`twin.io.illumisense.StreamDecoder`.
    connect_timeout : float
        s.
    resync_timeout : float
        Reconnect when the stream stays out of sync this long while the reader keeps up with it, s
        (:mod:`twin.io.drivers`).
    url, wait, retry_for, backoff
        See :class:`Driver`.
    """

    def __init__(self, host: str, port: int = codec.DEFAULT_PORT, *, channels_as: str = "cores",
                 n_cores: int | None = None, max_payload: int = codec.DEFAULT_MAX_PAYLOAD,
                 connect_timeout: float = 3.0, resync_timeout: float = RESYNC_TIMEOUT, layout_wait: float = 0.25,
                 url: str = "", **kw):
        self.host, self.port = host, int(port)
        self.connect_timeout = connect_timeout
        self.resync_timeout = resync_timeout
        self.layout_wait = layout_wait
        self._held_since: float | None = None
        self.decoder = StreamDecoder(max_payload=max_payload, channels_as=channels_as, n_cores=n_cores)
        self._client: TcpClient | None = None
        super().__init__(url or f"illumisense://{host}:{port}", **kw)

    def _connect(self) -> None:
        self._client = TcpClient(self.host, self.port, connect_timeout=self.connect_timeout, label=self.url)

    def _drop(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
            # a connection that dropped inside a record is a framing error (what came before is kept); closing
            # the source ourselves mid-record is not
            if not self._closed:
                self._push(self.decoder.finish())

    def _pump(self, timeout: float) -> None:
        data = self._client.recv(timeout)
        if data:
            self._push(self.decoder.feed_batch(data))
        if self.decoder.holding:  # records wait for the layout decision: not for long
            now = time.monotonic()
            self._held_since = self._held_since or now
            if now - self._held_since > self.layout_wait:
                self._push(self.decoder.settle())
        else:
            self._held_since = None
        self._watch_sync(len(data), self._client.recv_size, self.decoder.in_sync)

    def stats(self) -> dict:
        d = self.decoder
        out = super().stats()
        out.update(
            framing_errors=d.framing_errors,
            lost_samples=d.sequence.lost_samples,
            sequence_gaps=d.sequence.sequence_gaps,
            sequence_resets=d.sequence.sequence_resets,
            sequence_corrupt=d.sequence.sequence_corrupt,
            bytes_discarded=d.bytes_discarded,
            odd_records=d.odd_records,
            layout_changes=d.layout_changes,
            sensor_blocks_absent=d.sensor_blocks_absent,
        )
        if d.last_error is not None:
            out["last_framing_error"] = str(d.last_error)
        return out


# ---------------------------------------------------------------------------------------------------- opener


def open_illumisense(url: str, **options) -> IllumisenseSource:
    """``illumisense://HOST[:PORT]?channels=cores|single&cores=N&max_payload=B&wait=0|1&retry_for=S&start_wait=S``."""
    _, rest, query = parse_url(url)
    host, port = parse_host_port(rest, codec.DEFAULT_PORT, what=url)
    opts = parse_options(url, query, {**COMMON_OPTIONS, "channels": Option("str", choices=("cores", "single")),
                                      "cores": Option("int", low=1, high=64),
                                      "max_payload": Option("int", low=codec.MIN_PAYLOAD, high=1 << 24),
                                      **RESYNC_OPTIONS,
                                      "layout_wait": Option("float", low=0.0)})
    kw = split_common(opts)
    fiber = options.pop("fiber", None)
    channels_as = opts.pop("channels", "cores")
    n_cores = opts.pop("cores", None)
    if channels_as == "single" and n_cores is None and fiber is not None:
        n_cores = fiber.n_cores
    kw.update(opts)
    kw.update(options)
    return IllumisenseSource(host, port, channels_as=channels_as, n_cores=n_cores, url=url, **kw)
