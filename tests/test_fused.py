"""The fused compiled path (twin._fused) against the general path over the mode matrix.

The general path (``fused=False``) is the reconstruction as it was before the fused path existed; the fused path
must give the same positions within 1e-12 m and the same frames within 1e-12 (rotation entries), the same
curvature within 1e-9 1/m and the same validity, for every option it serves: inversion × integrator ×
interpolant × with/without a central core × lost peaks × one frame / a batch, and from wavelengths and from
strain (the live loop's path). The differences are summation order only (BLAS products vs the kernel's loops).
"""

import itertools

import numpy as np
import pytest

from twin import FiberModel, Reconstructor, strain
from twin.curve import INTEGRATORS

PAPER = FiberModel.paper()
# no central core: four outer cores at 90° (least squares estimates the common mode)
NO_CENTRE = FiberModel(core_angles=[0.0, np.pi / 2, np.pi, 3 * np.pi / 2], core_radii=[37.5e-6] * 4,
                       grating_s=PAPER.grating_s, lambda0=PAPER.lambda0)

TOL_POS = 1e-12  # m
TOL_FRAME = 1e-12
TOL_K = 1e-9  # 1/m: the pseudo-inverse amplifies strain rounding by 1/g ≈ 3e4


def wavelengths(fiber, n_frames, seed=0):
    """Smooth 3-D curvature profiles (|k| up to ≈ 50 1/m) with 1 pm noise, (n_frames, n_g, n_c)."""
    rng = np.random.default_rng(seed)
    x = fiber.grating_s / fiber.sensed_length
    amp = rng.uniform(-20, 20, (n_frames, 1, 2, 2))
    freq = rng.uniform(0.2, 1.5, (n_frames, 1, 2, 2))
    phase = rng.uniform(0, 2 * np.pi, (n_frames, 1, 2, 2))
    k = np.sum(amp * np.sin(2 * np.pi * freq * x[:, None, None] + phase), axis=-1)
    w = strain.forward(fiber, k)
    return w + rng.normal(scale=1e-3, size=w.shape)


