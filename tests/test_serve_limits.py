"""Limits of `twin serve` and its servers against careless users and hostile local clients (issue 23, B12, B14).

Everything on 127.0.0.1, bounded in count and time; the time bounds are hang guards, never speed limits.
"""

from __future__ import annotations

import socket
import time

import pytest
from io_helpers import singles, wait_until

from sim_interrogator.servers import HyperionServer, IllumisenseServer
from sim_interrogator.servers.common import MAX_CLIENTS
from twin.cli import main
from twin.io.hyperion.driver import HyperionSource
from twin.io.illumisense.driver import IllumisenseSource
from twin.synthetic import SyntheticSource, multicore_fiber


@pytest.mark.parametrize(("argv", "names"), [
    (["serve", "illumisense", "--port", "70000"], "--port"),
    (["serve", "hyperion", "--port", "-1"], "--port"),
    (["serve", "illumisense", "--port", "0", "--duration", "nan"], "--duration"),
    (["serve", "illumisense", "--port", "0", "--duration", "-1"], "--duration"),
    (["serve", "illumisense", "--port", "0", "--duration", "inf"], "--duration"),
    (["serve", "illumisense", "--port", "0", "--rate", "nan"], "--rate"),
    (["live", "synthetic://?rate=100", "--frames", "5", "--print-rate", "-1"], "--print-rate"),
    (["live", "synthetic://?rate=100", "--frames", "5", "--print-rate", "nan"], "--print-rate"),
])
def test_impossible_numbers_get_one_line_and_status_2(argv, names, capsys):
    """B14: --port 70000 gave a traceback, --duration nan never stopped, -1 was accepted, --print-rate -1 too."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"twin {argv[0]}: error: {names} must be"), err


# ------------------------------------------------------------------------------------------------------ B12
def idle_connections(address, n: int) -> list[socket.socket]:
    """``n`` connections that never read nor send (a small receive window, so they fall behind soon)."""
    out = []
    for _ in range(n):
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.settimeout(10.0)
        sock.connect(address)
        out.append(sock)
    return out


def read_n(src, n: int, timeout: float) -> list:
    out = []
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        out += singles(src.read_batch(n - len(out), 0.2))
    return out


@pytest.mark.parametrize("protocol", ["illumisense", "hyperion"])
def test_forty_idle_connections_do_not_lock_the_real_client_out(protocol):
    """B12: 40 idle local connections filled the 32-client cap; the real client was refused (Hyperion for as
    long as they stayed, ILLumiSense until each was 4,096 records, here 41 s, behind). Now each newcomer is
    served and the connection furthest behind (the quietest) makes way. 30 s is a hang guard."""
    fiber = multicore_fiber(4, 18)
    source = SyntheticSource(rate=100, fiber=fiber)
    server = (IllumisenseServer(source, port=0) if protocol == "illumisense" else HyperionServer(source, port=0))
    idle: list[socket.socket] = []
    with server:
        ports = [server.address] + ([server.stream_address] if protocol == "hyperion" else [])
        for address in ports:
            idle += idle_connections(address, 40)
        assert wait_until(lambda: server.stats()["evicted"] == len(ports) * (40 - MAX_CLIENTS))
        if protocol == "illumisense":
            src = IllumisenseSource("127.0.0.1", server.address[1])
        else:
            src = HyperionSource("127.0.0.1", server.address[1], stream_port=server.stream_address[1], fiber=fiber)
        try:
            got = read_n(src, 20, timeout=30.0)
        finally:
            src.close()
        assert len(got) == 20
        assert server.stats()["evicted"] >= len(ports) * (40 - MAX_CLIENTS + 1)  # the real client came in
    for sock in idle:
        sock.close()


def test_clients_that_take_nothing_are_dropped_after_the_idle_timeout():
    """B12: no idle timeout; a client that never reads is dropped once it has taken nothing for idle_timeout s
    (after the kernel's buffers filled), a command connection that asks nothing likewise."""
    fiber = multicore_fiber(4, 18)
    with IllumisenseServer(SyntheticSource(rate=500, fiber=fiber), port=0, idle_timeout=0.5) as server:
        (sock,) = idle_connections(server.address, 1)
        assert wait_until(lambda: server.stats()["dropped_idle"] == 1, timeout=60.0), server.stats()
        assert server.stats()["clients"] == 0 and server.stats()["dropped_slow"] == 0
        sock.close()
    with HyperionServer(SyntheticSource(rate=100, fiber=fiber), port=0, idle_timeout=0.5) as server:
        (conn,) = idle_connections(server.address, 1)
        conn.settimeout(30.0)
        assert conn.recv(100) == b""  # closed by the server
        assert wait_until(lambda: server.stats()["idle_closed"] == 1)
        conn.close()
