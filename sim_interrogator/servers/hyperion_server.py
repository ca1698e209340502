"""Luna/Micron Optics Hyperion TCP server (docs/protocols.md §3): command port and peak-stream port.

- Command port (51971 by default): each connection sends requests and gets one response each, from
  :func:`twin.io.hyperion.respond` with the server's :class:`~twin.io.hyperion.InstrumentState` and the latest
  frame (``#GetPeaks``). Requests are parsed defensively: a command longer than :data:`MAX_COMMAND` or an
  argument longer than :data:`MAX_ARGUMENT` bytes is refused from its header, before anything is buffered, so a
  partial request holds at most 8 + 256 + 8192 bytes; a request the responder cannot handle gets an error
  status (never an empty reply, never a dead thread). A connection that sends a malformed or oversized request
  header gets an error response and is closed (a binary stream without sync marker cannot be re-entered);
  other connections are unaffected. At most :data:`~sim_interrogator.servers.common.MAX_CLIENTS` (32)
  command connections and as many stream clients are served at once: one more command connection evicts the
  one that has been quiet longest (no request since), one more stream client the one furthest behind
  (:class:`~sim_interrogator.servers.common.TcpBroadcaster`); both counted (``evicted``). A command connection
  that sends no request for ``idle_timeout`` s (30 s) is closed, and counted (``idle_closed``): idle
  connections never lock a real client out.
- Peak stream (command port + 1 = 51972 by default): every frame is pushed to every connected client as one
  success response whose content is the peak data (:func:`twin.io.hyperion.encode_stream_frame`).

One instrument channel per core (channel k + 1 = core k); the reported channel count is the fibre's core count
(at least 1), the laser scan speed the source's rate (added to the available speeds if it is not one of them).
"""

from __future__ import annotations

import socket
import threading
import time

from sim_interrogator.servers.common import IDLE_TIMEOUT, MAX_CLIENTS, FramePump, TcpBroadcaster, log
from twin.frames import Frame
from twin.io import hyperion
from twin.io.errors import FramingError
from twin.io.source import Source

__all__ = ["MAX_ARGUMENT", "MAX_COMMAND", "HyperionServer"]

#: longest command name accepted, bytes (the longest real one, #GetMaximumPeakCountPerDutChannel, has 33)
MAX_COMMAND = 256
#: longest argument accepted, bytes (the simulated instrument's commands take at most one short number)
MAX_ARGUMENT = 8192
#: status of the error response to a malformed request (the codec's responder uses 1–3)
STATUS_BAD_REQUEST = 4
#: status of the error response when handling a request failed
STATUS_INTERNAL = 5


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
    max_clients : int
        Most command connections (and stream clients) at once.
    idle_timeout : float
        Longest a command connection may send no request, and a stream client take no data, s.
    """

    def __init__(self, source: Source, host: str = "127.0.0.1", port: int = hyperion.COMMAND_PORT, *,
                 stream_port: int | None = None, rate: float | None = None, log: bool = False,
                 max_clients: int = MAX_CLIENTS, idle_timeout: float = IDLE_TIMEOUT):
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
        self.stream = TcpBroadcaster(host, stream_port, name="hyperion-stream", log=log, max_clients=max_clients,
                                     idle_timeout=idle_timeout)
        self.pump = FramePump(source, rate=rate)
        self.pump.subscribe(self._publish)
        self.log = log
        self.max_clients = int(max_clients)
        self.idle_timeout = float(idle_timeout)
        self.requests = 0
        self.bad_requests = 0
        self.failed_requests = 0
        self.evicted = 0
        self.idle_closed = 0
        self._closed = threading.Event()
        self._conns: dict[socket.socket, float] = {}  # connection → when it last sent a request (or connected)
        self._conns_lock = threading.Lock()
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
            with self._conns_lock:
                victim = min(self._conns, key=self._conns.get) if len(self._conns) >= self.max_clients else None
                if victim is not None:
                    del self._conns[victim]  # its thread closes it; it is no longer counted, nor chosen again
                self._conns[conn] = time.monotonic()
            if victim is not None:
                # the newcomer is served; the connection quiet longest makes way (a real client asks)
                self.evicted += 1
                _shut(victim)
                if self.log and self.evicted == 1:
                    log(f"hyperion: more than {self.max_clients} command connections; the one quiet longest is "
                        "closed for each newcomer (counted, not shown again)")
            conn.settimeout(self.idle_timeout)
            threading.Thread(target=self._serve, args=(conn,), name="hyperion-command", daemon=True).start()

    def _respond(self, req: hyperion.Request) -> bytes:
        """The response to one request; an error status when handling it fails (the thread must live on)."""
        try:
            with self._lock:
                return hyperion.respond(req, self.state, frame=self.pump.latest)
        except Exception as exc:
            self.failed_requests += 1
            if self.log:
                log(f"hyperion: {req.command[:40]!r} failed: {type(exc).__name__}: {str(exc)[:80]}")
            return hyperion.encode_response(message=f"Request failed: {type(exc).__name__}", status=STATUS_INTERNAL)

    def _serve(self, conn: socket.socket) -> None:
        decoder = hyperion.RequestDecoder(max_argument=MAX_ARGUMENT, max_command=MAX_COMMAND)
        try:
            while not self._closed.is_set():
                try:
                    data = conn.recv(65536)
                except TimeoutError:
                    self.idle_closed += 1
                    break
                if not data:
                    break
                with self._conns_lock:
                    if conn in self._conns:
                        self._conns[conn] = time.monotonic()
                try:
                    requests = decoder.feed(data)
                except FramingError as exc:
                    requests, error = [], exc
                else:
                    error = decoder.last_error if decoder.failed else None
                for req in requests:
                    self.requests += 1
                    conn.sendall(self._respond(req))
                if error is not None:
                    # the stream cannot be re-entered: say why, then close this connection only
                    self.bad_requests += 1
                    conn.sendall(hyperion.encode_response(message=f"Bad request: {error.what}"[:200],
                                                          status=STATUS_BAD_REQUEST))
                    break
        except OSError:
            pass
        finally:
            conn.close()
            with self._conns_lock:
                self._conns.pop(conn, None)

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
        with self._conns_lock:
            conns = list(self._conns)
        for c in conns:
            _shut(c)
        self.stream.close()
        self.pump.stop()
        self.source.close()

    def stats(self) -> dict:
        return {"frames": self.pump.frames, "requests": self.requests, "bad_requests": self.bad_requests,
                "failed_requests": self.failed_requests, "evicted": self.evicted + self.stream.evicted,
                "idle_closed": self.idle_closed + self.stream.dropped_idle,
                "stream_clients": self.stream.clients, "behind_events": self.pump.meter.behind_events}

    def __enter__(self) -> HyperionServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


def _shut(conn: socket.socket) -> None:
    """End a connection from another thread: its reader wakes with no data and closes it."""
    try:
        conn.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
