"""The rod's ground truth on the smooth curve through its vertices (models.rod_state.RodState.smooth_at,
RodTruth): against centrelines known in closed form, sampled as the twin's rod is."""

import numpy as np
import pytest

from models.rod_state import RodState, _transport, so3_log

H = 1.95e-3  # the twin's vertex spacing, m


def _rod_on(curve, tangent, base: float, length: float, h: float = H) -> RodState:
    """A RodState whose vertices lie on ``curve`` (s ↦ (..., 3)) h apart from s = −``base`` to past ``length`` by
    15 mm (the twin's tip), its sensed length ``length``, its edge frames
    the chords' with d1 transported along the rod (no twist) and the Darboux vectors the frames' (as the rod
    read makes them: log(R_{e−1}ᵀ R_e) / l̄)."""
    s = -base + h * np.arange(round((base + length + 0.015) / h) + 1)
    x = curve(s)
    seg = np.diff(x, axis=0)
    t = seg / np.linalg.norm(seg, axis=1, keepdims=True)
    d1 = np.empty_like(t)
    u = np.cross(tangent(s[:1])[0], [0.0, 1.0, 0.0])
    u = np.cross(np.array([0.0, 1.0, 0.0]), t[0]) if np.linalg.norm(u) < 1e-3 else u
    d1[0] = u - t[0] * (u @ t[0])
    d1[0] /= np.linalg.norm(d1[0])
    for e in range(1, t.shape[0]):
        d1[e] = _transport(t[e - 1, :, None], t[e, :, None], d1[e - 1, :, None])[:, 0]
    frames = np.stack([d1, np.cross(t, d1), t], axis=-1)
    darboux = so3_log(np.einsum("eji,ejk->eik", frames[:-1], frames[1:])) / h
    return RodState(0.0, s, x, 0.5 * (s[:-1] + s[1:]), frames, darboux, length)


def _wave(k0: float, k1: float, k2: float):
    """A planar curve of curvature k0 + k1 s + k2 s² 1/m (the library's wave is of that size), through the origin
    along +z at s = 0, bending towards +x; the point by Gauss–Legendre quadrature of the tangent (exact to
    rounding at these lengths)."""
    nodes, weights = np.polynomial.legendre.leggauss(40)

    def theta(s):
        return k0 * s + k1 * s**2 / 2 + k2 * s**3 / 3

    def tangent(s):
        th = theta(np.asarray(s, dtype=np.float64))
        return np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], axis=-1)

    def curve(s):
        s = np.asarray(s, dtype=np.float64)
        u = 0.5 * s[..., None] * (nodes + 1.0)  # nodes on [0, s]
        tq = tangent(u)
        return 0.5 * s[..., None] * np.einsum("...n,...nk->...k", weights * np.ones_like(u), tq)

    return curve, tangent


def _helix(radius: float, pitch: float):
    """A helix about +z (curvature r/(r² + c²), torsion c/(r² + c²), c = pitch/2π) in arc length."""
    c = pitch / (2 * np.pi)
    w = 1.0 / np.hypot(radius, c)

    def curve(s):
        s = np.asarray(s, dtype=np.float64)
        return np.stack([radius * np.cos(w * s), radius * np.sin(w * s), c * w * s], axis=-1)

    def tangent(s):
        s = np.asarray(s, dtype=np.float64)
        return np.stack([-radius * w * np.sin(w * s), radius * w * np.cos(w * s), np.full_like(s, c * w)], axis=-1)

    return curve, tangent


