"""Sheath setups (sim://sheath-rotate, sheath-cycle, sheath-path) and the rotation, repeatability and sheath-motion
experiments: geometry and motion scripts exactly, the physics on reduced runs (fast), the full experiments against
the paper's figures (slow)."""

import dataclasses
import itertools
import json
import math

import numpy as np
import pytest

from models.catheter import Scene
from models.fixtures import ExtendedCurve, SettleError, add_rails, tube_rail_offsets
from models.fixtures.walls import _knots
from scenarios import repeatability, rotation, sheath_motion
from sim_interrogator.sheath_setups import (
    Motion,
    Section,
    SheathCycle,
    SheathGeometry,
    SheathPath,
    pre_bent_sheath,
    vascular_sheath,
)
from twin import FiberModel
from twin.io import open_source

#: nm of peak shift per 1/m of curvature on a core facing the bend: λ · S_ε · r with the twin's true gain
#: (3.9 % below the datasheet): 1550 nm × 0.777 × 0.961 × 37.5 µm.
SHIFT_PER_CURVATURE = 1550.0 * 0.777 * 0.961 * 37.5e-6


# ------------------------------------------------------------------ geometry and motion (no physics)
def test_sheath_geometry_turns_by_its_sections():
    """The smoothed curvature keeps each section's turning angle: the pre-bent sheath's end tangent is turned by
    exactly the bend angle (to the ShapeCurve's integration accuracy), the vascular path is 510 mm long and its
    sharpest bends curve at 1/(8 mm)."""
    geo = pre_bent_sheath(bend_angle=math.radians(60))
    end = geo.shape.frames(geo.length)[:, 2]
    assert end @ np.array([0.0, 0.0, 1.0]) == pytest.approx(math.cos(math.radians(60)), abs=1e-9)
    s = np.linspace(0.0, geo.length, 200001)
    turn = np.trapezoid(np.hypot(*geo.curvature(s).T), s)
    assert turn == pytest.approx(math.radians(60), rel=1e-6)
    vas = vascular_sheath()
    assert vas.length == pytest.approx(0.51)
    assert vas.max_curvature == pytest.approx(125.0)
    with pytest.raises(ValueError, match="guide"):
        SheathGeometry("bad", (Section.bend(0.05, 1.0), Section(0.1)))


def test_motion_profile():
    """Trapezoidal moves: waypoints are reached and held, the peak speed is distance / (duration·(1 − accel))."""
    m = Motion(np.array([0.0, 1.0, 3.0]), np.array([0.0, 0.1, 0.1]), np.array([0.0, 0.0, 1.0]), accel=0.25)
    d, r = m.at(np.array([0.0, 1.0, 2.0, 3.0, 5.0]))
    np.testing.assert_allclose(d, [0.0, 0.1, 0.1, 0.1, 0.1], atol=1e-15)
    np.testing.assert_allclose(r, [0.0, 0.0, 0.5, 1.0, 1.0], atol=1e-15)
    t = np.linspace(0.0, 1.0, 100001)
    v = np.gradient(m.at(t)[0], t)
    assert v.max() == pytest.approx(0.1 / 0.75, rel=1e-3) and v.min() >= -1e-12
    with pytest.raises(ValueError, match="strictly increasing"):
        Motion(np.array([0.0, 0.0]), 0.0, 0.0)


def test_motion_at_one_time_equals_the_array_path():
    """The float path of Motion.at (each physics step's actuate) gives the array path's doubles bit for bit: over
    dense times through every phase (ramp up, cruise, ramp down, hold), at the waypoints, before and after."""
    rng = np.random.default_rng(3)
    for accel in (0.05, 0.2, 0.3, 0.5):
        m = Motion(np.cumsum(np.r_[0.0, rng.uniform(0.1, 2.0, 6)]), rng.normal(0.0, 0.05, 7),
                   rng.normal(0.0, 1.0, 7), accel=accel)
        t = np.r_[np.linspace(-0.5, m.duration + 0.5, 20001), m.times, np.nextafter(m.times, np.inf),
                  np.nextafter(m.times, -np.inf), rng.uniform(0.0, m.duration, 5000)]
        d, r = m.at(t)
        one = np.array([m.at(float(x)) for x in t])
        assert all(type(v) is float for v in m.at(float(t[7])))
        np.testing.assert_array_equal(one[:, 0], d)
        np.testing.assert_array_equal(one[:, 1], r)
    still = Motion(np.array([0.0]), 0.02, 0.1)
    assert still.at(3.0) == (0.02, 0.1)


