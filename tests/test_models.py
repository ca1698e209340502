"""The MuJoCo catheter rod (models/): beam theory, rod-state reader, fixtures (docs/simulation.md §1–§3).

Tolerances and where they come from:

* pure torsion: τ = T/GJ to 1e-7 relative (docs/simulation.md §1). The floor is the constraint solver's tolerance
  (MuJoCo's default 1e-8 leaves 4e-6 of noise, 1e-12 leaves 6e-10), so the test runs at 1e-12.
* cantilever tip load: κ(s) = F·(z_tip − z(s))/EI with the deformed lever arm to 1e-4 (measured 2e-5), and the
  small-deflection F (L − s)/EI to 1 % at a load whose geometric nonlinearity is 0.1 %.
* discrete vs continuous curvature of a rod held on a curve (vertices at arc spacing l): the turning angle at
  a vertex is ∫ κ·hat(s − s_i) ds, so |k_discrete| − |k| ≈ l² |k''| / 12; and the discrete twist-free frames
  turn against the continuous Bishop frame by ≈ (l²/8) ∫ κ² |τ| ds (measured constant 1/8.1 on the library),
  which rotates the curvature vector by that angle. The bound used is twice the sum, plus 0.02 1/m for the
  residual of the soft constraints. Checked from 2.5 edges past the clamp to the end of the sensed region:
  the tip extension beyond it is excluded because a free end carries no moment, so constraints holding a
  curved shape up to it need large forces there (2–40 µm of vertex error in its last 3 vertices against
  < 1 µm elsewhere; the default 15 mm tip keeps that away from the last grating).
* tube and groove: the rod's axis stays within the geometric clearance (165 µm toward a wall, 180 µm between
  two tube rails) plus 20–25 µm of soft-contact penetration (measured ≤ 10 µm).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from models.catheter import CatheterSpec, Pose, Scene, set_rod_positions
from models.fixtures import (
    ExtendedCurve,
    SettleError,
    add_connect_fixture,
    build_connect,
    build_groove,
    build_tube,
    settle,
)
from models.rod_state import RodReader, RodState, so3_exp, so3_log
from twin import shapes


def _rot(rotvec) -> np.ndarray:
    return so3_exp(np.asarray(rotvec, dtype=np.float64))


def _tip_body(model: mujoco.MjModel, name: str = "cath") -> int:
    f = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, name)
    return int(model.flex_vertbodyid[model.flex_vertadr[f] + model.flex_vertnum[f] - 1])


def _away_from_ends(state: RodState, spec: CatheterSpec) -> np.ndarray:
    """Interior vertices from two edges past the clamp to the end of the sensed region (module docstring)."""
    s = state.interior_s
    return (s >= state.s[0] + 2.5 * spec.segment_length) & (s <= state.sensed_length + 1e-9)


def _discretisation_bound(curve: ExtendedCurve, s: np.ndarray, l: float) -> np.ndarray:
    """Expected |k_discrete − k| at vertices s for arc spacing l (module docstring), 1/m."""
    h = 1e-4
    kpp = (
        curve.curvature(np.clip(s + h, curve.s_min, curve.s_max))
        - 2 * curve.curvature(s)
        + curve.curvature(np.clip(s - h, curve.s_min, curve.s_max))
    ) / h**2
    dense = np.linspace(curve.s_min, curve.s_max, 4001)
    k = curve.curvature(dense)
    kappa2 = np.sum(k**2, axis=-1)
    dk = np.gradient(k, dense, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.nan_to_num((k[:, 0] * dk[:, 1] - k[:, 1] * dk[:, 0]) / kappa2)
    rate = kappa2 * np.abs(tau)  # d(drift)/ds / (l²/8): the frame drift integrand κ²|τ|
    integral = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(dense))])
    drift = l**2 / 8 * integral
    kmag = np.linalg.norm(curve.curvature(s), axis=-1)
    return l**2 / 12 * np.linalg.norm(kpp, axis=-1) + kmag * np.interp(s, dense, drift)


# ----------------------------------------------------------------------------------------------------
# Spec, scene, XML
# ----------------------------------------------------------------------------------------------------


def test_spec_defaults_and_material():
    spec = CatheterSpec()
    assert spec.radius == pytest.approx(1.335e-3)
    assert spec.young * spec.second_moment == pytest.approx(2e-4)
    assert spec.shear * spec.polar_moment == pytest.approx(1.5e-4)
    assert spec.length == pytest.approx(0.195)
    assert spec.vertex_s[0] == pytest.approx(-0.01) and spec.vertex_s[-1] == pytest.approx(0.185)
    assert spec.solref == (0.004, 1.0)
    with pytest.raises(ValueError, match="n_segments"):
        CatheterSpec(n_segments=2)
    with pytest.raises(ValueError, match="fiber_offset"):
        CatheterSpec(fiber_offset=2e-3)
    with pytest.raises(ValueError, match="solref_factor"):
        CatheterSpec(solref_factor=1.0)


def test_xml_is_readable_and_compiles():
    scene = Scene("xmltest")
    rod = scene.add_rod(CatheterSpec(n_segments=10), Pose((0.1, 0, 0), _rot([0.3, -0.2, 0.5])))
    scene.add_body("fixture", Pose((0, 0.05, 0)))
    scene.add_geom(parent="fixture", type="box", size=(0.01, 0.01, 0.01))
    scene.add_equality("connect", name="holdtip", body1="cath_10", body2="fixture", anchor=(0, 0, 0))
    xml = scene.to_xml()
    assert '\n    <flexcomp name="cath" type="direct" dim="1"' in xml  # indented, one element per line
    assert '<pin id="0 1" />' in xml and 'equality="true"' in xml and 'integrator="discrete"' in xml
    model = mujoco.MjModel.from_xml_string(xml)
    assert model.nflex == 1 and model.flex_vertnum[0] == 11
    # The user's equality row and the flexcomp's own edge row: select by type, never by index.
    assert sorted(model.eq_type.tolist()) == sorted(
        [int(mujoco.mjtEq.mjEQ_CONNECT), int(mujoco.mjtEq.mjEQ_FLEX)]
    )
    m2, _ = scene.build()
    assert np.all(m2.dof_damping[:3] == pytest.approx(0.01))  # applied after compiling (MJCF refuses it)
    assert rod.pose.pos[0] == 0.1


def test_plastic_layout_interleaved_per_edge():
    """mjData.plastic of the rod = (t_old, u_old) per edge interleaved, then the n−1 reference twists."""
    model, data, _ = build_connect(shapes.get("helix"), CatheterSpec(n_segments=30))
    n = 30
    assert model.flex_plasticadr[0] == 0 and model.nplastic == 6 * n + (n - 1)
    assert not data.plastic.any()  # zero until the first step
    mujoco.mj_step(model, data, nstep=5)
    p = data.plastic[: 6 * n].reshape(n, 6)
    x = data.flexvert_xpos
    t = np.diff(x, axis=0)
    t /= np.linalg.norm(t, axis=1)[:, None]
    assert np.abs(p[:, :3] - t).max() < 1e-12  # t_old is the current tangent after a step
    assert np.abs(np.linalg.norm(p[:, 3:], axis=1) - 1).max() < 1e-12
    assert np.abs(np.einsum("ij,ij->i", p[:, 3:], t)).max() < 1e-12
    # The n − 1 reference twists follow; they start at 0 (frames restarted twist-free along the rod).
    assert np.abs(data.plastic[6 * n :]).max() < 1e-3


# ----------------------------------------------------------------------------------------------------
# Beam theory
# ----------------------------------------------------------------------------------------------------


def test_pure_torsion_matches_T_over_GJ():
    spec = CatheterSpec(n_segments=50, solver_tolerance=1e-12)
    scene = Scene("torsion", gravity=(0, 0, 0))
    scene.add_rod(spec)
    model, data = scene.build()
    torque = 1e-4  # N·m about the tangent, on the free end's twist joint
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "cath_twist")
    data.qfrc_applied[model.jnt_dofadr[j]] = torque
    mujoco.mj_step(model, data, nstep=1500)  # 3 s; the twist settles in ≈ 1.5 s
    state = RodReader(model).read(data)
    rate = torque / spec.torsional_stiffness
    assert np.abs(state.twist / rate - 1).max() < 1e-7
    assert np.abs(state.curvature).max() < 1e-9
    # The free end turned by T/GJ times the twisting length (clamped edge excluded).
    assert data.qpos[model.jnt_qposadr[j]] == pytest.approx(
        rate * (spec.length - spec.segment_length), rel=1e-6
    )


def _cantilever(n: int, force: float) -> tuple[RodState, CatheterSpec]:
    spec = CatheterSpec(n_segments=n)
    scene = Scene("cantilever", gravity=(0, 0, 0))
    scene.add_rod(spec)
    model, data = scene.build()
    # Start near the small-deflection solution so that the slow, overdamped first mode has little to do.
    length, l = spec.length, spec.segment_length
    s = np.linspace(0.0, length, n + 1)
    kappa = force * (length - s) / spec.bending_stiffness
    kappa[:2] = 0.0
    angle = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1])) * l])
    edge_angle = 0.5 * (angle[1:] + angle[:-1])
    edge_angle[0] = 0.0
    p = np.zeros((n + 1, 3))
    p[1:, 1] = np.cumsum(l * np.sin(edge_angle))
    p[1:, 2] = np.cumsum(l * np.cos(edge_angle))
    set_rod_positions(model, data, p)
    data.xfrc_applied[_tip_body(model), :3] = (0.0, force, 0.0)  # +y at the tip vertex
    settle(model, data, tol=1e-8, window=0.1, max_time=40.0)
    return RodReader(model).read(data), spec


def test_cantilever_tip_load_curvature():
    force = 5e-4
    state, spec = _cantilever(50, force)
    x = state.positions
    k = state.curvature
    lever = x[-1, 2] - x[1:-1, 2]  # deformed lever arm of the +y tip force
    exact = force * lever / spec.bending_stiffness
    assert np.abs(k[:, 1] / exact - 1).max() < 1e-4  # measured 2e-5, at all interior vertices
    # Small-deflection beam theory F (L − s)/EI within 1 % away from the ends (clamp + 3 edges, last 10 %).
    away = (state.interior_s > state.s[0] + 3 * spec.segment_length) & (
        state.interior_s < state.s[-1] - 0.1 * spec.length
    )
    linear = force * (state.s[-1] - state.interior_s[away]) / spec.bending_stiffness
    assert np.abs(k[away, 1] / linear - 1).max() < 0.01
    # Sign convention: a bend toward +y (d2 of the clamp) is k_y > 0, k_x = 0 (docs/math.md §1).
    assert np.all(k[:, 1] > 0) and np.abs(k[:, 0]).max() < 1e-9
    assert x[-1, 1] > 0


# ----------------------------------------------------------------------------------------------------
# Reader
# ----------------------------------------------------------------------------------------------------


def test_so3_log_exp_roundtrip():
    rng = np.random.default_rng(1)
    axis = rng.normal(size=(200, 3))
    w = axis / np.linalg.norm(axis, axis=1)[:, None] * rng.uniform(1e-9, 3.1, size=(200, 1))  # angles < π
    assert np.abs(so3_log(so3_exp(w)) - w).max() < 1e-12


def test_helix_by_connect_constant_curvature_no_twist():
    shape = shapes.get("helix")  # κ = 40 1/m, geometric torsion 30 rad/m, no material twist
    spec = CatheterSpec(n_segments=100)
    model, data, fx = build_connect(shape, spec)
    settle(model, data, tol=1e-7, window=0.05, max_time=2.0)
    state = RodReader(model).read(data)
    inner = _away_from_ends(state, spec)
    kappa = np.linalg.norm(state.curvature[inner], axis=1)
    assert np.abs(kappa / 40.0 - 1).max() < 1e-3  # docs/simulation.md §1: 2.9e-4 at 100 segments
    assert np.abs(state.twist[inner]).max() < 1e-5  # rad/m: free end, no torque → no material twist
    assert fx.errors(state).max() < 5e-5


@pytest.mark.parametrize("name", ["tightening", "rotating-bend", "mixed"])
def test_connect_shapes_positions_and_curvature(name):
    shape = shapes.get(name)
    spec = CatheterSpec(n_segments=100)
    model, data, fx = build_connect(shape, spec)
    settle(model, data, tol=1e-7, window=0.05, max_time=2.0)
    state = RodReader(model).read(data)
    assert fx.errors(state).max() < 5e-5  # 0.05 mm at every vertex
    inner = _away_from_ends(state, spec)
    s = state.interior_s[inner]
    k = state.curvature[inner]
    bound = 2 * _discretisation_bound(fx.curve, s, spec.segment_length) + 0.02
    err = np.linalg.norm(k - fx.curve.curvature(s), axis=1)
    assert np.all(err <= bound), f"worst at s = {s[np.argmax(err / bound)]:.4f} m"
    # Interpolation to grating positions: the cubic spline holds the same accuracy between vertices.
    g = np.linspace(0.0, 0.17, 18)
    kg = state.curvature_at(g)
    gb = 2 * _discretisation_bound(fx.curve, g, spec.segment_length) + 0.05
    assert np.all(np.linalg.norm(kg - shape.curvature(g), axis=1) <= gb)
    # Frames: orthonormal, right-handed, and the shape's frames up to the discretisation drift.
    f = state.frames_at(g)
    assert np.abs(np.swapaxes(f, -1, -2) @ f - np.eye(3)).max() < 1e-12
    assert np.linalg.det(f) == pytest.approx(np.ones(18), abs=1e-12)
    assert np.abs(f - shape.frames(g)).max() < 0.02
    assert np.abs(state.positions_at(g) - shape.positions(g)).max() < 5e-5


def test_frames_orthonormal_and_consistent_with_darboux():
    model, data, _ = build_connect(shapes.get("widening-helix"), CatheterSpec(n_segments=60))
    mujoco.mj_step(model, data, nstep=50)
    state = RodReader(model).read(data)
    f = state.edge_frames
    assert np.abs(np.swapaxes(f, 1, 2) @ f - np.eye(3)).max() < 1e-13
    assert np.linalg.det(f).min() > 1 - 1e-13
    # d3 is the edge tangent.
    t = np.diff(state.positions, axis=0)
    assert np.abs(f[:, :, 2] - t / np.linalg.norm(t, axis=1)[:, None]).max() < 1e-13
    # frames_at reproduces the edge frames at the edge midpoints and integrates the Darboux vector between.
    assert np.abs(state.frames_at(state.edge_s) - f).max() < 1e-12
    # Linear and cubic interpolation both return the vertex values at the vertices.
    si = state.interior_s
    for method in ("linear", "cubic"):
        assert np.abs(state.darboux_at(si, method) - state.darboux).max() < 1e-10
    assert state.twist_at(si[3:5]).shape == (2,)
    assert state.curvature_at(np.zeros((2, 3))).shape == (2, 3, 2)


def test_reader_twist_sign_matches_mujoco_der_twist():
    """With +θ the frames' twist equals MuJoCo's (θ_i − θ_{i−1} + reftwist_i)/l̄ up to the log's φ²/12."""
    spec = CatheterSpec(n_segments=60)
    model, data, _ = build_connect(shapes.get("helix"), spec)
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "cath_twist")
    data.qfrc_applied[model.jnt_dofadr[j]] = 2e-5
    mujoco.mj_step(model, data, nstep=400)
    reader = RodReader(model)
    state = reader.read(data)
    n = spec.n_segments
    theta = np.zeros(n)
    theta[reader._tw_edges] = data.qpos[reader._tw_qadr]
    der = (np.diff(theta) + data.plastic[6 * n :]) / reader.lbar
    phi = np.linalg.norm(state.darboux[:, :2], axis=1) * reader.lbar
    assert np.abs(state.twist - der * (1 - phi**2 / 12)).max() < 2e-5 * np.abs(der).max() + 1e-9
    assert np.abs(state.twist).min() > 0.05  # the applied torque really twisted it


