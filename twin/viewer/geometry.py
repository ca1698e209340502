"""What the viewer draws, as numpy arrays: tube meshes, colour maps, placement, camera framing, the scale bar.

Pure numpy (and :mod:`twin.metrics` for exact point-to-polyline distances): no meshcat, no browser, so every
piece is tested on its own. Lengths are in whatever unit the caller passes (the viewer passes metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.frames import Shape, Truth

__all__ = [
    "VIRIDIS",
    "FrameScene",
    "camera_distance",
    "colorbar_stops",
    "colormap",
    "envelope",
    "frame_scene",
    "interp_curve",
    "local_error",
    "merge_meshes",
    "nice_length",
    "placement",
    "scale_bar",
    "subsample",
    "tube_mesh",
    "view_direction",
]

#: viridis (matplotlib's default colour map) sampled at 0, 1/8, …, 1: perceptually uniform and readable
#: without colour vision; interpolated linearly between these anchors.
VIRIDIS = np.array([
    [0.267004, 0.004874, 0.329415], [0.282623, 0.140926, 0.457517], [0.229739, 0.322361, 0.545706],
    [0.172719, 0.448791, 0.557885], [0.127568, 0.566949, 0.550556], [0.157851, 0.683765, 0.501686],
    [0.369214, 0.788888, 0.382914], [0.678489, 0.863742, 0.189503], [0.993248, 0.906157, 0.143936],
])


def colormap(values, lo: float, hi: float, anchors: np.ndarray = VIRIDIS, invalid=(0.5, 0.5, 0.5)) -> np.ndarray:
    """RGB in [0, 1] (..., 3) of ``values`` mapped linearly from [lo, hi] onto the anchors (clipped).

    NaN values get ``invalid``.
    """
    if not hi > lo:
        raise ValueError(f"colormap: the range must be increasing, got ({lo}, {hi})")
    v = np.asarray(values, dtype=np.float64)
    x = np.clip((np.nan_to_num(v, nan=lo) - lo) / (hi - lo), 0.0, 1.0) * (len(anchors) - 1)
    i = np.minimum(x.astype(int), len(anchors) - 2)
    f = (x - i)[..., None]
    rgb = (1 - f) * anchors[i] + f * anchors[i + 1]
    rgb[~np.isfinite(v)] = invalid
    return rgb


def colorbar_stops(anchors: np.ndarray = VIRIDIS) -> list[str]:
    """The anchors as CSS colours ``#rrggbb``, for a gradient in the page's legend."""
    rgb = np.rint(np.clip(anchors, 0, 1) * 255).astype(int)
    return [f"#{r:02x}{g:02x}{b:02x}" for r, g, b in rgb]


# ------------------------------------------------------------------------------------------------ tubes
def _tangents(points: np.ndarray) -> np.ndarray:
    t = np.gradient(points, axis=0)
    n = np.linalg.norm(t, axis=-1, keepdims=True)
    return t / np.where(n > 0, n, 1.0)


def _perpendicular(t: np.ndarray) -> np.ndarray:
    a = np.eye(3)[int(np.argmin(np.abs(t)))]
    v = np.cross(t, a)
    return v / np.linalg.norm(v)


def _transported_normals(points: np.ndarray, tangents: np.ndarray) -> np.ndarray:
    """Rotation-minimising normals along a polyline (double reflection, Wang et al. 2008).

    A sequential recurrence, used only for curves without material frames (a fixture, the scale bar, a truth
    without frames), which are short or drawn rarely.
    """
    n = np.empty_like(points)
    r = _perpendicular(tangents[0])
    n[0] = r
    for i in range(len(points) - 1):
        v1 = points[i + 1] - points[i]
        c1 = v1 @ v1
        if c1 <= 0:
            n[i + 1] = r
            continue
        r_l = r - (2.0 / c1) * (v1 @ r) * v1
        t_l = tangents[i] - (2.0 / c1) * (v1 @ tangents[i]) * v1
        v2 = tangents[i + 1] - t_l
        c2 = v2 @ v2
        r = r_l - (2.0 / c2) * (v2 @ r_l) * v2 if c2 > 1e-30 else r_l
        n[i + 1] = r
    return n