def test_hub_must_stay_in_the_guide():
    with pytest.raises(ValueError, match="straight guide"):
        SheathPath(start=0.2, travel=0.1)


# ------------------------------------------------------------------ setups in MuJoCo
def test_sheath_url_and_settling():
    """sim://sheath-rotate opens, settles and reads frames whose truth sits in the sheath; a settle time too short
    to settle is a clear error naming the setup and how far the catheter still moves."""
    src = open_source("sim://sheath-rotate?steps=1&dwell=0.2&move_time=0.2&rate=10&optics=ideal")
    f = src.read()
    assert f.truth is not None and np.isfinite(f.wavelengths).all()
    d = src.describe()
    assert d["setup"] == "sheath-rotate" and d["rail_geoms"] > 100
    assert src.setup.settle_result.time < 5.0
    # the true base pose matches the commanded one at rest: on the guide axis, not rolled
    pos, frames = src.setup.nominal_base_pose(0.0)
    assert np.linalg.norm(pos - f.truth.positions[0]) < 0.2e-3  # within the 65 µm clearance + sag near the hub
    assert frames[:, 0] @ f.truth.frames[0][:, 0] > math.cos(math.radians(0.5))
    src.close()
    with pytest.raises(ValueError, match="unknown option 'colour'"):
        open_source("sim://sheath-path?colour=red")
    with pytest.raises(SettleError, match=r"sim://sheath-cycle.*still moved"):
        open_source("sim://sheath-cycle?settle_time=0.02")


def test_hub_holds_the_rod_by_equalities_as_a_pin_would():
    """The rod hangs from the hub by connect and joint equalities (Scene.add_rod parent_world/roll_joint, not a
    pin): through a quarter turn of the hub in 0.5 s the clamped edge's vertices stay within 5 µm of their places
    on the hub and its twist follows the hub's hinge within 1e-5 rad; its material frame (MuJoCo's reference
    director turned by the twist angle) lags the hub's axes by up to 0.02 rad while turning and keeps to them
    within 5e-4 rad once the hub dwells."""
    import mujoco

    from sim_interrogator.sheath_setups import SheathRotate

    setup = SheathRotate(steps=4, total_angle=2 * math.pi, move_time=0.5, dwell=0.3, segments=40)
    model, data = setup.build()
    setup.prepare(model, data)
    hub = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "hub")
    assert model.flex_vertbodyid[model.flex_vertadr[0]] != hub
    qadr = {n: int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)])
            for n in ("cath_twist_0", "hub_roll")}
    pa, va, t0 = int(model.flex_plasticadr[0]), int(model.flex_vertadr[0]), data.time
    rest = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, setup.spec.segment_length]])
    worst = np.zeros(3)
    while data.time - t0 < 1.1:  # the first dwell, a quarter turn (0.3–0.8 s) and the next dwell
        setup.actuate(model, data, data.time - t0)
        mujoco.mj_step(model, data)
        rot, theta = data.xmat[hub].reshape(3, 3), data.qpos[qadr["cath_twist_0"]]
        local = (data.flexvert_xpos[va:va + 2] - data.xpos[hub]) @ rot
        t, u = data.plastic[pa:pa + 3], data.plastic[pa + 3:pa + 6]
        d1 = math.cos(theta) * u + math.sin(theta) * np.cross(t, u)
        frame = abs(math.atan2(d1 @ rot[:, 1], d1 @ rot[:, 0]))
        worst = np.maximum(worst, [np.abs(local - rest).max(), abs(theta - data.qpos[qadr["hub_roll"]]), frame])
    assert data.qpos[qadr["hub_roll"]] > 1.0  # the hub has turned (a quarter turn commanded)
    assert worst[0] < 5e-6 and worst[1] < 1e-5 and worst[2] < 0.02, worst
    assert frame < 5e-4


