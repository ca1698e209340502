"""The sensing fibre as its own body in the catheter's lumen (docs/integration.md).

Elsewhere in the twin the fibre is welded to the catheter's centreline: its strains are the catheter's
curvature. Here it is a second MuJoCo rod — a thin ``<flexcomp dim="1">`` discrete elastic rod with the
fibre's own bending and torsional stiffness — lying in a lumen of the catheter, so that the clearance,
the friction with the lumen, the fixations at its base and the gap at its tip show up in its own
curvature, twist and axial position, and from there in the wavelengths.

Model (the choices and the measurements behind them are in docs/integration.md):

* **The lumen** is the curve L(σ) = x(σ) + offset · d1(σ) of the catheter rod (its centreline x and the
  material director d1 of the edge at catheter arc length σ), of radial ``clearance`` around the fibre.
  MuJoCo cannot put one rod's collision geometry inside another's (its contacts are between solids), so the
  wall is a penalty force computed in numpy before every step (:class:`LumenCoupler`): on each fibre vertex
  farther than the clearance from the lumen's axis, a radial spring and a damper over the cross-section, and
  regularised Coulomb friction of coefficient ``friction`` (a low-friction lining is a lower coefficient)
  against the fibre's sliding along the lumen. Each vertex keeps its own lumen coordinate σ, updated by
  projection every step, so the fibre can slide along the lumen.
* **One-way coupling**: the wall forces act on the fibre only. The fibre's bending stiffness is 1/200 of the
  catheter's and the wall forces are millinewtons, so the catheter's shape is that of the welded model.
  Glue spots, being MuJoCo ``connect`` constraints, act on both bodies.
* **Fixations** (``n_fixations`` glue spots of ``glue_length`` at the fibre's base, the most distal one
  ``dx_prox`` before the first grating, ``fixation_spacing`` apart): MuJoCo connect constraints tie each fibre
  vertex of a spot to its point on the lumen (the anchor on the catheter's side is moved with d1 every step
  when the lumen is off-axis), and MuJoCo joint equalities tie the twist hinge of each glued fibre edge to the
  catheter edge's beside it: the glue holds the roll, implicitly. ``glued`` glues the whole fibre (the welded
  reference).
* **Traction at the base**: the fibre's proximal lead pulls with ``lead_tension`` (plus, in a sheath, a share
  ``hub_share`` of the hub's axial force), reacted by the glue on one side of the fibre, so a couple
  T · ``glue_eccentricity`` enters the fibre where it leaves the most distal glue spot; the lumen's wall and
  the fibre's stiffness decide how far it reaches (ramped in over :data:`TRACTION_RAMP`).
* **The tip** ends ``tail`` beyond the last grating, ``dx_dist`` short of the lumen's end; at or beyond the end
  a stiff axial spring pushes it back, and :meth:`LumenCoupler.tip_contact` reports the contact.
* **Quasi-static scaling**: like the catheter, the fibre carries a simulated mass far above its real one
  (its real ≈ 60 µg/m would need microsecond steps); its weight is cancelled (by an applied force) because the
  real weight is negligible against its stiffness. It hangs from the catheter's parent body (the world or the
  sheath's hub), so the hub carries it rigidly; a small viscous drag against the lumen settles it.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from models import _lumen_kernels
from models.catheter import CatheterSpec, Pose, RodHandle, Scene, _fmt, set_rod_positions
from models.rod_state import RodReader
from twin._numba_entry import compiled_entry

__all__ = ["PLACEMENT_RAMP", "TRACTION_RAMP", "FiberHandle", "FiberSpec", "LumenCoupler", "add_fiber", "place_fiber",
           "settle_fiber"]

#: s, over which the lead's traction is ramped in from the first step (quasi-static loading)
TRACTION_RAMP = 1.0
#: m, over which a randomly placed fibre leaves the axis beyond its most distal glue spot (place_fiber)
PLACEMENT_RAMP = 0.01


@dataclass(frozen=True)
class FiberSpec:
    """A sensing fibre in a lumen of the catheter (SI units).

    Parameters
    ----------
    name : str
        The fibre rod's flexcomp name.
    clearance : float
        Radial clearance between fibre and lumen wall, m (lumen radius − fibre radius).
    friction : float
        Coulomb coefficient fibre–lumen (≈ 0.05 with a PTFE lining, 0.2–0.3 against a polymer wall).
    n_fixations : int
        Glue spots at the fibre's base (0, 1 or 2 in the reference paper's guideline).
    dx_prox : float
        Distance from the most distal fixation to the first grating (fibre s = 0), m.
    fixation_spacing : float
        Distance between consecutive glue spots, m.
    glue_length : float
        Length of each glue spot, m (at least one fibre vertex is always glued).
    dx_dist : float
        Gap between the fibre's tip and the lumen's end, m (≤ 0: the tip is pressed against it).
    tail : float
        Fibre beyond the last grating, m.
    offset : float
        Distance of the lumen's axis from the catheter's neutral axis along d1, m.
    glued : bool
        Glue the fibre along its whole length (the welded reference; needs ``offset == 0``).
    bending_stiffness, torsional_stiffness : float
        EI and GJ of the fibre, N·m² (a 125 µm silica fibre with a polyimide/ormocer coat: EI ≈ 1e-6).
    diameter : float
        Outer diameter of the coated fibre, m.
    vertex_mass : float
        Simulated mass per fibre vertex, kg (quasi-static; see the module docstring).
    wall_stiffness : float
        Normal penalty stiffness per vertex, N/m. Bounded by the explicit-force stability limit
        ``vertex_mass / timestep²`` (2500 N/m at the defaults); 600 N/m lets ≈ 10 µm into the wall.
    wall_damping : float
        Normal damping per vertex, N·s/m. 0.3 let the fibre in a 25 1/m arc with 0.1 mm clearance oscillate
        against the wall with growing amplitude (unstable after ≈ 0.5 s); 2.0 (c·dt/m = 0.4) settles it.
    slip_speed : float
        Regularisation speed of the Coulomb friction, m/s (below it friction is viscous). The friction's
        viscosity μN/|v| is applied explicitly and capped at 0.5·m/dt (2.5 N·s/m at the defaults): uncapped,
        μN/slip_speed reached 10 N·s/m at 50 mN of wall force and the fibre went unstable within a second;
        with the cap a load below μN creeps at ≤ F / 2.5 N·s/m instead of sticking.
    drag : float
        Viscous drag per vertex against the lumen's motion, N·s/m: numerical, it settles the fibre where
        nothing else holds it (0.1 mN at 1 mm/s of sliding, below the friction at a loaded contact).
    lead_tension : float
        Axial pull of the fibre's proximal lead (toward the connector), N, reacted by the base glue. An
        assumption (docs/integration.md: no published value); negative is a push.
    hub_share : float
        Fraction of the hub's axial force that reaches the lead in the sheath setups (the shaft carries the
        rest): pushing the hub in shortens the shaft against the lead and slackens it, pulling stretches it.
    glue_eccentricity : float
        Lever of the traction at the most distal glue spot, m: glue on one side of the fibre (its radius), so
        the traction enters the fibre as a couple T·e where it leaves the glue.
    """

    name: str = "fiber"
    clearance: float = 0.0
    friction: float = 0.2
    n_fixations: int = 2
    dx_prox: float = 0.015
    fixation_spacing: float = 0.005
    glue_length: float = 0.002
    dx_dist: float = 0.002
    tail: float = 0.003
    offset: float = 0.0
    glued: bool = False
    bending_stiffness: float = 1.0e-6
    torsional_stiffness: float = 0.8e-6
    diameter: float = 0.2e-3
    vertex_mass: float = 0.01
    wall_stiffness: float = 600.0
    wall_damping: float = 2.0
    slip_speed: float = 1e-3
    drag: float = 0.1
    lead_tension: float = 0.02
    hub_share: float = 0.05
    glue_eccentricity: float = 1e-4

    def __post_init__(self) -> None:
        for k in ("clearance", "friction", "dx_prox", "fixation_spacing", "glue_length", "tail", "offset",
                  "bending_stiffness", "torsional_stiffness", "diameter", "vertex_mass", "wall_stiffness",
                  "wall_damping", "slip_speed", "drag", "hub_share", "glue_eccentricity"):
            v = getattr(self, k)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"FiberSpec.{k}: expected a finite number >= 0, got {v!r}")
        for k in ("dx_dist", "lead_tension"):
            if not (isinstance(getattr(self, k), int | float) and math.isfinite(getattr(self, k))):
                raise ValueError(f"FiberSpec.{k}: expected a finite number, got {getattr(self, k)!r}")
        if self.n_fixations not in (0, 1, 2, 3):
            raise ValueError(f"FiberSpec.n_fixations: expected 0–3, got {self.n_fixations!r}")
        if self.glued and self.offset:
            raise ValueError("FiberSpec: a glued fibre off the axis would have to stretch (an inextensible rod "
                             "cannot); use the welded model's OpticsConfig.fiber_offset instead")

    @property
    def radius(self) -> float:
        return 0.5 * self.diameter

    def fixation_s(self) -> np.ndarray:
        """Fibre arc length of the distal end of each glue spot, m, distal first (empty without fixations)."""
        return -self.dx_prox - self.fixation_spacing * np.arange(self.n_fixations)

    def base_s(self) -> float:
        """Fibre arc length of the fibre's proximal end, m: the last glue spot's start (or where it would be)."""
        n = max(self.n_fixations, 1)
        return -self.dx_prox - self.fixation_spacing * (n - 1) - self.glue_length

    def describe(self) -> dict:
        return {"clearance_m": self.clearance, "friction": self.friction, "n_fixations": self.n_fixations,
                "dx_prox_m": self.dx_prox, "dx_dist_m": self.dx_dist, "offset_m": self.offset,
                "glued": self.glued, "lead_tension_n": self.lead_tension, "hub_share": self.hub_share}


@dataclass(frozen=True)
class FiberHandle:
    """What :func:`add_fiber` put into a scene: the fibre's rest grid on the catheter's vertex grid.

    Attributes
    ----------
    spec : FiberSpec
    catheter : CatheterSpec
    s : ndarray (n,)
        Fibre arc length of the fibre's vertices at rest, m (a subset of the catheter's vertex arc lengths).
    first : int
        Index of the catheter vertex the fibre's first vertex sits on at rest.
    glued : ndarray of bool (n,)
        Vertices held by glue.
    lumen_end : float
        Catheter arc length of the lumen's end, m.
    glued_edges : ndarray of int
        Fibre edges whose roll the glue holds (a joint equality with the catheter edge beside each).
    """

    spec: FiberSpec
    catheter: CatheterSpec
    s: np.ndarray
    first: int
    glued: np.ndarray
    lumen_end: float
    glued_edges: np.ndarray


def add_fiber(scene: Scene, rod: RodHandle, spec: FiberSpec | None = None, world_pose: Pose | None = None
              ) -> FiberHandle:
    """Add the fibre rod in a lumen of ``rod`` (before :meth:`Scene.build`); returns its :class:`FiberHandle`.

    The fibre hangs from the same body as the catheter, or — when that body moves (a hub with joints, from
    which MuJoCo lets hang only a rod pinned to it) — from the world at ``world_pose``, the catheter's base pose
    in the world at ``qpos0``; the caller then gives :func:`install_coupler` the hub's acceleration.

    The fibre's vertices sit on the catheter's vertex grid (same edge length) so that at rest each fibre vertex
    has a catheter vertex beside it; the catheter needs a base long enough for the fixations and a tip long
    enough for the tail and gap.
    """
    spec = spec or FiberSpec()
    cath = rod.spec
    l = cath.segment_length
    cs = cath.vertex_s
    lo = spec.base_s()
    if lo < cs[0] + 2 * l - 1e-12:  # the catheter's first two vertices are clamped: no bodies to glue to
        raise ValueError(f"add_fiber: the fixations reach s = {lo * 1e3:.1f} mm but the catheter starts at "
                         f"{cs[0] * 1e3:.1f} mm; lengthen CatheterSpec.base_length")
    first = int(np.floor((lo - cs[0]) / l + 1e-9))
    tip = cath.sensed_length + spec.tail
    last = int(np.ceil((tip - cs[0]) / l - 1e-9))
    lumen_end = cs[last] + spec.dx_dist
    if lumen_end > cs[-1] + 1e-12:
        raise ValueError(f"add_fiber: the lumen would end {lumen_end * 1e3:.1f} mm beyond the catheter's tip "
                         f"({cs[-1] * 1e3:.1f} mm); lengthen CatheterSpec.tip_length or reduce dx_dist")
    s = cs[first:last + 1]
    glued = np.zeros(s.size, bool)
    if spec.glued:
        glued[:] = True
    else:
        for sf in spec.fixation_s():
            spot = (s <= sf + 1e-9) & (s >= sf - spec.glue_length - 1e-9)
            if not spot.any():  # a glue spot shorter than an edge: glue the vertex nearest to it
                spot[np.argmin(np.abs(s - (sf - 0.5 * spec.glue_length)))] = True
            glued |= spot
    n = s.size - 1
    points = np.zeros((n + 1, 3))
    points[:, 0] = spec.offset
    points[:, 2] = s - cs[0]
    i_rod = math.pi * spec.radius**4 / 4
    parent = scene._parent(rod.parent if world_pose is None else None)
    base = rod.pose if world_pose is None else world_pose
    parent.append(ET.Comment(f" fibre {spec.name!r} in a lumen of {cath.name!r}: {s[0] * 1e3:.1f} to {s[-1] * 1e3:.1f}"
                             f" mm, clearance {spec.clearance * 1e6:.0f} um, {spec.n_fixations} fixation(s) "))
    fc = ET.SubElement(parent, "flexcomp", name=spec.name, type="direct", dim="1", radius=_fmt(spec.radius),
                       mass=_fmt(spec.vertex_mass * (n + 1)), pos=_fmt(base.pos), quat=_fmt(base.quat),
                       rgba="0.2 0.5 0.95 1", point=_fmt(points),
                       element=_fmt(np.repeat(np.arange(n + 1), 2)[1:-1]))
    solref = _fmt(cath.solref)
    ET.SubElement(fc, "edge", equality="true", solref=solref, solimp=_fmt(cath.solimp))
    ET.SubElement(fc, "elasticity", young=_fmt(spec.bending_stiffness / i_rod),
                  shear=_fmt(spec.torsional_stiffness / (2 * i_rod)), poisson="0.3", damping=_fmt(cath.damping))
    ET.SubElement(fc, "contact", contype="0", conaffinity="0")  # the lumen wall is LumenCoupler's
    for k in np.flatnonzero(glued):
        # Fibre vertex k beside catheter vertex first + k (both bodies translate only): the connect's anchor on
        # the catheter's side is the lumen offset, rewritten by the coupler when the lumen is off-axis.
        scene.add_equality("connect", name=f"{spec.name}_glue_{k}", body1=f"{spec.name}_{k}",
                           body2=f"{cath.name}_{first + k}", anchor="0 0 0", solref=solref, solimp=_fmt(cath.solimp))
    edges = glued_edges(glued)
    for e in edges:
        # The glue holds the roll: the fibre edge's twist angle equals that of the catheter edge beside it. Both
        # angles turn the edges' reference directors, which MuJoCo transports in time along the same tangents
        # (the glue keeps them parallel), so their difference stays what it was at the first step: a constant
        # roll, which the coupler measures once (LumenCoupler.roll0). An implicit constraint: explicit roll
        # springs on the twist bodies' tiny inertia could not hold it (docs/integration.md).
        scene.add_equality("joint", name=f"{spec.name}_glue_roll_{e}", joint1=_twist_joint(spec.name, e, n),
                           joint2=_twist_joint(cath.name, first + e, cath.n_segments), polycoef="0 1 0 0 0",
                           solref=solref, solimp=_fmt(cath.solimp))
    scene.add_numeric(f"{spec.name}_s0", s[0])
    scene.add_numeric(f"{spec.name}_sensed_length", cath.sensed_length)
    scene.add_numeric(f"{spec.name}_vertex_damping", cath.dof_damping)
    return FiberHandle(spec, cath, s, first, glued, float(lumen_end), edges)


def _twist_joint(rod: str, edge: int, n_edges: int) -> str:
    """MuJoCo's name of the twist hinge of ``edge`` of a rod with ``n_edges`` edges (flexcomp dim=1)."""
    return f"{rod}_twist" if edge == n_edges - 1 else f"{rod}_twist_{edge}"


