"""Wavelengths ↔ curvature (docs/math.md §2): exactness for any layout, the paper's eqs. 5–7 and their bias, missing
peaks, bad input."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin import FiberModel, strain
from twin.strain import CurvatureSolver, design_matrix, optical_strain


def layout(angles, radii, central=None, n_g=5):
    return FiberModel(
        core_angles=angles,
        core_radii=radii,
        grating_s=0.01 * np.arange(n_g),
        lambda0=1530.0 + np.arange(n_g * len(angles)).reshape(n_g, len(angles)),
        central_core=central,
    )


LAYOUTS = {
    "paper (centre + 3 adjacent)": FiberModel.paper(),
    "3 symmetric, no centre": layout([0, 2 * np.pi / 3, 4 * np.pi / 3], [4e-5] * 3),
    "3 adjacent, no centre": layout([0, np.pi / 3, 2 * np.pi / 3], [3.75e-5] * 3),
    "4 symmetric + centre": layout([0, 0, np.pi / 2, np.pi, 3 * np.pi / 2], [0] + [3.5e-5] * 4, central=0),
    "6 outer + centre": layout([0, *list(np.arange(6) * np.pi / 3)], [0] + [3.5e-5] * 6, central=0),
    "random 3 fibres on a needle": layout([0.1, 2.3, 4.0], [0.41e-3, 0.39e-3, 0.43e-3]),
}


def test_eq4_sign_convention():
    """The core facing the centre of curvature (θ_i = θ_b) is compressed by κ r (docs/math.md §2.2)."""
    f = FiberModel.paper()
    k = np.zeros((18, 2))
    k[:, :] = 20.0 * np.array([np.cos(np.pi / 3), np.sin(np.pi / 3)])  # bend toward core 2 (θ = π/3)
    e = optical_strain(strain.forward(f, k), f.lambda0)
    np.testing.assert_allclose(e[:, 2], -20.0 * 37.5e-6 * 0.777, rtol=1e-12)  # 1e-12: float64 rounding only
    assert np.all(e[:, 0] == 0)  # centre core unstrained


@pytest.mark.parametrize("name", LAYOUTS)
def test_forward_inverse_exact_for_any_layout(name):
    """LS inversion is exact for every layout, with an unknown common mode of ~300 µε (docs/math.md §2.3)."""
    f = LAYOUTS[name]
    rng = np.random.default_rng(3)
    k = rng.uniform(-70, 70, size=(7, f.n_gratings, 2))
    axial = rng.uniform(-300e-6, 300e-6, size=(7, f.n_gratings))
    dT = rng.uniform(-30, 30, size=(7, f.n_gratings))
    w = strain.forward(f, k, axial_strain=axial, delta_T=dT)
    # 1e-9 1/m absolute: wavelengths ~1550 nm carry ~1e-13 relative rounding, i.e. ~1e-13/g ≈ 3e-9 1/m at g = 29 µm
    np.testing.assert_allclose(strain.curvature(f, w), k, atol=1e-8)
    sol = CurvatureSolver.for_fiber(f).solve(optical_strain(w, f.lambda0))
    np.testing.assert_allclose(sol.common_mode, 0.777 * axial + 6.6e-6 * dT, atol=1e-13)


def test_paper_equations_exact_at_pi_over_3():
    f = FiberModel.paper()
    rng = np.random.default_rng(0)
    k = rng.uniform(-70, 70, size=(50, 18, 2))
    w = strain.forward(f, k, delta_T=25.0)
    np.testing.assert_allclose(strain.curvature(f, w, method="paper"), k, atol=1e-8)


def test_paper_equations_biased_at_fitted_spacing():
    """With the paper's fitted Δθ = 1.039 rad, eqs. 5–7 err by 0.95 % in κ and 9.5 mrad in θ_b; LS stays exact
    (docs/math.md §0 item 1 and the table of §2.3)."""
    f = FiberModel.paper().replace(core_angles=[0.0, 0.0, 1.039, 2 * 1.039])
    theta_b = np.linspace(-np.pi, np.pi, 721)
    k = 30.0 * np.stack([np.cos(theta_b), np.sin(theta_b)], -1)
    k = np.repeat(k[:, None, :], 18, axis=1)
    w = strain.forward(f, k)
    kp = strain.curvature(f, w, method="paper")
    rel = np.abs(np.hypot(kp[..., 0], kp[..., 1]) / 30.0 - 1)
    dth = np.abs(np.angle(np.exp(1j * (np.arctan2(kp[..., 1], kp[..., 0]) - theta_b[:, None]))))
    assert rel.max() == pytest.approx(9.5e-3, rel=0.03)  # the doc's figure to its 2 digits
    assert dth.max() == pytest.approx(9.5e-3, rel=0.03)
    np.testing.assert_allclose(strain.curvature(f, w), k, atol=1e-8)


def test_common_mode_leak_of_adjacent_cores_in_paper_mode():
    """A residual common mode of 1 µε leaks into eq. 5–6 as 4/3·ε/r = 0.0356 1/m (docs/math.md §0)."""
    f = FiberModel.paper()
    e = np.zeros((18, 4))
    e[:, 1:] = 1e-6 * f.strain_sensitivity  # outer cores only: the centre does not remove it
    w = f.lambda0 * (1 + e)
    k = strain.curvature(f, w, method="paper")
    assert np.hypot(k[0, 0], k[0, 1]) == pytest.approx(4 / 3 * 1e-6 / 37.5e-6, rel=1e-9)


def test_missing_peak_drops_out_while_solvable():
    f = FiberModel.paper()
    k = np.tile([25.0, -10.0], (18, 1))
    w = strain.forward(f, k, delta_T=12.0)
    w[3, 2] = np.nan  # one outer core lost: centre + 2 outer still separate bending and common mode
    w[5, 1] = w[5, 3] = np.nan  # two outer cores lost: unsolvable
    w[7, 0] = np.nan  # centre lost: 3 outer cores still solve (common mode as an unknown)
    sol = CurvatureSolver.for_fiber(f).solve(optical_strain(w, f.lambda0))
    assert sol.valid.tolist() == [n != 5 for n in range(18)]
    np.testing.assert_allclose(sol.curvature[sol.valid], k[sol.valid], atol=1e-8)
    assert np.isnan(sol.curvature[5]).all()
    # the paper's eqs. need every core they use
    kp = strain.curvature(f, w, method="paper")
    assert np.isnan(kp[[3, 5, 7], 0]).all() and np.isfinite(kp[[0, 1, 2, 4, 6], 0]).all()


def test_missing_peaks_in_a_batch():
    f = FiberModel.paper()
    rng = np.random.default_rng(1)
    k = rng.uniform(-50, 50, (20, 18, 2))
    w = strain.forward(f, k)
    mask = rng.random(w.shape) < 0.1
    w[mask] = np.nan
    got = strain.curvature(f, w)
    ok = ~np.isnan(got[..., 0])
    np.testing.assert_allclose(got[ok], k[ok], atol=1e-8)
    # a node is solvable iff its remaining design has rank 3
    d = design_matrix(f)
    for idx in zip(*np.nonzero(mask.any(-1)), strict=True):
        rank = np.linalg.matrix_rank(d[idx[1]][~mask[idx]], tol=1e-9)
        assert ok[idx] == (rank == 3)


def test_no_central_core_needs_three_noncollinear_cores():
    with pytest.raises(ValueError, match="cannot separate bending"):
        CurvatureSolver.for_fiber(layout([0, np.pi], [4e-5, 4e-5]))
    with pytest.raises(ValueError, match="has no central core"):
        strain.curvature(LAYOUTS["3 symmetric, no centre"], np.full((5, 3), 1550.0), method="paper")


def test_noise_gain_matches_the_table():
    """Per-node curvature noise, in units of σ_ε/r, for the paper's layout with the joint LS: 1.000 / 1.291
    (docs/math.md §2.3 noise table). Computed exactly from the pseudo-inverse, no sampling."""
    f = FiberModel.paper()
    solver = CurvatureSolver.for_fiber(f)
    p = solver._p[0] * f.gains[1]  # k in units of 1/g per unit optical strain
    std = np.sqrt((p**2).sum(axis=1))
    np.testing.assert_allclose(std, [1.000, 1.291], atol=5e-4)


@settings(max_examples=200, deadline=None)
@given(
    n=st.integers(3, 7),
    central=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
)
def test_round_trip_random_layouts(n, central, seed):
    rng = np.random.default_rng(seed)
    angles = np.sort(rng.uniform(0, 2 * np.pi, n))
    radii = rng.uniform(20e-6, 500e-6, n)
    # the bending plane's design (common mode, x, y), columns scaled to O(1) as the solver does: cores too close
    # in angle, or all near one line across the section (three within 0.6 rad, seed 5047473), make it
    # ill-conditioned, which the model refuses; such draws are spread evenly instead (within the model's ±2π)
    xy = radii[:, None] * np.c_[np.cos(angles), np.sin(angles)]
    design = np.c_[np.ones(n), xy / np.abs(xy).max(axis=0)]
    if np.min(np.abs(np.diff(np.r_[angles, angles[0] + 2 * np.pi]))) < 0.3 or np.linalg.cond(design) > 30:
        angles = (np.arange(n) * 2 * np.pi / n + rng.uniform(0, 1)) % (2 * np.pi)
    if central:
        angles, radii = np.r_[0.0, angles], np.r_[0.0, radii]
    f = FiberModel(core_angles=angles, core_radii=radii, grating_s=[0.0, 0.01, 0.03],
                   lambda0=rng.uniform(800, 1600, (3, angles.size)), central_core=0 if central else None,
                   handedness=int(rng.choice([-1, 1])))
    k = rng.uniform(-80, 80, (4, 3, 2))
    w = strain.forward(f, k, axial_strain=rng.uniform(-1e-3, 1e-3, (4, 3)), delta_T=rng.uniform(-40, 40))
    # tolerance scales with the worst conditioning these random layouts reach (cond ≲ 1e3)
    np.testing.assert_allclose(strain.curvature(f, w), k, atol=1e-6)


@pytest.mark.parametrize(
    ("wavelengths", "message"),
    [
        (np.full((18, 3), 1550.0), r"shape \(\.\.\., 18, 4\)"),
        (np.full((4,), 1550.0), r"shape \(\.\.\., 18, 4\)"),
    ],
)
def test_wrong_shapes_are_clear(wavelengths, message):
    with pytest.raises(ValueError, match=message):
        strain.curvature(FiberModel.paper(), wavelengths)


def test_forward_checks_curvature_shape():
    with pytest.raises(ValueError, match=r"curvature must have shape \(\.\.\., 18, 2\)"):
        strain.forward(FiberModel.paper(), np.zeros((17, 2)))


def test_temperature_cancels_with_central_core_and_per_core_mismatch_leaks():
    f = FiberModel.paper()
    k = np.zeros((18, 2))
    w = strain.forward(f, k, delta_T=30.0)
    assert np.abs(strain.curvature(f, w)).max() < 1e-9
    # a 1 % S_T mismatch on one core leaves ≈ 0.07 1/m at 30 K (docs/math.md §6 "Systematic errors")
    g = f.replace(temperature_sensitivity=6.6e-6 * np.array([1, 1.01, 1, 1]))
    leak = np.hypot(*strain.curvature(f, strain.forward(g, k, delta_T=30.0))[0])
    assert 0.03 < leak < 0.12
