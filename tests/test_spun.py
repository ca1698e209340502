"""Spun (helical) multi-core fibres: the model, the exact and linear strains, the twist inversion, the
reconstruction with the material frame carried by the measured twist, and the spin-rate calibration
(docs/spun-fibers.md)."""

import numpy as np
import pytest
from scipy.linalg import expm

from twin import Calibration, FiberModel, Reconstructor, spun, strain
from twin.calibration import two_step

SPUN = FiberModel.spun(50.0)


def linear_wavelengths(fiber, k, tau, axial=0.0, lam0=None):
    e = fiber.strain_sensitivity * spun.linear_strain(fiber, k, tau, axial)
    return (fiber.lambda0 if lam0 is None else lam0) * (1.0 + e)


def exact_wavelengths(fiber, k, tau, axial=0.0, lam0=None):
    e = fiber.strain_sensitivity * spun.exact_strain(fiber, k, tau, axial)
    return (fiber.lambda0 if lam0 is None else lam0) * (1.0 + e)


def exact_helix(u, s):
    """Centreline and material frames of a rod with constant Darboux vector (κ1, κ2, τ): exp on SE(3)."""
    k1, k2, t = u
    a = np.zeros((4, 4))
    a[:3, :3] = [[0, -t, k2], [t, 0, -k1], [-k2, k1, 0]]
    a[2, 3] = 1.0
    g = np.array([expm(a * si) for si in s])
    return g[:, :3, 3], g[:, :3, :3]


# ------------------------------------------------------------------------------------------- the model
def test_straight_fiber_is_unchanged():
    f = FiberModel.paper()
    assert f.spin_rate == 0.0 and f.spin_omega == 0.0
    np.testing.assert_array_equal(f.helix_cos2, 1.0)
    assert "spin_rate" not in f.to_dict()  # today's files round-trip byte for byte


def test_core_phase_advances_with_spin_and_handedness():
    s = np.array([0.0, 0.005, 0.02])
    np.testing.assert_allclose(SPUN.core_phase(s), SPUN.ccw_angles + 2 * np.pi * 50 * s[:, None])
    cw = SPUN.replace(handedness=-1)
    np.testing.assert_allclose(cw.core_phase(s), -(SPUN.core_phase(s)))


