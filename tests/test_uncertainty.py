"""The linearised uncertainty (twin/uncertainty.py, docs/math.md §8) against Monte Carlo and closed forms."""

import itertools

import numpy as np
import pytest

from twin import Calibration, FiberModel, Reconstructor, shapes, strain
from twin.calibration import nominal_delta_theta, nominal_gain
from twin.tube import tube_radius
from twin.uncertainty import ModelError, Uncertainty

FIBER = FiberModel.paper()
N_MC = 2000
#: a sample covariance element S_ab of n draws has standard error √((C_aa C_bb + C_ab²)/(n − 1)); 4 of them
#: over the ~30 elements compared keeps a false alarm below 1e-3 while a 10 % error in σ² (0.45 SE per %) fails
N_SE = 4.0
#: points compared: on the first piece from the base (where C ~ s⁴), between gratings and at gratings
POINTS = (3, 7, 15, 40, 85, 130, 170)


def wavelengths(name: str, fiber=FIBER) -> np.ndarray:
    return strain.forward(fiber, shapes.get(name).curvature(fiber.grating_s))


def assert_covariance_matches(sample: np.ndarray, predicted: np.ndarray, n: int) -> None:
    """Every element of the sample covariances (k, 3, 3) within N_SE standard errors of the prediction. The
    standard error has a floor of 1e-3 of the point's trace: on the first 10 mm the variance along the tangent
    starts as s⁶ with s⁷, s⁸ terms of its size, which the first piece's t⁴(a + bt + ct²) follows only roughly —
    a component below 0.3 % of the trace there (the lateral ones, which the tube uses, are exact to s⁶)."""
    d2 = np.maximum(np.einsum("kaa->ka", predicted), 0.0)
    se = np.sqrt((d2[:, :, None] * d2[:, None, :] + predicted**2) / (n - 1))
    se = np.maximum(se, 1e-3 * d2.sum(axis=1)[:, None, None])
    z = np.abs(sample - predicted) / se
    assert z.max() < N_SE, f"largest deviation {z.max():.2f} standard errors"


def sample_covariance(positions: np.ndarray) -> np.ndarray:
    d = positions - positions.mean(axis=0)
    return np.einsum("npa,npb->pab", d, d) / (len(d) - 1)


@pytest.mark.parametrize("name", ["helix", "s-curve"])
def test_linearised_covariance_equals_monte_carlo_of_wavelength_noise(name):
    """(i) 2000 reconstructions under 1 pm Gaussian wavelength noise: their position covariance at seven points
    equals the linearised one within the Monte-Carlo sampling error (N_SE standard errors per element)."""
    rec = Reconstructor(FIBER)
    unc = Uncertainty(rec, wavelength_noise=1e-3, model_error=ModelError(), parameters=False)
    w0 = wavelengths(name)
    w = w0 + 1e-3 * np.random.default_rng(7).standard_normal((N_MC, *w0.shape))
    mc = sample_covariance(rec(w).positions)[list(POINTS)]
    lin = unc(w0).covariance[list(POINTS)]
    assert_covariance_matches(mc, lin, N_MC)


def test_missing_peaks_and_a_lost_grating_match_monte_carlo():
    """The masked inversion (a peak missing at grating 5) and a grating with no peaks (9, interpolated over):
    the same Monte-Carlo check, and the lost grating's own covariance is NaN."""
    rec = Reconstructor(FIBER)
    unc = Uncertainty(rec, wavelength_noise=1e-3, model_error=ModelError(), parameters=False)
    w0 = wavelengths("rotating-bend")
    w0[5, 2] = np.nan
    w0[9, :] = np.nan
    w = w0 + 1e-3 * np.random.default_rng(8).standard_normal((N_MC, *w0.shape))
    mc = sample_covariance(rec(w).positions)[list(POINTS)]
    out = unc(w0)
    assert_covariance_matches(mc, out.covariance[list(POINTS)], N_MC)
    assert np.isnan(out.curvature_covariance[9]).all()
    # one missing peak of four leaves the grating solvable but noisier
    full = unc(wavelengths("rotating-bend")).curvature_covariance
    assert np.trace(out.curvature_covariance[5]) > 1.2 * np.trace(full[5])


