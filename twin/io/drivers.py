"""Interrogator drivers: :class:`~twin.io.source.Source` implementations for ``illumisense://``,
``fispec://`` and ``hyperion://`` URLs, with reconnect, backoff and counters.

Common behaviour
----------------
- **Opening** connects at once and raises :class:`OSError` naming the URL and the reason when that fails (so a
  wrong address is one clear error), unless ``wait=1`` is given: then the driver keeps trying in the background
  of :meth:`read` like after a drop.
- **Reconnect policy**: after a connection drops (peer closed, reset, device gone, a protocol error that cannot
  be resynchronised), the first new attempt is immediate, then the delay doubles from 0.1 s up to 5 s
  (:class:`~twin.io.transport.Backoff`), and is reset once frames flow again. Retries go on forever unless
  ``retry_for=SECONDS`` is given, after which :meth:`read` raises :class:`~twin.io.source.SourceClosed`.
  :meth:`read` never blocks longer than its timeout while disconnected; it returns None.
- **Counters** in :meth:`stats`: ``state`` (connected / disconnected / closed), ``frames``, ``framing_errors``,
  ``lost_samples`` and ``sequence_gaps`` (from the source's sample numbers), ``disconnects``, ``reconnects``
  (successful connections after the first), ``connect_failures``, ``last_error`` (text).
- :meth:`read_many` returns every frame already received (a burst after a stall is reconstructed as one batch).

Protocol specifics
------------------
``illumisense://HOST[:PORT]`` (port 2055): the ILLumiSense TCP stream (docs/protocols.md §1). The stream decoder
resynchronises by itself after bad bytes; the driver reconnects only when the peer closes, or when the stream
stays out of sync for ``resync_timeout`` s (default 2). The channel layout is decided by a consensus of the
first records (records of another layout are counted in ``odd_records``; held records are released after
``layout_wait`` s at the latest). Options: ``channels=cores|single`` with ``cores=N`` for a fibre whose cores
are spliced onto one channel, ``max_payload`` (bytes), ``layout_wait`` (s, default 0.25).

``hyperion://HOST[:PORT]`` (command port 51971, peak stream on PORT + 1 = 51972 unless ``stream_port=``):
start-up queries on the command port (``#isready``, channel count, peaks per channel, serial number,
instrument name, laser scan speed → :attr:`HyperionSource.info`, ``rate``), then the pushed peak stream. A
binary stream without sync marker cannot be re-entered, so a framing error means reconnect. Channel k + 1 is
core k (``channels=2,3,4,5`` picks others). The instrument sends only the peaks it found: with a fibre model,
a channel that reports fewer (or more) peaks than gratings has its peaks assigned to the gratings nearest in
nominal wavelength (a duplicate keeps the closer peak); without one, peaks fill the gratings in order.

``fispec://PORT[,PORT…]`` (pyserial: device path, pty path, ``socket://host:port``, ``loop://``): a FiSpec
device measures one channel, so **one port per fibre core**: the k-th port is fibre core ``cores[k]``
(``cores=0,1,2,3``, default 0, 1, … in port order) and cores without a port are reported missing. After the
``?>`` / ``p?>`` handshake the driver, when it has a fibre model, programs one peak window per grating
(``Ke``, centred on the nominal λ0, ``window`` nm wide, default 3 nm as the public client uses), ``KA``, raw
wavelengths (``OBB,0``) and checks the device took them; without a model it reads the device's own windows.
Then it polls ``P>`` on every port at ``rate`` Hz (default 100). FiSpec has no sample numbers: the driver
numbers polls itself, and a poll that fails counts as a lost sample. A reply of the wrong length or without
``Ende`` is a framing error (input flushed, poll skipped); three in a row, or an I/O error, reconnect.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np

from twin.fiber import FiberModel
from twin.frames import Frame, PeakStatus
from twin.io import fispec, hyperion, illumisense
from twin.io.errors import FramingError
from twin.io.sequence import SequenceCounter
from twin.io.source import Source, SourceClosed, parse_url
from twin.io.transport import Backoff, ConnectionLost, TcpClient, open_serial, parse_host_port

__all__ = [
    "Driver",
    "FispecSource",
    "HyperionSource",
    "IllumisenseSource",
    "open_fispec",
    "open_hyperion",
    "open_illumisense",
]

_MISSING = np.uint8(PeakStatus.MISSING)


class Driver(Source):
    """Connection management shared by the drivers (module docstring: reconnect policy and counters).

    Subclasses implement :meth:`_connect` (open the transport and do the handshake), :meth:`_pump` (wait up
    to ``timeout`` s for bytes, decode, append frames to ``self._queue``) and :meth:`_drop` (close the
    transport).

    Parameters
    ----------
    url : str
        What was opened (every error message starts with it).
    wait : bool
        Do not fail when the first connection attempt fails; keep retrying.
    retry_for : float or None
        Give up (SourceClosed) after this many seconds without a connection; None retries forever.
    backoff : Backoff, optional
        Reconnect delays.
    """

    def __init__(self, url: str, *, wait: bool = False, retry_for: float | None = None,
                 backoff: Backoff | None = None):
        self.url = url
        self.backoff = backoff or Backoff()
        self.retry_for = retry_for
        self._queue: deque[Frame] = deque()
        self._connected = False
        self._closed = False
        self._ever_connected = False
        self._next_attempt = 0.0
        self._down_since: float | None = None
        self._frames_since_connect = 0
        self.counters = {
            "frames": 0,
            "framing_errors": 0,
            "lost_samples": 0,
            "sequence_gaps": 0,
            "disconnects": 0,
            "reconnects": 0,
            "connect_failures": 0,
        }
        self.last_error = ""
        if not self._attempt():
            if not wait:
                raise OSError(self.last_error)

    # ---------------------------------------------------------------- to implement
    def _connect(self) -> None:
        raise NotImplementedError

    def _pump(self, timeout: float) -> None:
        raise NotImplementedError

    def _drop(self) -> None:
        raise NotImplementedError

    # ---------------------------------------------------------------- machinery
    def _error(self, exc: BaseException) -> str:
        text = str(exc)
        return text if text.startswith(self.url) else f"{self.url}: {text}"

    def _attempt(self) -> bool:
        """One connection attempt; True when connected."""
        try:
            self._connect()
        except (OSError, FramingError, ValueError) as exc:
            self._drop()
            self.counters["connect_failures"] += 1
            self.last_error = self._error(exc)
            self._next_attempt = time.monotonic() + self.backoff.failed()
            if self._down_since is None:
                self._down_since = time.monotonic()
            return False
        if self._ever_connected:
            self.counters["reconnects"] += 1
        self._ever_connected = True
        self._connected = True
        self._down_since = None
        self._frames_since_connect = 0
        return True

    def _disconnect(self, exc: BaseException) -> None:
        self.last_error = self._error(exc)
        self._drop()
        self._connected = False
        self.counters["disconnects"] += 1
        self._down_since = time.monotonic()
        # immediate first retry after a connection that delivered frames; a connection that delivered nothing
        # (a server that accepts and closes, a device that never answers) counts as a failed attempt, so the
        # delays grow instead of spinning
        if self._frames_since_connect:
            self.backoff.reset()
            delay = 0.0
        else:
            delay = self.backoff.failed()
        self._next_attempt = time.monotonic() + delay

    def _push(self, frames: Sequence[Frame]) -> None:
        if frames:
            self._queue.extend(frames)
            self.counters["frames"] += len(frames)
            self._frames_since_connect += len(frames)
            if self.backoff.failures:
                self.backoff.reset()

    def read_many(self, max_frames: int = 1 << 30, timeout: float | None = None) -> list[Frame]:
        """Frames received so far (up to ``max_frames``), waiting up to ``timeout`` s for the first one.

        Returns an empty list when nothing arrived in time (also while disconnected and retrying).
        """
        if self._closed:
            raise SourceClosed(f"{self.url}: closed")
        deadline = None if timeout is None else time.monotonic() + timeout
        pumped = False
        while not self._queue:
            now = time.monotonic()
            remaining = None if deadline is None else deadline - now
            if remaining is not None and remaining <= 0:
                if pumped or not self._connected:
                    break
                remaining = 0.0  # read(0): one non-blocking look at the transport
            if not self._connected:
                if self.retry_for is not None and self._down_since is not None \
                        and now - self._down_since > self.retry_for:
                    raise SourceClosed(f"{self.url}: no connection for {self.retry_for:g} s ({self.last_error})")
                if now < self._next_attempt:
                    pause = self._next_attempt - now
                    time.sleep(pause if remaining is None else min(pause, remaining))
                    continue
                if not self._attempt():
                    continue
            try:
                pumped = True
                self._pump(0.5 if remaining is None else min(remaining, 0.5))
            except (ConnectionLost, OSError, FramingError) as exc:
                self._disconnect(exc)
        out = []
        while self._queue and len(out) < max_frames:
            out.append(self._queue.popleft())
        return out

    def read(self, timeout: float | None = None) -> Frame | None:
        frames = self.read_many(1, timeout)
        return frames[0] if frames else None

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._connected = False
            self._drop()

    @property
    def connected(self) -> bool:
        return self._connected

    def stats(self) -> dict:
        state = "closed" if self._closed else ("connected" if self._connected else "disconnected")
        return {"state": state, **self.counters, "last_error": self.last_error}


# ------------------------------------------------------------------------------------------------ ILLumiSense


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
        Reconnect when the stream stays out of sync this long, s.
    url, wait, retry_for, backoff
        See :class:`Driver`.
    """

    def __init__(self, host: str, port: int = illumisense.DEFAULT_PORT, *, channels_as: str = "cores",
                 n_cores: int | None = None, max_payload: int = illumisense.DEFAULT_MAX_PAYLOAD,
                 connect_timeout: float = 3.0, resync_timeout: float = 2.0, layout_wait: float = 0.25,
                 url: str = "", **kw):
        self.host, self.port = host, int(port)
        self.connect_timeout = connect_timeout
        self.resync_timeout = resync_timeout
        self.layout_wait = layout_wait
        self._held_since: float | None = None
        self.decoder = illumisense.StreamDecoder(max_payload=max_payload, channels_as=channels_as, n_cores=n_cores)
        self._client: TcpClient | None = None
        self._out_of_sync_since: float | None = None
        super().__init__(url or f"illumisense://{host}:{port}", **kw)

    def _connect(self) -> None:
        self._client = TcpClient(self.host, self.port, connect_timeout=self.connect_timeout, label=self.url)
        self._out_of_sync_since = None

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
            self._push(self.decoder.feed(data))
        if self.decoder.holding:  # records wait for the layout decision: not for long
            now = time.monotonic()
            self._held_since = self._held_since or now
            if now - self._held_since > self.layout_wait:
                self._push(self.decoder.settle())
        else:
            self._held_since = None
        if not data:
            return
        if self.decoder.in_sync:
            self._out_of_sync_since = None
        else:
            now = time.monotonic()
            self._out_of_sync_since = self._out_of_sync_since or now
            if now - self._out_of_sync_since > self.resync_timeout:
                raise ConnectionLost(f"{self.url}: stream out of sync for {self.resync_timeout:g} s")

    def stats(self) -> dict:
        d = self.decoder
        out = super().stats()
        out.update(
            framing_errors=d.framing_errors,
            lost_samples=d.sequence.lost_samples,
            sequence_gaps=d.sequence.sequence_gaps,
            sequence_resets=d.sequence.sequence_resets,
            bytes_discarded=d.bytes_discarded,
            odd_records=d.odd_records,
            layout_changes=d.layout_changes,
        )
        if d.last_error is not None:
            out["last_framing_error"] = str(d.last_error)
        return out