def lose(w, kind, seed=1):
    """The wavelengths with peaks lost in one of the ways the live loop meets (a copy)."""
    w = w.copy()
    rng = np.random.default_rng(seed)
    n_f = w.shape[0]
    if kind == "one core here and there":  # gratings stay solvable from the cores left
        for f in range(n_f):
            w[f, rng.integers(0, w.shape[1]), rng.integers(0, w.shape[2])] = np.nan
    elif kind == "whole gratings":  # gratings dropped from the interpolation, per-frame patterns
        for f in range(n_f):
            w[f, rng.choice(w.shape[1], size=1 + f % 3, replace=False), :] = np.nan
        w[0, 0, :] = np.nan  # the base grating: the interpolant is held from the next one
        w[-1, -1, :] = np.nan
    elif kind == "outside the window":  # corrupted values, treated as missing
        w[::2, 3, 1] = 1e300
        w[1::3, 7, 0] = -5.0
    elif kind == "a frame with nothing":
        w[n_f // 2] = np.nan
    return w


def compare(a, b):
    assert np.array_equal(a.valid, b.valid)
    assert np.array_equal(np.isnan(a.positions), np.isnan(b.positions))
    ok = ~np.isnan(b.positions)
    assert np.max(np.abs(a.positions - b.positions), where=ok, initial=0.0) <= TOL_POS
    assert np.max(np.abs(a.frames - b.frames), where=~np.isnan(b.frames), initial=0.0) <= TOL_FRAME
    kv = ~np.isnan(b.curvature)
    assert np.array_equal(kv, ~np.isnan(a.curvature))
    assert np.max(np.abs(a.curvature - b.curvature), where=kv, initial=0.0) <= TOL_K
    assert a.positions.shape == b.positions.shape and a.frames.shape == b.frames.shape
    assert a.curvature.shape == b.curvature.shape and a.valid.shape == b.valid.shape


LOSSES = ("none", "one core here and there", "whole gratings", "outside the window", "a frame with nothing")
MODES = [
    (fiber, inversion, integrator, interpolation)
    for fiber, inversion in ((PAPER, "lstsq"), (PAPER, "paper"), (NO_CENTRE, "lstsq"))
    for integrator in INTEGRATORS
    for interpolation in ("spline", "linear", "knn")
]


@pytest.mark.parametrize("fiber, inversion, integrator, interpolation", MODES,
                         ids=[f"{'centre' if f.central_core is not None else 'no-centre'}-{inv}-{i}-{p}"
                              for f, inv, i, p in MODES])
def test_fused_equals_general_over_the_mode_matrix(fiber, inversion, integrator, interpolation):
    opts = dict(inversion=inversion, integrator=integrator, interpolation=interpolation)
    fused, general = Reconstructor(fiber, **opts), Reconstructor(fiber, fused=False, **opts)
    assert fused.fused and not general.fused
    base = wavelengths(fiber, 12)
    for loss in LOSSES:
        w = lose(base, loss)
        a, b = fused(w), general(w)
        compare(a, b)
        if loss == "whole gratings":
            assert not a.valid.all()  # the pattern path ran
        for i in (0, 5):  # one frame: no batch axis
            compare(fused(w[i]), general(w[i]))
        # the live loop's path: the strain once, then the shapes from it
        e, outside = fused.strain(w)
        compare(fused.from_strain(e), b)
        assert np.array_equal(outside, general.peaks_outside(w))


def test_a_frame_with_nothing_is_nan_and_the_others_are_not():
    rec = Reconstructor(PAPER)
    w = lose(wavelengths(PAPER, 6), "a frame with nothing")
    shape = rec(w)
    assert np.isnan(shape.positions[3]).all() and np.isnan(shape.frames[3]).all()
    assert not shape.valid[3].any()
    assert np.isfinite(np.delete(shape.positions, 3, axis=0)).all()


def test_frames_only_when_asked():
    rec, general = Reconstructor(PAPER), Reconstructor(PAPER, fused=False)
    w = lose(wavelengths(PAPER, 8), "whole gratings")
    for r in (rec, general):
        full, lean = r(w), r(w, frames=False)
        assert lean.frames is None and lean[2].frames is None
        assert np.array_equal(full.positions, lean.positions, equal_nan=True)
        with pytest.raises(ValueError, match="frames=True"):
            lean.positions_at([0.05])


def test_batch_axes_are_kept():
    rec = Reconstructor(PAPER)
    w = wavelengths(PAPER, 6).reshape(2, 3, 18, 4)
    shape = rec(w)
    assert shape.positions.shape == (2, 3, rec.s.size, 3) and shape.valid.shape == (2, 3, 18)
    assert shape.frames.shape == (2, 3, rec.s.size, 3, 3) and shape.curvature.shape == (2, 3, 18, 2)
    compare(shape, Reconstructor(PAPER, fused=False)(w))
    # a Fortran-ordered or strided input reads the same
    compare(rec(np.asfortranarray(w)), shape)
    compare(rec(w[:, ::2]), Reconstructor(PAPER, fused=False)(w[:, ::2]))


def test_infinite_wavelength_is_the_same_clear_error():
    w = wavelengths(PAPER, 3)
    w[1, 2, 3] = np.inf
    for fused in (True, False):
        with pytest.raises(ValueError, match="inf"):
            Reconstructor(PAPER, fused=fused)(w)


def test_outputs_are_read_only_and_fresh():
    rec = Reconstructor(PAPER)
    w = wavelengths(PAPER, 2)
    a, b = rec(w), rec(w)
    for name in ("positions", "frames", "curvature", "valid"):
        assert not getattr(a, name).flags.writeable
        assert not np.shares_memory(getattr(a, name), getattr(b, name))


def test_calibration_swap_keeps_the_fused_path_exact():
    from twin.calibration import Calibration

    cal = Calibration(lambda0=PAPER.lambda0 + 0.01, twist=np.linspace(0, 0.2, 18), delta_theta=0.01, gain=2.95e-5)
    w = wavelengths(PAPER, 4)
    a = Reconstructor(PAPER).with_calibration(cal)(w)
    b = Reconstructor(PAPER, fused=False).with_calibration(cal)(w)
    compare(a, b)


@pytest.mark.parametrize("opts", [dict(method="paper"), dict(interpolation="pchip")])
def test_modes_outside_the_fused_path_take_the_general_one(opts):
    assert not Reconstructor(PAPER, **opts).fused
    with pytest.raises(ValueError, match="fused=True"):
        Reconstructor(PAPER, fused=True, **opts)
    assert not Reconstructor(FiberModel.spun()).fused  # the twist of a spun fibre


def test_matrix_covers_every_integrator_and_interpolant():
    assert {m[2] for m in MODES} == set(INTEGRATORS)
    assert set(itertools.chain.from_iterable(m[3:] for m in MODES)) == {"spline", "linear", "knn"}