ROTATION_NOISE_MM = 0.15
"""The interrogator's noise (1 pm → ≈ 0.1 mm tip std, docs/math.md §6), averaged over a 0.5 s window of 10 frames, plus
the drift (0.2 pm/√s): what is left of the tip deviation without mechanical twist."""


def test_rotation_reduced():
    """Two 90° turns (0.6 s each, 1.5 s dwells). Friction winds the catheter up while it turns and the error then
    is large; during the dwell the wind-up creeps out and the deviation after registration is the noise plus what
    wind-up is left: the residual wind-up ψ turns at most the sensed length L about a point on it, ≤ ψ·L."""
    p = rotation.Params(steps=2, total_angle=math.pi, move_time=0.6, dwell=1.5, calibration="true")
    r = rotation.run_experiment(p)
    s = r.summary()
    # the sheath acts on the catheter: friction in the bend winds it up by degrees while the hub turns
    assert s["max_windup_deg"] > 5.0
    # ... and the wind-up creeps out during the dwell (< 1° left at the measurements)
    assert s["max_windup_at_measurement_deg"] < 1.0
    # the fibre twists with the catheter and cannot see it: turning costs millimetres
    assert s["max_error_while_turning_mm"] > 5 * s["max_deviation_truth_mm"]
    budget = ROTATION_NOISE_MM + 0.17e3 * math.radians(s["max_windup_at_measurement_deg"])
    assert s["max_deviation_truth_mm"] <= budget
    assert s["max_deviation_truth_mm"] <= 1.0  # and below the paper's 0.36 mm with a short-dwell allowance
    # the EM reading adds its averaged noise (0.2 mm/axis over 10 frames: ≤ 4σ·√3 ≈ 0.44 mm in 3D)
    assert s["max_deviation_mm"] <= s["max_deviation_truth_mm"] + 0.44
    # placing the base from the commanded roll instead of tracking it: the hub–base roll difference at rest is a
    # servo error below 0.1° (0.17 mm over the sensed length)
    assert s["commanded_max_deviation_mm"] <= s["max_deviation_mm"] + 0.17
    # the paper's Frenet pipeline transcribed literally on a sheath shape with a straight shaft: θ_b is noise where
    # κ ≈ 0 (docs/math.md §3.6) and the bend rolls by centimetres; held through low curvature it stays within 1.5 mm
    assert s["paper_literal_max_deviation_mm"] > 5 * s["paper_pipeline_max_deviation_mm"]
    assert s["paper_pipeline_max_deviation_mm"] <= 1.5
    # scored the paper's way (whole-curve registration onto the 0° shape) the default pipeline agrees with itself
    # to the noise, and the literal pipeline does not
    assert r.registered["default"][0] < 1e-12 and s["registered_max_deviation_mm"] <= ROTATION_NOISE_MM
    assert s["paper_literal_registered_max_deviation_mm"] > 5 * s["registered_max_deviation_mm"]
    d = json.loads(json.dumps(r.to_dict()))
    assert len(d["per_angle"]) == 3 and d["summary"]["paper_max_deviation_mm"] == 0.36
    assert d["calibration"]["name"] == "true"


