"""Sheath setups: the catheter inserted, withdrawn and rotated through a rigid sheath by a driven hub.

The paper's dynamic experiments (Al-Ahmad et al. §IV-B, docs/simulation.md §7) move the catheter through
sheaths: rotation inside a pre-bent 8 Fr sheath, in-and-out cycles to a reference point, and a push through a
510 mm rigid printed sheath. Here each is a :class:`SheathSetup`:

* the **sheath** is a rigid tube of 8 capsule rails along a curve (:func:`models.fixtures.add_rails`, the
  construction of the tube fixture), described by a :class:`SheathGeometry`: a straight proximal *guide*
  followed by bends of given radius, angle and bend direction, with curvature changes smoothed over ``ramp``.
  Each rail chord is the longest that stays within 10 µm of its rail, so a straight stretch is one capsule per
  rail (the same solid as 4 mm pieces, without a second contact at every knot: docs/simulation.md §5);
* the catheter's proximal end (the rod's clamp) hangs from a **hub** body with a slide joint along the guide's
  axis (insertion and withdrawal) and a hinge about it (rotation), each driven by a MuJoCo position actuator
  (docs/simulation.md §5: this works, and MuJoCo 4.0 may print "Flex stiffness is too ill-conditioned …" and carry
  on). :meth:`SheathSetup.actuate` writes the actuators' set points from a :class:`Motion` (waypoints with
  trapezoidal velocity profiles) before every physics step.

Simplifications (what the model leaves out, and why it is enough):

* **Only the distal catheter is modelled**: base (10 mm) + sensed (170 mm) + tip (15 mm), 100 segments. The
  proximal shaft is replaced by the hub, which runs along the sheath's straight guide: a real shaft inside a
  rigid sheath is held on the centreline within the clearance, so what reaches the modelled part is the hub's
  insertion and roll. The hub therefore must stay in the straight guide (checked), and the torsional wind-up and
  axial compliance of a metre of proximal shaft are not modelled (the hub's roll reaches the fibre base through
  10 mm of shaft).
* The rails cover only the part of the sheath the rod can reach during the run (± 5 mm); the rest of the sheath
  cannot touch it. The whole centreline is the fixture of the truth (:meth:`SheathSetup.fixture_centreline`).
* The rod is inextensible (edge equality), so compression shows as bending and buckling within the clearance,
  not as axial strain; the optics see no common-mode compression strain.
* Quasi-static scaling of :class:`models.catheter.CatheterSpec` (mass ×100, gravity ×1/100): at the hand speeds
  used here (≤ 50 mm/s, ≤ 90 °/s) the inertial forces stay far below the elastic and friction forces.
* Friction μ is one Coulomb coefficient for the rod–rail contacts (default 0.2; MuJoCo takes the larger of the
  two geoms' values, both are set to μ).

The fibre's arc length s (s = 0 at the first grating) moves through the sheath: at hub insertion d the fibre
point s sits near the sheath arc length u = hub_start + d + base_length + s.

Why one module of this size: the sheath's geometry, its rails and the three motions through it (rotate, cycle,
path) share one model and one drive; they are one setup family.
"""

from __future__ import annotations

import bisect
import math
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from models.catheter import CatheterSpec, Pose, Scene, set_rod_positions
from models.fixtures import ExtendedCurve, RailSet, add_rails, settle, tube_rail_offsets
from sim_interrogator.setups import Setup
from twin.shapes import ShapeCurve

__all__ = [
    "SHEATH_8FR_ID",
    "Motion",
    "Section",
    "SheathCycle",
    "SheathGeometry",
    "SheathPath",
    "SheathRotate",
    "SheathSetup",
    "pre_bent_sheath",
    "vascular_sheath",
]

#: m, inner diameter of an 8 Fr sheath taking an 8 Fr catheter (2.67 mm outer): 65 µm radial clearance.
SHEATH_8FR_ID = 2.8e-3

#: Rotation of the sheath's coordinates into the world: the guide (curve +z) runs along world +x, the curve's d1
#: along world +y (bends with direction 0 are horizontal) and d2 up (direction π/2 bends upward).
HORIZONTAL = Pose(np.zeros(3), np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))


