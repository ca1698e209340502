"""The one compiled pass of Uncertainty.propagate (twin/_propagate.py) against the same propagation assembled step by
step from its parts in numpy (docs/math.md §8.1–8.2), and batch against single frames."""

import numpy as np
import pytest

from twin import Calibration, FiberModel, Reconstructor, shapes, strain
from twin.calibration import nominal_delta_theta, nominal_gain
from twin.uncertainty import ModelError, Uncertainty, _masked_inverse

FIBER = FiberModel.paper()
#: both routes do the same arithmetic in another order: they agree to rounding
RTOL = 1e-12


def batch() -> np.ndarray:
    """Six frames of three library shapes with a missing peak, a lost grating, a peak outside the physical
    window, a frame with no usable grating, and intact ones."""
    names = ["helix", "s-curve", "rotating-bend", "helix", "s-curve", "rotating-bend"]
    w = np.stack([strain.forward(FIBER, shapes.get(n).curvature(FIBER.grating_s)) for n in names])
    w += 2e-3 * np.random.default_rng(3).standard_normal(w.shape)
    w[0, 5, 2] = np.nan  # a missing peak: the grating is solved from three cores
    w[1, 9, :] = np.nan  # a lost grating: interpolated over
    w[2, 3, 1] += 80.0  # far outside the window: counts as missing
    w[3, :, :] = np.nan  # nothing usable
    return w


def stepwise(unc: Uncertainty, shape, w):
    """The propagation from its parts: the inversion's covariance for each frame's present peaks, the model
    error's σ (ModelError.sigma), ∂k/∂p = −P (∂D/∂p) k and the twist's column
    (ModelError.twist_sensitivity), then Uncertainty.position_covariance."""
    rec = unc.reconstructor
    present = ~(np.isnan(w) | rec.peaks_outside(w))
    p, cov = _masked_inverse(unc._design, present, unc._var_e)
    k = np.nan_to_num(shape.curvature)
    me = unc.model_error
    sig = me.sigma(k, FIBER.grating_s, shape.valid, unc.interpolation_order)
    ck = cov[..., 1:, 1:] + (sig**2)[..., None, None] * np.eye(2)
    op = -np.einsum("...nic,pncj->...nipj", p[..., 1:, :], unc._dd)
    sens = np.einsum("...nipj,...nj->...nip", op, k)
    sd = unc._par_sd * me.parameter_scale
    # the twist: one more shared column, per 1σ, that moves the positions and not the measured curvature
    shared = np.concatenate([sens, me.twist_sensitivity(k, FIBER.grating_s)], axis=-1)
    pos_cov = unc.position_covariance(shape, ck, shared, shape.valid, shared_sd=np.append(sd, 1.0))
    ck = ck + np.einsum("...nip,p,...njp->...nij", sens, sd**2, sens)
    return pos_cov, np.where(shape.valid[..., None, None], ck, np.nan)


@pytest.mark.parametrize("interpolation", ["spline", "linear"])
def test_one_pass_equals_the_stepwise_propagation(interpolation):
    """Noise with missing and out-of-window peaks (the table of peak patterns), calibration parameters, every
    model-error term (white, relative, interpolation of the interpolant's order, base angle, twist, a parameter
    scale): the compiled pass equals
    the propagation assembled from its parts to 1e-12 relative; a frame with no usable grating is NaN in both."""
    g = nominal_gain(FIBER)
    cal = Calibration(delta_theta=nominal_delta_theta(FIBER), gain=g, delta_theta_std=2e-3, gain_std=0.01 * g)
    rec = Reconstructor(FIBER, cal, interpolation=interpolation)
    me = ModelError(curvature=0.03, relative=0.02, interpolation=0.134, base_angle=5e-4, parameter_scale=0.7,
                    twist=0.4)
    unc = Uncertainty(rec, model_error=me)
    w = batch()
    shape = rec(w)
    assert not shape.valid[1, 9] and shape.valid[2, 3] and not shape.valid[3].any()
    out = unc.propagate(shape, w)
    pos_cov, ck = stepwise(unc, shape, w)
    assert np.isnan(out.covariance[3]).all() and np.isnan(pos_cov[3]).all()
    ok = [0, 1, 2, 4, 5]
    scale = np.abs(pos_cov[ok]).max()
    np.testing.assert_allclose(out.covariance[ok], pos_cov[ok], rtol=0, atol=RTOL * scale)
    np.testing.assert_array_equal(np.isnan(out.curvature_covariance), np.isnan(ck))
    fin = np.isfinite(ck)
    np.testing.assert_allclose(out.curvature_covariance[fin], ck[fin], rtol=RTOL, atol=RTOL * np.abs(ck[fin]).max())
    # the missing and the out-of-window peaks make their gratings' noise larger than with every peak present
    noise = Uncertainty(rec, model_error=ModelError(), parameters=False)
    masked, all_present = noise.propagate(shape, w).curvature_covariance, noise.propagate(shape).curvature_covariance
    for f, n in ((0, 5), (2, 3)):
        assert np.trace(masked[f, n]) > 1.2 * np.trace(all_present[f, n])


