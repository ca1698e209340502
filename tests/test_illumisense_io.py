"""ILLumiSense end to end: the twin's server with sensor blocks, the driver and `twin live` facing one odd first
record (issue 11.6), text logs with and without sensor blocks, and the distance to the vendor's shape that
`twin live` / `twin replay` report. Real sockets on loopback, real subprocesses.

Bound used below for the vendor distance: the server reconstructs from the frame's exact wavelengths, the
client from the wire's 4-decimal ones (≤ 5e-5 nm off). On a 37.5 µm core radius at 1510–1600 nm that is a
strain error ≤ 5e-5 / 1510 / 0.78 ≈ 4.3e-8 and a curvature error ≤ ~1.2e-3 1/m per grating; over the 0.17 m
fibre a systematic curvature error of that size moves the tip by κL²/2 ≈ 1.7e-5 m before registration. So
the two shapes agree within 0.02 mm, and any error of frame convention or units would be millimetres.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from io_helpers import ScriptedServer, singles, wait_until

from sim_interrogator.servers import IllumisenseServer
from twin import Reconstructor
from twin.io import illumisense
from twin.io.illumisense.driver import IllumisenseSource
from twin.io.illumisense.vendor import VENDOR_FROM_BASE
from twin.io.record import open_recording
from twin.io.source import open_source
from twin.live import LiveLoop
from twin.reference_errors import VendorDistance
from twin.synthetic import SyntheticSource, multicore_fiber

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg", "PYTHONUNBUFFERED": "1"}


def read_n(src, n: int, timeout: float = 30.0) -> list:
    out = []
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        out += singles(src.read_batch(n - len(out), 0.2))
    return out


def payload(seq: int, channels: int = 4) -> bytes:
    """A hand-written record: ``channels`` × 3 gratings near the test fibre's λ0 (1510, 1515, 1520 nm)."""
    body = b"".join(b"%d\t3\t0\t0\t0\t0\t1510.0%d\t1515.0%d\t1520.0%d\t-1\t-2\t-3\t" % (k + 1, k, k, k)
                    for k in range(channels))
    return b"2024/01/31\t13:45:%02d\t%d\t%d\t" % (seq % 60, seq, channels) + body[:-1] + b"\r\n"


def framed(p: bytes) -> bytes:
    return len(p).to_bytes(4, "big") + p


def odd_first_stream(n_good: int = 20) -> bytes:
    return framed(payload(0, channels=3)) + b"".join(framed(payload(k)) for k in range(1, n_good + 1))


def test_driver_learns_the_layout_despite_an_odd_first_record():
    server = ScriptedServer([odd_first_stream()])
    src = IllumisenseSource("127.0.0.1", server.port)
    try:
        got = read_n(src, 20, timeout=20)
        stats = src.stats()
    finally:
        src.close()
        server.close()
    assert [f.sequence for f in got] == list(range(1, 21))
    assert stats["odd_records"] == 1 and stats["framing_errors"] == 0 and stats["lost_samples"] == 0


def test_twin_live_keeps_going_after_an_odd_first_record(tmp_path):
    fiber = tmp_path / "fiber.toml"
    multicore_fiber(4, 3).save(fiber)
    server = ScriptedServer([lambda conn: (conn.sendall(odd_first_stream()), wait_until(lambda: False, 3))])
    try:
        run = subprocess.run([*TWIN, "live", f"illumisense://127.0.0.1:{server.port}", "--fiber", str(fiber),
                              "--frames", "20", "--duration", "30", "--json", "--quiet"],
                             capture_output=True, text=True, env=ENV, timeout=120)
    finally:
        server.close()
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["frames"] == 20 and out["frames_rejected"] == 0
    assert out["source"]["odd_records"] == 1


def test_log_whose_first_line_is_odd_keeps_the_good_lines(tmp_path):
    path = tmp_path / "log.txt"
    path.write_bytes(payload(0, channels=3) + b"".join(payload(k) for k in range(1, 21)))
    with open_recording(path) as r:
        assert len(r) == 20 and r.shape == (3, 4)
        np.testing.assert_array_equal(r.frames().sequence, np.arange(1, 21))
        assert len(r.errors) == 1 and r.errors[0].startswith("line 1: channel layout 3 channel(s)")
        assert not r.has_vendor and r.vendor() == ()


def test_server_sends_the_vendor_layout_from_its_own_reconstruction():
    fiber = multicore_fiber(7, 18)
    src = SyntheticSource(rate=500, fiber=fiber, noise=0.002, seed=3)
    server = IllumisenseServer(src, port=0)
    try:
        frames = [src.read(1.0) for _ in range(5)]
        rec = Reconstructor(fiber)
        for f in frames:
            r = illumisense.decode_record(server.encode(f)[4:])
            (sensor,) = r.sensors
            shape = rec(f.wavelengths[None])
            # 1 mm points from the base, x along the fibre axis: (x, y, z)_vendor = (z, x, y)_ours
            np.testing.assert_allclose(sensor.s, shape.s, rtol=0, atol=1e-12)
            np.testing.assert_allclose(sensor.positions, shape.positions[0] @ VENDOR_FROM_BASE.T, rtol=0, atol=1e-7)
            k = shape.curvature[0]
            np.testing.assert_allclose(sensor.curvature, np.hypot(k[:, 0], k[:, 1]), rtol=0, atol=0.5e-4 + 1e-12)
            np.testing.assert_allclose(sensor.angle, np.arctan2(k[:, 1], k[:, 0]), rtol=0, atol=0.5e-5 + 1e-12)
        assert server.encode(frames[0]).endswith(b"\r\n")
    finally:
        server.close()
    for blocks, has_curvature, has_e in (("none", False, False), ("engineering", False, True)):
        other = IllumisenseServer(SyntheticSource(rate=500, fiber=fiber), port=0, blocks=blocks)
        try:
            r = illumisense.decode_record(other.encode(frames[0])[4:])
        finally:
            other.close()
        assert bool(r.sensors) == has_curvature and (r.engineering.size == 7 * 18) == has_e


