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

__all__ = ["Scene", "main", "meshcat_dist", "page"]

PAGE = Path(__file__).with_name("static") / "index.html"


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

    def apply(self, kind: str, path: str, data: bytes) -> None:
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
            import umsgpack

            node["properties"][str(umsgpack.unpackb(data).get("property"))] = data

    def messages(self) -> list[bytes]:
        """Every stored command, in an order that rebuilds the scene (objects, then properties, transforms)."""
        out: list[bytes] = []
        for node in self.nodes.values():
            if node["object"] is not None:
                out.append(node["object"])
            out.extend(node["properties"].values())
            if node["transform"] is not None:
                out.append(node["transform"])
        return out

    def static_html(self, dist: Path) -> str:
        commands = ",\n".join(f'"{base64.b64encode(m).decode()}"' for m in self.messages())
        boot = (f"const commands = [{commands}];\n"
                "for (const c of commands) viewer.handle_command_bytearray("
                "Uint8Array.from(atob(c), ch => ch.charCodeAt(0)));\n"
                f"showHud({self.hud or 'null'});")
        script = "<script>" + (dist / "main.min.js").read_text(encoding="utf-8") + "</script>"
        return page(script=script, boot=boot)


MESHCAT_COMMANDS = ("set_object", "set_transform", "set_property", "delete")

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
    browsers: set = set()

    class PageHandler(tornado.web.RequestHandler):
        def get(self) -> None:
            self.set_header("Cache-Control", "no-store")
            self.write(page(script='<script src="main.min.js"></script>', boot=LIVE_BOOT))

    class Browser(tornado.websocket.WebSocketHandler):
        def open(self) -> None:
            browsers.add(self)
            for m in scene.messages():
                self.write_message(m, binary=True)
            if scene.hud is not None:
                self.write_message(scene.hud)

        def on_message(self, message) -> None:  # browsers have nothing to say
            pass

        def on_close(self) -> None:
            browsers.discard(self)

    def broadcast(message, binary: bool) -> None:
        for b in list(browsers):
            with contextlib.suppress(tornado.websocket.WebSocketClosedError):
                b.write_message(message, binary=binary)

    app = tornado.web.Application([
        (r"/static/?", PageHandler),
        (r"/static/index.html", PageHandler),
        (r"/static/(.*)", tornado.web.StaticFileHandler, {"path": str(dist)}),
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
    web_url = f"http://{host}:{sockets[0].getsockname()[1]}/static/"

    context = zmq.asyncio.Context.instance()
    rep = context.socket(zmq.REP)
    if zmq_port:
        rep.bind(f"tcp://{host}:{zmq_port}")
        zmq_url = f"tcp://{host}:{zmq_port}"
    else:
        zmq_url = f"tcp://{host}:{rep.bind_to_random_port(f'tcp://{host}')}"

    async def commands() -> None:
        while True:
            frames = await rep.recv_multipart()
            kind = frames[0].decode("utf-8", "replace")
            if kind in MESHCAT_COMMANDS and len(frames) == 3:
                path = frames[1].decode("utf-8", "replace")
                scene.apply(kind, path, frames[2])
                broadcast(frames[2], True)
                await rep.send(b"ok")
            elif kind == "batch" and len(frames) % 3 == 1:
                for i in range(1, len(frames), 3):
                    k, path = frames[i].decode("utf-8", "replace"), frames[i + 1].decode("utf-8", "replace")
                    if k in MESHCAT_COMMANDS:
                        scene.apply(k, path, frames[i + 2])
                        broadcast(frames[i + 2], True)
                await rep.send(b"ok")
            elif kind == "hud" and len(frames) == 3:
                scene.hud = frames[2].decode("utf-8")
                broadcast(scene.hud, False)
                await rep.send(b"ok")
            elif kind == "get_scene":
                await rep.send(scene.static_html(dist).encode("utf-8"))
            elif kind == "url":
                await rep.send(web_url.encode())
            else:
                await rep.send(b"error: unknown command " + frames[0][:40])

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
