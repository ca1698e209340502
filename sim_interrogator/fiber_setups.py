"""Setups with the sensing fibre as its own body in the catheter's lumen (:mod:`models.lumen_fiber`).

:class:`FiberStatic` holds the catheter in a library shape (connect constraints or a rigid tube) like
``sim://static``; :class:`FiberSheathCycle` drives it in and out of the pre-bent sheath like
``sim://sheath-cycle``. Both put a :class:`models.lumen_fiber.FiberSpec` fibre into the catheter and tell
:class:`~sim_interrogator.sim.SimInterrogator` to read the optics from the fibre's own rod
(:attr:`optics_rod_name`, :meth:`optics_roll`: a constant, the glue holds the roll), its axial strain from the
fibre's tension (:meth:`conditions`), and to disturb the distal grating's peaks while the tip touches the lumen's end
(:meth:`disturb_peaks`). The truth stays the catheter's centreline.

The catheter's base is 40 mm here (10 mm elsewhere; 45 mm when two glue spots 25 mm before the first grating
need it at 50 segments) so that the glue spots fit on it; the sheath's hub is moved back by the difference, so
the sensed region sits where ``sheath-cycle`` puts it.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from models.catheter import CatheterSpec, Pose, Scene
from models.fixtures import SettleError, add_connect_fixture, add_tube_fixture
from models.lumen_fiber import FiberHandle, FiberSpec, LumenCoupler, add_fiber, place_fiber, settle_fiber
from sim_interrogator.setups import Setup, StaticShape
from sim_interrogator.sheath_setups import SheathCycle
from twin import PeakStatus, shapes

__all__ = ["FIBER_BASE_LENGTH", "FiberSheathCycle", "FiberStatic", "TipContact"]

#: m, catheter shaft between the clamp and the first grating in the fibre setups
FIBER_BASE_LENGTH = 0.04


@dataclasses.dataclass(frozen=True)
class TipContact:
    """What tip contact does to the distal grating's peaks (an assumption: no published magnitudes found).

    While the fibre's tip presses on the lumen's end, the transverse load and the facet's back-reflection
    distort the distal grating's spectrum: each of its peaks is lost with probability ``loss`` and otherwise
    shifted by a random ``shift`` (1σ, nm) on top of the mechanical compression (−F/EA, from the contact force
    the model computes).

    Attributes
    ----------
    loss : float
        Probability that a peak of the distal grating is lost per frame in contact.
    shift : float
        1σ of the distortion of the remaining peaks, nm.
    axial_rigidity : float
        EA of the fibre, N (silica, 125 µm: 70 GPa × 12.3e-9 m²).
    """

    loss: float = 0.3
    shift: float = 0.02
    axial_rigidity: float = 860.0


class _FiberMixin:
    """The fibre's share of a setup: its handle and coupler, the optics hooks."""

    fiber: FiberSpec
    handle: FiberHandle | None = None
    coupler: LumenCoupler | None = None
    tip_contact = TipContact()
    optics_rod_name = "fiber"
    actuated = True  # the coupler acts before every step
    _rng: np.random.Generator
    contact_frames = 0
    random_start = True  #: start the fibre at a seeded place within its clearance (False: on the lumen's axis)
    settled = True  #: False when a fibre without fixation was still sliding at the end of settling

    def _add_fiber(self, scene: Scene, rod, world_pose=None) -> None:
        self.handle = add_fiber(scene, rod, self.fiber, world_pose)
        # the seed places the fibre within its clearance (a threaded fibre lies anywhere in its lumen)
        rng = np.random.default_rng([self.seed, 1]) if self.random_start else None
        scene.on_build(lambda m, d: place_fiber(m, d, self.handle, rng))

    def _install(self, model, data, carrier_acceleration=None, traction=None) -> None:
        self.coupler = LumenCoupler(model, data, self.handle, carrier_acceleration, traction)
        self._data = data
        fid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, self.fiber.name)
        self._va, self._nv = int(model.flex_vertadr[fid]), int(model.flex_vertnum[fid])
        self._l0 = np.diff(self.handle.s)

    def optics_roll(self) -> float:
        """The constant roll from MuJoCo's director of the fibre to the catheter's convention, rad (measured once
        after the first step: MuJoCo picks each rod's first reference director by itself). The glue holds the
        roll through joint equalities (:func:`models.lumen_fiber.add_fiber`), so nothing else is needed; without
        fixations nothing holds it, as in a real catheter."""
        return 0.0 if self.coupler is None else self.coupler.roll0

    def fiber_curvature(self, s: np.ndarray) -> np.ndarray:
        """The fibre's own curvature (k_x, k_y) at fibre arc lengths ``s`` (m) now, in the catheter's roll
        convention, 1/m, shape (len(s), 2)."""
        c = self.coupler
        d = c.fiber_reader.read(self._data).darboux_at(s)
        co, si = math.cos(c.roll0), math.sin(c.roll0)
        k1, k2 = co * d[:, 0] + si * d[:, 1], co * d[:, 1] - si * d[:, 0]
        return np.stack([k2, -k1], axis=-1)  # (k_x, k_y) = (κ2, −κ1)

    def curvature_error(self, s: np.ndarray) -> np.ndarray:
        """|k_fiber − k_catheter| at fibre arc lengths ``s`` (m) now, 1/m: what the fibre's own mechanics add to the
        curvature the welded model would read there (both in the catheter's roll convention)."""
        k_c = self.coupler.cath_reader.read(self._data).curvature_at(s)
        return np.linalg.norm(self.fiber_curvature(s) - k_c, axis=-1)

    def roll_loss(self) -> np.ndarray:
        """Roll of the fibre against the catheter at its glued edges now, rad (0 when the glue holds it)."""
        c = self.coupler
        c.fiber_reader.compute(self._data, c._fframes, c._fdarb)
        c.cath_reader.compute(self._data, c._cframes, c._cdarb)
        return c.roll_error(c._fframes, c.glued_edges)

    def fiber_axial_strain(self, grating_s: np.ndarray) -> np.ndarray:
        """The fibre's axial strain at the gratings: its tension from friction and the lumen's end over EA.

        (Not from the rod's edge lengths: the inextensible rod's edge constraints leave a slack of up to 3e-4
        where glue and edges pull against each other, 0.4 nm of spurious wavelength.)"""
        mid = 0.5 * (self.handle.s[1:] + self.handle.s[:-1])
        return np.interp(grating_s, mid, self.coupler.tension / self.tip_contact.axial_rigidity)

    def disturb_peaks(self, t: float, wavelengths: np.ndarray, status: np.ndarray) -> None:
        """Tip contact: compress, distort and drop the distal grating's peaks (in place)."""
        c = self.coupler
        if c is None or not c.tip_contact():
            return
        self.contact_frames += 1
        tc = self.tip_contact
        g = wavelengths.shape[0] - 1
        row = wavelengths[g]
        row *= 1.0 - 0.78 * c.tip_force / tc.axial_rigidity  # 0.78 = 1 − p_e, the strain-optic factor
        row += tc.shift * self._rng.standard_normal(row.shape)
        lost = self._rng.random(row.shape) < tc.loss
        row[lost] = np.nan
        status[g, lost] |= np.uint8(PeakStatus.MISSING)

    def fiber_describe(self) -> dict:
        d = {"fiber": self.fiber.describe()}
        if self.coupler is not None:
            d["fiber"].update(slide_max_m=float(np.abs(self.coupler.slide()).max()),
                              tip_gap_m=self.coupler.tip_gap(), contact_frames=self.contact_frames)
        return d