def test_repeatability_reduced(tmp_path):
    """Three cycles out by 40 mm and back. The hub returns exactly, so the true catheter's spread is what friction
    history leaves within the 65 µm clearance, amplified by the 50 mm free end (budget 0.2 mm); the sensor adds
    its noise averaged over the 0.3 s window (≈ 0.1/√6 mm) and the drift over a cycle: within 0.25 mm std of the
    truth's, and below the paper's ±0.82 mm."""
    p = repeatability.Params(cycles=3, withdraw=0.04, dwell=0.6, calibration="true")
    r = repeatability.run_experiment(p)
    s = r.summary()
    assert s["true_std_mm"] <= 0.2
    assert s["std_mm"] <= s["true_std_mm"] + 0.25
    assert s["max_mm"] <= 2 * (s["true_std_mm"] + 0.25)
    assert s["std_mm"] < repeatability.PAPER_STD_MM and s["max_mm"] < repeatability.PAPER_MAX_MM
    # the tip really went back into the sheath and out again: between returns it moved by about the withdrawal
    travel = np.linalg.norm(r.trajectories["truth"] - r.tips["true_world"][-1], axis=1).max()
    assert travel > 0.8 * p.withdraw
    # the paper's pipeline held through the straight shaft is about as repeatable; the literal one is not
    assert s["paper_pipeline_std_mm"] <= s["true_std_mm"] + 0.25 < s["paper_literal_std_mm"]
    path = repeatability.write_report(r, str(tmp_path))
    text = open(path).read()
    assert "±0.82 mm" in text and "calibration: true" in text
    for name in ("tip_scatter", "shape_overlays", "error_along_arc", "spread_per_cycle"):
        assert (tmp_path / f"{name}.png").stat().st_size > 1000


def test_sheath_motion_reduced(tmp_path):
    """Into the sharp kink (R 8 mm, 125 1/m): peaks are lost where the catheter bends so sharply that a
    grating's peak runs into its neighbour's (a 4 nm approach of peaks 5 nm apart needs ≥ 4 nm / (λ S_ε r) ≈ 92 1/m
    on a core facing the bend), they are flagged, and the errors grow there."""
    p = sheath_motion.Params(start=0.09, travel=0.06, speed=0.04, hold=0.3, return_trip=False, calibration="true")
    r = sheath_motion.run_experiment(p)
    s = r.summary()
    assert np.isfinite(r.max_error["default"]).all() and np.isfinite(r.max_error["paper"]).all()
    assert s["sharp_frames"] > 0 and (r.gentle).any()
    assert s["lost_peaks"] > 0 and s["frames_with_lost_peaks"] > 0
    assert s["rod_curvature_at_lost_1_m"] >= 4.0 / SHIFT_PER_CURVATURE
    # flagged: NaN in the frame, counted per frame and per grating, marked in the plot
    assert r.lost_gratings.sum() == r.lost_peaks.sum()
    # the default pipeline: larger errors at the sharp bend than in the gentle part (10 mm gratings cannot follow a
    # 125 1/m bend 11 mm long) ...
    assert s["sharp_mean_max_error_mm"] > s["gentle_mean_max_error_mm"]
    # ... but it solves a grating that lost one peak from the three left, so lost peaks cost it less than the paper's
    assert s["lost_mean_max_error_mm"] < s["paper_pipeline_lost_mean_max_error_mm"]
    # the paper's pipeline drops a grating with a lost peak: its error grows where peaks are lost
    assert s["paper_pipeline_lost_mean_max_error_mm"] > 2 * s["paper_pipeline_intact_mean_max_error_mm"]
    sheath_motion.write_report(r, str(tmp_path))
    assert "peaks lost" in (tmp_path / "report.md").read_text()
    assert (tmp_path / "shape_overlays.png").exists() and (tmp_path / "error_along_arc.png").exists()
    d = json.loads(json.dumps(r.to_dict()))
    assert d["summary"]["lost_peaks"] == s["lost_peaks"] and d["timeline_2hz"]


def test_cli_rotation_json_and_report(tmp_path, capsys):
    """`twin run rotation … --json --report DIR` prints one JSON object and writes the report with its plots."""
    from twin.cli import main

    code = main(["run", "rotation", "--steps", "1", "--angle-deg", "45", "--move-time", "0.3", "--dwell", "0.5",
                 "--window", "0.2", "--rate", "10", "--calibration", "true", "--json", "--report", str(tmp_path)])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["experiment"] == "rotation" and out["summary"]["paper_max_deviation_mm"] == 0.36
    assert out["params"]["total_angle"] == pytest.approx(math.pi / 4) and out["calibration"]["name"] == "true"
    summary = out["summary"]
    for key in ("paper_pipeline_max_deviation_mm", "paper_literal_max_deviation_mm", "registered_max_deviation_mm",
                "paper_pipeline_registered_max_deviation_mm"):
        assert math.isfinite(summary[key]) and summary[key] >= 0.0, key  # a number, never NaN (null in JSON)
    for name in ("report.md", "deviation_vs_angle.png", "error_over_time.png", "tip_trajectories.png",
                 "curvature_profiles.png", "shape_overlays.png", "error_along_arc.png", "registered_deviation.png"):
        assert (tmp_path / name).exists()


