"""OpenIGTLink for 3D Slicer: the live catheter shape, its tip pose and the truth, served over TCP.

``twin live URL --igtl [HOST:]PORT`` starts an :class:`IgtlServer` (127.0.0.1 unless a host is given) and feeds
it through :class:`IgtlSink`, a :class:`twin.live.LiveLoop` sink. For each reconstructed frame, at most
``rate`` times a second, every connected client receives:

- ``POLYDATA`` device ``CatheterShape``: the reconstructed centreline, points in mm, one polyline in the
  LINES cell array (no vertices or polygons); when the shape carries its uncertainty
  (:class:`twin.uncertainty.Uncertainty`), two point-scalar attributes: ``Sigma`` (the 1σ lateral radius of
  each point, mm) and ``Confidence95`` (the radius of the 95 % confidence tube, mm) — in Slicer, colour the
  model by either, or sweep a tube of that radius;
- ``TRANSFORM`` device ``CatheterTip``: the tip pose (material frame d1 d2 d3 as the rotation's columns,
  position in mm);
- ``POLYDATA`` device ``CatheterTruth``: the true centreline, when the source carries a truth (the twin).

In 3D Slicer: module OpenIGTLinkIF, add a connector of type *client* to the host and port, tick *Active*; the
two models and the transform appear as nodes named after the devices.

Placement: Slicer shows everything in one coordinate system. A shape lives in the fibre's base frame; with a
truth whose material frames are known at s = 0 (the twin), the shape is put at the truth's base pose, so shape
and truth overlay as in the browser viewer (:func:`twin.viewer.geometry.placement`); else both are sent as
they are (the base frame is the world).

The messages are written here from the OpenIGTLink specification (header version 1): a 58-byte big-endian
header (version uint16, type char[12], device name char[20], timestamp uint64 with seconds in the upper and
the fraction of a second in the lower 32 bits, body size uint64, CRC-64 of the body) and the body. The CRC is
ECMA-182 (polynomial 0x42F0E1EBA9EA3693, initial value 0, no reflection, no final XOR). TRANSFORM's body is
12 big-endian float32: the upper 3×4 of the homogeneous matrix column by column (R11 R21 R31 R12 … R33, then
TX TY TZ in mm). POLYDATA's body: 10 uint32 counts (NPOINTS, NVERTICES, SIZE_VERTICES, NLINES, SIZE_LINES,
NPOLYGONS, SIZE_POLYGONS, NTRIANGLE_STRIPS, SIZE_TRIANGLE_STRIPS, NATTRIBUTES; sizes in bytes), the points as
float32 x y z, then each cell array as (count, index…) uint32 words, then per attribute a 6-byte header (type
uint8, 0 for point scalars; number of components uint8; number of values uint32), then the attributes' names,
each NUL-terminated, with one NUL more when their total length is odd, then each attribute's values as
big-endian float32. No library is needed (pyigtl, the
obvious one, writes POLYDATA cell arrays in the wrong byte order).

The server never slows the live loop: :meth:`IgtlServer.publish` queues a whole bundle of messages for each
client and returns; one thread accepts clients, sends what is queued and reads (and discards) what clients
send. A client that does not keep up has its oldest bundles dropped whole (counted), never cut, so its stream
stays parseable and the newest shape is the one waiting; what waits for one client is bounded (``max_backlog``
bytes of whole bundles, plus the one being sent). At most ``max_clients`` (16) clients at once: one more
evicts the client furthest behind (of equals the newest), counted, so connections that never read cannot lock
3D Slicer out. A client that disconnects is forgotten. Clients may come and go at any time.
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import struct
import sys
import threading
import time
from collections import deque
from typing import TYPE_CHECKING, TextIO

import numba
import numpy as np

from twin import _jit_cache  # noqa: F401  (before the first cached kernel; see its docstring)
from twin.frames import Frame, Shape, Truth

if TYPE_CHECKING:  # pragma: no cover
    from twin.live import LiveStatus

__all__ = [
    "HEADER_SIZE",
    "MAX_CLIENTS",
    "IgtlServer",
    "IgtlSink",
    "crc64",
    "message",
    "parse_address",
    "polydata_body",
    "transform_body",
]

HEADER_SIZE = 58
#: ECMA-182, as OpenIGTLink's header specifies
CRC64_POLY = 0x42F0E1EBA9EA3693
_HEADER = struct.Struct(">H12s20sQQQ")


def _crc_table() -> np.ndarray:
    """CRC-64 of each byte value (MSB first), the usual 256-entry table."""
    crc = np.arange(256, dtype=np.uint64) << np.uint64(56)
    top, poly = np.uint64(1) << np.uint64(63), np.uint64(CRC64_POLY)
    for _ in range(8):
        crc = np.where(crc & top, (crc << np.uint64(1)) ^ poly, crc << np.uint64(1))
    return crc


_TABLE = _crc_table()


@numba.njit(cache=True)
def _crc64(data: np.ndarray, table: np.ndarray) -> np.uint64:  # pragma: no cover (compiled)
    crc = np.uint64(0)
    for byte in data:
        crc = table[np.uint64((crc >> np.uint64(56)) ^ np.uint64(byte)) & np.uint64(0xFF)] ^ (crc << np.uint64(8))
    return crc


def crc64(data: bytes) -> int:
    """CRC-64/ECMA-182 of ``data`` as OpenIGTLink computes it (init 0, MSB first, no final XOR)."""
    return int(_crc64(np.frombuffer(bytes(data), dtype=np.uint8), _TABLE))


def _ascii(text: str, size: int, what: str) -> bytes:
    raw = text.encode("ascii")
    if len(raw) > size:
        raise ValueError(f"OpenIGTLink {what} {text!r} is longer than {size} characters")
    return raw


def message(kind: str, device: str, body: bytes, timestamp: float | None = None) -> bytes:
    """One OpenIGTLink message (header version 1): the 58-byte header, then ``body``.

    Parameters
    ----------
    kind : str
        Message type, e.g. ``"TRANSFORM"`` (≤ 12 ASCII characters).
    device : str
        Device name (≤ 20 ASCII characters).
    body : bytes
    timestamp : float, optional
        Seconds since the Unix epoch (now by default); 0 means unused.
    """
    t = time.time() if timestamp is None else float(timestamp)
    seconds = int(t)
    fraction = min(round((t - seconds) * 2**32), 2**32 - 1)
    stamp = (seconds << 32) | fraction if t > 0 else 0
    return _HEADER.pack(1, _ascii(kind, 12, "type"), _ascii(device, 20, "device name"), stamp, len(body),
                        crc64(body)) + body


def transform_body(rotation, position_mm) -> bytes:
    """TRANSFORM body: R (3, 3) column by column, then the translation, mm; 12 big-endian float32."""
    R = np.asarray(rotation, dtype=np.float64)
    p = np.asarray(position_mm, dtype=np.float64)
    if R.shape != (3, 3) or p.shape != (3,):
        raise ValueError(f"transform_body: expected R (3, 3) and p (3,), got {R.shape}, {p.shape}")
    return np.concatenate([R.T.ravel(), p]).astype(">f4").tobytes()


def polydata_body(points_mm, scalars: dict[str, np.ndarray] | None = None) -> bytes:
    """POLYDATA body: the points (n, 3) in mm joined by one polyline (the LINES cell array), with optional
    point-scalar attributes ``{name: values (n,)}`` (ASCII names of at most 255 characters)."""
    p = np.asarray(points_mm, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
        raise ValueError(f"polydata_body: expected points of shape (n >= 2, 3), got {p.shape}")
    n = len(p)
    scalars = scalars or {}
    line = np.concatenate([[n], np.arange(n)]).astype(">u4").tobytes()
    counts = np.array([n, 0, 0, 1, len(line), 0, 0, 0, 0, len(scalars)], dtype=">u4").tobytes()
    heads, names, values = [], [], []
    for name, v in scalars.items():
        v = np.asarray(v, dtype=np.float64)
        if v.shape != (n,):
            raise ValueError(f"polydata_body: attribute {name!r} needs one value per point ({n}), got {v.shape}")
        heads.append(struct.pack(">BBI", 0, 1, n))  # point scalar, one component
        names.append(_ascii(name, 255, "attribute name") + b"\0")
        values.append(v.astype(">f4").tobytes())
    table = b"".join(names)
    pad = b"\0" if len(table) % 2 else b""
    return counts + p.astype(">f4").tobytes() + line + b"".join(heads) + table + pad + b"".join(values)


def parse_address(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``"[HOST:]PORT"`` → (host, port); the host is 127.0.0.1 unless given. Port 0: any free port."""
    host, sep, port = str(text).rpartition(":")
    host = host if sep else default_host
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f"--igtl: expected [HOST:]PORT, got {text!r}") from None
    if not 0 <= number <= 65535 or not host:
        raise ValueError(f"--igtl: expected [HOST:]PORT with a port in 0–65535, got {text!r}")
    return host, number


