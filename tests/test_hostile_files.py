"""Hostile fibre and calibration TOML files (twin/fiber.py, twin/calibration): any value of any TOML type in any
field, fields removed or unknown, files cut or with a byte flipped, numbers beyond float64 and nesting thousands
deep. Each either loads as a valid model or gives one line naming the file and the field (or the TOML error's
place); never another exception. Seeded (derandomised hypothesis) and bounded."""

from __future__ import annotations

import datetime
import math

import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from twin import FiberModel
from twin.calibration import Calibration

FIBER = FiberModel.paper().to_dict()
CALIBRATION = {"delta_theta": 0.01, "gain": 2.9e-5, "lambda0": FiberModel.paper().lambda0.tolist(),
               "twist": [0.0] * 18, "provenance": {"method": "two-step"}}

scalars = st.one_of(
    st.integers(-10, 10), st.integers(-2**70, 2**70), st.sampled_from([10**400, -(10**309), 2**1024, 2**1023]),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([1e300, -1e-300, 0.0, 1550.0, 3.7e-5]),
    st.text(max_size=8), st.booleans(), st.just(datetime.date(2024, 1, 31)), st.just(datetime.time(12, 0)),
)
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                       st.dictionaries(st.text("abc", min_size=1, max_size=3),
                                                                       inner, max_size=3)), max_leaves=12)


def check_one_line(load, path, fields) -> None:
    """``load(path)`` gives a model, or one ValueError/OSError line naming the file and a field or the TOML place."""
    try:
        load(path)
    except (ValueError, OSError) as exc:
        msg = str(exc)
        assert "\n" not in msg and msg.startswith(str(path)), msg
        assert any(f in msg for f in fields) or "TOML" in msg or "UTF-8" in msg or "table" in msg, msg


@pytest.mark.parametrize("cls, base", [(FiberModel, FIBER), (Calibration, CALIBRATION)], ids=["fiber", "calibration"])
@settings(max_examples=150, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_value_in_any_field_loads_or_is_one_line_naming_file_and_field(tmp_path, cls, base, data):
    doc = dict(base)
    field = data.draw(st.sampled_from([*base, "length", "spin_rate", "central_core", "design", "unknown"]))
    if data.draw(st.booleans()) and field in doc:
        del doc[field]
    else:
        doc[field] = data.draw(values)
    path = tmp_path / "hostile.toml"
    path.write_text(tomli_w.dumps(doc))
    check_one_line(cls.load, path, [*base, "length", "spin_rate", "central_core", "design", "unknown"])


@pytest.mark.parametrize("cls, base", [(FiberModel, FIBER), (Calibration, CALIBRATION)], ids=["fiber", "calibration"])
@settings(max_examples=100, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(cut=st.floats(0, 1), flips=st.lists(st.tuples(st.floats(0, 1), st.integers(1, 255)), max_size=3))
def test_cut_or_flipped_files_load_or_are_one_line(tmp_path, cls, base, cut, flips):
    raw = bytearray(tomli_w.dumps(base).encode())
    for where, bits in flips:
        raw[min(len(raw) - 1, int(where * len(raw)))] ^= bits
    path = tmp_path / "hostile.toml"
    path.write_bytes(bytes(raw[: math.ceil(cut * len(raw))]))
    check_one_line(cls.load, path, list(base))


@pytest.mark.parametrize("text, field", [
    ("core_angles = [{big}, 2.0944, 4.1888, 0.0]", "core_angles"),  # was OverflowError
    ("length = {big}", "length"),
    ("spin_rate = -{big}", "spin_rate"),
    ("strain_sensitivity = {big}", "strain_sensitivity"),
    ("temperature_sensitivity = [{big}, 0, 0, 0]", "temperature_sensitivity"),
    ("x = " + "[" * 5000 + "]" * 5000, "nested too deeply"),  # was RecursionError
    ("x = " + "9" * 5000, "digits"),  # was a ValueError naming no file
])
def test_numbers_beyond_float_and_deep_nesting_are_one_line(tmp_path, text, field):
    base = {k: v for k, v in FIBER.items() if k not in ("core_angles", "length", "spin_rate", "strain_sensitivity",
                                                        "temperature_sensitivity")}
    base.setdefault("core_angles", FIBER["core_angles"])
    line = text.format(big="9" * 400)
    key = line.split(" =")[0]
    path = tmp_path / "f.toml"
    path.write_text(tomli_w.dumps({k: v for k, v in base.items() if k != key}) + line + "\n")
    with pytest.raises(ValueError) as info:
        FiberModel.load(path)
    msg = str(info.value)
    assert msg.startswith(str(path)) and "\n" not in msg and field in msg, msg
    cal = tmp_path / "c.toml"
    cal.write_text(f"gain = {'9' * 400}\n")
    with pytest.raises(ValueError, match=r"c\.toml: gain: an integer of 400 digits"):
        Calibration.load(cal)


@pytest.mark.parametrize("value", ["true", '"5"', "[1.0]"])
def test_a_calibrations_spin_rate_must_be_a_number(tmp_path, value):
    """``spin_rate = true`` was read as 1 turn/m and ``"5"`` as 5 (the field was missing from the type checks)."""
    path = tmp_path / "c.toml"
    path.write_text(f"spin_rate = {value}\n")
    with pytest.raises(ValueError, match=r"c\.toml: spin_rate: expected a number"):
        Calibration.load(path)
