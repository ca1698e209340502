"""Luna/Micron Optics Hyperion TCP server (docs/protocols.md §3): command port and peak-stream port.

- Command port (51971 by default): each connection sends requests and gets one response each, from
  :func:`twin.io.hyperion.respond` with the server's :class:`~twin.io.hyperion.InstrumentState` and the latest
  frame (``#GetPeaks``). A connection that sends a malformed request header is closed (a binary stream without
  sync marker cannot be re-entered); other connections are unaffected.
- Peak stream (command port + 1 = 51972 by default): every frame is pushed to every connected client as one
  success response whose content is the peak data (:func:`twin.io.hyperion.encode_stream_frame`).

One instrument channel per core (channel k + 1 = core k); the reported channel count is the fibre's core count
(at least 1), the laser scan speed the source's rate (added to the available speeds if it is not one of them).
"""

from __future__ import annotations

import socket
import threading

from sim_interrogator.servers.common import FramePump, TcpBroadcaster
from twin.frames import Frame
from twin.io import hyperion
from twin.io.errors import FramingError
from twin.io.source import Source

__all__ = ["HyperionServer"]


class HyperionServer:
    """Serve a Source as a Hyperion instrument.

    Parameters
    ----------
    source : Source
        Frames (owned: closed by :meth:`close`).
    host : str
        Listening address (127.0.0.1 by default).
    port : int
        Command port; 0 picks free ports for both.
    stream_port : int, optional
        Peak-stream port; default ``port + 1`` (or a free port when ``port`` is 0).
    rate : float, optional
        Extra pacing, Hz (see :class:`FramePump`).
    log : bool
        Print client connects and disconnects on stderr.
    """

    def __init__(self, source: Source, host: str = "127.0.0.1", port: int = hyperion.COMMAND_PORT, *,
                 stream_port: int | None = None, rate: float | None = None, log: bool = False):
        self.source = source
        fiber = getattr(source, "fiber", None)
        speed = round(getattr(source, "rate", None) or rate or 1000)
        state = hyperion.InstrumentState(channel_count=max(1, fiber.n_cores if fiber else 4))
        speeds = sorted({*state.available_scan_speeds, speed})
        state.available_scan_speeds = tuple(speeds)
        state.laser_scan_speed = speed
        self.state = state
        self._lock = threading.Lock()  # #SetLaserScanSpeed mutates the state
        if stream_port is None:
            stream_port = 0 if port == 0 else port + 1
        try:
            self._listener = socket.create_server((host, port))
        except OSError as exc:
            raise OSError(f"hyperion: cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        self._listener.settimeout(0.2)
        self.stream = TcpBroadcaster(host, stream_port, name="hyperion-stream", log=log)
        self.pump = FramePump(source, rate=rate)
        self.pump.subscribe(self._publish)
        self.log = log
        self.requests = 0
        self.bad_requests = 0
        self._closed = threading.Event()
        self._conns: list[socket.socket] = []
        self._thread = threading.Thread(target=self._accept, name="hyperion-commands", daemon=True)

    @property
    def address(self) -> tuple[str, int]:
        """Command port address."""
        return self._listener.getsockname()[:2]

    @property
    def stream_address(self) -> tuple[str, int]:
        return self.stream.address

    def _publish(self, frame: Frame) -> None:
        if self.stream.clients:
            self.stream.publish(hyperion.encode_stream_frame(frame))

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            conn.settimeout(None)
            self._conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), name="hyperion-command", daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        decoder = hyperion.RequestDecoder()
        try:
            while not self._closed.is_set():
                data = conn.recv(65536)
                if not data:
                    break
                try:
                    requests = decoder.feed(data)
                except FramingError:
                    self.bad_requests += 1
                    break
                for req in requests:
                    self.requests += 1
                    with self._lock:
                        out = hyperion.respond(req, self.state, frame=self.pump.latest)
                    conn.sendall(out)
                if decoder.failed:
                    self.bad_requests += 1
                    break
        except OSError:
            pass
        finally:
            conn.close()
            if conn in self._conns:
                self._conns.remove(conn)

    def start(self) -> HyperionServer:
        self.stream.start()
        self._thread.start()
        self.pump.start()
        return self

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self._listener.close()
        for c in list(self._conns):
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self.stream.close()
        self.pump.stop()
        self.source.close()

    def stats(self) -> dict:
        return {"frames": self.pump.frames, "requests": self.requests, "bad_requests": self.bad_requests,
                "stream_clients": self.stream.clients}

    def __enter__(self) -> HyperionServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
