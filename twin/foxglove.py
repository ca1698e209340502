"""Foxglove: the live catheter shape served on the Foxglove WebSocket protocol (``twin live URL --foxglove PORT``).

:class:`FoxgloveServer` serves, :class:`FoxgloveSink` (a :class:`twin.live.LiveLoop` sink) feeds it the latest
usable frame of each batch, at most ``rate`` times a second. Topics, all in the frame ``world`` (a shape is
placed as the browser viewer places it: at the truth's base pose when there is one, else its own base frame,
:func:`twin.viewer.geometry.frame_scene`, which also computes the figures, so both displays show the same):

====================  ======================  =====================================================================
``/catheter/scene``   ``foxglove.SceneUpdate``  entity ``catheter``: the reconstruction (a line coloured per point by
                                                its local error against the truth, viridis 0–1 mm, else by
                                                |curvature|, 0–70 1/m), the truth (magenta), the interrogator's own
                                                shape (orange, registered as for its reported distance), the gratings
                                                (black spheres)
``/catheter/tip``     ``foxglove.PoseInFrame``  the tip pose (material frame d1 d2 d3)
``/catheter/figures`` JSON                      the overlay's figures: state, frames, rate, lost samples, max / mean /
                                                tip error (mm), the distance to the interrogator's shape (mm), the
                                                colouring and its range, the calibration
====================  ======================  =====================================================================

The protocol is foxglove-sdk's server (messages protobuf-encoded with their schemas, as the Foxglove app expects);
it runs on 127.0.0.1 at a port of its own, behind a gate that owns the public address (127.0.0.1 unless a host
is given): the gate accepts at most ``max_clients`` connections at a time, answers any further one with an
HTTP 503 and closes it (counted in ``clients_refused``), and relays bytes both ways for the others, one read
(64 KiB) at a time, so a client that does not keep up holds back only its own relay; behind it the SDK keeps at
most ``backlog`` messages per client and drops the oldest data first. Nothing here waits on a client: the live
loop only hands messages to the SDK.

In Foxglove (desktop app or web): *Open connection* → *Foxglove WebSocket* → ``ws://127.0.0.1:PORT``; add a 3D
panel (topic ``/catheter/scene``, display frame ``world``) and a Raw Messages or Plot panel on
``/catheter/figures``.
"""

from __future__ import annotations

import contextlib
import socket
import sys
import threading
import time
from typing import TYPE_CHECKING, TextIO

import numpy as np

from twin.extras import require
from twin.frames import Frame, Shape

if TYPE_CHECKING:  # pragma: no cover
    from twin.live import LiveStatus

__all__ = ["FoxgloveServer", "FoxgloveSink"]

_REFUSE = b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
_READ = 1 << 16
#: colours (r, g, b): truth magenta, the interrogator's shape orange, gratings black (as in the browser viewer)
TRUTH_RGB, VENDOR_RGB, GRATING_RGB = (1.0, 0.0, 1.0), (1.0, 0.55, 0.0), (0.0, 0.0, 0.0)
ERROR_RANGE, CURVATURE_RANGE = (0.0, 1e-3), (0.0, 70.0)


