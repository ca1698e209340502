"""The one real third-party FBG client, ``myfbgcommunication`` 2.0.2 (unmodified), reads the simulated FiSpec
interrogator over a pseudo-terminal (docs/protocols.md §2).

Tolerance: the protocol carries peak wavelengths as integers of 1e-4 nm and the client returns those integers
as they are, so what it reads must equal round(λ·1e4) exactly — the protocol's quantisation and nothing else.
On-board strain travels as int32 of 1e-4 µε, so it must match to 0.5e-4 µε plus float rounding.

The client spins forever on a reply of the wrong length, so every test has a pytest-timeout.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from conftest import require_module
from io_helpers import ManualSource, wait_until

from sim_interrogator.servers import FispecServer
from twin import strain
from twin.synthetic import multicore_fiber

os.environ.setdefault("MPLBACKEND", "Agg")
fbg = require_module("myFBGcommunication.myFBGcommunication",
                     "the FiSpec third-party client (pip install -e '.[test]' installs myfbgcommunication)")

CORE = 1  # an outer core: it sees bending, so a shape change moves its peaks


def shape(fiber, k_x: float, k_y: float) -> np.ndarray:
    k = np.zeros((fiber.n_gratings, 2))
    k[:, 0], k[:, 1] = k_x, k_y
    return strain.forward(fiber, k)


@pytest.fixture
def server():
    fiber = multicore_fiber(4, 18)
    source = ManualSource(fiber, shape(fiber, 10.0, 3.0))
    srv = FispecServer(source, cores=[CORE]).start()
    assert srv.pump.wait_first(10)
    yield srv, source, fiber
    srv.close()


@pytest.fixture
def client_class():
    """The client with raw wavelengths (its default ``on_boradCalc`` must be switched off before construction,
    docs/protocols.md §2.3); the class default is restored afterwards."""
    old = fbg.FBGcom._default_value.on_boradCalc
    fbg.FBGcom._default_value.on_boradCalc = False
    yield fbg.FBGcom
    fbg.FBGcom._default_value.on_boradCalc = old


@pytest.mark.timeout(120)
def test_client_detects_the_device_and_reads_the_simulated_peaks(server, client_class):
    srv, source, fiber = server
    client = client_class()
    try:
        assert client.init(srv.paths[0]) == 1  # device detected, 18 peaks found in the spectrum
        assert client.FBG_num == fiber.n_gratings
        want = np.round(source.wavelengths[:, CORE] * 1e4)
        for _ in range(3):
            np.testing.assert_array_equal(client.read_all(), want)
        # the windows the client set are centred on the peaks it found in the spectrum (±1.5 nm)
        centres = np.array([(lo + hi) / 2 for lo, hi in client.WL_ranges]) / 1e4
        assert np.all(np.abs(centres - want / 1e4) < 0.05)  # one pixel of the 2048-pixel table ≈ 0.049 nm

        # the simulated shape changes (peaks move by up to ~1 nm, inside the client's windows)
        source.set(shape(fiber, -12.0, 3.0))
        want2 = np.round(source.wavelengths[:, CORE] * 1e4)
        assert np.abs(want2 - want).max() > 5000  # the change is visible: > 0.5 nm
        # the server answers P> from its latest frame: the new shape shows within a few polls, then stays
        assert wait_until(lambda: np.array_equal(client.read_all(), want2), timeout=30)
        np.testing.assert_array_equal(client.read_all(), want2)
        assert srv.stats()["command_errors"] == 0
    finally:
        if client._ser is not None:
            client._ser.close()


@pytest.mark.timeout(120)
def test_client_on_board_strain(server):
    srv, source, fiber = server
    client = fbg.FBGcom()  # the default: on-board strain calculation (OBB,1)
    try:
        assert client.init(srv.paths[0]) == 1
        # OBN zeroed the strain at the current shape: it reads 0 until the shape changes
        np.testing.assert_allclose(client.read_all(), 0.0, atol=1e-4)
        before = source.wavelengths[:, CORE].copy()
        source.set(shape(fiber, 14.0, 3.0))
        after = np.round(source.wavelengths[:, CORE] * 1e4) / 1e4
        ref = np.round(before * 1e4) / 1e4
        want = (after - ref) / ref / fiber.strain_sensitivity * 1e6  # µε
        time.sleep(0.1)
        assert wait_until(lambda: np.allclose(client.read_all(), want, atol=0.5e-4 + 1e-9, rtol=0), timeout=30)
    finally:
        if client._ser is not None:
            client._ser.close()


@pytest.mark.timeout(120)
def test_a_second_client_session_on_the_same_port(server, client_class):
    """A client that left replies unread must not confuse the next one (the server flushes on '?>')."""
    srv, source, _ = server
    first = client_class()
    assert first.init(srv.paths[0]) == 1
    first._ser.write(b"P>s>")  # ask and leave without reading
    time.sleep(0.2)
    first._ser.close()
    second = client_class()
    try:
        assert second.init(srv.paths[0]) == 1
        np.testing.assert_array_equal(second.read_all(), np.round(source.wavelengths[:, CORE] * 1e4))
    finally:
        second._ser.close()
