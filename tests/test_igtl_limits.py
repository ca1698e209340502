"""OpenIGTLink server against connections that never read (issue 23 B13): a client cap that evicts the client
furthest behind, and a bounded per-client queue of whole bundles (the oldest dropped, counted).

Real sockets on 127.0.0.1, bounded in count and time; waits are hang guards, never speed limits.
"""

from __future__ import annotations

import socket

import numpy as np
from io_helpers import wait_until

from twin.frames import Shape, Truth
from twin.igtl import HEADER_SIZE, MAX_CLIENTS, IgtlServer, bundle, crc64


def arc(n: int = 2001, kappa: float = 20.0, length: float = 0.17) -> Shape:
    s = np.linspace(0.0, length, n)
    c, sn = np.cos(kappa * s), np.sin(kappa * s)
    pos = np.stack([(1 - c) / kappa, 0 * s, sn / kappa], -1)
    frames = np.stack([np.stack([c, 0 * s, -sn], -1), np.tile([0.0, 1.0, 0.0], (n, 1)),
                       np.stack([sn, 0 * s, c], -1)], -1)
    return Shape(s=s, positions=pos, frames=frames, curvature=np.tile([kappa, 0.0], (18, 1)),
                 grating_s=np.linspace(0.005, 0.165, 18), valid=np.ones(18, bool))


def read_exact(sock: socket.socket, n: int) -> bytes:
    out = bytearray()
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        assert chunk, "closed"
        out += chunk
    return bytes(out)


def message(sock: socket.socket) -> tuple[str, int, bytes]:
    """(device, timestamp word, body) of one message, its CRC checked: the stream is whole messages."""
    header = read_exact(sock, HEADER_SIZE)
    body = read_exact(sock, int.from_bytes(header[42:50], "big"))
    assert crc64(body) == int.from_bytes(header[50:58], "big")
    return header[14:34].rstrip(b"\0").decode(), int.from_bytes(header[34:42], "big"), body


def test_non_reading_clients_are_capped_and_their_queues_bounded_and_the_reader_gets_the_newest():
    """B13: no client cap and up to 1 MiB per non-reading client (500 clients: 190 → 814 MiB). 40 connections
    that never read: 16 are kept (the others evicted); ~20 MB of bundles later each has at most max_backlog
    bytes waiting plus the bundle in progress; a client that reads then gets in and receives whole bundles,
    the newest one included."""
    shape = arc()
    truth = Truth(s=shape.s, positions=shape.positions + np.array([0.0, 1e-4, 0.0]), frames=shape.frames)
    one = bundle(shape, truth, timestamp=1000.0)  # ~74 kB: three messages
    idle = []
    with IgtlServer(port=0) as server:
        for _ in range(40):
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            sock.connect(server.address)
            idle.append(sock)
        assert wait_until(lambda: server.clients_seen == 40 and server.clients == MAX_CLIENTS)
        assert server.evicted == 40 - MAX_CLIENTS
        for _ in range(300):
            server.publish(one)
        # the server thread sends what the kernel takes, then the rest waits: bounded
        assert wait_until(lambda: len(server.backlog()) == MAX_CLIENTS)
        assert max(server.backlog()) <= server.max_backlog + len(one)
        assert server.bundles_dropped > 0

        real = socket.create_connection(server.address, timeout=10)
        assert wait_until(lambda: server.evicted == 40 - MAX_CLIENTS + 1)  # one that does not read made way
        newest = bundle(shape, truth, timestamp=2000.0)
        server.publish(newest)
        seen = [message(real) for _ in range(3)]
        assert [d for d, _, _ in seen] == ["CatheterShape", "CatheterTip", "CatheterTruth"]
        assert all(t == 2000 << 32 for _, t, _ in seen)
        assert server.clients == MAX_CLIENTS
        real.close()
    for sock in idle:
        sock.close()