def test_reader_before_first_step_and_arbitrary_base_pose():
    """The clamp's d1 is the base pose's x axis for any pose, before and after the first step."""
    shape = shapes.get("two-plane")
    pose = Pose((0.2, -0.1, 0.3), _rot([0.4, -1.1, 2.2]))
    model, data, _ = build_connect(shape, CatheterSpec(n_segments=60), pose)
    reader = RodReader(model)
    before = reader.read(data)
    assert not data.plastic.any()
    mujoco.mj_step(model, data)
    after = reader.read(data)
    assert np.abs(before.edge_frames - after.edge_frames).max() < 1e-6
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "cath_base")
    # (to the 9 significant digits of the MJCF pose: the clamped edge and the site come from separate numbers)
    assert np.abs(after.edge_frames[0][:, 0] - data.site_xmat[site].reshape(3, 3)[:, 0]).max() < 1e-8
    settle(model, data, tol=1e-7, max_time=2.0)
    state = reader.read(data)
    # The curvature vector and twist are intrinsic: the same as with the identity pose.
    m0, d0, _ = build_connect(shape, CatheterSpec(n_segments=60))
    settle(m0, d0, tol=1e-7, max_time=2.0)
    ref = RodReader(m0).read(d0)
    g = np.linspace(0.0, 0.17, 18)
    assert np.abs(state.curvature_at(g) - ref.curvature_at(g)).max() < 1e-3
    assert np.abs(state.twist_at(g) - ref.twist_at(g)).max() < 1e-4
    assert np.abs(state.positions_at(g) - pose.apply(shape.positions(g))).max() < 5e-5
    assert np.abs(state.frames_at(g) - pose.apply_frames(ref.frames_at(g))).max() < 1e-6


