"""The real jig table of JHU AMIRo's needle_3CH_4AA_v2 (twin/data/jig/amiro, SOURCE.md there) and its twin.

The measured figures below are those SOURCE.md and docs/jig.md state; the bounds are their rounding (the table
is data, so the figures must come back to that precision, not to a tolerance that hides a change).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from scenarios.real_jig import EFFECTS, FACTOR, KEYS, compare, real_statistics
from sim_interrogator.needle_jig import AMIRO, amiro_fiber, loro, simulate
from twin import Calibration, FiberModel
from twin.calibration import jig
from twin.cli import main
from twin.data import jig_dir

DATA = jig_dir("amiro")  # package data (twin/data/jig/amiro)
POSES, NEEDLE, CALIBRATION = DATA / "poses.csv", DATA / "needle.toml", DATA / "calibration.toml"
DATA_3AA = jig_dir("amiro-3aa")  # package data (twin/data/jig/amiro-3aa)
GRATINGS = [0, 1, 2]
LEVELS = [0.0, 0.5, 1.6, 2.0, 2.5, 3.2, 4.0]
#: Measured on the table: in-sample RMS strain residual, LORO |Δκ| (1/m), LORO |Δdir| (deg).
REAL = {"rms_strain_residual": 21.86e-6, "loro_kappa_error_1_per_m": 0.1335, "loro_direction_error_deg": 5.279}


@pytest.fixture(scope="module")
def fiber() -> FiberModel:
    return FiberModel.load(NEEDLE)


@pytest.fixture(scope="module")
def poses(fiber) -> jig.JigPoses:
    return jig.read_poses(POSES, fiber=fiber)


def test_table_loads_as_described(poses):
    assert poses.n_poses == 84
    np.testing.assert_allclose(poses.orientations, np.deg2rad([0.0, 90.0, 180.0, 270.0]), atol=1e-12)
    assert sorted(set(poses.curvature.tolist())) == LEVELS
    for psi in poses.orientations:  # 3 trials of each groove, a reference per orientation
        rows = np.isclose(poses.orientation, psi)
        assert rows.sum() == 21 and (poses.curvature[rows] == 0).sum() == 3
    assert poses.std is not None
    assert 0.05e-3 < np.min(poses.std) and np.max(poses.std) < 1e-3  # 10 samples of ≈ 1.2 pm noise, nm
    w0 = poses.wavelengths[poses.curvature == 0]
    # the 12 references agree within 60 pm across re-seating; a mislabelled groove would be 100s of pm off
    assert np.all(np.abs(w0 - w0.mean(axis=0)) < 0.06)


def test_needle_toml_is_the_scenarios_amiro_fiber(fiber):
    twin = amiro_fiber()
    assert fiber.central_core is None and fiber.n_cores == 3 and fiber.n_gratings == 4
    for name in ("core_angles", "core_radii", "grating_s", "lambda0"):
        np.testing.assert_array_equal(getattr(fiber, name), getattr(twin, name))
    assert fiber.strain_sensitivity == twin.strain_sensitivity


def test_calibration_reproduces(tmp_path, capsys):
    """The shipped calibration is the error-model (nuisance) one, with its jig zero and error model, and the command
    in SOURCE.md makes it again; it prints the jig zero as the bent grooves' shortfall (docs/jig.md)."""
    out = tmp_path / "cal.toml"
    assert main(["jig-calibrate", str(POSES), "--fiber", str(NEEDLE), "--gratings", "0,1,2", "--model", "nuisance",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "Jig zero (the bent grooves' shortfall from their labels" in printed and "flat groove's" not in printed
    new, kept = Calibration.load(out), Calibration.load(CALIBRATION)
    assert kept.provenance["jig_model"] == "nuisance"
    np.testing.assert_allclose(np.array(new.lambda0), np.array(kept.lambda0), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.array(new.design), np.array(kept.design), rtol=1e-9, atol=1e-15)
    for key in ("jig_roll_rad", "jig_gratings", "jig_unfixed_gratings", "jig_core_angles_rad", "jig_gains_m",
                "jig_zero_1_per_m", "jig_rotation_zeros_1_per_m", "jig_error_strain_cov", "jig_reference_std_1_per_m"):
        np.testing.assert_allclose(np.array(new.provenance[key]), np.array(kept.provenance[key]), rtol=1e-9,
                                   atol=1e-15)
    assert kept.provenance["jig_gratings"] == GRATINGS and kept.provenance["jig_unfixed_gratings"] == [3]
    # the jig's zero as docs/jig.md states it (along/across the bend, 1/m, per grating AA1–AA3)
    np.testing.assert_allclose(kept.provenance["jig_zero_1_per_m"],
                               [[0.126, 0.043], [-0.074, 0.190], [0.333, 0.055]], atol=5e-4)


def test_in_sample_and_leave_one_rotation_out_figures(fiber):
    stats = real_statistics(POSES, fiber, GRATINGS)
    assert stats["rms_strain_residual"] == pytest.approx(REAL["rms_strain_residual"], rel=5e-4)
    assert stats["loro_kappa_error_1_per_m"] == pytest.approx(REAL["loro_kappa_error_1_per_m"], rel=5e-4)
    assert stats["loro_direction_error_deg"] == pytest.approx(REAL["loro_direction_error_deg"], rel=2e-4)
    # the figures are medians of the per-level array, over 4 held-out rotations × 3 gratings × 6 bent levels
    assert np.array(stats["kappa_rms_1_per_m"]).shape == (4, 3, 6)


def test_which_gratings_follow_the_groove(fiber, poses):
    """AA1–AA3 follow the groove; AA4, 11 mm from the tip, reads about half of it (docs/jig.md)."""
    result = jig.fit(fiber, poses)  # every grating, to see the tip one
    assert np.all(result.explained[:3] > 0.995) and result.explained[3] < 0.98
    ratio = result.gains[3].mean() / result.gains[:3].mean()
    assert 0.4 < ratio < 0.6
    assert any("grating 3" in w for w in result.warnings)


def test_orientation_sense_mirror(fiber, poses):
    """The pair (rotation sense, fibre order) of the table is the one the fit accepts without a mirror warning;
    the same rotations read the other way round with the same fibre order are flagged."""
    assert not any("mirror" in w for w in jig.fit(fiber, poses, gratings=GRATINGS).warnings)
    flipped = jig.JigPoses(orientation=(-poses.orientation) % (2 * np.pi), curvature=poses.curvature,
                           wavelengths=poses.wavelengths, std=poses.std, source="flipped")
    assert any("mirror" in w for w in jig.fit(fiber, flipped, gratings=GRATINGS).warnings)


def test_validate_another_session_after_reseating(tmp_path, poses, capsys):
    """A re-seated needle is the same sensor at another roll: with --fit-roll the calibration validates it exactly as
    it validates the unshifted rows; without, the roll error shows up as a direction error."""
    rows = np.isclose(poses.orientation, np.pi)
    session = poses.select(rows)
    reseated = jig.JigPoses(orientation=session.orientation + 0.35, curvature=session.curvature,
                            wavelengths=session.wavelengths, std=session.std, source="reseated")
    results = {}
    for name, table in (("same", session), ("reseated", reseated)):
        path = tmp_path / f"{name}.csv"
        jig.write_poses(path, table)
        for fit_roll in (True, False):
            capsys.readouterr()
            code = main(["jig-validate", str(path), "--calibration", str(CALIBRATION), "--json"]
                        + (["--fit-roll"] if fit_roll else []))
            assert code == 0
            results[name, fit_roll] = json.loads(capsys.readouterr().out)
    def summary(key):
        return results[key]["results"][0]["validation"]["summary"]
    same, moved = summary(("same", True)), summary(("reseated", True))
    for k in ("max_abs_magnitude_error_1_per_m", "max_abs_direction_error_deg"):
        assert moved[k] == pytest.approx(same[k], rel=1e-9)
    assert results["reseated", False]["results"][0]["validation"]["gratings"] == GRATINGS
    assert summary(("reseated", False))["max_abs_direction_error_deg"] > 15.0  # 0.35 rad = 20°
    assert summary(("same", False))["max_abs_direction_error_deg"] < 12.0


def test_twin_reproduces_the_real_table(fiber):
    """`twin run real-jig`: each figure of the twin (median of 10 sessions) within a factor 1.5 of the table's."""
    result = compare(real_statistics(POSES, fiber, GRATINGS), loro(AMIRO, amiro_fiber(), 10))
    assert result["passes"], result
    for k in KEYS:
        assert 1 / FACTOR <= result["ratio"][k] <= FACTOR


def test_twin_without_its_effects_is_exact():
    """The as-built sensor alone (angles, radii, twist off nominal; AA4 at the groove's end) is what the jig
    calibration absorbs: with every modelled jig effect and the interrogator's noise off, all figures vanish."""
    off = {k: v for effect in EFFECTS.values() for k, v in effect.items()}
    stats = loro(replace(AMIRO, **off), amiro_fiber(), 1)
    for k in KEYS:
        assert stats[k] < 1e-9


def test_real_jig_command_json(capsys):
    assert main(["run", "real-jig", "--json", "--seeds", "2"]) in (0, 1)
    out = json.loads(capsys.readouterr().out)
    assert set(out) >= {"real", "twin", "ratio"}
    for k in KEYS:
        assert out["ratio"][k] == pytest.approx(out["twin"][k] / out["real"][k])
        assert out["real"][k] == pytest.approx(REAL[k], rel=5e-4)


def test_jig_validate_leave_one_rotation_out_command(capsys):
    assert main(["jig-validate", str(POSES), "--fiber", str(NEEDLE), "--gratings", "0,1,2",
                 "--leave-one-rotation-out", "--model", "physical", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)["results"]["physical"]
    assert out["jig_zero"]  # the command adds the jig's zero unless told not to
    assert out["loro_kappa_error_1_per_m"] < 0.9 * REAL["loro_kappa_error_1_per_m"]
    assert main(["jig-validate", str(POSES), "--fiber", str(NEEDLE), "--gratings", "0,1,2",
                 "--leave-one-rotation-out", "--model", "physical", "--no-jig-zero", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)["results"]["physical"]
    for k in KEYS:  # without it, the table's own statistics (those the twin reproduces)
        assert out[k] == pytest.approx(REAL[k], rel=5e-4)
    assert main(["jig-validate", str(POSES), "--calibration", str(CALIBRATION), "--leave-one-rotation-out"]) == 2


# ------------------------------------------------------------------------------------------------ second needle


def test_second_needle_table_loads_as_described():
    """twin/data/jig/amiro-3aa (SOURCE.md there): needle_3CH_3AA, 81 rows (3 trials per groove but two folders of
    270°), the same grooves and rotations, its own reference per rotation, std columns from 6 samples."""
    fiber = FiberModel.load(DATA_3AA / "needle.toml")
    poses = jig.read_poses(DATA_3AA / "poses.csv", fiber=fiber)
    assert poses.n_poses == 81 and fiber.n_gratings == 3 and fiber.central_core is None
    np.testing.assert_allclose(poses.orientations, np.deg2rad([0.0, 90.0, 180.0, 270.0]), atol=1e-12)
    assert sorted(set(poses.curvature.tolist())) == LEVELS
    counts = [int(np.isclose(poses.orientation, psi).sum()) for psi in poses.orientations]
    assert counts == [21, 21, 21, 18]
    assert 0.05e-3 < np.min(poses.std) and np.max(poses.std) < 3e-3
    w0 = poses.wavelengths[poses.curvature == 0]
    dev = np.abs(w0 - w0.mean(axis=0))
    # the 12 references agree within 25 pm, but for CH2 AA2 at 270°, 55–130 pm low (SOURCE.md: a disturbed peak)
    odd = np.zeros(dev.shape, bool)
    odd[:, 1, 1] = True
    assert np.all(dev[~odd] < 0.025) and np.all(dev[odd] < 0.12)


def test_second_needle_calibration_reproduces_and_its_tip_grating_is_at_the_grooves_end(tmp_path):
    fiber = FiberModel.load(DATA_3AA / "needle.toml")
    poses = jig.read_poses(DATA_3AA / "poses.csv", fiber=fiber)
    every = jig.fit(fiber, poses)
    assert np.all(every.explained[:2] > 0.99) and every.explained[2] < 0.98
    assert 0.55 < every.gains[2].mean() / every.gains[:2].mean() < 0.8
    assert not any("mirror" in w for w in every.warnings)
    out = tmp_path / "cal.toml"
    assert main(["jig-calibrate", str(DATA_3AA / "poses.csv"), "--fiber", str(DATA_3AA / "needle.toml"),
                 "--gratings", "0,1", "--out", str(out)]) == 0
    new, kept = Calibration.load(out), Calibration.load(DATA_3AA / "calibration.toml")
    np.testing.assert_allclose(np.array(new.design), np.array(kept.design), rtol=1e-9, atol=1e-15)
    assert kept.provenance["jig_gratings"] == [0, 1] and kept.provenance["jig_unfixed_gratings"] == [2]


def test_every_model_on_both_needles_as_documented():
    """The side-by-side table of docs/jig.md ("Two real needles, every model"): leave one rotation out, score over all
    levels (median per-level RMS |Δκ| in 1/m, median |mean Δdir| in deg), with the jig's zero added to the held-out
    rotation's curvature and without, to the rounding shown there; the error model's 95 % coverage too."""
    from scenarios.real_jig import REAL_TABLES, VARIANTS, model_scores

    documented = {  # (with the jig's zero: |Δκ|, |Δdir|), (without)
        "needle_3CH_4AA_v2": {"linear": ((0.127, 5.99), (0.129, 5.98)), "physical": ((0.117, 5.92), (0.134, 5.28)),
                              "matrix": ((0.103, 5.74), (0.133, 5.47)), "nuisance": ((0.105, 5.33), (0.166, 5.15))},
        "needle_3CH_3AA": {"linear": ((0.265, 3.17), (0.270, 3.47)), "physical": ((0.224, 3.50), (0.246, 3.68)),
                           "matrix": ((0.227, 3.60), (0.253, 3.68)), "nuisance": ((0.198, 3.36), (0.259, 3.11))},
    }
    coverage = {"needle_3CH_4AA_v2": (0.986, 0.986), "needle_3CH_3AA": (0.920, 0.899)}
    for table, rows in documented.items():
        scores = {r["variant"]: r for r in model_scores(*REAL_TABLES[table], variants=VARIANTS[:4])}
        for variant, figures in rows.items():
            for key, (kappa, direction) in zip(("loro", "loro_raw"), figures, strict=True):
                assert scores[variant][f"{key}_all_kappa_1_per_m"] == pytest.approx(kappa, abs=5e-4)
                assert scores[variant][f"{key}_all_direction_deg"] == pytest.approx(direction, abs=5e-3)
        for key, cover in zip(("loro", "loro_raw"), coverage[table], strict=True):
            assert scores["nuisance"][f"{key}_coverage_95"] == pytest.approx(cover, abs=5e-4)
            assert scores["linear"][f"{key}_coverage_95"] is None


def test_twin_jig_zero_is_the_simulated_grooves_shortfall():
    """On the twin, whose bent grooves hold the needle 0.14 1/m less bent along the bend and 0.10 across than their
    labels in every session (AMIRO.reference_bias) plus 0.10 1/m of scatter per rotation, its references straight:
    the nuisance calibration's jig zero, mean over the gratings, median of 5 sessions, is that shortfall to 0.02 1/m;
    the plain linear map, which absorbed most of it into its gain, reads less than half of it. The references'
    absolute wavelengths find no bend fixed in the jig's frame (0.03 1/m), as on the real tables."""
    fiber = amiro_fiber()
    found = {"nuisance": [], "linear": []}
    bends = []
    for seed in range(5):
        poses, truth = simulate(replace(AMIRO, seed=seed), fiber)
        for model, zeros in found.items():
            cal = jig.fit(fiber, poses, model=model, gratings=truth["gratings_in_groove"]).calibration
            zeros.append(np.mean(cal.provenance["jig_zero_1_per_m"], axis=0))
        bends.append(jig.reference_bend(cal, poses)[0])
    np.testing.assert_allclose(np.median(found["nuisance"], axis=0), AMIRO.reference_bias, atol=0.02)
    assert np.all(np.median(found["linear"], axis=0) < 0.5 * np.array(AMIRO.reference_bias))
    assert np.abs(np.median(bends, axis=0)).max() < 0.03


def test_twin_local_seating_gain_and_twist_are_recovered():
    """On the twin, each rotation × grating follows 1 + N(0, 4.5 %) of every groove (AMIRO.conformity_std) and is
    twisted by N(0, 1.2°) (seat_twist_deg). The nuisance fit's local gain and roll, the budget's prior taken back
    out, recover them: median over 10 sessions within [3.0, 6.5] % and [0.8, 1.7]° (each session rests on 6 degrees
    of freedom, ≈ 30 % relative scatter of a standard deviation; the median of 10, ≈ 11 %, and the grooves' own
    scatter biases it up). Measured through the origin, as before session 7, they read about a fifth of that
    (0.9 %, 0.24°), which this test tells apart."""
    from twin.calibration.jig.nuisance import BUDGET, PRIOR_DOF

    def data_part(pooled, prior, dof):
        return np.sqrt(max(((dof + PRIOR_DOF) * pooled**2 - PRIOR_DOF * prior**2) / dof, 0.0))

    fiber = amiro_fiber()
    gains, rolls = [], []
    for seed in range(10):
        poses, truth = simulate(replace(AMIRO, seed=seed), fiber)
        nz = jig.fit(fiber, poses, model="nuisance", gratings=truth["gratings_in_groove"]).nuisance
        dof = 0.5 * 4 * len(truth["gratings_in_groove"])  # 2 rotations per axis keep half of each slope
        gains.append(data_part(nz.local_gain_std, BUDGET["local_gain"], dof))
        rolls.append(data_part(nz.local_roll_std, BUDGET["local_roll"], dof))
    assert AMIRO.conformity_std == 0.045 and AMIRO.seat_twist_deg == 1.2
    assert 0.030 <= np.median(gains) <= 0.065
    assert 0.8 <= np.rad2deg(np.median(rolls)) <= 1.7


def test_real_references_are_not_bent_by_the_jig():
    """docs/jig.md, "The jig's zero": on both real tables the references' absolute wavelengths, read through the
    nuisance calibration, hold no bend fixed in the jig's frame beyond 0.07 1/m per component (0.03 along the bend),
    while the jig zero reaches 0.33 (needle_3CH_4AA_v2, AA3) and 0.44 1/m (needle_3CH_3AA, AA2) along it: the zero
    is the bent grooves', not the flat one's. What the references keep besides is 0.01–0.08 1/m."""
    from scenarios.real_jig import REAL_TABLES

    for table, biggest in (("needle_3CH_4AA_v2", 0.333), ("needle_3CH_3AA", 0.441)):
        poses_path, fiber_path, gratings = REAL_TABLES[table]
        fiber = FiberModel.load(fiber_path)
        poses = jig.read_poses(poses_path, fiber=fiber)
        cal = jig.fit(fiber, poses, model="nuisance", gratings=list(gratings)).calibration
        bend, scatter = jig.reference_bend(cal, poses)
        assert np.max(np.array(cal.provenance["jig_zero_1_per_m"])[:, 0]) == pytest.approx(biggest, abs=5e-4)
        assert np.abs(bend[:, 0]).max() < 0.03 and np.abs(bend).max() < 0.07
        assert np.all((0.005 < scatter) & (scatter < 0.08))


def test_nuisance_against_linear_resolved_on_one_needle_not_the_other():
    """docs/jig.md, "Two real needles, every model": the nuisance model's score minus the linear map's, all levels
    with the jig's zero, and its range over leaving one rotation × grating out. needle_3CH_4AA_v2: −0.023 1/m
    (−0.034 … −0.011) and −0.66° (−0.99 … −0.53), resolved; needle_3CH_3AA: −0.066 1/m (−0.067 … −0.030), resolved,
    and +0.20° (−1.48 … +2.34), not."""
    from scenarios.real_jig import REAL_TABLES, VARIANTS, model_scores

    documented = {"needle_3CH_4AA_v2": ((-0.0229, -0.0339, -0.0108), (-0.66, -0.99, -0.53)),
                  "needle_3CH_3AA": ((-0.0664, -0.0672, -0.0304), (0.198, -1.48, 2.34))}
    for table, (kappa, direction) in documented.items():
        rows = {r["variant"]: r for r in model_scores(*REAL_TABLES[table], variants=(VARIANTS[0], VARIANTS[3]))}
        d = rows["nuisance"]["loro_all_vs_first"]
        assert [d["magnitude_1_per_m"], *d["magnitude_range_1_per_m"]] == pytest.approx(kappa, abs=5e-4)
        assert [d["direction_deg"], *d["direction_range_deg"]] == pytest.approx(direction, abs=5e-3)
        assert d["n_clusters"] == 4 * len(REAL_TABLES[table][2])
        assert rows["linear"]["loro_all_vs_first"]["magnitude_1_per_m"] == 0.0


def test_model_study_scores_with_and_without_the_jig_zero():
    """`twin run real-jig --models` on the twin: every variant scored on held-out rotations and a second session
    with the jig's zero and without, and on the truth session (straight references) without."""
    from scenarios.real_jig import VARIANTS, model_study

    out = model_study(replace(AMIRO, seed=0), amiro_fiber(), 1, variants=(VARIANTS[0], VARIANTS[3]))
    assert out["seeds"] == 1 and set(out["variants"]) == {"linear", "nuisance"}
    med = out["variants"]["nuisance"]["median"]
    for key in ("loro", "second", "loro_raw", "second_raw", "truth"):
        assert med[f"{key}_all_kappa_1_per_m"] > 0 and med[f"{key}_all_direction_deg"] > 0
    assert 0 < med["loro_coverage_95"] <= 1 and "loro_coverage_95" not in out["variants"]["linear"]["median"]
    assert out["variants"]["linear"]["better_than_linear"]["truth_all_kappa_1_per_m"] == 0.0