def base_length_for(fiber: FiberSpec, segments: int) -> float:
    """The catheter's base length, m: :data:`FIBER_BASE_LENGTH`, or longer when the glue spots need it (the
    catheter's first two vertices are clamped, so the fibre's base must lie beyond two edges)."""
    rest = CatheterSpec().sensed_length + CatheterSpec().tip_length
    need = (-fiber.base_s() + 2 * rest / segments) / (1 - 2 / segments) + 1e-4
    return max(FIBER_BASE_LENGTH, math.ceil(need * 200) / 200)  # in whole 5 mm


def _fiber_spec(clearance, friction, fixations, dx_prox, dx_dist, offset, glued, lead_tension,
                hub_share=FiberSpec.hub_share) -> FiberSpec:
    return FiberSpec(clearance=float(clearance), friction=float(friction), n_fixations=int(fixations),
                     dx_prox=float(dx_prox), dx_dist=float(dx_dist), offset=float(offset), glued=bool(glued),
                     lead_tension=float(lead_tension), hub_share=float(hub_share))


class FiberStatic(_FiberMixin, Setup):
    """A library shape held by connect constraints or a 3 mm tube, with the fibre in a lumen.

    Parameters
    ----------
    shape : str
    fixture : {"connect", "tube"}
    clearance, friction, fixations, dx_prox, dx_dist, offset, glued, lead_tension
        The :class:`models.lumen_fiber.FiberSpec` (m, –, count, m, m, m, bool, N).
    segments : int
    settle_time : float
        s.
    seed : int
        Seed of the fibre's start within its clearance and of the tip-contact distortion.
    """

    name = "fiber-static"

    def __init__(self, shape: str = "helix", fixture: str = "connect", clearance: float = 0.0,
                 friction: float = 0.2, fixations: int = 2, dx_prox: float = 0.015, dx_dist: float = 0.002,
                 offset: float = 0.0, glued: bool = False, lead_tension: float = FiberSpec.lead_tension,
                 segments: int = 100, settle_time: float = 10.0, seed: int = 0):
        if fixture not in ("connect", "tube"):
            raise ValueError(f"sim://{self.name}: fixture must be connect or tube, got {fixture!r}")
        self.curve = shapes.get(shape)
        self.fixture_kind = fixture
        self.fiber = _fiber_spec(clearance, friction, fixations, dx_prox, dx_dist, offset, glued, lead_tension)
        self.spec = CatheterSpec(n_segments=int(segments), base_length=base_length_for(self.fiber, int(segments)))
        self.settle_time = float(settle_time)
        self.seed = int(seed)
        self._rng = np.random.default_rng(seed)
        self.fixture = None

    def build(self):
        scene = Scene(f"fiber-{self.fixture_kind}:{self.curve.name}")
        add = add_connect_fixture if self.fixture_kind == "connect" else add_tube_fixture
        self.fixture = add(scene, self.curve, self.spec)
        self._add_fiber(scene, self.fixture.rod)
        model, data = scene.build()
        self._install(model, data)
        return model, data

    def prepare(self, model, data, progress=None):
        def step():
            self.coupler.apply(model, data)
            mujoco.mj_step(model, data)

        try:
            self.settle_s = settle_fiber(model, data, step, max_time=self.settle_time, label=f"sim://{self.name}")
        except SettleError:
            if self.fiber.n_fixations or self.fiber.glued:
                raise
            # A fibre without fixation may never come to rest: it slides along the lumen (what the guideline
            # is about). Read it as it is, and say so.
            self.settled = False
            self.settle_s = self.settle_time

    def actuate(self, model, data, t):
        self.coupler.apply(model, data)

    def conditions(self, t, grating_s):
        return 0.0, self.fiber_axial_strain(grating_s)

    fixture_centreline = StaticShape.fixture_centreline  # the same fixture (self.curve, self.fixture)

    def describe(self):
        return {"setup": self.name, "shape": self.curve.name, "fixture": self.fixture_kind,
                "segments": self.spec.n_segments, **self.fiber_describe()}


