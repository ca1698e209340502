"""Ground-truth fixtures that shape the catheter rod: connect constraints, a rigid tube of rails, a groove.

Every fixture takes a curve from :mod:`twin.shapes` (base at the origin, tangent +z, d1 = +x, 170 mm) and a
:class:`~models.catheter.Pose` that places the curve in the world. The rod (:mod:`models.catheter`) is longer
than the curve: ``base_length`` before s = 0 and ``tip_length`` after the end. The curve is continued over
those parts with its own curvature function (:class:`ExtendedCurve`), so the curvature is smooth across
s = 0 and s = L and the first and last gratings see the shape's curvature (with a constant-curvature
continuation, a vertex next to s = 0 saw up to 0.2 1/m of error from the kink in k'). The clamp sits on the
backward continuation at s = −base_length, the clamped first edge along the chord to the next vertex (the
chord is shorter than the arc by l³κ²/24, < 1 µm here).

How the rod gets into a fixture: the rod is defined straight in ``qpos0`` (its rest shape; MuJoCo keeps the
``qpos0`` curvature of a rod as its rest curvature, so the curve must not go into the flexcomp ``point``s),
then :func:`models.catheter.set_rod_positions` puts every vertex on the fixture's centreline with zero
velocity and twist-free reference frames, and the physics settles it against the constraints or walls.
Starting on the centreline means no initial penetration of the tube (the radial clearance is free all round),
no insertion transient and a settled state that is the elastic equilibrium within the clearance; it does not
reproduce the frictional history of a real insertion (a catheter pushed in may lock in a different state
within the clearance). The connect fixture starts from the same state, so it settles in a few tens of
steps (the constraints are satisfied from the start).

Settling is detected by how far the vertices move over a time window, not by velocity (low rod modes move
slowly and a velocity threshold either stops early or never), with a bounded time: :func:`settle`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import mujoco
import numpy as np
from scipy.integrate import solve_ivp
from scipy.spatial import cKDTree

from models.catheter import CatheterSpec, Pose, RodHandle, Scene, set_rod_positions
from models.rod_state import RodReader, RodState
from twin.shapes import ShapeCurve

__all__ = [
    "ConnectFixture",
    "ExtendedCurve",
    "RailSet",
    "SettleError",
    "SettleResult",
    "TubeFixture",
    "add_connect_fixture",
    "add_groove_fixture",
    "add_rails",
    "add_tube_fixture",
    "build_connect",
    "build_groove",
    "build_tube",
    "groove_pose",
    "groove_rail_offsets",
    "rod_base_pose",
    "settle",
    "tube_rail_offsets",
]


# ----------------------------------------------------------------------------------------------------
# The curve, continued beyond its ends
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ExtendedCurve:
    """A library curve continued ``before`` its start and ``after`` its end.

    Over [0, L] it is the shape itself. Beyond, the frames and positions are integrated (8th-order
    Runge–Kutta, rtol 1e-12, as :mod:`twin.shapes` does) from the end states with the continued curvature:

    * ``"natural"``: the shape's own curvature function evaluated beyond [0, L] (the library's are
      analytic), so the curvature is smooth across s = 0 and s = L and a vertex near a junction sees no kink;
      refused if it grows beyond 1.5 × the shape's largest |k| (+ 1 1/m) there;
    * ``"linear"``: k(0) + s k'(0) before, k(L) + (s − L) k'(L) after (C¹), under the same limit;
    * ``"arc"``: the constant end curvature vectors (C⁰; a discrete vertex next to the junction then sees a
      curvature error of order l |Δk'| / 8);
    * ``"auto"`` (default): the first of these three that stays within the limit (:attr:`mode` then holds the
      one chosen).

    Attributes
    ----------
    shape : ShapeCurve
    before, after : float
        Lengths of the continuations, m.
    mode : str
    """

    shape: ShapeCurve
    before: float = 0.0
    after: float = 0.0
    mode: str = "auto"

    def __post_init__(self) -> None:
        if self.before < 0 or self.after < 0:
            raise ValueError(f"ExtendedCurve({self.shape.name}): before/after must be >= 0 m")
        modes = ("natural", "linear", "arc")
        if self.mode not in (*modes, "auto"):
            raise ValueError(f"ExtendedCurve: mode must be one of {modes} or 'auto', got {self.mode!r}")
        ss = np.linspace(0.0, self.shape.length, 2001)
        limit = 1.5 * float(np.max(np.hypot(*self.shape.curvature(ss).T))) + 1.0
        ext = np.concatenate(
            [np.linspace(-self.before, 0.0, 201), np.linspace(0, self.after, 201) + self.length]
        )
        for mode in modes if self.mode == "auto" else (self.mode,):
            object.__setattr__(self, "mode", mode)
            worst = float(np.max(np.hypot(*self._k_ext(ext).T)))
            if mode == "arc" or worst <= limit:
                return
        raise ValueError(
            f"ExtendedCurve({self.name}): the curvature continued ({self.mode}) beyond the ends reaches "
            f"{worst:.1f} 1/m (limit {limit:.1f}); use a shorter continuation or mode='arc'"
        )

    @property
    def name(self) -> str:
        return self.shape.name

    @property
    def length(self) -> float:
        """Length of the original curve, m."""
        return self.shape.length

    @property
    def s_min(self) -> float:
        return -self.before

    @property
    def s_max(self) -> float:
        return self.shape.length + self.after

    def _k_ext(self, s: np.ndarray) -> np.ndarray:
        """Continued curvature vector (for s outside [0, L]; inside it is the shape's)."""
        s = np.asarray(s, dtype=np.float64)
        if self.mode == "natural":
            return self.shape.curvature(s)
        end = np.where(s < 0.5 * self.length, 0.0, self.length)
        k_end = self.shape.curvature(end)
        if self.mode == "arc":
            return k_end
        h = 1e-6
        slope = (self.shape.curvature(end + h) - self.shape.curvature(end - h)) / (2 * h)
        return k_end + (s - end)[..., None] * slope

    @cached_property
    def _ends(self):
        """Dense solutions over [−before, 0] and [L, L + after] (state: p (3), R row-major (9))."""

        def rhs(s, y):
            kx, ky = self._k_ext(np.array(s))
            r = y[3:].reshape(3, 3)
            uhat = np.array([[0.0, 0.0, kx], [0.0, 0.0, ky], [-kx, -ky, 0.0]])  # hat((−k_y, k_x, 0))
            return np.concatenate([r[:, 2], (r @ uhat).ravel()])

        out = []
        for s_end, span in ((0.0, -self.before), (self.length, self.after)):
            if span == 0.0:
                out.append(None)
                continue
            y0 = np.concatenate([self.shape.positions(s_end), self.shape.frames(s_end).ravel()])
            sol = solve_ivp(
                rhs, (s_end, s_end + span), y0, method="DOP853", rtol=1e-12, atol=1e-14, dense_output=True
            )
            if not sol.success:  # pragma: no cover - smooth right-hand sides
                raise RuntimeError(f"ExtendedCurve({self.name}): integration failed ({sol.message})")
            out.append(sol.sol)
        return tuple(out)

    def _state(self, s) -> np.ndarray:
        s = np.asarray(s, dtype=np.float64)
        if np.any((s < self.s_min - 1e-12) | (s > self.s_max + 1e-12)):
            raise ValueError(
                f"ExtendedCurve({self.name}): arc length outside [{self.s_min:.6g}, {self.s_max:.6g}] m"
            )
        flat = np.clip(s.ravel(), self.s_min, self.s_max)
        out = np.empty((flat.size, 12))
        lo, hi = flat < 0.0, flat > self.length
        mid = ~(lo | hi)
        if mid.any():
            out[mid, :3] = self.shape.positions(flat[mid])
            out[mid, 3:] = self.shape.frames(flat[mid]).reshape(-1, 9)
        for mask, sol in ((lo, self._ends[0]), (hi, self._ends[1])):
            if mask.any():
                out[mask] = sol(flat[mask]).T
        return out.reshape((*s.shape, 12))

    def curvature(self, s) -> np.ndarray:
        """(k_x, k_y) in the twist-free frame, 1/m, shape (..., 2)."""
        s = np.asarray(s, dtype=np.float64)
        inside = (s >= 0.0) & (s <= self.length)
        return np.where(inside[..., None], self.shape.curvature(np.clip(s, 0.0, self.length)), self._k_ext(s))

    def frames(self, s) -> np.ndarray:
        """Twist-free (Bishop) frames [d1 d2 d3], shape (..., 3, 3)."""
        st = self._state(s)
        return st[..., 3:].reshape((*st.shape[:-1], 3, 3))

    def positions(self, s) -> np.ndarray:
        """Centreline positions, m, shape (..., 3)."""
        return self._state(s)[..., :3]


def rod_base_pose(curve: ExtendedCurve, spec: CatheterSpec) -> Pose:
    """Clamp pose (in the curve's coordinates) that lays ``spec``'s rod along ``curve``.

    The clamp is at the curve point s = −base_length, its z axis along the chord to the next vertex (the
    clamped edge is straight), its x axis the curve's d1 at the edge midpoint made perpendicular to the chord.
    """
    s0, s1 = -spec.base_length, -spec.base_length + spec.segment_length
    p0, p1 = curve.positions(np.array([s0, s1]))
    z = (p1 - p0) / np.linalg.norm(p1 - p0)
    d1 = curve.frames(0.5 * (s0 + s1))[:, 0]
    x = d1 - z * (d1 @ z)
    x /= np.linalg.norm(x)
    return Pose(p0, np.column_stack([x, np.cross(z, x), z]))


def _rod_targets(curve: ExtendedCurve, spec: CatheterSpec, pose: Pose) -> np.ndarray:
    """World positions of the rod's vertices on the curve; the two clamped ones where the clamp puts them."""
    p = pose.apply(curve.positions(spec.vertex_s))
    base = pose @ rod_base_pose(curve, spec)
    p[0] = base.pos
    p[1] = base.pos + spec.segment_length * base.rot[:, 2]
    return p


# ----------------------------------------------------------------------------------------------------
# (a) Connect constraints
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ConnectFixture:
    """One ``<connect>`` per free rod vertex, holding it at its arc length on a curve.

    The targets live in ``mjModel.eq_data[row, 3:6]`` (world frame; the vertex anchor is the body origin), so
    the shape can change at runtime (:meth:`set_shape`, :meth:`set_targets`). Rows are found by name and
    checked to be ``mjEQ_CONNECT`` (the flexcomp's own edge-equality row also exists; never index by
    position).

    Attributes
    ----------
    name : str
    rod : RodHandle
    curve : ExtendedCurve
    pose : Pose
        Curve coordinates → world.
    vertices : ndarray of int
        Rod vertices that carry a constraint (all but the two clamped ones).
    eq_names : tuple of str
    """

    name: str
    rod: RodHandle
    curve: ExtendedCurve
    pose: Pose
    vertices: np.ndarray
    eq_names: tuple[str, ...]

    @property
    def spec(self) -> CatheterSpec:
        return self.rod.spec

    def eq_ids(self, model: mujoco.MjModel) -> np.ndarray:
        """Equality rows of this fixture, by name, checked to be connect constraints."""
        ids = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_EQUALITY, n) for n in self.eq_names])
        if np.any(ids < 0):
            raise KeyError(
                f"ConnectFixture {self.name!r}: the model lacks constraint "
                f"{self.eq_names[int(np.argmin(ids))]}"
            )
        if np.any(model.eq_type[ids] != mujoco.mjtEq.mjEQ_CONNECT):
            raise ValueError(
                f"ConnectFixture {self.name!r}: equality rows {ids} are not all connect constraints"
            )
        return ids

    def targets(
        self, shape: ShapeCurve | ExtendedCurve | None = None, pose: Pose | None = None
    ) -> np.ndarray:
        """World positions (n_vertices, 3) of the rod's vertices on ``shape`` (default: the fixture's)."""
        curve = self.curve if shape is None else self._extend(shape)
        return _rod_targets(curve, self.spec, pose or self.pose)

    def _extend(self, shape: ShapeCurve | ExtendedCurve) -> ExtendedCurve:
        if isinstance(shape, ExtendedCurve):
            return shape
        return ExtendedCurve(shape, self.curve.before, self.curve.after)

    def set_targets(self, model: mujoco.MjModel, positions: np.ndarray) -> None:
        """Write target positions (n_vertices, 3), world frame, m; the clamped vertices' rows are ignored."""
        positions = np.asarray(positions, dtype=np.float64)
        n = self.spec.n_vertices
        if positions.shape != (n, 3):
            raise ValueError(
                f"ConnectFixture {self.name!r}: expected targets of shape ({n}, 3), got {positions.shape}"
            )
        model.eq_data[self.eq_ids(model), 3:6] = positions[self.vertices]

    def set_shape(
        self, model: mujoco.MjModel, shape: ShapeCurve | ExtendedCurve, pose: Pose | None = None
    ) -> None:
        """Retarget the constraints to another curve (its clamp pose must match the rod's: same start frame
        and curvature at s = 0, or the clamped edge fights the constraints)."""
        self.set_targets(model, self.targets(shape, pose))

    def set_active(self, model: mujoco.MjModel, data: mujoco.MjData, active: bool) -> None:
        """Switch the constraints on or off (``mjData.eq_active``), e.g. to release a shaped rod."""
        data.eq_active[self.eq_ids(model)] = 1 if active else 0

    def initialize(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Write the targets and put the rod on them (zero velocity, no twist)."""
        p = self.targets()
        self.set_targets(model, p)
        set_rod_positions(model, data, p, self.rod.name)

    def errors(self, state: RodState) -> np.ndarray:
        """Distance of each rod vertex from its target on the fixture's curve, m, shape (n_vertices,)."""
        return np.linalg.norm(state.positions - self.targets(), axis=1)


def add_connect_fixture(
    scene: Scene,
    shape: ShapeCurve,
    spec: CatheterSpec | None = None,
    pose: Pose | None = None,
    name: str | None = None,
) -> ConnectFixture:
    """Add a rod and one connect constraint per free vertex holding it on ``shape`` placed by ``pose``.

    The targets are written at build time (``Scene.build`` runs :meth:`ConnectFixture.initialize`): MJCF
    cannot express a connect target on a flexcomp vertex body other than its rest position.
    """
    spec = spec or CatheterSpec()
    pose = pose or Pose()
    name = name or f"{spec.name}_connect"
    curve = ExtendedCurve(shape, spec.base_length, spec.tip_length)
    rod = scene.add_rod(spec, pose @ rod_base_pose(curve, spec))
    vertices = np.arange(2, spec.n_vertices)
    names = tuple(f"{name}_v{i}" for i in vertices)
    solref, solimp = spec.solref, spec.solimp
    scene.comment(
        f"{name}: vertices of {spec.name!r} held on shape {shape.name!r}; the targets are written to "
        "eq_data[:, 3:6] at runtime (ConnectFixture.set_targets)",
        section="equality",
    )
    for i, n in zip(vertices, names, strict=True):
        scene.add_equality(
            "connect",
            name=n,
            body1=f"{spec.name}_{i}",
            body2="world",
            anchor=(0.0, 0.0, 0.0),
            solref=solref,
            solimp=solimp,
        )
    fixture = ConnectFixture(name, rod, curve, pose, vertices, names)
    scene.on_build(fixture.initialize)
    return fixture


# ----------------------------------------------------------------------------------------------------
# (b) Tube of capsule rails, (c) groove plate
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class TubeFixture:
    """A rigid tube or groove made of straight capsule rails laid along the curve's Bishop frame.

    Rail j runs parallel to the centreline at the fixed offset ``rail_offsets[j]`` in the curve's twist-free
    frame (d1, d2), so the cross-section is the same all along the curve and the clearance is what the
    geometry says (a Frenet frame would spin the rails about the centreline wherever the torsion is high, and
    is undefined where κ = 0). Each rail is split into straight capsules with knots close enough that a chord
    departs from the curved rail by at most ``sagitta`` (reported as built).

    Attributes
    ----------
    name : str
    kind : str
        ``"tube"`` or ``"groove"``.
    rod : RodHandle
    curve : ExtendedCurve
        The fixture's centreline (curve coordinates).
    pose : Pose
        Curve coordinates → world.
    width : float
        Inner diameter of a tube, or width of a groove, m.
    rail_radius : float
        m.
    rail_offsets : ndarray, shape (n_rails, 2)
        Rail axes in (d1, d2), m.
    knots : ndarray
        Arc lengths where the rail segments meet, m.
    segments : ndarray, shape (n_rails, n_knots − 1, 2, 3)
        Capsule end points in world coordinates, m.
    sagitta : float
        Largest departure of a capsule axis from its curved rail, m (the clearance shrinks locally by ≤ this).
    """

    name: str
    kind: str
    rod: RodHandle
    curve: ExtendedCurve
    pose: Pose
    width: float
    rail_radius: float
    rail_offsets: np.ndarray
    knots: np.ndarray
    segments: np.ndarray = field(repr=False)
    sagitta: float
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def spec(self) -> CatheterSpec:
        return self.rod.spec

    @property
    def inner_diameter(self) -> float:
        return self.width

    @property
    def clearance(self) -> float:
        """Radial play of the rod's axis toward a wall: width/2 − rod radius, m (165 µm: 3 mm, 8 Fr)."""
        return 0.5 * self.width - self.spec.radius

    @property
    def max_clearance(self) -> float:
        """Largest distance the rod's axis can move from the centreline in any direction of the cross-section
        without overlapping a rail, m (inf toward an open side). For 8 rails it is reached between two rails:
        180 µm for the default tube against 165 µm toward a rail."""
        if "max_clearance" not in self._cache:
            self._cache["max_clearance"] = float(self.free_travel(np.linspace(0, 2 * np.pi, 1441)).max())
        return self._cache["max_clearance"]

    def free_travel(self, directions: np.ndarray) -> np.ndarray:
        """How far the rod's axis can move from the centreline along directions ψ (rad, in (d1, d2)), m."""
        psi = np.asarray(directions, dtype=np.float64)
        e = np.stack([np.cos(psi), np.sin(psi)], axis=-1)  # (m, 2)
        c = self.rail_offsets  # (n, 2)
        reach = self.rail_radius + self.spec.radius
        # |d e − c| = reach  →  d² − 2 d (e·c) + |c|² − reach² = 0; the first root ahead of the centre.
        b = e @ c.T
        disc = b**2 - (np.sum(c**2, axis=1) - reach**2)[None]
        with np.errstate(invalid="ignore"):
            hit = np.where((disc >= 0) & (b > 0), b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        return hit.min(axis=1)

    def centreline(self, s) -> np.ndarray:
        """Fixture centreline in world coordinates at arc lengths ``s``, m."""
        return self.pose.apply(self.curve.positions(s))

    def initialize(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Put the rod on the centreline (zero velocity, no twist); it settles against the rails."""
        set_rod_positions(model, data, _rod_targets(self.curve, self.spec, self.pose), self.rod.name)

    def cross_section_offsets(self, points: np.ndarray) -> np.ndarray:
        """Offsets (…, 2) of world points from the centreline in the fixture's (d1, d2) at the nearest
        centreline point, m (nearest point found on a 50 µm polyline, refined on its adjacent chords)."""
        if "tree" not in self._cache:
            s = np.arange(self.curve.s_min, self.curve.s_max, 5e-5)
            self._cache["tree"] = (cKDTree(self.centreline(s)), s, self.centreline(s))
        tree, s, c = self._cache["tree"]
        pts = np.asarray(points, dtype=np.float64)
        flat = pts.reshape(-1, 3)
        _, i = tree.query(flat)
        best_d = np.full(len(flat), np.inf)
        best_s = np.zeros(len(flat))
        for j0 in (np.maximum(i - 1, 0), np.minimum(i, len(c) - 2)):
            a, ab = c[j0], c[j0 + 1] - c[j0]
            t = np.clip(np.einsum("ij,ij->i", flat - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
            d = np.linalg.norm(flat - (a + t[:, None] * ab), axis=1)
            better = d < best_d
            best_d = np.where(better, d, best_d)
            best_s = np.where(better, s[j0] + t * (s[j0 + 1] - s[j0]), best_s)
        frames = self.pose.apply_frames(self.curve.frames(best_s))
        rel = flat - self.centreline(best_s)
        out = np.einsum("kij,ki->kj", frames[:, :, :2], rel)
        return out.reshape((*pts.shape[:-1], 2))

    def radial_offsets(self, points: np.ndarray) -> np.ndarray:
        """Distance of world points (…, 3) from the centreline, m."""
        return np.linalg.norm(self.cross_section_offsets(points), axis=-1)


def _knots(
    curve: ExtendedCurve, s0: float, s1: float, rail_offset: float, max_segment: float, max_sagitta: float
) -> np.ndarray:
    """Knots with chord sagitta ≤ max_sagitta on rails up to ``rail_offset`` from the centreline.

    A rail on the outside of a bend of curvature κ is longer by (1 + κR) and curves at κ/(1 + κR), so a chord
    over an arc-length step h departs from it by h² κ (1 + κR) / 8: the worst rail of the cross-section.
    """
    dense = np.linspace(s0, s1, int(np.ceil((s1 - s0) / 2e-4)) + 1)
    k = curve.curvature(dense)
    kappa = np.hypot(k[:, 0], k[:, 1])
    kr = kappa * (1.0 + kappa * rail_offset)
    knots = [s0]
    while knots[-1] < s1 - 1e-12:
        s = knots[-1]
        window = (dense >= s - 1e-12) & (dense <= s + max_segment + 1e-12)
        kmax = float(kr[window].max()) if window.any() else 0.0
        h = max_segment if kmax <= 0 else min(max_segment, math.sqrt(8.0 * max_sagitta / kmax))
        knots.append(min(s + h, s1))
    knots = np.array(knots)
    if len(knots) > 2 and knots[-1] - knots[-2] < 0.25 * (knots[-2] - knots[-3]):
        knots[-2] = 0.5 * (knots[-3] + knots[-1])  # no sliver at the end: split the last two pieces evenly
    return knots


@dataclass(frozen=True, eq=False)
class RailSet:
    """Static capsule rails laid along a curve's Bishop frame, without a rod (e.g. a sheath the catheter moves
    through; :func:`add_rails`).

    Attributes
    ----------
    name : str
        Prefix of the geoms (``<name>_r<rail>_<segment>``).
    curve : ExtendedCurve
        The centreline (curve coordinates).
    pose : Pose
        Curve coordinates → world.
    width : float
        Inner diameter (tube) or width (groove), m.
    rail_radius : float
        m.
    rail_offsets : ndarray, shape (n_rails, 2)
        Rail axes in (d1, d2), m.
    knots : ndarray
        Arc lengths where the rail segments meet, m (the rails cover [knots[0], knots[-1]]).
    segments : ndarray, shape (n_rails, n_knots − 1, 2, 3)
        Capsule end points in world coordinates, m.
    sagitta : float
        Largest departure of a capsule axis from its curved rail, m.
    """

    name: str
    curve: ExtendedCurve
    pose: Pose
    width: float
    rail_radius: float
    rail_offsets: np.ndarray
    knots: np.ndarray
    segments: np.ndarray = field(repr=False)
    sagitta: float

    @property
    def n_geoms(self) -> int:
        return int(self.segments.shape[0] * self.segments.shape[1])

    def centreline(self, s) -> np.ndarray:
        """Centreline in world coordinates at arc lengths ``s`` of the curve, m."""
        return self.pose.apply(self.curve.positions(s))


def tube_rail_offsets(inner_diameter: float, rail_radius: float = 0.5e-3, n_rails: int = 8) -> np.ndarray:
    """Axes (d1, d2) of ``n_rails`` rails of ``rail_radius`` evenly round a tube of ``inner_diameter`` (the first at
    +d1), m, shape (n_rails, 2)."""
    angles = 2 * np.pi * np.arange(n_rails) / n_rails
    return (0.5 * inner_diameter + rail_radius) * np.stack([np.cos(angles), np.sin(angles)], axis=-1)


def add_rails(
    scene: Scene,
    name: str,
    curve: ExtendedCurve,
    pose: Pose | None = None,
    *,
    width: float,
    rail_offsets: np.ndarray,
    rail_radius: float = 0.5e-3,
    s_range: tuple[float, float] | None = None,
    max_segment: float = 4e-3,
    max_sagitta: float = 10e-6,
    friction: float = 0.1,
    solref: Sequence[float] = (4e-3, 1.0),
    solimp: Sequence[float] = (0.95, 0.99, 0.001),
    margin: float = 0.0,
    rgba: str = "0.6 0.7 0.9 0.35",
    label: str | None = None,
) -> RailSet:
    """Add static capsule rails along ``curve`` (placed by ``pose``) over ``s_range`` (default: all of it).

    Rail j runs at the fixed offset ``rail_offsets[j]`` in the curve's twist-free frame (d1, d2), split into
    straight capsules whose chords depart from the curved rail by at most ``max_sagitta``. The geoms collide only
    with what has ``contype`` bits (the rod's flex), not with each other. ``solref``/``solimp`` are the contacts'
    (MuJoCo mixes them with the rod's). This is the construction of the tube and groove fixtures, usable without a
    rod, e.g. for a sheath that the catheter moves through.
    """
    pose = pose or Pose()
    s0, s1 = (curve.s_min, curve.s_max) if s_range is None else (float(s_range[0]), float(s_range[1]))
    if not (curve.s_min - 1e-12 <= s0 < s1 <= curve.s_max + 1e-12):
        raise ValueError(
            f"{name}: rail range [{s0:.6g}, {s1:.6g}] m is not inside the curve's "
            f"[{curve.s_min:.6g}, {curve.s_max:.6g}] m"
        )
    offsets = np.asarray(rail_offsets, dtype=np.float64).reshape(-1, 2)
    reach = float(np.linalg.norm(offsets, axis=1).max())
    knots = _knots(curve, s0, s1, reach, max_segment, max_sagitta)
    mids = 0.5 * (knots[1:] + knots[:-1])

    def rails_at(s):  # (n_rails, len(s), 3), curve coordinates
        f = curve.frames(s)
        return curve.positions(s)[None] + np.einsum("kij,rj->rki", f[:, :, :2], offsets)

    rails = rails_at(knots)
    sagitta = float(np.linalg.norm(rails_at(mids) - 0.5 * (rails[:, 1:] + rails[:, :-1]), axis=-1).max())
    segments = pose.apply(np.stack([rails[:, :-1], rails[:, 1:]], axis=2))
    scene.comment(
        f"{name}: {len(offsets)} rails of {2 * rail_radius * 1e3:g} mm capsules along {label or repr(curve.name)} "
        f"(Bishop frame), width {width * 1e3:g} mm, {len(knots) - 1} segments per rail, sagitta <= "
        f"{sagitta * 1e6:.1f} um"
    )
    for j in range(len(offsets)):
        for k in range(segments.shape[1]):
            scene.add_geom(
                name=f"{name}_r{j}_{k}",
                type="capsule",
                size=rail_radius,
                fromto=segments[j, k].ravel(),
                contype=0,
                conaffinity=1,
                condim=3,
                friction=(friction, 0.005, 0.0001),
                solref=tuple(solref),
                solimp=tuple(solimp),
                margin=margin,
                group=1,
                rgba=rgba,
            )
    return RailSet(name, curve, pose, width, rail_radius, offsets, knots, segments, sagitta)


def _add_rails(
    scene: Scene,
    name: str,
    kind: str,
    shape: ShapeCurve,
    spec: CatheterSpec,
    pose: Pose,
    *,
    width: float,
    rail_radius: float,
    rail_offsets: np.ndarray,
    max_segment: float,
    max_sagitta: float,
    friction: float,
    margin: float,
    rgba: str,
) -> TubeFixture:
    if width <= spec.outer_diameter:
        raise ValueError(
            f"{name}: width {width * 1e3:.3f} mm does not fit the catheter "
            f"({spec.outer_diameter * 1e3:.3f} mm)"
        )
    # The fixture covers the whole rod and 3 mm beyond the tip (the clamped, inextensible rod cannot slide
    # out by that much).
    extra = 3e-3
    curve = ExtendedCurve(shape, spec.base_length, spec.tip_length + extra)
    rod = scene.add_rod(spec, pose @ rod_base_pose(curve, spec))
    rails = add_rails(
        scene,
        name,
        curve,
        pose,
        width=width,
        rail_offsets=rail_offsets,
        rail_radius=rail_radius,
        max_segment=max_segment,
        max_sagitta=max_sagitta,
        friction=friction,
        solref=spec.solref,
        solimp=spec.contact_solimp,
        margin=margin,
        rgba=rgba,
        label=f"shape {shape.name!r}",  # the comment as before this refactor
    )
    fixture = TubeFixture(
        name, kind, rod, curve, pose, width, rail_radius, rails.rail_offsets, rails.knots, rails.segments,
        rails.sagitta,
    )
    scene.on_build(fixture.initialize)
    return fixture


def add_tube_fixture(
    scene: Scene,
    shape: ShapeCurve,
    spec: CatheterSpec | None = None,
    pose: Pose | None = None,
    *,
    name: str | None = None,
    inner_diameter: float = 3e-3,
    rail_radius: float = 0.5e-3,
    n_rails: int = 8,
    max_segment: float = 4e-3,
    max_sagitta: float = 10e-6,
    friction: float = 0.1,
    margin: float = 0.0,
) -> TubeFixture:
    """Add a rod inside a rigid tube of ``n_rails`` capsule rails following ``shape`` (placed by ``pose``).

    Defaults: the paper's printed tubes (inner diameter 3 mm) as 8 rails of 0.5 mm-radius capsules (the first
    at +d1), segments of at most 4 mm and shorter where the rail curves (chord sagitta ≤ 10 µm, against a
    radial clearance of 165 µm for an 8 Fr catheter), friction 0.1.
    """
    spec = spec or CatheterSpec()
    offsets = tube_rail_offsets(inner_diameter, rail_radius, n_rails)
    return _add_rails(
        scene,
        name or f"{spec.name}_tube",
        "tube",
        shape,
        spec,
        pose or Pose(),
        width=inner_diameter,
        rail_radius=rail_radius,
        rail_offsets=offsets,
        max_segment=max_segment,
        max_sagitta=max_sagitta,
        friction=friction,
        margin=margin,
        rgba="0.6 0.7 0.9 0.35",
    )


def groove_pose(pos: Sequence[float] = (0.0, 0.0, 0.0)) -> Pose:
    """A pose that lays a planar library curve (in its x–z plane) flat on a horizontal plate, groove open
    upward: the curve's +y (the plate normal, d2 of a planar curve) becomes world +z; the catheter runs along
    −y."""
    return Pose(pos, np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]))


def groove_rail_offsets(
    width: float, depth: float, rail_radius: float, spacing: float | None = None, lid: bool = True
) -> np.ndarray:
    """Rail axes (d1, d2) of a U-channel ``width`` wide and ``depth`` deep whose floor is at d2 = −width/2.

    Capsules ``spacing`` apart (default: touching, two rail radii) along the floor and up both walls, and
    along the top when ``lid`` is set (a cover plate). A wall of rails is scalloped: a rod of radius ρ can
    sink between two rails by (r + ρ) − √((r + ρ)² − spacing²/4), 69 µm for touching 0.5 mm rails and an 8 Fr
    catheter.
    """
    spacing = 2 * rail_radius if spacing is None else spacing

    def spaced(a, b):
        n = max(2, math.ceil((b - a) / spacing - 1e-9) + 1)
        return np.linspace(a, b, n)

    floor_y, half = -0.5 * width, 0.5 * width
    xs = spaced(-half + rail_radius, half - rail_radius)
    ys = spaced(floor_y + rail_radius, floor_y + depth - rail_radius)
    parts = [np.stack([xs, np.full_like(xs, floor_y - rail_radius)], axis=-1)]
    parts += [np.stack([np.full_like(ys, sgn * (half + rail_radius)), ys], axis=-1) for sgn in (1.0, -1.0)]
    if lid:
        parts.append(np.stack([xs, np.full_like(xs, floor_y + depth + rail_radius)], axis=-1))
    return np.concatenate(parts)


def add_groove_fixture(
    scene: Scene,
    shape: ShapeCurve,
    spec: CatheterSpec | None = None,
    pose: Pose | None = None,
    *,
    name: str | None = None,
    width: float = 3e-3,
    depth: float = 3e-3,
    rail_radius: float = 0.5e-3,
    rail_spacing: float | None = None,
    lid: bool = True,
    max_segment: float = 4e-3,
    max_sagitta: float = 10e-6,
    friction: float = 0.1,
    margin: float = 0.0,
    plate: bool = True,
) -> TubeFixture:
    """Add a rod lying in a groove plate that follows a planar ``shape``.

    The groove is a U-channel ``width`` wide and ``depth`` deep, its floor at d2 = −width/2, opening toward
    +d2 (the curve's plate normal), built from touching capsule rails along the floor and both walls
    (:func:`groove_rail_offsets`), and by default covered (``lid``: a cover plate over the groove).

    Why the cover: the catheter's weight (≈ 0.07 N/m) is tiny next to the lateral forces of a bent catheter on
    the walls, so in an open groove its height is decided by small things. Seen: with walls only at axis
    height (a half tube) a bent catheter rode over them and left (0.1 m off); with flat box walls it climbed
    out; with rail walls at 50 segments on 'tightening' it hopped 0.5 mm up into the valley between two wall
    rails or kept wandering for 10 s. With the cover the vertical play is bounded by the clearance (165 µm
    each way for 8 Fr in 3 × 3 mm) and every library planar shape settles in < 5 s. With the default pose
    (:func:`groove_pose`) the plate is horizontal and gravity holds the catheter on the floor (its axis
    165 µm below the groove's centreline). ``plate`` adds a visual (non-colliding) plate under the groove.
    """
    if not shape.planar:
        raise ValueError(f"groove fixture: shape {shape.name!r} is not planar; use a tube for spatial shapes")
    if depth < 2 * (spec or CatheterSpec()).radius:
        raise ValueError(f"groove fixture: depth {depth * 1e3:g} mm is shallower than the catheter")
    spec = spec or CatheterSpec()
    pose = pose or groove_pose()
    name = name or f"{spec.name}_groove"
    fixture = _add_rails(
        scene,
        name,
        "groove",
        shape,
        spec,
        pose,
        width=width,
        rail_radius=rail_radius,
        rail_offsets=groove_rail_offsets(width, depth, rail_radius, rail_spacing, lid),
        max_segment=max_segment,
        max_sagitta=max_sagitta,
        friction=friction,
        margin=margin,
        rgba="0.7 0.7 0.6 0.5",
    )
    if plate:
        pts = fixture.curve.positions(np.linspace(fixture.curve.s_min, fixture.curve.s_max, 200))
        lo, hi = pts.min(axis=0) - 0.01, pts.max(axis=0) + 0.01
        thickness = 2e-3
        y_top = -0.5 * width - 2 * rail_radius  # plate top under the floor rails (curve coordinates)
        centre = np.array([0.5 * (lo[0] + hi[0]), y_top - 0.5 * thickness, 0.5 * (lo[2] + hi[2])])
        scene.add_geom(
            name=f"{name}_plate",
            type="box",
            pos=pose.apply(centre),
            quat=pose.quat,
            size=(0.5 * (hi[0] - lo[0]), 0.5 * thickness, 0.5 * (hi[2] - lo[2])),
            contype=0,
            conaffinity=0,
            group=2,
            rgba="0.8 0.8 0.75 0.4",
        )
    return fixture


# ----------------------------------------------------------------------------------------------------
# One-call builders
# ----------------------------------------------------------------------------------------------------


def build_connect(
    shape: ShapeCurve, spec: CatheterSpec | None = None, pose: Pose | None = None, **scene_kw
) -> tuple[mujoco.MjModel, mujoco.MjData, ConnectFixture]:
    """Scene with the rod held on ``shape`` by connect constraints: (model, data, fixture), rod on it."""
    scene = Scene(f"connect:{shape.name}", **scene_kw)
    fixture = add_connect_fixture(scene, shape, spec, pose)
    model, data = scene.build()
    return model, data, fixture


def build_tube(
    shape: ShapeCurve, spec: CatheterSpec | None = None, pose: Pose | None = None, scene_kw=None, **tube_kw
) -> tuple[mujoco.MjModel, mujoco.MjData, TubeFixture]:
    """Scene with the rod in a capsule-rail tube along ``shape``: (model, data, fixture), rod on its axis."""
    scene = Scene(f"tube:{shape.name}", **(scene_kw or {}))
    fixture = add_tube_fixture(scene, shape, spec, pose, **tube_kw)
    model, data = scene.build()
    return model, data, fixture


def build_groove(
    shape: ShapeCurve, spec: CatheterSpec | None = None, pose: Pose | None = None, scene_kw=None, **groove_kw
) -> tuple[mujoco.MjModel, mujoco.MjData, TubeFixture]:
    """Scene with the rod in a groove plate along planar ``shape``: (model, data, fixture)."""
    scene = Scene(f"groove:{shape.name}", **(scene_kw or {}))
    fixture = add_groove_fixture(scene, shape, spec, pose, **groove_kw)
    model, data = scene.build()
    return model, data, fixture


# ----------------------------------------------------------------------------------------------------
# Settling
# ----------------------------------------------------------------------------------------------------


class SettleError(RuntimeError):
    """The model did not come to rest within the allowed time (or went unstable)."""


@dataclass(frozen=True)
class SettleResult:
    """How :func:`settle` ended.

    Attributes
    ----------
    time : float
        Simulated time spent settling, s.
    steps : int
    moved : float
        Largest vertex displacement over the last window, m.
    """

    time: float
    steps: int
    moved: float


def _model_name(model: mujoco.MjModel) -> str:
    raw = bytes(model.names[:256])
    return raw.split(b"\0", 1)[0].decode(errors="replace") or "model"


def _vertex_where(model: mujoco.MjModel, v: int) -> str:
    """'rod 'cath' vertex 35 (s = 123.0 mm)' for global flex vertex ``v`` (for error messages)."""
    f = int(np.searchsorted(model.flex_vertadr, v, side="right") - 1)
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_FLEX, f) or f"flex {f}"
    i = v - int(model.flex_vertadr[f])
    try:
        s = RodReader(model, name).s[i]
    except (KeyError, ValueError):
        return f"{name!r} vertex {i}"
    return f"rod {name!r} vertex {i} (s = {s * 1e3:.1f} mm)"


_UNSTABLE = (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
)


def settle(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    *,
    tol: float = 1e-6,
    window: float = 0.05,
    max_time: float = 10.0,
    min_time: float = 0.0,
    label: str | None = None,
    progress: Callable[[float, float], None] | None = None,
    samples: int = 5,
) -> SettleResult:
    """Step until no flex vertex moves more than ``tol`` over a ``window`` of simulated time.

    The displacement is measured from the window's start to ``samples`` evenly spaced points in it (so a mode
    whose period matches the window is not mistaken for rest).

    Parameters
    ----------
    tol : float
        m.
    window, max_time, min_time : float
        s of simulated time.
    label : str or None
        Names the fixture in errors; default: the model's name (e.g. ``tube:helix``).
    progress : callable (time s, moved m) or None
        Called after every window.

    Raises
    ------
    SettleError
        When ``max_time`` passes first (the message names the fixture, how far the vertices still moved and
        where), or when the simulation goes unstable (MuJoCo's bad-qacc/qpos/qvel warnings: MuJoCo then
        resets the state silently, which would otherwise look like rest).
    """
    label = label or _model_name(model)
    if model.nflexvert == 0:
        raise ValueError(f"settle({label}): the model has no flex vertices to watch")
    warned = [data.warning[w].number for w in _UNSTABLE]
    dt = model.opt.timestep
    per = max(1, round(window / dt / samples))
    t0, steps = data.time, 0
    moved = math.inf
    while True:
        start = data.flexvert_xpos.copy()
        moved = 0.0
        worst = 0
        for _ in range(samples):
            mujoco.mj_step(model, data, nstep=per)
            steps += per
            d = np.linalg.norm(data.flexvert_xpos - start, axis=1)
            if not np.all(np.isfinite(d)) or [data.warning[w].number for w in _UNSTABLE] != warned:
                raise SettleError(
                    f"{label}: the simulation became unstable (non-finite or reset state) at t = "
                    f"{data.time - t0:.3f} s of settling; try a smaller timestep"
                )
            i = int(np.argmax(d))
            if d[i] > moved:
                moved, worst = float(d[i]), i
        elapsed = data.time - t0
        if progress is not None:
            progress(elapsed, moved)
        if moved < tol and elapsed >= min_time:
            return SettleResult(elapsed, steps, moved)
        if elapsed >= max_time:
            raise SettleError(
                f"{label}: not settled after {elapsed:.2f} s simulated: {_vertex_where(model, worst)} "
                "still moved "
                f"{moved * 1e6:.2f} µm in the last {per * samples * dt:.3f} s "
                f"(tolerance {tol * 1e6:.3g} µm); "
                "raise max_time, loosen tol, or check the fixture"
            )