class FoxgloveServer:
    """A Foxglove WebSocket server with a client cap (module docstring).

    Parameters
    ----------
    host, port : str, int
        The public address (port 0: any free port; :attr:`address` says which).
    max_clients : int
        Most clients connected at once.
    handshake_timeout : float
        s a client has to send its whole HTTP request (a client trickling it byte by byte is dropped then, not
        kept holding one of the ``max_clients`` places).
    backlog : int
        Most messages queued per client by the SDK.
    name : str
        The server's name shown by Foxglove.

    Attributes
    ----------
    address : (str, int)
    clients_seen, clients_refused : int
    clients_forbidden : int
        Connections refused with 403 for a foreign ``Host`` or ``Origin`` (:meth:`_admitted`).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, *, max_clients: int = 4, backlog: int = 64,
                 name: str = "catheter-twin", handshake_timeout: float = 5.0):
        foxglove = require("foxglove", "Foxglove")
        if max_clients < 1:
            raise ValueError(f"FoxgloveServer: max_clients must be at least 1, got {max_clients}")
        self.max_clients = int(max_clients)
        self.handshake_timeout = float(handshake_timeout)
        self.context = foxglove.Context()
        self._sdk = foxglove.start_server(name=name, host="127.0.0.1", port=0, context=self.context,
                                          message_backlog_size=int(backlog))
        self._inner = ("127.0.0.1", self._sdk.port)
        try:
            self._listener = socket.create_server((host, port))
        except OSError as exc:
            self._sdk.stop()
            raise OSError(f"Foxglove: cannot listen on {host}:{port} ({exc.strerror or exc})") from None
        self._listener.settimeout(0.2)
        self.address = self._listener.getsockname()[:2]
        self.clients_seen = self.clients_refused = self.clients_forbidden = 0
        self._lock = threading.Lock()
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._closed = threading.Event()
        self._accept_thread = threading.Thread(target=self._accept, name="foxglove-gate", daemon=True)
        self._accept_thread.start()

    @property
    def clients(self) -> int:
        """Clients connected now."""
        with self._lock:
            return len(self._pairs)

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # the listener was closed
            with self._lock:
                full = len(self._pairs) >= self.max_clients
                if full:
                    self.clients_refused += 1
            if full:
                threading.Thread(target=_refuse, args=(conn,), name="foxglove-refuse", daemon=True).start()
                continue
            with self._lock:
                self._pairs.append((conn,))
                self.clients_seen += 1
            threading.Thread(target=self._serve, args=(conn,), name="foxglove-client", daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        """Open the client's connection to the SDK's server (the handshake translated, :func:`_handshake`),
        then relay both ways."""
        pair: tuple = (conn,)
        try:
            head, rest = _read_head(conn, self.handshake_timeout)
            conn.settimeout(self.handshake_timeout)  # the rest of the handshake; the relay then blocks
            if not self._admitted(head):
                with self._lock:
                    self.clients_forbidden += 1
                with contextlib.suppress(OSError):
                    conn.sendall(_FORBIDDEN)
                self._drop(pair)
                return
            inner = socket.create_connection(self._inner, timeout=5.0)
            pair = (conn, inner)
            with self._lock:
                self._pairs[self._pairs.index((conn,))] = pair
            _handshake(head, rest, conn, inner, self.handshake_timeout)
        except (OSError, ValueError):
            self._drop(pair)
            return
        conn.settimeout(None)
        inner.settimeout(None)
        done = threading.Barrier(2, action=lambda: self._drop(pair))
        threading.Thread(target=_relay, args=(inner, conn, done), name="foxglove-relay", daemon=True).start()
        _relay(conn, inner, done)

    def _admitted(self, head: bytes) -> bool:
        """DNS rebinding and foreign pages: the ``Host`` must name this server by a loopback name (or the address
        it was told to listen on) and its port; an ``Origin``, when a browser sends one, must be a loopback page
        of that port or Foxglove's own app (:data:`FOXGLOVE_APP_ORIGINS`), which is what opens this server."""
        from twin.viewer.server import LOOPBACK_NAMES, host_allowed, origin_allowed

        headers = _headers(head)
        names = (*LOOPBACK_NAMES, str(self.address[0]).strip("[]"))
        port = int(self.address[1])
        origin = headers.get("origin")
        return host_allowed(headers.get("host", ""), port, names) and (
            origin in FOXGLOVE_APP_ORIGINS or origin_allowed(origin, port, names))

    def _drop(self, pair) -> None:
        with self._lock:
            if pair in self._pairs:
                self._pairs.remove(pair)
        for s in pair:
            s.close()

    def close(self) -> None:
        """Stop accepting, disconnect every client, stop the SDK's server."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._listener.close()
        self._accept_thread.join(timeout=2.0)
        with self._lock:
            pairs = list(self._pairs)
        for pair in pairs:
            for s in pair:
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
        self._sdk.stop()

    def __enter__(self) -> FoxgloveServer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: the subprotocol of the published specification (ws-protocol, "foxglove.websocket.v1") and the name under which
#: foxglove-sdk 0.30 serves the same messages; the gate lets a client that asks for either have it
SPEC_SUBPROTOCOL, SDK_SUBPROTOCOL = "foxglove.websocket.v1", "foxglove.sdk.v1"
_HEAD_MAX = 16384


def _read_head(sock: socket.socket, timeout: float) -> tuple[bytes, bytes]:
    """An HTTP head (up to the blank line) and whatever came after it, all within ``timeout`` s (a deadline for
    the whole head, not for each read: a peer sending a byte now and then would otherwise hold on for hours)."""
    deadline = time.monotonic() + timeout
    buf = b""
    while b"\r\n\r\n" not in buf:
        if len(buf) > _HEAD_MAX:
            raise ValueError("HTTP head too long")
        left = deadline - time.monotonic()
        if left <= 0:
            raise ValueError(f"HTTP head not complete within {timeout:g} s")
        sock.settimeout(left)
        chunk = sock.recv(4096)
        if not chunk:
            raise ValueError("connection closed during the handshake")
        buf += chunk
    head, _, rest = buf.partition(b"\r\n\r\n")
    return head + b"\r\n\r\n", rest


def _swap_protocol(head: bytes, old: str, new: str) -> tuple[bytes, bool]:
    """Replace subprotocol ``old`` by ``new`` in the Sec-WebSocket-Protocol header of an HTTP head."""
    lines = head.split(b"\r\n")
    changed = False
    for i, line in enumerate(lines):
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == b"sec-websocket-protocol":
            offered = [v.strip() for v in value.decode("latin-1").split(",")]
            if old in offered and new not in offered:
                offered = [new if v == old else v for v in offered]
                lines[i] = name + b": " + ", ".join(offered).encode("latin-1")
                changed = True
    return b"\r\n".join(lines), changed


#: the origins of Foxglove's hosted app, the client this server is for (a browser page elsewhere is refused)
FOXGLOVE_APP_ORIGINS = frozenset({"https://app.foxglove.dev"})
_FORBIDDEN = b"HTTP/1.1 403 Forbidden\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"


def _headers(head: bytes) -> dict[str, str]:
    """An HTTP head's header fields, names in lower case (the request line left out)."""
    out = {}
    for line in head.split(b"\r\n")[1:]:
        name, sep, value = line.partition(b":")
        if sep:
            out[name.strip().lower().decode("latin-1")] = value.strip().decode("latin-1")
    return out


