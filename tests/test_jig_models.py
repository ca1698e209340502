"""The jig's plain linear baseline, the error-model (nuisance) calibration, the one score and the coverage of stated
intervals (docs/jig.md, "Judging a calibration" and "The error model")."""

import json

import numpy as np
import pytest

from sim_interrogator.needle_jig import needle_fiber
from twin import Calibration, strain
from twin.calibration.jig import (
    JigPoses,
    fit,
    jig_curvature,
    leave_one_rotation_out,
    reference_bend,
    validate,
    write_poses,
)
from twin.calibration.jig.nuisance import BUDGET, DEFAULT_TERMS, PRIOR_DOF, TERMS, median_variance
from twin.calibration.jig.score import ALL_LEVELS, CLINICAL, Z95, cells, coverage, difference, score
from twin.cli import main

NEEDLE = needle_fiber()
ROLL = np.deg2rad(17.0)
ORIENTATIONS = np.deg2rad([0.0, 90.0, 180.0, 270.0])
LEVELS = (0.0, 0.25, 0.8, 1.0, 1.25, 3.125)


def as_built():
    """A needle 4° and 3–6 % off nominal, its cores' centroid on the axis and core 0 at 0° (the jig's gauge)."""
    g = NEEDLE.gains[0]
    p0 = 1.03 * g * np.array([1.0, 0.0])
    p1 = 0.94 * g * np.array([np.cos(np.deg2rad(124.0)), np.sin(np.deg2rad(124.0))])
    p = np.array([p0, p1, -p0 - p1])
    return NEEDLE.replace(core_angles=np.arctan2(p[:, 1], p[:, 0]) % (2 * np.pi),
                          core_radii=np.hypot(p[:, 0], p[:, 1]) / NEEDLE.strain_sensitivity)


def session(true, roll_errors=None, references=None, trials=2, seed=0, deficit=0j):
    """Noise-free poses from the forward model. Rotation o is really at ψ_o + roll_errors[o]; its reference pose is
    bent by references[o] (fibre frame, 1/m, every grating); the bent poses carry a random common mode, and are bent
    less than their label by ``deficit`` (jig frame, along + i across, 1/m)."""
    rng = np.random.default_rng(seed)
    n_o = ORIENTATIONS.size
    roll_errors = np.zeros(n_o) if roll_errors is None else np.asarray(roll_errors)
    references = np.zeros((n_o, 2)) if references is None else np.asarray(references)
    o_idx, kappa = (a.ravel() for a in np.meshgrid(np.repeat(np.arange(n_o), trials), LEVELS, indexing="ij"))
    k = jig_curvature(ORIENTATIONS[o_idx] + roll_errors[o_idx], kappa, ROLL)
    short = deficit * np.exp(1j * (ROLL - ORIENTATIONS[o_idx] - roll_errors[o_idx]))
    k = k - np.stack([short.real, short.imag], axis=-1)
    k = np.where((kappa == 0)[:, None], references[o_idx], k)
    d_t = np.where(kappa > 0, rng.normal(0, 2.0, o_idx.size), 0.0)[:, None]
    w = strain.forward(true, np.repeat(k[:, None, :], true.n_gratings, axis=1), delta_T=d_t)
    return JigPoses(ORIENTATIONS[o_idx], kappa, w)


# ------------------------------------------------------------------------------------------------ linear baseline


def test_linear_map_recovers_an_exact_linear_sensor():
    """Noise-free poses of a sensor that is exactly linear: the plain per-grating least-squares map reproduces every
    curvature, of its own poses and of bends it never saw, to 1e-10, and finds the roll."""
    true = as_built()
    result = fit(NEEDLE, session(true), model="linear")
    assert result.model == "linear" and result.chi2_reduced is None
    assert result.roll == pytest.approx(ROLL, abs=1e-10)
    np.testing.assert_allclose(result.gains, np.broadcast_to(true.gains, (4, 3)), rtol=1e-10)
    check = validate(result.calibration, session(true, trials=1, seed=1))
    assert np.abs(check.magnitude_error).max() < 1e-10 and np.abs(check.direction_error).max() < 1e-10
    # bends in directions between the jig's: the map, not the fit, is being checked
    k = jig_curvature(np.deg2rad(np.arange(5.0, 360.0, 30.0)), 1.7, 0.0)
    w = strain.forward(true, np.repeat(k[:, None, :], 4, axis=1))
    e = (w - true.lambda0) / true.lambda0
    from twin.strain import CurvatureSolver

    k_hat = CurvatureSolver(np.array(result.calibration.design)).solve(e).curvature
    np.testing.assert_allclose(k_hat, np.repeat(k[:, None, :], 4, axis=1), atol=1e-10)