# -------------------------------------------------------------------------------------------------- Hyperion


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
    return out, np.where(np.isnan(out), _MISSING, np.uint8(0)).astype(np.uint8)


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
                 connect_timeout: float = 3.0, url: str = "", **kw):
        self.host, self.port = host, int(port)
        self.stream_port = int(stream_port) if stream_port is not None else self.port + 1
        self.fiber = fiber
        self.channels = None if channels is None else [int(c) for c in channels]
        if self.channels is not None and any(c < 1 for c in self.channels):
            raise ValueError(f"{url or host}: channels are numbered from 1, got {self.channels}")
        self.connect_timeout = connect_timeout
        self.info: dict = {}
        self._stream: TcpClient | None = None
        self._decoder: hyperion.ResponseDecoder | None = None
        self._framing_errors = 0
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
        # a fresh decoder per connection (the stream cannot be re-entered); counters are carried over
        self._decoder = hyperion.ResponseDecoder()

    def _drop(self) -> None:
        if self._stream is not None:
            self._stream.close()
            self._stream = None
        if self._decoder is not None:
            # a connection that dropped inside a frame is a framing error, as on ILLumiSense; closing the
            # source ourselves mid-frame is not
            if not self._closed:
                self._decoder.finish()
            self._framing_errors += self._decoder.framing_errors
            self._decoder = None

    def _pump(self, timeout: float) -> None:
        data = self._stream.recv(timeout)
        if not data:
            return
        frames = [self._map(f) for f in self._decoder.feed_frames(data)]
        # gaps are counted here rather than by the per-connection decoder, so that samples lost across a
        # reconnect count too
        for f in frames:
            lost = self._sequence.count(f.sequence)
            if lost:
                self.counters["sequence_gaps"] += 1
                self.counters["lost_samples"] += lost
        self._push(frames)

    def _map(self, frame: Frame) -> Frame:
        """Select the channels and put each peak on its grating."""
        w, st = frame.wavelengths, frame.status
        n_ch = w.shape[1]
        cols = [c - 1 for c in (self.channels or range(1, (self.fiber.n_cores if self.fiber else n_ch) + 1))]
        if self.fiber is None:
            sel = np.full((w.shape[0], len(cols)), np.nan)
            sst = np.full(sel.shape, _MISSING, np.uint8)
            ok = [c for c in cols if c < n_ch]
            idx = [k for k, c in enumerate(cols) if c < n_ch]
            sel[:, idx], sst[:, idx] = w[:, ok], st[:, ok]
            return Frame(sel, frame.timestamp, frame.sequence, status=sst)
        n_g = self.fiber.n_gratings
        out = np.full((n_g, len(cols)), np.nan)
        ost = np.full(out.shape, _MISSING, np.uint8)
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
        out["framing_errors"] = self._framing_errors + (self._decoder.framing_errors if self._decoder else 0)
        return out


