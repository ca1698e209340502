"""The catheter as a MuJoCo 4.0 discrete elastic rod, and a small scene builder for it and its fixtures.

The catheter is a 1D ``<flexcomp type="direct" dim="1">`` rod (docs/simulation.md §1): straight in its
reference configuration ``qpos0`` along the local +z axis of its base pose, first edge clamped
(``<pin id="0 1"/>``), inextensible through the flex edge equality, bending and torsion from
``<elasticity young=EI/I shear=GJ/J>`` with I = πr⁴/4 and J = πr⁴/2 of the flex radius, integrated with
``integrator="discrete"``.

Arc length. The rod is longer than the sensed region so that every grating sits where the rod has a
two-sided discrete curvature: ``base_length`` of shaft between the clamp and the fibre's s = 0 (the first
grating) and ``tip_length`` beyond the sensed length. Everything in :mod:`models` reports arc length in the
*fibre's* coordinate, s = 0 at the start of the sensed region, so the clamp sits at s = −base_length and the
tip at s = sensed_length + tip_length. Defaults: 10 mm of base (a clamp on the first grating would force
zero curvature there: the clamped edge is straight) and 15 mm of tip (an ablation tip electrode and the
fibre's end). The tip length also keeps the last grating away from the free end, where a shape held by
constraints needs large forces because a free end carries no moment (2–40 µm of vertex error in the last
three vertices against < 1 µm elsewhere): with 10 mm the last grating still saw up to 0.06 1/m of it,
with 15 mm 0.002 1/m.

Quasi-static settings (docs/simulation.md §1). MuJoCo constraints are mass-normalised and soft, so with the
real mass (≈ 13 mg per vertex at 100 segments) connect constraints leave 0.4–1.5 mm of error. The rod
therefore carries ×100 its mass and the scene ×1/100 gravity (statics unchanged: the weight per length is the
real one), constraint ``solref`` time constant 2·dt (the stiffest MuJoCo accepts) and ``solimp`` 0.9999, and
a velocity damping of 0.01 N·s/m on each vertex slide DOF to settle the low, barely Rayleigh-damped modes.
Contacts use a softer ``contact_solimp`` and the solver a tighter ``tolerance`` (see :class:`CatheterSpec`).

MuJoCo 4.0 refuses joint damping on flex vertex bodies in MJCF ("flex vertex/node body ... cannot have joint
damping"), so the vertex damping is written into ``mjModel.dof_damping`` after compiling, by
:func:`apply_runtime_settings` (which :meth:`Scene.build` calls). The value is stored in the XML as the custom
numeric ``<rod>_vertex_damping``, so a model loaded from :meth:`Scene.to_xml` elsewhere gets it back with one
call to :func:`apply_runtime_settings`.

The clamped edge's material frame. MuJoCo picks the reference director of the first edge from the tangent
alone (for a tangent along the parent body's +z it is the body's +y axis, whatever the flexcomp ``quat``). The
project's convention is that d1 of the clamped edge is the x axis of the base pose, so each rod also gets a
site ``<rod>_base`` at its base pose and :mod:`models.rod_state` rotates MuJoCo's frames about the tangent by
the constant angle that puts d1 of the clamped edge on that site's x axis (isotropic section: the physics does
not depend on this choice).

Example
-------
>>> scene = Scene("demo")
>>> rod = scene.add_rod(CatheterSpec(n_segments=50))
>>> model, data = scene.build()

Why one module of this size: the catheter's spec, the MJCF it generates and the helpers that read and place
the rod are one description of one body; each piece is meaningless without the others.
"""

from __future__ import annotations

import math
import weakref
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "CatheterSpec",
    "Pose",
    "RodHandle",
    "Scene",
    "apply_runtime_settings",
    "collect_warnings",
    "rod_vertex_qpos_addresses",
    "set_rod_positions",
]

#: m, outer radius of an 8 Fr catheter (8 Fr = 8/3 mm diameter).
RADIUS_8FR = 1.335e-3


def _fmt(value) -> str:
    """MJCF attribute text: numbers with 9 significant digits, sequences space-separated."""
    if isinstance(value, str):
        return value
    if isinstance(value, bool | np.bool_):
        return "true" if value else "false"
    a = np.asarray(value)
    if a.ndim == 0:
        v = a.item()
        return str(v) if isinstance(v, int | np.integer) else f"{float(v):.9g}"
    if a.dtype.kind in "iu":
        return " ".join(str(int(v)) for v in a.ravel())
    return " ".join(f"{float(v):.9g}" for v in a.ravel())


