"""The SIMD paths of the fused reconstruction against the scalar chain they stand for.

:func:`twin._kernels.exp_lanes` chains up to LANES curves at once and :func:`twin._kernels.exp_material` one curve
in two passes, both with the exponential's series for steps |φ|² < LANES_T2_MAX; :func:`twin._kernels.exp_curve`
(the general path's chain, exact coefficients at any angle) is the reference. Positions must agree within 1e-13 m
and frames within 1e-13 (the differences are fused multiply-adds); a curve with a longer step must be flagged and,
through the reconstructor, come out as the general path's. :func:`twin.curve.piecewise` must reproduce
:func:`twin.curve.basis`, and the recycled outputs (:mod:`twin._recycle`) must never be shared by live results.
"""

import numpy as np
import pytest
from test_fused import PAPER, compare, lose, wavelengths

from twin import FiberModel, Reconstructor, _recycle, curve, strain
from twin._fused import BLOCK
from twin._kernels import LANES, LANES_T2_MAX, exp_curve, exp_lanes, exp_material

H = 1e-3
N_STEPS = 170


def reference(rates):
    """exp_curve of one curve's rates (2, n, m): positions (n + 1, 3), frames (n + 1, 3, 3)."""
    n = rates.shape[1]
    pos, fr = np.empty((n + 1, 3)), np.empty((n + 1, 3, 3))
    exp_curve(np.ascontiguousarray(rates), False, H, np.eye(3), pos, fr, True)
    return pos, fr


def lane_rates(rng, n_lanes, m, scale):
    """Rates in exp_lanes' layout (n · m, 2L) and per curve (L, 2, n, m)."""
    rt = rng.normal(size=(N_STEPS * m, 2 * n_lanes)) * scale
    per_curve = np.stack([np.stack([rt[:, i], rt[:, n_lanes + i]]).reshape(2, N_STEPS, m) for i in range(n_lanes)])
    return rt, per_curve


@pytest.mark.parametrize("m", [1, 2])
@pytest.mark.parametrize("n_lanes", [1, 3, LANES])
def test_lanes_equal_the_scalar_chain(m, n_lanes):
    rng = np.random.default_rng(n_lanes * 10 + m)
    rt, per_curve = lane_rates(rng, n_lanes, m, scale=30.0)  # |φ| up to ≈ 0.15 rad a step: the series' range
    which = np.arange(n_lanes)[::-1] * 2 + 1  # lanes write to scattered, out-of-order rows
    pos = np.full((2 * n_lanes + 2, N_STEPS + 1, 3), np.nan)
    fr = np.full((2 * n_lanes + 2, N_STEPS + 1, 3, 3), np.nan)
    ok = np.zeros(LANES, bool)
    exp_lanes(rt, H, m, which, pos, fr, True, ok)
    assert ok[:n_lanes].all()
    for i in range(n_lanes):
        p, f = reference(per_curve[i])
        assert np.max(np.abs(pos[which[i]] - p)) <= 1e-13
        assert np.max(np.abs(fr[which[i]] - f)) <= 1e-13
    untouched = np.setdiff1d(np.arange(pos.shape[0]), which)
    assert np.isnan(pos[untouched]).all() and np.isnan(fr[untouched]).all()
    # positions only: the frames argument is not touched
    pos2 = np.empty_like(pos)
    no_frames = np.full((1, 1, 3, 3), 7.0)
    exp_lanes(rt, H, m, which, pos2, no_frames, False, ok)
    assert np.array_equal(pos2[which], pos[which]) and (no_frames == 7.0).all()


def test_a_lane_with_a_long_step_is_flagged_and_the_others_are_not():
    rng = np.random.default_rng(3)
    rt, per_curve = lane_rates(rng, LANES, 2, scale=20.0)
    rt[100, 2] = 500.0  # lane 2's k_x at one sample: |φ| ≈ 0.25 rad > √LANES_T2_MAX
    rt[41, LANES + 5] = np.nan  # lane 5's k_y: a NaN is flagged too
    assert (0.5 * H * 500.0) ** 2 > LANES_T2_MAX
    pos, fr = np.empty((LANES, N_STEPS + 1, 3)), np.empty((LANES, N_STEPS + 1, 3, 3))
    ok = np.zeros(LANES, bool)
    exp_lanes(rt, H, 2, np.arange(LANES), pos, fr, True, ok)
    assert ok.tolist() == [i not in (2, 5) for i in range(LANES)]
    for i in np.flatnonzero(ok):
        assert np.max(np.abs(pos[i] - reference(per_curve[i])[0])) <= 1e-13