# ---------------------------------------------------------------------------------------------------- FiSpec


class _Port:
    """One FiSpec serial port (one fibre core)."""

    def __init__(self, url: str, label: str):
        self.url, self.label = url, label
        self.ser = None
        self.n_peaks = 0
        self.identity = ""
        self.parameters: dict[str, int] = {}
        self.failures = 0

    def write(self, data: bytes) -> None:
        self.ser.write(data)

    def read_quiet(self, gap: float = 0.05, timeout: float = 1.0) -> bytes:
        """Bytes until the line is quiet for ``gap`` s after the first byte (replies without terminator)."""
        out = bytearray()
        start = last = time.monotonic()
        while True:
            chunk = self.ser.read(4096)
            now = time.monotonic()
            if chunk:
                out += chunk
                last = now
            elif out and now - last >= gap:
                break
            if now - start > timeout:
                break
        return bytes(out)

    def read_exactly(self, n: int, timeout: float) -> bytes:
        out = bytearray()
        deadline = time.monotonic() + timeout
        while len(out) < n:
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.label}: {len(out)} of {n} reply bytes within {timeout:g} s")
            out += self.ser.read(n - len(out))
        return bytes(out)

    def close(self) -> None:
        if self.ser is not None:
            try:
                self.ser.close()
            except OSError:
                pass
            self.ser = None