def _positive(owner: str, **values: float) -> None:
    for name, v in values.items():
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            raise ValueError(f"{owner}.{name}: expected a finite number > 0, got {v!r}")


# ----------------------------------------------------------------------------------------------------
# Pose
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Pose:
    """A rigid transform: ``world = rot @ local + pos``.

    Attributes
    ----------
    pos : ndarray, shape (3,)
        Translation, m.
    rot : ndarray, shape (3, 3)
        Rotation matrix whose columns are the local axes in the parent (world) frame.
    """

    pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rot: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        pos = np.array(self.pos, dtype=np.float64).reshape(3)
        rot = np.array(self.rot, dtype=np.float64)
        if rot.shape != (3, 3):
            raise ValueError(f"Pose.rot: expected a 3x3 rotation matrix, got shape {rot.shape}")
        if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-9) or np.linalg.det(rot) < 0:
            raise ValueError("Pose.rot: not a proper rotation matrix (expected RᵀR = I, det R = +1)")
        # Re-orthonormalise so that quaternions written to MJCF round-trip exactly.
        rot = Rotation.from_matrix(rot).as_matrix()
        pos.setflags(write=False)
        rot.setflags(write=False)
        object.__setattr__(self, "pos", pos)
        object.__setattr__(self, "rot", rot)

    @classmethod
    def from_quat(cls, pos: Sequence[float], quat: Sequence[float]) -> Pose:
        """From a position (m) and a MuJoCo-order quaternion (w, x, y, z)."""
        return cls(pos, Rotation.from_quat(np.asarray(quat, dtype=np.float64), scalar_first=True).as_matrix())

    @property
    def quat(self) -> np.ndarray:
        """MuJoCo-order unit quaternion (w, x, y, z) with w ≥ 0."""
        q = Rotation.from_matrix(self.rot).as_quat(scalar_first=True)
        return -q if q[0] < 0 else q

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points (..., 3) from the local to the parent frame, m."""
        return np.asarray(points) @ self.rot.T + self.pos

    def apply_frames(self, frames: np.ndarray) -> np.ndarray:
        """Map frames (..., 3, 3) (columns = axes) from the local to the parent frame."""
        return self.rot @ np.asarray(frames)

    def __matmul__(self, other: Pose) -> Pose:
        """Composition ``self ∘ other`` (apply ``other`` first)."""
        return Pose(self.rot @ other.pos + self.pos, self.rot @ other.rot)


# ----------------------------------------------------------------------------------------------------
# Catheter specification
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CatheterSpec:
    """Mechanical and numerical description of the catheter rod (SI units).

    The defaults describe an 8 Fr ablation catheter like the reference paper's (docs/simulation.md §1).

    Parameters
    ----------
    name : str
        MJCF name of the flexcomp; prefix of every generated body and joint (``<name>_<i>``,
        ``<name>_twist_<e>``).
    sensed_length : float
        Length of the sensed (fibre) region, m.
    base_length : float
        Shaft between the clamp and the start of the sensed region (fibre s = 0), m.
    tip_length : float
        Rod beyond the end of the sensed region, m (see the module docstring for why 15 mm).
    outer_diameter : float
        m; the flex radius (contact and the I, J used by MuJoCo) is half of it.
    bending_stiffness : float
        EI, N·m².
    torsional_stiffness : float
        GJ, N·m².
    mass : float
        Real mass of the modelled length (base + sensed + tip), kg; default ≈ 6.8 g/m, a braided 8 Fr shaft.
        The simulation uses ``mass * mass_scale``.
    n_segments : int
        Number of rod edges over the whole modelled length.
    fiber_offset : float
        Distance of the sensing fibre's axis from the catheter's neutral axis, m (used by the optics model;
        the mechanics ignore it).
    damping : float
        Rayleigh damping coefficient of the rod elasticity, s.
    friction : float
        Sliding friction coefficient of the rod's contacts.
    mass_scale : float
        Factor on the simulated mass (quasi-static trick: stiffer effective constraints).
    gravity_scale : float
        Factor on gravity, normally ``1 / mass_scale`` so that the weight per length stays the real one.
    timestep : float
        Physics step, s. 2 ms worked for 50–200 segments in connect, tube and groove fixtures; at 5 ms a
        50-segment rod sprang out through the rails of a tube while settling.
    solref_factor : float
        Constraint ``solref`` time constant as a multiple of ``timestep`` (MuJoCo clamps it to ≥ 2).
    solimp : tuple of 3 floats
        Constraint impedance (d0, dwidth, width) of the edge and connect constraints.
    contact_solimp : tuple of 3 floats
        Impedance of the rod's contacts. Softer than ``solimp`` on purpose: with 0.9999 the rod chattered
        against tube rails and never settled (tip wobbling by 0.1–0.5 mm per 0.25 s); 0.95–0.99 settles in
        1–2 s with ≤ 20 µm of penetration.
    dof_damping : float
        Velocity damping on each vertex slide DOF, N·s/m (applied after compiling, see module docstring).
    solver_tolerance : float
        ``<option tolerance>`` of the constraint solver. MuJoCo's default 1e-8 leaves a relative noise of
        ≈ 4e-6 on a settled twist rate; 1e-10 ≈ 5e-8, 1e-12 ≈ 6e-10 (≈ 15 % slower with connect constraints).
    solver_iterations : int
        ``<option iterations>``: most Newton iterations per step; MuJoCo's default 100, kept. MuJoCo 4.0's step
        costs more the higher this cap is, whether the solver gets there or not (a sheath step ≈ 1.5× faster at
        30, the same rod over 2 s of ``sim://sheath-cycle``), but such caps bind in the vascular sheath and for a glued
        fibre, and change their physics (docs/simulation.md §4).
    """

    name: str = "cath"
    sensed_length: float = 0.17
    base_length: float = 0.01
    tip_length: float = 0.015
    outer_diameter: float = 2 * RADIUS_8FR
    bending_stiffness: float = 2.0e-4
    torsional_stiffness: float = 1.5e-4
    mass: float = 1.3e-3
    n_segments: int = 100
    fiber_offset: float = 0.0
    damping: float = 2.0e-3
    friction: float = 0.1
    mass_scale: float = 100.0
    gravity_scale: float = 0.01
    timestep: float = 2.0e-3
    solref_factor: float = 2.0
    solimp: tuple[float, float, float] = (0.9999, 0.9999, 0.001)
    contact_solimp: tuple[float, float, float] = (0.95, 0.99, 0.001)
    dof_damping: float = 0.01
    solver_tolerance: float = 1e-10
    solver_iterations: int = 100

    def __post_init__(self) -> None:
        owner = "CatheterSpec"
        if not self.name or not self.name.replace("_", "").replace("-", "").isalnum():
            raise ValueError(f"{owner}.name: expected a non-empty identifier, got {self.name!r}")
        _positive(
            owner,
            sensed_length=self.sensed_length,
            outer_diameter=self.outer_diameter,
            bending_stiffness=self.bending_stiffness,
            torsional_stiffness=self.torsional_stiffness,
            mass=self.mass,
            mass_scale=self.mass_scale,
            timestep=self.timestep,
        )
        for name in (
            "base_length",
            "tip_length",
            "fiber_offset",
            "damping",
            "friction",
            "gravity_scale",
            "dof_damping",
            "solver_tolerance",
        ):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{owner}.{name}: expected a finite number >= 0, got {v!r}")
        if not isinstance(self.solver_iterations, int | np.integer) or self.solver_iterations < 1:
            raise ValueError(f"{owner}.solver_iterations: expected an integer >= 1, got {self.solver_iterations!r}")
        if not isinstance(self.n_segments, int | np.integer) or self.n_segments < 3:
            raise ValueError(f"{owner}.n_segments: expected an integer >= 3, got {self.n_segments!r}")
        if self.solref_factor < 2.0:
            raise ValueError(
                f"{owner}.solref_factor: MuJoCo needs a solref time constant >= 2 timesteps, "
                f"got {self.solref_factor}"
            )
        for name in ("solimp", "contact_solimp"):
            v = getattr(self, name)
            if len(v) != 3 or not all(0 < d < 1 for d in v[:2]):
                raise ValueError(f"{owner}.{name}: expected (d0, dwidth, width) with 0 < d < 1, got {v!r}")
        if self.fiber_offset >= self.radius:
            raise ValueError(
                f"{owner}.fiber_offset: {self.fiber_offset} m puts the fibre outside the catheter "
                f"(radius {self.radius} m)"
            )

    @classmethod
    def ablation_8fr(cls, **overrides) -> CatheterSpec:
        """The default 8 Fr ablation catheter, with any field overridden by keyword."""
        return cls(**overrides)

    # -- geometry --
    @property
    def length(self) -> float:
        """Modelled rod length base + sensed + tip, m."""
        return self.base_length + self.sensed_length + self.tip_length

    @property
    def radius(self) -> float:
        """Outer radius, m."""
        return 0.5 * self.outer_diameter

    @property
    def segment_length(self) -> float:
        """Rest length of one edge, m."""
        return self.length / self.n_segments

    @property
    def n_vertices(self) -> int:
        return self.n_segments + 1

    @property
    def vertex_s(self) -> np.ndarray:
        """Fibre arc length of each vertex at rest, m, shape (n_segments + 1,): −base_length to the tip."""
        return np.linspace(0.0, self.length, self.n_segments + 1) - self.base_length

    # -- material --
    @property
    def second_moment(self) -> float:
        """I = πr⁴/4 of the flex radius, m⁴ (what MuJoCo's circle section uses)."""
        return math.pi * self.radius**4 / 4

    @property
    def polar_moment(self) -> float:
        """J = πr⁴/2 of the flex radius, m⁴."""
        return math.pi * self.radius**4 / 2

    @property
    def young(self) -> float:
        """Young's modulus that gives ``bending_stiffness`` with the flex radius, Pa."""
        return self.bending_stiffness / self.second_moment

    @property
    def shear(self) -> float:
        """Shear modulus that gives ``torsional_stiffness`` with the flex radius, Pa."""
        return self.torsional_stiffness / self.polar_moment

    @property
    def simulated_mass(self) -> float:
        """kg, the ``mass`` attribute written to the flexcomp."""
        return self.mass * self.mass_scale

    @property
    def solref(self) -> tuple[float, float]:
        """(time constant s, damping ratio) for the rod's and its fixtures' constraints."""
        return (self.solref_factor * self.timestep, 1.0)


@dataclass(frozen=True, eq=False)
class RodHandle:
    """A rod placed in a :class:`Scene`.

    Attributes
    ----------
    spec : CatheterSpec
    pose : Pose
        Base (clamp) pose in the parent body's frame: the rod runs along its +z axis, d1 of the clamped edge
        is its +x axis.
    parent : str or None
        Name of the parent body (None: the world body).
    """

    spec: CatheterSpec
    pose: Pose
    parent: str | None = None

    @property
    def name(self) -> str:
        return self.spec.name


# ----------------------------------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------------------------------


class Scene:
    """Collects a catheter rod, fixture bodies/geoms/sites and equality constraints, then writes MJCF.

    Elements are :class:`xml.etree.ElementTree.Element` objects, so callers can add children or attributes to
    what the ``add_*`` methods return. Attribute values may be numbers or sequences (formatted with 9
    significant digits) or strings.

    Parameters
    ----------
    name : str
        Model name (it appears in error messages, e.g. of :func:`models.fixtures.settle`).
    gravity : sequence of 3 floats
        Real gravity, m/s²; the option written is ``gravity * gravity_scale`` of the rods' spec.
    timestep : float or None
        Physics step, s; None takes the first rod's ``spec.timestep``.
    solver : str
        ``Newton`` (fastest here) or ``CG``; ``PGS`` does not support flexes.
    options : mapping
        Extra ``<option>`` attributes.
    """

    def __init__(
        self,
        name: str = "catheter",
        *,
        gravity: Sequence[float] = (0.0, 0.0, -9.81),
        timestep: float | None = None,
        solver: str = "Newton",
        options: Mapping[str, object] | None = None,
    ) -> None:
        self.name = name
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3)
        self.timestep = timestep
        self.solver = solver
        self.options = dict(options or {})
        self.rods: list[RodHandle] = []
        self._world = ET.Element("worldbody")
        self._bodies: dict[str, ET.Element] = {}
        self._equality = ET.Element("equality")
        self._custom = ET.Element("custom")
        self._contact = ET.Element("contact")
        self._hooks: list[Callable[[mujoco.MjModel, mujoco.MjData], None]] = []

    # -- building blocks --
    def _parent(self, parent: str | None) -> ET.Element:
        if parent is None:
            return self._world
        try:
            return self._bodies[parent]
        except KeyError:
            raise KeyError(f"Scene {self.name!r}: no body {parent!r}; add it with add_body first") from None

    def comment(self, text: str, parent: str | None = None, *, section: str = "worldbody") -> None:
        """Add an XML comment (for readability) to the world body, a body, or the ``equality`` section."""
        where = self._equality if section == "equality" else self._parent(parent)
        where.append(ET.Comment(f" {text.strip()} "))

    def on_build(self, hook: Callable[[mujoco.MjModel, mujoco.MjData], None]) -> None:
        """Run ``hook(model, data)`` in :meth:`build` after compiling, in the order added (fixtures use it to
        write what MJCF cannot hold, e.g. connect targets, and to put the rod on their curve)."""
        self._hooks.append(hook)

    def add_body(
        self, name: str, pose: Pose | None = None, parent: str | None = None, **attrib
    ) -> ET.Element:
        """Add a body (static unless the caller adds joints to the returned element)."""
        if name in self._bodies:
            raise ValueError(f"Scene {self.name!r}: body {name!r} exists already")
        pose = pose or Pose()
        el = ET.SubElement(self._parent(parent), "body", name=name, pos=_fmt(pose.pos), quat=_fmt(pose.quat))
        for k, v in attrib.items():
            el.set(k, _fmt(v))
        self._bodies[name] = el
        return el

    def add_geom(self, parent: str | None = None, **attrib) -> ET.Element:
        """Add a geom to the world body (default) or a body; MJCF attributes (``type``, ``fromto``, ...)."""
        return ET.SubElement(self._parent(parent), "geom", {k: _fmt(v) for k, v in attrib.items()})

    def add_site(
        self, name: str, pose: Pose | None = None, parent: str | None = None, **attrib
    ) -> ET.Element:
        pose = pose or Pose()
        el = ET.SubElement(self._parent(parent), "site", name=name, pos=_fmt(pose.pos), quat=_fmt(pose.quat))
        for k, v in attrib.items():
            el.set(k, _fmt(v))
        return el

    def add_equality(self, kind: str, **attrib) -> ET.Element:
        """Add an equality constraint (``connect``, ``weld``, ``joint``, ...) with MJCF attributes."""
        return ET.SubElement(self._equality, kind, {k: _fmt(v) for k, v in attrib.items()})

    def add_exclude(self, body1: str, body2: str) -> ET.Element:
        return ET.SubElement(self._contact, "exclude", body1=body1, body2=body2)

    def add_numeric(self, name: str, data) -> ET.Element:
        """Add a custom numeric (model metadata readable at runtime through ``mjModel.numeric_data``)."""
        return ET.SubElement(self._custom, "numeric", name=name, data=_fmt(data))

    # -- the rod --
    def add_rod(
        self, spec: CatheterSpec | None = None, pose: Pose | None = None, parent: str | None = None, *,
        parent_world: Pose | None = None, roll_joint: str | None = None,
    ) -> RodHandle:
        """Add a catheter rod with its clamp at ``pose`` (in the parent body's frame).

        The rod lies straight along the pose's +z axis in ``qpos0`` (its rest shape), first edge clamped to
        the parent body (the world, or e.g. a hub body with joints for insertion and rotation).

        A parent that moves is best given with ``parent_world``, its world pose in ``qpos0``: the rod then lies in
        the world and hangs from the parent by constraints instead of a pin — connect equalities hold the clamped
        edge's two vertices where the pin would, and a joint equality makes that edge's twist joint follow
        ``roll_joint`` (the parent's hinge about the rod's axis; None: the twist is held at 0). The parent may only
        translate and roll about the rod's axis. Why: MuJoCo assembles the rod's stiffness in 3×3 vertex blocks only
        while no flex vertex sits on a body with joints; a rod pinned to one has it pulled back through the
        attachment Jacobians, and its effective-metric solve runs long — 2.2–2.6× the step of the same
        sheath scene (docs/simulation.md §4).
        """
        spec = spec or CatheterSpec()
        pose = pose or Pose()
        if parent_world is not None and parent is None:
            raise ValueError(f"Scene {self.name!r}: parent_world needs the parent body the rod hangs from")
        if any(r.name == spec.name for r in self.rods):
            raise ValueError(f"Scene {self.name!r}: a rod named {spec.name!r} exists already")
        if self.rods:
            first = self.rods[0].spec
            if spec.gravity_scale != first.gravity_scale:
                raise ValueError(
                    f"Scene {self.name!r}: rods disagree on gravity_scale ({first.gravity_scale} vs "
                    f"{spec.gravity_scale}); the scene has one gravity"
                )
        rod = RodHandle(spec, pose, parent)
        self.rods.append(rod)
        p = self._parent(parent)
        n = spec.n_segments
        points = np.zeros((n + 1, 3))
        points[:, 2] = np.linspace(0.0, spec.length, n + 1)
        elements = np.repeat(np.arange(n + 1), 2)[1:-1]  # 0 1 1 2 2 3 ...
        solref = _fmt(spec.solref)
        solimp = _fmt(spec.solimp)
        p.append(
            ET.Comment(
                f" catheter {spec.name!r}: {spec.length * 1e3:.1f} mm in {n} segments, clamp at fibre s = "
                f"{-spec.base_length * 1e3:g} mm, EI = {spec.bending_stiffness:g} N m2, GJ = "
                f"{spec.torsional_stiffness:g} N m2, mass {spec.mass * 1e3:g} g x {spec.mass_scale:g} "
                "(quasi-static) "
            )
        )
        ET.SubElement(
            p,
            "site",
            name=f"{spec.name}_base",
            pos=_fmt(pose.pos),
            quat=_fmt(pose.quat),
            size="0.0005",
            group="3",
        )
        rod_pose = pose if parent_world is None else parent_world @ pose
        fc = ET.SubElement(
            p if parent_world is None else self._world,
            "flexcomp",
            name=spec.name,
            type="direct",
            dim="1",
            radius=_fmt(spec.radius),
            mass=_fmt(spec.simulated_mass),
            pos=_fmt(rod_pose.pos),
            quat=_fmt(rod_pose.quat),
            rgba="0.85 0.45 0.2 1",
            point=_fmt(points),
            element=_fmt(elements),
        )
        if parent_world is None:
            ET.SubElement(fc, "pin", id="0 1")  # clamp the first edge and its material frame
        else:  # the same clamp by constraints (the vertex bodies' origins are their places in qpos0)
            # stiffer than the rod's own rows (equality rows are stable at any time constant under the discrete
            # integrator): at 2·dt the clamped edge tilted by up to 1e-4 rad under the sheath's friction (≈ 18 µm
            # at the tip), at 0.1·dt by 1.7e-5 rad
            clamp = _fmt((0.1 * spec.timestep, 1.0))
            for i in (0, 1):
                self.add_equality("connect", name=f"{spec.name}_clamp_{i}", body1=f"{spec.name}_{i}", body2=parent,
                                  anchor="0 0 0", solref=clamp, solimp=solimp)
            twist = {"joint2": roll_joint} if roll_joint is not None else {}
            self.add_equality("joint", name=f"{spec.name}_clamp_twist", joint1=f"{spec.name}_twist_0", **twist,
                              solref=clamp, solimp=solimp)
        ET.SubElement(fc, "edge", equality="true", solref=solref, solimp=solimp)  # inextensible
        ET.SubElement(
            fc,
            "elasticity",
            young=_fmt(spec.young),
            shear=_fmt(spec.shear),
            poisson="0.3",
            damping=_fmt(spec.damping),
        )
        ET.SubElement(
            fc,
            "contact",
            condim="3",
            friction=_fmt(spec.friction),
            solref=solref,
            solimp=_fmt(spec.contact_solimp),
            selfcollide="none",
        )
        # Metadata for the rod-state reader and apply_runtime_settings (the model then describes itself).
        self.add_numeric(f"{spec.name}_s0", -spec.base_length)
        self.add_numeric(f"{spec.name}_sensed_length", spec.sensed_length)
        self.add_numeric(f"{spec.name}_vertex_damping", spec.dof_damping)
        self.add_numeric(f"{spec.name}_fiber_offset", spec.fiber_offset)
        return rod

    # -- output --
    def _timestep(self) -> float:
        if self.timestep is not None:
            return float(self.timestep)
        return self.rods[0].spec.timestep if self.rods else 2e-3

    def to_element(self) -> ET.Element:
        root = ET.Element("mujoco", model=self.name)
        ET.SubElement(root, "compiler", angle="radian", autolimits="true")
        g_scale = self.rods[0].spec.gravity_scale if self.rods else 1.0
        opt = {
            "timestep": _fmt(self._timestep()),
            "integrator": "discrete",  # required for rod bending in MuJoCo 4.0 (docs/simulation.md §1)
            "solver": self.solver,
            "gravity": _fmt(self.gravity * g_scale),
        }
        if self.rods:
            opt["tolerance"] = _fmt(min(r.spec.solver_tolerance for r in self.rods))
            opt["iterations"] = _fmt(max(int(r.spec.solver_iterations) for r in self.rods))
        opt.update({k: _fmt(v) for k, v in self.options.items()})
        ET.SubElement(root, "option", opt)
        for el in (self._custom, self._world, self._contact, self._equality):
            if len(el) or el is self._world:
                root.append(el)
        return root

    def to_xml(self) -> str:
        """Indented MJCF text of the scene."""
        root = self.to_element()
        ET.indent(root, space="  ")
        return ET.tostring(root, encoding="unicode") + "\n"

    def build(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        """Compile the scene, apply the runtime settings and the :meth:`on_build` hooks; (model, data) after
        ``mj_forward``."""
        xml = self.to_xml()
        try:
            model = mujoco.MjModel.from_xml_string(xml)
        except ValueError as exc:
            raise ValueError(f"Scene {self.name!r}: MuJoCo rejected the generated MJCF: {exc}") from exc
        apply_runtime_settings(model)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        for hook in self._hooks:
            hook(model, data)
        return model, data


# ----------------------------------------------------------------------------------------------------
# Runtime helpers
# ----------------------------------------------------------------------------------------------------


def _flex_id(model: mujoco.MjModel, name: str) -> int:
    fid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, name)
    if fid < 0:
        known = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_FLEX, i) for i in range(model.nflex)]
        raise KeyError(f"model has no rod (flex) named {name!r}; flexes: {known}")
    return fid