def test_curvature_sign_against_known_bend_direction():
    """The library 'arc' bends toward +x = d1 at the base: the reader must give k_x = +25 1/m, k_y = 0."""
    model, data, _ = build_connect(shapes.get("arc"), CatheterSpec(n_segments=100))
    settle(model, data, tol=1e-7, max_time=2.0)
    state = RodReader(model).read(data)
    k = state.curvature_at(np.linspace(0.0, 0.17, 18))
    assert np.abs(k[:, 0] - 25.0).max() < 0.05 and np.abs(k[:, 1]).max() < 1e-6
    assert state.positions_at(0.17)[0] > 0.02  # the tip went toward +x in the world


def test_runtime_retarget_and_release():
    base = shapes.ShapeCurve(
        "straight-start", True, lambda s: np.stack(np.broadcast_arrays(25.0 + 0 * s, 0 * s), -1)
    )
    bent = shapes.ShapeCurve(
        "bent-later",
        True,
        lambda s: np.stack(np.broadcast_arrays(25.0 + 2000.0 * np.maximum(s - 0.06, 0.0) ** 2, 0 * s), -1),
    )
    scene = Scene("retarget")
    fx = add_connect_fixture(scene, base, CatheterSpec(n_segments=50))
    model, data = scene.build()
    ids = fx.eq_ids(model)
    assert np.all(model.eq_type[ids] == mujoco.mjtEq.mjEQ_CONNECT) and len(ids) == 49
    fx.set_shape(model, bent)
    settle(model, data, tol=1e-7, max_time=5.0)
    state = RodReader(model).read(data)
    assert np.abs(state.positions - fx.targets(bent)).max() < 5e-5
    tip_before = state.positions[-1].copy()
    fx.set_active(model, data, False)
    mujoco.mj_step(model, data, nstep=100)
    assert np.linalg.norm(data.flexvert_xpos[-1] - tip_before) > 1e-3  # released: it springs back