@pytest.mark.parametrize("m", [1, 2])
@pytest.mark.parametrize("scale", [30.0, 400.0])  # within the series' range; beyond it (the exact fallback)
def test_two_pass_material_chain_equals_the_scalar_chain(m, scale):
    rates = np.random.default_rng(int(scale)).normal(size=(2, N_STEPS, m)) * scale
    p, f = reference(rates)
    pos, fr = np.empty_like(p), np.empty_like(f)
    exp_material(rates, H, pos, fr, True)
    assert np.max(np.abs(pos - p)) <= 1e-13 and np.max(np.abs(fr - f)) <= 1e-13
    pos2 = np.empty_like(p)
    exp_material(rates, H, pos2, np.empty((1, 3, 3)), False)
    assert np.array_equal(pos2, pos)


def bent(fiber, n_frames, big, seed=0):
    """Wavelengths of smooth bends, the frames in ``big`` bent to |k| ≈ 300 1/m over the middle gratings (steps
    of |φ| ≈ 0.3 rad: beyond the lanes' series), with 1 pm noise."""
    rng = np.random.default_rng(seed)
    x = fiber.grating_s / fiber.sensed_length
    k = np.zeros((n_frames, fiber.n_gratings, 2))
    k[..., 0] = rng.uniform(-30, 30, (n_frames, 1)) * np.sin(2 * np.pi * x)
    k[..., 1] = rng.uniform(-30, 30, (n_frames, 1)) * np.cos(np.pi * x)
    k[big, 6:12, 0] = 300.0
    w = strain.forward(fiber, k)
    return w + rng.normal(scale=1e-3, size=w.shape)


@pytest.mark.parametrize("integrator", ["magnus4", "hem-mid"])
def test_long_steps_mixed_with_short_ones_in_one_block_take_the_exact_chain(integrator):
    fused, general = Reconstructor(PAPER, integrator=integrator), Reconstructor(PAPER, fused=False,
                                                                                integrator=integrator)
    # in the first lane group, twice in the second, and in the last, which is small enough to be chained
    # frame by frame (the two passes' own fallback)
    big = [1, LANES - 2, LANES - 1, 2 * LANES + 1]
    w = bent(PAPER, 2 * LANES + 3, big)
    a = fused(w)
    compare(a, general(w))
    # the steep frames really were beyond the series: the frames turn by > 0.2 rad in one step
    steps = np.einsum("...ij,...ij->...", a.frames[:, :-1], a.frames[:, 1:])  # trace(Rᵀ R⁺) = 1 + 2 cos θ
    theta = np.arccos(np.clip((steps - 1) / 2, -1, 1)).max(axis=1)
    assert (theta[big] > 0.2).all() and (np.delete(theta, big) < 0.2).all()
    for i in (1, 2):  # and one at a time (the two-pass chain's fallback)
        compare(fused(w[i]), general(w[i]))


@pytest.mark.parametrize("n_frames", [1, 2, LANES - 1, LANES + 1, BLOCK + 3, 2 * BLOCK + LANES + 1])
def test_batch_sizes_that_fill_lanes_and_blocks_partly(n_frames):
    fused, general = Reconstructor(PAPER), Reconstructor(PAPER, fused=False)
    w = wavelengths(PAPER, n_frames, seed=n_frames)
    compare(fused(w), general(w))
    lean = fused(w, frames=False)
    assert lean.frames is None and np.max(np.abs(lean.positions - general(w).positions)) <= 1e-12


def test_missing_gratings_and_nan_peaks_between_complete_frames():
    fused, general = Reconstructor(PAPER), Reconstructor(PAPER, fused=False)
    w = wavelengths(PAPER, 3 * LANES + 2, seed=5)
    w[[0, 9, 10, 25], 4, :] = np.nan  # whole gratings: those frames leave the lanes for the pattern path
    w[[3, 17], 2, 1] = np.nan  # one peak: still complete after the solve
    w[12] = np.nan  # nothing at all
    shape = fused(w)
    compare(shape, general(w))
    assert np.isnan(shape.positions[12]).all() and np.isfinite(np.delete(shape.positions, 12, axis=0)).all()