class FiberSheathCycle(_FiberMixin, SheathCycle):
    """``sheath-cycle`` (in and out of a pre-bent sheath) with the fibre in a lumen.

    Parameters are those of :class:`~sim_interrogator.sheath_setups.SheathCycle` and the fibre's (see
    :class:`FiberStatic`), plus ``hub_share``: the fraction of the hub actuator's axial force that reaches the
    fibre's lead (:class:`models.lumen_fiber.FiberSpec`); ``sheath_friction`` is the sheath's μ.
    """

    name = "fiber-sheath-cycle"

    def __init__(self, cycles: int = 3, protrusion: float = 0.05, withdraw: float = 0.06, speed: float = 0.05,
                 dwell: float = 0.5, clearance: float = 0.0, friction: float = 0.2, fixations: int = 2,
                 dx_prox: float = 0.015, dx_dist: float = 0.002, offset: float = 0.0, glued: bool = False,
                 lead_tension: float = FiberSpec.lead_tension, hub_share: float = FiberSpec.hub_share,
                 sheath_friction: float = 0.2, segments: int = 100, settle_time: float = 10.0, seed: int = 0):
        fiber = _fiber_spec(clearance, friction, fixations, dx_prox, dx_dist, offset, glued, lead_tension, hub_share)
        base = base_length_for(fiber, int(segments))
        extra = base - CatheterSpec().base_length
        super().__init__(cycles=cycles, protrusion=protrusion - extra, withdraw=withdraw, speed=speed, dwell=dwell,
                         friction=sheath_friction, segments=segments, settle_time=settle_time, seed=seed)
        self.spec = dataclasses.replace(self.spec, base_length=base)
        self.protrusion = float(protrusion)
        self.fiber = fiber
        self.seed = int(seed)
        self._rng = np.random.default_rng(seed)

    def extend_scene(self, scene, rod) -> None:
        # MuJoCo hangs from a body with joints only rods pinned to it: the fibre hangs from the world at the
        # hub's start pose and is carried with the hub's acceleration (models/lumen_fiber.py)
        hub = self.world @ Pose(self.curve.positions(self.hub_start), self.curve.frames(self.hub_start))
        self._add_fiber(scene, rod, hub)

    def build(self):
        model, data = super().build()
        slide = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "hub_slide")
        dof = int(model.jnt_dofadr[slide])
        hub = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "hub")

        def carrier(data):  # the hub slides along its own z axis (the sheath's guide)
            return data.qacc[dof] * data.xmat[hub].reshape(3, 3)[:, 2]

        act, f = self._act[0], self.fiber

        def traction(data):  # the lead's pull, less the hub's push's share (pushing in slackens the lead)
            return f.lead_tension - f.hub_share * data.actuator_force[act]

        self._install(model, data, carrier, traction)
        return model, data

    def prepare(self, model, data, progress=None):
        SheathCycle.actuate(self, model, data, 0.0)

        def step():
            self.coupler.apply(model, data)
            mujoco.mj_step(model, data)

        self.settle_s = settle_fiber(model, data, step, max_time=self.settle_time,
                                     label=f"sim://{self.name} (catheter and fibre in the sheath)")

    def actuate(self, model, data, t):
        SheathCycle.actuate(self, model, data, t)
        self.coupler.apply(model, data)

    def conditions(self, t, grating_s):
        return 0.0, self.fiber_axial_strain(grating_s)

    def describe(self):
        return {**super().describe(), **self.fiber_describe()}