def test_parameter_covariance_matches_monte_carlo_of_calibrations():
    """(b) Δθ and g drawn from the calibration's 1σ (noise-free wavelengths): the reconstructions' covariance
    equals the linearised parameter term, at the same sampling tolerance."""
    dth, g = nominal_delta_theta(FIBER), nominal_gain(FIBER)
    cal = Calibration(delta_theta=dth, gain=g, delta_theta_std=4e-3, gain_std=0.01 * g)
    rec = Reconstructor(FIBER, cal)
    unc = Uncertainty(rec, wavelength_noise=0.0, model_error=ModelError())
    w0 = wavelengths("helix")
    rng = np.random.default_rng(9)
    n = 1000  # a reconstructor per draw: fewer draws, the same test in standard errors
    draws = zip(dth + 4e-3 * rng.standard_normal(n), g * (1 + 0.01 * rng.standard_normal(n)), strict=True)
    pos = np.stack([rec.with_calibration(cal.replace(delta_theta=a, gain=b))(w0).positions for a, b in draws])
    assert_covariance_matches(sample_covariance(pos)[list(POINTS)], unc(w0).covariance[list(POINTS)], n)


def test_constant_curvature_arc_gives_the_analytic_tip_covariance():
    """(ii) An arc of κ = 20 1/m in the x–z plane, p(L) = ((1 − cos κL)/κ, 0, sin κL/κ), and a gain known to
    1 %: κ ∝ 1/g, so every grating's κ has variance (κ σ_g/g)², fully correlated, and the tip's covariance is
    (κ σ_g/g)² ∂p/∂κ ∂p/∂κᵀ. Agreement to 1e-5 relative (the 3-point rule on 5 mm with κh = 0.1 errs by
    ~(κh)⁴/180 ≈ 6e-7)."""
    kappa, g = 20.0, nominal_gain(FIBER)
    cal = Calibration(gain=g, gain_std=0.01 * g)
    rec = Reconstructor(FIBER, cal)
    unc = Uncertainty(rec, wavelength_noise=0.0, model_error=ModelError())
    k = np.zeros((FIBER.n_gratings, 2))
    k[:, 0] = kappa
    out = unc(strain.forward(FIBER, k))
    var_k = (kappa * 0.01) ** 2
    np.testing.assert_allclose(out.curvature_covariance[:, 0, 0], var_k, rtol=1e-6)
    big_l = FIBER.sensed_length
    c, s = np.cos(kappa * big_l), np.sin(kappa * big_l)
    dp = np.array([big_l * s / kappa - (1 - c) / kappa**2, 0.0, big_l * c / kappa - s / kappa**2])
    expected = var_k * np.outer(dp, dp)
    np.testing.assert_allclose(out.covariance[-1], expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())


def test_white_model_error_on_a_straight_fiber_with_linear_interpolation():
    """(ii) White curvature error σ per component and grating, linear interpolation, straight fibre: the tip
    moves by ∫(L − s) δk(s) ds, so Var = σ² Σ w_n² with w_n = ∫(L − s) φ_n ds over the hat functions:
    (L − s_n)Δ inside, LΔ/2 − Δ²/6 at the base, Δ²/6 at the tip. Exact up to rounding (the integrand is a
    polynomial of degree 2 on each piece)."""
    rec = Reconstructor(FIBER, interpolation="linear")
    sigma = 0.05
    unc = Uncertainty(rec, wavelength_noise=0.0, model_error=ModelError(curvature=sigma), parameters=False)
    out = unc(FIBER.lambda0)
    s_n, big_l = FIBER.grating_s, FIBER.sensed_length
    delta = s_n[1] - s_n[0]
    w = (big_l - s_n) * delta
    w[0] = big_l * delta / 2 - delta**2 / 6
    w[-1] = delta**2 / 6
    var = sigma**2 * np.sum(w**2)
    np.testing.assert_allclose(np.diag(out.covariance[-1]), [var, var, 0.0], rtol=1e-9, atol=1e-9 * var)
    # and the lateral 1σ radius is that σ (isotropic)
    assert out.sigma[-1] == pytest.approx(np.sqrt(var), rel=1e-9)