# ----------------------------------------------------------------------------------------------------
# Geometry
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Section:
    """One piece of a sheath centreline.

    Attributes
    ----------
    length : float
        Arc length, m.
    curvature : float
        1/m; 0 for a straight piece.
    direction : float
        Bend direction about the tangent, measured from the twist-free frame's d1, rad.
    """

    length: float
    curvature: float = 0.0
    direction: float = 0.0

    @classmethod
    def bend(cls, radius: float, angle: float, direction: float = 0.0) -> Section:
        """A bend of ``radius`` (m) through ``angle`` (rad) toward ``direction`` (rad)."""
        if not (radius > 0 and angle > 0):
            raise ValueError(f"Section.bend: radius and angle must be > 0, got {radius} m, {angle} rad")
        return cls(radius * angle, 1.0 / radius, direction)

    @property
    def angle(self) -> float:
        """Turning angle, rad."""
        return self.length * self.curvature


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True)
class SheathGeometry:
    """A rigid sheath: its centreline as straight and bent sections, and its bore.

    The first section is the straight guide the hub slides in. The curvature vector is piecewise constant over
    the sections with each change smoothed over ``ramp`` (a C¹ smoothstep centred on the junction), so every
    section keeps its turning angle; the centreline starts at the origin with tangent +z and d1 = +x (the
    :mod:`twin.shapes` convention) and is placed in the world by the setup.

    Attributes
    ----------
    name : str
    sections : tuple of Section
    inner_diameter : float
        m.
    ramp : float
        Length over which the curvature changes at a junction, m.
    """

    name: str
    sections: tuple[Section, ...]
    inner_diameter: float = 3e-3
    ramp: float = 5e-3

    def __post_init__(self) -> None:
        if not self.sections:
            raise ValueError(f"sheath {self.name!r}: no sections")
        if self.sections[0].curvature != 0.0:
            raise ValueError(f"sheath {self.name!r}: the first section is the hub's guide and must be straight")
        for i, sec in enumerate(self.sections):
            if not (math.isfinite(sec.length) and sec.length > 0 and math.isfinite(sec.curvature)
                    and sec.curvature >= 0):
                raise ValueError(f"sheath {self.name!r}: section {i} needs length > 0 m and curvature >= 0 1/m, "
                                 f"got {sec}")
        if not (self.inner_diameter > 0 and self.ramp >= 0):
            raise ValueError(f"sheath {self.name!r}: inner_diameter must be > 0 and ramp >= 0 m")
        if self.ramp > min(s.length for s in self.sections):
            raise ValueError(f"sheath {self.name!r}: ramp {self.ramp * 1e3:g} mm is longer than a section")

    @property
    def length(self) -> float:
        """m."""
        return float(sum(s.length for s in self.sections))

    @property
    def guide_length(self) -> float:
        """Length of the straight guide where the curvature is exactly 0, m (the hub must stay in it)."""
        return self.sections[0].length - 0.5 * self.ramp

    @cached_property
    def _table(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ends = np.cumsum([s.length for s in self.sections])
        starts = ends - np.array([s.length for s in self.sections])
        k = np.array([[s.curvature * math.cos(s.direction), s.curvature * math.sin(s.direction)]
                      for s in self.sections])
        return starts, ends, k

    def curvature(self, s) -> np.ndarray:
        """Curvature vector (k_x, k_y) of the centreline in its twist-free frame, 1/m, shape (..., 2); 0 beyond
        the ends (a straight continuation)."""
        s = np.asarray(s, dtype=np.float64)
        starts, ends, k = self._table
        out = np.zeros((*s.shape, 2))
        r = max(self.ramp, 1e-9)
        for a, b, kv in zip(starts, ends, k, strict=True):
            if not kv.any():
                continue
            w = _smoothstep((s - a) / r + 0.5) - _smoothstep((s - b) / r + 0.5)
            out += w[..., None] * kv
        return out

    @cached_property
    def shape(self) -> ShapeCurve:
        """The centreline as a :class:`twin.shapes.ShapeCurve` (positions and Bishop frames)."""
        planar = all(s.curvature == 0 or abs(math.sin(s.direction)) < 1e-12 for s in self.sections)
        return ShapeCurve(self.name, planar, self.curvature, f"sheath {self.name}", self.length)

    @property
    def max_curvature(self) -> float:
        """Largest curvature of the centreline, 1/m."""
        return max(s.curvature for s in self.sections)

    def describe(self) -> dict:
        return {
            "name": self.name,
            "length_m": self.length,
            "inner_diameter_m": self.inner_diameter,
            "guide_length_m": self.sections[0].length,
            "sections": [{"length_m": s.length, "curvature_1_m": s.curvature, "direction_rad": s.direction,
                          "angle_deg": math.degrees(s.angle)} for s in self.sections],
        }


def pre_bent_sheath(guide: float = 0.2, bend_radius: float = 0.035, bend_angle: float = math.pi / 3,
                    distal: float = 0.02, inner_diameter: float = SHEATH_8FR_ID) -> SheathGeometry:
    """A pre-bent 8 Fr sheath: a straight shaft (the guide), one bend, a short straight distal end.

    Defaults: 200 mm shaft, a 60° bend of 35 mm radius (28.6 1/m, like a fixed-curve transseptal sheath), 20 mm
    distal straight, inner diameter 2.8 mm (65 µm radial clearance around an 8 Fr catheter).
    """
    return SheathGeometry(
        "pre-bent-8fr",
        (Section(guide), Section.bend(bend_radius, bend_angle), Section(distal)),
        inner_diameter=inner_diameter,
    )


def vascular_sheath(inner_diameter: float = 3e-3, guide: float = 0.25) -> SheathGeometry:
    """The 510 mm rigid sheath of the sheath-motion experiment: a vascular-like spatial path with sharp bends.

    After a straight guide (femoral access and iliac artery: ``guide``, default 250 mm) come a 45° bend (R 40 mm),
    a sharp 70° kink (R 8 mm), a 150° arch (R 25 mm) at right angles to the first bend, a sharp 80° branch
    take-off (R 8 mm) and a 60° turn (R 12 mm), 10–12 mm of straight between them, then straight to 510 mm. The
    sharp bends curve at 125 1/m: ≈ 5.4 nm of shift on a core facing the bend at the paper's r·S_ε, enough to run a
    grating's peak into its neighbour's 5 nm away (the paper's peak overlap). Pushed in by the sheath-path setup,
    the kink passes under most of the sensed region and the take-off under its distal third. Inner diameter 3 mm
    like the paper's printed sheath.
    """
    bends = (
        Section.bend(0.040, math.radians(45), 0.0),
        Section(0.010),
        Section.bend(0.008, math.radians(70), math.radians(200)),
        Section(0.012),
        Section.bend(0.025, math.radians(150), math.pi / 2),
        Section(0.012),
        Section.bend(0.008, math.radians(80), math.radians(200)),
        Section(0.012),
        Section.bend(0.012, math.radians(60), math.radians(20)),
    )
    used = guide + sum(b.length for b in bends)
    if used >= 0.51 - 0.01:
        raise ValueError(f"vascular_sheath: guide {guide * 1e3:g} mm leaves no room for the bends in 510 mm")
    return SheathGeometry("vascular-510", (Section(guide), *bends, Section(0.51 - used)),
                          inner_diameter=inner_diameter)


# ----------------------------------------------------------------------------------------------------
# Motion script
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Motion:
    """The hub's insertion and roll over time: waypoints joined by trapezoidal velocity profiles.

    Between consecutive waypoints both coordinates move with a velocity that ramps up over the first
    ``accel`` fraction of the interval, stays constant, and ramps down over the last ``accel`` fraction (0.5: a
    triangle; small: near-constant speed), so the hub starts and stops without jerks of infinite size. Before the
    first and after the last waypoint it holds.

    Attributes
    ----------
    times : ndarray (n,)
        s, strictly increasing, from 0.
    depth : ndarray (n,)
        Insertion of the hub from its start, m (positive = deeper into the sheath).
    roll : ndarray (n,)
        Hub rotation about the guide axis, rad.
    accel : float
        Fraction of each interval spent accelerating (and as much decelerating), in (0, 0.5].
    """

    times: np.ndarray
    depth: np.ndarray
    roll: np.ndarray
    accel: float = 0.25

    def __post_init__(self) -> None:
        t = np.asarray(self.times, dtype=np.float64)
        d = np.broadcast_to(np.asarray(self.depth, dtype=np.float64), t.shape).copy()
        r = np.broadcast_to(np.asarray(self.roll, dtype=np.float64), t.shape).copy()
        if t.ndim != 1 or t.size < 1 or t[0] != 0.0 or np.any(np.diff(t) <= 0):
            raise ValueError("Motion.times: expected strictly increasing times starting at 0 s")
        if not (0.0 < self.accel <= 0.5):
            raise ValueError(f"Motion.accel: expected a fraction in (0, 0.5], got {self.accel}")
        for a in (t, d, r):
            a.setflags(write=False)
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "depth", d)
        object.__setattr__(self, "roll", r)
        # the waypoints as Python floats, for the one-time-at-a-time path of :meth:`at` (a setup's actuate, every
        # physics step): ≈ 20 numpy calls on 0-d arrays cost ≈ 80 µs after a MuJoCo step, the floats ≈ 2 µs
        object.__setattr__(self, "_points", (t.tolist(), d.tolist(), r.tolist()))

    @property
    def duration(self) -> float:
        """Time of the last waypoint, s."""
        return float(self.times[-1])

    def _fraction(self, t) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=np.float64)
        times = self.times
        if times.size == 1:
            return np.zeros(t.shape, dtype=np.int64), np.zeros(t.shape)
        i = np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 2)
        x = np.clip((t - times[i]) / (times[i + 1] - times[i]), 0.0, 1.0)
        a = self.accel
        v = 1.0 / (1.0 - a)
        f = np.where(x < a, 0.5 * v * x * x / a,
                     np.where(x > 1.0 - a, 1.0 - 0.5 * v * (1.0 - x) ** 2 / a, v * (x - 0.5 * a)))
        return i, f

    def at(self, t) -> tuple[np.ndarray, np.ndarray]:
        """(depth m, roll rad) at times ``t`` (any shape; a Python float gives two floats)."""
        if type(t) is float:
            return self._at_float(t)
        i, f = self._fraction(t)
        if self.times.size == 1:
            return np.full(np.shape(t), self.depth[0]), np.full(np.shape(t), self.roll[0])
        d = self.depth[i] + f * (self.depth[i + 1] - self.depth[i])
        r = self.roll[i] + f * (self.roll[i + 1] - self.roll[i])
        return d, r

    def _at_float(self, t: float) -> tuple[float, float]:
        """:meth:`at` of one time in Python floats: the same operations in the same order as the array path, so
        the same doubles (tests/test_sheath.py compares them bit for bit)."""
        times, depth, roll = self._points
        if len(times) == 1:
            return depth[0], roll[0]
        i = min(max(bisect.bisect_right(times, t) - 1, 0), len(times) - 2)
        x = min(max((t - times[i]) / (times[i + 1] - times[i]), 0.0), 1.0)
        a = self.accel
        v = 1.0 / (1.0 - a)
        if x < a:
            f = 0.5 * v * x * x / a
        elif x > 1.0 - a:
            f = 1.0 - 0.5 * v * ((1.0 - x) * (1.0 - x)) / a
        else:
            f = v * (x - 0.5 * a)
        return depth[i] + f * (depth[i + 1] - depth[i]), roll[i] + f * (roll[i + 1] - roll[i])


