"""Integrators and interpolants (docs/math.md §3): HEM closed form, limits, convergence orders, planarity."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from twin import curve


def hat(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def hem_closed_form(kappa, tau, h):
    """docs/math.md §3.3 written out: (R_step, Δp) in the Frenet body frame."""
    w = np.hypot(kappa, tau)
    th = w * h
    if th < 1e-3:  # the series of docs/math.md §3.3 (the quotients cancel catastrophically there)
        a, b, c_ = 1 - th**2 / 6 + th**4 / 120, 0.5 - th**2 / 24 + th**4 / 720, 1 / 6 - th**2 / 120 + th**4 / 5040
    else:
        a, b, c_ = np.sin(th) / th, (1 - np.cos(th)) / th**2, (th - np.sin(th)) / th**3
    t_new = np.array([1 - kappa**2 * h**2 * b, kappa * h * a, kappa * tau * h**2 * b])
    n_new = np.array([-kappa * h * a, np.cos(th), tau * h * a])
    b_new = np.array([kappa * tau * h**2 * b, -tau * h * a, 1 - tau**2 * h**2 * b])
    dp = np.array([h - kappa**2 * h**3 * c_, kappa * h**2 * b, kappa * tau * h**3 * c_])
    return np.stack([t_new, n_new, b_new], axis=1), dp


def one_step(kappa, tau, h, integrator="hem-mid"):
    m = len(curve._OFFSETS[integrator])
    rates = np.empty((2, 1, m))
    rates[0], rates[1] = tau, kappa
    pos, frames = curve.integrate(rates, h, integrator, frenet=True)
    return frames[1], pos[1]


@pytest.mark.parametrize(("kappa", "tau"), [(50.0, 120.0), (67.5, -40.0), (0.0, 80.0), (30.0, 0.0), (0.0, 0.0),
                                            (1e-7, 2e-7)])
@pytest.mark.parametrize("h", [1e-3, 1e-2, 0.05])
def test_hem_equals_closed_form_and_se3_exponential(kappa, tau, h):
    r, p = one_step(kappa, tau, h)
    r_ref, p_ref = hem_closed_form(kappa, tau, h)
    twist = np.zeros((4, 4))
    twist[:3, :3] = hat([tau, 0.0, kappa]) * h
    twist[:3, 3] = [h, 0, 0]
    g = expm(twist)
    # 1e-14: both are closed forms of the same exponential; only rounding differs
    np.testing.assert_allclose(r, r_ref, atol=1e-14)
    np.testing.assert_allclose(r, g[:3, :3], atol=1e-14)
    np.testing.assert_allclose(p, p_ref, atol=1e-16 + 1e-14 * h)
    np.testing.assert_allclose(p, g[:3, 3], atol=1e-16 + 1e-14 * h)


def test_hem_limits():
    # κ = 0: pure rotation about T by τh, and p advances h along T
    r, p = one_step(0.0, 40.0, 0.01)
    np.testing.assert_allclose(r, expm(hat([0.4, 0, 0])), atol=1e-15)
    np.testing.assert_allclose(p, [0.01, 0, 0], atol=1e-17)
    # τ = 0: circular arc
    kappa, h = 25.0, 0.02
    _, p = one_step(kappa, 0.0, h)
    np.testing.assert_allclose(p, [np.sin(kappa * h) / kappa, (1 - np.cos(kappa * h)) / kappa, 0], atol=1e-16)


def test_helix_full_turn_returns_identity_and_advances_the_pitch():
    kappa, tau = 50.0, 100.0
    w2 = kappa**2 + tau**2
    h = 2 * np.pi / np.sqrt(w2)
    r, p = one_step(kappa, tau, h)
    np.testing.assert_allclose(r, np.eye(3), atol=1e-14)
    pitch = 2 * np.pi * tau / w2
    # the helix axis is the Darboux vector (τ, 0, κ)/w in the body frame
    np.testing.assert_allclose(p, pitch * np.array([tau, 0, kappa]) / np.sqrt(w2), atol=1e-15)


# ------------------------------------------------------------------ convergence orders (docs/math.md §3.4)
L = 0.17


def kappa_fn(s):
    return 35.0 + 30.0 * np.sin(2 * np.pi * s / L + 0.4)


def tau_fn(s):
    return 120.0 * np.sin(3 * np.pi * s / L + 0.3)


def frenet_tip(h, integrator):
    n = round(L / h)
    s_pts = np.linspace(0, L, n + 1)
    smp = curve.sample_points(s_pts, L / n, integrator)
    rates = np.stack([tau_fn(smp), kappa_fn(smp)])
    pos, _ = curve.integrate(rates, L / n, integrator, frenet=True)
    return pos[-1]


@pytest.fixture(scope="module")
def reference_tip():
    def rhs(s, y):
        f = y[3:].reshape(3, 3)
        return np.concatenate([f[:, 0], (f @ hat([tau_fn(s), 0, kappa_fn(s)])).ravel()])

    sol = solve_ivp(rhs, (0, L), np.r_[np.zeros(3), np.eye(3).ravel()], method="DOP853", rtol=1e-13, atol=1e-15)
    return sol.y[:3, -1]


@pytest.mark.parametrize(("integrator", "order", "hs"), [
    ("hem-left", 1, (2.5e-3, 1.25e-3, 0.625e-3)),
    ("hem-mid", 2, (2.5e-3, 1.25e-3, 0.625e-3)),
    ("magnus4", 4, (5e-3, 2.5e-3, 1.25e-3)),
    ("rk4", 4, (5e-3, 2.5e-3, 1.25e-3)),
])
def test_observed_convergence_order(integrator, order, hs, reference_tip):
    """log2 of successive error ratios within ±0.1 of the order (docs/math.md §7.8), on the §3.4 varying curve."""
    errs = [np.linalg.norm(frenet_tip(h, integrator) - reference_tip) for h in hs]
    observed = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(np.abs(observed - order) < 0.1), (errs, observed)


def _se3_rate(s: float) -> np.ndarray:
    """ξ̂(s) of the §3.4 curve in the Frenet body frame: F' = F ω̂ with ω = (τ, 0, κ), p' = F e1 (4 × 4)."""
    k, t = kappa_fn(s), tau_fn(s)
    m = np.zeros((4, 4))
    m[:3, :3] = [[0.0, -k, 0.0], [k, 0.0, -t], [0.0, t, 0.0]]
    m[0, 3] = 1.0
    return m


def reference_scheme_tip(h: float, scheme: str) -> np.ndarray:
    """The tip by each scheme as docs/math.md §3.3–3.4 define it, written independently of twin.curve's kernels:
    products of scipy.linalg.expm of the se(3) step (HEM at the step's start or midpoint; the 2-point Gauss
    Magnus step h/2 (A1 + A2) + √3/12 h² [A1, A2], the commutator's sign that of g' = g A), or classical RK4 on
    the 4 × 4 matrix equation g' = g ξ̂(s)."""
    from scipy.linalg import expm

    n = round(L / h)
    h = L / n
    g = np.eye(4)
    for k in range(n):
        s = k * h
        if scheme == "rk4":
            k1 = g @ _se3_rate(s)
            k2 = (g + h / 2 * k1) @ _se3_rate(s + h / 2)
            k3 = (g + h / 2 * k2) @ _se3_rate(s + h / 2)
            k4 = (g + h * k3) @ _se3_rate(s + h)
            g = g + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            continue
        if scheme == "magnus4":
            a1, a2 = (_se3_rate(s + (0.5 + sign * np.sqrt(3) / 6) * h) for sign in (-1, 1))
            step = h / 2 * (a1 + a2) + np.sqrt(3) / 12 * h**2 * (a1 @ a2 - a2 @ a1)
        else:
            step = h * _se3_rate(s + (h / 2 if scheme == "hem-mid" else 0.0))
        g = g @ expm(step)
    return g[:3, 3]