def test_zero_noise_gives_zero_radius():
    """(iii) No noise, no model error, no parameter errors: every covariance, σ and tube radius is exactly 0."""
    rec = Reconstructor(FIBER)
    unc = Uncertainty(rec, wavelength_noise=0.0, model_error=ModelError(), parameters=False)
    out = unc(np.stack([wavelengths("helix"), wavelengths("s-curve")]))
    assert out.covariance.shape == (2, rec.s.size, 3, 3)
    assert np.all(out.covariance == 0.0)
    assert np.all(out.sigma == 0.0)
    assert np.all(out.confidence(0.95) == 0.0)


def test_batch_equals_single_frames():
    """One call on a batch gives what single calls give (batch-first, no per-frame state), to rounding: numpy's
    einsum sums in another order for a batch than for one frame, so elements near zero differ by ~1e-12 of the
    largest."""
    unc = Uncertainty(Reconstructor(FIBER), model_error=ModelError(0.02, 0.01))
    w = np.stack([wavelengths(n) for n in ("arc", "helix", "mixed")])
    batch = unc(w)
    for i in range(3):
        one = unc(w[i])
        scale = np.abs(one.covariance).max()
        np.testing.assert_allclose(batch.covariance[i], one.covariance, rtol=1e-10, atol=1e-12 * scale)
        np.testing.assert_allclose(batch[i].confidence(0.9), one.confidence(0.9), rtol=1e-12)


@pytest.mark.parametrize("level", [0.5, 0.95, 0.99])
def test_tube_radius_closed_forms_and_monte_carlo(level):
    """The lateral radius: σ√(−2 ln(1 − level)) for an isotropic error (Rayleigh), the two-sided normal quantile
    for a one-dimensional one, and for an anisotropic one the fraction of 400 000 draws inside it equals the
    level within 4 binomial standard errors. The tangent's component never counts."""
    from scipy.stats import norm

    t = np.array([0.0, 0.0, 1.0])
    iso = np.diag([4e-8, 4e-8, 9.0])  # a huge error along the tangent is ignored
    assert tube_radius(iso, t, level) == pytest.approx(2e-4 * np.sqrt(-2 * np.log(1 - level)), rel=1e-6)
    line = np.diag([0.0, 4e-8, 0.0])
    assert tube_radius(line, t, level) == pytest.approx(2e-4 * norm.ppf(0.5 + level / 2), rel=1e-5)
    rng = np.random.default_rng(3)
    a = rng.standard_normal((3, 3))
    cov = a @ a.T * 1e-8
    tangent = np.array([0.6, 0.0, 0.8])
    r = tube_radius(cov, tangent, level)
    x = rng.multivariate_normal(np.zeros(3), cov, size=400_000)
    lateral = x - np.outer(x @ tangent, tangent)
    inside = np.mean(np.linalg.norm(lateral, axis=1) <= r)
    assert abs(inside - level) < 4 * np.sqrt(level * (1 - level) / len(x))


def test_shape_without_uncertainty_says_so():
    shape = Reconstructor(FIBER)(wavelengths("arc"))
    with pytest.raises(ValueError, match="no uncertainty"):
        shape.confidence(0.95)
    with pytest.raises(ValueError, match=r"\(0, 1\)"):
        Uncertainty(Reconstructor(FIBER))(wavelengths("arc")).confidence(95)


def test_the_paper_pipeline_is_refused():
    with pytest.raises(ValueError, match="material method"):
        Uncertainty(Reconstructor.paper(FIBER))


def perturbed(names, sigma_k: float, n: int, seed: int, fiber=FIBER):
    """``n`` frames of each library shape with a white curvature error σ_k per component and grating (the model
    error's form) and 1 pm wavelength noise, and the exact truth at the reconstruction's arc lengths."""
    rng = np.random.default_rng(seed)
    s = Reconstructor(fiber).s
    w, truth = [], []
    for name in names:
        c = shapes.get(name)
        k = c.curvature(fiber.grating_s) + sigma_k * rng.standard_normal((n, fiber.n_gratings, 2))
        w.append(strain.forward(fiber, k) + 1e-3 * rng.standard_normal((n, fiber.n_gratings, fiber.n_cores)))
        truth.append(np.broadcast_to(c.positions(s), (n, s.size, 3)))
    return np.concatenate(w), np.concatenate(truth)


