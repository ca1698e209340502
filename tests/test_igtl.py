"""OpenIGTLink for 3D Slicer (twin.igtl), checked by an independent receiver written here from the specification.

The receiver below parses the 58-byte header (version, type, device name, timestamp, body size, CRC-64), checks
the CRC with its own bit-by-bit ECMA-182 CRC-64 (not our sender's table-driven one), and decodes the TRANSFORM
and POLYDATA bodies field by field. Nothing of twin.igtl is used to read what twin.igtl wrote. Real sockets on
loopback; clients connect and disconnect while the live loop runs. Where Debian's libopenigtlink-dev is
installed (``apt-get install libopenigtlink-dev g++``), a reader built on it checks the stream too.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import require_tool

from twin import FiberModel, Reconstructor
from twin.frames import Frame, Shape, Truth
from twin.igtl import IgtlServer, IgtlSink, crc64, parse_address
from twin.live import LiveLoop, LiveStatus
from twin.synthetic import SyntheticSource

POLY = 0x42F0E1EBA9EA3693  # ECMA-182, from the OpenIGTLink header specification
MASK = (1 << 64) - 1


# ------------------------------------------------------------------------------------------------ the receiver
def crc64_bitwise(data: bytes) -> int:
    """CRC-64/ECMA-182, one bit at a time: initial value 0, MSB first, no reflection, no final XOR."""
    crc = 0
    for byte in data:
        crc ^= byte << 56
        for _ in range(8):
            crc = ((crc << 1) ^ POLY) & MASK if crc & (1 << 63) else (crc << 1) & MASK
    return crc


def read_exact(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise EOFError("the sender closed the connection")
        buf += chunk
    return buf


def receive(sock: socket.socket) -> dict:
    """One message: header fields, the CRC checked, the body decoded for TRANSFORM and POLYDATA."""
    header = read_exact(sock, 58)
    version = int.from_bytes(header[0:2], "big")
    kind = header[2:14].rstrip(b"\0").decode("ascii")
    device = header[14:34].rstrip(b"\0").decode("ascii")
    stamp = int.from_bytes(header[34:42], "big")
    size = int.from_bytes(header[42:50], "big")
    crc = int.from_bytes(header[50:58], "big")
    body = read_exact(sock, size)
    assert crc64_bitwise(body) == crc, (kind, device)
    msg = {"version": version, "type": kind, "device": device, "time": (stamp >> 32) + (stamp & 0xFFFFFFFF) / 2**32,
           "size": size}
    if kind == "TRANSFORM":
        assert size == 48
        v = struct.unpack(">12f", body)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = v[0:3], v[3:6], v[6:9], v[9:12]
        msg["matrix"] = m
    elif kind == "POLYDATA":
        (npoints, nvert, svert, nlines, slines, npoly, spoly, nstrips, sstrips, nattr) = struct.unpack(
            ">10I", body[:40])
        at = 40
        msg["points"] = np.array(struct.unpack(f">{3 * npoints}f", body[at: at + 12 * npoints])).reshape(npoints, 3)
        at += 12 * npoints
        cells = {}
        for name, n, s in (("vertices", nvert, svert), ("lines", nlines, slines), ("polygons", npoly, spoly),
                           ("strips", nstrips, sstrips)):
            words = struct.unpack(f">{s // 4}I", body[at: at + s])
            at += s
            out, i = [], 0
            while i < len(words):  # (count, index …) per cell
                out.append(list(words[i + 1: i + 1 + words[i]]))
                i += 1 + words[i]
            assert len(out) == n, name
            cells[name] = out
        # attributes: 6-byte headers (type, components, count), NUL-terminated names padded to an even length,
        # then the values as big-endian float32
        heads = [struct.unpack(">BBI", body[at + 6 * i: at + 6 * i + 6]) for i in range(nattr)]
        at += 6 * nattr
        names = []
        start = at
        for _ in range(nattr):
            end = body.index(b"\0", at)
            names.append(body[at:end].decode("ascii"))
            at = end + 1
        at += (at - start) % 2
        attributes = {}
        for name, (kind, components, count) in zip(names, heads, strict=True):
            assert kind == 0 and components == 1 and count == npoints  # point scalars
            attributes[name] = np.array(struct.unpack(f">{count}f", body[at: at + 4 * count]))
            at += 4 * count
        assert at == size  # nothing else in the body
        msg.update(cells, attributes=attributes)
    return msg


# ------------------------------------------------------------------------------------------------ helpers
def arc(kappa: float = 20.0, n: int = 171) -> Shape:
    s = np.linspace(0.0, 0.17, n)
    c, sn = np.cos(kappa * s), np.sin(kappa * s)
    pos = np.stack([(1 - c) / kappa, 0 * s, sn / kappa], -1)
    frames = np.stack([np.stack([c, 0 * s, -sn], -1), np.tile([0.0, 1.0, 0.0], (n, 1)), np.stack([sn, 0 * s, c], -1)],
                      -1)
    return Shape(s=s, positions=pos, frames=frames, curvature=np.tile([kappa, 0.0], (18, 1)),
                 grating_s=np.linspace(0.005, 0.165, 18), valid=np.ones(18, bool))


def batch(shape: Shape) -> Shape:
    return Shape(s=shape.s, positions=shape.positions[None], frames=shape.frames[None],
                 curvature=shape.curvature[None], grating_s=shape.grating_s, valid=shape.valid[None],
                 covariance=None if shape.covariance is None else shape.covariance[None])


def connect(server: IgtlServer) -> socket.socket:
    sock = socket.create_connection(server.address, timeout=10)
    deadline = time.monotonic() + 10
    while server.clients_seen == 0 or server.clients < 1:  # accepted by the server thread
        assert time.monotonic() < deadline
        time.sleep(0.01)
    return sock


# ------------------------------------------------------------------------------------------------ tests
def test_crc64_matches_the_ecma_182_check_value():
    # the CRC catalogue's check value of CRC-64/ECMA-182 for b"123456789"
    assert crc64_bitwise(b"123456789") == 0x6C40DF5F0B497347
    assert crc64(b"123456789") == 0x6C40DF5F0B497347
    rng = np.random.default_rng(1)
    for n in (0, 1, 57, 1000):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert crc64(data) == crc64_bitwise(data)


def test_address_defaults_to_loopback():
    assert parse_address("18944") == ("127.0.0.1", 18944)
    assert parse_address("0.0.0.0:5000") == ("0.0.0.0", 5000)
    for bad in ("x", "70000", ":", "host:"):
        with pytest.raises(ValueError, match="igtl"):
            parse_address(bad)


def test_a_frame_arrives_as_shape_polyline_tip_transform_and_truth():
    shape = arc()
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90° about z
    p = np.array([0.01, 0.02, 0.03])
    world = shape.positions @ R.T + p
    truth = Truth(s=shape.s, positions=world + np.array([0.0, 0.0, 1e-4]), frames=R @ shape.frames)
    with IgtlServer(port=0) as server:
        assert server.address[0] == "127.0.0.1"
        sock = connect(server)
        sink = IgtlSink(server, rate=1000.0, close_server=False)
        status = LiveStatus(state="live", flags=np.zeros(1, np.uint8))
        sink([Frame(np.zeros((18, 4)), truth=truth)], batch(shape), status)
        t0 = time.time()
        got = {m["device"]: m for m in (receive(sock) for _ in range(3))}
        sock.close()
    assert sink.frames_sent == 1 and sink.errors == 0
    poly = got["CatheterShape"]
    assert poly["version"] == 1 and poly["type"] == "POLYDATA" and abs(poly["time"] - t0) < 60
    # placed at the truth's base pose (its frame and point at s = 0), in mm; float32 on the wire (≈ 1e-5 mm)
    base = truth.positions[0]
    np.testing.assert_allclose(poly["points"], 1e3 * (shape.positions @ R.T + base), atol=1e-4)
    assert poly["lines"] == [list(range(len(shape.s)))] and poly["vertices"] == [] and poly["polygons"] == []
    tip = got["CatheterTip"]
    assert tip["type"] == "TRANSFORM"
    np.testing.assert_allclose(tip["matrix"][:3, :3], R @ shape.frames[-1], atol=1e-6)
    np.testing.assert_allclose(tip["matrix"][:3, 3], poly["points"][-1], atol=1e-4)
    tr = got["CatheterTruth"]
    np.testing.assert_allclose(tr["points"], 1e3 * truth.positions, atol=1e-4)
    assert tr["lines"] == [list(range(len(shape.s)))]
    assert poly["attributes"] == {} and tr["attributes"] == {}  # no uncertainty on this shape


def test_the_confidence_tube_travels_as_point_scalars():
    """A shape with its uncertainty: CatheterShape carries Sigma and Confidence95 per point, in mm."""
    from twin import FiberModel, strain
    from twin.uncertainty import ModelError, Uncertainty

    fiber = FiberModel.paper()
    k = np.tile([20.0, 5.0], (fiber.n_gratings, 1))
    unc = Uncertainty(Reconstructor(fiber), model_error=ModelError(0.05, base_angle=1e-3))
    shape = unc(strain.forward(fiber, k)[None])
    with IgtlServer(port=0) as server:
        sock = connect(server)
        sink = IgtlSink(server, rate=1000.0, close_server=False)
        sink([Frame(np.zeros((18, 4)))], shape, LiveStatus(state="live", flags=np.zeros(1, np.uint8)))
        got = {m["device"]: m for m in (receive(sock) for _ in range(2))}
        sock.close()
    att = got["CatheterShape"]["attributes"]
    assert sorted(att) == ["Confidence95", "Sigma"]
    np.testing.assert_allclose(att["Sigma"], 1e3 * shape.sigma[0], rtol=1e-6, atol=1e-9)  # float32 on the wire
    np.testing.assert_allclose(att["Confidence95"], 1e3 * shape.confidence(0.95)[0], rtol=1e-6, atol=1e-9)
    assert att["Sigma"][0] == 0.0 and np.all(att["Confidence95"][1:] > att["Sigma"][1:])


def test_without_truth_only_shape_and_tip_are_sent():
    with IgtlServer(port=0) as server:
        sock = connect(server)
        sink = IgtlSink(server, close_server=False)
        sink([Frame(np.zeros((18, 4)))], batch(arc()), LiveStatus(state="live", flags=np.zeros(1, np.uint8)))
        first = [receive(sock)["device"] for _ in range(2)]
        sock.settimeout(0.3)
        with pytest.raises(TimeoutError):
            sock.recv(1)
        sock.close()
    assert first == ["CatheterShape", "CatheterTip"]


def test_clients_come_and_go_during_a_live_run():
    """A client reads and leaves abruptly, another connects mid-run, a third never reads: the loop runs on."""
    server = IgtlServer(port=0, max_backlog=64 * 1024)
    sink = IgtlSink(server, rate=50.0)
    src = SyntheticSource(rate=500, pace=True)
    loop = LiveLoop(src, Reconstructor(src.fiber), [sink])
    import threading

    result = {}
    # the run ends when the clients are done (loop.stop), not after a set time: a slow start on a loaded machine
    # cannot end it under them; 120 s is only a hang guard
    runner = threading.Thread(target=lambda: result.update(summary=loop.run(duration=120.0, handle_signals=False)))
    runner.start()
    try:
        a = connect(server)
        seen_a = [receive(a) for _ in range(9)]
        a.close()  # gone without a word
        idle = socket.create_connection(server.address, timeout=10)  # connected, never reads
        idle.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        time.sleep(0.5)
        b = socket.create_connection(server.address, timeout=10)
        seen_b = [receive(b) for _ in range(12)]
        b.close()
    finally:
        loop.stop("clients done")
        runner.join(timeout=60)
    summary = result["summary"]
    assert summary.sink_errors == () and sink.errors == 0 and summary.reason == "clients done"
    # the loop kept going through the clients' comings and goings: every bundle sent (3 messages: shape, tip,
    # truth) is a frame reconstructed, a and b saw 3 and 4 distinct bundles, and the source never failed
    assert summary.status.frames >= sink.frames_sent >= 9 // 3 + 12 // 3 and summary.status.source_errors == 0
    for seen in (seen_a, seen_b):  # whole bundles, in order, truth included (the synthetic source has one)
        assert [m["device"] for m in seen[:3]] == ["CatheterShape", "CatheterTip", "CatheterTruth"]
        assert all(m["lines"] and len(m["lines"][0]) == len(m["points"]) for m in seen if m["type"] == "POLYDATA")
    assert server.clients_seen == 3
    idle.close()
    assert sink.frames_sent >= 10
    # the loop closed the sink, which closed the server: nobody can connect any more
    with pytest.raises(OSError):
        socket.create_connection(server.address, timeout=2)


def test_twin_live_igtl_flag():
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "twin.cli", "live", "synthetic://?rate=200", "--duration", "6",
                             "--igtl", "127.0.0.1:0", "--json", "--quiet"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = ""
        deadline = time.monotonic() + 60
        while "OpenIGTLink on" not in line:
            line = proc.stderr.readline()
            assert line or proc.poll() is None, "twin live ended before serving"
            assert time.monotonic() < deadline
        host, port = line.rsplit(" ", 1)[1].strip().rsplit(":", 1)
        assert host == "127.0.0.1"
        with socket.create_connection((host, int(port)), timeout=10) as sock:
            devices = {receive(sock)["device"] for _ in range(6)}
        assert devices == {"CatheterShape", "CatheterTip", "CatheterTruth"}
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    summary = json.loads(out)
    assert summary["igtl_frames"] >= 1 and summary["igtl_clients"] == 1 and summary["igtl_errors"] == 0


# ------------------------------------------------------------------------------------------------ libopenigtlink
INCLUDE = "/usr/include/openigtlink"


def test_debians_libopenigtlink_reads_the_stream(tmp_path):
    """A reader built on Debian's libopenigtlink (tests/data/igtl_reader.cxx) checks the CRCs and decodes."""
    require_tool(os.path.isdir(INCLUDE) and shutil.which("g++") is not None,
                 "Debian's libopenigtlink-dev and g++ are not installed (.ci/run installs them)")
    reader = tmp_path / "igtl_reader"
    build = subprocess.run(["g++", "-O1", f"-I{INCLUDE}", "-o", str(reader),
                            str(Path(__file__).with_name("data") / "igtl_reader.cxx"), "-lOpenIGTLink"],
                           capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stderr[-3000:]
    from twin.uncertainty import ModelError, Uncertainty

    shape = arc()
    truth = Truth(s=shape.s, positions=shape.positions + np.array([0.0, 0.0, 1e-4]), frames=shape.frames)
    # the arc's own uncertainty: a white curvature error and a base angle, closed-form enough to be anything
    fiber = FiberModel.paper()
    unc = Uncertainty(Reconstructor(fiber), wavelength_noise=0.0, model_error=ModelError(0.05, base_angle=1e-3),
                      parameters=False)
    shape = dataclasses.replace(shape, covariance=unc.propagate(unc.reconstructor(fiber.lambda0)).covariance)
    with IgtlServer(port=0) as server:
        proc = subprocess.Popen([str(reader), "127.0.0.1", str(server.address[1]), "3"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 30
            while server.clients < 1:
                assert time.monotonic() < deadline and proc.poll() is None, proc.stderr.read()
                time.sleep(0.01)
            sink = IgtlSink(server, close_server=False)
            sink([Frame(np.zeros((18, 4)), truth=truth)], batch(shape),
                 LiveStatus(state="live", flags=np.zeros(1, np.uint8)))
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert proc.returncode == 0, err
    got = {m["device"]: m for m in map(json.loads, out.splitlines())}
    assert all(m["crc_ok"] for m in got.values())
    expected = 1e3 * (shape.positions + truth.positions[0])  # placed at the truth's base
    np.testing.assert_allclose(got["CatheterShape"]["points"], expected, atol=1e-4)
    assert got["CatheterShape"]["lines"] == [list(range(len(shape.s)))]
    assert got["CatheterShape"]["vertices"] == [] and got["CatheterShape"]["polygons"] == []
    np.testing.assert_allclose(got["CatheterTruth"]["points"], 1e3 * truth.positions, atol=1e-4)
    att = got["CatheterShape"]["attributes"]
    assert sorted(att) == ["Confidence95", "Sigma"] and att["Sigma"]["type"] == 0  # POINT_SCALAR
    np.testing.assert_allclose(att["Sigma"]["values"], 1e3 * shape.sigma, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(att["Confidence95"]["values"], 1e3 * shape.confidence(0.95), rtol=1e-6, atol=1e-9)
    assert got["CatheterTruth"]["attributes"] == {}
    m = np.array(got["CatheterTip"]["matrix"])
    np.testing.assert_allclose(m[:3, :3], shape.frames[-1], atol=1e-6)
    np.testing.assert_allclose(m[:3, 3], expected[-1], atol=1e-4)