def test_linear_map_is_unweighted_and_takes_the_references_as_they_are():
    """The baseline ignores the std columns (same map with or without them) and fits no zero per rotation: a
    reference bent by 0.1 1/m biases it, where the nuisance model, which fits each rotation's zero, stays exact but
    for the strain's second order: (λ − λ_ref)/λ_ref against a bent reference is 1/(1 + ε_ref) ≈ 1 − 3e-5 of the
    first-order strain, which leaves ≤ 1e-5 1/m at 3 1/m."""
    true = as_built()
    plain = session(true)
    weighted = JigPoses(plain.orientation, plain.curvature, plain.wavelengths,
                        std=np.random.default_rng(3).uniform(1e-4, 1e-3, plain.wavelengths.shape))
    a = fit(NEEDLE, plain, model="linear").calibration.design
    b = fit(NEEDLE, weighted, model="linear").calibration.design
    np.testing.assert_allclose(np.array(a), np.array(b), rtol=1e-12, atol=1e-15)
    bent_refs = session(true, references=[[0.1, 0.0], [0.0, -0.1], [-0.05, 0.05], [0.0, 0.1]])
    linear = validate(fit(NEEDLE, bent_refs, model="linear").calibration, session(true, trials=1, seed=2))
    nuisance = validate(fit(NEEDLE, bent_refs, model="nuisance").calibration, session(true, trials=1, seed=2))
    assert np.nanmax(np.abs(linear.magnitude_error)) > 1e-3
    assert np.nanmax(np.abs(nuisance.magnitude_error)) < 1e-5


# ------------------------------------------------------------------------------------------------ nuisance model


def test_nuisance_model_recovers_injected_rolls_and_reference_offsets():
    """A session whose rotations are each off by a roll (mean 0 on each axis: what the two rotations of an axis share
    is a shear of the sensor's map that no jig at 0/90/180/270° can tell apart, docs/jig.md) and whose reference
    poses are bent: the nuisance fit returns the rolls (to 1e-5 rad), the references' curvature along and across
    the bend (to 5e-5 1/m), the jig's roll (to 5e-5 rad) and the calibration to 1e-5 1/m (the second order of a
    strain against a bent reference, see above); the physical model, which has no roll per rotation and whose zero
    the reference rows pin, does not."""
    true = as_built()
    rolls = np.deg2rad([2.0, -1.5, -2.0, 1.5])
    refs = np.array([[0.12, -0.03], [0.02, 0.09], [-0.10, 0.04], [0.05, 0.11]])
    poses = session(true, roll_errors=rolls, references=refs)
    result = fit(NEEDLE, poses, model="nuisance")
    nz = result.nuisance
    assert nz.terms == DEFAULT_TERMS and nz.iterations < 300
    # rotating the sensor by +φ turns the bend by −φ in its frame: z_o = exp(−iφ_o)
    np.testing.assert_allclose(np.angle(nz.gain), -rolls, atol=1e-5)
    np.testing.assert_allclose(np.abs(nz.gain), 1.0, atol=1e-12)
    bend = np.stack([np.cos(ROLL - ORIENTATIONS), np.sin(ROLL - ORIENTATIONS)], axis=-1)
    across = np.stack([-bend[:, 1], bend[:, 0]], axis=-1)
    expected = np.stack([np.sum(refs * bend, axis=1), np.sum(refs * across, axis=1)], axis=-1)
    np.testing.assert_allclose(nz.reference, np.broadcast_to(expected[:, None, :], nz.reference.shape), atol=5e-5)
    assert result.roll == pytest.approx(ROLL, abs=5e-5)
    exact = session(true, trials=1, seed=4)
    assert np.abs(validate(result.calibration, exact).magnitude_error).max() < 1e-5
    physical = validate(fit(NEEDLE, poses, model="physical").calibration, exact)
    assert np.abs(physical.magnitude_error).max() > 1e-3