def tube_mesh(points, radius, sides: int = 12, normals=None) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh of a tube swept along a centreline, closed by flat caps.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Centreline, n >= 2.
    radius : float or array_like, shape (n,)
        Tube radius, same unit: one for the whole tube, or one per point (a confidence tube, :func:`envelope`).
    sides : int
        Vertices per cross-section.
    normals : array_like, shape (n, 3), optional
        A direction normal to the centreline at each point (e.g. the material frame's d1), setting the
        orientation of the cross-sections; projected onto the normal plane. Without it, rotation-minimising
        frames are transported along the curve.

    Returns
    -------
    vertices : ndarray, shape (n·sides + 2·(sides + 1), 3)
        Ring vertices (ring i is rows i·sides … i·sides + sides − 1), then the two caps (centre, then a copy
        of the end ring so the caps shade flat).
    faces : ndarray of uint32, shape (2·(n − 1)·sides + 2·sides, 3)
        Triangles, wound so their normals point out of the tube.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 2:
        raise ValueError(f"tube_mesh: points must have shape (n >= 2, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("tube_mesh: points contain NaN or inf")
    r = np.asarray(radius, dtype=np.float64)
    if r.ndim and r.shape != (p.shape[0],):
        raise ValueError(f"tube_mesh: radius must be one number or one per point ({p.shape[0]}), got {r.shape}")
    if not np.all(np.isfinite(r) & (r >= 0)):
        raise ValueError("tube_mesh: radii must be finite and >= 0")
    t = _tangents(p)
    if normals is None:
        u = _transported_normals(p, t)
    else:
        u = np.asarray(normals, dtype=np.float64)
        if u.shape != p.shape:
            raise ValueError(f"tube_mesh: normals must have the shape of points {p.shape}, got {u.shape}")
        u = u - np.sum(u * t, axis=-1, keepdims=True) * t
        bad = np.linalg.norm(u, axis=-1) < 1e-9
        if bad.any():
            u[bad] = _transported_normals(p, t)[bad]
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    w = np.cross(t, u)
    phi = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
    ring = np.cos(phi)[None, :, None] * u[:, None, :] + np.sin(phi)[None, :, None] * w[:, None, :]
    rings = p[:, None, :] + (r[:, None, None] if r.ndim else r) * ring
    n = p.shape[0]
    vertices = np.concatenate([rings.reshape(-1, 3), p[:1], rings[0], p[-1:], rings[-1]])
    i = np.arange(n - 1)[:, None]
    j = np.arange(sides)[None, :]
    a = i * sides + j
    b = i * sides + (j + 1) % sides
    c = b + sides
    d = a + sides
    side_faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    jj = np.arange(sides)
    c0 = n * sides
    c1 = c0 + sides + 1
    start = np.stack([np.full(sides, c0), c0 + 1 + (jj + 1) % sides, c0 + 1 + jj], -1)
    end = np.stack([np.full(sides, c1), c1 + 1 + jj, c1 + 1 + (jj + 1) % sides], -1)
    faces = np.concatenate([side_faces, start, end]).astype(np.uint32)
    return vertices, faces


def envelope(shape: Shape, level: float, wall: float) -> np.ndarray:
    """Radius of the confidence envelope of a catheter of radius ``wall`` at each point of ``shape``:
    ``wall`` + the level-% tube radius of its centreline (:meth:`Shape.confidence`), where the catheter's wall
    lies with that confidence (the lateral error moves the whole cross-section)."""
    return wall + shape.confidence(level)


def tube_colors(ring_colors, sides: int) -> np.ndarray:
    """Per-vertex colours (as :func:`tube_mesh` lays the vertices out) from one colour per ring (n, 3)."""
    c = np.asarray(ring_colors, dtype=np.float64)
    return np.concatenate([np.repeat(c, sides, axis=0), np.repeat(c[:1], sides + 1, axis=0),
                           np.repeat(c[-1:], sides + 1, axis=0)])


def merge_meshes(*meshes: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """One mesh (vertices, faces) from several, the faces re-indexed."""
    verts, faces, offset = [], [], 0
    for v, f in meshes:
        verts.append(v)
        faces.append(np.asarray(f, dtype=np.int64) + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces).astype(np.uint32)


def nice_length(extent: float, fraction: float = 0.25) -> float:
    """A round length (1, 2 or 5 × 10^k) no longer than ``fraction`` of ``extent``: the scale bar's."""
    if not (np.isfinite(extent) and extent > 0):
        raise ValueError(f"nice_length: extent must be positive, got {extent}")
    target = fraction * extent
    k = np.floor(np.log10(target))
    for m in (5.0, 2.0, 1.0):
        if m * 10**k <= target * (1 + 1e-12):
            return float(m * 10**k)
    return float(10**k)  # pragma: no cover (m = 1 always fits)


def scale_bar(start, direction, up, length: float, radius: float, sides: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A bar of ``length`` from ``start`` along ``direction`` with end ticks along ``up`` (a mesh)."""
    a = np.asarray(start, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    u = np.asarray(up, dtype=np.float64)
    d, u = d / np.linalg.norm(d), u / np.linalg.norm(u)
    b = a + length * d
    tick = 0.12 * length
    return merge_meshes(tube_mesh(np.stack([a, b]), radius, sides),
                        tube_mesh(np.stack([a - tick * u, a + tick * u]), radius, sides),
                        tube_mesh(np.stack([b - tick * u, b + tick * u]), radius, sides))


# ------------------------------------------------------------------------------------------------ curves
def subsample(n: int, most: int) -> np.ndarray:
    """Indices of at most ``most`` evenly spread points of n, always keeping both ends."""
    if n <= most:
        return np.arange(n)
    return np.unique(np.rint(np.linspace(0, n - 1, most)).astype(int))


def interp_curve(s_new, s, points) -> np.ndarray:
    """Linear interpolation of a sampled curve (m, 3) at arc lengths ``s_new`` (clamped to its range)."""
    s_new = np.asarray(s_new, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    return np.stack([np.interp(s_new, s, pts[:, k]) for k in range(3)], axis=-1)


def local_error(points, truth_polyline, *, return_closest: bool = False):
    """Exact distance from each point (n, 3) to the truth polyline (k, 3), same unit (n,); with
    ``return_closest`` also the closest point of the polyline to each (n, 3)."""
    from twin.metrics import point_to_polyline

    return point_to_polyline(points, truth_polyline, return_closest=return_closest)


def magnification(max_error: float, target: float) -> float:
    """The factor that shows a deviation of ``max_error`` as at most ``target`` (same unit): the largest of
    1, 2, 5 × 10^k not above ``target / max_error`` (a round number a person can read), at least 1."""
    if not (np.isfinite(max_error) and max_error > 0):
        return 1.0
    ratio = target / max_error * (1 + 1e-6)  # an error a hair above a round one (rounding) keeps its factor
    if ratio <= 1:
        return 1.0
    decade = 10.0 ** np.floor(np.log10(ratio))
    return float(max(m * decade for m in (1.0, 2.0, 5.0) if m * decade <= ratio))


def nice_ceiling(value: float) -> float:
    """The smallest of 1, 2, 5 × 10^k at or above ``value`` > 0 (an axis' end)."""
    if not (np.isfinite(value) and value > 0):
        return 1.0
    decade = 10.0 ** np.floor(np.log10(value))
    return float(min(m * decade for m in (1.0, 2.0, 5.0, 10.0) if m * decade >= value * (1 - 1e-12)))


def _check_pose(base_pose) -> tuple[np.ndarray, np.ndarray]:
    try:
        R, p = base_pose
    except (TypeError, ValueError):
        raise ValueError("base_pose must be a pair (R (3, 3), p (3,))") from None
    R = np.asarray(R, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    if R.shape != (3, 3) or p.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(p))):
        raise ValueError(f"base_pose must be (R (3, 3), p (3,)) finite; got shapes {R.shape}, {p.shape}")
    return R, p


def placement(shape: Shape, truth: Truth | None = None, base_pose=None) -> tuple[np.ndarray, np.ndarray, str]:
    """Where the base frame of ``shape`` sits in the world: (R (3, 3), p (3,), how).

    ``how`` is ``"base_pose"`` (given), ``"truth_base"`` (the truth's material frame at s = 0: what a tracked
    catheter base gives), ``"kabsch"`` (rigid registration onto the truth at equal arc lengths) or
    ``"base_frame"`` (no truth: the scene is the fibre's base frame).
    """
    if base_pose is not None:
        R, p = _check_pose(base_pose)
        return R, p, "base_pose"
    if truth is None:
        return np.eye(3), np.zeros(3), "base_frame"
    ts = np.asarray(truth.s, dtype=np.float64)
    tp = np.asarray(truth.positions, dtype=np.float64)
    if truth.frames is not None and ts.size:
        i0 = int(np.argmin(np.abs(ts)))
        if abs(ts[i0]) < 1e-9:
            return np.asarray(truth.frames[i0], dtype=np.float64), tp[i0], "truth_base"
    from twin.metrics import kabsch

    inside = (shape.s >= ts.min() - 1e-12) & (shape.s <= ts.max() + 1e-12)
    if inside.sum() < 3:
        raise ValueError("the truth does not overlap the reconstruction's arc lengths; give base_pose")
    R, p = kabsch(shape.positions[inside], interp_curve(shape.s[inside], ts, tp))
    return R, p, "kabsch"


@dataclass(frozen=True, eq=False)
class FrameScene:
    """One frame as every live display shows it (the browser viewer, Foxglove), in world coordinates, m.

    Attributes
    ----------
    R, p, how :
        The placement of the fibre's base frame (:func:`placement`).
    world : ndarray (n, 3)
        The reconstruction's points.
    mode : {"error", "curvature"}
        What ``values`` are: the local error against the truth (m), else |curvature| (1/m), at each point.
    values : ndarray (n,)
    errors : dict or None
        ``max``, ``mean``, ``tip`` error against the truth, m (None without a truth).
    truth : ndarray (k, 3) or None
        The truth's finite points.
    truth_ok : ndarray of bool or None
        Which truth samples those are.
    nearest : ndarray (n, 3) or None
        The truth's closest point to each reconstructed point (None without a truth).
    markers : ndarray (g, 3)
        The gratings.
    vendor : ndarray (N, 3) or None
        The interrogator's own shape, registered onto the reconstruction and placed like it.
    vendor_errors : dict or None
        ``max``, ``mean``, ``tip`` distance between the two, m.
    """

    R: np.ndarray
    p: np.ndarray
    how: str
    world: np.ndarray
    mode: str
    values: np.ndarray
    errors: dict | None
    truth: np.ndarray | None
    truth_ok: np.ndarray | None
    nearest: np.ndarray | None
    markers: np.ndarray
    vendor: np.ndarray | None
    vendor_errors: dict | None


def frame_scene(shape: Shape, truth: Truth | None = None, vendor=None, base_pose=None,
                vendor_sensor: int = 0) -> FrameScene:
    """Place one reconstruction in the world and compute what is shown with it (:class:`FrameScene`).

    ``vendor``: a tuple of VendorSensor (sensor ``vendor_sensor`` is shown) or one VendorSensor, or None.
    """
    if shape.positions.ndim != 2:
        raise ValueError(f"one shape expected, got a batch of shape {shape.batch_shape}; index it")
    if not np.all(np.isfinite(shape.positions)):
        raise ValueError("the shape has NaN points (an unusable frame)")
    R, p, how = placement(shape, truth, base_pose)
    world = shape.positions @ R.T + p
    truth_pts = ok = errors = nearest = None
    if truth is not None:
        ts, tp = np.asarray(truth.s, dtype=np.float64), np.asarray(truth.positions, dtype=np.float64)
        ok = np.all(np.isfinite(tp), axis=1)
        truth_pts, ts = tp[ok], ts[ok]
        values, nearest = local_error(world, truth_pts, return_closest=True)
        tip = float(np.linalg.norm(world[-1] - interp_curve(shape.s[-1:], ts, truth_pts)[0]))
        errors = {"max": float(values.max()), "mean": float(values.mean()), "tip": tip}
        mode = "error"
    else:
        mode = "curvature"
        k = np.linalg.norm(np.asarray(shape.curvature, dtype=np.float64), axis=-1)
        good = np.isfinite(k)
        values = np.interp(shape.s, shape.grating_s[good], k[good]) if good.any() else np.full(len(world), np.nan)
    vendor_pts = vendor_errors = None
    block = vendor[vendor_sensor] if isinstance(vendor, tuple | list) and len(vendor) > vendor_sensor else (
        None if isinstance(vendor, tuple | list) else vendor)
    if block is not None:
        from twin.reference_errors import vendor_in_base

        moved = vendor_in_base(shape.positions, shape.s, block.positions, block.s)
        if moved is not None:  # else no overlap, or NaN points: nothing to show or report
            base, e = moved
            vendor_errors = {"max": float(e.max), "mean": float(e.mean), "tip": float(e.tip)}
            vendor_pts = base @ R.T + p
    markers = interp_curve(shape.grating_s, shape.s, world)
    return FrameScene(R, p, how, world, mode, values, errors, truth_pts, ok, nearest, markers, vendor_pts,
                      vendor_errors)


# ------------------------------------------------------------------------------------------------ camera
def view_direction(points, min_elevation_deg: float = 15.0, max_elevation_deg: float = 60.0) -> np.ndarray:
    """Unit vector from the catheter towards the camera: face-on to its best-fit plane, z up.

    The normal of the plane of the two largest principal axes shows a planar shape undistorted (and a spatial
    one at its widest); its elevation is kept within [min, max] so the grid is seen from above and the orbit
    controls' up axis (+z) never lines up with the view.
    """
    x = np.asarray(points, dtype=np.float64)
    x = x - x.mean(axis=0)
    _, sv, vt = np.linalg.svd(x, full_matrices=False)
    n = vt[-1] if sv.size == 3 else np.array([1.0, 0.0, 0.0])
    if sv.size >= 2 and sv[1] < 1e-6 * max(sv[0], 1e-30):  # a straight line: any normal; prefer horizontal
        n = np.cross(vt[0], [0.0, 0.0, 1.0])
        if np.linalg.norm(n) < 1e-9:
            n = np.array([1.0, 0.0, 0.0])
    n = n / np.linalg.norm(n)
    if n[2] < 0:
        n = -n
    h = np.hypot(n[0], n[1])
    azimuth = np.arctan2(n[1], n[0]) if h > 1e-6 else np.arctan2(vt[0][1], vt[0][0]) + np.pi / 2
    elevation = np.clip(np.arctan2(n[2], h), np.radians(min_elevation_deg), np.radians(max_elevation_deg))
    return np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])


def camera_distance(radius: float, fov_deg: float = 75.0, fill: float = 0.75) -> float:
    """Camera distance at which a sphere of ``radius`` spans ``fill`` of the view's height (same unit)."""
    return radius / (fill * np.tan(np.radians(fov_deg) / 2))
