"""Parameter identification (docs/math.md §5): recovers known [Δθ, g], the r–S_ε degeneracy, uncertainties."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from twin import Calibration, FiberModel, Reconstructor, shapes, strain
from twin.calibration import scaled_core_angles
from twin.calibration.identify import Observation, identify, paper_cost, parameter_jacobian

NOMINAL = FiberModel.paper()
# The paper's identified fibre (docs/math.md §5.3): Δθ = 1.039 rad, r = 38.0 µm, S_ε = 0.737 → g = 28.006 µm
TRUE = NOMINAL.replace(core_angles=scaled_core_angles(NOMINAL, 1.039), core_radii=[0, 38e-6, 38e-6, 38e-6],
                       strain_sensitivity=0.737)
G_TRUE = 38e-6 * 0.737
S_TRUTH = np.linspace(0, 0.17, 171)


def observations(names, noise=1e-3, with_s=True, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for name in names:
        c = shapes.get(name)
        w = strain.forward(TRUE, c.curvature(NOMINAL.grating_s))
        w = w + rng.normal(scale=noise, size=(20, *w.shape))
        # truth in another frame: registration must not care
        pose = Rotation.random(random_state=rng).as_matrix()
        truth = c.positions(S_TRUTH) @ pose.T + rng.normal(scale=0.05, size=3)
        out.append(Observation(w, truth, S_TRUTH if with_s else None, name) if with_s
                   else Observation(w, truth[::2], None, name))
    return out


SIX = ["arc", "s-curve", "hook", "helix", "mixed", "two-plane"]


@pytest.fixture(scope="module")
def six():
    return observations(SIX)


def test_recovers_delta_theta_and_gain(six):
    """1 pm noise, 20 frames per shape: Δθ within 0.002 rad and g within 0.2 % (docs/math.md §5.3 row D reached
    1e-4 rad and 0.02 %), and the reported 1σ covers the error at 3σ."""
    res = identify(NOMINAL, six)
    assert abs(res.delta_theta - 1.039) < 0.002
    assert abs(res.gain / G_TRUE - 1) < 0.002
    assert abs(res.delta_theta - 1.039) < 3 * res.delta_theta_std
    assert abs(res.gain - G_TRUE) < 3 * res.gain_std
    assert res.nfev < 20 and res.rms_end < res.rms_start / 50
    assert np.all(res.shape_max_error < 0.05e-3)
    cal = res.calibration(Calibration(provenance={"who": "test"}))
    assert cal.delta_theta == res.delta_theta and cal.provenance["who"] == "test"


def test_identified_parameters_cut_the_papers_metric(six):
    before = paper_cost(NOMINAL, six)
    after = paper_cost(NOMINAL, six, identify(NOMINAL, six, jackknife=False).calibration())
    assert before.max() > 1e-3  # a 3.9 % gain error and 8 mrad of Δθ: millimetres (docs/math.md §5.4)
    assert after.max() < 0.05e-3


def test_r_and_strain_sensitivity_columns_coincide(six):
    """The Jacobian columns w.r.t. ln r and ln S_ε are identical (docs/math.md §0 item 2): only g = r·S_ε matters."""
    jac = parameter_jacobian(NOMINAL, six[3:], 1.047, 37.5e-6, 0.777)
    scale = np.linalg.norm(jac[:, 1])
    assert scale > 1e-3
    np.testing.assert_allclose(jac[:, 1], jac[:, 2], atol=1e-7 * scale)  # central differences, rounding only
    assert np.linalg.svd(jac, compute_uv=False)[-1] < 1e-6 * np.linalg.svd(jac, compute_uv=False)[0]


def test_paper_formulation_reports_the_degeneracy():
    obs = observations(["arc", "hook", "helix", "two-plane"])
    res = identify(NOMINAL, obs, formulation="paper")
    assert abs(res.gain / G_TRUE - 1) < 0.005  # g is found; r and S_ε individually are not
    assert "not separately identifiable" in res.degeneracy and "valley" in res.degeneracy
    assert res.singular_values[-1] < 1e-6 * res.singular_values[0]
    assert res.radius * res.strain_sensitivity == pytest.approx(res.gain)


def test_without_arc_lengths_uses_point_to_curve_distances():
    obs = observations(["hook", "helix", "two-plane"], with_s=False)
    res = identify(NOMINAL, obs, jackknife=False)
    assert abs(res.delta_theta - 1.039) < 0.004 and abs(res.gain / G_TRUE - 1) < 0.004


def test_planar_shapes_identify_delta_theta_poorly():
    """From planar shapes Δθ is only weakly identifiable (docs/math.md §5.1): its uncertainty is much larger."""
    planar = identify(NOMINAL, observations(["arc", "s-curve", "hook"]))
    spatial = identify(NOMINAL, observations(["helix", "mixed", "two-plane"]))
    assert planar.delta_theta_std > 3 * spatial.delta_theta_std


def test_bad_observations_are_clear():
    with pytest.raises(ValueError, match="truth must be"):
        Observation(np.zeros((18, 4)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="truth_s must be 3 finite"):
        Observation(np.zeros((18, 4)), np.zeros((3, 3)), np.zeros(4))
    with pytest.raises(ValueError, match="gratings × 4 cores"):
        identify(NOMINAL, [Observation(np.full((10, 4), 1550.0), np.zeros((3, 3)))])
    with pytest.raises(ValueError, match="formulation must be one of"):
        identify(NOMINAL, observations(["arc"]), formulation="max")


@pytest.mark.slow
def test_the_stated_uncertainty_is_the_spread_over_noise_seeds():
    """Monte Carlo over 100 noise seeds where the true σ is known: the lab's six shapes, one frame of 1 pm noise
    each, truths the true fibre's own noise-free reconstructions (no model error), so the identifications' spread
    over seeds is their error. The stated 1σ (the larger of the least-squares value and the delete-one jackknife)
    is that spread within −20 %/+25 % (100 draws pin a standard deviation to ≈ 7 %; measured +7 % for Δθ, −1 % for
    g), and the least-squares value alone is not: it takes the residuals along a curve as independent, which the
    integrated noise is not (12–14 times too small measured). The lab calibration's actual Δθ error of 0.18 mrad
    against 8.4 stated is one lucky set of fixtures, not this (docs/math.md §8.4)."""
    names = ["arc", "s-curve", "hook", "helix", "rotating-bend", "two-plane"]
    s = np.linspace(0, 0.17, 86)
    clean = {n: strain.forward(TRUE, shapes.get(n).curvature(NOMINAL.grating_s)) for n in names}
    rec = Reconstructor(NOMINAL, Calibration(delta_theta=1.039, gain=G_TRUE))
    truth = {n: rec(clean[n]).positions_at(s) for n in names}
    est, stated, lsq = [], [], []
    for seed in range(100):
        rng = np.random.default_rng(seed)
        res = identify(NOMINAL, [Observation(clean[n] + rng.normal(scale=1e-3, size=clean[n].shape), truth[n], s, n)
                                 for n in names])
        est.append([res.delta_theta, res.gain])
        stated.append([res.delta_theta_std, res.gain_std])
        lsq.append(np.sqrt(np.diag(res.covariance)))
    spread = np.std(est, axis=0, ddof=1)
    ratio = np.sqrt(np.mean(np.square(stated), axis=0)) / spread
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    assert np.all(np.sqrt(np.mean(np.square(lsq), axis=0)) < 0.2 * spread)