def test_fit_recovers_an_injected_curvature_error_and_covers_held_out_shapes():
    """The model-error fit finds a white curvature error of 0.2 1/m injected into six shapes (to 10 %: the
    95 % coverage of 600 frames pins the scale to a few per cent; the spline's own error, ≤ 0.05 mm, is 1/16 of
    the resulting σ at the tip), and its tube holds 93–97 % of six other shapes' points."""
    from twin.uncertainty import coverage, fit_model_error

    rec = Reconstructor(FIBER)
    unc = Uncertainty(rec, parameters=False)
    w, truth = perturbed(["arc", "s-curve", "hook", "helix", "rotating-bend", "two-plane"], 0.2, 100, 11)
    me = fit_model_error(unc, rec(w), w, truth)
    assert me.curvature == pytest.approx(0.2, rel=0.1) and me.parameter_scale == 1.0
    w2, truth2 = perturbed(["tightening", "wave", "clothoid", "through-zero", "mixed", "widening-helix"], 0.2, 100, 12)
    assert 0.93 <= coverage(unc.with_model_error(me)(w2), truth2) <= 0.97


def test_fit_lowers_an_overstated_parameter_error():
    """A calibration that states a 3 % gain error it does not have: noise and parameters alone over-cover, so
    the fit leaves the model error at 0 and scales the stated 1σ down until 95 % of the points are inside."""
    from twin.uncertainty import coverage, fit_model_error

    g = nominal_gain(FIBER)
    rec = Reconstructor(FIBER, Calibration(gain=g, gain_std=0.03 * g))
    unc = Uncertainty(rec)
    w, truth = perturbed(["arc", "helix", "s-curve"], 0.0, 100, 13)
    me = fit_model_error(unc, rec(w), w, truth)
    assert me.curvature == 0.0 and 0.0 < me.parameter_scale < 0.5
    assert coverage(unc.with_model_error(me)(w), truth) == pytest.approx(0.95, abs=0.01)


@pytest.mark.parametrize("lost", [None, 9])
def test_interpolation_term_equals_the_linear_interpolants_error_on_a_quadratic_profile(lost):
    """The interpolation term (ModelError.interpolation, docs/math.md §8.1) with c = 1/12 against the actual
    error of the linear interpolant of a quadratic curvature profile (in both components), on every piece
    between valid gratings: each grating's white error carries, in variance, half the angle error ∫(k − k_lin)
    ds of each of its pieces, σ_n² w_n² · 2 = ½ Σ |∫e|², w_n the half-sum of its pieces. Exact for a quadratic
    (the second divided difference is k'' on any spacing; the integral is taken by Simpson's rule on a fine
    grid, exact for the quadratic error), so 1e-9 relative; with grating 9 lost its neighbours' pieces are 20
    mm long and their error 8 times a 10 mm piece's."""
    s_n = FIBER.grating_s
    valid = np.ones(s_n.size, bool)
    if lost is not None:
        valid[lost] = False

    def profile(s):
        return np.stack([40.0 * (s - 0.05) ** 2 + 3.0, -25.0 * (s - 0.12) ** 2], axis=-1)

    k = profile(s_n)
    k[~valid] = np.nan  # what the reconstruction has at a lost grating
    sigma = ModelError(interpolation=1 / 12).interpolation_sigma(k, s_n, valid)
    nodes = np.flatnonzero(valid)
    var_angle = np.zeros(s_n.size)
    for a, b in itertools.pairwise(nodes):
        x = np.linspace(s_n[a], s_n[b], 201)
        lin = k[a] + (x - s_n[a])[:, None] / (s_n[b] - s_n[a]) * (k[b] - k[a])
        e = profile(x) - lin
        wts = np.full(x.size, 2.0)
        wts[1::2], wts[0], wts[-1] = 4.0, 1.0, 1.0
        angle = (x[1] - x[0]) / 3 * wts @ e  # Simpson's rule, exact for the quadratic error
        var_angle[[a, b]] += 0.5 * angle @ angle
    w = np.zeros(s_n.size)
    for a, b in itertools.pairwise(nodes):
        w[[a, b]] += 0.5 * (s_n[b] - s_n[a])
    expected = np.where(valid, np.sqrt(var_angle) / np.where(valid, w, 1.0) / np.sqrt(2.0), 0.0)
    # the end gratings take their neighbour's k'', which for a quadratic is the same k''
    np.testing.assert_allclose(sigma, expected, rtol=1e-9, atol=0.0)
    if lost is not None:
        inner = sigma[lost + 2]
        assert sigma[lost - 1] == pytest.approx(inner * np.sqrt(0.5 * (1 + 64)) / 1.5, rel=1e-9)