class FispecSource(Driver):
    """``fispec://PORT[,PORT…]``: FiSpec-type serial interrogators, one port per core (module docstring).

    Parameters
    ----------
    ports : sequence of str
        pyserial URLs or device/pty paths, one per core.
    rate : float
        Polls per second, Hz.
    fiber : FiberModel, optional
        Sensor: peak windows from its λ0, frames of (n_gratings, n_cores).
    cores : sequence of int, optional
        Fibre core of each port (default 0, 1, …).
    window : float
        Peak-window width, nm.
    baudrate : int
        Ignored by ptys and sockets.
    reply_timeout : float
        Time allowed for each reply, s.
    url, wait, retry_for, backoff
        See :class:`Driver`.
    """

    def __init__(self, ports: Sequence[str], *, rate: float = 100.0, fiber: FiberModel | None = None,
                 cores: Sequence[int] | None = None, window: float = 3.0, baudrate: int = fispec.BAUDRATE,
                 reply_timeout: float = 0.5, url: str = "", **kw):
        if not ports:
            raise ValueError(f"{url}: expected at least one serial port")
        if not (np.isfinite(rate) and rate > 0):
            raise ValueError(f"{url}: rate must be a positive frequency in Hz, got {rate}")
        self.fiber = fiber
        self.rate = float(rate)
        self.cores = list(range(len(ports))) if cores is None else [int(c) for c in cores]
        if len(self.cores) != len(ports):
            raise ValueError(f"{url}: {len(ports)} port(s) but cores={self.cores}")
        if fiber is not None and any(not 0 <= c < fiber.n_cores for c in self.cores):
            raise ValueError(f"{url}: cores {self.cores} outside the fibre's 0..{fiber.n_cores - 1}")
        self.window, self.baudrate, self.reply_timeout = float(window), int(baudrate), float(reply_timeout)
        label = url or "fispec://" + ",".join(ports)
        self._ports = [_Port(p, f"{label} [{p}]") for p in ports]
        self._sequence = 0
        self._next_poll = 0.0
        super().__init__(label, **kw)

    # ---------------------------------------------------------------- handshake
    def _connect(self) -> None:
        for port in self._ports:
            self._connect_port(port)
        self._next_poll = time.monotonic()

    def _connect_port(self, port: _Port) -> None:
        port.close()
        port.ser = open_serial(port.url, baudrate=self.baudrate, timeout=0.01, label=self.url)
        port.ser.reset_input_buffer()
        port.write(fispec.encode_command("?"))
        port.identity = fispec.decode_identity(port.read_quiet())
        port.write(fispec.encode_command("p?"))
        params = fispec.decode_parameters(port.read_quiet())
        if self.fiber is not None:
            core = self.cores[self._ports.index(port)]
            lam = self.fiber.lambda0[:, core]
            half = 0.5 * self.window
            for n, centre in enumerate(lam):
                lo, hi = round((centre - half) * 1e4), round((centre + half) * 1e4)
                port.write(fispec.encode_command("Ke", n, lo, hi))
            port.write(fispec.encode_command("KA", lam.size))
            port.write(fispec.encode_command("OBB", 0))
            port.write(fispec.encode_command("a"))
            port.write(fispec.encode_command("p?"))
            params = fispec.decode_parameters(port.read_quiet())
            if params.get("Kanalanzahl") != lam.size or params.get("OBBerechnen", 0) != 0:
                raise OSError(
                    f"{port.label}: the device did not take the configuration (Kanalanzahl "
                    f"{params.get('Kanalanzahl')}, OBBerechnen {params.get('OBBerechnen')}; wanted {lam.size}, 0)"
                )
        elif params.get("OBBerechnen", 0) != 0:
            port.write(fispec.encode_command("OBB", 0))
            port.write(fispec.encode_command("p?"))
            params = fispec.decode_parameters(port.read_quiet())
        port.parameters = params
        port.n_peaks = int(params.get("Kanalanzahl", 0))
        if port.n_peaks <= 0:
            raise OSError(f"{port.label}: the device has no active peak windows (Kanalanzahl 0); pass a fibre "
                          "model so the driver can program them")
        port.failures = 0

    def _drop(self) -> None:
        for port in self._ports:
            port.close()

    # ---------------------------------------------------------------- polling
    def _pump(self, timeout: float) -> None:
        wait = self._next_poll - time.monotonic()
        if wait > 0:
            time.sleep(min(wait, timeout))
            if wait > timeout:
                return
        self._next_poll = max(self._next_poll + 1.0 / self.rate, time.monotonic() - 1.0 / self.rate)
        for port in self._ports:
            port.write(fispec.encode_command("P"))
        seq = self._sequence
        self._sequence += 1
        columns: list[np.ndarray | None] = []
        for port in self._ports:
            n = 8 * port.n_peaks + 12
            try:
                reply = fispec.decode_peaks(port.read_exactly(n, self.reply_timeout), port.n_peaks)
            except (TimeoutError, FramingError) as exc:
                self.counters["framing_errors"] += 1
                self.last_error = self._error(exc)
                port.failures += 1
                # resynchronise: let a late or over-long reply finish, then discard it
                time.sleep(0.02)
                port.ser.reset_input_buffer()
                if port.failures >= 3:
                    raise ConnectionLost(f"{port.label}: 3 bad replies in a row ({exc})") from None
                columns.append(None)
                continue
            port.failures = 0
            columns.append(reply.wavelengths)
        if any(c is None for c in columns):
            self.counters["lost_samples"] += 1
            self.counters["sequence_gaps"] += 1
            return
        self._push([self._frame(columns, seq)])

    def _frame(self, columns: list[np.ndarray], seq: int) -> Frame:
        now = time.time()
        if self.fiber is None:
            n_g = max(c.size for c in columns)
            w = np.full((n_g, len(columns)), np.nan)
            for k, c in enumerate(columns):
                w[: c.size, k] = c
        else:
            n_g = self.fiber.n_gratings
            w = np.full((n_g, self.fiber.n_cores), np.nan)
            for core, c in zip(self.cores, columns, strict=True):
                m = min(n_g, c.size)
                w[:m, core] = c[:m]
        status = np.where(np.isnan(w), _MISSING, np.uint8(0)).astype(np.uint8)
        return Frame(w, timestamp=now, sequence=seq, status=status)

    def stats(self) -> dict:
        out = super().stats()
        out["identity"] = [p.identity for p in self._ports]
        return out


