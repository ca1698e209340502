"""Calibration and identification as a user runs them (twin calibrate, static-shapes --record, twin identify),
and the paper's ablation in the twin."""

import json

import numpy as np
import pytest

from scenarios import paper_ablation
from twin import Calibration, jsonout
from twin.cli import main


def run_cli(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def calibration(tmp_path_factory):
    path = tmp_path_factory.mktemp("cal") / "calibration.toml"
    assert main(["calibrate", "sim://calibration", "--out", str(path), "--frames", "40", "--json"]) == 0
    return path


def test_calibrate_against_the_twin(calibration):
    cal = Calibration.load(calibration)
    from twin.io import open_source

    src = open_source("sim://calibration?truth=0")
    true = src.describe()
    # 25° + 8° of twist found to ≈ 0.1°: noise (≈ 0.01° after averaging) and the bias of measuring the bend
    # angle with the nominal Δθ = π/3 instead of the true 1.039 rad (≈ 0.05°)
    assert np.rad2deg(np.abs(cal.twist - np.asarray(true["twist_rad"])).max()) < 0.2
    # the as-built reference wavelengths, to the noise of 40 averaged frames plus drift (≈ 0.2 pm)
    assert np.abs(cal.lambda0 - src.optics.true_fiber.lambda0).max() < 2e-3
    assert cal.provenance["source"] == "sim://calibration"


def test_calibrate_refuses_a_weak_bend(tmp_path, capsys):
    code, _, err = run_cli(capsys, "calibrate", "sim://calibration?bend_curvature=2", "--out",
                           str(tmp_path / "c.toml"), "--frames", "10")
    assert code == 2 and "refused" in err and "bend the whole sensed length more" in err
    assert not (tmp_path / "c.toml").exists()


def test_calibrate_source_errors_are_one_line(tmp_path, capsys):
    code, _, err = run_cli(capsys, "calibrate", "sim://nowhere", "--out", str(tmp_path / "c.toml"))
    assert code == 2 and err.count("\n") == 1 and "unknown simulated setup" in err


def test_record_then_identify(calibration, tmp_path, capsys):
    """static-shapes --record writes what twin identify reads; identification on 2 planar + 2 spatial shapes
    (connect fixture, 1 pm noise) recovers the twin's Δθ within 0.005 rad and g within 0.5 %, and improves a
    shape it did not fit (--validate-frames/--validate-truth) as much as the fitted ones."""
    rec = tmp_path / "rec"
    names = ["arc", "hook", "helix", "two-plane"]
    held_out = "mixed"
    code, _, _ = run_cli(capsys, "run", "static-shapes", "--shapes", ",".join([*names, held_out]), "--repeats", "4",
                         "--calibration", str(calibration), "--record", str(rec), "--json")
    assert code == 0
    pairs = [a for n in names for a in ("--frames", str(rec / f"{n}.h5"), "--truth", str(rec / f"{n}_truth.csv"))]
    out_cal = tmp_path / "identified.toml"
    code, out, _ = run_cli(capsys, "identify", *pairs, "--validate-frames", str(rec / f"{held_out}.h5"),
                           "--validate-truth", str(rec / f"{held_out}_truth.csv"), "--out", str(out_cal), "--json")
    assert code == 0
    r = json.loads(out)
    v = r["validation"]
    assert v["shapes"] == [held_out] and v["worst_after_mm"] < 0.15 < v["worst_before_mm"]
    g_true = 37.5 * 0.777 * 0.961
    assert abs(r["delta_theta"] - 1.039) < 0.005 and abs(r["g_um"] / g_true - 1) < 0.005
    assert abs(r["delta_theta"] - 1.039) < 3 * r["delta_theta_std"] + 1e-4
    assert max(r["max_error_after_mm"]) < 0.15 < min(r["max_error_before_mm"])
    cal = Calibration.load(out_cal)
    assert cal.delta_theta == pytest.approx(r["delta_theta"]) and cal.twist is not None  # λ0 and twist kept


def test_identify_input_errors(tmp_path, capsys):
    with pytest.raises(SystemExit) as usage:  # argparse: --truth is required
        main(["identify", "--frames", "a.h5", "--out", str(tmp_path / "x.toml")])
    assert usage.value.code == 2
    code, _, err = run_cli(capsys, "identify", "--frames", "a.h5", "--truth", "a.csv", "--out", str(tmp_path / "x"))
    assert code == 2 and "no such recording" in err
    (tmp_path / "t.csv").write_text("x_mm,y_mm,z_mm\n1,2,3\n")
    from twin.calibration.identify import read_truth

    with pytest.raises(ValueError, match="missing column"):
        read_truth(tmp_path / "t.csv")
    (tmp_path / "t.csv").write_text("x_m,y_m,z_m\n0,0,0\n0,0,0.001\n0,0,abc\n")
    with pytest.raises(ValueError, match="line 4: a value is not a number"):
        read_truth(tmp_path / "t.csv")
    (tmp_path / "t.csv").write_text("x_m,y_m,z_m\n0,0,0\n0,0,10\n0,0,170\n")
    with pytest.raises(ValueError, match="in m, not mm"):
        read_truth(tmp_path / "t.csv")


ABLATION_CI = paper_ablation.Params(identify_shapes=("arc", "hook", "helix", "two-plane"),
                                    validate_shapes=("s-curve", "mixed"), repeats=3, calibration_frames=50,
                                    truth="rod")


def check_ablation(r: dict) -> None:
    """The issue's acceptance: identification within 0.005 rad and 0.5 % and covered by its uncertainty; the
    paper's ordering (1) > (2) > (3) in max error for the paper mode; default mode, calibrated and identified,
    on the validation shapes: mean ≤ 0.3 mm and max ≤ 1.0 mm against the rod."""
    ident, true = r["identified"], r["true"]
    assert abs(ident["delta_theta"] - true["delta_theta"]) < 0.005
    assert abs(ident["g_um"] / true["g_um"] - 1) < 0.005
    assert abs(ident["delta_theta"] - true["delta_theta"]) <= 3 * ident["delta_theta_std"]
    assert abs(ident["g_um"] - true["g_um"]) <= 3 * ident["g_std_um"]
    paper = {row["row"]: row["identification_rod"]["max_error_mm"] for row in r["rows"] if row["mode"] == "paper"}
    assert paper["1"] > paper["2"] > paper["3"]
    final = next(row for row in r["rows"] if row["row"] == "3" and row["mode"] == "default")["validation_rod"]
    assert final["mean_error_mm"] <= 0.3 and final["max_error_mm"] <= 1.0


def test_paper_ablation_reduced_set(tmp_path):
    """4 identification shapes (2 planar in the groove, 2 spatial in tubes), 2 validation shapes, 3 frames."""
    r = paper_ablation.run_experiment(ABLATION_CI)
    check_ablation(r)
    report = paper_ablation.write_report(r, tmp_path / "report")
    assert (tmp_path / "report" / "ablation.png").stat().st_size > 10_000
    for name in ("shape_overlays", "error_along_arc_default", "errors_per_shape_rod", "errors_per_shape_fixture"):
        assert (tmp_path / "report" / f"{name}.png").stat().st_size > 10_000
    assert "identified, compensated" in report.read_text() and "calibration: per row" in report.read_text()
    assert {row["mode"] for row in r["rows"]} == {"paper", "paper-literal", "default"}


@pytest.mark.slow
def test_paper_ablation_full_set():
    """The acceptance of the identification itself, so against the catheter's centreline (a CT's truth); the
    default, against the fixtures' CAD geometry, is what README reports."""
    r = paper_ablation.run_experiment(paper_ablation.Params(truth="rod"))
    check_ablation(r)
    # the paper's interpolation ranking at the top: the spline is the best of the four
    interp = {k: v["max_error_mm"] for k, v in r["interpolation"].items()}
    assert interp["spline"] <= min(interp.values()) + 0.05


# ------------------------------------------------------------------ the scenarios' shared glue and calibration
def test_scenario_options_come_from_the_parameters():
    """scenarios/_common/entry.py: one option per Params field with metadata, values scaled to SI, defaults shown
    in the option's unit; the parsed Params equal the defaults; bools get --x/--no-x; bad choices are refused."""
    import argparse

    from scenarios import rotation, sheath_motion
    from scenarios._common import entry

    parser = argparse.ArgumentParser()
    rotation.add_arguments(parser)
    assert entry.params_from_args(rotation.Params, parser.parse_args([])) == rotation.Params()
    p = entry.params_from_args(rotation.Params, parser.parse_args(["--angle-deg", "90", "--protrusion-mm", "40"]))
    assert p.total_angle == pytest.approx(np.pi / 2) and p.protrusion == pytest.approx(0.04)
    assert "(default 50.0)" in parser.format_help() and "--json" in parser.format_help()
    with pytest.raises(SystemExit):
        parser.parse_args(["--optics", "perfect"])
    parser = argparse.ArgumentParser()
    sheath_motion.add_arguments(parser)
    assert entry.params_from_args(sheath_motion.Params, parser.parse_args(["--no-return"])).return_trip is False
    assert jsonout.finite({"a": [1.0, float("nan")], "b": float("inf")}) == {"a": [1.0, None], "b": None}


def test_calibration_choices_are_checked_and_described(tmp_path):
    """scenarios/_common/calibration.py: true, lambda0, nominal and a TOML resolve without simulation, each with a
    description for reports; anything else is one clear error."""
    from scenarios._common.calibration import calibration_for, check_calibration, label
    from scenarios._common.optics_presets import optics_config

    true = calibration_for("true", optics_config("realistic"))
    assert true.calibration.delta_theta == pytest.approx(1.039) and "no lab" in true.description
    assert calibration_for("nominal", optics_config("realistic")).calibration is None
    path = tmp_path / "c.toml"
    true.calibration.save(path)
    loaded = calibration_for(str(path), optics_config("ideal"))
    assert loaded.calibration.gain == pytest.approx(true.calibration.gain) and loaded.to_dict()["name"] == str(path)
    assert label({"name": "lab"}).startswith("calibration: lab (two-step")
    with pytest.raises(ValueError, match="no such file"):
        check_calibration("perfect")
    with pytest.raises(ValueError, match="optics must be"):
        optics_config("perfect")


@pytest.mark.slow
def test_lab_calibration_is_close_to_the_truth_and_cached(tmp_path, monkeypatch):
    """The lab calibration (two-step, then identification against the fixtures' geometry on 6 shapes) recovers
    Δθ within 0.005 rad and g within 1 % (the fixtures' centrelines are not the catheter's: the catheter's play in
    the grooves and tubes costs accuracy); a second call loads the cached file."""
    from scenarios._common.calibration import cache_dir, calibration_for
    from scenarios._common.optics_presets import optics_config

    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path))
    used = calibration_for("lab", optics_config("realistic"))
    assert abs(used.calibration.delta_theta - 1.039) < 0.005
    assert abs(used.calibration.gain / (37.5e-6 * 0.777 * 0.961) - 1) < 0.01
    assert cache_dir() == tmp_path and len(list(tmp_path.glob("lab-calibration-*.toml"))) == 1
    again = calibration_for("lab", optics_config("realistic", seed=7))  # the noise seed of a run does not matter
    assert again.calibration.gain == used.calibration.gain


def test_static_shapes_draws_while_settling():
    """static-shapes --viewer draws the catheter while it settles (through the optics and the reconstruction),
    not only its last frame; each drawing carries the rod and the fixture."""
    from scenarios import static_shapes

    class Viewer:
        def __init__(self):
            self.labels = []

        def show(self, shape, truth=None, *, base_pose=None, label=None, force=False, reframe=False):
            assert shape.positions.ndim == 2 and np.isfinite(shape.positions).all()
            assert truth.fixture is not None and truth.positions.shape[-1] == 3
            self.labels.append(label)
            return True

    v = Viewer()
    static_shapes.run_experiment(static_shapes.Params(shapes=("arc",), repeats=1, calibration="true"), viewer=v)
    settling = [lb for lb in v.labels if "settling" in lb]
    assert len(settling) >= 2 and v.labels[-1] == "arc"