def test_tip_errors_match_the_table(reference_tip):
    """docs/math.md §3.4 at h = 1.25 mm: HEM-left 4.79 mm, HEM-mid 0.0330 mm, Magnus-4 4.0e-5 mm, RK4 2.5e-3 mm.

    The kernels' tips equal those of an independent implementation of each scheme (reference_scheme_tip) to
    rounding over 136 steps (1e-13 m; measured ≤ 2e-16), and that implementation's errors against DOP853 are the
    table's to half a unit of its last printed digit."""
    table = {"hem-left": (4.79e-3, 0.005e-3), "hem-mid": (3.30e-5, 0.005e-5), "magnus4": (4.0e-8, 0.05e-8),
             "rk4": (2.5e-6, 0.05e-6)}
    for integrator, (expected, half_digit) in table.items():
        ours, independent = frenet_tip(1.25e-3, integrator), reference_scheme_tip(1.25e-3, integrator)
        np.testing.assert_allclose(ours, independent, rtol=0, atol=1e-13, err_msg=integrator)
        err = np.linalg.norm(independent - reference_tip)
        assert abs(err - expected) <= half_digit, (integrator, err)


def test_frames_stay_orthonormal():
    rng = np.random.default_rng(0)
    rates = rng.normal(scale=60, size=(5, 2, 170, 2))
    _, frames = curve.integrate(rates, 1e-3, "magnus4")
    gram = np.einsum("...ji,...jk->...ik", frames, frames)
    assert np.abs(gram - np.eye(3)).max() < 1e-13  # exact exponentials: only rounding accumulates
    assert np.allclose(np.linalg.det(frames), 1.0, atol=1e-13)


