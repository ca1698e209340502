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


# ------------------------------------------------------------------------------------------ ILLumiSense text logs


def _peak(fn) -> tuple[object, int]:
    """``fn()``'s result (or the exception it raised) and the peak of Python's allocations while it ran, bytes."""
    import tracemalloc

    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        try:
            out = fn()
        except Exception as exc:  # handed back to the test, which checks its kind
            out = exc
        return out, tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


@pytest.mark.timeout(120)  # hang guard: every line of junk was walked in Python (≈ 0.2 ms a line)
def test_a_log_of_random_bytes_is_refused_in_one_line_in_bounded_memory(tmp_path):
    import numpy as np

    from twin.io.illumisense.log import read_log

    path = tmp_path / "junk.txt"
    size = 8 << 20
    junk = np.random.default_rng(3).integers(0, 256, size).astype(np.uint8).tobytes()
    path.write_bytes(junk[:4096])
    with pytest.raises(ValueError):  # the compiled passes loaded before measuring
        read_log(path)
    path.write_bytes(b"Date\tTime\tSample\tChannels\r\n" + junk)
    out, peak = _peak(lambda: read_log(path))
    assert isinstance(out, ValueError) and str(out).startswith(str(path)) and "\n" not in str(out), out
    # the file itself, the lines' bounds and one block of lines; 21× the file before lines were decoded in blocks
    assert peak < 3 * size + (16 << 20), f"peak {peak / 2**20:.0f} MiB for a {size >> 20} MiB file"


def test_a_log_longer_than_a_block_keeps_every_intact_record_once_and_names_each_bad_line(tmp_path):
    """40,000 records across ten blocks of lines, a junk line, a cut record and a blank line in each block:
    every intact record read once, in order; every bad line counted, the first ones reported by their number."""
    import numpy as np

    from twin.frames import Frame
    from twin.io.illumisense import codec
    from twin.io.illumisense.log import _BLOCK_LINES, MAX_EXAMPLES, read_log

    n = 40_000
    rng = np.random.default_rng(4)
    lam = 1550.0 + rng.normal(0, 0.1, (n, 2, 1))
    one = [codec.encode_payload(Frame(lam[0], 1.7e9, 0))]
    lines = [b"Date\tTime\tSample\tChannels\r\n"]
    bad = []
    for i in range(n):
        if i % (_BLOCK_LINES - 7) == 100:
            bad.append(len(lines) + 1)
            lines.append(b"\x00junk\tline\r\n")
            bad.append(len(lines) + 1)
            lines.append(one[0][:25] + b"\n")  # a record cut short
            lines.append(b"  \t\r\n")  # blank: not a record, not an error
        lines.append(codec.encode_payload(Frame(lam[i], 1.7e9 + 0.01 * i, i)))
    path = tmp_path / "long.txt"
    path.write_bytes(b"".join(lines))
    log = read_log(path)
    assert np.array_equal(log.sequences, np.arange(n))
    np.testing.assert_allclose(log.wavelengths, lam, atol=5e-5, rtol=0)
    assert log.skipped_lines == len(bad) and len(bad) > MAX_EXAMPLES
    assert [int(e.split(":")[0].split()[1]) for e in log.errors] == bad[:MAX_EXAMPLES]  # the first, named


@pytest.mark.timeout(300)  # hang guard
def test_a_log_of_many_bad_lines_keeps_a_count_and_a_few_examples_not_a_message_each(tmp_path):
    """Defect: every bad line after the first record kept its own message (memory grew with the bad input: a
    million lines held ~150 MB of strings). Now: counted, the first ten named, in bounded memory, and reported."""
    import subprocess
    import sys

    from twin.frames import Frame
    from twin.io.illumisense import codec
    from twin.io.illumisense.log import MAX_EXAMPLES, read_log
    from twin.io.record import open_recording

    lam0 = FiberModel.paper().lambda0  # what `twin replay` assumes without --fiber
    good = b"".join(codec.encode_payload(Frame(lam0 + 0.001 * i, 1.7e9 + i, i)) for i in range(5))
    n_bad = 50_000
    path = tmp_path / "bad.txt"
    path.write_bytes(good + b"not\ta\trecord\n" * n_bad + good)
    read_log(path)  # the compiled passes loaded before measuring
    log, peak = _peak(lambda: read_log(path))
    assert log.skipped_lines == n_bad and len(log.errors) == MAX_EXAMPLES
    assert [int(e.split(":")[0].split()[1]) for e in log.errors] == list(range(6, 6 + MAX_EXAMPLES))
    assert len(log.sequences) == 10
    size = path.stat().st_size
    # the file, the lines' bounds (3 int64 a line) and one block of lines; a message a line took ~12× the file
    assert peak < 2 * size + 24 * (n_bad + 10) + (16 << 20), f"peak {peak / 2**20:.0f} MiB for {size >> 20} MiB"
    with open_recording(path) as r:
        assert r.skipped_lines == n_bad and len(r.errors) == MAX_EXAMPLES
    out = subprocess.run([sys.executable, "-m", "twin.cli", "replay", str(path)], capture_output=True, text=True,
                         timeout=240)
    assert f"{n_bad} line(s) skipped, first: line 6:" in out.stderr, out.stderr
