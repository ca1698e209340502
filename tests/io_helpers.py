"""Shared helpers of the driver, live-loop and recording tests: real sockets and sources, no mocks."""

from __future__ import annotations

import base64
import os
import socket
import threading
import time
from collections.abc import Callable

import numpy as np

from twin.frames import Frame
from twin.io import illumisense
from twin.io.source import Source, SourceClosed
from twin.synthetic import SyntheticSource

os.environ.setdefault("MPLBACKEND", "Agg")  # the FiSpec client imports matplotlib


def synthetic_frames(n: int, **kw) -> list[Frame]:
    """The first ``n`` frames of an unpaced synthetic source (a pure function of the sample index)."""
    src = SyntheticSource(pace=False, frames=n, **kw)
    return list(src)


def records(frames: list[Frame]) -> list[bytes]:
    """ILLumiSense wire records of ``frames``."""
    return [illumisense.encode_record(f) for f in frames]


class ScriptedServer:
    """A TCP server on 127.0.0.1 that plays one script per accepted connection.

    A script is a callable ``script(conn)`` (send what it likes, then return to close the connection) or bytes
    (sent, then the connection is closed). Connections beyond the scripts are held open silently.
    """

    def __init__(self, scripts: list[bytes | Callable[[socket.socket], None]]):
        self.scripts = list(scripts)
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.settimeout(0.2)
        self.port = self.listener.getsockname()[1]
        self.accepted = 0
        self._stop = threading.Event()
        self._conns: list[socket.socket] = []
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except (TimeoutError, OSError):
                continue
            i = self.accepted
            self.accepted += 1
            if i >= len(self.scripts):
                self._conns.append(conn)
                continue
            threading.Thread(target=self._play, args=(self.scripts[i], conn), daemon=True).start()

    @staticmethod
    def _play(script, conn: socket.socket) -> None:
        try:
            if callable(script):
                script(conn)
            else:
                conn.sendall(script)
        except OSError:
            pass
        finally:
            conn.close()

    def close(self) -> None:
        self._stop.set()
        self.listener.close()
        for c in self._conns:
            c.close()
        self._thread.join(timeout=2)


class ManualSource(Source):
    """A source whose current frame the test sets; ``read`` delivers each new frame once, at ``rate``."""

    def __init__(self, fiber, wavelengths: np.ndarray, rate: float = 200.0):
        self.fiber, self.rate = fiber, rate
        self._lock = threading.Lock()
        self._seq = 0
        self._w = np.array(wavelengths, dtype=np.float64)
        self._closed = False
        self._next = time.monotonic()

    def set(self, wavelengths: np.ndarray) -> None:
        with self._lock:
            self._w = np.array(wavelengths, dtype=np.float64)

    @property
    def wavelengths(self) -> np.ndarray:
        with self._lock:
            return self._w.copy()

    def read(self, timeout: float | None = None) -> Frame | None:
        if self._closed:
            raise SourceClosed("manual source closed")
        wait = self._next - time.monotonic()
        if wait > 0:
            if timeout is not None and timeout < wait:
                time.sleep(timeout)
                return None
            time.sleep(wait)
        self._next = max(self._next + 1 / self.rate, time.monotonic() - 1 / self.rate)
        with self._lock:
            frame = Frame(self._w.copy(), timestamp=time.time(), sequence=self._seq)
        self._seq += 1
        return frame

    def close(self) -> None:
        self._closed = True


def wait_until(predicate: Callable[[], bool], timeout: float = 20.0, poll: float = 0.02) -> bool:
    """Poll ``predicate`` until it holds or ``timeout`` s pass (generous: tests run on loaded machines)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll)
    return predicate()


def singles(batch) -> list:
    """The single frames of what a source's ``read_batch`` returned (None: none)."""
    return [] if batch is None else list(batch)


def request(port: int, path: str, host: str | None = None, origin: str | None = None, *, upgrade: bool = False,
            rcvbuf: int | None = None, headers: tuple[str, ...] = ()) -> tuple[int, socket.socket]:
    """Send one raw HTTP/1.1 GET to 127.0.0.1 (a websocket handshake with ``upgrade``; ``headers``: more header
    lines); (status, the open socket)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)  # before connecting: the window it offers
    sock.settimeout(10.0)
    sock.connect(("127.0.0.1", port))
    lines = [f"GET {path} HTTP/1.1", f"Host: {f'127.0.0.1:{port}' if host is None else host}"]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    if upgrade:
        lines += ["Upgrade: websocket", "Connection: Upgrade", "Sec-WebSocket-Version: 13",
                  "Sec-WebSocket-Key: " + base64.b64encode(os.urandom(16)).decode()]
    else:
        lines.append("Connection: close")
    lines += headers
    sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
    head = b""
    while b"\r\n" not in head:
        chunk = sock.recv(4096)
        if not chunk:
            break
        head += chunk
    return int(head.split(b" ", 2)[1]), sock