def test_planar_material_curve_stays_planar():
    """k_y ≡ 0 keeps the curve exactly in the x–z plane (|y| < 1e-12 m, docs/math.md §7.8)."""
    s, h = curve.step_grid(0, L, 1e-3)
    smp = curve.sample_points(s, h, "magnus4")
    kx = 45 * np.sin(2 * np.pi * smp / L + 0.3)
    pos, _frames = curve.integrate(np.stack([kx, 0 * kx]), h, "magnus4")
    assert np.abs(pos[:, 1]).max() < 1e-12


def test_step_grid_divides_evenly():
    s, h = curve.step_grid(0.0, 0.17, 1.5e-3)
    assert h <= 1.5e-3 and s[-1] == pytest.approx(0.17) and np.allclose(np.diff(s), h)
    with pytest.raises(ValueError, match="positive length"):
        curve.step_grid(0, 0.17, 0.0)


@pytest.mark.parametrize("kind", ["spline", "linear", "knn"])
def test_basis_reproduces_what_it_should(kind):
    nodes = np.array([0.0, 0.01, 0.025, 0.03, 0.05])
    x = np.linspace(-0.01, 0.06, 200)
    b = curve.basis(nodes, x, kind)
    np.testing.assert_allclose(b.sum(axis=1), 1.0, atol=1e-12)  # constants are reproduced
    xc = np.clip(x, nodes[0], nodes[-1])
    if kind == "spline":  # a cubic is reproduced exactly by a not-a-knot spline
        np.testing.assert_allclose(b @ (nodes**3 - nodes), xc**3 - xc, atol=1e-15)
        np.testing.assert_allclose(curve.basis(nodes, x, kind, derivative=True) @ nodes**3,
                                   np.where((x < 0) | (x > 0.05), 0, 3 * x**2), atol=1e-12)
    elif kind == "linear":
        np.testing.assert_allclose(b @ nodes, xc, atol=1e-15)
    else:
        assert set(np.unique(b)) <= {0.0, 1.0}
        np.testing.assert_allclose(b @ nodes, nodes[np.argmin(np.abs(xc[:, None] - nodes), axis=1)])


def test_pchip_is_monotone_and_clamped():
    nodes = np.linspace(0, 0.17, 18)
    v = np.where(nodes < 0.08, 0.0, 50.0)[:, None]
    out = curve.interpolate(nodes, v, np.linspace(-0.01, 0.2, 500), "pchip")[:, 0]
    assert out.min() >= 0 and out.max() <= 50 and np.all(np.diff(out) >= -1e-12)


def test_torsion_schemes():
    s = 0.01 * np.arange(5)
    theta = np.array([0.0, 0.5, 1.2, 2.1, 3.2])
    st, tau = curve.torsion_nodes(theta, s, "forward")
    d = np.diff(theta)
    np.testing.assert_allclose(tau, np.r_[d, 2 * d[-1] - d[-2]] / 0.01)  # the paper's extrapolated last node
    st, tau = curve.torsion_nodes(theta, s, "centred")
    np.testing.assert_allclose(st, s[:-1] + 0.005)
    # an angle jump across ±π is wrapped, not taken as a 2π turn
    _, tau = curve.torsion_nodes(np.array([3.0, -3.0, -2.9]), s[:3], "forward")
    assert tau[0] == pytest.approx((2 * np.pi - 6.0) / 0.01)


def test_hold_bend_angle():
    """θ_b held at the last reliable value, leading nodes take the first reliable one, batch-wise; κ_min = 0 is
    the identity; a curve with no reliable node keeps its first angle."""
    theta = np.array([[0.1, 0.2, 0.3, 0.4, 0.5, 0.6], [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]])
    kappa = np.array([[0.0, 0.5, 3.0, 0.2, 4.0, 0.9], [0.1, 0.1, 0.1, 0.1, 0.1, 0.1]])
    held = curve.hold_bend_angle(theta, kappa, 1.0)
    np.testing.assert_array_equal(held[0], [0.3, 0.3, 0.3, 0.3, 0.5, 0.5])
    np.testing.assert_array_equal(held[1], np.full(6, 1.0))
    np.testing.assert_array_equal(curve.hold_bend_angle(theta, kappa, 0.0), theta)
    _, tau = curve.torsion_nodes(held[:1], np.arange(6) * 0.01, "forward")
    assert np.count_nonzero(tau) == 2  # the turn is taken where the next reliable grating is reached
