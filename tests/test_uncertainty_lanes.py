"""The complete frames of a batch side by side on SIMD lanes (twin/_propagate.py `_lanes_block`) against the same
arithmetic one frame at a time (`_frame`, the path of the frames that lost a grating): every batch size around
the lane count, complete frames mixed with incomplete and empty ones, a NaN position."""

import dataclasses

import numpy as np
import pytest

from twin import Calibration, FiberModel, Reconstructor, shapes, strain
from twin._propagate import LANES, propagate
from twin.calibration import nominal_delta_theta, nominal_gain
from twin.uncertainty import ModelError, Uncertainty

FIBER = FiberModel.paper()
#: the same operations per frame, only laid out across frames: equal to rounding
RTOL = 1e-12


def uncertainty(fiber: FiberModel = FIBER) -> Uncertainty:
    g = nominal_gain(fiber)
    cal = Calibration(delta_theta=nominal_delta_theta(fiber), gain=g, delta_theta_std=2e-3, gain_std=0.01 * g)
    me = ModelError(curvature=0.03, relative=0.02, interpolation=0.134, base_angle=5e-4, twist=0.4)
    return Uncertainty(Reconstructor(fiber, cal), model_error=me)


def wavelengths(n: int, seed: int, fiber: FiberModel = FIBER) -> np.ndarray:
    """``n`` frames of three library shapes scaled at random, with noise."""
    rng = np.random.default_rng(seed)
    names = ["helix", "s-curve", "rotating-bend"]
    k = np.stack([shapes.get(names[i % 3]).curvature(fiber.grating_s) * rng.uniform(0.3, 1.2) for i in range(n)])
    w = strain.forward(fiber, k)
    return w + 2e-3 * rng.standard_normal(w.shape)


def one_at_a_time(unc: Uncertainty, shape, w) -> np.ndarray:
    """Every frame through `_frame` (each frame given its pattern's row, the intact one included)."""
    n_f, n_p = w.shape[0], shape.positions.shape[-2]
    vf = np.ascontiguousarray(shape.valid)
    bases, which = unc._patterns(vf)
    cov, ck = np.empty((n_f, n_p, 3, 3)), np.empty((n_f, unc.reconstructor.fiber.n_gratings, 2, 2))
    propagate(unc._const(), np.ascontiguousarray(shape.positions), np.ascontiguousarray(shape.frames),
              np.ascontiguousarray(shape.curvature), vf, w, bases, which, cov, ck)
    return cov


def check(out: np.ndarray, ref: np.ndarray):
    np.testing.assert_array_equal(np.isnan(out), np.isnan(ref))
    fin = np.isfinite(ref)
    assert fin.any()
    np.testing.assert_allclose(out[fin], ref[fin], rtol=0, atol=RTOL * np.abs(ref[fin]).max())


@pytest.mark.parametrize("n", [1, LANES - 1, LANES, LANES + 1, 35])
def test_complete_frames_on_lanes_equal_one_frame_at_a_time(n):
    """Batches of 1, LANES − 1, LANES, LANES + 1 and 35 complete frames (a missing peak in some: the lanes take any
    peak pattern): the lanes' covariance equals the one-frame route's to 1e-12 of the largest element, lanes left
    empty in the last block included."""
    unc = uncertainty()
    w = wavelengths(n, seed=n)
    w[::4, 5, 2] = np.nan  # a missing peak: the grating still solved, from three cores
    shape = unc.reconstructor(w)
    assert shape.valid.all()
    check(unc.propagate(shape, w).covariance, one_at_a_time(unc, shape, w))


@pytest.mark.parametrize("n_gratings", [17, 3])
def test_an_odd_grating_count_takes_its_last_grating_alone(n_gratings):
    """The lanes take gratings two at a time; with an odd count the last goes alone (`_lanes_block`'s
    ``n_g % 2`` branch): the paper's fibre cut to 17 gratings (and to 3) equals the one-frame route."""
    fiber = FIBER.replace(grating_s=FIBER.grating_s[:n_gratings], lambda0=FIBER.lambda0[:n_gratings],
                          length=float(FIBER.grating_s[n_gratings - 1]) + 0.01)
    unc = uncertainty(fiber)
    w = wavelengths(LANES + 3, seed=n_gratings, fiber=fiber)
    shape = unc.reconstructor(w)
    assert shape.valid.all() and fiber.n_gratings % 2 == 1
    check(unc.propagate(shape, w).covariance, one_at_a_time(unc, shape, w))


def test_mixed_complete_incomplete_and_empty_frames():
    """Complete frames between frames that lost a grating and frames with nothing usable: the complete ones go on
    lanes (their lane order skips the others), the rest the one-frame route; every frame equals the one-frame
    route."""
    unc = uncertainty()
    w = wavelengths(21, seed=7)
    w[[1, 2, 9, 17], 9, :] = np.nan  # a lost grating
    w[[4, 12], :, :] = np.nan  # nothing usable
    shape = unc.reconstructor(w)
    assert (~shape.valid.all(axis=1)).sum() == 6 and not shape.valid[4].any()
    out = unc.propagate(shape, w).covariance
    assert np.isnan(out[[4, 12]]).all() and np.isfinite(out[[0, 1, 3, 20]]).all()
    check(out, one_at_a_time(unc, shape, w))


def test_a_nan_position_stays_in_its_own_lane():
    """A NaN in one frame's positions (as a corrupted input would give) makes that frame's covariance NaN where
    it is read, and leaves its seven neighbours on the same lanes exactly as alone."""
    unc = uncertainty()
    w = wavelengths(LANES, seed=3)
    shape = unc.reconstructor(w)
    pos = np.array(shape.positions)
    pos[2, 40, 1] = np.nan
    out = unc.propagate(dataclasses.replace(shape, positions=pos), w).covariance
    assert np.isnan(out[2]).any()
    others = [i for i in range(LANES) if i != 2]
    check(out[others], unc.propagate(shape, w).covariance[others])


def test_recycled_covariances_are_never_shared_by_live_results():
    """A batch's covariances come from the uncertainty's recycler (:mod:`twin._recycle`), as the reconstructor's
    positions do: a result still alive keeps its memory, one let go gives it back, and values are never shared."""
    from twin import _recycle

    unc = uncertainty()
    shape0 = unc.reconstructor(wavelengths(1, seed=0))
    n = _recycle.MIN_BYTES // (8 * 9 * shape0.positions.shape[-2]) + 1  # frames beyond the recycling threshold
    w = wavelengths(n, seed=5)
    shape = unc.reconstructor(w)
    a = unc.propagate(shape, w)
    b = unc.propagate(shape, w)  # a still alive: fresh memory
    assert not np.shares_memory(a.covariance, b.covariance)
    reference = a.covariance.copy()
    address = a.covariance.__array_interface__["data"][0]
    del a
    c = unc.propagate(shape, w)  # a's memory again, b's untouched
    assert c.covariance.__array_interface__["data"][0] == address
    assert np.array_equal(c.covariance, reference) and np.array_equal(b.covariance, reference)
    assert not c.covariance.flags.writeable
    # a copy with another model error shares the pool and still never hands out live memory
    d = unc.with_twist(0.5).propagate(shape, w)
    assert not np.shares_memory(d.covariance, c.covariance) and not np.shares_memory(d.covariance, b.covariance)
    assert np.array_equal(c.covariance, reference)
