"""Plumbing shared by the protocol servers: a thread that pumps frames out of a Source, a TCP server that
pushes the same bytes to every connected client, and the one log writer every server thread uses.

Local clients that connect and then do nothing never lock the real client out: a client that takes no data for
:data:`IDLE_TIMEOUT` s is dropped, and a connection beyond :data:`MAX_CLIENTS` evicts the client furthest
behind (the most data waiting for it, ours and the kernel's; of equals the newest, so a client that reads keeps
its place while idle connections make way for each other and for it) instead of being refused.

Log lines go through :func:`log`: one ``write`` of the whole line under one lock, so lines from the pump, the
accept threads and the client threads never interleave or leave blank lines (``print`` writes the text and the
newline separately).
"""

from __future__ import annotations

import fcntl
import queue
import socket
import struct
import sys
import termios
import threading
import time
from collections.abc import Callable

from twin.frames import Frame
from twin.io.rate import RateMeter
from twin.io.source import Source, SourceClosed

__all__ = ["IDLE_TIMEOUT", "MAX_CLIENTS", "FramePump", "TcpBroadcaster", "log", "unsent_bytes"]

#: most clients a server port serves at once; one more evicts the client furthest behind (counted)
MAX_CLIENTS = 32
#: s a client may take no data (a stream client) or send no request (a command connection) before it is dropped
IDLE_TIMEOUT = 30.0

#: a client with no more than this waiting for it (messages queued, bytes in the kernel) keeps up
SLACK_MESSAGES, SLACK_BYTES = 8, 64 << 10

_LOG_LOCK = threading.Lock()


def log(message: str, stream=None) -> None:
    """Write one line ``twin serve: message`` on stderr (or ``stream``), whole, under the servers' one lock."""
    line = "twin serve: " + " ".join(str(message).split("\n")) + "\n"
    with _LOG_LOCK:
        out = stream if stream is not None else sys.stderr
        try:
            out.write(line)
            out.flush()
        except (OSError, ValueError):  # a closed stderr must not kill a server thread
            pass


class FramePump:
    """Reads a Source on a thread, keeps its latest frame and hands every frame to the subscribers.

    Parameters
    ----------
    source : Source
        Any source of frames; it owns its own pacing (the synthetic and simulated sources run in real time).
    rate : float, optional
        Additionally release frames no faster than this, Hz, on an absolute schedule (for sources that deliver
        as fast as asked, e.g. a replay at maximum speed). A pump more than 1 s behind schedule restarts the
        schedule instead of bursting.

    Attributes
    ----------
    latest : Frame or None
        The most recent frame (what request/response protocols answer with).
    frames : int
        Frames pumped.
    meter : RateMeter
        Frames pumped per second against the source's nominal rate: when the source falls behind real time
        (a simulator slower than the clock), the pump says so once on stderr and counts it
        (``meter.behind_events``).
    ended : threading.Event
        Set when the source ended, failed or the pump was stopped.
    error : BaseException or None
        Why the source failed, if it did.
    """

    def __init__(self, source: Source, *, rate: float | None = None):
        self.source = source
        self.rate = rate
        self.latest: Frame | None = None
        self.frames = 0
        self.error: BaseException | None = None
        self.ended = threading.Event()
        self._subscribers: list[Callable[[Frame], None]] = []
        self._stop = threading.Event()
        self._first = threading.Event()
        self._thread = threading.Thread(target=self._run, name="frame-pump", daemon=True)
        self.meter = RateMeter(rate or getattr(source, "rate", None))

    def subscribe(self, fn: Callable[[Frame], None]) -> None:
        """Call ``fn(frame)`` (on the pump thread) for every frame from now on."""
        self._subscribers.append(fn)

    def start(self) -> FramePump:
        self._thread.start()
        return self

    def wait_first(self, timeout: float | None = None) -> bool:
        """Block until the first frame has been pumped; True if it was."""
        return self._first.wait(timeout)

    def _run(self) -> None:
        t0 = None
        k = 0
        try:
            while not self._stop.is_set():
                try:
                    # one frame at a time: a source that runs behind real time must not be sent in bursts
                    frame = self.source.read(0.1)
                except SourceClosed:
                    break
                if frame is None:
                    continue
                if self.rate:
                    now = time.monotonic()
                    if t0 is None or now - (t0 + k / self.rate) > 1.0:
                        t0, k = now, 0
                    wait = t0 + k / self.rate - now
                    if wait > 0:
                        time.sleep(wait)
                    k += 1
                self.latest = frame
                self.frames += 1
                if self.meter.add([frame.timestamp]) and self.meter.behind_events == 1:
                    m = self.meter
                    log(f"the source delivers {m.arrival_rate:.0f} frames/s, below its nominal {m.nominal:g} Hz: it "
                        "runs behind real time (said once; counted in behind_events)")
                self._first.set()
                for fn in self._subscribers:
                    fn(frame)
        except Exception as exc:  # reported through .error; servers must not die silently
            self.error = exc
            log(f"source failed: {exc}")
        finally:
            self.ended.set()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self.ended.set()


def unsent_bytes(sock: socket.socket) -> int:
    """Bytes written to ``sock`` that its peer has not yet taken (the kernel's send queue; 0 where unknown)."""
    try:
        return struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0"))[0]
    except (OSError, ValueError):
        return 0


