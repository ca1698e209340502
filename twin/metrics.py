"""Registration and error metrics between a reconstructed centreline and a ground-truth curve (docs/math.md §5.2, §7.6).

* :func:`kabsch`: closed-form rigid registration on paired points (arc-length correspondences).
* :func:`point_to_polyline`: exact distance from points to a polyline (closest points on the segments).
* :func:`icp`: iterative closest point of a reconstruction to a dense ground-truth polyline.
* :func:`translation_search`: the paper's brute-force translation grid minimising the max distance.
* :func:`plane_split`: in-plane / out-of-plane parts of the error against a planar ground truth.
* :func:`shape_error`: the standard comparison of reconstructions with truth, returning :class:`ErrorStats`.

All lengths are in m. Rotations act on column vectors: a registered point is ``R @ p + t``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from scipy.spatial import cKDTree

from twin._validate import real_array

__all__ = [
    "REGISTRATIONS",
    "ErrorStats",
    "icp",
    "kabsch",
    "plane_split",
    "point_to_polyline",
    "shape_error",
    "translation_search",
]

REGISTRATIONS = ("none", "kabsch", "icp", "icp+translation")

#: Vertices queried first per point; doubled for the rare points whose result it cannot certify.
_K_NEAREST = 8
#: Query points handled at once, bounding the (points × 2k candidate segments) work arrays (30 MB at k = 8).
_CHUNK = 16384
#: Arc lengths may overshoot the truth's range by this much (rounding of s grids), m.
_S_SLACK = 1e-12


def _coords(value, name: str, *, min_points: int = 1, batched: bool = True) -> np.ndarray:
    """Checked float64 points, shape (..., n, 3) (or (n, 3) if not ``batched``) with n >= ``min_points``."""
    a = real_array(value, name)
    ok = a.ndim >= 2 if batched else a.ndim == 2
    if not ok or a.shape[-1] != 3 or a.shape[-2] < min_points:
        want = "(..., n, 3)" if batched else "(n, 3)"
        raise ValueError(f"{name}: expected points in m of shape {want} with n >= {min_points}, "
                         f"got shape {a.shape}")
    return a


def _apply(R: np.ndarray, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """R @ x_i + t for stacks: R (..., 3, 3), t (..., 3), x (..., n, 3)."""
    return x @ np.swapaxes(R, -1, -2) + t[..., None, :]


# --------------------------------------------------------------------------------------------------- Kabsch


def _kabsch(source: np.ndarray, target: np.ndarray, w: np.ndarray | None = None):
    if w is None:
        w = np.ones(source.shape[:-1])
    w = w / w.sum(axis=-1, keepdims=True)
    mu_s = np.einsum("...n,...ni->...i", w, source)
    mu_t = np.einsum("...n,...ni->...i", w, target)
    h = np.einsum("...ni,...n,...nj->...ij", source - mu_s[..., None, :], w, target - mu_t[..., None, :])
    u, _, vt = np.linalg.svd(h)
    # R = V D Uᵀ: D flips the singular vector of the smallest singular value when V Uᵀ is a reflection.
    vt[..., 2, :] *= np.sign(np.linalg.det(u) * np.linalg.det(vt))[..., None]
    R = np.swapaxes(u @ vt, -1, -2)
    return R, mu_t - np.einsum("...ij,...j->...i", R, mu_s)


def kabsch(source, target, weights=None) -> tuple[np.ndarray, np.ndarray]:
    """Proper rigid motion best mapping ``source`` onto ``target`` (paired points) in the least-squares sense.

    Minimises Σ_i w_i |R source_i + t − target_i|² over rotations R (det R = +1, never a reflection) and
    translations t, by SVD of the weighted cross-covariance with the determinant correction.

    Parameters
    ----------
    source, target : array_like, shape (..., n, 3)
        Paired points (e.g. the same arc lengths on both curves), m; n >= 3. Leading axes are a batch.
        Collinear points fix R only up to a rotation about their line.
    weights : array_like, shape broadcastable to (..., n), optional
        Non-negative weights with a positive sum per curve; uniform by default.

    Returns
    -------
    R : ndarray, shape (..., 3, 3)
        Rotation matrix.
    t : ndarray, shape (..., 3)
        Translation, m.
    """
    src = _coords(source, "kabsch(source)", min_points=3)
    tgt = _coords(target, "kabsch(target)", min_points=3)
    if src.shape != tgt.shape:
        raise ValueError(f"kabsch: source and target must be paired points of the same shape, "
                         f"got {src.shape} and {tgt.shape}")
    w = None
    if weights is not None:
        w = real_array(weights, "kabsch(weights)")
        try:
            w = np.broadcast_to(w, src.shape[:-1])
        except ValueError:
            raise ValueError(f"kabsch(weights): expected shape broadcastable to {src.shape[:-1]}, "
                             f"got {w.shape}") from None
        if np.any(w < 0) or np.any(w.sum(axis=-1) <= 0):
            raise ValueError("kabsch(weights): expected non-negative weights with a positive sum per curve")
    return _kabsch(src, tgt, w)


# ------------------------------------------------------------------------------------- point to polyline


class _Polyline:
    """A polyline with a k-d tree on its vertices, answering exact closest-point queries."""

    def __init__(self, vertices: np.ndarray) -> None:
        self.tree = cKDTree(vertices)
        self.n = len(vertices)
        self.start = vertices[:-1]
        self.edge = np.diff(vertices, axis=0)
        self.len2 = np.einsum("ij,ij->i", self.edge, self.edge)
        self.quarter_h2 = self.len2.max() / 4

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (...) and closest points (..., 3) on the polyline for points (..., 3)."""
        p = points.reshape(-1, 3)
        dist, near = np.empty(len(p)), np.empty_like(p)
        for lo in range(0, len(p), _CHUNK):
            dist[lo : lo + _CHUNK], near[lo : lo + _CHUNK] = self._closest(p[lo : lo + _CHUNK])
        return dist.reshape(points.shape[:-1]), near.reshape(points.shape)

    def _closest(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dist, near = np.empty(len(p)), np.empty_like(p)
        todo, k = np.arange(len(p)), min(_K_NEAREST, self.n)
        while todo.size:
            q = p[todo]
            r, j = self.tree.query(q, k=k)
            # The segments on both sides of each of the k nearest vertices.
            seg = np.clip(np.concatenate([j - 1, j], axis=1), 0, self.n - 2)
            a, e, l2 = self.start[seg], self.edge[seg], self.len2[seg]
            num = np.einsum("mkj,mkj->mk", q[:, None, :] - a, e)
            u = np.clip(np.divide(num, l2, out=np.zeros_like(num), where=l2 > 0), 0.0, 1.0)
            cand = a + u[..., None] * e
            d = np.linalg.norm(q[:, None, :] - cand, axis=-1)
            best = np.argmin(d, axis=1)
            rows = np.arange(len(q))
            dist[todo], near[todo] = d[rows, best], cand[rows, best]
            # Certificate: a segment nearer than d* has an endpoint within √(d*² + h²/4) of the point (h the
            # longest segment). If the k-th nearest vertex lies beyond that, every such endpoint was tested.
            done = (r[:, -1] ** 2 >= dist[todo] ** 2 + self.quarter_h2) | (k == self.n)
            todo, k = todo[~done], min(2 * k, self.n)
        return dist, near


def point_to_polyline(points, polyline, *, return_closest: bool = False) -> np.ndarray | tuple[np.ndarray, ...]:
    """Exact distance from points to a polyline (its segments, not just its vertices).

    The nearest vertices are found with a k-d tree and the segments on both sides of each are tested: the
    distance to the nearest vertex alone is biased up by as much as half a segment (docs/math.md §5.2). The nearest
    vertex need not neighbour the nearest segment where the polyline folds back closely on itself, so several
    vertices are tested, and their number is doubled for any point where a nearer segment cannot be ruled out
    (a segment nearer than d has an endpoint within √(d² + h_max²/4)). The result is therefore exact up to
    rounding for any polyline, folded or not; the cost grows only where folds come closer than a segment.

    Parameters
    ----------
    points : array_like, shape (..., 3)
        Query points, m.
    polyline : array_like, shape (k, 3)
        Vertices in order, m; k >= 2. Repeated vertices are allowed.
    return_closest : bool
        Also return the closest point on the polyline to each query point.

    Returns
    -------
    distances : ndarray, shape (...)
        m.
    closest : ndarray, shape (..., 3)
        Only with ``return_closest``; m.
    """
    p = real_array(points, "point_to_polyline(points)")
    if p.ndim < 1 or p.shape[-1] != 3:
        raise ValueError(f"point_to_polyline(points): expected points in m of shape (..., 3), "
                         f"got shape {p.shape}")
    index = _Polyline(_coords(polyline, "point_to_polyline(polyline)", min_points=2, batched=False))
    dist, near = index.closest(p)
    return (dist, near) if return_closest else dist


# ------------------------------------------------------------------------------------------ ICP and grid


def icp(
    points, polyline, R0=None, t0=None, max_iter: int = 50, tol: float = 1e-9
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Iterative closest point registration of point sets to a dense ground-truth polyline.

    Each iteration finds the closest point on the polyline's segments (:func:`point_to_polyline`) to every
    registered point and re-solves :func:`kabsch` from the original points to those closest points, so it
    descends Σ_i d_i², the squared point-to-polyline distances. ICP finds the nearest local minimum: start it
    from Kabsch on arc-length correspondences (docs/math.md §5.2), since arcs can slide along themselves.

    Convergence is linear. It is fast where the curve's shape pins the motion, but motions that slide the
    curve along itself (for arcs and helices, opposed only by the two ends) shrink by just a few per cent per
    iteration; the distances converge sooner than the pose. Raise ``max_iter`` when the pose itself matters.

    Parameters
    ----------
    points : array_like, shape (..., n, 3)
        Points to register (a reconstruction), m; n >= 3. Leading axes are a batch, all against ``polyline``.
    polyline : array_like, shape (k, 3)
        Dense ground truth, m; k >= 2.
    R0 : array_like, shape broadcastable to (..., 3, 3), optional
        Initial rotation; identity by default.
    t0 : array_like, shape broadcastable to (..., 3), optional
        Initial translation, m; zero by default.
    max_iter : int
        Iterations at most. Reaching it is not an error: the last estimate is returned.
    tol : float
        Stop once an iteration moves no point by more than this, m.

    Returns
    -------
    R : ndarray, shape (..., 3, 3)
    t : ndarray, shape (..., 3)
        m; the registered points are ``points @ R.T + t``.
    distances : ndarray, shape (..., n)
        Point-to-polyline distance of each registered point, m.
    """
    x = _coords(points, "icp(points)", min_points=3)
    index = _Polyline(_coords(polyline, "icp(polyline)", min_points=2, batched=False))
    batch = x.shape[:-2]
    R = np.eye(3) if R0 is None else real_array(R0, "icp(R0)")
    t = np.zeros(3) if t0 is None else real_array(t0, "icp(t0)")
    try:
        R, t = np.broadcast_to(R, (*batch, 3, 3)), np.broadcast_to(t, (*batch, 3))
    except ValueError:
        raise ValueError(f"icp: R0 and t0 must broadcast to {(*batch, 3, 3)} and {(*batch, 3)}, "
                         f"got {R.shape} and {t.shape}") from None
    if not np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-9) or np.any(np.linalg.det(R) < 0):
        raise ValueError("icp(R0): expected a rotation matrix (orthonormal, det +1)")
    moved = _apply(R, t, x)
    for _ in range(max_iter):
        R, t = _kabsch(x, index.closest(moved)[1])
        new = _apply(R, t, x)
        step = np.max(np.linalg.norm(new - moved, axis=-1))
        moved = new
        if step <= tol:
            break
    return R, t, index.closest(moved)[0]


def _best_on_grid(x: np.ndarray, index: _Polyline, centre: np.ndarray, radius: float, n: int):
    """The translation among centre + an n³ grid over ±radius minimising the max distance of x (..., P, 3)."""
    axis = np.linspace(-radius, radius, n)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    trial = centre[..., None, :] + grid  # (..., G, 3)
    worst = index.closest(x[..., None, :, :] + trial[..., None, :])[0].max(axis=-1)  # (..., G)
    best = np.argmin(worst, axis=-1)[..., None]
    return np.take_along_axis(trial, best[..., None], -2)[..., 0, :], np.take_along_axis(worst, best, -1)[..., 0]


def translation_search(
    points, polyline, radius: float = 0.5e-3, n: int = 5, *, refine: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force translation minimising the max point-to-polyline distance (the paper's metric, docs/math.md §5.2).

    Tries every translation of an n³ grid over ±``radius`` on each axis (the paper: 5³ over ±0.5 mm, after
    ICP) and keeps the one with the smallest max distance. ``n`` is odd, so the grid holds the zero
    translation and the search never makes the max worse. ``refine`` repeats the search on an n³ grid spanning
    one coarse grid step on each side of the best translation. Use it to report the paper's metric, not to
    register.

    Parameters
    ----------
    points : array_like, shape (..., n_points, 3)
        Registered points, m. Leading axes are a batch, all against ``polyline``.
    polyline : array_like, shape (k, 3)
        Dense ground truth, m; k >= 2.
    radius : float
        Half-width of the grid, m.
    n : int
        Grid points per axis, odd, >= 3.
    refine : bool
        Search a second, finer grid around the best translation.

    Returns
    -------
    translation : ndarray, shape (..., 3)
        Best translation, m, to add to ``points``.
    max_distance : ndarray, shape (...)
        Max point-to-polyline distance after that translation, m.
    """
    x = _coords(points, "translation_search(points)")
    index = _Polyline(_coords(polyline, "translation_search(polyline)", min_points=2, batched=False))
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"translation_search: radius must be a positive length in m, got {radius}")
    if int(n) != n or n < 3 or n % 2 == 0:
        raise ValueError(f"translation_search: n must be an odd integer >= 3 (the grid holds zero), got {n}")
    t, worst = _best_on_grid(x, index, np.zeros((*x.shape[:-2], 3)), radius, int(n))
    if refine:
        t, worst = _best_on_grid(x, index, t, 2 * radius / (n - 1), int(n))
    return t, worst


# ---------------------------------------------------------------------------------------------- errors


@dataclass(frozen=True, eq=False)
class ErrorStats:
    """Shape error of a reconstruction against truth, m.

    Each attribute is a float for one curve, or an array of the batch shape for a stack of curves.

    Attributes
    ----------
    max, mean, rms : float or ndarray
        Max, mean and root-mean-square point-to-polyline distance of the registered points to the truth, m.
    tip : float or ndarray
        Distance from the registered reconstructed tip (last point) to the truth at the same arc length, m.
    in_plane_max, in_plane_mean, out_of_plane_max, out_of_plane_mean : float or ndarray or None
        Max and mean of the error's components in and normal to the plane of a planar truth
        (:func:`plane_split`), m; None unless asked for.
    """

    max: float | np.ndarray
    mean: float | np.ndarray
    rms: float | np.ndarray
    tip: float | np.ndarray
    in_plane_max: float | np.ndarray | None = None
    in_plane_mean: float | np.ndarray | None = None
    out_of_plane_max: float | np.ndarray | None = None
    out_of_plane_mean: float | np.ndarray | None = None

    def as_mm(self) -> dict[str, float | list]:
        """The statistics in mm for humans and JSON: ``max_error_mm``, ``mean_error_mm``, ``rms_error_mm``,
        ``tip_error_mm`` and, when present, ``in_plane_max_error_mm`` etc. Lists for a batch."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        return {f"{k}_error_mm": (np.asarray(v) * 1e3).tolist() for k, v in values.items() if v is not None}


def _plane_normal(polyline: np.ndarray) -> np.ndarray:
    """Unit normal (..., 3) of the least-squares plane through the vertices (..., k, 3)."""
    return np.linalg.svd(polyline - polyline.mean(axis=-2, keepdims=True), full_matrices=False)[2][..., -1, :]


def _split(error: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    normal_part = np.sum(error * normal, axis=-1)
    return np.linalg.norm(error - normal_part[..., None] * normal, axis=-1), np.abs(normal_part)


def plane_split(points, truth_polyline) -> tuple[np.ndarray, np.ndarray]:
    """Split each point's error into its parts in and normal to the plane of a planar truth.

    The plane is the least-squares plane through the truth's vertices (SVD of the centred vertices; a straight
    truth has no unique plane). The error vector of a point runs from its closest point on the truth polyline
    (:func:`point_to_polyline`) to the point; its component along the plane normal is the out-of-plane error,
    the rest the in-plane error, so in_plane² + out_of_plane² = distance².

    Parameters
    ----------
    points : array_like, shape (..., 3)
        Registered points, m.
    truth_polyline : array_like, shape (k, 3)
        Planar ground truth, m; k >= 2.

    Returns
    -------
    in_plane, out_of_plane : ndarray, shape (...)
        Non-negative lengths, m.
    """
    _, near = point_to_polyline(points, truth_polyline, return_closest=True)
    normal = _plane_normal(np.asarray(truth_polyline, dtype=np.float64))
    return _split(np.asarray(points, dtype=np.float64) - near, normal)


def _closest(x: np.ndarray, polyline: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return point_to_polyline(x, polyline, return_closest=True)


def _each_truth(fn, x: np.ndarray, polyline: np.ndarray, *args: np.ndarray) -> tuple:
    """``fn(x, polyline, *args)`` at once when the batch x (..., n, 3) shares one polyline (k, 3), frame by
    frame (a k-d tree each) when each frame has its own (..., k, 3). ``args`` are per-frame arrays (..., *)."""
    if polyline.ndim == 2:
        return fn(x, polyline, *args)
    batch = x.shape[:-2]
    flat = [a.reshape(-1, *a.shape[len(batch) :]) for a in (x, polyline, *args)]
    rows = [fn(*frame) for frame in zip(*flat, strict=True)]
    return tuple(np.stack(r).reshape(*batch, *np.shape(r[0])) for r in zip(*rows, strict=True))


def _truth(value, name: str, batch: tuple[int, ...]) -> np.ndarray:
    a = _coords(value, f"shape_error({name})", min_points=2)
    if a.ndim > 2 and a.shape[:-2] != batch:
        raise ValueError(f"shape_error({name}): expected one curve (m, 3) or one per reconstruction "
                         f"{(*batch, 'm', 3)}, got shape {a.shape}")
    return a


def _at_arc_length(truth: np.ndarray, truth_s, s, n: int) -> np.ndarray:
    """Truth (..., m, 3) sampled at arc lengths s (n,) by linear interpolation in truth_s (m,)."""
    ts = real_array(truth_s, "shape_error(truth_s)", shape=(truth.shape[-2],), unit="m")
    if np.any(np.diff(ts) <= 0):
        raise ValueError("shape_error(truth_s): expected strictly increasing arc lengths in m")
    sv = real_array(s, "shape_error(s)", shape=(n,), unit="m")
    if sv.min() < ts[0] - _S_SLACK or sv.max() > ts[-1] + _S_SLACK:
        raise ValueError(f"shape_error(s): arc lengths must lie within truth_s, [{ts[0]}, {ts[-1]}] m; got "
                         f"[{sv.min()}, {sv.max()}] m")
    j = np.clip(np.searchsorted(ts, sv, side="right") - 1, 0, ts.size - 2)
    f = ((np.clip(sv, ts[0], ts[-1]) - ts[j]) / (ts[j + 1] - ts[j]))[:, None]
    return truth[..., j, :] * (1 - f) + truth[..., j + 1, :] * f


def _has_points(value) -> bool:
    """A Shape or a Truth (anything with ``positions`` and ``s``), as opposed to an array of points."""
    return hasattr(value, "positions") and hasattr(value, "s")


def shape_error(
    positions,
    truth_positions,
    *,
    s=None,
    truth_s=None,
    register: str = "kabsch",
    truth_polyline=None,
    split_plane: bool = False,
) -> ErrorStats:
    """Error of reconstructed centrelines against the truth, after a rigid registration (docs/math.md §7.6).

    1. **Correspondences.** With ``truth_s``, the truth is interpolated linearly at the reconstruction's arc
       lengths ``s`` (fine for a dense truth). Without it, ``truth_positions`` must already be sampled at the
       reconstructed points (same number of points, paired in order) and ``s`` is not used.
    2. **Registration** (``register``), a rigid motion applied to the reconstruction:

       * ``"none"``: none; reconstruction and truth are already in the same frame.
       * ``"kabsch"`` (default): the closed-form rigid motion minimising the summed squared distance between
         paired points (:func:`kabsch`). Smooth in the shape, so it is also what identification uses.
       * ``"icp"``: the Kabsch result refined by :func:`icp` against the truth polyline, minimising the summed
         squared point-to-polyline distance; the pairing only initialises it, so an arc-length offset of the
         truth costs less.
       * ``"icp+translation"``: ``"icp"``, then :func:`translation_search` (5³ grid over ±0.5 mm) minimising
         the max distance: the paper's registration, for reporting its metric.
    3. **Errors.** Exact distances from the registered points to the truth polyline
       (:func:`point_to_polyline`) give max, mean and RMS; the tip error is the distance from the registered
       last point to its paired truth point (the truth at the same arc length). ``split_plane`` adds
       :func:`plane_split` statistics.

    Parameters
    ----------
    positions : array_like, shape (..., n, 3), or Shape
        Reconstructed centrelines, m; n >= 3. Leading axes are a batch (vectorised, except ICP and the
        translation search against per-frame truths, which loop over frames). A :class:`twin.Shape` (one or a
        batch) gives its positions and, unless ``s`` is given, its arc lengths.
    truth_positions : array_like, shape (m, 3) or (..., m, 3), or Truth
        The truth, m: one curve for the whole batch or one per reconstruction. A :class:`twin.frames.Truth`
        gives its positions and, unless ``truth_s`` is given, its arc lengths (used when ``s`` is known), so
        ``shape_error(shape, frame.truth)`` pairs the two at equal arc length.
    s : array_like, shape (n,), optional
        Arc length of each reconstructed point, m; needed with ``truth_s``.
    truth_s : array_like, shape (m,), optional
        Arc length of each truth point, m, strictly increasing and covering ``s``.
    register : {"none", "kabsch", "icp", "icp+translation"}
    truth_polyline : array_like, shape (k, 3) or (..., k, 3), optional
        Dense truth for the distances, m; ``truth_positions`` by default. Pass it when ``truth_positions`` is
        sampled only at the reconstructed points: a coarse polyline cuts corners by up to h²κ/8 (docs/math.md
        §5.2).
    split_plane : bool
        Also report in-plane and out-of-plane errors against the plane of a planar truth.

    Returns
    -------
    ErrorStats
        Floats for one curve, arrays of the batch shape for a stack.
    """
    if register not in REGISTRATIONS:
        raise ValueError(f"shape_error: register must be one of {', '.join(REGISTRATIONS)}; got {register!r}")
    # a Shape and a Truth (twin.frames) carry their own arc lengths: ``shape_error(shape, frame.truth)``
    if _has_points(positions):
        s = positions.s if s is None else s
        positions = positions.positions
    if _has_points(truth_positions):
        if truth_s is None and s is not None:
            truth_s = truth_positions.s
        truth_positions = truth_positions.positions
    x = _coords(positions, "shape_error(positions)", min_points=3)
    batch, n = x.shape[:-2], x.shape[-2]
    truth = _truth(truth_positions, "truth_positions", batch)
    polyline = truth if truth_polyline is None else _truth(truth_polyline, "truth_polyline", batch)
    if truth_s is not None:
        if s is None:
            raise ValueError("shape_error: truth_s needs s, the arc length of each reconstructed point in m")
        paired = _at_arc_length(truth, truth_s, s, n)
    elif truth.shape[-2] == n:
        paired = truth
    else:
        raise ValueError(f"shape_error(truth_positions): without truth_s, expected the truth at the {n} "
                         f"reconstructed points, got {truth.shape[-2]} points")
    paired = np.broadcast_to(paired, x.shape)
    if register != "none":
        R, t = _kabsch(x, paired)
        if register != "kabsch":
            R, t, _ = _each_truth(icp, x, polyline, R, t)
        x = _apply(R, t, x)
        if register == "icp+translation":
            x = x + _each_truth(translation_search, x, polyline)[0][..., None, :]
    d, near = _each_truth(_closest, x, polyline)
    split = {}
    if split_plane:
        in_plane, out_of_plane = _split(x - near, _plane_normal(polyline)[..., None, :])
        split = {"in_plane_max": in_plane.max(axis=-1), "in_plane_mean": in_plane.mean(axis=-1),
                 "out_of_plane_max": out_of_plane.max(axis=-1),
                 "out_of_plane_mean": out_of_plane.mean(axis=-1)}
    return ErrorStats(max=d.max(axis=-1), mean=d.mean(axis=-1), rms=np.sqrt(np.mean(d**2, axis=-1)),
                      tip=np.linalg.norm(x[..., -1, :] - paired[..., -1, :], axis=-1), **split)