def test_batch_equals_single_frames_and_keeps_the_batch_axes():
    """A (2, 3) batch gives (2, 3, n_points, 3, 3) and each frame what it gives alone (bit for bit up to the
    order of the same operations); without wavelengths every peak of a valid grating counts as present."""
    rec = Reconstructor(FIBER)
    unc = Uncertainty(rec)
    w = batch()
    w[3] = w[0]  # no frame without gratings here
    shape = rec(w.reshape(2, 3, *w.shape[1:]))
    out = unc.propagate(shape, w.reshape(2, 3, *w.shape[1:]))
    assert out.covariance.shape == (2, 3, rec.s.size, 3, 3)
    assert out.curvature_covariance.shape == (2, 3, FIBER.n_gratings, 2, 2)
    for i in range(6):
        one = unc(w[i])
        np.testing.assert_allclose(out.covariance.reshape(6, -1, 3, 3)[i], one.covariance, rtol=1e-13,
                                   atol=1e-13 * np.abs(one.covariance).max())
    # the shape carries the same geometry, and its arrays are read-only
    assert out.positions is shape.positions and not out.covariance.flags.writeable
    intact = unc.propagate(rec(w[4]))
    np.testing.assert_allclose(intact.covariance, unc(w[4]).covariance, rtol=1e-13, atol=1e-20)


def test_mismatched_wavelengths_and_missing_frames_are_clear_errors():
    """The compiled pass reads its arrays unchecked, so their shapes are checked before it: wavelengths of
    another frame count or core count, and a shape reconstructed without its frames, are one-line errors."""
    rec = Reconstructor(FIBER)
    unc = Uncertainty(rec)
    w = batch()[[0, 1]]
    shape = rec(w)
    with pytest.raises(ValueError, match="do not match"):
        unc.propagate(shape, w[:1])
    with pytest.raises(ValueError, match="do not match"):
        unc.propagate(shape, w[..., :3])
    with pytest.raises(ValueError, match="frames=True"):
        unc.propagate(rec(w, frames=False), w)


@pytest.mark.parametrize("order", [2, 4])
def test_intact_pattern_stencils_equal_the_divided_differences(order):
    """The intact pattern's interpolation term as one precomputed weighted sum per grating (_propagate._stencils,
    the compiled pass's path for a frame with every grating valid) equals the divided differences of
    interpolation_kernel (every other pattern's path) to 1e-12 relative, on unevenly spaced gratings and on
    curvature with fine structure (large high differences)."""
    from twin._propagate import _stencils, interpolation_kernel

    rng = np.random.default_rng(5)
    s = np.cumsum(rng.uniform(3e-3, 8e-3, 18))
    k = rng.normal(0.0, 20.0, (40, 18, 2))
    valid = np.ones((40, 18), bool)
    ref = np.empty((40, 18))
    interpolation_kernel(k, valid, s, order, ref)
    start, weights = _stencils(s, order)
    idx = start.astype(int)[:, None] + np.arange(order + 1)
    d = np.einsum("nq,fnqc->fnc", weights, k[:, idx])
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), ref, rtol=1e-12, atol=0)