#: most OpenIGTLink clients at once (3D Slicer needs one)
MAX_CLIENTS = 16
#: bytes waiting for a client that still count as keeping up (a few bundles of a 1 mm-sampled catheter)
SLACK_BYTES = 64 << 10


class _Client:
    __slots__ = ("address", "order", "out", "queued", "sock", "waiting")

    def __init__(self, sock: socket.socket, address, order: int):
        self.sock, self.address, self.order = sock, address, order
        self.out = memoryview(b"")  # the rest of the bundle being sent
        self.waiting: deque[bytes] = deque()  # whole bundles not yet started
        self.queued = 0  # bytes in ``waiting``

    def behind(self) -> tuple[int, int]:
        """The eviction order: (bytes waiting, arrival); up to :data:`SLACK_BYTES` waiting counts as keeping up
        (a reader has a bundle or two in flight), and of those the newest goes first."""
        waiting = self.queued + len(self.out)
        return (waiting if waiting > SLACK_BYTES else 0), self.order


class IgtlServer:
    """A TCP server pushing OpenIGTLink messages to every connected client (see the module notes).

    Parameters
    ----------
    host, port : str, int
        Where to listen (127.0.0.1; port 0 picks a free one: see :attr:`address`).
    max_backlog : int
        Most bytes of whole bundles waiting for one client; the oldest beyond are dropped (the newest is kept).
    max_clients : int
        Most clients at once; one more evicts the one furthest behind.

    Attributes
    ----------
    clients_seen, bundles_published, bundles_dropped, evicted : int
        Connections accepted; bundles handed to :meth:`publish`; bundles dropped for slow clients; clients
        evicted at the cap.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 18944, *, max_backlog: int = 256 << 10,
                 max_clients: int = MAX_CLIENTS):
        if not max_clients >= 1 or not max_backlog >= 0:
            raise ValueError(f"IgtlServer: max_clients >= 1 and max_backlog >= 0 needed, got {max_clients}, "
                             f"{max_backlog}")
        self.max_backlog, self.max_clients = int(max_backlog), int(max_clients)
        self._listener = socket.create_server((host, port), reuse_port=False)
        self._listener.setblocking(False)
        self.address: tuple[str, int] = self._listener.getsockname()[:2]
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ, None)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._selector.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._clients: dict[int, _Client] = {}
        self._lock = threading.Lock()
        self._closed = False
        self.clients_seen = 0
        self.bundles_published = 0
        self.bundles_dropped = 0
        self.evicted = 0
        self._thread = threading.Thread(target=self._serve, name="twin-igtl", daemon=True)
        self._thread.start()

    @property
    def clients(self) -> int:
        """Clients connected now."""
        with self._lock:
            return len(self._clients)

    def backlog(self) -> list[int]:
        """Bytes waiting for each client (whole bundles queued plus the rest of the one being sent)."""
        with self._lock:
            return [c.queued + len(c.out) for c in self._clients.values()]

    def publish(self, bundle: bytes) -> int:
        """Queue ``bundle`` (whole messages) for every client; returns how many clients it was queued for."""
        if self._closed:
            return 0
        queued = 0
        with self._lock:
            self.bundles_published += 1
            for c in self._clients.values():
                c.waiting.append(bundle)  # one object shared by every client
                c.queued += len(bundle)
                while len(c.waiting) > 1 and c.queued > self.max_backlog:  # the newest shape wins
                    c.queued -= len(c.waiting.popleft())
                    self.bundles_dropped += 1
                queued += 1
        if queued:
            with contextlib.suppress(OSError):
                self._wake_w.send(b"x")
        return queued

    # ---------------------------------------------------------------- the server thread
    def _serve(self) -> None:
        while not self._closed:
            with self._lock:
                for fd, c in self._clients.items():
                    busy = len(c.out) or c.waiting
                    self._selector.modify(c.sock, selectors.EVENT_READ | (selectors.EVENT_WRITE if busy else 0), fd)
            try:
                events = self._selector.select(timeout=0.5)
            except (OSError, ValueError):
                if self._closed:
                    return
                raise
            for key, mask in events:
                if key.fileobj is self._listener:
                    self._accept()
                elif key.data == "wake":
                    with contextlib.suppress(OSError):
                        while self._wake_r.recv(4096):
                            pass
                else:
                    self._service(key.data, mask)

    def _accept(self) -> None:
        with contextlib.suppress(BlockingIOError, InterruptedError):
            while True:
                sock, address = self._listener.accept()
                sock.setblocking(False)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                with self._lock:
                    full = len(self._clients) >= self.max_clients
                    victim = max(self._clients, key=lambda fd: self._clients[fd].behind()) if full else None
                if victim is not None:  # the newcomer is served; the one furthest behind makes way
                    self.evicted += 1
                    self._drop(victim)
                with self._lock:
                    self._clients[sock.fileno()] = _Client(sock, address, self.clients_seen)
                    self.clients_seen += 1
                self._selector.register(sock, selectors.EVENT_READ, sock.fileno())

    def _service(self, fd: int, mask: int) -> None:
        with self._lock:
            c = self._clients.get(fd)
        if c is None:
            return
        try:
            if mask & selectors.EVENT_READ and not c.sock.recv(65536):
                raise ConnectionResetError("closed by the client")  # requests from clients are not answered
            if mask & selectors.EVENT_WRITE:
                with self._lock:
                    if not len(c.out) and c.waiting:
                        nxt = c.waiting.popleft()
                        c.queued -= len(nxt)
                        c.out = memoryview(nxt)
                    data = c.out
                sent = c.sock.send(data) if len(data) else 0
                with self._lock:
                    c.out = c.out[sent:]
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._drop(fd)

    def _drop(self, fd: int) -> None:
        with self._lock:
            c = self._clients.pop(fd, None)
        if c is not None:
            with contextlib.suppress(Exception):
                self._selector.unregister(c.sock)
            c.sock.close()

    def close(self) -> None:
        """Stop serving and disconnect every client. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        self._thread.join(timeout=5)
        for fd in list(self._clients):
            self._drop(fd)
        for s in (self._listener, self._wake_r, self._wake_w):
            s.close()
        self._selector.close()

    def __enter__(self) -> IgtlServer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class IgtlSink:
    """A :class:`twin.live.LiveLoop` sink sending the latest usable shape of each batch over OpenIGTLink.

    At most ``rate`` bundles a second (``CatheterShape``, ``CatheterTip``, and ``CatheterTruth`` when the frame
    has a truth); a frame dropped by the rate limit is kept and sent at the next call. Nothing raises out of the
    sink: errors are counted (the first one reported on ``stream``).

    Attributes
    ----------
    frames_sent, errors : int
    """

    def __init__(self, server: IgtlServer, rate: float = 30.0, *, close_server: bool = True,
                 stream: TextIO | None = None, uncertainty=None):
        from twin.live import LatestUsable

        self.latest = LatestUsable(rate, "IgtlSink")
        self.server, self.close_server, self.stream = server, close_server, stream
        self.uncertainty = uncertainty  # a twin.uncertainty.Uncertainty: the sent shape gets its tube
        self.frames_sent = 0
        self.errors = 0
        self.last_error: str | None = None

    def __call__(self, frames: Frame, shapes: Shape | None, status: LiveStatus) -> None:
        try:
            self.latest.offer(frames, shapes, status.flags)
            taken = self.latest.take()
            if taken is not None:
                frame, shape = taken
                # propagated for the frame sent only, not for every batch's pick the rate limit then replaces
                if self.uncertainty is not None and shape.covariance is None:
                    shape = self.uncertainty.propagate(shape, frame)
                self.server.publish(bundle(shape, frame.truth))
                self.frames_sent += 1
        except Exception as exc:  # OpenIGTLink must never end the live loop
            self.errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            if self.errors == 1:
                print(f"twin live: igtl: {self.last_error} (further errors counted, not shown)",
                      file=self.stream or sys.stderr)

    def close(self) -> None:
        if self.close_server:
            self.server.close()


def bundle(shape: Shape, truth: Truth | None = None, timestamp: float | None = None) -> bytes:
    """The messages of one frame: CatheterShape, CatheterTip and (with a truth) CatheterTruth."""
    from twin.viewer.geometry import placement

    R, p, _ = placement(shape, truth)
    world = shape.positions @ R.T + p
    tip_frame = R @ shape.frames[-1]
    t = time.time() if timestamp is None else timestamp
    scalars = None
    if shape.covariance is not None:
        scalars = {"Sigma": 1e3 * shape.sigma, "Confidence95": 1e3 * shape.confidence(0.95)}
    out = [message("POLYDATA", "CatheterShape", polydata_body(1e3 * world, scalars), t),
           message("TRANSFORM", "CatheterTip", transform_body(tip_frame, 1e3 * world[-1]), t)]
    if truth is not None:
        tp = np.asarray(truth.positions, dtype=np.float64)
        ok = np.all(np.isfinite(tp), axis=1)
        if ok.sum() >= 2:
            out.append(message("POLYDATA", "CatheterTruth", polydata_body(1e3 * tp[ok]), t))
    return b"".join(out)
