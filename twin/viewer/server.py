"""The viewer's scene server: ``python -m twin.viewer.server [--host 127.0.0.1] [--web-port 7000]``.

A small tornado application in the role of meshcat's own server, bound to loopback (meshcat 0.3.2's server
listens on every interface and offers no option to change it):

- **commands** arrive on a zmq REP socket (``tcp://HOST:PORT``) in meshcat's format — frames (type, path,
  msgpack command) — and are answered ``ok``; the server keeps the scene (per path: the last object, the last
  value of each property, the last transform) and forwards each command to every browser;
- **the page**, ``http://HOST:PORT/static/``: meshcat's browser viewer (its ``main.min.js``, served from the
  installed meshcat package) in a page of ours, which adds an overlay for figures and the legend;
- **browsers** connect to the websocket ``/ws`` and get the whole scene first, then every change; the overlay
  travels as text messages (JSON), scene commands as binary ones;
- ``get_scene`` answers the scene as one self-contained HTML page (the viewer inlined, commands embedded), and
  ``hud`` (frames: ``hud``, empty, JSON) replaces the overlay; ``batch`` (frames: ``batch``, then type, path,
  command for each) applies several commands in one request (one frame of the live view).

On start it prints one JSON line ``{"zmq_url": …, "web_url": …}`` on stdout. With ``--parent PID`` it exits
when that process is gone, so a killed run never leaves a server holding its ports.

Hostile or careless local clients:

- **DNS rebinding**: pages and ``/ws`` answer only requests whose ``Host`` is a loopback name (``127.0.0.1``,
  ``localhost``, ``[::1]``, or the ``--host`` address) with the page's port, and whose ``Origin``, when sent, is
  ``http://`` such a host and port; others get 403. (A web page elsewhere that rebinds its own name to
  127.0.0.1 sends its own name as Host and Origin.)
- **A browser that does not read** never grows the server's memory: each browser has its own queue
  (:class:`Outbox`) of at most :data:`MAX_QUEUED` messages and :data:`MAX_QUEUED_BYTES` bytes, written one at
  a time (the next only when the previous has left for the socket). A newer command for the same node (and
  property) replaces the one still queued — the latest state wins, so a late reader still rebuilds the current
  scene — and beyond the bounds the oldest is dropped; both are counted (``dropped``). At most
  :data:`MAX_BROWSERS` browsers at once: one more evicts the browser furthest behind (the most bytes queued; of
  equals, the newest), counted in ``evicted``.
- **A malformed command** on the zmq socket (a ``hud`` that is not a UTF-8 JSON object, a scene command that is
  not a msgpack map of its type, a ``set_property`` without a property name) is answered ``error: …`` and
  counted (``bad_commands``); the command task goes on. ``stats`` answers these counters as JSON.
- A static path that cannot be a file (``/static/%00``) is a 404, not a 500.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import contextlib
import json
import os
import sys
import threading
import time
import warnings
from pathlib import Path

__all__ = ["MAX_BROWSERS", "MAX_QUEUED", "MAX_QUEUED_BYTES", "Outbox", "Scene", "host_allowed", "main",
           "meshcat_dist", "origin_allowed", "page"]

PAGE = Path(__file__).with_name("static") / "index.html"

#: most messages queued for one browser; the oldest beyond are dropped (counted). The whole scene a new browser
#: gets first must fit (the live view's has ~10 nodes); queued messages are the scene's own bytes, shared, so
#: what a queue holds on its own is only what newer commands have replaced
MAX_QUEUED = 256
#: most bytes queued for one browser (a few frames of the live view: one frame's meshes are ~0.2 MB)
MAX_QUEUED_BYTES = 8 << 20
#: most browsers served at once; one more evicts the one furthest behind
MAX_BROWSERS = 16
#: host names a page of ours may be reached by (DNS rebinding: no other name may reach the server)
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1")


def meshcat_dist() -> Path:
    """The directory of meshcat's built browser viewer (``main.min.js``) in the installed package."""
    import importlib.util

    spec = importlib.util.find_spec("meshcat")
    if spec is None or spec.origin is None:
        raise ImportError("meshcat is not installed")
    dist = Path(spec.origin).parent / "viewer" / "dist"
    if not (dist / "main.min.js").exists():
        raise ImportError(f"meshcat's viewer is missing: no {dist / 'main.min.js'}")
    return dist


def page(*, script: str, boot: str) -> str:
    """Our page with the viewer's script tag (or inlined script) and the start-up code filled in."""
    html = PAGE.read_text(encoding="utf-8")
    return html.replace("<!--VIEWER-->", script).replace("/*BOOT*/", boot)


