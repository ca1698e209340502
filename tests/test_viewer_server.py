"""The viewer's scene server against hostile or careless local clients (issue 23 B9, B10, B11, ``/static/%00``):
browsers that never read, malformed commands on the zmq socket, requests by a foreign name (DNS rebinding).

Real server process (``python -m twin.viewer.server``), real sockets on 127.0.0.1, bounded in count and time;
waits are hang guards, never speed limits.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from io_helpers import request

from twin.viewer import commands as cmd
from twin.viewer.client import SceneClient
from twin.viewer.server import MAX_BROWSERS, MAX_QUEUED, MAX_QUEUED_BYTES

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


@pytest.fixture
def server():
    """A scene server on loopback: (web port, zmq url, pid); killed at the end."""
    proc = subprocess.Popen([sys.executable, "-m", "twin.viewer.server", "--web-port", "0"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        urls = json.loads(proc.stdout.readline())
        port = int(urls["web_url"].split(":")[2].split("/")[0])
        yield port, urls["zmq_url"], proc.pid
    finally:
        proc.kill()
        proc.wait(timeout=30)


def status(port: int, path: str, host: str | None = None, origin: str | None = None, upgrade: bool = False) -> int:
    code, sock = request(port, path, host, origin, upgrade=upgrade)
    sock.close()
    return code


def stats(zmq_url: str) -> dict:
    client = SceneClient(zmq_url, timeout=10.0)
    try:
        return json.loads(client._request([b"stats"]))
    finally:
        client.close()


def rss_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024


# ------------------------------------------------------------------------------------------ B11, /static/%00
def test_only_loopback_hosts_and_origins_reach_pages_and_the_websocket(server):
    """B11: any Host was served and /ws upgraded when Origin equalled that foreign host (DNS rebinding)."""
    port = server[0]
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"LOCALHOST:{port}", f"[::1]:{port}"):
        assert status(port, "/static/", host) == 200, host
        assert status(port, "/ws", host, f"http://{host}", upgrade=True) == 101, host
    assert status(port, "/static/main.min.js") == 200
    assert status(port, "/ws", upgrade=True) == 101  # a program (no Origin) on loopback
    evil = f"evil.example:{port}"
    for host, origin in [(evil, f"http://{evil}"),  # the rebinding page itself
                         (evil, None), (f"127.0.0.1.evil.example:{port}", None), (f"127.0.0.1:{port + 1}", None),
                         ("127.0.0.1", None), ("", None), (f"127.0.0.1:{port}", f"http://{evil}"),
                         (f"127.0.0.1:{port}", f"http://127.0.0.1:{port + 1}"),
                         (f"127.0.0.1:{port}", f"https://127.0.0.1:{port}"), (f"127.0.0.1:{port}", "null")]:
        assert status(port, "/ws", host, origin, upgrade=True) == 403, (host, origin)
        assert status(port, "/static/", host, origin) == 403, (host, origin)
        assert status(port, "/static/main.min.js", host, origin) == 403, (host, origin)


def test_a_path_with_a_nul_byte_is_not_found(server):
    """Also seen: GET /static/%00 answered 500 (the OS refuses the name)."""
    assert status(server[0], "/static/%00") == 404
    assert status(server[0], "/static/a%00b.js") == 404
    assert status(server[0], "/static/") == 200  # and the server goes on


# ------------------------------------------------------------------------------------------------------ B10
def test_malformed_commands_are_answered_counted_and_the_task_goes_on(server):
    """B10: a non-UTF-8 hud or a set_property that is not a map killed the command task silently."""
    import umsgpack
    import zmq

    port, zmq_url, _ = server
    sock = zmq.Context.instance().socket(zmq.REQ)
    sock.setsockopt(zmq.RCVTIMEO, 10_000)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(zmq_url)
    bad = [[b"hud", b"", b"\xff\xfe{}"],  # not UTF-8
           [b"hud", b"", b"[1, 2]"],  # JSON, not an object
           [b"hud", b"", b"{"],
           [b"set_property", b"/twin", umsgpack.packb([1, 2])],  # not a map
           [b"set_property", b"/twin", umsgpack.packb({"type": "set_property", "value": 1})],  # no name
           [b"set_property", b"/twin", b"\xc1"],  # not msgpack
           [b"set_object", b"/tw\xffin", cmd.set_object("/a", {})[2]],  # path not UTF-8
           [b"set_transform", b"/twin", cmd.set_property("/twin", "x", 1)[2]],  # a map of another type
           [b"batch", *cmd.set_transform("/ok", np.eye(4))[:2], b"", b"delete", b"/x", b"\x00"],
           [b"\xff"], [b"nonsense", b"", b""]]
    try:
        for frames in bad:
            sock.send_multipart([f if isinstance(f, bytes) else f.encode() for f in frames])
            assert sock.recv().startswith(b"error: "), frames
        assert stats(zmq_url)["bad_commands"] == len(bad)
        # the task lives: a good command is applied and reaches a browser; the half-bad batch was not applied
        client = SceneClient(zmq_url, timeout=10.0)
        client.send(cmd.set_property("/twin/probe", "visible", False))
        client.hud({"title": "still here"})
        client.close()
    finally:
        sock.close()
    got = asyncio.run(_read(f"ws://127.0.0.1:{port}/ws", 2))
    import umsgpack as u

    assert [u.unpackb(m)["path"] for m in got if isinstance(m, bytes)] == ["/twin/probe"]
    assert [json.loads(m) for m in got if isinstance(m, str)] == [{"title": "still here"}]


async def _read(url: str, n: int, until=None) -> list:
    import tornado.websocket

    conn = await tornado.websocket.websocket_connect(url)
    out = []
    try:
        while len(out) < n:
            m = await asyncio.wait_for(conn.read_message(), 20)
            assert m is not None, "closed"
            out.append(m)
            if until is not None and until(m):
                break
    finally:
        conn.close()
    return out


# ------------------------------------------------------------------------------------------------------- B9
def test_outbox_keeps_the_latest_per_key_in_order_within_its_bounds():
    from twin.viewer.server import Outbox

    box = Outbox(max_items=3, max_bytes=10)
    box.put(("a",), b"a1", True)
    box.put(("b",), b"b1", True)
    box.put(("a",), b"a2", True)  # replaces a1, goes to the back
    assert (len(box), box.bytes, box.dropped) == (2, 4, 1)
    box.put(("c",), "c1", False)
    box.put(("d",), b"d1", True)  # four keys: the oldest (b1) goes
    assert box.dropped == 2 and [box.pop() for _ in range(4)] == [(b"a2", True), ("c1", False), (b"d1", True), None]
    assert box.bytes == 0 and not box.ready.is_set()
    box.put(("e",), b"e" * 6, True)
    box.put(("f",), b"f" * 6, True)  # 12 bytes > 10: the oldest goes
    assert [box.pop() for _ in range(2)] == [(b"f" * 6, True), None] and box.dropped == 3
    box.put(("g",), b"g" * 50, True)  # alone over the byte bound: still kept (never fewer than one)
    assert box.pop() == (b"g" * 50, True)


def test_browsers_that_never_read_hold_bounded_queues_and_a_reader_gets_the_latest_scene(server):
    """B9: the server buffered without bound for a websocket client that does not read (66 → 326 MiB in 25 s
    with two). Here MAX_BROWSERS + 2 browsers connect and never read (a small receive window), ~16 MB of scene
    commands per browser are sent; the queues stay within their bounds, the process's RSS grows by less than
    48 MiB (the bound: 16 queues holding the one ~0.25 MB mesh they keep plus small commands, ~0.3 MB each,
    and tornado's one message in writing each; before the fix it grew by the whole ~260 MB), the two extra
    browsers evicted the ones furthest behind, and a browser that reads gets the latest state."""
    import umsgpack

    port, zmq_url, pid = server
    idle = []
    try:
        for _ in range(MAX_BROWSERS + 2):
            code, sock = request(port, "/ws", upgrade=True, rcvbuf=4096)
            assert code == 101
            idle.append(sock)
        client = SceneClient(zmq_url, timeout=20.0)
        rng = np.random.default_rng(0)
        verts = rng.normal(size=(7000, 3))
        faces = rng.integers(0, 7000, size=(14000, 3))
        mesh = cmd.set_object("/twin/shape", cmd.mesh(verts, faces, cmd.material()))  # ~0.25 MB
        client.send(mesh)
        s0 = stats(zmq_url)
        assert s0["browsers"] == MAX_BROWSERS and s0["evicted"] == 2
        rss0 = rss_mib(pid)
        frames = 64
        for k in range(frames):
            # one frame: the big mesh, the probe's new value, and a node of its own (distinct paths: the
            # count bound, not only the replacement, is exercised)
            client.send_many([mesh, cmd.set_property("/twin/probe", "value", k),
                              cmd.set_transform(f"/twin/node{k}", np.eye(4))])
        client.hud({"title": f"frame {frames - 1}"})
        s = stats(zmq_url)
        grown = rss_mib(pid) - rss0
        assert s["browsers"] == MAX_BROWSERS
        assert max(s["queued"]) <= MAX_QUEUED and max(s["queued_bytes"]) <= MAX_QUEUED_BYTES
        assert s["dropped"] > 0
        assert grown < 48, f"RSS grew by {grown:.0f} MiB with {MAX_BROWSERS} browsers that do not read"

        # a browser that reads: it gets in (one that does not read goes) and sees the latest state
        got = asyncio.run(_read(f"ws://127.0.0.1:{port}/ws", 10_000, until=lambda m: isinstance(m, str)))
        probe = [umsgpack.unpackb(m) for m in got if isinstance(m, bytes)]
        probe = [c["value"] for c in probe if c["path"] == "/twin/probe"]
        assert probe == [frames - 1] and json.loads(got[-1]) == {"title": f"frame {frames - 1}"}
        assert stats(zmq_url)["evicted"] == 3
        client.close()
    finally:
        for sock in idle:
            sock.close()
