"""The vendor's shape, pinned by hand (docs/protocols-illumisense.md, "The vendor frame and what the twin sends").

The other vendor tests build their expectations with the code's own conversion (``VENDOR_FROM_BASE``) and compare
our reconstruction with itself. Here the expectations are written out from the document alone: an arc bent
toward the first core's direction d1 (or d2) has a closed form, and the vendor frame is ours permuted so that x
runs along the fibre; and the distance the tools report is checked on a case with a closed-form answer.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_interrogator.servers import IllumisenseServer
from twin import FiberModel, strain
from twin.frames import Frame
from twin.io import illumisense
from twin.reference_errors import vendor_distance
from twin.synthetic import SyntheticSource

FIBER = FiberModel.paper()
KAPPA = 20.0  # 1/m


@pytest.mark.parametrize(("direction", "bend_axis"), [((1.0, 0.0), 1), ((0.0, 1.0), 2)])
def test_the_server_sends_an_arc_in_the_vendor_frame_written_out_by_hand(direction, bend_axis):
    """An arc of 20 1/m bent toward d1 (our +x) is, in the vendor frame (x along the fibre; d1 → y, d2 → z):
    x = sin(κs)/κ, and (1 − cos κs)/κ along y (bent toward d2: along z).

    Tolerance: our reconstruction of an arc is exact to rounding (< 1e-9 m, test_reconstruct.py); the wire
    carries the shape to 5 decimals of a cm (±5e-8 m), the curvature to 6 decimals of 1/cm (±5e-5 1/m) and the
    angle to 5 decimals (±5e-6 rad)."""
    k = np.tile(KAPPA * np.array(direction), (FIBER.n_gratings, 1))
    frame = Frame(strain.forward(FIBER, k), timestamp=0.0, sequence=1)
    server = IllumisenseServer(SyntheticSource(fiber=FIBER), port=0)
    try:
        record = illumisense.decode_record(server.encode(frame)[4:])
    finally:
        server.close()
    (sensor,) = record.sensors
    s = sensor.s
    assert s[1] - s[0] == pytest.approx(1e-3) and s[-1] == pytest.approx(0.17)  # 1 mm points over the fibre
    expected = np.zeros((s.size, 3))
    expected[:, 0] = np.sin(KAPPA * s) / KAPPA
    expected[:, bend_axis] = (1 - np.cos(KAPPA * s)) / KAPPA
    np.testing.assert_allclose(sensor.positions, expected, rtol=0, atol=1e-7)
    np.testing.assert_allclose(sensor.curvature, KAPPA, rtol=0, atol=5e-5 + 1e-9)
    np.testing.assert_allclose(sensor.angle, np.arctan2(direction[1], direction[0]), rtol=0, atol=5e-6 + 1e-12)


def test_vendor_distance_of_a_bent_shape_from_a_straight_one_has_its_closed_form():
    """Ours straight along z, the vendor's a shallow parabola y = c x² (x along the fibre, 1 mm points): after the
    best rigid fit the parabola's residual from its least-squares line is c (s² − L s + L²/6), largest at the
    ends, c L²/6 (continuous least squares over [0, L]; the sampled fit and the tilt, of order c L = 2e-3 rad,
    change it by well under 1 %). With c = 0.1 1/m over 0.17 m that is 0.482 mm; the registration is free to
    move the vendor shape anywhere, so any error of frame convention would not show, but a wrong distance
    would."""
    c, length = 0.1, 0.17
    s = np.linspace(0.0, length, 171)
    ours = np.stack([np.zeros_like(s), np.zeros_like(s), s], axis=-1)
    vendor = np.stack([s, c * s**2, np.zeros_like(s)], axis=-1)
    stats = vendor_distance(ours, s, vendor, s)
    residual = c * (s**2 - length * s + length**2 / 6)
    assert stats.max == pytest.approx(c * length**2 / 6, rel=0.01)
    # the mean over the 171 points (the ends, where the residual is largest, weigh 1/171 each: 1 % above the
    # continuous mean c L²/(9√3))
    assert stats.mean == pytest.approx(np.abs(residual).mean(), rel=0.01)