def _handshake(head: bytes, rest: bytes, client: socket.socket, server: socket.socket, timeout: float) -> None:
    """Pass the WebSocket opening handshake (the client's ``head`` and what followed it) between a client and
    the SDK's server, letting a client that asks for the specification's subprotocol name have it (the SDK
    answers to its own name for the same protocol; the accept key does not depend on the subprotocol)."""
    head, asked_spec = _swap_protocol(head, SPEC_SUBPROTOCOL, SDK_SUBPROTOCOL)
    server.sendall(head + rest)
    reply, rest = _read_head(server, timeout)
    if asked_spec:
        reply, _ = _swap_protocol(reply, SDK_SUBPROTOCOL, SPEC_SUBPROTOCOL)
    client.sendall(reply + rest)


def _refuse(conn: socket.socket) -> None:
    """Answer a client over the cap with HTTP 503 after its request (a reply before it, or a close with its
    request unread, can reach the client as a reset instead of the answer); at most 2 s in all (a deadline, not a
    timeout per read: a client that keeps sending would otherwise hold this thread for as long as it likes)."""
    deadline = time.monotonic() + 2.0
    try:
        with contextlib.suppress(OSError, ValueError):
            _read_head(conn, 1.0)
        conn.settimeout(1.0)
        conn.sendall(_REFUSE)
        conn.shutdown(socket.SHUT_WR)
        while (left := deadline - time.monotonic()) > 0:  # until the client closes, or the deadline
            conn.settimeout(left)
            if not conn.recv(4096):
                break
    except OSError:
        pass
    finally:
        conn.close()


def _relay(src: socket.socket, dst: socket.socket, done: threading.Barrier) -> None:
    """Copy src → dst until either side ends; then end both directions (the barrier's action closes them)."""
    try:
        while True:
            data = src.recv(_READ)
            if not data:
                break
            dst.sendall(data)
    except OSError:
        pass
    for s in (src, dst):
        with contextlib.suppress(OSError):
            s.shutdown(socket.SHUT_RDWR)
    with contextlib.suppress(threading.BrokenBarrierError):
        done.wait(timeout=5.0)


