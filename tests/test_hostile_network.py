"""Hostile local clients of the network endpoints that hold a place (the Foxglove gate's ``max_clients``) and hostile
source URLs.
Real servers and sockets on 127.0.0.1, bounded in count and time; waits are hang guards, never speed limits."""

from __future__ import annotations

import select
import socket
import threading
import time

import pytest
from conftest import require_module
from io_helpers import request, wait_until

SUBPROTOCOL = "foxglove.websocket.v1"


def trickle(port: int, dropped: threading.Event, stop: threading.Event) -> None:
    """Send the start of an HTTP request a byte every 0.1 s, never its end, until the server closes (or 60 s)."""
    head = b"GET / HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nX-Pad: " % port + b"a" * 1000
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        deadline = time.monotonic() + 60
        for byte in head:
            if stop.is_set() or time.monotonic() > deadline:
                return
            try:
                s.sendall(bytes([byte]))
                if select.select([s], [], [], 0.1)[0] and not s.recv(4096):
                    break  # closed by the server
            except OSError:
                break
        dropped.set()


@pytest.mark.timeout(120)
def test_foxglove_clients_trickling_their_request_are_dropped_at_the_deadline_and_free_their_places():
    """Each read had a 5 s timeout but the handshake none: two clients sending a byte every 0.1 s held both
    places for as long as they liked (a 16 KiB head: hours) and the real client got 503."""
    require_module("foxglove", "foxglove-sdk (the ros extra)")
    from twin.foxglove import FoxgloveServer

    with FoxgloveServer(port=0, max_clients=2, handshake_timeout=1.0) as server:
        port = server.address[1]
        stop = threading.Event()
        drops = [threading.Event() for _ in range(2)]
        threads = [threading.Thread(target=trickle, args=(port, d, stop), daemon=True) for d in drops]
        for t in threads:
            t.start()
        try:
            assert wait_until(lambda: all(d.is_set() for d in drops), timeout=60), "tricklers still held"
            assert wait_until(lambda: server.clients == 0, timeout=20)
            code, sock = request(port, "/", f"127.0.0.1:{port}", None, upgrade=True,
                                 headers=(f"Sec-WebSocket-Protocol: {SUBPROTOCOL}",))
            sock.close()
            assert code == 101 and server.clients_refused == 0
        finally:
            stop.set()
            for t in threads:
                t.join(timeout=10)


@pytest.mark.timeout(120)
def test_a_refused_foxglove_client_that_keeps_sending_is_closed_at_the_refusal_deadline():
    """A client over the cap gets 503 and is then drained until it closes, within 2 s in all: the drain had a 1 s
    timeout per read and no deadline, so a refused client sending a byte every 0.1 s held its thread for ever (one
    thread per refused connection, without bound)."""
    require_module("foxglove", "foxglove-sdk (the ros extra)")
    from twin.foxglove import FoxgloveServer

    with FoxgloveServer(port=0, max_clients=1, handshake_timeout=60.0) as server:
        port = server.address[1]
        with socket.create_connection(("127.0.0.1", port), timeout=5) as holder:
            holder.sendall(b"GET / HTTP/1.1\r\n")  # holds the only place (its head never ends)
            assert wait_until(lambda: server.clients == 1, timeout=20)
            with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
                s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1:%d\r\n\r\n" % port)
                reply = b""
                while b"\r\n\r\n" not in reply:
                    chunk = s.recv(4096)
                    assert chunk, reply
                    reply += chunk
                assert b" 503 " in reply.split(b"\r\n")[0], reply
                t0 = time.monotonic()
                closed = False
                while time.monotonic() - t0 < 30:  # hang guard; the server closes after 2 s at most
                    try:
                        s.sendall(b"x")  # the server's close answers these with a reset
                    except OSError:
                        closed = True
                        break
                    time.sleep(0.1)
                assert closed, "a refused client that keeps sending is never closed"
                assert server.clients_refused == 1


@pytest.mark.parametrize("url", ["replay://r.h5?speed=1&speed=2", "illumisense://127.0.0.1:1?start_wait=0&start_wait=9",
                                 "synthetic://?frames=3&rate=5&frames=4000"])
def test_an_option_given_twice_in_a_url_is_one_line_naming_it(url):
    """``speed=1&speed=2`` played at 2× without a word (the last one won)."""
    from twin.io.source import open_source

    with pytest.raises(ValueError) as info:
        open_source(url)
    msg = str(info.value)
    assert "\n" not in msg and url in msg and "given more than once" in msg, msg


def test_twin_live_whose_interrogator_stays_away_past_retry_for_fails_in_one_line(capsys):
    """Giving up after ``retry_for`` ended as "source ended", status 0, with no word of why."""
    from twin.cli import main

    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]  # closed again: nothing listens there
    url = f"illumisense://127.0.0.1:{port}?wait=1&retry_for=0.3"
    code = main(["live", url, "--frames", "5", "--quiet"])
    err = [line for line in capsys.readouterr().err.splitlines() if "no connection" in line]
    assert code == 1 and len(err) == 1, (code, err)
    assert err[0].endswith(f"source failed: {url}: no connection for 0.3 s (cannot connect to 127.0.0.1:{port}: "
                           "connection refused)"), err


def test_an_interrogator_sending_another_grating_count_is_one_line_naming_its_url(capsys):
    """17 gratings where the fibre model has 18: one line, which named neither the URL nor the source."""
    import numpy as np
    from io_helpers import ScriptedServer

    from twin.cli import main
    from twin.frames import Frame
    from twin.io.illumisense import codec

    lam = (1510.0 + 5.0 * np.arange(17))[:, None] + np.zeros(4)
    recs = b"".join(codec.encode_record(Frame(lam, 1.7e9 + 0.01 * i, i)) for i in range(20))

    def script(conn: socket.socket) -> None:
        conn.sendall(recs)
        conn.recv(1)  # until the client closes

    server = ScriptedServer([script] * 3)
    try:
        url = f"illumisense://127.0.0.1:{server.port}"
        code = main(["live", url, "--duration", "60", "--quiet"])
    finally:
        server.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1] == (f"twin live: error: {url}: frames have 17 gratings × 4 cores but the fibre "
                                     "model has 18 × 4; give the sensor's fibre model (--fiber FILE)"), err