def test_spin_rate_toml_round_trip(tmp_path):
    path = tmp_path / "spun.toml"
    SPUN.save(path)
    back = FiberModel.load(path)
    assert back.spin_rate == 50.0
    np.testing.assert_array_equal(back.core_angles, SPUN.core_angles)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('"50"', "spin_rate: expected a number"),
        ("true", "spin_rate: expected a number"),
        ("nan", "spin_rate: expected turns/m with |spin_rate| <= 1000"),
        ("-5e4", "spin_rate: expected turns/m with |spin_rate| <= 1000"),
        ("[50]", "spin_rate: expected a number"),
    ],
)
def test_bad_spin_rate_in_toml_is_one_line_naming_file_and_field(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    SPUN.replace(spin_rate=0.0).save(path)
    path.write_text(path.read_text() + f"spin_rate = {text}\n")
    with pytest.raises(ValueError) as err:
        FiberModel.load(path)
    line = str(err.value)
    assert "\n" not in line and line.startswith(str(path)) and message in line


def test_left_handed_spin_is_accepted():
    assert FiberModel.spun(-50.0).spin_omega == pytest.approx(-2 * np.pi * 50)


# ------------------------------------------------------------------------------------------- forward models
def test_twist_term_magnitude_quoted_in_the_issue():
    """r = 35 µm, 50 turns/m: cos²α r² Ω = 0.385 µε per rad/m, ≈ 0.46 pm per rad/m at 1550 nm with S_ε = 0.777."""
    per_rad = spun.twist_sensitivity(SPUN)[SPUN.bending_cores]
    np.testing.assert_allclose(per_rad, 0.385e-6, rtol=1e-3)
    assert spun.twist_sensitivity(SPUN)[SPUN.central_core] == 0.0
    assert 1550 * SPUN.strain_sensitivity * per_rad[0] * 1e3 == pytest.approx(0.465, abs=0.005)  # pm


@pytest.mark.parametrize("tau", [1.0, 10.0, -10.0, 30.0])
def test_exact_against_linear_twist_term(tau):
    """Pure twist, no bend: the exact strain is √(1 + cos²α r²(2Ωτ + τ²)) − 1, so the linear form is low by
    τ/(2Ω) − cos²α r²Ωτ/2 relative (1.59 % at 10 rad/m, 50 turns/m)."""
    k = np.zeros((SPUN.n_gratings, 2))
    t = np.full(SPUN.n_gratings, tau)
    ex = spun.exact_strain(SPUN, k, t)[:, 1:]
    li = spun.linear_strain(SPUN, k, t)[:, 1:]
    r, om, c2 = 35e-6, SPUN.spin_omega, SPUN.helix_cos2[1]
    np.testing.assert_allclose(ex, np.sqrt(1 + c2 * r * r * (2 * om * tau + tau * tau)) - 1, rtol=1e-9)
    rel = (ex - li) / li
    np.testing.assert_allclose(rel, tau / (2 * om) - c2 * r * r * om * tau / 2, rtol=2e-3, atol=1e-8)
    if tau == 10.0:
        assert rel[0, 0] == pytest.approx(0.0159, abs=1e-4)


def test_exact_equals_linear_in_bending_to_second_order():
    """Bending alone: the exact strain differs from −cos²α r k·u by cos²α sin²α (r k·u)²/2 (no first-order
    error), and a straight fibre's exact strain is exactly linear."""
    rng = np.random.default_rng(1)
    k = rng.normal(scale=30.0, size=(SPUN.n_gratings, 2))
    t = np.zeros(SPUN.n_gratings)
    a = SPUN.core_radii * (k[:, :1] * np.cos(SPUN.core_phase(SPUN.grating_s)) +
                           k[:, 1:] * np.sin(SPUN.core_phase(SPUN.grating_s)))
    c2 = SPUN.helix_cos2
    diff = spun.exact_strain(SPUN, k, t) - spun.linear_strain(SPUN, k, t)
    # the next term is smaller by O(r k·u) ≤ 5e-3 here
    assert np.abs(a).max() < 5e-3
    np.testing.assert_allclose(diff, c2 * (1 - c2) * a * a / 2, rtol=1e-2, atol=1e-16)
    straight = SPUN.replace(spin_rate=0.0)
    np.testing.assert_allclose(spun.exact_strain(straight, k, t), spun.linear_strain(straight, k, t), atol=1e-15)


def test_axial_strain_reads_as_twist_minus_omega_eps():
    """Stretching the helix lowers its turns per stretched length: the exact model's outer cores see cos²α ε_0,
    which the linear inversion reads as a twist of −Ω ε_0 (0.031 rad/m at 100 µε, 50 turns/m)."""
    eps0 = 1e-4
    k = np.zeros((SPUN.n_gratings, 2))
    e = SPUN.strain_sensitivity * spun.exact_strain(SPUN, k, np.zeros(SPUN.n_gratings), eps0)
    sol = spun.TwistSolver(spun.twist_design(SPUN)).solve(e)
    np.testing.assert_allclose(sol.twist_rate, -SPUN.spin_omega * eps0, rtol=2e-3)


def test_design_matrix_carries_spin_and_linear_strain_matches_forward():
    rng = np.random.default_rng(2)
    k = rng.normal(scale=20.0, size=(SPUN.n_gratings, 2))
    w = strain.forward(SPUN, k, axial_strain=2e-4)
    np.testing.assert_allclose(w, linear_wavelengths(SPUN, k, np.zeros(SPUN.n_gratings), 2e-4), rtol=1e-14)


# ------------------------------------------------------------------------------------------- the inversion
def test_twist_solver_is_exact_on_the_linear_model_and_survives_missing_peaks():
    rng = np.random.default_rng(3)
    k = rng.normal(scale=20.0, size=(5, SPUN.n_gratings, 2))
    tau = rng.normal(scale=10.0, size=(5, SPUN.n_gratings))
    e = SPUN.strain_sensitivity * spun.linear_strain(SPUN, k, tau, 1e-4)
    solver = spun.TwistSolver(spun.twist_design(SPUN))
    sol = solver.solve(e)
    np.testing.assert_allclose(sol.curvature, k, atol=1e-9)
    np.testing.assert_allclose(sol.twist_rate, tau, atol=1e-7)
    np.testing.assert_allclose(sol.common_mode, SPUN.strain_sensitivity * 1e-4, rtol=1e-9)
    # an outer core lost: 3 equations, 4 unknowns → τ there is interpolated from the frame's other gratings and
    # the curvature solved with it; the centre core lost → the same; two cores lost → invalid
    e[0, 3, 1] = np.nan
    e[1, 4, 0] = np.nan
    e[2, 5, 1:3] = np.nan
    sol = solver.solve(e)
    assert sol.valid[0, 3] and sol.valid[1, 4] and not sol.valid[2, 5]
    assert sol.valid.sum() == sol.valid.size - 1
    assert np.isnan(sol.twist_rate[2, 5]) and sol.twist_filled.sum() == 2
    assert sol.twist_filled[0, 3] and sol.twist_filled[1, 4]
    measured = sol.valid & ~sol.twist_filled
    np.testing.assert_allclose(sol.twist_rate[measured], tau[measured], atol=1e-7)
    np.testing.assert_allclose(sol.curvature[measured], k[measured], atol=1e-9)
    for f, n in ((0, 3), (1, 4)):
        good = measured[f]
        fill = np.interp(SPUN.grating_s[n], SPUN.grating_s[good], tau[f, good])
        assert sol.twist_rate[f, n] == pytest.approx(fill, abs=1e-7)
        # the curvature is exact up to the twist term's share of the interpolation error
        err = np.abs(sol.curvature[f, n] - k[f, n]).max()
        assert err < 3 * 35e-6 * SPUN.spin_omega * abs(fill - tau[f, n]) + 1e-9


def test_a_lost_peak_keeps_the_grating_and_interpolates_the_twist():
    """A 4-core spun fibre losing one peak keeps the grating's curvature; the reconstruction fills its twist
    from the neighbouring gratings, so a constant-twist helix stays within 0.1 mm."""
    u = (0.0, 20.0, 6.0)
    k = np.tile([u[1], -u[0]], (SPUN.n_gratings, 1))
    w = exact_wavelengths(SPUN, k, np.full(SPUN.n_gratings, u[2]))
    w[[4, 9, 10], [1, 2, 0]] = np.nan
    rec = Reconstructor(SPUN)
    shape = rec(w)
    assert shape.valid.all()
    pos, _ = exact_helix(u, shape.s)
    assert np.linalg.norm(shape.positions - pos, axis=-1).max() < 0.1e-3
    np.testing.assert_allclose(rec.twist_angle(w)[-1], u[2] * SPUN.sensed_length, rtol=1e-4)


def test_seven_core_spun_fiber_survives_a_lost_outer_core():
    f = FiberModel(core_angles=np.r_[0.0, np.arange(6) * np.pi / 3], core_radii=[0.0] + [35e-6] * 6,
                   grating_s=[0.0, 0.01, 0.02], lambda0=np.full((3, 7), 1550.0), central_core=0, spin_rate=50.0)
    k = np.array([[10.0, -4.0], [3.0, 8.0], [0.0, 20.0]])
    tau = np.array([5.0, -2.0, 7.0])
    e = f.strain_sensitivity * spun.linear_strain(f, k, tau)
    e[1, 3] = np.nan
    sol = spun.TwistSolver(spun.twist_design(f)).solve(e)
    assert sol.valid.all()
    np.testing.assert_allclose(sol.twist_rate, tau, atol=1e-7)


def test_twist_resolution_matches_linear_error_propagation():
    """White wavelength noise σ: the scatter of τ and k over many frames matches the reported
    √diag((DᵀΣ⁻¹D)⁻¹) (2.49 rad/m at 1 pm for centre + 3 outer cores, 50 turns/m: σ_e √(1 + 1/3) / (S_ε r²Ω))."""
    sigma = 1e-3  # nm
    rec = Reconstructor(SPUN, wavelength_noise=sigma)
    k = np.tile([12.0, -7.0], (SPUN.n_gratings, 1))
    w = linear_wavelengths(SPUN, k, np.full(SPUN.n_gratings, 3.0))
    n = 4000
    noisy = w + np.random.default_rng(4).normal(scale=sigma, size=(n, *w.shape))
    sol = rec.curvature(noisy)
    # 4000 samples: the std of a std estimate is 1.1 %; 5 % is 4.5σ
    np.testing.assert_allclose(sol.twist_rate.std(axis=0), sol.twist_rate_std, rtol=0.05)
    np.testing.assert_allclose(sol.curvature.std(axis=0), sol.curvature_std, rtol=0.05)
    assert np.all(np.abs(sol.twist_rate.mean(axis=0) - 3.0) < 5 * sol.twist_rate_std / np.sqrt(n))
    lam = SPUN.lambda0[:, 1]
    predicted = sigma / lam * np.sqrt(1 + 1 / 3) / (SPUN.strain_sensitivity * spun.twist_sensitivity(SPUN)[1])
    np.testing.assert_allclose(sol.twist_rate_std, predicted, rtol=1e-9)


# ------------------------------------------------------------------------------------------- the reconstruction
@pytest.mark.parametrize("u", [(-5.0, 20.0, 8.0), (0.0, 15.0, -12.0), (7.0, 0.0, 0.0), (0.0, 0.0, 10.0)])
def test_constant_curvature_and_twist_give_the_exact_helix_with_its_roll(u):
    """Constant Darboux vector (κ1, κ2, τ), wavelengths from the exact helical path length: the centreline is a
    helix (an arc when τ = 0) and the material frame rolls by τ s about the tangent. The reconstruction's model
    omits only the (r κ)² sin²α and r κ · r²Ωτ terms: τ off by ≤ sin²α κ²/(4Ω) ≈ 4e-5 rad/m at κ = 21 1/m, so
    the roll is off by < 1e-5 rad and the tip by a few tenths of a µm; the integrator (Magnus-4, constant rates)
    is exact."""
    k = np.tile([u[1], -u[0]], (SPUN.n_gratings, 1))  # (k_x, k_y) = (κ2, −κ1)
    w = exact_wavelengths(SPUN, k, np.full(SPUN.n_gratings, u[2]))
    rec = Reconstructor(SPUN)
    assert rec.twist
    shape = rec(w)
    pos, frames = exact_helix(u, shape.s)
    np.testing.assert_allclose(shape.positions, pos, atol=1e-6)
    np.testing.assert_allclose(shape.frames, frames, atol=1e-5)
    np.testing.assert_allclose(rec.twist_angle(w), u[2] * shape.s, atol=1e-5)
    if not (u[0] or u[1]):  # pure twist: the exact-twist mapping inverts the path length exactly
        np.testing.assert_allclose(shape.frames, frames, atol=1e-9)
    ignored = Reconstructor(SPUN, twist=False)(w)
    if u[2] and np.hypot(u[0], u[1]):
        # ignoring the twist puts the bend in the wrong plane: millimetres over 170 mm
        assert np.linalg.norm(ignored.positions - pos, axis=-1).max() > 1e-3
    # the curvature vector itself does not depend on whether the twist is measured
    np.testing.assert_allclose(ignored.curvature, k, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("tau", [10.0, -25.0])
def test_exact_optics_give_the_predicted_twist_bias_and_the_helix_correction_removes_it(tau):
    """Wavelengths from the exact path length: the linear inversion reads τ (1 + τ/(2Ω)) to first order; the
    reconstruction's exact-twist mapping recovers τ (the bending cross terms cancel over 3 evenly spaced cores)."""
    k = np.tile([15.0, 4.0], (SPUN.n_gratings, 1))
    e = SPUN.strain_sensitivity * spun.exact_strain(SPUN, k, np.full(SPUN.n_gratings, tau))
    linear = spun.TwistSolver(spun.twist_design(SPUN)).solve(e)
    np.testing.assert_allclose(linear.twist_rate, tau * (1 + tau / (2 * SPUN.spin_omega)), rtol=1e-3)
    sol = Reconstructor(SPUN).curvature(SPUN.lambda0 * (1 + e))
    np.testing.assert_allclose(sol.twist_rate, tau, rtol=1e-5)
    np.testing.assert_allclose(sol.curvature, k, rtol=1e-3)


def test_exact_twist_inverts_the_pure_twist_path_length():
    tau = np.linspace(-60.0, 60.0, 13)
    for omega in (2 * np.pi * 50, -2 * np.pi * 20):
        c = 1 / (1 + (35e-6 * omega) ** 2)
        lin = (np.sqrt(1 + c * 35e-6**2 * (2 * omega * tau + tau**2)) - 1) / (c * 35e-6**2 * omega)
        np.testing.assert_allclose(spun.exact_twist(lin, omega, 35e-6), tau, atol=1e-9)


def test_straight_core_reconstruction_is_untouched():
    f = FiberModel.paper()
    rec = Reconstructor(f)
    assert not rec.twist
    with pytest.raises(ValueError, match="spun fibre"):
        Reconstructor(f, twist=True)
    with pytest.raises(ValueError, match="material"):
        Reconstructor(SPUN, method="paper", twist=True)
    with pytest.raises(ValueError, match="twist"):
        rec.twist_angle(f.lambda0)


def test_with_calibration_keeps_the_twist_inversion():
    k = np.tile([10.0, 0.0], (SPUN.n_gratings, 1))
    lam0 = SPUN.lambda0 + 0.2
    w = exact_wavelengths(SPUN, k, np.full(SPUN.n_gratings, 5.0), lam0=lam0)
    rec = Reconstructor(SPUN).with_calibration(Calibration(lambda0=lam0))
    np.testing.assert_allclose(rec.curvature(w).twist_rate, 5.0, atol=1e-5)


# ------------------------------------------------------------------------------------------- calibration
def test_two_step_finds_the_spin_rate_and_phase():
    """The as-drawn fibre spins at 50.4 turns/m with a 0.05 rad phase wobble; the nominal model says 50 (0.43 rad
    of core angle lost over the sensed length). The bend step's residual core angles give the rate; the
    calibrated fibre then reconstructs a twisted helix."""
    true_rate = 50.4
    wobble = 0.05 * np.sin(2 * np.pi * SPUN.grating_s / SPUN.grating_s[-1])
    true = SPUN.replace(spin_rate=true_rate)
    lam0 = SPUN.lambda0 + np.random.default_rng(5).normal(scale=0.3, size=SPUN.lambda0.shape)
    k_bend = np.tile([20.0, 0.0], (SPUN.n_gratings, 1))

    def measure(k, tau):
        e = true.strain_sensitivity * spun.exact_strain(true, k, tau, twist=wobble)
        return lam0 * (1 + e)

    zero = np.zeros(SPUN.n_gratings)
    cal, report = two_step(SPUN, measure(0 * k_bend, zero), measure(k_bend, zero))
    # the rate is the slope of the best line through the true core phase (the wobble tilts it a little)
    slope = np.polyfit(SPUN.grating_s, 2 * np.pi * true_rate * SPUN.grating_s + wobble, 1)[0] / (2 * np.pi)
    assert abs(slope - true_rate) < 0.1
    assert cal.spin_rate == pytest.approx(slope, abs=1e-6)
    assert report.spin_rate == cal.spin_rate and report.spin_rate_std is not None
    # the calibrated core angles reproduce the true ones (relative to grating 0)
    true_phase = 2 * np.pi * true_rate * SPUN.grating_s + wobble - wobble[0]
    cal_phase = 2 * np.pi * cal.spin_rate * SPUN.grating_s + cal.twist
    np.testing.assert_allclose(cal_phase, true_phase, atol=1e-6)
    u = (3.0, 18.0, 6.0)
    k = np.tile([u[1], -u[0]], (SPUN.n_gratings, 1))
    w = measure(k, np.full(SPUN.n_gratings, u[2]))
    shape = Reconstructor(SPUN, cal)(w)
    pos, _ = exact_helix(u, shape.s)
    # what is left: the twist scale follows the fitted rate, 0.15 % below the true one (the wobble tilts the
    # line), which at τ = 6 rad/m rolls the tip by ≈ 1.5 mrad: ≈ 80 µm
    assert np.linalg.norm(shape.positions - pos, axis=-1).max() < 0.1e-3
    nominal = Reconstructor(SPUN, Calibration(lambda0=lam0))(w)
    assert np.linalg.norm(nominal.positions - pos, axis=-1).max() > 1e-3
    back = Calibration.from_dict(cal.to_dict())
    assert back.spin_rate == cal.spin_rate


def test_peak_window_holds_for_a_spun_fiber():
    """An absurd peak on a spun fibre (twist measured) is missing like on straight cores, not a NaN shape."""
    from twin import FiberModel, Reconstructor

    f = FiberModel.spun(100.0)
    rec = Reconstructor(f)
    w = f.lambda0.copy()
    clean = rec(w)
    w[5, 1] = 1e300
    assert rec.peaks_outside(w)[5, 1] and rec.peaks_outside(w).sum() == 1
    shape = rec(w)
    assert np.isfinite(shape.positions).all()
    assert np.abs(shape.positions - clean.positions).max() < 1e-9  # straight either way: one core of 4 lost