def test_interpolation_term_widens_the_tube_over_a_lost_grating():
    """The interpolation term enters the position covariance: with it a lost grating's gap widens the tube
    there (the 2h piece's error is 8 times a piece h's), and at zero curvature variation (an arc) it adds
    nothing but rounding (the inverted curvatures differ by ~1e-13 1/m between gratings: σ < 1e-12 m)."""
    rec = Reconstructor(FIBER)
    me = ModelError(interpolation=0.134)
    unc = Uncertainty(rec, wavelength_noise=0.0, model_error=me, parameters=False)
    arc = unc(strain.forward(FIBER, np.broadcast_to([20.0, 0.0], (FIBER.n_gratings, 2))))
    assert np.all(arc.sigma < 1e-12)
    w = wavelengths("rotating-bend")
    whole = unc(w)
    w_lost = w.copy()
    w_lost[9] = np.nan
    gap = unc(w_lost)
    assert not gap.valid[9]
    i = np.searchsorted(rec.s, FIBER.grating_s[9])
    # 1.42 times here: the gap's two neighbours carry 3.8 times their σ, the gratings before the gap as before
    assert gap.sigma[i] > 1.2 * whole.sigma[i] > 0


def test_twist_term_equals_monte_carlo_of_an_unseen_twist():
    """The twist term (ModelError.twist, docs/math.md §8.1): the fibre does not see the catheter's twist, and a
    constant twist rate τ turns the true curvature by ψ(s) = τ s about the tangent, so the reconstruction of
    the unturned curvature errs by δk = (Rψ − I) k. 2000 draws of τ ~ N(0, (0.05 rad/m)²) — the gratings'
    curvature turned by τ s_n, reconstructed — against the linearised covariance (only this term), within the
    Monte-Carlo sampling error; ψ ≤ 0.04 rad at the tip keeps the second order below 2 % of the first. At the
    gratings and the tip, where the propagation forms C exactly: between them it interpolates C (cubic Hermite),
    which for an error of rank one — its covariance a single direction turning along s — puts ~5 % of the trace
    into a component of 1 % of it at 15 mm, more than the other tests' floor (the lateral radius moves by less
    than that)."""
    rec = Reconstructor(FIBER)
    sd = 0.05
    unc = Uncertainty(rec, wavelength_noise=0.0, model_error=ModelError(twist=sd), parameters=False)
    k = shapes.get("helix").curvature(FIBER.grating_s)
    tau = sd * np.random.default_rng(11).standard_normal(N_MC)
    psi = tau[:, None] * FIBER.grating_s  # (draws, gratings)
    c, s = np.cos(psi), np.sin(psi)
    turned = np.stack([c * k[:, 0] - s * k[:, 1], s * k[:, 0] + c * k[:, 1]], axis=-1)
    at = [10, 20, 50, 100, 130, 170]  # mm: gratings and the tip
    mc = sample_covariance(rec(strain.forward(FIBER, turned)).positions)[at]
    lin = unc(wavelengths("helix")).covariance[at]
    assert_covariance_matches(mc, lin, N_MC)
    # it moves the positions, not the measured curvature (the cores turn with the catheter)
    assert np.allclose(unc(wavelengths("helix")).curvature_covariance, 0.0)


