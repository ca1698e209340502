"""The FiSpec driver: :class:`FispecSource`.

``fispec://PORT[,PORT…]`` (pyserial: device path, pty path, ``socket://host:port``, ``loop://``): a FiSpec
device measures one channel, so **one port per fibre core**: the k-th port is fibre core ``cores[k]``
(``cores=0,1,2,3``, default 0, 1, … in port order) and cores without a port are reported missing. After the
``?>`` / ``p?>`` handshake the driver, when it has a fibre model, programs one peak window per grating
(``Ke``, centred on the nominal λ0, ``window`` nm wide, default 3 nm as the public client uses), ``KA``, raw
wavelengths (``OBB,0``) and checks the device took them; without a model it reads the device's own windows.
Then it polls ``P>`` on every port at ``rate`` Hz (default 100). FiSpec has no sample numbers: the driver
numbers polls itself, and a poll that fails counts as a lost sample. A reply of the wrong length or without
``Ende`` is a framing error (input flushed, poll skipped); three in a row, or an I/O error, reconnect.

Common behaviour (opening, reconnect policy, counters): :mod:`twin.io.drivers`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from twin.fiber import FiberModel
from twin.frames import Frame
from twin.io.drivers import COMMON_OPTIONS, MISSING, Driver, split_common
from twin.io.errors import FramingError
from twin.io.fispec import codec as fispec
from twin.io.options import Option, parse_options
from twin.io.source import parse_url
from twin.io.transport import ConnectionLost, open_serial

__all__ = ["FispecSource", "open_fispec"]


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

    START_WAIT = 0.0  #: a serial device that is not there is more likely a wrong path: fail at once by default

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
        status = np.where(np.isnan(w), MISSING, np.uint8(0)).astype(np.uint8)
        return Frame(w, timestamp=now, sequence=seq, status=status)

    def stats(self) -> dict:
        out = super().stats()
        out["identity"] = [p.identity for p in self._ports]
        return out


# ---------------------------------------------------------------------------------------------------- openers


def open_fispec(url: str, **options) -> FispecSource:
    """``fispec://PORT[,PORT…]?rate=HZ&cores=0,1,2,3&window=NM&baudrate=N&wait=0|1&retry_for=S&start_wait=S``."""
    _, rest, query = parse_url(url)
    ports = [p for p in rest.split(",") if p]
    if not ports:
        raise ValueError(f"{url!r}: expected fispec://PORT (a device, a pty path or a pyserial URL)")
    opts = parse_options(url, query, {**COMMON_OPTIONS, "rate": Option("float", low=0.0, low_open=True, high=1e4),
                                      "cores": Option("ints", low=0, high=63),
                                      "window": Option("float", low=0.0, low_open=True),
                                      "baudrate": Option("int", low=1),
                                      "reply_timeout": Option("float", low=0.0, low_open=True)})
    opts.pop("connect_timeout", None)
    kw = split_common(opts)
    kw.update(opts)
    kw.update(options)
    return FispecSource(ports, url=url, **kw)