def test_viewer_hook_is_called():
    class Viewer:
        def __init__(self):
            self.calls = 0

        def show(self, shape, truth=None, *, base_pose=None, label=None, force=False):
            # one shape (no batch), its truth in the world, the tracked base pose (R, p)
            assert shape.positions.ndim == 2 and truth.positions.shape[-1] == 3
            R, p = base_pose
            np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
            assert np.linalg.norm(p - truth.positions[0]) < 1e-9
            self.calls += 1

    v = Viewer()
    rotation.run_experiment(rotation.Params(steps=1, total_angle=0.3, move_time=0.2, dwell=0.3, window=0.2,
                                            rate=10.0, calibration="true"), viewer=v)
    assert v.calls > 0


# ------------------------------------------------------------------ the full experiments (CI's slow stage)
@pytest.mark.slow
def test_rotation_full():
    """One turn in 8 steps with 2 s dwells, the lab calibration: the deviation after registration is within the
    paper's 0.36 mm (the wind-up has crept out to ≤ 0.3°; the rest is noise and the calibration), and the paper's
    pipeline, held through the straight shaft, within 1.5 mm (issue 12's regression)."""
    s = rotation.run_experiment(rotation.Params()).summary()
    assert s["max_windup_at_measurement_deg"] <= 0.3
    assert s["max_deviation_mm"] <= rotation.PAPER_MAX_DEVIATION_MM
    assert s["max_deviation_truth_mm"] <= ROTATION_NOISE_MM + 0.17e3 * math.radians(0.3)
    assert s["paper_pipeline_max_deviation_mm"] <= 1.5
    assert s["paper_literal_max_deviation_mm"] > 10 * s["paper_pipeline_max_deviation_mm"]


@pytest.mark.slow
def test_repeatability_full():
    """Ten cycles, the lab calibration: the sensed tip's spread is within the paper's ±0.82 mm std and 2.84 mm
    max, the guarded paper pipeline's std within 0.2 mm."""
    s = repeatability.run_experiment(repeatability.Params()).summary()
    assert s["cycles"] == 10
    assert s["std_mm"] <= repeatability.PAPER_STD_MM and s["max_mm"] <= repeatability.PAPER_MAX_MM
    assert s["std_mm"] <= s["true_std_mm"] + 0.25
    assert s["paper_pipeline_std_mm"] <= 0.2  # issue 12's regression: the guarded paper pipeline


@pytest.mark.slow
def test_sheath_motion_full():
    """In and out of the 510 mm sheath: peaks are lost at the sharp bends; the default pipeline's mean max error
    at 2 Hz is within the paper's ≈ 2.5 mm; the paper's pipeline loses the bend where peaks are lost; the 95 %
    tube holds 92–98 % of the catheter's points, and at least 90 % of each quarter of its length (94.4 % and
    91.9 % measured)."""
    r = sheath_motion.run_experiment(sheath_motion.Params())
    s = r.summary()
    assert s["lost_peaks"] > 0
    assert s["rod_curvature_at_lost_1_m"] >= 4.0 / SHIFT_PER_CURVATURE
    assert s["rod_curvature_at_lost_1_m"] <= 200.0  # the catheter stayed in the bore (no kink)
    assert s["mean_max_error_mm"] <= sheath_motion.PAPER_MEAN_MAX_MM
    assert s["paper_pipeline_lost_mean_max_error_mm"] > 2 * s["paper_pipeline_intact_mean_max_error_mm"]
    assert FiberModel.paper().n_gratings == r.lost_gratings.shape[1]
    # the 95 % tube with the lab calibration (issue 21: 92–98 % of the truth points), the distal half included:
    # the twist term carries the catheter's twist the fibre cannot see (docs/math.md §8.1)
    assert 0.92 <= s["coverage_95"] <= 0.98
    assert min(r.uncertainty["coverage_95_by_quarter"]) >= 0.90