@pytest.mark.parametrize("kind", ["spline", "linear"])
def test_piecewise_polynomials_reproduce_the_basis(kind):
    s_eval = np.linspace(-0.01, PAPER.sensed_length + 0.01, 701)  # outside the gratings too (clamped)
    for nodes in (PAPER.grating_s, PAPER.grating_s[:2], PAPER.grating_s[[0, 5, 6, 17]]):
        segment, t, coef = curve.piecewise(nodes, s_eval, kind)
        powers = t[:, None] ** np.arange(4)
        b = np.einsum("qd,qdn->qn", powers, coef[segment])
        assert np.max(np.abs(b - curve.basis(nodes, s_eval, kind))) <= 1e-13
    assert curve.piecewise(PAPER.grating_s, s_eval, "knn") is None
    assert curve.piecewise(PAPER.grating_s[:1], s_eval, kind) is None


def test_knn_keeps_the_dense_operator_and_still_matches():
    w = wavelengths(PAPER, LANES + 3)
    compare(Reconstructor(PAPER, interpolation="knn")(w), Reconstructor(PAPER, interpolation="knn", fused=False)(w))


def test_recycled_outputs_are_never_shared_by_live_results():
    rec = Reconstructor(PAPER)
    n = _recycle.MIN_BYTES // (8 * 9 * rec.s.size) + 1  # frames beyond the recycling threshold
    w = wavelengths(PAPER, n)
    a = rec(w)
    b = rec(w)  # a still alive: fresh memory
    assert not np.shares_memory(a.frames, b.frames) and not np.shares_memory(a.positions, b.positions)
    reference_positions = a.positions.copy()
    address = a.frames.__array_interface__["data"][0]
    del a
    c = rec(w)  # a's memory again, b's untouched
    assert c.frames.__array_interface__["data"][0] == address
    assert not np.shares_memory(c.frames, b.frames)
    assert np.array_equal(c.positions, reference_positions) and np.array_equal(b.positions, reference_positions)
    assert not c.frames.flags.writeable
    # bounded: however many results are kept alive, the recycler holds at most KEEP buffers
    kept = [rec(w) for _ in range(_recycle.KEEP + 2)]
    assert len(rec._outputs._buffers) <= _recycle.KEEP
    assert len({s.frames.__array_interface__["data"][0] for s in kept}) == len(kept)


def test_the_recycler_holds_at_most_max_held_bytes(monkeypatch):
    cap = 3 * _recycle.MIN_BYTES
    monkeypatch.setattr(_recycle, "MAX_HELD_BYTES", cap)
    pool = _recycle.Recycler()
    n = _recycle.MIN_BYTES // 8 + 1  # just over the threshold: one buffer is a little over MIN_BYTES
    for _ in range(10):
        pool.empty((n,))  # let go at once: free for the next call
        assert sum(b.nbytes for b in pool._buffers) <= cap
    kept = [pool.empty((n,)) for _ in range(4)]  # all in use: none beyond the cap is held
    assert sum(b.nbytes for b in pool._buffers) <= cap
    assert len({a.__array_interface__["data"][0] for a in kept}) == 4
    big = pool.empty((cap // 8 + 1,))  # larger than the cap by itself: handed out, never held
    assert all(b.nbytes <= cap for b in pool._buffers) and big.nbytes > cap


def test_a_view_of_a_result_keeps_its_memory_from_being_reused():
    rec = Reconstructor(PAPER)
    n = _recycle.MIN_BYTES // (8 * 3 * rec.s.size) + 1
    w = wavelengths(PAPER, n)
    tip = rec(w, frames=False).positions[:, -1]  # a view; the Shape itself is gone
    before = tip.copy()
    rec(w[::-1].copy(), frames=False)
    assert np.array_equal(tip, before)


def test_no_centre_fiber_in_lanes():
    fiber = FiberModel(core_angles=[0.0, np.pi / 2, np.pi, 3 * np.pi / 2], core_radii=[37.5e-6] * 4,
                       grating_s=PAPER.grating_s, lambda0=PAPER.lambda0)
    w = lose(wavelengths(fiber, 2 * LANES + 1), "one core here and there")
    compare(Reconstructor(fiber)(w), Reconstructor(fiber, fused=False)(w))