class _Client:
    def __init__(self, sock: socket.socket, addr, owner: TcpBroadcaster, max_queue: int, order: int):
        self.sock, self.addr, self.owner, self.order = sock, addr, owner, order
        self.queue: queue.Queue[bytes | None] = queue.Queue(max_queue)
        self.alive = True
        self.sent = 0
        self.thread = threading.Thread(target=self._run, name=f"{owner.name}-client", daemon=True)

    def behind(self) -> tuple[bool, int, int, int]:
        """How far behind the client is, for eviction: (far behind, messages queued, bytes in the kernel,
        arrival). A reader has at most a record or two in flight: below :data:`SLACK_MESSAGES` messages and
        :data:`SLACK_BYTES` bytes a client counts as keeping up, and of those the newest goes first."""
        q, u = self.queue.qsize(), unsent_bytes(self.sock) if self.alive else 0
        if q > SLACK_MESSAGES or u > SLACK_BYTES:
            return True, q, u, self.order
        return False, 0, 0, self.order

    def _run(self) -> None:
        why = "disconnected"
        try:
            while True:
                data = self.queue.get()
                if data is None:
                    break
                self.sock.sendall(data)  # the socket's timeout is the idle timeout: no progress, no client
                self.sent += 1
        except TimeoutError:
            why = f"dropped: took no data for {self.owner.idle_timeout:g} s"
            self.owner.dropped_idle += 1
        except OSError:
            pass  # the client went away; the broadcaster notices below
        finally:
            self.owner._remove(self, why)

    def close(self) -> None:
        self.alive = False
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        try:  # wake the sender if it waits for data (if it is sending, the closed socket wakes it)
            self.queue.put_nowait(None)
        except queue.Full:
            pass


class TcpBroadcaster:
    """A TCP server pushing the same bytes to every connected client; clients come and go freely.

    Each client has its own sender thread and queue, so a slow client delays nobody: when its queue holds
    ``max_queue`` messages (4096 records ≈ 4 s at 1 kHz) it is disconnected and counted in ``dropped_slow``; a
    client that takes no data for ``idle_timeout`` s is disconnected and counted in ``dropped_idle``. At most
    ``max_clients`` clients are served at once (one thread each); a connection beyond them evicts the client
    furthest behind (the module notes), counted in ``evicted``.

    Parameters
    ----------
    host, port : str, int
        Where to listen (port 0: any free port; see :attr:`address`).
    name : str
        Used in thread names and messages.
    max_queue : int
        Messages buffered per client.
    on_connect : callable, optional
        ``on_connect(sock)`` runs in the accept thread before the client joins the broadcast.
    log : bool
        Print connects and disconnects on stderr.
    max_clients : int
        Most clients at once.
    idle_timeout : float
        Longest a client may take no data while some waits for it, s.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, *, name: str = "tcp", max_queue: int = 4096,
                 on_connect: Callable[[socket.socket], None] | None = None, log: bool = False,
                 max_clients: int = MAX_CLIENTS, idle_timeout: float = IDLE_TIMEOUT):
        if not max_clients >= 1 or not idle_timeout > 0:
            raise ValueError(f"{name}: max_clients >= 1 and idle_timeout > 0 needed, got {max_clients}, "
                             f"{idle_timeout}")
        self.name, self.max_queue, self.on_connect, self.log = name, max_queue, on_connect, log
        self.max_clients = int(max_clients)
        self.idle_timeout = float(idle_timeout)
        try:
            self._listener = socket.create_server((host, port), reuse_port=False)
        except OSError as exc:
            raise OSError(f"{name}: cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        self._listener.settimeout(0.2)
        self.address: tuple[str, int] = self._listener.getsockname()[:2]
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self.connections = 0
        self.disconnects = 0
        self.dropped_slow = 0
        self.dropped_idle = 0
        self.evicted = 0
        self.published = 0
        self._thread = threading.Thread(target=self._accept, name=f"{name}-accept", daemon=True)

    def start(self) -> TcpBroadcaster:
        self._thread.start()
        return self

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                sock, addr = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            with self._lock:
                full = list(self._clients) if len(self._clients) >= self.max_clients else None
            if full:
                # the newcomer is served; the one furthest behind (of equals the newest) makes way
                victim = max(full, key=_Client.behind)
                self.evicted += 1
                self._remove(victim, f"evicted: {self.max_clients} clients, this one furthest behind")
            sock.settimeout(self.idle_timeout)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            try:
                if self.on_connect is not None:
                    self.on_connect(sock)
            except OSError:
                sock.close()
                continue
            with self._lock:
                client = _Client(sock, addr, self, self.max_queue, self.connections)
                self._clients.append(client)
                self.connections += 1
            client.thread.start()
            if self.log:
                log(f"{self.name}: client {addr[0]}:{addr[1]} connected")

    def _remove(self, client: _Client, why: str) -> None:
        with self._lock:
            if client not in self._clients:
                return
            self._clients.remove(client)
            self.disconnects += 1
        client.close()
        # evictions are said once (a storm of connections must not flood the log); all are counted
        if self.log and not self._closed.is_set() and (not why.startswith("evicted") or self.evicted == 1):
            log(f"{self.name}: client {client.addr[0]}:{client.addr[1]} {why}"
                + (" (further evictions counted, not shown)" if why.startswith("evicted") else ""))

    def publish(self, data: bytes) -> None:
        """Queue ``data`` for every connected client."""
        self.published += 1
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            try:
                c.queue.put_nowait(data)
            except queue.Full:
                self.dropped_slow += 1
                self._remove(c, f"dropped: more than {self.max_queue} messages behind")

    def close(self) -> None:
        """Stop accepting, disconnect every client. Idempotent."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._listener.close()
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            c.close()
            try:
                c.queue.put_nowait(None)
            except queue.Full:
                pass
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