def glued_edges(glued: np.ndarray) -> np.ndarray:
    """Fibre edges whose roll the glue holds: those with both vertices glued or, for a glue spot shorter than an
    edge (one vertex), the edge distal of it (proximal at the fibre's tip)."""
    both = glued[:-1] & glued[1:]
    lone = np.flatnonzero(glued & ~np.r_[False, both] & ~np.r_[both, False])
    out = set(np.flatnonzero(both).tolist())
    out.update(int(min(k, glued.size - 2)) for k in lone)
    return np.array(sorted(out), dtype=np.int64)


def place_fiber(model: mujoco.MjModel, data: mujoco.MjData, handle: FiberHandle,
                rng: np.random.Generator | None = None) -> None:
    """Put the fibre on the lumen's axis of the catheter as it is now, at rest and untwisted (calls
    ``mj_forward``). Run it after the catheter has been placed (e.g. as a later :meth:`Scene.on_build` hook).

    With ``rng`` and a clearance, the fibre beyond its most distal glue spot starts off the axis instead, as a
    threaded fibre lies anywhere in its lumen: by a random fraction of the clearance toward a random direction
    of the cross-section, reached smoothly over :data:`PLACEMENT_RAMP` from the glue (the whole fibre without
    fixations)."""
    state = RodReader(model, handle.catheter.name).read(data)
    pts = state.positions_at(handle.s)
    frames = state.frames_at(handle.s)
    if handle.spec.offset:
        pts = pts + handle.spec.offset * frames[:, :, 0]
    if rng is not None and handle.spec.clearance > 0:
        r = handle.spec.clearance * rng.uniform()
        psi = rng.uniform(0.0, 2 * math.pi)
        glued = np.flatnonzero(handle.glued)
        s0 = handle.s[glued.max()] if glued.size else -np.inf
        w = np.clip((handle.s - s0) / PLACEMENT_RAMP, 0.0, 1.0)
        pts = pts + (r * w)[:, None] * (math.cos(psi) * frames[:, :, 0] + math.sin(psi) * frames[:, :, 1])
    set_rod_positions(model, data, pts, handle.spec.name)