def test_nuisance_terms_are_checked_and_the_gain_term_finds_a_rotation_gain():
    true = as_built()
    poses = session(true)
    with pytest.raises(ValueError, match="unknown nuisance terms"):
        fit(NEEDLE, poses, model="nuisance", terms={"roll", "stiffness"})
    # a rotation that follows only 95 % of every groove. A jig at 0/90/180/270° bends along two axes, and a gain
    # common to both rotations of an axis is the sensor's own anisotropy: only the ratio within an axis is the jig's
    # (docs/jig.md). With the gain term the 90° rotation reads 0.95 of the 270° one, and 0° and 180° agree.
    scaled = session(true)
    kappa = np.where(np.isclose(scaled.orientation, ORIENTATIONS[1]), 0.95, 1.0) * scaled.curvature
    k = jig_curvature(scaled.orientation, kappa, ROLL)
    w = strain.forward(true, np.repeat(k[:, None, :], 4, axis=1))
    poses = JigPoses(scaled.orientation, scaled.curvature, w)
    nz = fit(NEEDLE, poses, model="nuisance", terms=TERMS).nuisance
    gains = np.abs(nz.gain)
    assert gains[1] / gains[3] == pytest.approx(0.95, abs=1e-6)
    assert gains[0] / gains[2] == pytest.approx(1.0, abs=1e-6)
    assert np.mean(np.log(gains)) == pytest.approx(0.0, abs=1e-12)


def following(true, deficit, seed=0):
    """Noise-free poses of a sensor that follows a fraction 1 + deficit[o, n] of every groove at rotation o and
    grating n (a seating's local gain), references straight."""
    poses = session(true, seed=seed)
    frac = 1.0 + np.asarray(deficit)[poses.orientation_index]  # (P, G)
    k = jig_curvature(poses.orientation, poses.curvature, ROLL)[:, None, :] * frac[..., None]
    return JigPoses(poses.orientation, poses.curvature, strain.forward(true, k))


def test_local_gain_is_measured_about_the_grooves_mean_curvature():
    """Each rotation's zero is free, so it takes a seating's local gain δ at the grooves' mean curvature κ̄ and the
    residuals keep (κ − κ̄)·δ; the map takes the mean δ of the two rotations on an axis. Noise-free poses with a
    known δ per rotation and grating: the fit's local gain is the budget's prior pooled with exactly
    Σ(δ − δ̄_axis)²/(1 + δ̄_axis)² / Σ(1 − 1/2) (to 1e-6 relative); a slope through the origin would read
    Σ(κ − κ̄)²/Σκ² = 0.37 of each δ here. What the slopes explain is not left in the per-groove covariance, and
    κ̄ is the bent grooves' mean."""
    true = as_built()
    deficit = np.array([[0.04, -0.02, 0.03, 0.00], [-0.03, 0.05, -0.01, 0.02],
                        [-0.02, 0.01, 0.02, -0.04], [0.03, -0.04, 0.00, 0.03]])  # (O, G)
    nz = fit(NEEDLE, following(true, deficit), model="nuisance").nuisance
    bent = np.array(LEVELS[1:])
    assert nz.mean_curvature == pytest.approx(bent.mean(), rel=1e-12)
    axis_mean = 0.5 * (deficit + np.roll(deficit, 2, axis=0))  # 0° with 180°, 90° with 270°
    slope = (deficit - axis_mean) / (1.0 + axis_mean)
    dof = deficit.size * 0.5
    expected = np.sqrt((np.sum(slope**2) + PRIOR_DOF * BUDGET["local_gain"] ** 2) / (dof + PRIOR_DOF))
    assert nz.local_gain_std == pytest.approx(expected, rel=1e-6)
    # the through-origin regression would have read this fraction of every slope: the test can tell them apart
    assert np.sum((bent - bent.mean()) ** 2) / np.sum(bent**2) == pytest.approx(0.366, abs=1e-3)
    floor = (1e-5 / 1550.0) ** 2
    assert np.max(np.einsum("gcc->g", nz.strain_cov_seat)) < 10 * floor