def _numeric(model: mujoco.MjModel, name: str) -> np.ndarray | None:
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, name)
    if i < 0:
        return None
    adr, size = model.numeric_adr[i], model.numeric_size[i]
    return np.array(model.numeric_data[adr : adr + size])


def rod_vertex_qpos_addresses(model: mujoco.MjModel, name: str = "cath") -> tuple[np.ndarray, np.ndarray]:
    """Which rod vertices move, and their slide joints' qpos (and dof) addresses.

    Returns
    -------
    vertices : ndarray of int, shape (k,)
        Indices (within the rod) of the vertices that have their own body with 3 slide joints.
    qposadr : ndarray of int, shape (k, 3)
        qpos addresses of those slide joints (along the parent body's x, y, z axes, in this order).
    """
    fid = _flex_id(model, name)
    va, nv = model.flex_vertadr[fid], model.flex_vertnum[fid]
    bodies = model.flex_vertbodyid[va : va + nv]
    verts, qadr = [], []
    for i, b in enumerate(bodies):
        if model.body_jntnum[b] != 3:
            continue  # pinned to the parent body
        j0 = model.body_jntadr[b]
        if not np.all(model.jnt_type[j0 : j0 + 3] == mujoco.mjtJoint.mjJNT_SLIDE):
            continue
        verts.append(i)
        qadr.append(model.jnt_qposadr[j0 : j0 + 3])
    return np.array(verts, dtype=np.int64), np.array(qadr, dtype=np.int64).reshape(-1, 3)