def _largest_departure(curve, knots, offsets) -> float:
    """The largest distance of the rails (``offsets`` in the curve's Bishop frame) from their chords between
    ``knots``, sampled at 201 points a chord, m."""
    def rail_points(s):  # (n_rails, len(s), 3), curve coordinates
        return curve.positions(s)[None] + np.einsum("kij,rj->rki", curve.frames(s)[:, :, :2], offsets)

    worst = 0.0
    for a, b in itertools.pairwise(knots):
        p, ends = rail_points(np.linspace(a, b, 201)), rail_points(np.array([a, b]))
        d = ends[:, 1:] - ends[:, :1]
        u = np.clip(np.einsum("rki,rki->rk", p - ends[:, :1], d) / np.einsum("rki,rki->rk", d, d), 0.0, 1.0)
        worst = max(worst, float(np.linalg.norm(p - ends[:, :1] - u[..., None] * d, axis=-1).max()))
    return worst


@pytest.mark.parametrize("make", [lambda: SheathCycle(segments=50), lambda: SheathPath(segments=50)],
                         ids=["pre-bent", "vascular"])
def test_sheath_rails_are_the_longest_chords_within_their_sagitta(make):
    """Each rail chord keeps within 10 µm of its curved rail over its whole length, none could be two grid steps
    (0.4 mm) longer within the bound h² max κ(1 + κR)/8 the knots are chosen by, and a straight run of the sheath is
    one capsule per rail (models.fixtures.walls._knots without ``max_segment``: the same solid as 4 mm pieces,
    without their second contact at every knot)."""
    setup = make()
    setup.build()
    rails = setup.rails
    curve, knots, offsets = rails.curve, rails.knots, rails.rail_offsets
    reach = float(np.linalg.norm(offsets, axis=1).max())
    assert _largest_departure(curve, knots, offsets) <= 10e-6 + 1e-9
    assert rails.sagitta <= 10e-6 + 1e-9

    grid = np.linspace(knots[0], knots[-1], 20001)
    kappa = np.linalg.norm(curve.curvature(grid), axis=-1)
    kr = kappa * (1.0 + kappa * reach)
    for a, b in itertools.pairwise(knots[:-2]):  # the last two pieces may have been evened out
        h = b - a + 4e-4
        assert h * h * kr[(grid >= a) & (grid <= a + h)].max() > 8 * 10e-6

    # the guide is exactly straight: one capsule covers it to within the knots' 0.2 mm grid (and this grid's step)
    # of the first bend
    first_bent = grid[np.argmax(kappa > 0.0)]
    near = 2e-4 + (grid[1] - grid[0])
    assert np.count_nonzero(knots < first_bent - near) == 1 and knots[1] > first_bent - near
    capped = _knots(curve, knots[0], knots[-1], reach, 4e-3, 10e-6)
    assert len(knots) < 0.75 * len(capped)  # 4 mm pieces: 2.6 (pre-bent) and 1.46 (vascular) times as many


def test_rails_without_a_cap_even_the_end_only_within_the_bound():
    """A rail range ending just past a straight run: the last piece is a sliver after a long straight chord, and
    halving the two would run the second half into the bend; the knots keep every chord within the sagitta."""
    geo = dataclasses.replace(pre_bent_sheath(), ramp=2e-4)  # the bend starts (almost) at once at 200 mm
    curve = ExtendedCurve(geo.shape, 0.0, 0.01)
    offsets = tube_rail_offsets(geo.inner_diameter)
    reach = float(np.linalg.norm(offsets, axis=1).max())
    for end in (0.2012, 0.202, 0.205, 0.21):
        knots = _knots(curve, 0.0, end, reach, None, 10e-6)
        assert _largest_departure(curve, knots, offsets) <= 10e-6 + 1e-9, end
    with pytest.raises(ValueError, match="sheath: max_sagitta and max_segment must be > 0 m"):
        add_rails(Scene("t"), "sheath", curve, width=geo.inner_diameter, rail_offsets=offsets, max_sagitta=0.0)
