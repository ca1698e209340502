"""Byte transports for the drivers: TCP client sockets and pyserial ports, with explicit timeouts, and the
reconnect policy they share.

Everything here moves bytes and nothing else; framing lives in the codec modules (:mod:`twin.io.illumisense`,
:mod:`twin.io.fispec`, :mod:`twin.io.hyperion`) and the drivers (:mod:`twin.io.drivers`) glue the two.

Errors are :class:`OSError` subclasses whose message names the endpoint and what failed
(``illumisense://127.0.0.1:2055: cannot connect to 127.0.0.1:2055: connection refused``), so the command line
reports them as one line.
"""

from __future__ import annotations

import os
import socket
import time
from dataclasses import dataclass

__all__ = [
    "Backoff",
    "ConnectionLost",
    "TcpClient",
    "connect_tcp",
    "open_serial",
    "parse_host_port",
    "read_exactly",
]


class ConnectionLost(ConnectionError):
    """The peer closed the connection or the port disappeared (EOF, reset, device gone)."""


def parse_host_port(text: str, default_port: int | None, *, what: str = "address") -> tuple[str, int]:
    """``HOST[:PORT]`` (IPv6 literals in brackets, ``[::1]:2055``) → (host, port).

    Parameters
    ----------
    text : str
        The authority part of a URL.
    default_port : int or None
        Port when ``text`` has none; None makes the port mandatory.
    what : str
        Used in error messages.

    Raises
    ------
    ValueError
        No host, a port that is not an integer in 0..65535, or a missing mandatory port.
    """
    text = text.strip().rstrip("/")
    host, port_text = text, ""
    if text.startswith("["):
        end = text.find("]")
        if end < 0:
            raise ValueError(f"{what} {text!r}: unclosed '[' in an IPv6 address")
        host, rest = text[1:end], text[end + 1 :]
        if rest and not rest.startswith(":"):
            raise ValueError(f"{what} {text!r}: expected ':PORT' after the IPv6 address")
        port_text = rest[1:]
    elif text.count(":") == 1:
        host, port_text = text.split(":")
    if not host:
        raise ValueError(f"{what} {text!r}: expected HOST or HOST:PORT")
    if not port_text:
        if default_port is None:
            raise ValueError(f"{what} {text!r}: expected HOST:PORT (no default port for this protocol)")
        return host, int(default_port)
    if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise ValueError(f"{what} {text!r}: port {port_text!r} is not an integer in 0..65535")
    return host, int(port_text)


@dataclass
class Backoff:
    """Exponential reconnect delays: ``initial``, ×``factor`` after each failure, capped at ``maximum`` (s).

    The first retry after a connection that *worked* is immediate (a server restart is usually quick); the
    delay grows only while attempts keep failing, and :meth:`reset` is called once a connection has delivered
    data again (not merely accepted: a server that accepts and closes at once must not cause a busy loop).

    Attributes
    ----------
    initial, factor, maximum : float
        First delay (s), growth factor, largest delay (s).
    failures : int
        Consecutive failed attempts so far.
    """

    initial: float = 0.1
    factor: float = 2.0
    maximum: float = 5.0
    failures: int = 0

    def delay(self) -> float:
        """Delay before the next attempt, s (0 before the first failure)."""
        if self.failures == 0:
            return 0.0
        return min(self.maximum, self.initial * self.factor ** (self.failures - 1))

    def failed(self) -> float:
        """Record a failed attempt; return the delay before the next one, s."""
        self.failures += 1
        return self.delay()

    def reset(self) -> None:
        self.failures = 0


def connect_tcp(host: str, port: int, *, timeout: float = 3.0, label: str = "") -> socket.socket:
    """A connected TCP socket (TCP_NODELAY on, blocking with per-call timeouts set by the caller).

    Parameters
    ----------
    host, port
        Where to connect.
    timeout : float
        Connect timeout, s.
    label : str
        Prefix of error messages (the URL being opened).

    Raises
    ------
    OSError
        With a message naming ``label``, the address and the reason (refused, timed out, unknown host).
    """
    prefix = f"{label}: " if label else ""
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except TimeoutError:
        raise TimeoutError(f"{prefix}cannot connect to {host}:{port}: timed out after {timeout:g} s") from None
    except socket.gaierror as exc:
        raise OSError(f"{prefix}cannot resolve host {host!r}: {exc.strerror or exc}") from None
    except OSError as exc:
        reason = (exc.strerror or str(exc)).lower()
        raise type(exc)(exc.errno, f"{prefix}cannot connect to {host}:{port}: {reason}") from None
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