def test_live_loop_reports_the_distance_to_the_vendor_shape():
    fiber = multicore_fiber(7, 18)
    with IllumisenseServer(SyntheticSource(rate=500, fiber=fiber, noise=0.002, seed=1), port=0) as server:
        src = open_source(f"illumisense://127.0.0.1:{server.address[1]}", fiber=fiber)
        vendor = VendorDistance()
        summary = LiveLoop(src, Reconstructor(fiber), [vendor]).run(max_frames=300, duration=20,
                                                                    handle_signals=False)
    assert summary.status.frames >= 300
    d = vendor.as_dict()
    assert d["vendor_frames_compared"] >= 2
    assert 0 <= d["vendor_distance_mean_mm"] <= d["vendor_distance_max_mm"] <= 0.02


def test_replay_of_a_log_with_and_without_sensor_blocks(tmp_path):
    fiber = multicore_fiber(7, 18)
    src = SyntheticSource(rate=500, fiber=fiber, noise=0.002, seed=2, pace=False, frames=40)
    frames = list(src)
    server = IllumisenseServer(SyntheticSource(rate=500, fiber=fiber), port=0)
    lines = [server.encode(f)[4:] for f in frames]
    server.close()
    fiber_toml = tmp_path / "fiber.toml"
    fiber.save(fiber_toml)
    with_blocks, without = tmp_path / "with.txt", tmp_path / "without.txt"
    with_blocks.write_bytes(b"".join(lines))
    without.write_bytes(b"".join(illumisense.encode_payload(f, line_ending=b"\n") for f in frames))
    outs = []
    for path in (with_blocks, without):
        run = subprocess.run([*TWIN, "replay", str(path), "--fiber", str(fiber_toml), "--json", "--compare-rate", "0"],
                             capture_output=True, text=True, env=ENV, timeout=120)
        assert run.returncode == 0, run.stderr
        outs.append(json.loads(run.stdout))
    a, b = outs
    assert a["frames"] == b["frames"] == 40 and a["skipped_lines"] == b["skipped_lines"] == 0
    assert a["vendor_frames_compared"] == 40 and 0 <= a["vendor_distance_max_mm"] <= 0.02
    assert "vendor_distance_max_mm" not in b
    with open_recording(with_blocks) as r:
        (v,) = r.vendor()
        assert r.has_vendor and v.positions.shape == (40, 171, 3) and v.present.all()


def test_log_line_endings_header_and_decimal_comma(tmp_path):
    lines = [payload(k).rstrip(b"\r\n") for k in range(1, 6)]
    lines[2] = lines[2].replace(b".", b",")  # a European-locale export
    for sep in (b"\r\n", b"\n", b"\r"):
        path = tmp_path / "log.txt"
        path.write_bytes(b"Date\tTime\tSample\t(export)" + sep + sep.join(lines[:3]) + sep + b"garbage\tline" + sep
                         + sep.join(lines[3:]) + sep)
        with open_recording(path) as r:
            np.testing.assert_array_equal(r.frames().sequence, np.arange(1, 6))
            assert r.frames().wavelengths[2, 1, 1] == 1515.01  # grating 1 of channel 2, read with its comma
            assert len(r.errors) == 1 and r.errors[0].startswith("line 5:")


@pytest.mark.parametrize(("url", "key"), [
    ("illumisense://127.0.0.1:9?layout_wait=nan", "option layout_wait='nan': expected a number in [0, inf)"),
    ("illumisense://127.0.0.1:9?layout_wait=-1", "option layout_wait='-1': expected a number in [0, inf)"),
    ("illumisense://127.0.0.1:9?resync_timeout=-1", "option resync_timeout='-1': expected a number in (0, inf)"),
    ("illumisense://127.0.0.1:9?resync_timeout=inf", "option resync_timeout='inf': expected a number"),
    ("illumisense://127.0.0.1:9?retry_for=nan", "option retry_for='nan': expected a number in [0, inf)"),
    ("illumisense://127.0.0.1:9?connect_timeout=0", "option connect_timeout='0': expected a number in (0, 3600]"),
    ("illumisense://[::1:2055", "not a source URL (Invalid IPv6 URL"),
])
def test_url_options_out_of_range_name_the_url_and_key(url, key):
    """Issue 23, also seen: `layout_wait=nan` and `resync_timeout=-1` were accepted (a timer that never or at
    once elapses); "Invalid IPv6 URL" named neither the URL nor the place."""
    with pytest.raises(ValueError) as info:
        open_source(url)
    msg = str(info.value)
    assert msg.startswith(repr(url) + ":") and key in msg and "\n" not in msg, msg