def test_median_variance_is_exact_for_few_rotations():
    """The variance of the median of n standard normals: 1, 1/2 (the mean of two), 1 − √3/π for n = 3 (to 1e-9);
    below the asymptotic π/2n for the few rotations of a jig and within 0.5 % of it at n = 101."""
    assert median_variance(1) == pytest.approx(1.0, abs=1e-9)
    assert median_variance(2) == pytest.approx(0.5, abs=1e-9)
    assert median_variance(3) == pytest.approx(1.0 - np.sqrt(3.0) / np.pi, abs=1e-9)
    for n in range(2, 10):
        assert median_variance(n) < np.pi / (2 * n)
        assert median_variance(n + 1) < median_variance(n)
    assert median_variance(101) == pytest.approx(np.pi / 202, rel=0.005)
    with pytest.raises(ValueError, match="at least 1"):
        median_variance(0)


def test_interval_terms_of_a_known_error_model():
    """Exact poses (k̂ = the label) through a calibration whose error model is set by hand, one term at a time:
    σ² = (1 + v_3)·σ_along² for a rotation's zero (v_3 = 1 − √3/π, the median of the 3 fitted zeros), and
    ((κ − κ̄)² + κ²/n)·σ_gain,n² for the seatings' local gain (n = 1 fitted rotation on the held-out axis), to
    1e-9 1/m."""
    from dataclasses import replace

    true = as_built()
    poses = session(true)
    held = np.isclose(poses.orientation, ORIENTATIONS[3])
    cal = fit(true, poses.select(~held), model="nuisance").calibration
    prov = dict(cal.provenance)
    n_g = len(prov["jig_gratings"])
    quiet = {"jig_error_strain_cov": np.zeros((n_g, 3, 3)).tolist(),
             "jig_positions_cov_m2": np.zeros((n_g, 6, 6)).tolist(),
             "jig_reseat_roll_std_rad": 0.0, "jig_reseat_gain_std": 0.0,
             "jig_local_roll_std_rad": 0.0, "jig_local_gain_std": 0.0,
             "jig_reference_std_1_per_m": np.zeros((n_g, 2)).tolist(), "jig_mean_curvature_1_per_m": 1.3}
    exact = session(true, trials=1, seed=5).select(np.isclose(session(true, trials=1, seed=5).orientation,
                                                              ORIENTATIONS[3]))
    kappa = np.abs(exact.curvature[~exact.is_reference])[:, None]
    zero = replace(cal, provenance={**prov, **quiet, "jig_reference_std_1_per_m": np.tile([0.1, 0.3], (n_g, 1))
                                    .tolist()})
    sigma = validate(zero, exact).magnitude_sigma
    np.testing.assert_allclose(sigma, np.full(sigma.shape, 0.1 * np.sqrt(2.0 - np.sqrt(3.0) / np.pi)), atol=1e-9)
    gain = replace(cal, provenance={**prov, **quiet, "jig_local_gain_std": 0.05})
    sigma = validate(gain, exact).magnitude_sigma
    np.testing.assert_allclose(sigma, np.broadcast_to(0.05 * np.sqrt((kappa - 1.3) ** 2 + kappa**2), sigma.shape),
                               atol=1e-9)


def test_nuisance_calibration_saves_its_error_model(tmp_path):
    true = as_built()
    cal = fit(NEEDLE, session(true), model="nuisance").calibration
    cal.save(tmp_path / "c.toml")
    prov = Calibration.load(tmp_path / "c.toml").provenance
    for key in ("jig_error_strain_cov", "jig_reference_bias_1_per_m", "jig_reference_std_1_per_m",
                "jig_reseat_roll_std_rad", "jig_reseat_gain_std", "jig_positions_cov_m2"):
        assert key in prov
    assert np.array(prov["jig_error_strain_cov"]).shape == (4, 3, 3)
    assert np.array(prov["jig_positions_cov_m2"]).shape == (4, 6, 6)


# ------------------------------------------------------------------------------------------------ the jig's zero


