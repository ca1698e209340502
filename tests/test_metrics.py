"""Registration and error metrics (docs/math.md §5.2, §7.6): Kabsch, exact point-to-polyline, ICP, translation
search, shape_error and the in-plane / out-of-plane split."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from twin import metrics

seeds = st.integers(0, 2**32 - 1)


def rigid(seed):
    """A random rotation and a translation of a few cm."""
    rng = np.random.default_rng(seed)
    return Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 0.05, 3)


def brute_force(points, polyline):
    """Distance to every segment, no tree: the reference for point_to_polyline."""
    a, e = polyline[:-1], np.diff(polyline, axis=0)
    u = np.clip(np.einsum("mkj,kj->mk", points[:, None] - a, e) / np.einsum("kj,kj->k", e, e), 0, 1)
    return np.linalg.norm(points[:, None] - (a + u[..., None] * e), axis=-1).min(axis=1)


def space_curve(s):
    """A 3D curve without continuous symmetry (a helix or an arc can slide along itself), s in m."""
    return np.stack([0.02 * np.sin(30 * s) + 0.5 * s**2, 0.03 * (1 - np.cos(20 * s)), s + 0.3 * s**3], axis=-1)


S_DENSE = np.linspace(0.0, 0.17, 1701)  # 0.1 mm spacing over the paper's 170 mm
TRUTH = space_curve(S_DENSE)


# ---------------------------------------------------------------------------------------------- Kabsch


@settings(max_examples=40, deadline=None)
@given(seeds, st.integers(3, 40))
def test_kabsch_recovers_random_rigid_motions(seed, n):
    src = np.random.default_rng(seed).normal(0, 0.05, (n, 3))
    R, t = rigid(seed)
    R_k, t_k = metrics.kabsch(src, src @ R.T + t)
    # 1e-10: exact data; only rounding, amplified by the conditioning of a few random points, remains
    np.testing.assert_allclose(R_k, R, atol=1e-10)
    np.testing.assert_allclose(t_k, t, atol=1e-10)


def test_kabsch_exact_on_planar_points_where_naive_svd_reflects():
    # Coplanar points leave the third singular vector's sign to LAPACK, so V Uᵀ is a reflection in about
    # half the cases; the determinant correction must return the true rotation in all of them.
    rng = np.random.default_rng(1)
    src = np.column_stack([rng.normal(0, 0.05, (12, 2)), np.zeros(12)])
    reflected = 0
    for seed in range(20):
        R, t = rigid(seed)
        tgt = src @ R.T + t
        u, _, vt = np.linalg.svd((src - src.mean(0)).T @ (tgt - tgt.mean(0)))
        reflected += np.linalg.det(vt.T @ u.T) < 0
        R_k, t_k = metrics.kabsch(src, tgt)
        # 1e-12: exact data, well-conditioned in-plane spread; rounding only
        np.testing.assert_allclose(R_k, R, atol=1e-12)
        np.testing.assert_allclose(t_k, t, atol=1e-12)
        assert np.linalg.det(R_k) == pytest.approx(1.0, abs=1e-12)
    assert reflected > 0, "no case exercised the determinant correction"


def test_kabsch_batched_weighted_and_least_squares():
    rng = np.random.default_rng(2)
    src = rng.normal(0, 0.05, (4, 15, 3))
    tgt = src @ Rotation.random(4, random_state=3).as_matrix().swapaxes(-1, -2) + rng.normal(0, 0.05, (4, 1, 3))
    tgt += rng.normal(0, 1e-3, tgt.shape)  # noise: the answer is a least-squares fit, not exact
    w = rng.uniform(0.5, 2.0, (4, 15))
    R, t = metrics.kabsch(src, tgt, w)
    for i in range(4):
        R_i, t_i = metrics.kabsch(src[i], tgt[i], w[i])
        # 1e-14: the same arithmetic batched or not
        np.testing.assert_allclose(R[i], R_i, atol=1e-14)
        np.testing.assert_allclose(t[i], t_i, atol=1e-14)
        # Wahba's problem on weighted-centred points, solved independently by scipy
        mu_s, mu_t = np.average(src[i], 0, w[i]), np.average(tgt[i], 0, w[i])
        ref, _ = Rotation.align_vectors(tgt[i] - mu_t, src[i] - mu_s, weights=w[i])
        # 1e-10: two different SVD-based solvers of the same well-posed problem
        np.testing.assert_allclose(R[i], ref.as_matrix(), atol=1e-10)
        np.testing.assert_allclose(t[i], mu_t - R[i] @ mu_s, atol=1e-12)
    # A zero weight removes an outlier entirely.
    R0, t0 = rigid(5)
    clean = src[0] @ R0.T + t0
    dirty = clean.copy()
    dirty[3] += 0.01
    w0 = np.ones(15)
    w0[3] = 0
    R_k, t_k = metrics.kabsch(src[0], dirty, w0)
    np.testing.assert_allclose(R_k, R0, atol=1e-12)  # exact data on the weighted points: rounding only
    np.testing.assert_allclose(t_k, t0, atol=1e-12)


# ------------------------------------------------------------------------------------- point to polyline


def test_point_to_polyline_circle():
    rho, n = 0.05, 200
    phi = np.linspace(0, 2 * np.pi, n + 1)  # closed: the last vertex repeats the first
    circle = rho * np.column_stack([np.cos(phi), np.sin(phi), np.zeros(n + 1)])
    apothem = rho * np.cos(np.pi / n)
    sagitta = rho - apothem  # = h²κ/8 to leading order (h the chord, κ = 1/ρ): 7.7e-7 m here
    h = 2 * rho * np.sin(np.pi / n)
    assert sagitta == pytest.approx(h**2 / rho / 8, rel=1e-4)
    rng = np.random.default_rng(4)
    p = rng.uniform(-0.1, 0.1, (2000, 3))
    d = metrics.point_to_polyline(p, circle)
    d_circle = np.hypot(np.hypot(p[:, 0], p[:, 1]) - rho, p[:, 2])
    # The inscribed polygon and the circle are a sagitta apart (Hausdorff), so distances differ by at most that.
    assert np.max(np.abs(d - d_circle)) <= sagitta + 1e-15
    # Exact polygon distances: on the ray through a chord's midpoint, the chord is nearest (inside or out).
    mid = phi[:-1] + np.pi / n
    radial = rng.uniform(0, 0.1, n)
    z = rng.uniform(-0.02, 0.02, n)
    q = np.column_stack([radial * np.cos(mid), radial * np.sin(mid), z])
    d, near = metrics.point_to_polyline(q, circle, return_closest=True)
    # 1e-15 m: rounding of coordinates ~0.1 m; the vertex-only distance would be off by up to h/2 = 0.8 mm
    np.testing.assert_allclose(d, np.hypot(radial - apothem, z), rtol=0, atol=1e-15)
    np.testing.assert_allclose(near, apothem * np.column_stack([np.cos(mid), np.sin(mid), 0 * mid]), atol=1e-15)
    # The centre is equidistant from every vertex and every chord.
    assert metrics.point_to_polyline([0.0, 0.0, 0.0], circle) == pytest.approx(apothem, rel=1e-15)


def test_point_to_polyline_straight_segment_and_no_vertex_bias():
    for line in (np.array([[0, 0, 0], [0.1, 0, 0]]), np.column_stack([np.linspace(0, 0.1, 11), np.zeros((11, 2))])):
        p = np.random.default_rng(6).uniform(-0.05, 0.15, (500, 3))
        foot = np.column_stack([np.clip(p[:, 0], 0, 0.1), np.zeros((500, 2))])
        d, near = metrics.point_to_polyline(p, line, return_closest=True)
        # 1e-15 m: analytic projection onto the x axis; rounding only
        np.testing.assert_allclose(d, np.linalg.norm(p - foot, axis=1), rtol=0, atol=1e-15)
        np.testing.assert_allclose(near, foot, atol=1e-15)
    # Opposite the middle of a 100 mm segment: the nearest vertex is 50 mm away, the segment 1 mm.
    assert metrics.point_to_polyline([0.05, 1e-3, 0], [[0, 0, 0], [0.1, 0, 0]]) == pytest.approx(1e-3, abs=1e-16)


def test_point_to_polyline_exact_where_the_polyline_folds_back():
    # A hairpin: a coarse leg (10 mm segments) and, 0.5 mm away, a dense leg (0.1 mm). Near the coarse leg's
    # segment midpoints the nearest vertices all belong to the dense leg, whose segments are not the nearest.
    coarse = np.column_stack([np.linspace(0, 0.1, 11), np.zeros(11), np.zeros(11)])
    dense = np.column_stack([np.linspace(0.1, 0, 1001), np.full(1001, 5e-4), np.zeros(1001)])
    hairpin = np.vstack([coarse, dense])
    rng = np.random.default_rng(7)
    p = np.column_stack([rng.uniform(0, 0.1, 500), rng.uniform(-2e-4, 7e-4, 500), rng.uniform(-2e-4, 2e-4, 500)])
    walk = np.cumsum(rng.normal(0, 2e-3, (300, 3)), axis=0)  # a tangled random walk folds everywhere
    q = rng.uniform(walk.min(0), walk.max(0), (500, 3))
    for points, line in ((p, hairpin), (q, walk)):
        # 1e-15 m: the same formula as the reference; only the candidate search differs
        np.testing.assert_allclose(metrics.point_to_polyline(points, line), brute_force(points, line),
                                   rtol=0, atol=1e-15)


@settings(max_examples=30, deadline=None)
@given(seeds)
def test_point_to_polyline_invariant_under_rigid_motion(seed):
    rng = np.random.default_rng(seed)
    line = np.cumsum(rng.normal(0, 5e-3, (50, 3)), axis=0)
    p = rng.normal(0, 0.03, (100, 3))
    R, t = rigid(seed)
    # 1e-12 m: rounding of coordinates up to ~0.2 m after the motion
    np.testing.assert_allclose(metrics.point_to_polyline(p @ R.T + t, line @ R.T + t),
                               metrics.point_to_polyline(p, line), rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------------ ICP and grid


def test_icp_recovers_a_small_perturbation():
    pts = TRUTH[::10]  # 1 mm spacing, exactly on the truth: the optimum has zero distance
    perturbations = [Rotation.from_rotvec(v).as_matrix() for v in ([0.01, -0.02, 0.015], [-0.005, 0.01, 0.0])]
    moved = np.stack([pts @ R.T + t for R, t in zip(perturbations, ([3e-4, -2e-4, 5e-4], [0, 1e-4, -3e-4]),
                                                    strict=True)])
    # ICP converges linearly (≈ 7 % per iteration on this curve), so 300 iterations for a µm-exact pose
    R, t, d = metrics.icp(moved, TRUTH, max_iter=300)
    registered = moved @ R.swapaxes(-1, -2) + t[:, None]
    # 1e-6 m: the requirement; the fixed point is exact, so this measures convergence only
    assert np.max(np.linalg.norm(registered - pts, axis=-1)) < 1e-6
    assert np.max(d) < 1e-6
    # Started at the answer, ICP stays there.
    R0 = perturbations[0].T
    R, t, d = metrics.icp(moved[0], TRUTH, R0=R0, t0=-R0 @ [3e-4, -2e-4, 5e-4])
    np.testing.assert_allclose(R, R0, atol=1e-12)  # exact start; rounding only
    assert np.max(d) < 1e-12


def test_translation_search_reduces_the_max_distance():
    pts = TRUTH[::10]
    on_grid = np.array([0.25e-3, -0.25e-3, 0.5e-3])  # a node of the 5³ grid over ±0.5 mm
    t, worst = metrics.translation_search(pts + on_grid, TRUTH)
    # 1e-12 m: the grid holds the exact answer; rounding of grid nodes and coordinates only
    np.testing.assert_allclose(t, -on_grid, atol=1e-12)
    assert worst < 1e-12
    off_grid = np.array([0.1e-3, -0.37e-3, 0.2e-3])
    before = metrics.point_to_polyline(pts + off_grid, TRUTH).max()
    t, worst = metrics.translation_search(pts + off_grid, TRUTH)
    assert worst < before / 2  # the nearest node is 0.17 mm from the answer; we start 0.43 mm away
    assert worst == pytest.approx(metrics.point_to_polyline(pts + off_grid + t, TRUTH).max(), rel=1e-12)
    t_fine, finer = metrics.translation_search(pts + off_grid, TRUTH, refine=True)
    assert finer < worst / 2  # the second grid is 4× finer: 0.0625 mm steps
    assert finer == pytest.approx(metrics.point_to_polyline(pts + off_grid + t_fine, TRUTH).max(), rel=1e-12)
    t_batch, worst_batch = metrics.translation_search(np.stack([pts + on_grid, pts + off_grid]), TRUTH)
    np.testing.assert_allclose(worst_batch, [0, worst], atol=1e-12)
    np.testing.assert_allclose(t_batch[1], t, atol=1e-15)


# ---------------------------------------------------------------------------------------------- errors


def test_shape_error_of_identical_curves_is_zero():
    stats = metrics.shape_error(TRUTH, TRUTH, register="none")
    # 1e-15 m: points on the vertices; the segment parametrisation rounds at ~1e-17
    assert max(stats.max, stats.mean, stats.rms, stats.tip) < 1e-15
    assert stats.as_mm() == pytest.approx({"max_error_mm": 0, "mean_error_mm": 0, "rms_error_mm": 0,
                                           "tip_error_mm": 0}, abs=1e-12)


def test_shape_error_registers_by_arc_length():
    s = np.linspace(0.0, 0.17, 18)  # the gratings, 10 mm apart, between the truth's samples
    s[1:-1] += 3.3e-4
    R, t = rigid(8)
    recon = space_curve(s) @ R.T + t
    for register in ("kabsch", "icp", "icp+translation"):
        stats = metrics.shape_error(recon, TRUTH, s=s, truth_s=S_DENSE, register=register)
        # 1e-6 m: the points lie on the true curve, within the chord sagitta h²κ/8 ≈ 1e-9 m of the polyline;
        # linear interpolation of the truth at s has the same error, which Kabsch averages into the pose
        assert stats.max < 1e-6 and stats.tip < 1e-6, register
    assert metrics.shape_error(recon, TRUTH, s=s, truth_s=S_DENSE, register="none").max > 0.01


def test_shape_error_takes_a_shape_and_a_truth():
    """``shape_error(shape, frame.truth)``: both carry their arc lengths, so the pairing is by arc length."""
    from twin.frames import Shape, Truth

    s = np.linspace(0.0, 0.17, 18)
    s[1:-1] += 3.3e-4
    R, t = rigid(8)
    n = len(s)
    shape = Shape(s=s, positions=space_curve(s) @ R.T + t, frames=np.tile(np.eye(3), (n, 1, 1)),
                  curvature=np.zeros((n, 2)), grating_s=s, valid=np.ones(n, bool))
    truth = Truth(s=S_DENSE, positions=TRUTH)
    stats = metrics.shape_error(shape, truth)
    expected = metrics.shape_error(shape.positions, TRUTH, s=s, truth_s=S_DENSE)
    assert stats.max == expected.max and stats.tip == expected.tip and stats.max < 1e-6  # as above
    bent = Truth(s=S_DENSE, positions=TRUTH + np.array([0.0, 0.0, 1e-3]) * (S_DENSE[:, None] / 0.17) ** 2)
    assert metrics.shape_error(shape, bent).max > 1e-4  # a different truth is seen


def test_shape_error_batches_match_single_curves():
    rng = np.random.default_rng(9)
    s = np.linspace(0.0, 0.17, 35)
    recon = space_curve(s) + rng.normal(0, 3e-4, (3, 35, 3))  # three noisy reconstructions
    truths = TRUTH + rng.normal(0, 1e-4, (3, 1, 3))  # each frame its own truth
    for register in metrics.REGISTRATIONS:
        shared = metrics.shape_error(recon, TRUTH, s=s, truth_s=S_DENSE, register=register)
        own = metrics.shape_error(recon, truths, s=s, truth_s=S_DENSE, register=register, split_plane=True)
        for i in range(3):
            one = metrics.shape_error(recon[i], TRUTH, s=s, truth_s=S_DENSE, register=register)
            one_own = metrics.shape_error(recon[i], truths[i], s=s, truth_s=S_DENSE, register=register,
                                          split_plane=True)
            # 1e-12 m: the same arithmetic batched or not (ICP may take a different number of iterations)
            for a, b in ((shared, one), (own, one_own)):
                for key, value in b.as_mm().items():
                    assert a.as_mm()[key][i] == pytest.approx(value, abs=1e-9), (register, key)
        assert np.shape(shared.max) == (3,)
    # ICP improves on Kabsch in its own measure; the translation search in the max.
    kab, icp, both = (metrics.shape_error(recon, TRUTH, s=s, truth_s=S_DENSE, register=r) for r in
                      ("kabsch", "icp", "icp+translation"))
    assert np.all(icp.rms <= kab.rms) and np.all(both.max <= icp.max)


def test_plane_split():
    # An arc of a circle in a tilted plane.
    phi = np.linspace(0, 2.0, 400)
    arc = np.column_stack([0.05 * np.cos(phi), 0.05 * np.sin(phi), np.zeros_like(phi)])
    R, t = rigid(10)
    truth = arc @ R.T + t
    normal = R[:, 2]
    pts = truth[5:-5:7]
    delta = 2e-4
    in_plane, out_of_plane = metrics.plane_split(pts + delta * normal, truth)
    # 1e-12 m: a pure normal offset; rounding of the plane fit and coordinates only
    np.testing.assert_allclose(out_of_plane, delta, atol=1e-12)
    np.testing.assert_allclose(in_plane, 0, atol=1e-12)
    radial = (arc[5:-5:7] / 0.05) @ R.T  # outward in the plane, the arc's principal normal
    in_plane, out_of_plane = metrics.plane_split(pts + delta * radial, truth)
    # 1e-9 m: the arc's chords sit up to a sagitta h²κ/8 = 5e-10 m inside the circle
    np.testing.assert_allclose(in_plane, delta, atol=1e-9)
    np.testing.assert_allclose(out_of_plane, 0, atol=1e-12)
    stats = metrics.shape_error(pts + delta * normal, truth[5:-5:7], truth_polyline=truth, register="none",
                                split_plane=True)
    assert stats.out_of_plane_max == pytest.approx(delta, abs=1e-12)
    assert stats.out_of_plane_mean == pytest.approx(delta, abs=1e-12)
    assert stats.in_plane_max < 1e-12
    assert set(stats.as_mm()) == {"max_error_mm", "mean_error_mm", "rms_error_mm", "tip_error_mm",
                                  "in_plane_max_error_mm", "in_plane_mean_error_mm",
                                  "out_of_plane_max_error_mm", "out_of_plane_mean_error_mm"}
    assert stats.as_mm()["out_of_plane_max_error_mm"] == pytest.approx(0.2, abs=1e-9)


# ------------------------------------------------------------------------------------------- bad input


def test_bad_input_is_named():
    good = TRUTH[::100]
    nan = good.copy()
    nan[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"kabsch\(target\): expected finite numbers, got nan at index \(2, 1\)"):
        metrics.kabsch(good, nan)
    with pytest.raises(ValueError, match=r"kabsch\(source\): expected points in m of shape \(\.\.\., n, 3\)"):
        metrics.kabsch(good[:, :2], good[:, :2])
    with pytest.raises(ValueError, match=r"n >= 3, got shape \(2, 3\)"):
        metrics.kabsch(good[:2], good[:2])
    with pytest.raises(ValueError, match="same shape"):
        metrics.kabsch(good, good[1:])
    with pytest.raises(ValueError, match="non-negative weights"):
        metrics.kabsch(good, good, -np.ones(len(good)))
    with pytest.raises(ValueError, match=r"point_to_polyline\(polyline\): .* n >= 2, got shape \(1, 3\)"):
        metrics.point_to_polyline(good, good[:1])
    with pytest.raises(ValueError, match=r"point_to_polyline\(points\): expected finite"):
        metrics.point_to_polyline(nan, good)
    with pytest.raises(ValueError, match=r"icp\(R0\): expected a rotation"):
        metrics.icp(good, TRUTH, R0=2 * np.eye(3))
    with pytest.raises(ValueError, match="odd integer"):
        metrics.translation_search(good, TRUTH, n=4)
    with pytest.raises(ValueError, match="register must be one of"):
        metrics.shape_error(good, good, register="icp-translation")
    with pytest.raises(ValueError, match=r"shape_error\(positions\): expected finite"):
        metrics.shape_error(nan, good)
    with pytest.raises(ValueError, match=r"without truth_s, expected the truth at the 18 reconstructed points"):
        metrics.shape_error(good, TRUTH)
    with pytest.raises(ValueError, match="truth_s needs s"):
        metrics.shape_error(good, TRUTH, truth_s=S_DENSE)
    with pytest.raises(ValueError, match=r"shape_error\(s\): arc lengths must lie within truth_s"):
        metrics.shape_error(good, TRUTH, s=np.linspace(0, 0.18, 18), truth_s=S_DENSE)
    with pytest.raises(ValueError, match=r"shape_error\(truth_positions\): expected one curve"):
        metrics.shape_error(np.stack([good, good]), np.stack([TRUTH] * 3), s=S_DENSE[::100], truth_s=S_DENSE)