def _vertex_dofadr(model: mujoco.MjModel, name: str) -> np.ndarray:
    fid = _flex_id(model, name)
    va, nv = model.flex_vertadr[fid], model.flex_vertnum[fid]
    out = []
    for b in model.flex_vertbodyid[va : va + nv]:
        if model.body_jntnum[b] == 3:
            j0 = model.body_jntadr[b]
            out.extend(model.jnt_dofadr[j0 : j0 + 3])
    return np.array(out, dtype=np.int64)


class Warnings(list):
    """MuJoCo's warnings caught since :func:`collect_warnings` made this list (a list that can be weakly held)."""


_collectors: weakref.WeakValueDictionary[int, Warnings] = weakref.WeakValueDictionary()  # by id: lists compare equal


def _caught(msg) -> None:
    text = str(msg).strip()
    for collector in list(_collectors.values()):
        collector.append(text)


#: what the warnings mean, for the commands that report them
WARNINGS_NOTE = "expected at the flex rod's start-up, results unaffected (docs/simulation.md §1)"


def collect_warnings() -> Warnings:
    """Collect MuJoCo's solver warnings in the returned list instead of letting MuJoCo print them mid-line and
    write ``MUJOCO_LOG.TXT`` into the current folder.

    The flex rod's "ill-conditioned stiffness" and "inertia matrix is too close to singular" notes when a scene is
    built or first stepped are expected (docs/simulation.md §1: results are unaffected); callers report how many
    there were (:data:`WARNINGS_NOTE`). Every list made here gets every warning from then on (a command and the
    simulated sources it opens each count theirs), for as long as it is referenced.
    """
    caught = Warnings()
    _collectors[id(caught)] = caught
    mujoco.set_mju_user_warning(_caught)
    return caught


