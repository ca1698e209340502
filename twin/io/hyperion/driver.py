"""The Hyperion driver: :class:`HyperionSource`.

``hyperion://HOST[:PORT]`` (command port 51971, peak stream on PORT + 1 = 51972 unless ``stream_port=``):
start-up queries on the command port (``#isready``, channel count, peaks per channel, serial number,
instrument name, laser scan speed → :attr:`HyperionSource.info`, ``rate``), then the pushed peak stream. Bad
bytes on the stream (garbage, a frame cut short) are counted and skipped: the decoder resynchronises by itself
and delivers the intact frames after them (:mod:`twin.io.hyperion.stream`); the driver reconnects when the peer
closes, or when the stream stays out of sync for ``resync_timeout`` s (default 2) of reading that keeps up with
what arrives (a reader that fell behind reads what waits first; a garbage stream that fills every read is
skipped, not reconnected: the rule ILLumiSense keeps, :mod:`twin.io.drivers`). Channel k + 1 is core k
(``channels=2,3,4,5`` picks others). The instrument sends only the peaks it found: with a fibre model,
a channel that reports fewer (or more) peaks than gratings has its peaks assigned to the gratings nearest in
nominal wavelength (a duplicate keeps the closer peak); without one, peaks fill the gratings in order.

Common behaviour (opening, reconnect policy, counters): :mod:`twin.io.drivers`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from twin.fiber import FiberModel
from twin.frames import Frame
from twin.io.drivers import COMMON_OPTIONS, MISSING, RESYNC_OPTIONS, RESYNC_TIMEOUT, Driver, split_common
from twin.io.hyperion import codec as hyperion
from twin.io.hyperion.stream import PeakStreamDecoder
from twin.io.options import Option, parse_options
from twin.io.sequence import SequenceCounter
from twin.io.source import parse_url
from twin.io.transport import TcpClient, parse_host_port

__all__ = ["HyperionSource", "assign_peaks", "open_hyperion"]


def assign_peaks(peaks: np.ndarray, lambda0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Assign one channel's reported peaks to gratings by nearest nominal wavelength.

    Parameters
    ----------
    peaks : ndarray (k,)
        Reported peak wavelengths, nm (NaN entries are ignored).
    lambda0 : ndarray (n_gratings,)
        Nominal wavelengths of the channel's gratings, nm.

    Returns
    -------
    wavelengths : ndarray (n_gratings,)
        nm, NaN for gratings no peak was assigned to.
    status : ndarray of uint8 (n_gratings,)
        MISSING where NaN.
    """
    p = peaks[np.isfinite(peaks)]
    out = np.full(lambda0.shape, np.nan)
    if p.size:
        d = np.abs(p[:, None] - lambda0[None, :])
        g = np.argmin(d, axis=1)
        dist = d[np.arange(p.size), g]
        # a grating claimed twice keeps the closer peak: write in order of decreasing distance
        order = np.argsort(-dist)
        out[g[order]] = p[order]
    return out, np.where(np.isnan(out), MISSING, np.uint8(0)).astype(np.uint8)