class Scene:
    """The scene as the server keeps it: per path, the last object, properties by name, the last transform."""

    def __init__(self) -> None:
        self.nodes: dict[str, dict] = {}
        self.hud: str | None = None

    @staticmethod
    def check(kind: str, path: str, data: bytes) -> tuple:
        """The key of one scene command (what a newer command of the same key replaces); raises ValueError
        when it is not meshcat's: a msgpack map of its own type, ``set_property`` naming its property."""
        import umsgpack

        if kind not in MESHCAT_COMMANDS:
            raise ValueError(f"unknown command {kind[:40]!r}")
        try:
            body = umsgpack.unpackb(data)
        except Exception as exc:  # umsgpack raises its own classes for every kind of bad input
            raise ValueError(f"{kind} {path[:80]}: not msgpack ({type(exc).__name__})") from None
        if not isinstance(body, dict) or body.get("type") != kind:
            raise ValueError(f"{kind} {path[:80]}: expected a msgpack map of type {kind!r}")
        if kind == "set_property":
            name = body.get("property")
            if not isinstance(name, str):
                raise ValueError(f"set_property {path[:80]}: no property name")
            return kind, path, name
        return kind, path

    def apply(self, key: tuple, data: bytes) -> None:
        """Keep one command (``key`` from :meth:`check`)."""
        kind, path = key[0], key[1]
        if kind == "delete":
            gone = [p for p in self.nodes if p == path or p.startswith(path.rstrip("/") + "/")]
            for p in gone:
                del self.nodes[p]
            return
        node = self.nodes.setdefault(path, {"object": None, "properties": {}, "transform": None})
        if kind == "set_object":
            # meshcat puts the object under PATH/<object>: properties of the node PATH itself (its visibility)
            # outlive it, as in the browser
            node["object"] = data
        elif kind == "set_transform":
            node["transform"] = data
        elif kind == "set_property":
            node["properties"][key[2]] = data

    def messages(self) -> list[tuple[tuple, bytes]]:
        """Every stored command with its key, in an order that rebuilds the scene (objects, then properties,
        transforms)."""
        out: list[tuple[tuple, bytes]] = []
        for path, node in self.nodes.items():
            if node["object"] is not None:
                out.append((("set_object", path), node["object"]))
            out.extend((("set_property", path, name), m) for name, m in node["properties"].items())
            if node["transform"] is not None:
                out.append((("set_transform", path), node["transform"]))
        return out

    def static_html(self, dist: Path) -> str:
        commands = ",\n".join(f'"{base64.b64encode(m).decode()}"' for _, m in self.messages())
        boot = (f"const commands = [{commands}];\n"
                "for (const c of commands) viewer.handle_command_bytearray("
                "Uint8Array.from(atob(c), ch => ch.charCodeAt(0)));\n"
                f"showHud({self.hud or 'null'});")
        script = "<script>" + (dist / "main.min.js").read_text(encoding="utf-8") + "</script>"
        return page(script=script, boot=boot)


MESHCAT_COMMANDS = ("set_object", "set_transform", "set_property", "delete")
#: the key of the overlay's message in a browser's queue
HUD_KEY = ("hud",)


class Outbox:
    """One browser's queue: at most ``max_items`` messages and ``max_bytes`` bytes (never fewer than one).

    A message put with the key of one still queued replaces it (the older is dropped and the newer goes to the
    back: the latest state wins, and the order of the latest commands is kept, so the scene rebuilt is the
    current one); beyond the bounds the oldest are dropped. Both count in ``dropped``.
    """

    def __init__(self, max_items: int = MAX_QUEUED, max_bytes: int = MAX_QUEUED_BYTES):
        from collections import OrderedDict

        self.max_items, self.max_bytes = int(max_items), int(max_bytes)
        self._items: OrderedDict[tuple, tuple[bytes | str, bool]] = OrderedDict()
        self.bytes = 0
        self.dropped = 0
        self.ready = asyncio.Event()

    def __len__(self) -> int:
        return len(self._items)

    def put(self, key: tuple, message: bytes | str, binary: bool) -> None:
        old = self._items.pop(key, None)
        if old is not None:
            self.bytes -= len(old[0])
            self.dropped += 1
        self._items[key] = (message, binary)
        self.bytes += len(message)
        while len(self._items) > 1 and (len(self._items) > self.max_items or self.bytes > self.max_bytes):
            _, (gone, _) = self._items.popitem(last=False)
            self.bytes -= len(gone)
            self.dropped += 1
        self.ready.set()

    def pop(self) -> tuple[bytes | str, bool] | None:
        if not self._items:
            self.ready.clear()
            return None
        _, (message, binary) = self._items.popitem(last=False)
        self.bytes -= len(message)
        return message, binary


