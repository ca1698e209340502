"""FiberModel: the reference fibre, validation with clear messages, TOML round trips."""

import numpy as np
import pytest

from twin import FiberModel


def test_paper_fiber_matches_the_paper():
    f = FiberModel.paper()
    assert f.n_cores == 4 and f.n_gratings == 18
    assert f.central_core == 0 and f.core_radii[0] == 0
    np.testing.assert_allclose(np.diff(f.core_angles[1:]), np.pi / 3)
    np.testing.assert_allclose(f.core_radii[1:], 37.5e-6)
    assert f.strain_sensitivity == 0.777
    np.testing.assert_allclose(f.grating_s[[0, -1]], [0.0, 0.17])
    np.testing.assert_allclose(np.diff(f.grating_s), 0.01)
    assert f.sensed_length == pytest.approx(0.17)
    np.testing.assert_allclose(f.gains[1:], 37.5e-6 * 0.777)


def test_model_is_immutable():
    f = FiberModel.paper()
    with pytest.raises(ValueError):
        f.core_angles[0] = 1.0
    with pytest.raises(AttributeError):
        f.handedness = -1


def test_toml_round_trip(tmp_path):
    f = FiberModel.paper().replace(temperature_sensitivity=[6.6e-6, 6.61e-6, 6.59e-6, 6.6e-6], length=0.18)
    path = tmp_path / "fiber.toml"
    f.save(path)
    g = FiberModel.load(path)
    for name in ("core_angles", "core_radii", "grating_s", "lambda0", "temperature_sensitivity"):
        np.testing.assert_array_equal(getattr(f, name), getattr(g, name))
    assert (g.central_core, g.handedness, g.length, g.name) == (f.central_core, f.handedness, f.length, f.name)


def test_toml_without_central_core(tmp_path):
    f = FiberModel(
        core_angles=[0, 2 * np.pi / 3, 4 * np.pi / 3],
        core_radii=[0.5e-3] * 3,
        grating_s=[0.02, 0.05, 0.09],
        lambda0=np.full((3, 3), 1550.0),
    )
    f.save(tmp_path / "n.toml")
    assert FiberModel.load(tmp_path / "n.toml").central_core is None


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"core_radii": [0.0, 37.5e-6, -1e-6, 37.5e-6]}, "core_radii: expected radii >= 0 m, got -1e-06 for core 2"),
        ({"core_radii": [0.0, 37.5e-6, 37.5e-6]},
         "FiberModel.core_radii: core_angles has 4 entries, core_radii 3: both need one per core (lambda0 has 4"),
        # issue 23 A11: one entry removed from core_angles blamed core_radii
        ({"core_angles": [0.0, 0.0, 1.0]},
         "FiberModel.core_angles: core_angles has 3 entries, core_radii 4: both need one per core (lambda0 has 4"),
        ({"core_angles": [0.0, 0.0, 1.0], "lambda0": np.full((18, 5), 1550.0)},
         "FiberModel.core_angles, core_radii: core_angles has 3 entries, core_radii 4"),
        ({"core_radii": [0.0, 37.5, 37.5, 37.5]}, "radii are in metres"),
        ({"grating_s": [0.0, 0.02, 0.01] + [0.03 + 0.01 * i for i in range(15)]}, "strictly increasing"),
        ({"lambda0": np.full((18, 4), 1.55)}, "expected a Bragg wavelength in nm"),
        ({"lambda0": np.full((18, 3), 1550.0)}, "lambda0: expected shape (18, 4), got (18, 3)"),
        ({"central_core": 2}, "central core sits on the neutral axis"),
        ({"central_core": 7}, "expected an index in 0..3"),
        ({"handedness": 0}, "handedness: expected +1 (CCW) or -1 (CW)"),
        ({"strain_sensitivity": -0.7}, "strain_sensitivity"),
        ({"temperature_sensitivity": 6.6}, "expected S_T in 1/K"),
        ({"core_angles": [0.0, np.nan, 1.0, 2.0]}, "core_angles: expected finite numbers, got nan at index 1"),
        ({"length": 0.1}, "at or beyond the last grating"),
        # issue 23 B15 and "also seen": lengths in the wrong unit, angles out of any unit
        ({"grating_s": 1e6 * 0.01 * np.arange(18)}, "grating_s: grating 17 at 170000.0 m from the base"),
        ({"grating_s": 1e3 * 0.01 * np.arange(18)}, "expected arc lengths in m up to 20 m"),
        ({"length": 1e4}, "length: expected a length in m at or beyond the last grating"),
        ({"core_angles": [0.0, 0.0, 1e300, 2.0]}, "core_angles: core 2 at 1e+300 rad; expected angles in rad"),
        ({"core_angles": [0.0, 0.0, 60.0, 120.0]}, "core_angles: core 2 at 60.0 rad"),
    ],
)
def test_validation_names_field_and_expectation(change, message):
    with pytest.raises(ValueError) as info:
        FiberModel.paper().replace(**change)
    assert message in str(info.value)
    assert "FiberModel." in str(info.value)


def test_a_fiber_toml_short_of_one_core_angle_blames_core_angles_naming_the_file(tmp_path):
    path = tmp_path / "f.toml"
    FiberModel.paper().save(path)
    path.write_text(path.read_text().replace("    1.0471975511965976,\n", "", 1))
    with pytest.raises(ValueError) as info:
        FiberModel.load(path)
    assert str(info.value).startswith(f"{path}: FiberModel.core_angles: core_angles has 3 entries, core_radii 4")


def test_layout_needs_two_bending_cores():
    with pytest.raises(ValueError, match="at least 2 off-axis cores"):
        FiberModel(core_angles=[0, 0], core_radii=[0, 1e-5], grating_s=[0.0], lambda0=[[1550, 1550]])


