"""`twin live --foxglove PORT` (issue 22): a client written from the Foxglove WebSocket protocol's specification —
not the SDK — connects with subprotocol ``foxglove.websocket.v1``, reads the JSON ``serverInfo`` and
``advertise`` operations, subscribes with the JSON ``subscribe`` operation, and decodes the binary message data
frames (opcode 0x01, uint32 subscription id, uint64 timestamp, little endian, then the payload) with the
protobuf schema the server advertised (a base64 FileDescriptorSet). The shapes arrive at ≥ 20 Hz, counted over a
stated window, while another client stalls; a client beyond the cap is refused (HTTP 503).
"""

from __future__ import annotations

import base64
import json
import re
import signal
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from io_helpers import request
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

SUBPROTOCOL = "foxglove.websocket.v1"
WINDOW = 3.0  # s over which the shape messages are counted
GRATINGS = 18


def _decoder(channel: dict):
    """A protobuf message class from an advertised channel (schema: base64 FileDescriptorSet)."""
    assert channel["encoding"] == "protobuf" and channel.get("schemaEncoding", "protobuf") == "protobuf"
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def _open(port: int):
    return connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=10, max_size=None,
                   close_timeout=2)


def _advertised(ws, topics: set[str], deadline: float) -> dict:
    """serverInfo first, then advertise operations until every topic is known: topic → channel."""
    first = json.loads(ws.recv(timeout=10))
    assert first["op"] == "serverInfo"
    channels: dict = {}
    while not topics <= set(channels):
        assert time.monotonic() < deadline, f"not advertised: {topics - set(channels)}"
        msg = ws.recv(timeout=10)
        if isinstance(msg, str):
            op = json.loads(msg)
            if op["op"] == "advertise":
                channels.update({c["topic"]: c for c in op["channels"]})
    return channels


@pytest.fixture
def live():
    """`twin live synthetic://… --foxglove 0` (any free port) with a cap of two clients."""
    proc = subprocess.Popen([sys.executable, "-m", "twin.cli", "live", "synthetic://?rate=200", "--foxglove", "0",
                             "--foxglove-clients", "2", "--duration", "120", "--quiet", "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = None
        deadline = time.monotonic() + 90
        while port is None and time.monotonic() < deadline:
            line = proc.stderr.readline()
            assert line, "twin live ended before serving"
            m = re.search(r"Foxglove on ws://127\.0\.0\.1:(\d+)", line)
            port = int(m.group(1)) if m else None
        assert port is not None
        yield proc, port
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=30)


def test_a_spec_client_decodes_shapes_at_20_hz_beside_a_stalled_client_and_a_third_is_refused(live):
    proc, port = live
    deadline = time.monotonic() + 60
    with _open(port) as stalled, _open(port) as ws:
        # the first client subscribes, then never reads: its queues fill and it stops taking data
        ch = _advertised(stalled, {"/catheter/scene"}, deadline)
        stalled.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": ch["/catheter/scene"]
                                                                       ["id"]}]}))
        assert ws.subprotocol == SUBPROTOCOL
        ch = _advertised(ws, {"/catheter/scene", "/catheter/tip", "/catheter/figures"}, deadline)
        assert ch["/catheter/scene"]["schemaName"] == "foxglove.SceneUpdate"
        assert ch["/catheter/figures"]["encoding"] == "json"
        scene_cls = _decoder(ch["/catheter/scene"])
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": 11, "channelId": ch["/catheter/scene"]["id"]},
            {"id": 12, "channelId": ch["/catheter/figures"]["id"]}]}))
        # a third client while two are connected: refused by the cap
        with pytest.raises(InvalidStatus) as refused:
            _open(port)
        assert refused.value.response.status_code == 503
        scenes, figures = [], []
        t0 = None
        while t0 is None or time.monotonic() - t0 < WINDOW:
            assert time.monotonic() < deadline
            msg = ws.recv(timeout=10)
            if not isinstance(msg, bytes):
                continue
            assert msg[0] == 0x01  # message data
            sub, stamp = struct.unpack_from("<IQ", msg, 1)
            assert abs(stamp * 1e-9 - time.time()) < 3600
            payload = msg[13:]
            if sub == 11:
                if t0 is None:
                    t0 = time.monotonic()  # the window starts at the first shape
                scenes.append(scene_cls.FromString(payload))
            elif sub == 12:
                figures.append(json.loads(payload))
            else:
                raise AssertionError(f"message for unknown subscription {sub}")
    rate = (len(scenes) - 1) / WINDOW
    assert rate >= 20, f"{len(scenes)} shape messages in {WINDOW} s"
    last = scenes[-1].entities[0]
    assert last.id == "catheter" and last.frame_id == "world"
    shape, truth = last.lines[0], last.lines[1]
    pts = np.array([[p.x, p.y, p.z] for p in shape.points])
    assert len(pts) > 100 and np.all(np.isfinite(pts)) and len(shape.colors) == len(pts)
    tpts = np.array([[p.x, p.y, p.z] for p in truth.points])
    assert (truth.color.r, truth.color.g, truth.color.b) == (1.0, 0.0, 1.0)
    # the synthetic source's reconstruction lies on its truth (well under a millimetre)
    assert np.linalg.norm(pts[-1] - tpts[-1]) < 1e-3
    assert len(last.spheres) == GRATINGS
    assert figures and figures[-1]["colour"] == "error" and figures[-1]["max_error_mm"] < 1.0
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130  # Ctrl-C cut a bounded run (--duration) short: README's exit statuses
    summary = json.loads(out)
    assert summary["foxglove_clients"] == 2 and summary["foxglove_clients_refused"] == 1
    assert summary["foxglove_errors"] == 0 and summary["foxglove_frames"] >= len(scenes)


def _upgrade_status(port: int, host: str, origin: str | None) -> int:
    """The HTTP status a raw WebSocket upgrade request with these ``Host`` and ``Origin`` headers gets."""
    code, sock = request(port, "/", host, origin, upgrade=True, headers=(f"Sec-WebSocket-Protocol: {SUBPROTOCOL}",))
    sock.close()
    return code


def test_foreign_host_or_origin_is_forbidden_foxglove_app_and_loopback_are_served():
    """DNS rebinding (another site's name resolved to 127.0.0.1 arrives as the Host) and pages of other sites
    (their Origin) get 403; a program (no Origin), a loopback page and Foxglove's app get the upgrade (101)."""
    from twin.foxglove import FoxgloveServer

    with FoxgloveServer(port=0, max_clients=8) as server:
        port = server.address[1]
        assert _upgrade_status(port, f"evil.example:{port}", None) == 403
        assert _upgrade_status(port, f"127.0.0.1:{port + 1}", None) == 403  # another port's name
        assert _upgrade_status(port, f"127.0.0.1:{port}", "http://evil.example") == 403
        assert _upgrade_status(port, f"localhost:{port}", f"http://evil.example:{port}") == 403
        assert server.clients_forbidden == 4
        assert _upgrade_status(port, f"127.0.0.1:{port}", None) == 101
        assert _upgrade_status(port, f"localhost:{port}", "https://app.foxglove.dev") == 101
        assert _upgrade_status(port, f"[::1]:{port}", f"http://localhost:{port}") == 101
        assert server.clients_forbidden == 4