@pytest.mark.parametrize("lost", [None, 9])
def test_fourth_difference_of_the_spline_term_is_exact_on_a_quartic(lost):
    """The spline's interpolation term (order 4) on a quartic curvature profile k(s) = a (s − s0)⁴ + …: 4! times
    the fourth divided difference over five valid gratings is k⁽⁴⁾ = 24 a exactly on any spacing (a lost
    grating included), so σ_n = c |24 a| √(½ Σ H¹⁰) / (w_n √2) with H the valid pieces, 1e-9 relative."""
    s_n = FIBER.grating_s
    valid = np.ones(s_n.size, bool)
    if lost is not None:
        valid[lost] = False
    a = np.array([3.0e4, -1.0e4])
    k = a * (s_n[:, None] - 0.07) ** 4 + 5.0 * s_n[:, None] ** 3 - 2.0 * s_n[:, None] + 1.0
    k[~valid] = np.nan
    sigma = ModelError(interpolation=0.05).interpolation_sigma(k, s_n, valid, order=4)
    nodes = np.flatnonzero(valid)
    h10, w = np.zeros(s_n.size), np.zeros(s_n.size)
    for p, q in itertools.pairwise(nodes):
        h10[[p, q]] += 0.5 * (s_n[q] - s_n[p]) ** 10
        w[[p, q]] += 0.5 * (s_n[q] - s_n[p])
    expected = np.where(valid, 0.05 * 24 * np.hypot(*a) * np.sqrt(h10) / np.where(valid, w, 1.0) / np.sqrt(2), 0)
    np.testing.assert_allclose(sigma, expected, rtol=1e-9, atol=0.0)
    with pytest.raises(ValueError, match="order must be 2 or 4"):
        ModelError(interpolation=0.05).interpolation_sigma(k, s_n, valid, order=3)


def test_the_default_tube_says_when_the_calibration_states_no_parameter_errors():
    """The twin's default model error scales the calibration's stated 1σ of Δθ and g; without them the tube
    holds noise and interpolation only, and says so (the live loop's ``tube_caveat``)."""
    from twin import Frame
    from twin.reference_errors import TubeFigures
    from twin.uncertainty import TWIN_MODEL_ERROR

    bare = Uncertainty(Reconstructor(FIBER, Calibration()))
    assert bare.caveat is not None and "delta_theta" in bare.caveat
    stated = Calibration(delta_theta=nominal_delta_theta(FIBER), gain=nominal_gain(FIBER), delta_theta_std=1e-3,
                         gain_std=1e-2 * nominal_gain(FIBER))
    assert Uncertainty(Reconstructor(FIBER, stated)).caveat is None
    # a model error chosen by the caller is the caller's statement
    assert Uncertainty(Reconstructor(FIBER, Calibration()), model_error=TWIN_MODEL_ERROR).caveat is None
    assert bare.with_model_error(TWIN_MODEL_ERROR).caveat is None
    figures = TubeFigures(bare, per_second=None)
    w = wavelengths("arc")[None]
    figures(Frame(wavelengths=w, timestamp=np.zeros(1), sequence=np.zeros(1, dtype=np.int64)),
            bare.reconstructor(w), None)
    assert figures.as_dict()["tube_caveat"] == bare.caveat


def test_with_twist_sets_only_the_twist_term_and_keeps_the_caveat():
    """Uncertainty.with_twist(τ) is the propagation with TWIN_MODEL_ERROR.replace(twist=τ) (the same covariance
    to rounding), and, the rest of the model error being still the default's, keeps its caveat; τ = 0 is the
    default's tube."""
    from twin.uncertainty import TWIN_MODEL_ERROR

    rec = Reconstructor(FIBER, Calibration())
    bare = Uncertainty(rec)
    w = wavelengths("arc")[None]
    twisted = bare.with_twist(0.82)
    assert twisted.model_error == TWIN_MODEL_ERROR.replace(twist=0.82) and twisted.caveat == bare.caveat
    assert bare.model_error.twist == 0.0  # the original is unchanged
    explicit = Uncertainty(rec, model_error=TWIN_MODEL_ERROR.replace(twist=0.82))
    np.testing.assert_allclose(twisted(w).covariance, explicit(w).covariance, rtol=1e-12, atol=1e-18)
    # the arc bends, so an unmeasured twist widens its tube; none leaves the default's
    assert (twisted(w).sigma[..., 1:] > bare(w).sigma[..., 1:]).all()
    np.testing.assert_array_equal(bare.with_twist(0.0)(w).covariance, bare(w).covariance)
    with pytest.raises(ValueError, match="ModelError.twist"):
        bare.with_twist(-1.0)