def _split_host(netloc: str) -> tuple[str, int | None] | None:
    from urllib.parse import urlsplit

    try:
        parts = urlsplit("//" + netloc)
        return (parts.hostname or ""), parts.port
    except ValueError:  # a port that is no number, an unbalanced bracket
        return None


def host_allowed(host: str, port: int, names=LOOPBACK_NAMES) -> bool:
    """Whether a request's ``Host`` header names this server by a loopback name (``names``) and its ``port``."""
    split = _split_host(host or "")
    return split is not None and split[0] in names and (split[1] or 80) == port


def origin_allowed(origin: str | None, port: int, names=LOOPBACK_NAMES) -> bool:
    """Whether a request's ``Origin`` (None: not sent, as by a program rather than a browser) is a page of this
    server: ``http://`` a loopback name (``names``) and ``port``."""
    if origin is None:
        return True
    scheme, sep, rest = origin.partition("://")
    return bool(sep) and scheme.lower() == "http" and "/" not in rest and host_allowed(rest, port, names)

LIVE_BOOT = """
const ws = new WebSocket(`ws://${location.host}/ws`);
ws.binaryType = "arraybuffer";
ws.onmessage = (event) => {
  if (typeof event.data === "string") showHud(JSON.parse(event.data));
  else viewer.handle_command_bytearray(new Uint8Array(event.data));
};
ws.onclose = () => showHud(null, "the viewer's server has stopped: the last picture stays");
"""


