"""The fibre as its own body in the catheter's lumen (models/lumen_fiber.py) and the integration experiment.

Physics (slow): glued with zero clearance the fibre reads what the welded model reads; with clearance, in a
constant-curvature lumen the fibre rides on the outer wall with the curvature of that wall, 1/(R + c); the
guideline trends (error grows with clearance, tip contact disturbs peaks, no base fixation lets the fibre slide).
Fast: the fibre's geometry in the scene and bad specs.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mujoco")

from models._lumen_kernels import lumen_forces
from models.catheter import CatheterSpec, Scene
from models.lumen_fiber import TRACTION_RAMP, FiberSpec, LumenCoupler, add_fiber, glued_edges
from sim_interrogator.fiber_setups import FIBER_BASE_LENGTH, FiberSheathCycle, FiberStatic
from sim_interrogator.optics import Optics, OpticsConfig
from sim_interrogator.sim import SimInterrogator
from twin import FiberModel


# ------------------------------------------------------------------------------------------------------ fast
def test_fiber_sits_on_the_catheters_grid_with_its_glue_spots_and_tip_gap():
    spec = CatheterSpec(base_length=FIBER_BASE_LENGTH)
    scene = Scene("t")
    rod = scene.add_rod(spec)
    h = add_fiber(scene, rod, FiberSpec(n_fixations=2, dx_prox=0.015, fixation_spacing=0.005, dx_dist=0.002))
    assert np.allclose(h.s, spec.vertex_s[h.first:h.first + h.s.size])  # beside catheter vertices at rest
    glued = h.s[h.glued]
    assert glued.max() <= -0.015 + 1e-9 and glued.min() >= -0.015 - 0.005 - 0.002 - 1e-9
    assert ((glued > -0.0175) & (glued <= -0.015 + 1e-9)).any() and (glued <= -0.020 + 1e-9).any()
    assert h.s[-1] >= spec.sensed_length + 0.003 - 1e-9  # the tail beyond the last grating
    assert h.lumen_end == pytest.approx(h.s[-1] + 0.002)
    model, _ = scene.build()
    assert model.nflex == 2


def test_the_glue_holds_the_roll_of_its_edges():
    # two spots of two vertices, and one spot shorter than an edge (one vertex): its edge is the distal one
    glued = np.array([0, 1, 1, 0, 0, 1, 1, 0, 1, 0, 0], bool)
    assert glued_edges(glued).tolist() == [1, 5, 8]
    assert glued_edges(np.ones(4, bool)).tolist() == [0, 1, 2]
    assert glued_edges(np.array([0, 0, 1], bool)).tolist() == [1]  # a lone vertex at the tip: the edge before it
    assert glued_edges(np.zeros(4, bool)).size == 0


def test_lumen_kernel_on_a_straight_lumen():
    from models._lumen_kernels import lumen_forces

    # a straight catheter along z (frames = identity), a fibre 0.2 mm off the axis in a 0.1 mm clearance, its
    # tip 0.5 mm beyond the lumen's end, sliding distally at 2 mm/s: the wall pushes back with k·(d − c), the
    # friction is μN regularised, the end pushes with k·0.5 mm, and the tension sums their axial parts distally
    nc, nf, l, k, c, mu, vs = 11, 5, 0.01, 600.0, 1e-4, 0.2, 1e-3
    x_c = np.zeros((nc, 3))
    x_c[:, 2] = l * np.arange(nc)
    frames = np.broadcast_to(np.eye(3), (nc - 1, 3, 3)).copy()
    sigma = l * np.arange(nf) + 0.003
    x_f = np.zeros((nf, 3))
    x_f[:, 0] = 2e-4
    x_f[:, 2] = sigma
    v_f = np.zeros((nf, 3))
    v_f[:, 2] = 2e-3
    free = np.ones(nf, bool)
    free[0] = False  # glued: no wall there
    p, force, normal, tension = np.zeros((nf, 3)), np.zeros((nf, 3)), np.zeros(nf), np.zeros(nf - 1)
    v_l = np.zeros((nf, 3))
    end = sigma[-1] - 5e-4
    tip = lumen_forces(x_c, frames, 0.0, l, 0.0, x_f, v_f, sigma.copy(), free, np.zeros((nf, 3)), 0.0, v_l,
                       0.0, c, k, 2.0, mu, vs, 1e9, end, p, force, normal, tension)
    assert tip == pytest.approx(k * 5e-4)
    assert np.allclose(normal, [0.0] + [k * 1e-4] * 4)
    fric = mu * k * 1e-4 * 2e-3 / np.hypot(2e-3, vs)
    assert np.allclose(force[1:, 0], -k * 1e-4) and np.allclose(force[1:-1, 2], -fric)
    assert force[-1, 2] == pytest.approx(-fric - tip)
    assert np.allclose(tension, [-4 * fric - tip, -3 * fric - tip, -2 * fric - tip, -fric - tip])


class _NumpyCoupler(LumenCoupler):
    """The coupler's step as it was before it became one compiled call (numpy around the lumen kernel): the
    reference the compiled step must equal."""

    def apply(self, model, data):
        spec, h = self.spec, self.handle
        self.calls += 1
        x_c = self.cath_reader.compute(data, self._cframes, self._cdarb)
        x_f = data.flexvert_xpos[self.fiber_reader._va: self.fiber_reader._va + self.fiber_reader._nv]
        axes_w = self._axes @ data.xmat[self._parent].reshape(3, 3).T
        v_f = np.einsum("nj,nji->ni", data.qvel[self._dof], axes_w)
        tnow = float(data.time)
        dt = tnow - self._prev_t if self._prev_t is not None and tnow > self._prev_t else 0.0
        force = self._force
        self.tip_force = float(lumen_forces(
            x_c, self._cframes, self._cs0, self._l, spec.offset, x_f, v_f, self.sigma, self._free, self._prev_p, dt,
            self._v_lumen, spec.drag, spec.clearance, spec.wall_stiffness, spec.wall_damping, spec.friction,
            spec.slip_speed, 0.5 * spec.vertex_mass / model.opt.timestep, h.lumen_end, self._p, force,
            self.normal, self.tension))
        if self._prev_t is None or tnow > self._prev_t:
            self._prev_t = tnow
            np.copyto(self._prev_p, self._p)
        force -= self._weight
        if self.carrier_acceleration is not None:
            force += spec.vertex_mass * self.carrier_acceleration(data)
        if self._couple_k is not None:
            k = self._couple_k
            edge = x_f[k + 1] - x_f[k]
            le = np.sqrt(edge @ edge)
            t = edge / le
            g = self._cframes[min(h.first + k, self._cframes.shape[0] - 1), :, 0]
            n = g - (g @ t) * t
            n /= np.sqrt(n @ n)
            if self._t_first is None:
                self._t_first = tnow
            ramp = min(1.0, (tnow - self._t_first) / TRACTION_RAMP)
            self.glue_moment = ramp * float(self.traction(data)) * spec.glue_eccentricity
            f = (self.glue_moment / le) * n
            force[k] += f
            force[k + 1] -= f
        data.qfrc_applied[self._dof] = np.einsum("ni,nji->nj", force, axes_w)
        if self._glue_eq.size and spec.offset:
            model.eq_data[self._glue_eq, 3:6] = (spec.offset * self._cframes[np.minimum(
                h.first + self._glue_idx, self._cframes.shape[0] - 1), :, 0]) @ data.xmat[
                    self._cath_parent].reshape(3, 3)
        if not self._roll_ready and any(data.plastic[self.fiber_reader._pa + 3: self.fiber_reader._pa + 6]):
            self.calibrate_roll(data)
            self._roll_ready = True


@pytest.mark.parametrize("make", [
    # the study's standard point (clearance 0.1 mm, μ 0.2, two fixations, the lead's couple), the glue spots
    # with the lumen off the axis (the anchors follow it), and the sheath's fibre carried with the hub (d'Alembert)
    lambda: FiberStatic("helix", clearance=1e-4),
    lambda: FiberStatic("arc", clearance=1e-4, offset=3e-4),
    lambda: FiberSheathCycle(cycles=1, segments=50, clearance=1e-4),
], ids=["standard", "offset", "sheath"])
def test_compiled_coupler_step_equals_the_numpy_step(make):
    import mujoco

    # two copies of one scene, one with the compiled coupler and one with the numpy step, stepped side by side
    # from the start (the catheter's restarted frames on the first step, the roll's calibration after it)
    setups = [make(), make()]
    (model, data), (model_r, data_r) = (s.build() for s in setups)
    c = setups[1].coupler
    setups[1].coupler = ref = _NumpyCoupler(model_r, data_r, c.handle, c.carrier_acceleration, c.traction)
    co = setups[0].coupler
    contact = moment = 0
    for _ in range(400):
        setups[0].actuate(model, data, data.time)
        setups[1].actuate(model_r, data_r, data_r.time)
        scale = max(1e-9, float(np.abs(data_r.qfrc_applied).max()))
        np.testing.assert_allclose(data.qfrc_applied, data_r.qfrc_applied, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(co.sigma, ref.sigma, rtol=0, atol=1e-12)
        np.testing.assert_allclose(co.normal, ref.normal, rtol=0, atol=1e-12 * max(1e-9, ref.normal.max()))
        np.testing.assert_allclose(co.tension, ref.tension, rtol=0, atol=1e-12 * max(1e-9, abs(ref.tension).max()))
        np.testing.assert_allclose(model.eq_data, model_r.eq_data, rtol=0, atol=1e-15)
        assert co.tip_force == pytest.approx(ref.tip_force, rel=0, abs=1e-12)
        assert co.glue_moment == ref.glue_moment and co.roll0 == ref.roll0
        contact += int((co.normal > 0).sum())
        moment = max(moment, abs(co.glue_moment))
        mujoco.mj_step(model, data)
        mujoco.mj_step(model_r, data_r)
    np.testing.assert_allclose(data.qpos, data_r.qpos, rtol=0, atol=1e-12)
    # what each case is there for did happen
    assert co.calls == ref.calls == 400 and co.roll0 != 0.0
    if co.spec.offset:
        assert np.any(model.eq_data[co._glue_eq, 3:6])
    if co.spec.clearance:
        assert contact and moment > 0  # the wall (with its friction) and the lead's couple acted
    if co.carrier_acceleration is not None:
        assert np.any(co._carrier_force)


def test_bad_fiber_specs_are_refused():
    with pytest.raises(ValueError, match="stretch"):
        FiberSpec(glued=True, offset=2e-4)
    with pytest.raises(ValueError, match="n_fixations"):
        FiberSpec(n_fixations=5)
    with pytest.raises(ValueError, match="clearance"):
        FiberSpec(clearance=-1e-4)
    with pytest.raises(ValueError, match="lead_tension"):
        FiberSpec(lead_tension=float("nan"))
    scene = Scene("t")
    rod = scene.add_rod(CatheterSpec())  # 10 mm base: no room for fixations 25 mm before the first grating
    with pytest.raises(ValueError, match="base_length"):
        add_fiber(scene, rod, FiberSpec(dx_prox=0.025))


# ------------------------------------------------------------------------------------------------------ slow
@pytest.mark.slow
def test_glued_fiber_without_clearance_reads_what_the_welded_model_reads():
    setup = FiberStatic("helix", glued=True, clearance=0.0)
    sim = SimInterrogator(setup, FiberModel.paper(), OpticsConfig.ideal())
    g = sim.fiber.grating_s
    k_cath = sim.reader.read(sim.data).curvature_at(g)  # what the welded model's optics read
    k_fib = setup.fiber_curvature(g)
    # measured 0.019 1/m (helix, |k| = 40 1/m): the glue's connect constraints leave sub-micrometre play
    assert np.abs(k_fib - k_cath).max() < 0.05
    optics = Optics(sim.fiber, OpticsConfig.ideal())
    w_weld, _ = optics.wavelengths(k_cath, 0.0)
    frame = sim.read()
    # 0.05 1/m × g (28 µm) × λ (1550 nm) ≈ 2 pm
    assert np.nanmax(np.abs(frame.wavelengths - w_weld)) < 3e-3
    assert setup.coupler.tip_gap() == pytest.approx(0.002, abs=1e-6) and not setup.contact_frames


@pytest.mark.slow
def test_glue_holds_the_fibers_roll_in_the_moving_sheath():
    # In and out of the pre-bent sheath, the glued fibre's roll against the catheter's is held by the glue's
    # joint equalities: with explicit roll springs it drifted by 3–4° (|Δk| up to 2 1/m); measured now 0.003°.
    setup = FiberSheathCycle(cycles=1, segments=50, glued=True, clearance=0.0)
    sim = SimInterrogator(setup, FiberModel.paper(), OpticsConfig.ideal(), rate=5.0)
    g = sim.fiber.grating_s
    roll, dk = 0.0, 0.0
    for _ in range(int(setup.duration * 5.0 + 1e-9) + 1):
        sim.read()
        roll = max(roll, float(np.abs(setup.roll_loss()).max()))
        k_cath = sim.reader.read(sim.data).curvature_at(g[:-1])
        dk = max(dk, float(np.abs(setup.fiber_curvature(g[:-1]) - k_cath).max()))
    assert roll < np.radians(0.05)
    # measured 0.034 1/m (|k| ≈ 29 1/m in the bend); the static helix's tolerance. Not the last grating: the
    # fibre's rod ends 3 mm beyond it, so its curvature there is clipped to the last interior vertex (4.5 mm
    # before the end at 50 segments) while the catheter's is interpolated across; they differ by up to 0.5 1/m
    # while the tip leaves the sheath, and agree at rest.
    assert dk < 0.05


@pytest.mark.slow
def test_fiber_with_clearance_rides_the_outer_wall_of_a_bent_lumen():
    # Free of axial load, a fibre in a bent lumen takes the path of least bending energy: the outer wall, of
    # curvature 1/(R + c). (The first version showed it on the inner wall: its 100× simulated weight, never
    # cancelled, compressed it, and a compressed fibre takes the shorter path.)
    c = 1.5e-4
    setup = FiberStatic("arc", clearance=c)  # a planar arc of 25 1/m
    setup.random_start = False
    sim = SimInterrogator(setup, FiberModel.paper(), OpticsConfig.ideal())
    co = setup.coupler
    cath = sim.reader.read(sim.data)
    fib = sim.optics_reader.read(sim.data)
    p, t, _ = co.lumen(cath.positions, co.sigma)
    r = fib.positions - p
    r -= np.einsum("ni,ni->n", r, t)[:, None] * t
    k = cath.curvature_at(co.sigma)
    fr = cath.frames_at(co.sigma)
    towards_centre = k[:, :1] * fr[:, :, 0] + k[:, 1:] * fr[:, :, 1]
    towards_centre /= np.linalg.norm(towards_centre, axis=1, keepdims=True)
    outer = -np.einsum("ni,ni->n", r, towards_centre)
    mid = (fib.s > 0.03) & (fib.s < 0.12)  # away from the glue's transition and the free tail
    # on the outer wall, measured 150.01–150.04 µm (the wall pushes it with micronewtons: no give to speak of)
    assert np.all(outer[mid] > c - 5e-6) and np.all(outer[mid] < c + 5e-6)
    # with the outer wall's curvature 1/(R + c) = 24.907 1/m (measured 24.912–24.915), not the axis' 25
    s_mid = np.linspace(0.04, 0.11, 8)
    kf = np.linalg.norm(setup.fiber_curvature(s_mid), axis=1)
    assert np.allclose(kf, 1 / (1 / 25.0 + c), atol=0.03)
    # the longer outer path pulls the free tip back from the lumen's end by ≈ c·∫κ ds (≤ 0.64 mm over 170 mm;
    # measured 0.48 mm: the glue's transition and the free tail take the shorter line)
    assert 0.3e-3 < co.tip_gap() - 0.002 < 0.9e-3


@pytest.mark.slow
def test_the_leads_traction_enters_at_the_fixation_and_dies_out_along_the_lumen():
    # A lead pulling with T through glue on one side of the fibre (lever e = its radius) puts a couple M = T·e
    # on the fibre where it leaves the most distal glue spot. Held off the wall only by the clearance c, the
    # fibre bends over the length a it needs to reach the wall: for a beam pinned at the glue with an end
    # couple, tangent to the wall where it lands, M a² / (6 EI) = c, a = sqrt(6 c EI / M) = 7.7 mm at
    # T = 0.1 N, c = 0.1 mm. Measured in the 25 1/m arc against the same fibre without traction: 1.8–3.0 1/m
    # within 5 mm of the glue, 0.5 1/m at 15 mm, 0.008 1/m at 25 mm.
    c, t = 1e-4, 0.1
    s = np.arange(0.0, 0.0401, 0.0025)
    k = {}
    for tension in (0.0, t):
        setup = FiberStatic("arc", clearance=c, lead_tension=tension, dx_prox=0.0)
        setup.random_start = False
        SimInterrogator(setup, FiberModel.paper(), OpticsConfig.ideal())  # builds and settles the setup
        k[tension] = setup.fiber_curvature(s)
    spec = setup.fiber
    m = setup.coupler.glue_moment
    assert m == pytest.approx(t * spec.glue_eccentricity)
    a = np.sqrt(6 * c * spec.bending_stiffness / m)
    dk = np.linalg.norm(k[t] - k[0.0], axis=1)
    assert dk[s <= 0.005].max() > 0.1 * m / spec.bending_stiffness  # the couple reaches the first grating
    assert dk[s >= 3 * a].max() < 0.05  # and has died out three pinned-beam lengths on


@pytest.mark.slow
def test_the_grating_at_the_fixation_is_disturbed_and_one_15_mm_away_much_less():
    from scenarios.integration import BASELINE, Params, run_point

    # The fibre leaves the glue on the lumen's axis and must reach the outer wall of the bend: the first grating
    # reads that transition at Δx_prox = 0. Without the lead's traction (whose couple, at 0.02 N, reaches
    # farther: see the test above), measured on arc and helix, seed 0: 1.17 1/m added to its curvature at 0 mm,
    # 0.24 1/m at 15 mm (seed 1: 1.67 and 0.68).
    params = Params(shapes=("arc", "helix"), repeats=1, cycles=0)
    near = run_point({**BASELINE, "label": "0", "dx_prox": 0.0, "lead_tension": 0.0}, params)
    far = run_point({**BASELINE, "label": "15", "dx_prox": 0.015, "lead_tension": 0.0}, params)
    assert near["grating0_dk"] > 2 * far["grating0_dk"]


@pytest.mark.slow
def test_error_grows_with_clearance_and_tip_contact_disturbs_peaks():
    from scenarios.integration import BASELINE, Params, run_point

    params = Params(shapes=("arc", "helix"), repeats=2, cycles=0)
    tight = run_point({**BASELINE, "label": "0", "clearance": 0.0}, params)
    loose = run_point({**BASELINE, "label": "0.3", "clearance": 3e-4}, params)
    assert loose["max_error_mm"] > tight["max_error_mm"] and loose["mean_error_mm"] > tight["mean_error_mm"]
    # on the outer wall of a bend the tip retracts (≈ 0.5 mm in the arc): a tip cut flush with the lumen's end
    # does not touch it there, one pressed 0.5 mm into it does
    contact = run_point({**BASELINE, "label": "c", "dx_dist": -5e-4}, params)
    assert contact["static_contact_frames"] > 0 and contact["static_lost_peaks"] > 0
    assert tight["static_contact_frames"] == 0


@pytest.mark.slow
def test_without_base_fixation_the_fiber_slides_and_repeatability_worsens():
    from scenarios.integration import BASELINE, Params, run_point

    params = Params(shapes=(), cycles=3)
    fixed = run_point({**BASELINE, "label": "2"}, params)
    free = run_point({**BASELINE, "label": "0", "fixations": 0}, params)
    assert free["cycle_slide_max_mm"] > fixed["cycle_slide_max_mm"]
    assert free["repeat_std_mm"] > fixed["repeat_std_mm"]
