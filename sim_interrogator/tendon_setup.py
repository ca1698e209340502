"""``sim://tendon``: a catheter whose distal section is steered back and forth by pull-wires.

The mechanics
-------------
A steerable catheter carries a pull-wire in a lumen at distance r_t from its axis. Along the shaft the wire runs
inside a compression coil; it is anchored at the tip (a pull ring) and the coil ends where the deflectable
section begins. The wire tension T and the coil's compression cancel along the shaft, which stays unloaded;
the deflectable section, between the coil's end and the anchor, carries a bending moment T·r_t about its d2
axis (the wire at +d1 pulls the tip toward +d1) and an axial compression T.

MuJoCo's flex vertices carry no rotating sites for a ``<spatial>`` tendon, so the wire is applied as its
equivalent load (docs/simulation.md §5) through ``mjData.xfrc_applied`` on the vertex bodies. The section's
internal moment from the wire is m(s) = T·r_t·d2(s), following the section's own material frame. Discretely,
the moment across vertex i is m_i = T·r_t·d̄2_i (d̄2_i the normalised mean of the adjacent edges' d2), zero at the
coil's end and at the free tip; edge e then carries the couple C_e = m_e − m_{e+1}, applied as the force pair
±(C_e × t_e)/l_e on its two vertices (a pair f, −f makes the moment l·t × f = C_e for C_e ⟂ t_e). In the planar
equilibrium d2 is the same on every edge of the section, so this is docs/simulation.md's "M = T·r_t at the tip
and −M where the coil ends": only the two end edges carry a couple. Out of plane it differs, and that matters:
with the couples at the two ends only (each following its own edge's frame), the section held at 10 N drifted out
of its plane (κ_y grew from 1e-10 to 21 1/m within 4 s at mass ×10; a follower *end* moment is not conservative),
while the distributed form stays planar (κ_y ~ 1e-27) at 50–200 segments. The couple's component along the edge
(twist) is zero in the planar state and is not applied (vertex forces cannot carry it; put on the twist DOFs it
was either neutral or slowly destabilising, depending on the sign convention, so it is left out).

The wire's compression T acts along the tangent at every section and does not change the bending equilibrium of
an inextensible rod (M' + t × n = 0 with n ∥ t), so it is left out of the mechanics; it appears as axial strain in
the optics (below). The frames are read every physics step with :meth:`models.rod_state.RodReader.compute`
(compiled, ≈ 5–10 µs at 100 segments; the whole actuation costs ≈ 0.1 ms per step: 2600–2800 steps/s at 100
segments against ≈ 3500 for the free rod), so the load follows the section as it turns; everything is vectorised
over the section's edges.

Check (tests/test_tendon_thermal.py): with gravity off, r_t = 0.9 mm and EI = 2e-4 N·m², the curvature on the
deflectable section settles to T·r_t/EI — 2.24999 vs 2.25 1/m at 0.5 N (6e-6 relative) and 0.26 % low at 10 N
(45 1/m), a discretisation effect ∝ (κ·l)² (1.0 % at 50 segments, 0.064 % at 200) — and the shaft's curvature
decays to zero.

The dynamics
------------
The base (clamp) is fixed and the catheter hangs free in air, pointing down (−z), so gravity (the real weight
per length, CatheterSpec's scaling) does not sag the shaft; the steering plane is vertical, spanned by the
base's x axis (d1) and the rod. Steering is a dynamic load case, unlike the quasi-static fixtures, and the
default ×100 mass and 0.01 N·s/m vertex damping of :class:`models.catheter.CatheterSpec` made the clamped shaft
bend by up to 2 1/m (first bending mode at 0.25 Hz, overdamped by the vertex damping) while the tip was
steered with a 5 s period — an artefact of the quasi-static trick: the real catheter is 100× lighter and air
barely damps it. This setup therefore uses mass ×10 (gravity ×1/10; edge stretch ≤ 2e-4 measured) and
2e-4 N·s/m of vertex damping: steered with a 10 s period, the shaft's curvature after the first quarter period
stays ≤ 0.12 1/m without gravity (the dynamic artefact) and ≤ 0.35 1/m with it (the steered section's weight
acting on the shaft: real physics). The real mass (×1) is not usable: the soft edge constraints then stretched
the rod by up to 12 %. Frames and truth are those of this rod, whatever its dynamics.

The script
----------
With ``wires=2`` (a bidirectional catheter, wires at ±d1) the signed tension is
T(t) = T_max·sin(2π t/P), with sin³ instead over the first quarter period (a ramp-in with a continuous rate, so
the start excites little vibration); then the tip sweeps from one side to the other. The positive part pulls
the wire at +d1, the negative part the one at −d1. With ``wires=1`` the one wire pulls and releases,
T(t) = T_max·sin²(π t/P): the tip goes from straight to bent and back.

At the defaults (T_max = 10 N, r_t = 0.9 mm, EI = 2e-4 N·m², a 60 mm deflectable section, the last 45 mm of
the sensed length and the 15 mm tip) the section reaches κ = T·r_t/EI = 45 1/m (0.45 1/cm) and the end of the
sensed length moves ≈ ±28 mm sideways (a 56 mm sweep) — a realistic ablation-catheter deflection. The coil's
end is modelled at s = 125.5 mm (100 segments), between the gratings at 120 and 130 mm: where the curvature
steps between two gratings is something the 10 mm grating pitch cannot resolve.

Compression in the optics
-------------------------
The compression T shortens the deflectable section by ε = −|T|/EA (one wire pulls at a time), which a fibre
bonded in it feels as axial strain: a common mode on the gratings distal of the coil's end, which the central
core removes (:meth:`Tendon.conditions`). The shaft proximal of the coil's end carries no compression (the coil
does), so its gratings see none. The effective EA is a parameter, default 20 kN: a homogeneous polymer section
with the model's EI = 2e-4 N·m² has EA = EI·A/I = 4EI/r² ≈ 450 N (solid; ≈ 330 N as a 1.6 mm-bore tube),
which would put −2 to −3 % on a bonded fibre at 10 N — a 25–35 nm Bragg shift, out of every 5 nm grating slot,
so the paper's sensor could not have worked that way. A working deflectable section is reinforced axially
(braid, slotted tube) or the fibre floats in its lumen; an effective EA of 10–50 kN gives 200–1000 µε at
10 N (0.25–1.2 nm, in-slot, larger than the 30 K thermal common mode of ≈ 0.3 nm), and 20 kN is the middle of
that range (−500 µε, ≈ −0.6 nm at 10 N). The rod itself is inextensible (30 µm of shortening is ignored).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import mujoco
import numpy as np

from models.catheter import CatheterSpec, Pose, Scene
from models.fixtures import settle
from models.rod_state import RodReader
from sim_interrogator.setups import Setup

__all__ = ["Tendon", "hanging_pose"]


def hanging_pose(height: float = 0.3) -> Pose:
    """A base pose at (0, 0, ``height``) m pointing the catheter down (local +z = world −z, local x = world x)."""
    return Pose((0.0, 0.0, height), np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]))


class Tendon(Setup):
    """A steerable catheter: a deflectable distal section bent back and forth by pull-wires.

    Parameters
    ----------
    max_tension : float
        Largest pull-wire tension T_max, N.
    period : float
        Period P of the steering script, s.
    cycles : float
        Number of periods; the run lasts ``cycles * period`` s.
    wires : int
        2: bidirectional (the tip sweeps to both sides), 1: one wire pulled and released.
    deflectable_length : float
        From the compression coil's end to the tip (the rod's end), m; the model puts the coil's end at the
        midpoint of the nearest rod edge (:attr:`coil_s`).
    tendon_offset : float
        r_t, distance of the pull-wire from the catheter's axis, m.
    axial_stiffness : float
        Effective EA of the deflectable section for the strain the fibre feels, N (0: no compression strain).
    segments : int
        Rod segments over the whole catheter.
    mass_scale : float
        Factor on the catheter's real mass (gravity is divided by it).
    vertex_damping : float
        Velocity damping per vertex slide DOF, N·s/m.
    gravity : bool
        Gravity on (the catheter hangs down) or off (for exact beam checks).
    timestep : float
        Physics step, s.
    """

    name = "tendon"
    actuated = True

    def __init__(self, max_tension: float = 10.0, period: float = 10.0, cycles: float = 2.0, wires: int = 2,
                 deflectable_length: float = 0.06, tendon_offset: float = 0.9e-3, axial_stiffness: float = 2.0e4,
                 segments: int = 100, mass_scale: float = 10.0, vertex_damping: float = 2.0e-4,
                 gravity: bool = True, timestep: float = 2.0e-3):
        checks = dict(max_tension=max_tension, period=period, cycles=cycles, deflectable_length=deflectable_length,
                      tendon_offset=tendon_offset, mass_scale=mass_scale, timestep=timestep)
        for key, v in checks.items():
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"sim://tendon: {key} must be a finite number > 0, got {v!r}")
        for key, v in (("axial_stiffness", axial_stiffness), ("vertex_damping", vertex_damping)):
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"sim://tendon: {key} must be a finite number >= 0, got {v!r}")
        if wires not in (1, 2):
            raise ValueError(f"sim://tendon: wires must be 1 (pull and release) or 2 (bidirectional), got {wires!r}")
        self.spec = CatheterSpec(n_segments=int(segments), mass_scale=float(mass_scale),
                                 gravity_scale=(1.0 / mass_scale) if gravity else 0.0,
                                 dof_damping=float(vertex_damping), timestep=float(timestep))
        if not tendon_offset < self.spec.radius:
            raise ValueError(f"sim://tendon: tendon_offset {tendon_offset * 1e3:g} mm lies outside the catheter "
                             f"(radius {self.spec.radius * 1e3:g} mm)")
        s_end = self.spec.sensed_length + self.spec.tip_length
        s_coil = s_end - float(deflectable_length)
        # the coil's end must leave the clamped edge and at least one free edge behind it
        if s_coil < -self.spec.base_length + 2 * self.spec.segment_length:
            raise ValueError(f"sim://tendon: deflectable_length {deflectable_length * 1e3:g} mm exceeds the "
                             f"catheter ({self.spec.length * 1e3:g} mm from the clamp to the tip)")
        self.max_tension = float(max_tension)
        self.period = float(period)
        self.cycles = float(cycles)
        self.duration = self.cycles * self.period
        self.wires = int(wires)
        self.deflectable_length = float(deflectable_length)
        self.tendon_offset = float(tendon_offset)
        self.axial_stiffness = float(axial_stiffness)
        self.gravity = bool(gravity)
        # The coil's end is modelled at the midpoint of the edge nearest to it: the moment pair acts across one
        # edge, so the curvature steps there (the section's length is rounded to the rod's segments).
        mid = 0.5 * (self.spec.vertex_s[:-1] + self.spec.vertex_s[1:])
        self._coil_edge = int(np.argmin(np.abs(mid[2:] - s_coil))) + 2  # never a clamped edge (0, 1)
        #: fibre arc length of the modelled compression coil's end (the start of the deflectable section), m
        self.coil_s = float(mid[self._coil_edge])
        self.base_pose = hanging_pose()
        self._reader: RodReader | None = None

    # ------------------------------------------------------------------ the script and its consequences
    def tension(self, t) -> np.ndarray:
        """Signed pull-wire tension at times ``t`` (s, any shape), N: > 0 pulls the wire at +d1, < 0 the one
        at −d1 (``wires=2``); always ≥ 0 for ``wires=1``. Zero before 0 and after the run."""
        t = np.asarray(t, dtype=np.float64)
        inside = (t >= 0.0) & (t <= self.duration)
        if self.wires == 2:
            phase = np.sin(2 * np.pi * t / self.period)
            value = np.where(t < 0.25 * self.period, phase**3, phase)  # a C¹ ramp-in over the first quarter
        else:
            value = np.sin(np.pi * t / self.period) ** 2
        return np.where(inside, self.max_tension * value, 0.0)

    def section_curvature(self, tension) -> np.ndarray:
        """Beam theory for the deflectable section: κ = T·r_t/EI (signed like ``tension``), 1/m."""
        return np.asarray(tension, dtype=np.float64) * self.tendon_offset / self.spec.bending_stiffness

    def axial_strain(self, t, s) -> np.ndarray:
        """Axial strain at fibre arc lengths ``s`` (shape (n,), m) at times ``t`` (shape (...)): −|T|/EA on
        the deflectable section, 0 on the shaft; shape (..., n)."""
        s = np.asarray(s, dtype=np.float64)
        if self.axial_stiffness == 0:
            return np.zeros(np.shape(t) + s.shape)
        eps = -np.abs(self.tension(t))[..., None] / self.axial_stiffness
        return eps * (s >= self.coil_s)

    def conditions(self, t: float, grating_s: np.ndarray) -> tuple[float, np.ndarray]:
        """(ΔT = 0 K, axial strain from the wire's compression of the deflectable section)."""
        return 0.0, self.axial_strain(t, grating_s)

    # ------------------------------------------------------------------ the scene
    def build(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        scene = Scene("tendon", timestep=self.spec.timestep)
        scene.add_rod(self.spec, self.base_pose)
        model, data = scene.build()
        name = self.spec.name
        fid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, name)
        va, nv = int(model.flex_vertadr[fid]), int(model.flex_vertnum[fid])
        #: the deflectable section's edges (coil's end to tip) and their vertices
        self._edges = np.arange(self._coil_edge, nv - 1)
        self._vertices = np.arange(self._coil_edge, nv)
        bodies = model.flex_vertbodyid[va : va + nv][self._vertices]
        if np.any(model.body_jntnum[bodies] != 3):
            raise ValueError("sim://tendon: a loaded vertex is pinned; shorten deflectable_length")
        self._bodies = bodies
        self._reader = RodReader(model, name)
        self._frames = np.empty((nv - 1, 3, 3))
        self._darboux = np.empty((nv - 2, 3))
        self._moment = np.zeros((self._vertices.size, 3))
        self._force = np.zeros((self._vertices.size, 3))
        return model, data

    def prepare(self, model: mujoco.MjModel, data: mujoco.MjData,
                progress: Callable[[float, float], None] | None = None) -> None:
        """Let the straight, hanging catheter settle (its weight stretches the soft edge constraints a little)."""
        settle(model, data, max_time=2.0, progress=progress, label="tendon: hanging catheter")

    def actuate(self, model: mujoco.MjModel, data: mujoco.MjData, t: float) -> None:
        """Write the pull-wire's equivalent load for time ``t`` into ``data.xfrc_applied``."""
        self.apply_tension(data, float(self.tension(t)))

    def apply_tension(self, data: mujoco.MjData, tension: float) -> None:
        """The wire's load for a signed tension (N) as vertex forces, from the current material frames.

        The internal moment across each vertex of the section is m_i = T·r_t·d2_i (d2_i: the mean of the two
        adjacent edges' d2, normalised), zero at the coil's end and at the free tip. Edge e then carries the
        couple C_e = m_e − m_{e+1}, applied as the force pair ±(C_e × t_e)/l_e on its two vertices (moment
        l_e t_e × f = C_e for C_e ⟂ t_e).
        """
        x = self._reader.compute(data, self._frames, self._darboux)
        e = self._edges
        d2 = self._frames[e, :, 1]
        mean = d2[:-1] + d2[1:]
        m = self._moment
        m[1:-1] = (tension * self.tendon_offset) * mean / np.linalg.norm(mean, axis=1, keepdims=True)
        couple = m[:-1] - m[1:]
        seg = x[e + 1] - x[e]
        length_sq = np.einsum("ij,ij->i", seg, seg)
        f = np.cross(couple, seg) / length_sq[:, None]  # (C × t)/l with t = seg/l
        force = self._force
        force[:] = 0.0
        force[1:] += f
        force[:-1] -= f
        data.xfrc_applied[self._bodies, :3] = force

    def describe(self) -> dict:
        return {"setup": self.name, "max_tension": self.max_tension, "period_s": self.period,
                "cycles": self.cycles, "wires": self.wires, "deflectable_length": self.deflectable_length,
                "modelled_deflectable_length": self.spec.sensed_length + self.spec.tip_length - self.coil_s,
                "coil_end_s": self.coil_s, "tendon_offset": self.tendon_offset,
                "axial_stiffness": self.axial_stiffness, "segments": self.spec.n_segments,
                "mass_scale": self.spec.mass_scale, "vertex_damping": self.spec.dof_damping,
                "gravity": self.gravity, "timestep": self.spec.timestep,
                "max_section_curvature": float(self.section_curvature(self.max_tension)),
                "max_compression_strain": (-self.max_tension / self.axial_stiffness
                                           if self.axial_stiffness else 0.0)}