def serve(host: str, zmq_port: int, web_port: int, parent: int | None) -> None:
    import tornado.httpserver
    import tornado.netutil
    import tornado.web
    import tornado.websocket
    import zmq
    import zmq.asyncio

    dist = meshcat_dist()
    scene = Scene()
    browsers: list = []  # in order of arrival
    stats = {"bad_commands": 0, "evicted": 0, "dropped_closed": 0}
    names = (*LOOPBACK_NAMES, host.strip("[]"))
    bound: dict[str, int] = {}

    class Guarded(tornado.web.RequestHandler):
        def prepare(self) -> None:
            # DNS rebinding: another site's name resolved to 127.0.0.1 arrives with that name as its Host
            if not host_allowed(self.request.host, bound["port"], names) or not origin_allowed(
                    self.request.headers.get("Origin"), bound["port"], names):
                raise tornado.web.HTTPError(403)

    class PageHandler(Guarded):
        def get(self) -> None:
            self.set_header("Cache-Control", "no-store")
            self.write(page(script='<script src="main.min.js"></script>', boot=LIVE_BOOT))

    class StaticHandler(Guarded, tornado.web.StaticFileHandler):
        def parse_url_path(self, url_path: str) -> str:
            if "\x00" in url_path:  # no file has such a name (the OS would refuse it: a 500)
                raise tornado.web.HTTPError(404)
            return super().parse_url_path(url_path)

    class Browser(Guarded, tornado.websocket.WebSocketHandler):
        def check_origin(self, origin: str) -> bool:
            return origin_allowed(origin, bound["port"], names)

        def open(self) -> None:
            self.outbox = Outbox()
            if len(browsers) >= MAX_BROWSERS:
                # the one furthest behind goes (of equals the newest): a reading browser keeps its place
                victim = max(reversed(browsers), key=lambda b: b.outbox.bytes)
                stats["evicted"] += 1
                victim.close(1013, "too many browsers")
                forget(victim)
            browsers.append(self)
            for key, m in scene.messages():
                self.outbox.put(key, m, True)
            if scene.hud is not None:
                self.outbox.put(HUD_KEY, scene.hud, False)
            self.sender = asyncio.ensure_future(self.send_queued())

        async def send_queued(self) -> None:
            # one message at a time: the next is taken only when the previous has left for the socket, so
            # a browser that does not read holds its outbox's bound and nothing more
            try:
                while True:
                    item = self.outbox.pop()
                    if item is None:
                        await self.outbox.ready.wait()
                        continue
                    await self.write_message(item[0], binary=item[1])
            except tornado.websocket.WebSocketClosedError:
                forget(self)

        def on_message(self, message) -> None:  # browsers have nothing to say
            pass

        def on_close(self) -> None:
            forget(self)

    def forget(b) -> None:
        """Let a browser go (closed, evicted or failed): its queue with it, its drops kept in the count."""
        if b in browsers:
            browsers.remove(b)
            stats["dropped_closed"] += b.outbox.dropped
            b.outbox = Outbox()  # the queued messages are freed now, not when the connection is
            b.sender.cancel()  # its sending task ends with it

    def broadcast(key: tuple, message, binary: bool) -> None:
        for b in browsers:
            b.outbox.put(key, message, binary)

    app = tornado.web.Application([
        (r"/static/?", PageHandler),
        (r"/static/index.html", PageHandler),
        (r"/static/(.*)", StaticHandler, {"path": str(dist)}),
        (r"/ws", Browser),
    ])
    sockets = None
    for port in ([web_port, *range(web_port + 1, web_port + 20)] if web_port else []) + [0]:
        with contextlib.suppress(OSError):
            sockets = tornado.netutil.bind_sockets(port, address=host)
            break
    if sockets is None:
        raise OSError(f"no free port for the viewer's page on {host}")
    http = tornado.httpserver.HTTPServer(app)
    http.add_sockets(sockets)
    bound["port"] = sockets[0].getsockname()[1]
    web_url = f"http://{host}:{bound['port']}/static/"

    context = zmq.asyncio.Context.instance()
    rep = context.socket(zmq.REP)
    if zmq_port:
        rep.bind(f"tcp://{host}:{zmq_port}")
        zmq_url = f"tcp://{host}:{zmq_port}"
    else:
        zmq_url = f"tcp://{host}:{rep.bind_to_random_port(f'tcp://{host}')}"

    def text(frame: bytes, what: str) -> str:
        try:
            return frame.decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError(f"{what} is not UTF-8") from None

    def handle(frames: list[bytes]) -> bytes:
        """The answer to one request; ValueError for a malformed one (nothing of it applied)."""
        kind = text(frames[0], "the command's type")
        if kind in MESHCAT_COMMANDS and len(frames) == 3:
            items = [(kind, text(frames[1], "the path"), frames[2])]
        elif kind == "batch" and len(frames) % 3 == 1:
            items = [(text(frames[i], "a command's type"), text(frames[i + 1], "a path"), frames[i + 2])
                     for i in range(1, len(frames), 3)]
        elif kind == "hud" and len(frames) == 3:
            hud = text(frames[2], "the overlay")
            try:
                content = json.loads(hud)
            except ValueError:
                raise ValueError("the overlay is not JSON") from None
            if not isinstance(content, dict):
                raise ValueError("the overlay is not a JSON object")
            scene.hud = hud
            broadcast(HUD_KEY, hud, False)
            return b"ok"
        elif kind == "get_scene" and len(frames) == 1:
            return scene.static_html(dist).encode("utf-8")
        elif kind == "url" and len(frames) == 1:
            return web_url.encode()
        elif kind == "stats" and len(frames) == 1:
            return json.dumps({**stats, "browsers": len(browsers),
                               "queued": [len(b.outbox) for b in browsers],
                               "queued_bytes": [b.outbox.bytes for b in browsers],
                               "dropped": stats["dropped_closed"] + sum(b.outbox.dropped for b in browsers)
                               }).encode()
        else:
            raise ValueError(f"unknown command {kind[:40]!r} with {len(frames)} frames")
        keyed = [(Scene.check(k, path, data), data) for k, path, data in items]  # all checked, then applied
        for key, data in keyed:
            scene.apply(key, data)
            broadcast(key, data, True)
        return b"ok"

    async def commands() -> None:
        while True:
            frames = await rep.recv_multipart()
            try:
                answer = handle(frames)
            except Exception as exc:  # a malformed command is answered and counted; the task goes on
                stats["bad_commands"] += 1
                answer = f"error: {exc}"[:300].encode()
            await rep.send(answer)

    if parent is not None:
        threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()
    print(json.dumps({"zmq_url": zmq_url, "web_url": web_url}), flush=True)
    loop = asyncio.get_event_loop()
    task = loop.create_task(commands())  # kept: the loop holds tasks only weakly
    loop.run_forever()
    task.cancel()


def _watch_parent(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twin.viewer.server", description=__doc__.split("\n\n")[0])
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--zmq-port", type=int, default=0, help="command socket port (default: any free one)")
    parser.add_argument("--web-port", type=int, default=7000,
                        help="page port, or the next free one after it (default 7000; 0: any free one)")
    parser.add_argument("--parent", type=int, default=None, help="exit when this process id is no longer the parent")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore", DeprecationWarning)  # pyzmq/tornado event-loop notes, irrelevant here
    asyncio.set_event_loop(asyncio.new_event_loop())
    try:
        serve(args.host, args.zmq_port, args.web_port, args.parent)
    except KeyboardInterrupt:
        return 0
    except (ImportError, OSError) as exc:
        print(f"twin viewer server: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