class LumenCoupler:
    """The lumen's wall, friction, end and roll fixations acting on the fibre: :meth:`apply` before every step.

    It writes ``mjData.qfrc_applied`` of the fibre's degrees of freedom (a setup calls it from its ``actuate``).
    Not MuJoCo's passive-force callback: that one is global to the process, and MuJoCo's compiler calls it on
    models under construction, where the Python bindings fail ("engine error: Python exception raised").

    ``carrier_acceleration(data)`` → (3,) m/s², world: the acceleration of the body the catheter hangs from
    when the fibre hangs from the world (see :func:`add_fiber`).
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, handle: FiberHandle,
                 carrier_acceleration: Callable[[mujoco.MjData], np.ndarray] | None = None,
                 traction: Callable[[mujoco.MjData], float] | None = None) -> None:
        self.handle = h = handle
        self.carrier_acceleration = carrier_acceleration
        self.traction = traction or (lambda data: handle.spec.lead_tension)
        self.spec = spec = handle.spec
        cath = handle.catheter
        self.cath_reader = RodReader(model, cath.name)
        self.fiber_reader = RodReader(model, spec.name)
        nf = handle.s.size
        # the catheter read through views of ``data`` taken once (RodView): its frames are the coupler's
        self._cview = self.cath_reader.bind(data)
        self._cframes, self._cdarb = self._cview.frames, self._cview.darboux
        self._fframes = np.empty((nf - 1, 3, 3))
        self._fdarb = np.empty((nf - 2, 3))
        fid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, spec.name)
        bodies = model.flex_vertbodyid[model.flex_vertadr[fid]: model.flex_vertadr[fid] + nf]
        if np.any(model.body_jntnum[bodies] != 3):
            raise ValueError(f"LumenCoupler: every vertex of fibre {spec.name!r} must move (3 slide joints)")
        self._parent = int(model.body_parentid[bodies[0]])
        cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, cath.name)
        cb = model.flex_vertbodyid[model.flex_vertadr[cid] + model.flex_vertnum[cid] - 1]
        self._cath_parent = int(model.body_parentid[cb])
        j0 = model.body_jntadr[bodies]
        self._dof = model.jnt_dofadr[j0[:, None] + np.arange(3)]  # (nf, 3)
        self._axes = model.jnt_axis[j0[:, None] + np.arange(3)]  # (nf, 3 joints, 3) in the parent frame
        # The fibre's weight is cancelled by an applied force: body_gravcomp written after compiling does nothing
        # (MuJoCo counts gravity-compensated bodies when it compiles), and the flexcomp's vertex bodies take no
        # gravcomp attribute. Uncancelled, the 100× simulated weight (1 mN per vertex) compressed a fibre standing
        # on its glue by 0.07 N and buckled it into a helix against the wall (curvature 3–4 1/m, 0.1 mm clearance).
        self._weight = spec.vertex_mass * model.opt.gravity.copy()
        self.glued_edges = h.glued_edges  #: fibre edges whose roll the glue holds
        self._glue_eq = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_EQUALITY, f"{spec.name}_glue_{k}")
                                  for k in np.flatnonzero(h.glued)], dtype=int)
        self._glue_idx = np.flatnonzero(h.glued)
        # the traction's couple acts on the first free edge beyond the most distal glued vertex (none when the
        # whole fibre is glued or nothing is)
        k = int(self._glue_idx.max()) if self._glue_idx.size else nf - 1
        self._couple_k = k if k < nf - 1 else None
        self._t_first: float | None = None
        self.glue_moment = 0.0  # N·m, the couple T·e entering the fibre at the most distal glue spot (last step)
        cs = cath.vertex_s
        self._cs0, self._l = float(cs[0]), cath.segment_length
        self.sigma = handle.s.copy()  # lumen coordinate (catheter arc length) of each fibre vertex, m
        self._free = ~h.glued
        self._prev_t: float | None = None
        self._prev_p = np.zeros((nf, 3))  # lumen points at the fibre's vertices, previous step
        self._p = np.zeros((nf, 3))
        self._v_lumen = np.zeros((nf, 3))
        self._force = np.zeros((nf, 3))
        self.roll0 = 0.0
        self._roll_ready = False
        self.tip_force = 0.0  # N, axial push of the lumen's end on the tip (last step)
        self.normal = np.zeros(nf)  # N, wall force per vertex (last step)
        self.tension = np.zeros(nf - 1)  # N, axial force per fibre edge from the wall and the end (last step)
        self.calls = 0
        self._bind(model, data)

    def _bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Views of ``model``'s and ``data``'s arrays (MuJoCo keeps them where they are), the work arrays and the
        compiled overload of :func:`models._lumen_kernels.coupler_step` for their types (twin/_numba_entry.py)."""
        self._model, self._data = model, data
        nf = self.sigma.size
        self._x_f = data.flexvert_xpos[self.fiber_reader._va: self.fiber_reader._va + nf]
        self._fplastic = data.plastic[self.fiber_reader._pa: self.fiber_reader._pa + 6]
        self._dof = np.ascontiguousarray(self._dof, dtype=np.int64)
        self._axes = np.ascontiguousarray(self._axes, dtype=np.float64)
        self._axes_w = np.zeros((nf, 3, 3))
        self._v_f = np.zeros((nf, 3))
        self._carrier_force = np.zeros(3)
        self._glue_eq = self._glue_eq.astype(np.int64)
        self._glue_idx = self._glue_idx.astype(np.int64)
        self._visc_cap = 0.5 * self.spec.vertex_mass / model.opt.timestep
        spec, h, d = self.spec, self.handle, data
        # the kernel's arguments that stay put, in three runs around those that change per call
        self._args_frames = self._cview.kernel_arguments()
        self._args_lumen = (self._cs0, self._l, spec.offset, self._x_f, d.qvel, self._dof, self._axes,
                            d.xmat[self._parent], self._axes_w, self._v_f, self.sigma, self._free, self._prev_p)
        self._args_forces = (self._v_lumen, spec.drag, spec.clearance, spec.wall_stiffness, spec.wall_damping,
                             spec.friction, spec.slip_speed, self._visc_cap, h.lumen_end, self._p, self._force,
                             self.normal, self.tension, self._weight, self._carrier_force,
                             -1 if self._couple_k is None else self._couple_k)
        self._args_glue = (h.first, d.qfrc_applied, self._glue_eq, self._glue_idx, model.eq_data,
                           d.xmat[self._cath_parent])
        self._kernel = compiled_entry(_lumen_kernels.coupler_step, *self._args_frames, True, *self._args_lumen, 0.0,
                                      False, *self._args_forces, 0.0, *self._args_glue)

    def _step(self, read_frames: bool, dt: float, advance: bool, moment: float) -> float:
        """One call of the compiled step (:func:`models._lumen_kernels.coupler_step`); the tip force, N."""
        return self._kernel(*self._args_frames, read_frames, *self._args_lumen, dt, advance, *self._args_forces,
                            moment, *self._args_glue)

    # -- geometry --
    def lumen(self, x: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Lumen axis points (n, 3), tangents (n, 3) and d1 (n, 3) at catheter arc lengths ``sigma``."""
        u = (sigma - self._cs0) / self._l
        j = np.clip(np.floor(u).astype(np.int64), 0, x.shape[0] - 2)
        w = (u - j)[:, None]
        f = self._cframes[j]
        d1, t = f[:, :, 0], f[:, :, 2]
        p = (1.0 - w) * x[j] + w * x[j + 1] + self.spec.offset * d1
        return p, t, d1

    def roll_error(self, frames_f: np.ndarray, edges: np.ndarray) -> np.ndarray:
        """Roll of the fibre's material frame against the catheter's at fibre edges ``edges``, rad."""
        c, s = math.cos(self.roll0), math.sin(self.roll0)
        f = frames_f[edges]
        d1f = c * f[:, :, 0] + s * f[:, :, 1]  # the fibre's d1 in the catheter's convention
        cf = self._cframes[self.handle.first + edges]
        return np.arctan2(np.einsum("ni,ni->n", d1f, cf[:, :, 1]), np.einsum("ni,ni->n", d1f, cf[:, :, 0]))

    def calibrate_roll(self, data: mujoco.MjData) -> float:
        """Fix the constant roll between MuJoCo's director of the fibre and the catheter's convention (d1 = the
        base's x axis), from the present state (call after the first step, with the fibre at rest beside the
        catheter's grid)."""
        self.cath_reader.compute(data, self._cframes, self._cdarb)
        self.fiber_reader.compute(data, self._fframes, self._fdarb)
        self.roll0 = 0.0
        self.roll0 = -float(np.median(self.roll_error(self._fframes, np.arange(self._fframes.shape[0]))))
        return self.roll0

    # -- the forces --
    def apply(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Write the lumen's forces on the fibre for the next step into ``data.qfrc_applied`` (the ``model`` and
        ``data`` the coupler was made with)."""
        if data is not self._data or model is not self._model:
            raise ValueError("LumenCoupler.apply: called with another model or data than it was made with")
        self.calls += 1
        # the lumen's velocity is by differences over steps (the catheter is a quasi-static rod)
        tnow = float(data.time)
        advance = self._prev_t is None or tnow > self._prev_t
        dt = tnow - self._prev_t if self._prev_t is not None and tnow > self._prev_t else 0.0
        # the simulated mass's weight is cancelled and, for a fibre hung from the world, the hub's acceleration
        # carried along (d'Alembert): artefacts of the quasi-static mass, left out of the tension read-out
        if self.carrier_acceleration is not None:
            np.multiply(self.spec.vertex_mass, self.carrier_acceleration(data), out=self._carrier_force)
        moment = self._couple_moment(data) if self._couple_k is not None else 0.0
        # the catheter's frames, the lumen's coordinates, wall, friction, end, glue couple, the tension read-out,
        # the generalised forces and the glue's anchors: one compiled call (models/_lumen_kernels.py)
        tip = self._step(True, dt, advance, moment)
        if tip != tip:  # the catheter's plastic is still zero: its frames as MuJoCo restarts them
            self._cview.restart()
            tip = self._step(False, dt, advance, moment)
        self.tip_force = float(tip)
        if advance:
            self._prev_t = tnow
        if not self._roll_ready and (self._fplastic[3] or self._fplastic[4] or self._fplastic[5]):
            self.calibrate_roll(data)  # MuJoCo has chosen the fibre's reference directors (after the first step)
            self._roll_ready = True

    def _couple_moment(self, data: mujoco.MjData) -> float:
        """The couple T·e of the lead's traction T through the eccentric glue, N·m (also :attr:`glue_moment`): it
        acts on the fibre's first free edge as a force pair ±T·e/l across it (:func:`models._lumen_kernels.
        coupler_step`).

        The glue sits on the catheter's d1 side of the fibre (an assumption: which side only turns the
        disturbance's direction). The glue pulls that side of the fibre's surface distally (T > 0) while the lead
        pulls the axis proximally, so the couple is e·T (d1 × t) = −e·T d2: it tilts the free edge toward −d1.
        The fibre's rotation at the glue's exit is held by its own bending across the last glued vertex; beyond,
        the lumen's wall and the fibre's stiffness decide how fast the moment dies out."""
        # ramped in over TRACTION_RAMP from the first step: quasi-static loading, no impulse on the heavy
        # (quasi-static scaled) fibre
        if self._t_first is None:
            self._t_first = float(data.time)
        ramp = min(1.0, (float(data.time) - self._t_first) / TRACTION_RAMP)
        self.glue_moment = ramp * float(self.traction(data)) * self.spec.glue_eccentricity
        return self.glue_moment

    # -- observables --
    def slide(self) -> np.ndarray:
        """Axial slide of each fibre vertex along the lumen since rest, m (positive: toward the tip)."""
        return self.sigma - self.handle.s

    def tip_gap(self) -> float:
        """Lumen's end minus the fibre tip's lumen coordinate, m (≤ 0: in contact)."""
        return float(self.handle.lumen_end - self.sigma[-1])

    def tip_contact(self) -> bool:
        return self.tip_gap() <= 0.0


def settle_fiber(model: mujoco.MjModel, data: mujoco.MjData, step: Callable[[], None], *, tol: float = 1e-6,
                 window: float = 0.05, max_time: float = 10.0, min_time: float = TRACTION_RAMP,
                 label: str = "fiber") -> float:
    """Step (``step()`` applies the coupler and steps once) until no flex vertex moves more than ``tol`` (m) over
    ``window`` (s), and at least ``min_time`` (s: the lead's traction is ramped in over it); the settling time
    (s). Raises ``SettleError`` after ``max_time`` or on instability.

    :func:`models.fixtures.settle` steps MuJoCo in blocks; the fibre needs its coupler before every step."""
    from models.fixtures.settle import UNSTABLE_WARNINGS, SettleError

    warned = [data.warning[w].number for w in UNSTABLE_WARNINGS]
    n = max(1, round(window / model.opt.timestep))
    t0 = data.time
    while True:
        start = data.flexvert_xpos.copy()
        for _ in range(n):
            step()
        moved = np.linalg.norm(data.flexvert_xpos - start, axis=1)
        if not np.all(np.isfinite(moved)) or [data.warning[w].number for w in UNSTABLE_WARNINGS] != warned:
            raise SettleError(f"{label}: the simulation became unstable while settling the fibre")
        if moved.max() < tol and data.time - t0 >= min_time:
            return float(data.time - t0)
        if data.time - t0 > max_time:
            raise SettleError(f"{label}: not settled after {max_time:g} s simulated: a vertex still moved "
                              f"{moved.max() * 1e6:.2f} µm in {window:g} s (tolerance {tol * 1e6:.3g} µm)")