def test_settle_reports_the_fixture_when_it_does_not_settle():
    scene = Scene("free-fall-check", gravity=(0, -9.81, 0))
    scene.add_rod(CatheterSpec(n_segments=20))
    model, data = scene.build()
    with pytest.raises(SettleError, match=r"free-fall-check: not settled after .* still moved"):
        settle(model, data, tol=1e-9, window=0.05, max_time=0.2)
    seen = []
    settle_model, settle_data, _ = build_connect(shapes.get("arc"), CatheterSpec(n_segments=20))
    settle(settle_model, settle_data, tol=1e-6, progress=lambda t, moved: seen.append((t, moved)))
    assert seen and all(math.isfinite(m) for _, m in seen)


# ----------------------------------------------------------------------------------------------------
# Tube and groove
# ----------------------------------------------------------------------------------------------------


def test_extended_curve_is_smooth_across_the_ends():
    c = ExtendedCurve(shapes.get("s-curve"), 0.01, 0.01)
    for s0 in (0.0, 0.17):
        a, b = c.positions(s0 - 1e-7), c.positions(s0 + 1e-7)
        assert np.linalg.norm(a - b) == pytest.approx(2e-7, rel=1e-6)
        fa, fb = c.frames(s0 - 1e-7), c.frames(s0 + 1e-7)
        assert np.abs(fa - fb).max() < 1e-5
    # The frames stay orthonormal and positions follow the tangent over the continuations.
    s = np.linspace(-0.01, 0.18, 400)
    f = c.frames(s)
    assert np.abs(np.swapaxes(f, -1, -2) @ f - np.eye(3)).max() < 1e-10
    p = c.positions(s)
    assert np.abs(np.gradient(p, s, axis=0)[1:-1] - f[1:-1, :, 2]).max() < 1e-3