def apply_runtime_settings(model: mujoco.MjModel) -> None:
    """Write what MJCF cannot hold into ``model``: the vertex slide-DOF damping of every rod built by
    :class:`Scene` (custom numeric ``<rod>_vertex_damping``), N·s/m."""
    for f in range(model.nflex):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_FLEX, f)
        value = _numeric(model, f"{name}_vertex_damping") if name else None
        if value is not None and value.size:
            model.dof_damping[_vertex_dofadr(model, name)] = value[0]


def set_rod_positions(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    positions: np.ndarray,
    name: str = "cath",
    *,
    atol: float = 1e-6,
) -> None:
    """Put the rod's vertices at ``positions`` (world frame, m, shape (n_vertices, 3)) with zero velocity.

    Pinned vertices cannot move; their given positions must agree with where they are to ``atol`` (m). The
    rod's twist angles are zeroed and its reference frames (``mjData.plastic``) cleared, so MuJoCo restarts
    them twist-free from the clamped edge at the next step: the rod starts in this shape without twist.
    Calls ``mj_forward``.
    """
    fid = _flex_id(model, name)
    va, nv = model.flex_vertadr[fid], model.flex_vertnum[fid]
    positions = np.asarray(positions, dtype=np.float64)
    if positions.shape != (nv, 3):
        raise ValueError(
            f"set_rod_positions({name!r}): expected positions of shape ({nv}, 3), got {positions.shape}"
        )
    mujoco.mj_kinematics(model, data)
    verts, qadr = rod_vertex_qpos_addresses(model, name)
    pinned = np.setdiff1d(np.arange(nv), verts)
    off = np.abs(data.flexvert_xpos[va + pinned] - positions[pinned]).max(initial=0.0)
    if off > atol:
        raise ValueError(
            f"set_rod_positions({name!r}): pinned vertices {pinned.tolist()} are {off:.3g} m from the "
            "requested "
            f"positions (tolerance {atol} m); place the rod's base pose to match"
        )
    bodies = model.flex_vertbodyid[va + verts]
    parents = model.body_parentid[bodies]
    # Slide joints along the parent's axes: x_world = x_parent + R_parent (body_pos + q).
    rel = positions[verts] - data.xpos[parents]
    local = np.einsum("kji,kj->ki", data.xmat[parents].reshape(-1, 3, 3), rel) - model.body_pos[bodies]
    j0 = model.body_jntadr[bodies]
    axes = model.jnt_axis[j0[:, None] + np.arange(3)]  # (k, 3 joints, 3)
    q = np.linalg.solve(np.transpose(axes, (0, 2, 1)), local[..., None])[..., 0]
    data.qpos[qadr] = q
    # Twist angles and the rod's velocities to zero, reference frames cleared (restart twist-free).
    data.qvel[_vertex_dofadr(model, name)] = 0.0
    for e in range(nv - 1):
        jname = f"{name}_twist_{e}" if e < nv - 2 else f"{name}_twist"
        j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, jname)
        if j >= 0:
            data.qpos[model.jnt_qposadr[j]] = 0.0
            data.qvel[model.jnt_dofadr[j]] = 0.0
    pa = model.flex_plasticadr[fid]
    data.plastic[pa : pa + 6 * (nv - 1) + (nv - 2)] = 0.0
    mujoco.mj_forward(model, data)