def jig_bent_references(along: float, across: float) -> np.ndarray:
    """Each rotation's reference pose bent by the same curvature in the jig's frame (a flat groove that is not
    flat): in the sensor's frame it turns with the rotation, along (cos, sin)(α − ψ_o) and across it."""
    return (along + 1j * across) * np.exp(1j * (ROLL - ORIENTATIONS))


def test_jig_zero_is_the_flat_grooves_curvature_and_makes_a_new_session_exact():
    """Every session's flat groove bends the sensor by 0.14 1/m along the grooves' bend and 0.10 across. The nuisance
    fit carries it as its jig zero (to 1e-4 1/m: the second order of strain against a bent reference); a new session
    zeroed in the same jig, its curvature with the zero added, is exact to 1e-4 1/m and 1e-4 rad, with the
    calibration's roll or one fitted; without the zero it reads the change from the bent reference, 0.14 1/m short
    along the bend (|κ − 0.14 − 0.10i| − κ at each level)."""
    true = as_built()
    z = jig_bent_references(0.14, 0.10)
    refs = np.stack([z.real, z.imag], axis=-1)
    result = fit(NEEDLE, session(true, references=refs), model="nuisance")
    prov = result.calibration.provenance
    np.testing.assert_allclose(prov["jig_zero_1_per_m"], np.tile([0.14, 0.10], (4, 1)), atol=1e-4)
    np.testing.assert_allclose(prov["jig_rotation_zeros_1_per_m"], np.tile([0.14, 0.10], (4, 4, 1)), atol=1e-4)
    new = session(true, references=refs, trials=1, seed=5)
    for fit_roll in (False, True):
        check = validate(result.calibration, new, fit_roll=fit_roll, jig_zero=True)
        assert check.roll == pytest.approx(ROLL, abs=1e-4)
        np.testing.assert_allclose(check.jig_zero, np.tile([0.14, 0.10], (4, 1)), atol=1e-4)
        assert np.nanmax(np.abs(check.magnitude_error)) < 1e-4
        assert np.nanmax(np.abs(check.direction_error)) < 1e-4
    raw = validate(result.calibration, new)
    assert raw.jig_zero is None
    kappa = np.abs(raw.curvature)[:, None]
    np.testing.assert_allclose(raw.magnitude_error, np.abs(kappa - 0.14 - 0.10j) - kappa + 0 * raw.magnitude_error,
                               atol=1e-4)


def test_jig_zero_is_one_rule_for_every_model():
    """The zero of each rotation is read through the calibration itself (the mean over its bent poses of label − k̂,
    along and across the bend) and the jig zero is their median, for every model. An exact sensor with straight
    references: every model's zero is 0 (1e-9). With bent ones, the plain linear map, which takes the references as
    the zero, has absorbed part of the bend into its gain and reads a smaller zero than the nuisance model."""
    true = as_built()
    for model in ("linear", "physical", "matrix", "nuisance"):
        prov = fit(NEEDLE, session(true), model=model).calibration.provenance
        assert np.abs(prov["jig_zero_1_per_m"]).max() < 1e-9
    z = jig_bent_references(0.14, 0.0)
    bent = session(true, references=np.stack([z.real, z.imag], axis=-1))
    linear = np.array(fit(NEEDLE, bent, model="linear").calibration.provenance["jig_zero_1_per_m"])
    nuisance = np.array(fit(NEEDLE, bent, model="nuisance").calibration.provenance["jig_zero_1_per_m"])
    assert np.all(np.abs(linear[:, 0]) < 0.1) and np.all(np.abs(nuisance[:, 0] - 0.14) < 1e-4)