def test_tube_keeps_rod_within_clearance():
    shape = shapes.get("helix")
    spec = CatheterSpec(n_segments=50)
    model, data, tube = build_tube(shape, spec)
    assert tube.clearance == pytest.approx(165e-6, abs=1e-9)
    assert tube.max_clearance == pytest.approx(180e-6, abs=2e-6)  # between two rails
    assert tube.sagitta <= 10e-6 + 1e-9
    settle(model, data, tol=1e-6, window=0.05, max_time=10.0)
    state = RodReader(model).read(data)
    off = tube.radial_offsets(state.positions[2:])
    # Within the worst-direction clearance (between two rails, 180 µm) + soft-contact penetration (≤ 20 µm).
    assert off.max() < tube.max_clearance + 20e-6
    assert off.mean() > 0.3 * tube.clearance  # it does press against the walls (a stiff rod cuts corners)
    # The rod's own curvature is close to, not equal to, the tube's (docs/simulation.md §3: it cuts corners).
    g = np.linspace(0.0, 0.17, 18)
    diff = np.linalg.norm(state.curvature_at(g) - shape.curvature(g), axis=1)
    assert 0.05 < np.sqrt(np.mean(diff**2)) < 5.0


def _check_groove(name: str, n: int) -> None:
    spec = CatheterSpec(n_segments=n)
    model, data, groove = build_groove(shapes.get(name), spec)
    settle(model, data, tol=1e-6, window=0.05, max_time=10.0)
    state = RodReader(model).read(data)
    off = groove.cross_section_offsets(state.positions[2:])  # (d1: in the plate plane, d2: up), m
    clear = groove.clearance
    assert np.abs(off[:, 0]).max() < clear + 20e-6  # side walls, + soft-contact penetration
    assert off[:, 1].min() > -clear - 20e-6  # floor
    assert off[:, 1].max() < clear + 20e-6  # the cover
    # Most of it rests on the floor (the clamped base holds the first few millimetres at the centreline).
    assert np.median(off[:, 1]) < -0.8 * clear