# ---------------------------------------------------------------------------------------------------- openers


def _options(url: str, query: dict[str, str], parsers: dict[str, Callable[[str], object]]) -> dict:
    unknown = sorted(set(query) - set(parsers))
    if unknown:
        raise ValueError(f"{url!r}: unknown option(s) {', '.join(unknown)}; known: {', '.join(sorted(parsers))}")
    out = {}
    for key, value in query.items():
        try:
            out[key] = parsers[key](value)
        except ValueError:
            raise ValueError(f"{url!r}: option {key}={value!r} is not valid") from None
    return out


def _bool(v: str) -> bool:
    if v.lower() in ("1", "true", "yes", "on"):
        return True
    if v.lower() in ("0", "false", "no", "off"):
        return False
    raise ValueError(v)


def _ints(v: str) -> list[int]:
    return [int(x) for x in v.split(",") if x.strip()]


_COMMON = {"wait": _bool, "retry_for": float, "connect_timeout": float}


def _split_common(opts: dict) -> dict:
    return {k: opts.pop(k) for k in ("wait", "retry_for") if k in opts}


def open_illumisense(url: str, **options) -> IllumisenseSource:
    """``illumisense://HOST[:PORT]?channels=cores|single&cores=N&max_payload=B&wait=0|1&retry_for=S``."""
    _, rest, query = parse_url(url)
    host, port = parse_host_port(rest, illumisense.DEFAULT_PORT, what=url)
    opts = _options(url, query, {**_COMMON, "channels": str, "cores": int, "max_payload": int,
                                 "resync_timeout": float, "layout_wait": float})
    if opts.get("channels", "cores") not in ("cores", "single"):
        raise ValueError(f"{url!r}: channels must be 'cores' or 'single'")
    kw = _split_common(opts)
    fiber = options.pop("fiber", None)
    channels_as = opts.pop("channels", "cores")
    n_cores = opts.pop("cores", None)
    if channels_as == "single" and n_cores is None and fiber is not None:
        n_cores = fiber.n_cores
    kw.update(opts)
    kw.update(options)
    return IllumisenseSource(host, port, channels_as=channels_as, n_cores=n_cores, url=url, **kw)