def test_malformed_files_name_the_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("core_angles = [0, 1,\n")
    with pytest.raises(ValueError, match="bad.toml: not valid TOML"):
        FiberModel.load(bad)
    d = FiberModel.paper().to_dict()
    d["colour"] = "red"
    import tomli_w

    bad.write_text(tomli_w.dumps(d))
    with pytest.raises(ValueError, match="unknown field.*colour"):
        FiberModel.load(bad)
    del d["colour"], d["lambda0"]
    bad.write_text(tomli_w.dumps(d))
    with pytest.raises(ValueError, match="missing required field.*lambda0"):
        FiberModel.load(bad)
    d = FiberModel.paper().to_dict()
    d["core_radii"] = [0, 1e-5, "x", 1e-5]
    bad.write_text(tomli_w.dumps(d))
    with pytest.raises(ValueError, match=r"bad.toml: core_radii: expected a list of numbers"):
        FiberModel.load(bad)
    with pytest.raises(FileNotFoundError, match="no such fibre model"):
        FiberModel.load(tmp_path / "missing.toml")


# ------------------------------------------------------------------------------ bad files (issue 11 items 9, 10)

_GOOD_TOML = """
name = "probe"
core_angles = [0.0, 0.0, 1.0471975511965976, 2.0943951023931953]
core_radii = [0.0, 3.75e-05, 3.75e-05, 3.75e-05]
grating_s = [0.0, 0.01, 0.02]
lambda0 = [[1510.0, 1510.0, 1510.0, 1510.0], [1515.0, 1515.0, 1515.0, 1515.0], [1520.0, 1520.0, 1520.0, 1520.0]]
central_core = 0
strain_sensitivity = 0.777
"""


@pytest.mark.parametrize(
    "line, field, kind",
    [
        ("strain_sensitivity = [0.7]", "strain_sensitivity", "a list"),
        ("strain_sensitivity = {a = 1}", "strain_sensitivity", "a table"),
        ("strain_sensitivity = 1979-05-27", "strain_sensitivity", "a date"),
        ("strain_sensitivity = true", "strain_sensitivity", "a boolean"),
        ("name = {first = 1}", "name", "a table"),
        ("central_core = true", "central_core", "a boolean"),
        ("handedness = 1.0", "handedness", "float"),
        ("length = [0.2]", "length", "a list"),
        ("temperature_sensitivity = {x = 1}", "temperature_sensitivity", "a table"),
        ("core_radii = [0.0, true, 3.75e-05, 3.75e-05]", "core_radii", "a list"),
        ("lambda0 = [1510.0, 1515.0, 1520.0]", "lambda0", "a list"),
        ("grating_s = 0.1", "grating_s", "float"),
    ],
)
def test_a_wrong_type_in_a_fiber_file_is_one_line_naming_file_and_field(tmp_path, line, field, kind):
    key = line.split(" = ")[0]
    text = "\n".join(x for x in _GOOD_TOML.splitlines() if not x.startswith(key + " ")) + "\n" + line + "\n"
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as err:
        FiberModel.load(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: {field}: expected ") and kind in msg and "\n" not in msg


def test_the_good_fiber_file_of_those_tests_loads(tmp_path):
    (tmp_path / "good.toml").write_text(_GOOD_TOML)
    f = FiberModel.load(tmp_path / "good.toml")
    assert f.n_gratings == 3 and f.strain_sensitivity == 0.777 and f.name == "probe"


def test_a_binary_fiber_file_is_one_line_naming_the_file(tmp_path):
    path = tmp_path / "fiber.toml"
    path.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(range(256)))
    with pytest.raises(ValueError, match=rf"^{path}: not a fibre model file: byte 0 is not UTF-8 text"):
        FiberModel.load(path)
    with pytest.raises(ValueError, match=rf"^{path}: not valid TOML"):
        path.write_text("name = 'x\n")
        FiberModel.load(path)


@pytest.mark.timeout(120)  # a hang guard: the model below made `twin replay` allocate 127 GiB
@pytest.mark.parametrize(("field", "value", "message"), [
    ("grating_s", [1e4 * 0.01 * i for i in range(18)], "grating_s: grating 17 at 1700.0 m"),
    ("core_angles", [0.0, 0.0, 1e300, 2.0], "core_angles: core 2 at 1e+300 rad"),
])
def test_a_fiber_file_in_the_wrong_unit_fails_in_one_line_before_allocating(tmp_path, field, value, message):
    """Issue 23 B15: `grating_s` off by 1e6 passed validation and `twin replay` died allocating 127 GiB."""
    import subprocess
    import sys

    from io_helpers import synthetic_frames

    from twin.io.record import Recorder

    rec = tmp_path / "r.h5"
    with Recorder(rec, fiber=FiberModel.paper()) as r:
        r.append(synthetic_frames(5))
    import tomli_w

    d = FiberModel.paper().to_dict()
    d[field] = value
    (tmp_path / "bad.toml").write_text(tomli_w.dumps(d))
    proc = subprocess.run([sys.executable, "-m", "twin.cli", "replay", str(rec), "--fiber", str(tmp_path / "bad.toml")],
                          capture_output=True, text=True, timeout=100)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert f"{tmp_path / 'bad.toml'}: " in proc.stderr and message in proc.stderr


def test_a_step_count_beyond_the_bound_fails_before_allocating():
    from twin.reconstruct import Reconstructor

    with pytest.raises(ValueError, match=r"step 1e-09 m over 0.17 m makes more than 100000 steps"):
        Reconstructor(FiberModel.paper(), step=1e-9)