# ----------------------------------------------------------------------------------------------------
# The setups
# ----------------------------------------------------------------------------------------------------


class _ActuatedScene(Scene):
    """A :class:`models.catheter.Scene` with an ``<actuator>`` section."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.actuators = ET.Element("actuator")

    def to_element(self) -> ET.Element:
        root = super().to_element()
        if len(self.actuators):
            root.append(self.actuators)
        return root


class SheathSetup(Setup):
    """A catheter driven by a hub (insertion slide + roll hinge, position actuators) through a rigid sheath.

    Subclasses (the registered setups) choose the geometry, the hub's start and the :class:`Motion`, and call
    :meth:`_configure` from their ``__init__``.

    Attributes
    ----------
    geometry : SheathGeometry
    motion : Motion
    hub_start : float
        Sheath arc length of the hub (the rod's clamp) at t = 0, m.
    spec : CatheterSpec
    world : Pose
        Sheath coordinates → world (default :data:`HORIZONTAL`).
    rails : RailSet or None
        After :meth:`build`.
    settle_result : SettleResult or None
        After :meth:`prepare`.
    """

    actuated = True
    #: position-servo stiffness of the insertion slide, N/m, and of the roll hinge, N·m/rad (critically damped)
    kp_slide = 5000.0
    kp_roll = 1.0
    #: capsule rails round the bore
    n_rails = 8
    #: pin the rod to the hub instead of hanging it from the hub by equalities (Scene.add_rod): the same clamp
    #: within 1.4 µm and 2e-6 rad, but MuJoCo's step then costs 2–2.5× as much (docs/simulation.md §4)
    pin_to_hub = False

    def _configure(self, geometry: SheathGeometry, motion: Motion, hub_start: float, *, friction: float,
                   segments: int, timestep: float, settle_time: float, world: Pose = HORIZONTAL,
                   hold: float = 0.0) -> None:
        if not (0.0 <= friction <= 2.0):
            raise ValueError(f"sim://{self.name}: friction must be in [0, 2], got {friction}")
        self.geometry = geometry
        self.motion = motion
        self.hub_start = float(hub_start)
        self.spec = CatheterSpec(n_segments=int(segments), timestep=float(timestep), friction=float(friction))
        if self.spec.outer_diameter >= geometry.inner_diameter:
            raise ValueError(f"sim://{self.name}: the catheter ({self.spec.outer_diameter * 1e3:.2f} mm) does not fit "
                             f"the sheath's {geometry.inner_diameter * 1e3:.2f} mm bore")
        self.friction = float(friction)
        self.settle_time = float(settle_time)
        self.world = world
        self.duration = motion.duration + float(hold)
        self.rails: RailSet | None = None
        self.settle_result = None
        lo, hi = self.hub_range
        if lo < 0.0 or hi > geometry.guide_length + 1e-12:
            raise ValueError(
                f"sim://{self.name}: the hub moves over sheath arc length [{lo * 1e3:.1f}, {hi * 1e3:.1f}] mm but must "
                f"stay in the straight guide [0, {geometry.guide_length * 1e3:.1f}] mm; shorten the travel or "
                "lengthen the guide"
            )
        self._act = (-1, -1)

    # -- geometry over time --
    @property
    def hub_range(self) -> tuple[float, float]:
        """Sheath arc lengths the hub visits, m."""
        d = np.asarray(self.motion.depth)
        return self.hub_start + float(d.min()), self.hub_start + float(d.max())

    @cached_property
    def curve(self) -> ExtendedCurve:
        """The sheath centreline, continued straight beyond its end as far as the rod can reach."""
        reach = self.hub_range[1] + self.spec.length + 0.01
        return ExtendedCurve(self.geometry.shape, 0.0, max(0.0, reach - self.geometry.length) + 0.01, mode="natural")

    def sheath_u(self, t, s) -> np.ndarray:
        """Nominal sheath arc length of fibre point ``s`` (m) at time ``t`` (s): the rod following the centreline
        behind the hub's commanded insertion (broadcast over t and s)."""
        depth, _ = self.motion.at(t)
        return self.hub_start + np.asarray(depth)[..., None] + self.spec.base_length + np.asarray(s)

    def nominal_base_pose(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Where an experimenter places the fibre base (s = 0) from the commanded insertion and roll alone.

        The catheter is taken to follow the sheath centreline without twist: the base sits on the centreline at
        :meth:`sheath_u` (t, 0), its frame is the centreline's twist-free frame rolled by the commanded hub angle.

        Returns
        -------
        positions : ndarray (..., 3)
            World, m.
        frames : ndarray (..., 3, 3)
            [d1 d2 d3] columns in the world.
        """
        t = np.asarray(t, dtype=np.float64)
        _, roll = self.motion.at(t)
        u = self.sheath_u(t, np.zeros(1))[..., 0]
        pos = self.world.apply(self.curve.positions(u))
        frames = self.world.apply_frames(self.curve.frames(u))
        c, s = np.cos(roll), np.sin(roll)
        rz = np.zeros((*np.shape(roll), 3, 3))
        rz[..., 0, 0], rz[..., 0, 1], rz[..., 1, 0], rz[..., 1, 1], rz[..., 2, 2] = c, -s, s, c, 1.0
        return pos, frames @ rz

    def bore_offsets(self, points) -> np.ndarray:
        """Distance of world points (..., 3) from the sheath's centreline, m; NaN where the nearest centreline point
        is an end of the sheath (a point outside it, e.g. the catheter's protruding part).

        A catheter in the bore stays within the radial clearance (inner radius − catheter radius, plus the
        ≈ 15 µm the rails' scallops and the soft contacts allow); much more means it went through the wall.
        """
        if not hasattr(self, "_bore_tree"):
            u = np.linspace(0.0, self.geometry.length, round(self.geometry.length / 5e-5) + 1)
            self._bore_tree = cKDTree(self.world.apply(self.curve.positions(u)))
        pts = np.asarray(points, dtype=np.float64)
        d, i = self._bore_tree.query(pts.reshape(-1, 3))
        n = self._bore_tree.n
        d = np.where((i == 0) | (i == n - 1), np.nan, d)
        return d.reshape(pts.shape[:-1])

    def nominal_curvature(self, t, s) -> np.ndarray:
        """Curvature magnitude of the sheath centreline where fibre point ``s`` nominally is at time ``t``, 1/m."""
        k = self.geometry.curvature(self.sheath_u(t, s))
        return np.hypot(k[..., 0], k[..., 1])

    # -- Setup interface --
    def build(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        spec, geo, curve = self.spec, self.geometry, self.curve
        scene = _ActuatedScene(f"sheath:{self.name}")
        hub_pose = self.world @ Pose(curve.positions(self.hub_start), curve.frames(self.hub_start))
        scene.comment(f"hub: insertion slide and roll hinge along the guide at sheath arc length "
                      f"{self.hub_start * 1e3:.1f} mm, driven by position actuators")
        hub = scene.add_body("hub", hub_pose)
        # The hub moves the simulated (x100 mass) rod: servo frequencies sqrt(kp/inertia) ≈ 120 rad/s (insertion,
        # 0.33 kg with the rod) and ≈ 220 rad/s (roll, 2e-5 kg m²), critically damped; the discrete integrator
        # treats the actuators implicitly. Tracking lag at 20 mm/s: 0.3 mm; at 90 °/s: 0.8°.
        ET.SubElement(hub, "inertial", pos="0 0 0", mass="0.1", diaginertia="1e-5 1e-5 1e-5")
        ET.SubElement(hub, "joint", name="hub_slide", type="slide", axis="0 0 1", armature="0.1")
        ET.SubElement(hub, "joint", name="hub_roll", type="hinge", axis="0 0 1", armature="1e-5")
        ET.SubElement(scene.actuators, "position", name="hub_insert", joint="hub_slide", kp=f"{self.kp_slide:g}",
                      dampratio="1")
        ET.SubElement(scene.actuators, "position", name="hub_rotate", joint="hub_roll", kp=f"{self.kp_roll:g}",
                      dampratio="1")
        if self.pin_to_hub:
            rod = scene.add_rod(spec, Pose(), parent="hub")
        else:
            rod = scene.add_rod(spec, Pose(), parent="hub", parent_world=hub_pose, roll_joint="hub_roll")
        lo, hi = self.hub_range
        s_range = (max(0.0, lo - 5e-3), min(geo.length, hi + spec.length + 5e-3))
        self.rails = add_rails(
            scene, "sheath", curve, self.world, width=geo.inner_diameter,
            rail_offsets=tube_rail_offsets(geo.inner_diameter, n_rails=self.n_rails), s_range=s_range,
            max_segment=None, friction=self.friction,
            solref=spec.solref, solimp=spec.contact_solimp, rgba="0.55 0.75 0.6 0.3", label=f"sheath {geo.name!r}",
        )
        targets = self.world.apply(curve.positions(self.hub_start + spec.base_length + spec.vertex_s))

        def place(model: mujoco.MjModel, data: mujoco.MjData) -> None:
            set_rod_positions(model, data, targets, spec.name)

        scene.on_build(place)
        self.extend_scene(scene, rod)
        model, data = scene.build()
        self._act = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "hub_insert"),
                     mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "hub_rotate"))
        self._joints = tuple(int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)])
                             for n in ("hub_slide", "hub_roll"))
        return model, data

    def extend_scene(self, scene: Scene, rod) -> None:
        """Add to the scene before it compiles, after the rod is placed (e.g. a fibre in its lumen)."""

    def prepare(self, model: mujoco.MjModel, data: mujoco.MjData,
                progress: Callable[[float, float], None] | None = None) -> None:
        """Hold the hub at its start and let the catheter settle in the sheath (a clear error if it does not)."""
        self.actuate(model, data, 0.0)
        self.settle_result = settle(model, data, max_time=self.settle_time, tol=1e-6, progress=progress,
                                    label=f"sim://{self.name} (catheter in sheath {self.geometry.name!r})")

    def actuate(self, model: mujoco.MjModel, data: mujoco.MjData, t: float) -> None:
        depth, roll = self.motion.at(t)
        data.ctrl[self._act[0]] = depth
        data.ctrl[self._act[1]] = roll

    def hub_state(self, data: mujoco.MjData) -> tuple[float, float]:
        """The hub's actual (insertion m, roll rad), for comparison with the commanded motion."""
        return float(data.qpos[self._joints[0]]), float(data.qpos[self._joints[1]])

    def fixture_centreline(self) -> np.ndarray:
        """The whole sheath centreline in the world, 1 mm apart, (k, 3) m."""
        n = round(self.geometry.length / 1e-3) + 1
        return self.world.apply(self.curve.positions(np.linspace(0.0, self.geometry.length, n)))

    def describe(self) -> dict:
        return {
            "setup": self.name,
            "sheath": self.geometry.describe(),
            "hub_start_m": self.hub_start,
            "hub_range_m": list(self.hub_range),
            "friction": self.friction,
            "segments": self.spec.n_segments,
            "timestep": self.spec.timestep,
            "duration_s": self.duration,
            "rail_geoms": self.rails.n_geoms if self.rails is not None else None,
        }


def _hub_for_protrusion(geometry: SheathGeometry, spec_base: float, sensed: float, protrusion: float) -> float:
    """Hub arc length that puts the end of the sensed region ``protrusion`` (m) beyond the sheath's end."""
    return geometry.length + protrusion - sensed - spec_base


class SheathRotate(SheathSetup):
    """The catheter rotated inside a pre-bent 8 Fr sheath (the paper's rotation experiment).

    The sensed region runs from the sheath's straight shaft through its bend and out of its end by
    ``protrusion`` (the tip, 15 mm further, carries the EM sensor in the paper). The hub turns in ``steps`` equal
    steps to ``total_angle``, each a move of ``move_time`` and a dwell of ``dwell`` (measured at the end of the
    dwell), after an initial dwell.

    Parameters
    ----------
    protrusion : float
        How far the end of the sensed region sticks out of the sheath, m (negative: inside).
    bend_radius, bend_angle : float
        The sheath's pre-bend, m and rad.
    inner_diameter : float
        m.
    total_angle : float
        rad (default one turn).
    steps : int
    move_time, dwell : float
        s.
    friction : float
    segments : int
    timestep, settle_time : float
        s.
    """

    name = "sheath-rotate"

    def __init__(self, protrusion: float = 0.05, bend_radius: float = 0.035, bend_angle: float = math.pi / 3,
                 inner_diameter: float = SHEATH_8FR_ID, total_angle: float = 2 * math.pi, steps: int = 8,
                 move_time: float = 1.0, dwell: float = 2.0, friction: float = 0.2, segments: int = 100,
                 timestep: float = 2e-3, settle_time: float = 10.0):
        if steps < 1 or move_time <= 0 or dwell <= 0:
            raise ValueError(f"sim://{self.name}: steps >= 1, move_time > 0 and dwell > 0 needed")
        geo = pre_bent_sheath(bend_radius=bend_radius, bend_angle=bend_angle, inner_diameter=inner_diameter)
        spec = CatheterSpec()
        hub = _hub_for_protrusion(geo, spec.base_length, spec.sensed_length, protrusion)
        times = [0.0, dwell]
        angles = [0.0, 0.0]
        for k in range(1, steps + 1):
            times += [times[-1] + move_time, times[-1] + move_time + dwell]
            angles += [total_angle * k / steps] * 2
        self.protrusion = float(protrusion)
        self.steps = int(steps)
        self.step_angles = np.array(angles[::2])  # the angle held during each dwell, rad
        self.dwell_ends = np.array(times[1::2])  # s
        self._configure(geo, Motion(np.array(times), 0.0, np.array(angles), accel=0.3), hub, friction=friction,
                        segments=segments, timestep=timestep, settle_time=settle_time)

    def describe(self) -> dict:
        return {**super().describe(), "protrusion_m": self.protrusion, "steps": self.steps,
                "step_angles_rad": self.step_angles.tolist(), "dwell_ends_s": self.dwell_ends.tolist()}


class SheathCycle(SheathSetup):
    """In and out of the same pre-bent sheath to a reference point, ``cycles`` times (the paper's repeatability).

    At the reference the sensed region sticks out of the sheath by ``protrusion``; each cycle withdraws the hub by
    ``withdraw`` (default 80 mm: the tip goes back inside the sheath), pauses, and pushes back to the reference,
    where it dwells; it is measured at the end of the dwell. ``depth_jitter`` and ``roll_jitter`` (1σ, m and rad,
    seeded by ``seed``) let the return to the reference vary like a hand's (default: the hub returns exactly).

    Parameters
    ----------
    cycles : int
    protrusion, withdraw, speed : float
        m, m, m/s.
    dwell : float
        s at the reference (and a fifth of it withdrawn).
    depth_jitter, roll_jitter : float
        m, rad.
    seed : int
    bend_radius, bend_angle, inner_diameter, friction, segments, timestep, settle_time
        As :class:`SheathRotate`.
    """

    name = "sheath-cycle"

    def __init__(self, cycles: int = 10, protrusion: float = 0.05, withdraw: float = 0.08, speed: float = 0.05,
                 dwell: float = 0.5, depth_jitter: float = 0.0, roll_jitter: float = 0.0, seed: int = 0,
                 bend_radius: float = 0.035, bend_angle: float = math.pi / 3, inner_diameter: float = SHEATH_8FR_ID,
                 friction: float = 0.2, segments: int = 100, timestep: float = 2e-3, settle_time: float = 10.0):
        if cycles < 1 or withdraw <= 0 or speed <= 0 or dwell <= 0:
            raise ValueError(f"sim://{self.name}: cycles >= 1, withdraw > 0, speed > 0 and dwell > 0 needed")
        geo = pre_bent_sheath(bend_radius=bend_radius, bend_angle=bend_angle, inner_diameter=inner_diameter)
        spec = CatheterSpec()
        hub = _hub_for_protrusion(geo, spec.base_length, spec.sensed_length, protrusion)
        rng = np.random.default_rng(seed)
        move = withdraw / speed
        # each move: a trapezoid accelerating over a fifth of it, peaking at 1.25 × the mean speed
        times, depth, roll = [0.0, dwell], [0.0, 0.0], [0.0, 0.0]
        refs = []
        for _ in range(int(cycles)):
            dj = depth_jitter * rng.standard_normal()
            rj = roll_jitter * rng.standard_normal()
            t = times[-1]
            times += [t + move, t + move + 0.2 * dwell, t + 2 * move + 0.2 * dwell, t + 2 * move + 1.2 * dwell]
            depth += [-withdraw, -withdraw, dj, dj]
            roll += [0.0, 0.0, rj, rj]
            refs.append(times[-1])
        self.cycles = int(cycles)
        self.protrusion = float(protrusion)
        self.withdraw = float(withdraw)
        self.reference_times = np.array([dwell, *refs])  # dwell ends at the reference: the start, then each cycle
        self._configure(geo, Motion(np.array(times), np.array(depth), np.array(roll), accel=0.2), hub,
                        friction=friction, segments=segments, timestep=timestep, settle_time=settle_time)

    def describe(self) -> dict:
        return {**super().describe(), "cycles": self.cycles, "protrusion_m": self.protrusion,
                "withdraw_m": self.withdraw, "reference_times_s": self.reference_times.tolist()}


class SheathPath(SheathSetup):
    """The catheter pushed through the 510 mm rigid vascular-like sheath and back (the paper's sheath motion).

    The hub starts at sheath arc length ``start`` and is pushed ``travel`` deeper at ``speed`` (near-constant:
    5 % of each move accelerating, 5 % braking, peak = ``speed``), held for ``hold``, and with ``return_trip``
    pulled back to the start and held again. With the defaults the catheter's tip starts at the end of the
    straight guide, and the sensed region ends up spanning the first bend, the sharp kink, the arch, the sharp
    take-off and part of the last turn (:func:`vascular_sheath`).

    Parameters
    ----------
    start, travel, speed : float
        m, m, m/s (a hand's 10–50 mm/s).
    hold : float
        s.
    return_trip : bool
    inner_diameter, friction : float
        The paper's printed sheath: 3 mm, rough (default μ 0.3).
    segments : int
    timestep, settle_time : float
        s. The default step is 1 ms, not the rod's usual 2 ms: pushing the tip into the outer wall of an 8 mm
        bend takes newtons, and MuJoCo's soft contacts (time constant 2 steps) then let it sink between the rails;
        at 2 ms the tip sank ≈ 2 mm, snagged and kinked the catheter in 3 of 9 runs (start offsets of 0.1 mm
        changed which), at 1 ms (contacts 4× stiffer) 10 of 10 runs passed with the tip ≤ 1.2 mm off the
        centreline for a moment and the sensed region within 0.3 mm of it.
    """

    name = "sheath-path"

    def __init__(self, start: float = 0.06, travel: float = 0.185, speed: float = 0.02, hold: float = 0.5,
                 return_trip: bool = True, inner_diameter: float = 3e-3, friction: float = 0.3, segments: int = 100,
                 timestep: float = 1e-3, settle_time: float = 10.0):
        if travel <= 0 or speed <= 0 or hold < 0:
            raise ValueError(f"sim://{self.name}: travel > 0, speed > 0 and hold >= 0 needed")
        geo = vascular_sheath(inner_diameter)
        self.travel = float(travel)
        self.speed = float(speed)
        self.return_trip = bool(return_trip)
        move = travel / speed / 0.95  # mean speed 0.95 × peak with 5 % ramps
        times, depth = [0.0, 0.2, 0.2 + move], [0.0, 0.0, travel]
        if return_trip:
            times += [times[-1] + hold, times[-1] + hold + move]
            depth += [travel, 0.0]
        self.insertion_end = 0.2 + move  # s, when the hub reaches its deepest point
        self._configure(geo, Motion(np.array(times), np.array(depth), 0.0, accel=0.05), start, friction=friction,
                        segments=segments, timestep=timestep, settle_time=settle_time, hold=hold)

    def describe(self) -> dict:
        return {**super().describe(), "travel_m": self.travel, "speed_m_s": self.speed,
                "return_trip": self.return_trip}