def open_hyperion(url: str, **options) -> HyperionSource:
    """``hyperion://HOST[:PORT]?stream_port=P&channels=1,2,3,4&wait=0|1&retry_for=S``."""
    _, rest, query = parse_url(url)
    host, port = parse_host_port(rest, hyperion.COMMAND_PORT, what=url)
    opts = _options(url, query, {**_COMMON, "stream_port": int, "channels": _ints})
    kw = _split_common(opts)
    kw.update(opts)
    kw.update(options)
    return HyperionSource(host, port, url=url, **kw)


def open_fispec(url: str, **options) -> FispecSource:
    """``fispec://PORT[,PORT…]?rate=HZ&cores=0,1,2,3&window=NM&baudrate=N&wait=0|1&retry_for=S``."""
    _, rest, query = parse_url(url)
    ports = [p for p in rest.split(",") if p]
    if not ports:
        raise ValueError(f"{url!r}: expected fispec://PORT (a device, a pty path or a pyserial URL)")
    opts = _options(url, query, {**_COMMON, "rate": float, "cores": _ints, "window": float, "baudrate": int,
                                 "reply_timeout": float})
    opts.pop("connect_timeout", None)
    kw = _split_common(opts)
    kw.update(opts)
    kw.update(options)
    return FispecSource(ports, url=url, **kw)