def test_reference_bend_tells_a_bent_reference_from_grooves_that_bend_less():
    """A flat groove that bends the sensor by 0.14 1/m along the grooves' bend and 0.10 across, and bent grooves that
    hold it 0.14 and 0.10 less bent than their labels, give the same zero (label − k̂) at every rotation, so every
    figure taken against each rotation's own reference is the same (1e-4 1/m: the second order of strain). The
    references' absolute wavelengths tell them apart: reference_bend finds (0.14, 0.10) for the first and 0 for the
    second (1e-4), whatever all references share in the sensor's frame (here 0.05 1/m), with nothing left over."""
    true = as_built()
    z = jig_bent_references(0.14, 0.10) + 0.05
    bent_reference = session(true, references=np.stack([z.real, z.imag], axis=-1))
    shallow = session(true, references=np.tile([0.05, 0.0], (4, 1)), deficit=0.14 + 0.10j)
    found = []
    for poses in (bent_reference, shallow):
        cal = fit(NEEDLE, poses, model="nuisance").calibration
        np.testing.assert_allclose(cal.provenance["jig_zero_1_per_m"], np.tile([0.14, 0.10], (4, 1)), atol=1e-4)
        bend, scatter = reference_bend(cal, poses)
        assert bend.shape == (4, 2) and np.all(scatter < 1e-4)
        found.append(bend)
    np.testing.assert_allclose(found[0], np.tile([0.14, 0.10], (4, 1)), atol=1e-4)
    np.testing.assert_allclose(found[1], 0.0, atol=1e-4)
    with pytest.raises(ValueError, match="3 or more rotations"):
        reference_bend(cal, shallow.select(np.isin(shallow.orientation, ORIENTATIONS[:2])))


def test_a_disturbed_reference_is_reported():
    """Three trials per groove with 1 pm noise and a common shift per bent pose (the session's 2 K); one reference
    trial's peak 100 pm off: its rotation and grating stand out of the table's trial scatter (> 10 times; the common
    shift, no bend, is not counted) and the fit says so; nothing else does."""
    true = as_built()
    poses = session(true, trials=3)
    rng = np.random.default_rng(11)
    w = poses.wavelengths + 1e-3 * rng.standard_normal(poses.wavelengths.shape)
    clean = JigPoses(poses.orientation, poses.curvature, w)
    ratio = clean.reference_scatter()
    assert ratio.shape == (4, 4) and np.nanmax(ratio) < 10
    assert not any("reference trials" in x for x in fit(NEEDLE, clean, model="nuisance").warnings)
    row = np.flatnonzero(clean.is_reference & np.isclose(clean.orientation, ORIENTATIONS[2]))[1]
    w[row, 1, 2] += 0.1
    disturbed = JigPoses(poses.orientation, poses.curvature, w)
    ratio = disturbed.reference_scatter()
    assert ratio[2, 1] > 10 and np.sum(ratio > 10) == 1
    warnings = fit(NEEDLE, disturbed, model="nuisance").warnings
    assert any(x.startswith("orientation 180°: the reference trials disagree at grating 1 ") for x in warnings)


# ------------------------------------------------------------------------------------------------ score, coverage


def test_score_is_two_medians_over_the_cells_in_the_bands():
    """Hand-made table: 2 rotations × 1 grating × 3 levels (0.5, 1.0, 2.0 1/m); the clinical band holds 0.5 and 1.0
    for the magnitude and 1.0 for the direction; 'all levels' every level, direction from 0.8 on."""
    orientation = np.repeat([0.0, 1.0], 6)
    curvature = np.tile([0.5, 0.5, 1.0, 1.0, 2.0, 2.0], 2)
    mag = np.array([0.1, -0.1, 0.2, 0.2, 0.4, -0.4, 0.3, 0.3, 0.0, 0.0, 0.1, 0.1])[:, None]
    ang = np.deg2rad(np.array([10, 10, 1, 3, 5, 5, 20, 20, -4, -2, 7, 7.0]))[:, None]
    _, levels, rms, mean = cells(orientation, curvature, mag, ang)
    np.testing.assert_allclose(levels, [0.5, 1.0, 2.0])
    np.testing.assert_allclose(rms[:, 0], [[0.1, 0.2, 0.4], [0.3, 0.0, 0.1]])
    np.testing.assert_allclose(np.rad2deg(mean[:, 0]), [[10, 2, 5], [20, -3, 7]])
    clinical = score(levels, rms, mean, CLINICAL)
    assert clinical.magnitude_error == pytest.approx(np.median([0.1, 0.2, 0.3, 0.0]))
    assert np.rad2deg(clinical.direction_error) == pytest.approx(np.median([2.0, 3.0]))
    everything = score(levels, rms, mean, ALL_LEVELS)
    assert everything.magnitude_error == pytest.approx(np.median([0.1, 0.2, 0.4, 0.3, 0.0, 0.1]))
    assert np.rad2deg(everything.direction_error) == pytest.approx(np.median([2, 5, 3, 7.0]))
    empty = score(np.array([2.0, 3.0]), rms[:, :, 1:], mean[:, :, 1:], CLINICAL)
    assert empty.magnitude_error is None and empty.direction_error is None and empty.n_magnitude == 0