class TcpClient:
    """A TCP connection that reads with timeouts and reports a closed peer as :class:`ConnectionLost`.

    Parameters
    ----------
    host, port
        Where to connect.
    connect_timeout : float
        s.
    label : str
        Prefix of error messages.
    recv_size : int
        Bytes asked of each ``recv`` (64 KiB holds ~28 ILLumiSense records of 7 × 18 gratings).
    """

    def __init__(
        self, host: str, port: int, *, connect_timeout: float = 3.0, label: str = "", recv_size: int = 1 << 16
    ):
        self.host, self.port, self.label = host, port, label
        self.recv_size = recv_size
        self.sock: socket.socket | None = connect_tcp(host, port, timeout=connect_timeout, label=label)

    def recv(self, timeout: float | None) -> bytes:
        """Bytes available within ``timeout`` s (b"" when none arrived; None blocks).

        Raises
        ------
        ConnectionLost
            The peer closed or reset the connection.
        """
        if self.sock is None:
            raise ConnectionLost(f"{self.label}: connection is closed")
        self.sock.settimeout(None if timeout is None else max(0.0, timeout))
        try:
            data = self.sock.recv(self.recv_size)
        except (TimeoutError, BlockingIOError):
            return b""
        except OSError as exc:
            raise ConnectionLost(f"{self.label}: connection to {self.host}:{self.port} lost: {exc}") from None
        if not data:
            raise ConnectionLost(f"{self.label}: {self.host}:{self.port} closed the connection")
        return data

    def sendall(self, data: bytes, timeout: float = 3.0) -> None:
        """Send everything within ``timeout`` s; ConnectionLost otherwise."""
        if self.sock is None:
            raise ConnectionLost(f"{self.label}: connection is closed")
        self.sock.settimeout(timeout)
        try:
            self.sock.sendall(data)
        except OSError as exc:
            raise ConnectionLost(f"{self.label}: sending to {self.host}:{self.port} failed: {exc}") from None

    def close(self) -> None:
        if self.sock is not None:
            try:
                self.sock.close()
            finally:
                self.sock = None


def read_exactly(read, n: int, timeout: float, *, what: str = "reply") -> bytes:
    """Exactly ``n`` bytes from ``read(max_bytes, remaining_s) -> bytes`` within ``timeout`` s.

    Parameters
    ----------
    read : callable
        Returns up to ``max_bytes`` bytes, possibly none, waiting at most ``remaining_s``.
    n : int
        Bytes wanted.
    timeout : float
        Total time allowed, s.
    what : str
        Named in the error.

    Raises
    ------
    TimeoutError
        Fewer than ``n`` bytes arrived in time (the message gives how many did).
    """
    out = bytearray()
    deadline = time.monotonic() + timeout
    while len(out) < n:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError(f"{what}: {len(out)} of {n} bytes arrived within {timeout:g} s")
        out += read(n - len(out), remaining)
    return bytes(out)


def open_serial(url: str, *, baudrate: int = 115200, timeout: float = 0.05, label: str = ""):
    """A pyserial port from a device path, a pty path or a pyserial URL (``socket://``, ``loop://``, …).

    Parameters
    ----------
    url : str
        Passed to :func:`serial.serial_for_url`.
    baudrate : int
        Bits per second (ignored by ptys and sockets).
    timeout : float
        Read timeout, s; writes time out after 1 s.
    label : str
        Prefix of error messages.

    Raises
    ------
    OSError
        (``serial.SerialException`` is one) naming the port and the reason.
    """
    import serial

    prefix = f"{label}: " if label else ""
    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout, write_timeout=1.0)
    except (serial.SerialException, OSError, ValueError) as exc:
        # pyserial's text repeats the errno and the path ("[Errno 2] could not open port P: [Errno 2] … 'P'")
        errno = getattr(exc, "errno", None)
        reason = os.strerror(errno).lower() if isinstance(errno, int) and errno > 0 else str(exc)
        if errno:  # OSError(errno, text) keeps the kind (FileNotFoundError, PermissionError, …)
            raise OSError(errno, f"{prefix}cannot open serial port {url!r}: {reason}") from None
        raise OSError(f"{prefix}cannot open serial port {url!r}: {reason}") from None