def test_groove_keeps_planar_rod_on_the_floor_between_the_walls():
    assert CatheterSpec().radius * 2 < 3e-3
    _check_groove("tightening", 50)  # the sharpest planar shape, coarse rod: it left an uncovered groove
    with pytest.raises(ValueError, match="not planar"):
        build_groove(shapes.get("helix"), CatheterSpec(n_segments=20))


# ----------------------------------------------------------------------------------------------------
# Long runs
# ----------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_cantilever_100_segments():
    force = 5e-4
    state, spec = _cantilever(100, force)
    lever = state.positions[-1, 2] - state.positions[1:-1, 2]
    assert np.abs(state.curvature[:, 1] / (force * lever / spec.bending_stiffness) - 1).max() < 1e-4


@pytest.mark.slow
@pytest.mark.parametrize("n", [50, 100, 200])
@pytest.mark.parametrize("name", [c.name for c in shapes.library()])
def test_connect_every_library_shape(name, n):
    shape = shapes.get(name)
    spec = CatheterSpec(n_segments=n)
    model, data, fx = build_connect(shape, spec)
    settle(model, data, tol=1e-7, window=0.05, max_time=3.0)
    state = RodReader(model).read(data)
    assert fx.errors(state).max() < 5e-5
    inner = _away_from_ends(state, spec)
    s = state.interior_s[inner]
    bound = 2 * _discretisation_bound(fx.curve, s, spec.segment_length) + 0.02
    assert np.all(np.linalg.norm(state.curvature[inner] - fx.curve.curvature(s), axis=1) <= bound)


@pytest.mark.slow
@pytest.mark.parametrize("n", [100, 200])
@pytest.mark.parametrize("name", ["helix", "mixed", "two-plane", "through-zero"])
def test_tube_every_spatial_shape(name, n):
    spec = CatheterSpec(n_segments=n)
    model, data, tube = build_tube(shapes.get(name), spec)
    settle(model, data, tol=1e-6, window=0.05, max_time=20.0)
    state = RodReader(model).read(data)
    assert tube.radial_offsets(state.positions[2:]).max() < tube.max_clearance + 25e-6


@pytest.mark.slow
@pytest.mark.parametrize("name", [c.name for c in shapes.library() if c.planar])
def test_groove_every_planar_shape(name):
    _check_groove(name, 100)


def test_positions_at_is_linear_interpolation_along_the_rod():
    """The compiled centreline interpolation (models/_rod_kernels.py) is np.interp per coordinate: clamped at
    the ends, exact at the vertices, NaN for NaN."""
    from models import _rod_kernels

    rng = np.random.default_rng(3)
    s = np.sort(rng.uniform(-0.01, 0.2, 40))
    p = rng.normal(size=(40, 3))
    q = np.concatenate([rng.uniform(-0.05, 0.25, 300), s, [np.nan]])
    out = np.empty((q.size, 3))
    _rod_kernels.positions_at(s, p, q, out)
    ref = np.stack([np.interp(q, s, p[:, k]) for k in range(3)], axis=-1)
    np.testing.assert_allclose(out[:-1], ref[:-1], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(out[300:-1], p)
    assert np.isnan(out[-1]).all()