def test_score_difference_and_its_range_over_clusters():
    """Two calibrations on 2 rotations × 1 grating × 3 levels (0.5, 1, 2 1/m), all levels. a is 0.05 1/m better in
    every cell: the difference is −0.05 whichever rotation is left out. In direction they differ in one cell only
    (7° against 9° at rotation 1, 2 1/m): the medians over the four direction cells tie (4° each), with rotation 0
    left out a is 1° better (5° against 6°), with rotation 1 left out they tie: range (−1°, 0°)."""
    levels = np.array([0.5, 1.0, 2.0])
    a_rms = np.array([[[0.1, 0.2, 0.4]], [[0.3, 0.0, 0.1]]])
    a_mean = np.deg2rad(np.array([[[10.0, 2.0, 5.0]], [[20.0, -3.0, 7.0]]]))
    b_mean = np.deg2rad(np.array([[[10.0, 2.0, 5.0]], [[20.0, -3.0, 9.0]]]))
    d = difference(levels, a_rms, a_mean, a_rms + 0.05, b_mean, ALL_LEVELS)
    assert d.magnitude == pytest.approx(-0.05) and d.magnitude_range == pytest.approx((-0.05, -0.05))
    assert np.rad2deg(d.direction) == pytest.approx(0.0, abs=1e-12)
    assert np.rad2deg(d.direction_range) == pytest.approx([-1.0, 0.0])
    assert d.n_clusters == 2 and d.to_dict()["direction_range_deg"] == pytest.approx([-1.0, 0.0])
    none = difference(np.array([2.0, 3.0]), a_rms[:, :, 1:], a_mean[:, :, 1:], a_rms[:, :, 1:], b_mean[:, :, 1:],
                      CLINICAL)
    assert none.magnitude is None and none.direction is None and none.magnitude_range is None
    # a cell one calibration did not score is left out of both: b's missing 0.4 must not leave a's 0.4 in its
    # median (a's median alone would be 0.15, b's over the other five 0.25 + 0.05: a difference of −0.15)
    b_rms = a_rms + 0.05
    b_rms[0, 0, 2] = np.nan
    d = difference(levels, a_rms, a_mean, b_rms, b_mean, ALL_LEVELS)
    assert d.magnitude == pytest.approx(-0.05)


def test_coverage_of_known_gaussian_errors():
    """Errors drawn N(0, σ²) with σ stated right: 95 % ± 3 binomial σ (n = 40 000); stated at half their size: the
    fraction inside ±1.96·σ/2, 67.3 %; NaNs and non-positive σ are not judged."""
    rng = np.random.default_rng(7)
    n = 40_000
    sigma = rng.uniform(0.01, 0.3, n)
    err = sigma * rng.standard_normal(n)
    tol = 3 * np.sqrt(0.95 * 0.05 / n)
    c, judged = coverage(err, sigma)
    assert judged == n and abs(c - 0.95) < tol
    half, _ = coverage(err, sigma / 2)
    p_half = 0.6729  # P(|z| < Z95 / 2)
    assert abs(half - p_half) < 3 * np.sqrt(p_half * (1 - p_half) / n)
    err[:10], sigma[10:20] = np.nan, 0.0
    assert coverage(err, sigma)[1] == n - 20
    assert coverage([np.nan], [1.0]) == (None, 0)
    assert Z95 == pytest.approx(1.959964, abs=1e-6)


