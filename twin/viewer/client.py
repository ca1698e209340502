"""The viewer's client: commands over the scene server's zmq socket (meshcat's command protocol).

One REQ socket with send and receive timeouts: a server that died or froze raises :class:`ViewerError` after
``timeout`` s instead of hanging the caller, and the client then gives up on it (a REQ socket that missed an
answer cannot be used again).
"""

from __future__ import annotations

import json

from twin.viewer.commands import Command

__all__ = ["SceneClient", "ViewerError"]


class ViewerError(OSError):
    """The viewer cannot draw: a package is missing, its server is gone or does not answer, or it was closed."""


class SceneClient:
    """Send scene commands to a server at ``zmq_url`` (e.g. ``tcp://127.0.0.1:6000``).

    Parameters
    ----------
    zmq_url : str
    timeout : float
        Longest wait for one answer, s.
    """

    def __init__(self, zmq_url: str, timeout: float = 2.0):
        import zmq

        self._zmq = zmq
        self.zmq_url = zmq_url
        self._context = zmq.Context.instance()
        self._socket = self._context.socket(zmq.REQ)
        ms = int(timeout * 1000)
        for opt, value in ((zmq.RCVTIMEO, ms), (zmq.SNDTIMEO, ms), (zmq.LINGER, 0)):
            self._socket.setsockopt(opt, value)
        self._socket.connect(zmq_url)
        self.broken: str | None = None
        self.closed = False

    def _request(self, frames: list[bytes]) -> bytes:
        if self.closed:
            raise ViewerError("the viewer is closed")
        if self.broken:
            raise ViewerError(self.broken)
        try:
            self._socket.send_multipart(frames)
            return self._socket.recv()
        except self._zmq.ZMQError as exc:
            self.broken = f"the viewer's server did not answer ({exc})"
            raise ViewerError(self.broken) from None

    def send(self, command: Command) -> None:
        """One scene command (see :mod:`twin.viewer.commands`)."""
        kind, path, data = command
        answer = self._request([kind.encode(), path.encode(), data])
        if answer != b"ok":
            raise ViewerError(f"the viewer's server refused {kind} {path}: {answer[:200]!r}")

    def send_many(self, commands: list[Command]) -> None:
        """Several commands in one request (``batch``: type, path, data for each; our server's extension)."""
        if not commands:
            return
        frames = [b"batch"]
        for kind, path, data in commands:
            frames += [kind.encode(), path.encode(), data]
        answer = self._request(frames)
        if answer != b"ok":
            raise ViewerError(f"the viewer's server refused a batch: {answer[:200]!r}")

    def hud(self, content: dict) -> None:
        """Replace the page's overlay (figures, legend): a JSON object the page renders."""
        self._request([b"hud", b"", json.dumps(content, allow_nan=False).encode()])

    def static_html(self) -> str:
        """The current scene as one self-contained HTML page."""
        return self._request([b"get_scene"]).decode("utf-8")

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._socket.close(linger=0)