@pytest.mark.parametrize("a", [0.0, 0.128, 0.5, 0.9])
@pytest.mark.parametrize("shape", ["wave", "helix"])
def test_the_truth_is_the_smooth_curve_through_the_vertices(shape, a):
    """On a planar curve of curvature 10 + 1500 s − 9000 s² 1/m (κ' up to 1500 1/m², κ up to 72 1/m) and on a
    helix of curvature 25 1/m and torsion 8 rad/m, vertices 1.95 mm apart with s = 0 a fraction ``a`` past one:
    the truth's point at every sample, at s = 0 and at the sensed length (between vertices) included, is the
    curve's within 1 nm (0.12 nm measured) and its frame's tangent the curve's within 3 µrad (1.4 µrad measured,
    where the wave bends most; 0.16 µrad at s = 0, bound 0.3), where the chord and the geodesic frame
    (positions_at, frames_at) are off at s = 0 by the derived κ h² a(1 − a)/2 + κ' h³ a(1 − a)(1 − 2a)/6 (to
    1 %) and κ' h² (1/6 − b²/2), b = a or a − 1 from the nearest vertex (to 3 %: the next order in h) — up to
    4.8 µm and 0.95 mrad here. The frames stay rotations (within 1e-14) and keep the geodesic frame's roll
    (d1 · d2_geodesic within 1 µrad)."""
    if shape == "wave":
        curve, tangent = _wave(10.0, 1500.0, -9000.0)
    else:
        r = 25.0 / (25.0**2 + 8.0**2)
        curve, tangent = _helix(r, 2 * np.pi * 8.0 / (25.0**2 + 8.0**2))
    rod = _rod_on(curve, tangent, (5 + a) * H, 0.17)
    truth = rod.to_truth(np.linspace(0.0, 0.17, 18))
    s = truth.s
    assert s[0] == 0.0 and s[-1] == 0.17
    np.testing.assert_allclose(truth.positions, curve(s), rtol=0, atol=1e-9)
    tilt = np.linalg.norm(np.cross(truth.frames[..., 2], tangent(s)), axis=-1)
    assert tilt.max() < 3e-6 and tilt[0] < 3e-7
    np.testing.assert_allclose(np.einsum("...ji,...jk->...ik", truth.frames, truth.frames),
                               np.broadcast_to(np.eye(3), truth.frames.shape), rtol=0, atol=1e-14)
    geodesic = rod.frames_at(s)
    roll = np.einsum("...i,...i->...", truth.frames[..., 0], geodesic[..., 1])
    assert np.abs(roll).max() < 1e-6
    # the sampled pose it replaces, at s = 0
    chord, frame = rod.positions_at(0.0), rod.frames_at(0.0)
    if shape == "wave":
        k0, k1 = 10.0, 1500.0
        want_off = k0 * H**2 * a * (1 - a) / 2 + k1 * H**3 * a * (1 - a) * (1 - 2 * a) / 6
        b = a if a <= 0.5 else a - 1.0  # from the nearest vertex: the geodesic turns at its rate
        want_tilt = k1 * H**2 * (1 / 6 - b**2 / 2)
        assert np.linalg.norm(chord - curve(0.0)) == pytest.approx(want_off, rel=0.01, abs=1e-12)
        assert np.linalg.norm(np.cross(frame[:, 2], tangent(0.0))) == pytest.approx(want_tilt, rel=0.03)


@pytest.mark.parametrize("a", [0.0, 0.128, 0.5])
def test_the_truth_placed_in_its_own_pose_at_the_base_is_the_curve(a):
    """What the coverage check compares a tube with (twin.uncertainty.truth_in_base: the truth in its own pose at
    s = 0, a cubic spline between its samples): on the wave above, the curve in its own pose at s = 0 (its point
    and tangent there, the truth's roll) within 0.05 µm over 170 mm (0.022 µm measured); the chord's point and the
    geodesic frame there, as the truth was sampled before, put it 0.016–0.055 mm off at the tip, over 500 times
    farther."""
    from twin.uncertainty import truth_in_base

    curve, tangent = _wave(10.0, 1500.0, -9000.0)
    rod = _rod_on(curve, tangent, (5 + a) * H, 0.17)
    truth = rod.to_truth(np.linspace(0.0, 0.17, 18))
    s = np.linspace(0.0, 0.17, 171)
    got = truth_in_base(truth.s, truth.positions, truth.frames[0], truth.positions[0], s)
    t0 = tangent(0.0)
    d1 = truth.frames[0][:, 0] - t0 * (truth.frames[0][:, 0] @ t0)
    d1 /= np.linalg.norm(d1)
    exact = (curve(s) - curve(0.0)) @ np.stack([d1, np.cross(t0, d1), t0], axis=-1)
    err = np.linalg.norm(got - exact, axis=-1)
    assert err.max() < 5e-8
    before = truth_in_base(truth.s, np.concatenate([rod.positions_at(truth.s[:1]), truth.positions[1:]]),
                           rod.frames_at(0.0), rod.positions_at(0.0), s)
    assert np.linalg.norm(before - exact, axis=-1).max() > 500 * err.max()