class HyperionSource(Driver):
    """``hyperion://HOST[:PORT]``: Luna/Micron Optics Hyperion, command port + peak stream (module docstring).

    Parameters
    ----------
    host, port
        Command port (51971); ``stream_port`` defaults to ``port + 1``.
    stream_port : int, optional
    channels : sequence of int, optional
        1-based instrument channels, in core order; default 1 … n_cores (or all channels without a fibre).
    fiber : FiberModel, optional
        For assigning peaks to gratings by wavelength and for the frame's (n_gratings, n_cores).
    connect_timeout : float
        s (also the timeout of each start-up query).
    resync_timeout : float
        Reconnect when the peak stream stays out of sync this long while the reader keeps up with it, s
        (:mod:`twin.io.drivers`).
    url, wait, retry_for, backoff
        See :class:`Driver`.

    Attributes
    ----------
    info : dict
        Answers to the start-up queries.
    """

    QUERIES = (
        ("ready", "#isready", hyperion.decode_u8),
        ("channel_count", "#GetDutChannelCount", hyperion.decode_u32),
        ("max_peaks_per_channel", "#GetMaximumPeakCountPerDutChannel", hyperion.decode_u32),
        ("serial_number", "#GetSerialNumber", hyperion.decode_ascii),
        ("instrument_name", "#GetInstrumentName", hyperion.decode_ascii),
        ("laser_scan_speed", "#GetLaserScanSpeed", hyperion.decode_u32),
    )

    def __init__(self, host: str, port: int = hyperion.COMMAND_PORT, *, stream_port: int | None = None,
                 channels: Sequence[int] | None = None, fiber: FiberModel | None = None,
                 connect_timeout: float = 3.0, resync_timeout: float = RESYNC_TIMEOUT, url: str = "", **kw):
        self.host, self.port = host, int(port)
        self.stream_port = int(stream_port) if stream_port is not None else self.port + 1
        self.fiber = fiber
        self.channels = None if channels is None else [int(c) for c in channels]
        if self.channels is not None and any(c < 1 for c in self.channels):
            raise ValueError(f"{url or host}: channels are numbered from 1, got {self.channels}")
        self.connect_timeout = connect_timeout
        self.resync_timeout = resync_timeout
        self.info: dict = {}
        self._stream: TcpClient | None = None
        # one decoder for every connection: it starts each in sync, and its counts run across reconnects
        self._decoder = PeakStreamDecoder()
        self._sequence = SequenceCounter()
        super().__init__(url or f"hyperion://{host}:{port}", **kw)

    def _query(self, client: TcpClient, decoder: hyperion.ResponseDecoder, command: str) -> hyperion.Response:
        client.sendall(hyperion.encode_request(command), timeout=self.connect_timeout)
        deadline = time.monotonic() + self.connect_timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"{self.url}: no reply to {command} within {self.connect_timeout:g} s")
            responses = decoder.feed(client.recv(remaining))
            if responses:
                return responses[0]

    def _connect(self) -> None:
        cmd = TcpClient(self.host, self.port, connect_timeout=self.connect_timeout, label=self.url)
        try:
            dec = hyperion.ResponseDecoder()
            info = {}
            for key, command, decode in self.QUERIES:
                r = self._query(cmd, dec, command)
                if not r.ok:
                    raise OSError(f"{self.url}: {command} failed with status {r.status}: {r.message}")
                info[key] = decode(r.content)
        finally:
            cmd.close()
        if not info["ready"]:
            raise OSError(f"{self.url}: the instrument reports it is not ready (#isready = 0)")
        n_ch = info["channel_count"]
        wanted = self.channels or list(range(1, (self.fiber.n_cores if self.fiber else n_ch) + 1))
        if max(wanted) > n_ch:
            raise OSError(f"{self.url}: channels {wanted} asked for, the instrument has {n_ch}")
        self.info = info
        self.rate = float(info["laser_scan_speed"]) or None
        self._stream = TcpClient(self.host, self.stream_port, connect_timeout=self.connect_timeout,
                                 label=self.url)

    def _drop(self) -> None:
        if self._stream is not None:
            self._stream.close()
            self._stream = None
            # a connection that dropped inside a frame is a framing error, as on ILLumiSense; closing the
            # source ourselves mid-frame is not
            if not self._closed:
                self._decoder.finish()

    def _pump(self, timeout: float) -> None:
        data = self._stream.recv(timeout)
        if not data:
            return
        frames = [self._map(f) for f in self._decoder.feed(data)]
        # gaps are counted here, by the rule every source shares (twin.io.sequence), across reconnects
        if frames:
            self._sequence.count_many([f.sequence for f in frames])
            self.counters.update(self._sequence.as_dict())
        self._push(frames)
        self._watch_sync(len(data), self._stream.recv_size, self._decoder.in_sync)

    def _map(self, frame: Frame) -> Frame:
        """Select the channels and put each peak on its grating."""
        w, st = frame.wavelengths, frame.status
        n_ch = w.shape[1]
        cols = [c - 1 for c in (self.channels or range(1, (self.fiber.n_cores if self.fiber else n_ch) + 1))]
        if self.fiber is None:
            sel = np.full((w.shape[0], len(cols)), np.nan)
            sst = np.full(sel.shape, MISSING, np.uint8)
            ok = [c for c in cols if c < n_ch]
            idx = [k for k, c in enumerate(cols) if c < n_ch]
            sel[:, idx], sst[:, idx] = w[:, ok], st[:, ok]
            return Frame(sel, frame.timestamp, frame.sequence, status=sst)
        n_g = self.fiber.n_gratings
        out = np.full((n_g, len(cols)), np.nan)
        ost = np.full(out.shape, MISSING, np.uint8)
        for k, c in enumerate(cols):
            if c >= n_ch:
                continue
            col = w[:, c]
            count = int(np.count_nonzero(np.isfinite(col)))
            if count == n_g and np.all(np.isfinite(col[:n_g])):
                out[:, k], ost[:, k] = col[:n_g], st[:n_g, c]  # the usual case: every grating reported
            else:
                out[:, k], ost[:, k] = assign_peaks(col, self.fiber.lambda0[:, k])
        return Frame(out, frame.timestamp, frame.sequence, status=ost)

    def stats(self) -> dict:
        out = super().stats()
        d = self._decoder
        out.update(framing_errors=d.framing_errors, bytes_discarded=d.bytes_discarded)
        if d.last_error is not None:
            out["last_framing_error"] = str(d.last_error)
        return out


# ---------------------------------------------------------------------------------------------------- opener


def open_hyperion(url: str, **options) -> HyperionSource:
    """``hyperion://HOST[:PORT]?stream_port=P&channels=1,2,3,4&resync_timeout=S&wait=0|1&retry_for=S&start_wait=S``."""
    _, rest, query = parse_url(url)
    host, port = parse_host_port(rest, hyperion.COMMAND_PORT, what=url)
    opts = parse_options(url, query, {**COMMON_OPTIONS, "stream_port": Option("int", low=1, high=65535),
                                      "channels": Option("ints", low=1, high=256), **RESYNC_OPTIONS})
    kw = split_common(opts)
    kw.update(opts)
    kw.update(options)
    return HyperionSource(host, port, url=url, **kw)