def test_validation_states_intervals_only_with_an_error_model():
    true = as_built()
    poses = session(true, roll_errors=np.deg2rad([1.0, -1.0, 0.5, -0.5]), references=0.05 * np.eye(4, 2))
    phys = leave_one_rotation_out(NEEDLE, poses, model="physical")
    nz = leave_one_rotation_out(NEEDLE, poses, model="nuisance")
    assert phys.coverage_95 is None and phys.n_coverage == 0
    assert nz.n_coverage > 0
    # the session holds only what the nuisance model describes (rolls, reference offsets): its 95 % intervals
    # must not under-cover beyond sampling (3 binomial σ); they may over-cover (the error budget's prior
    # dominates the variances of 4 rotations: 160 of 160 covered here)
    assert nz.coverage_95 >= 0.95 - 3 * np.sqrt(0.95 * 0.05 / nz.n_coverage)
    d = nz.to_dict()
    assert d["score"]["bands"] == "clinical" and d["score_all_levels"]["bands"] == "all levels"


# ------------------------------------------------------------------------------------------------ CLI


def test_cli_linear_and_nuisance_models(tmp_path, capsys):
    true = as_built()
    poses = session(true, roll_errors=np.deg2rad([1.0, -1.0, 0.5, -0.5]), references=0.05 * np.eye(4, 2))
    csv_path = tmp_path / "poses.csv"
    write_poses(csv_path, poses)
    fiber_args = ["--fiber", str(tmp_path / "n.toml")]
    NEEDLE.save(tmp_path / "n.toml")
    for model in ("linear", "nuisance"):
        out = tmp_path / f"{model}.toml"
        assert main(["jig-calibrate", str(csv_path), *fiber_args, "--model", model, "--out", str(out)]) == 0
        assert f"({model} model)" in capsys.readouterr().out
        assert Calibration.load(out).provenance["jig_model"] == model
    assert main(["jig-validate", str(csv_path), "--calibration", str(tmp_path / "nuisance.toml"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)["results"][0]["validation"]["summary"]
    assert summary["n_coverage"] > 0 and summary["coverage_95"] is not None
    assert set(summary["score"]) >= {"magnitude_error_1_per_m", "direction_error_deg", "bands"}
    assert main(["jig-validate", str(csv_path), "--calibration", str(tmp_path / "linear.toml"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["results"][0]["validation"]["summary"]["coverage_95"] is None
    assert main(["jig-validate", str(csv_path), *fiber_args, "--leave-one-rotation-out"]) == 0
    out = capsys.readouterr().out
    assert "Score, leave one rotation out" in out
    for model in ("physical", "matrix", "linear", "nuisance"):
        assert f"{model:>9s}  clinical:" in out


def test_a_pose_bent_the_other_way_gives_the_same_zero():
    """(κ, ψ) and (−κ, ψ + π) are one bend; the zero is read in the frame of ψ, so it changes sign with the frame
    and nothing else. Exact strain of a known zero through a 3-core design, solved exactly (to 1e-12 1/m)."""
    from twin.calibration.jig.fits import rotation_zeros

    rng = np.random.default_rng(3)
    g, c = 2, 3
    design = rng.normal(size=(g, c, 3))
    psi = np.array([0.0, 0.0, np.pi / 2, np.pi / 2])
    kappa = np.array([2.0, 4.0, 1.0, 3.0])
    zero = 0.3 - 0.2j  # along + i across, in each pose's bend frame
    group = np.array([0, 0, 1, 1])

    def strain(kap, ps):
        k_hat = (kap - zero) * np.exp(1j * (ROLL - ps))  # the change from the bent reference, fibre frame
        x = np.stack([np.zeros((4, g)), np.broadcast_to(k_hat.real[:, None], (4, g)),
                      np.broadcast_to(k_hat.imag[:, None], (4, g))], axis=-1)  # (c, k_x, k_y)
        return np.einsum("gck,pgk->pgc", design, x)

    plain = rotation_zeros(design, ROLL, strain(kappa, psi), psi, kappa, group, 2)
    np.testing.assert_allclose(plain, np.broadcast_to([0.3, -0.2], (2, g, 2)), atol=1e-12)
    flipped = rotation_zeros(design, ROLL, strain(kappa, psi), psi + np.pi, -kappa, group, 2)
    np.testing.assert_allclose(flipped, -plain, atol=1e-12)