class FoxgloveSink:
    """A :class:`twin.live.LiveLoop` sink publishing the latest usable frame of each batch to a
    :class:`FoxgloveServer`, at most ``rate`` times a second (a frame held back by the rate is sent at the next
    call). Nothing raises out of the sink: errors are counted, the first one reported on ``stream``.

    Attributes
    ----------
    frames_sent, errors : int
    """

    def __init__(self, server: FoxgloveServer, rate: float = 30.0, *, calibration: str | None = None,
                 close_server: bool = True, stream: TextIO | None = None):
        from twin.live import LatestUsable

        self.latest = LatestUsable(rate, "FoxgloveSink")
        foxglove = require("foxglove", "Foxglove")
        from foxglove.channels import PoseInFrameChannel, SceneUpdateChannel

        self.server, self.close_server, self.stream = server, close_server, stream
        self.calibration = calibration
        ctx = server.context
        self._scene = SceneUpdateChannel("/catheter/scene", context=ctx)
        self._tip = PoseInFrameChannel("/catheter/tip", context=ctx)
        self._figures = foxglove.Channel("/catheter/figures", message_encoding="json", context=ctx,
                                         schema=foxglove.Schema(name="catheter_twin.Figures", encoding="jsonschema",
                                                                data=b'{"type": "object"}'))
        self.frames_sent = 0
        self.errors = 0
        self.last_error: str | None = None

    def __call__(self, frames: Frame, shapes: Shape | None, status: LiveStatus) -> None:
        try:
            self.latest.offer(frames, shapes, status.flags)
            taken = self.latest.take() if status.state != "ended" else None
            if taken is not None:
                frame, shape = taken
                self._publish(shape, frame.truth, frame.vendor, float(frame.timestamp), status)
                self.frames_sent += 1
        except Exception as exc:  # Foxglove must never end the live loop
            self.errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            if self.errors == 1:
                print(f"twin live: foxglove: {self.last_error} (further errors counted, not shown)",
                      file=self.stream or sys.stderr)

    def _publish(self, shape: Shape, truth, vendor, t: float, status: LiveStatus) -> None:
        import foxglove.messages as M

        from twin import so3
        from twin.viewer.geometry import colormap, frame_scene

        sc = frame_scene(shape, truth, vendor)
        log = time.time_ns()
        stamp = M.Timestamp.from_epoch_secs(t) if np.isfinite(t) and t >= 0 else M.Timestamp.now()
        rng = ERROR_RANGE if sc.mode == "error" else CURVATURE_RANGE
        rgb = colormap(sc.values, *rng)
        if status.state == "stale":
            rgb = np.full_like(rgb, 0.5)

        def points(xyz: np.ndarray) -> list:
            return [M.Point3(x=x, y=y, z=z) for x, y, z in xyz.tolist()]

        lines = [M.LinePrimitive(type=M.LinePrimitiveLineType.LineStrip, thickness=2.5e-3, points=points(sc.world),
                                 colors=[M.Color(r=r, g=g, b=b, a=1.0) for r, g, b in rgb.tolist()])]
        for pts, (r, g, b) in ((sc.truth, TRUTH_RGB), (sc.vendor, VENDOR_RGB)):
            if pts is not None and len(pts) >= 2:
                lines.append(M.LinePrimitive(type=M.LinePrimitiveLineType.LineStrip, thickness=3.0,
                                             scale_invariant=True, points=points(pts),
                                             color=M.Color(r=r, g=g, b=b, a=1.0)))
        black = M.Color(r=GRATING_RGB[0], g=GRATING_RGB[1], b=GRATING_RGB[2], a=1.0)
        size = M.Vector3(x=1.5e-3, y=1.5e-3, z=1.5e-3)
        spheres = [M.SpherePrimitive(pose=M.Pose(position=M.Vector3(x=x, y=y, z=z)), size=size, color=black)
                   for x, y, z in sc.markers.tolist()]
        entity = M.SceneEntity(timestamp=stamp, frame_id="world", id="catheter", lines=lines, spheres=spheres)
        self._scene.log(M.SceneUpdate(entities=[entity]), log_time=log)
        qx, qy, qz, qw = so3.to_quaternion(sc.R @ shape.frames[-1]).tolist()
        x, y, z = sc.world[-1].tolist()
        self._tip.log(M.PoseInFrame(timestamp=stamp, frame_id="world", pose=M.Pose(
            position=M.Vector3(x=x, y=y, z=z), orientation=M.Quaternion(x=qx, y=qy, z=qz, w=qw))), log_time=log)
        mm = {f"{k}_error_mm": round(1e3 * v, 4) for k, v in (sc.errors or {}).items()}
        mm.update({f"vendor_{k}_distance_mm": round(1e3 * v, 4) for k, v in (sc.vendor_errors or {}).items()})
        self._figures.log({"state": status.state, "frames": status.frames, "rate_hz": round(status.rate_hz, 3),
                           "lost_samples": status.lost_samples, "colour": sc.mode, "colour_range": list(rng),
                           "placement": sc.how, "calibration": self.calibration, **mm}, log_time=log)

    def close(self) -> None:
        if self.close_server:
            self.server.close()
