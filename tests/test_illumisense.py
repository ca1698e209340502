"""The ILLumiSense codec (twin.io.illumisense): byte fixtures written out by hand from the vendor layout
(docs/protocols-illumisense.md, never produced by our encoder), round trips at the protocol's quantisation,
the layout consensus, and fuzzing against a plain reading of the layout written here.

Tolerances: wavelengths travel with 4 decimals, so a round trip holds them to exactly ``float(f"{w:.4f}")``;
timestamps with microseconds (2 µs held: 0.5 µs rounding plus float64 at 4e9 s); the vendor's shape with 5
decimals of a cm (≤ 5e-8 m rounding, 1e-7 m held with the float64 of the unit conversion).
"""

from __future__ import annotations

import calendar
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from twin.frames import Frame, PeakStatus
from twin.io import illumisense
from twin.io.errors import FramingError, OversizeFrameError, TruncatedFrameError
from twin.io.illumisense import VendorSensor

FUZZ = settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
ROUND = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
MISSING, CHANNEL_ERROR, INVALID = (int(PeakStatus.MISSING), int(PeakStatus.CHANNEL_ERROR),
                                   int(PeakStatus.INVALID_VALUE))

# --------------------------------------------------------------------------------------------------- fixtures

# 1 channel × 3 gratings, no sensor block, time without fraction, CR LF: 91 payload bytes, prefix 00 00 00 5b
EXAMPLE = (
    b"\x00\x00\x00\x5b"
    b"2024/01/31\t13:45:12\t1042\t1\t1\t3\t0\t0\t0\t0\t"
    b"1530.1234\t1535.5678\t1540.9012\t-20.50\t-21.00\t-19.75\r\n"
)
EXAMPLE_EPOCH = calendar.timegm((2024, 1, 31, 13, 45, 12))

# 8 channels × 1 grating (the public client's grouping: channels 1–4 are sensor 1, 5–8 sensor 2, G = 1 each),
# channel 6 lost its peak (wavelength 0, power 0), two sensor blocks of 3 shape points; no line ending here
TWO_SENSORS = (
    b"2024/01/31\t13:45:12.5\t7\t8\t"
    b"1\t1\t0\t0\t0\t0\t1530.0001\t-20.01\t"
    b"2\t1\t0\t0\t0\t0\t1535.0002\t-20.02\t"
    b"3\t1\t0\t0\t0\t0\t1540.0003\t-20.03\t"
    b"4\t1\t0\t0\t0\t0\t1545.0004\t-20.04\t"
    b"5\t1\t0\t0\t0\t0\t1550.0005\t-20.05\t"
    b"6\t1\t0\t0\t0\t0\t0\t0\t"
    b"7\t1\t0\t0\t0\t0\t1560.0007\t-20.07\t"
    b"8\t1\t1\t0\t0\t0\t1565.0008\t-20.08\t"
    b"Curvature [1/cm]\t0.05\tCurvature angle [rad]\t1.5708\t"
    b"Shape x [cm]\t3\t0\t0.1\t0.2\tShape y [cm]\t3\t0\t0\t0.0001\tShape z [cm]\t3\t0\t0\t-0.0002\t"
    b"Curvature [1/cm]\t-0.125\tCurvature angle [rad]\t-3.1416\t"
    b"Shape x [cm]\t3\t0\t0.1\t0.19995\tShape y [cm]\t3\t0\t0.001\t0.004\tShape z [cm]\t3\t0\t0\t0"
)

# the older output some public clients also read: an engineering-value count and values after the channels
ENGINEERING = b"2024/01/31\t13:45:12\t9\t1\t1\t2\t0\t0\t0\t0\t1530.5\t1531.5\t-1\t-2\t2\t12.3\t-4.5\r\n"


def record(payload: bytes) -> bytes:
    return len(payload).to_bytes(4, "big") + payload


def check_two_sensors(rec: illumisense.Record) -> None:
    f = rec.frame
    assert f.wavelengths.shape == (1, 8) and f.sequence == 7
    expect = [1530.0001, 1535.0002, 1540.0003, 1545.0004, 1550.0005, np.nan, 1560.0007, 1565.0008]
    np.testing.assert_array_equal(f.wavelengths[0], expect)
    np.testing.assert_array_equal(f.status[0], [0, 0, 0, 0, 0, MISSING, 0, CHANNEL_ERROR])
    assert np.isnan(f.powers[0, 5]) and f.powers[0, 7] == -20.08
    assert f.timestamp == EXAMPLE_EPOCH + 0.5
    np.testing.assert_array_equal(rec.channel_numbers, np.arange(1, 9))
    assert len(rec.sensors) == 2 and f.vendor == rec.sensors
    s1, s2 = rec.sensors
    np.testing.assert_allclose(s1.curvature, [5.0], rtol=1e-15)  # 0.05 1/cm
    np.testing.assert_array_equal(s1.angle, [1.5708])
    np.testing.assert_allclose(s1.positions, [[0, 0, 0], [1e-3, 0, 0], [2e-3, 1e-6, -2e-6]], rtol=0, atol=1e-18)
    np.testing.assert_allclose(s2.curvature, [-12.5], rtol=1e-15)
    np.testing.assert_array_equal(s2.angle, [-3.1416])
    np.testing.assert_allclose(s2.positions, [[0, 0, 0], [1e-3, 1e-5, 0], [1.9995e-3, 4e-5, 0]], rtol=0, atol=1e-18)
    np.testing.assert_allclose(s1.s, [0, 1e-3, 2e-3], rtol=0, atol=1e-18)
    assert rec.extra_fields == 0 and rec.engineering.size == 0


# ---------------------------------------------------------------------------------------- hand-written bytes


def test_example_decodes_to_its_numbers_and_the_encoder_writes_it_byte_for_byte():
    assert len(EXAMPLE) == 4 + 91
    dec = illumisense.StreamDecoder(layout_quorum=0)
    (rec,) = dec.feed_records(EXAMPLE)
    f = rec.frame
    np.testing.assert_array_equal(f.wavelengths[:, 0], [1530.1234, 1535.5678, 1540.9012])
    np.testing.assert_array_equal(f.powers[:, 0], [-20.50, -21.00, -19.75])
    np.testing.assert_array_equal(f.status, 0)
    assert f.sequence == 1042 and f.timestamp == EXAMPLE_EPOCH and f.vendor is None
    assert (rec.date, rec.time) == ("2024/01/31", "13:45:12") and rec.sensors == ()
    frame = Frame(np.array([[1530.1234], [1535.5678], [1540.9012]]), EXAMPLE_EPOCH, 1042,
                  np.array([[-20.5], [-21.0], [-19.75]]))
    assert illumisense.encode_record(frame, time_digits=0) == EXAMPLE


@pytest.mark.parametrize("ending", [b"\r\n", b"\n", b"", b"\t\r\n", b"\t"])
def test_two_sensor_record_with_any_line_ending(ending):
    check_two_sensors(illumisense.decode_record(TWO_SENSORS + ending))
    dec = illumisense.StreamDecoder(layout_quorum=0)
    (rec,) = dec.feed_records(record(TWO_SENSORS + ending))
    check_two_sensors(rec)
    assert dec.framing_errors == 0 and dec.pending == 0


def test_engineering_values_and_unknown_trailing_fields():
    rec = illumisense.decode_record(ENGINEERING)
    np.testing.assert_array_equal(rec.engineering, [12.3, -4.5])
    np.testing.assert_array_equal(rec.frame.wavelengths[:, 0], [1530.5, 1531.5])
    rec = illumisense.decode_record(ENGINEERING[:-2] + b"\tTemperature [C]\t21.5\r\n")
    assert rec.extra_fields == 2 and rec.engineering.size == 2


def test_units_are_read_from_the_labels():
    p = (b"d\tt\t1\t1\t1\t1\t0\t0\t0\t0\t1550\t-3\tCurvature [1/m]\t2.5\tCurvature angle [deg]\t90\t"
         b"Shape x [mm]\t2\t0\t1\tShape y [mm]\t2\t0\t0.5\tShape z [mm]\t2\t0\t0\n")
    (s,) = illumisense.decode_record(p).sensors
    assert s.curvature[0] == 2.5 and s.angle[0] == pytest.approx(math.pi / 2, rel=1e-15)
    np.testing.assert_allclose(s.positions, [[0, 0, 0], [1e-3, 5e-4, 0]], rtol=1e-15)


@pytest.mark.parametrize(
    ("old", "new", "what"),
    [
        (b"Curvature angle [rad]\t1.5708", b"Curvature angel [rad]\t1.5708", "curvature angle label"),
        (b"Shape y [cm]\t3\t0\t0\t0.0001", b"Shape y [cm]\t2\t0\t0.0001", "shape y has 2 points"),
        (b"0.05\tCurvature angle", b"0.05\t\tCurvature angle", "not a number"),
        (b"Shape z [cm]\t3\t0\t0\t-0.0002", b"Shape q [cm]\t3\t0\t0\t-0.0002", "shape z label"),
        (b"1530.0001", b"1530.0x01", "not a number"),
        (b"\t7\t8\t1", b"\t7\t8.0\t1", "not an integer"),
    ],
)
def test_malformed_records_name_the_byte_offset(old, new, what):
    assert old in TWO_SENSORS
    bad = TWO_SENSORS.replace(old, new, 1) + b"\r\n"
    with pytest.raises(FramingError, match=what) as info:
        illumisense.decode_record(bad)
    err = info.value
    assert err.protocol == "illumisense" and err.offset is not None and 0 <= err.offset <= len(bad)


def test_truncated_records_and_ragged_bomb():
    with pytest.raises(TruncatedFrameError):
        illumisense.decode_record(TWO_SENSORS[: TWO_SENSORS.index(b"Shape z") + 15])
    with pytest.raises(FramingError):
        illumisense.decode_record(EXAMPLE[4:40])
    bomb = b"d\tt\t1\t41\t" + b"1\t0\t0\t0\t0\t0\t" * 40 + b"1\t100\t0\t0\t0\t0\t" + b"1\t" * 199 + b"1\r\n"
    with pytest.raises(FramingError, match="exceeds"):
        illumisense.decode_record(bomb, max_cells=1000)
    assert illumisense.decode_record(bomb).frame.wavelengths.shape == (100, 41)


def test_missing_invalid_ragged_and_channel_status():
    payload = (b"x\ty\t5\t2\t3\t3\t0\t0\t2\t0\t0.000\tnan\t1550.5\t-1\t-2\t-3\t4\t1\t0\t0\t0\t0\t1560.25\t-7\r\n")
    rec = illumisense.decode_record(payload)
    f = rec.frame
    np.testing.assert_array_equal(f.wavelengths, [[np.nan, 1560.25], [np.nan, np.nan], [1550.5, np.nan]])
    np.testing.assert_array_equal(f.powers, [[np.nan, -7.0], [-2.0, np.nan], [-3.0, np.nan]])
    np.testing.assert_array_equal(
        f.status, [[MISSING | CHANNEL_ERROR, 0], [INVALID | CHANNEL_ERROR, MISSING], [CHANNEL_ERROR, MISSING]])
    assert math.isnan(f.timestamp)
    np.testing.assert_array_equal(rec.grating_counts, [3, 1])


def test_single_channel_layout():
    payload = b"2024/01/31\t00:00:00\t7\t1\t1\t4\t0\t0\t0\t0\t1530.1\t0\t1550\t1560\t-1\t0\t-3\t-4\r\n"
    f = illumisense.decode_payload(payload, channels_as="single", n_cores=2)
    np.testing.assert_array_equal(f.wavelengths, [[1530.1, 1550.0], [np.nan, 1560.0]])
    with pytest.raises(FramingError):
        illumisense.decode_payload(payload, channels_as="single", n_cores=3)
    frame = Frame(np.array([[1530.1, 1550.0], [np.nan, 1560.0]]), EXAMPLE_EPOCH - 13 * 3600 - 45 * 60 - 12, 7,
                  np.array([[-1.0, -3.0], [0.0, -4.0]]))
    assert illumisense.encode_payload(frame, channels_as="single", time_digits=0) == payload.replace(
        b"1530.1\t0\t1550\t1560\t-1\t0\t-3\t-4", b"1530.1000\t0\t1550.0000\t1560.0000\t-1.00\t0\t-3.00\t-4.00")


def test_timestamps_parse_or_give_nan():
    assert illumisense.parse_timestamp(b"1970/01/02", b"00:00:01.5") == 86401.5
    assert illumisense.parse_timestamp(b"1970-01-02", b"00:00:01") == 86401.0
    for date, time in [(b"31.01.2024", b"13:45:12"), (b"2024/02/30", b"00:00:00"), (b"2024/01/31", b"25:00:00"),
                       (b"2024/01-31", b"12:00:00"), (b"\xff", b"\x00"), (b"0000/00/00", b"00:00:00.000000")]:
        assert math.isnan(illumisense.parse_timestamp(date, time))
        p = date + b"\t" + time + b"\t1\t1\t1\t1\t0\t0\t0\t0\t1550\t0\n"
        if b"\x00" not in p:
            assert math.isnan(illumisense.decode_record(p).frame.timestamp)
    # the compiled reader and Python's agree on fractions of any length
    for t in (b"13:45:12.3", b"13:45:12.123456", b"13:45:12.1234567890123456789", b"13:45:12."):
        p = b"2024/01/31\t" + t + b"\t1\t0\n"
        assert illumisense.decode_record(p).frame.timestamp == illumisense.parse_timestamp(b"2024/01/31", t)
    assert illumisense.format_timestamp(math.nan) == ("0000/00/00", "00:00:00.000000")
    assert illumisense.format_timestamp(86399.9999996) == ("1970/01/02", "00:00:00.000000")


def test_encoder_writes_sensor_blocks_in_the_vendor_units():
    frame = Frame(np.array([[1550.0]]), EXAMPLE_EPOCH, 3, np.array([[-5.0]]))
    sensor = VendorSensor(np.array([5.0]), np.array([1.5708]), np.array([[0, 0, 0], [1e-3, 0, 2e-6]]))
    got = illumisense.encode_payload(frame, sensors=[sensor], time_digits=0, line_ending=b"")
    assert got == (b"2024/01/31\t13:45:12\t3\t1\t1\t1\t0\t0\t0\t0\t1550.0000\t-5.00\t"
                   b"Curvature [1/cm]\t0.050000\tCurvature angle [rad]\t1.57080\t"
                   b"Shape x [cm]\t2\t0.00000\t0.10000\tShape y [cm]\t2\t0.00000\t0.00000\t"
                   b"Shape z [cm]\t2\t0.00000\t0.00020")


# -------------------------------------------------------------------------------------------------- stream


def test_stream_survives_every_split_point():
    stream = EXAMPLE + record(TWO_SENSORS + b"\n") + EXAMPLE + record(TWO_SENSORS)
    for cut in range(len(stream) + 1):
        dec = illumisense.StreamDecoder(layout_quorum=0)
        frames = dec.feed(stream[:cut]) + dec.feed(stream[cut:])
        assert [f.sequence for f in frames] == [1042, 7, 1042, 7]
        assert dec.framing_errors == 0
    dec = illumisense.StreamDecoder(layout_quorum=0)
    frames = [f for b in stream for f in dec.feed(bytes([b]))]
    assert len(frames) == 4 and dec.sequence.sequence_resets == 2


def test_stream_refuses_a_huge_prefix_and_resynchronises():
    dec = illumisense.StreamDecoder(max_payload=1000, layout_quorum=0)
    frames = dec.feed(b"\x7f\xff\xff\xff" + EXAMPLE)
    assert [f.sequence for f in frames] == [1042]
    assert dec.framing_errors == 1 and isinstance(dec.last_error, OversizeFrameError)
    assert dec.bytes_discarded == 4 and dec.in_sync
    dec = illumisense.StreamDecoder(max_payload=90)
    assert dec.feed(EXAMPLE[:4]) == [] and dec.framing_errors == 1
    with pytest.raises(ValueError):
        illumisense.StreamDecoder(max_payload=1 << 24)


def rec_of(seq: int, channels: int = 4, ending: bytes = b"\r\n") -> bytes:
    body = b"".join(b"%d\t2\t0\t0\t0\t0\t%d.5\t%d.25\t-1\t-2\t" % (k + 1, 1530 + k, 1540 + k) for k in range(channels))
    return record(b"2024/01/31\t13:45:%02d\t%d\t%d\t" % (seq % 60, seq, channels) + body[:-1] + ending)


def test_stream_counts_garbage_gaps_and_truncation():
    dec = illumisense.StreamDecoder()
    frames = dec.feed(rec_of(1) + b"garbage\r\n\x00\x01" + rec_of(2) + rec_of(5, ending=b"") +
                      b"\x00\x00\x00\x20abc" + rec_of(6))
    assert [f.sequence for f in frames] == [1, 2, 5, 6]
    assert dec.framing_errors == 2
    assert dec.sequence.sequence_gaps == 1 and dec.sequence.lost_samples == 2
    dec.feed(rec_of(7)[:20])
    dec.finish()
    assert dec.framing_errors == 3 and isinstance(dec.last_error, TruncatedFrameError)
    assert [f.sequence for f in dec.feed(rec_of(8))] == [8]


def test_one_odd_first_record_does_not_fix_the_layout():
    """Issue 11.6: a first record with 3 channels, then 4-channel records."""
    dec = illumisense.StreamDecoder()
    frames = dec.feed(rec_of(0, channels=3) + b"".join(rec_of(k) for k in range(1, 21)))
    assert [f.sequence for f in frames] == list(range(1, 21))
    assert all(f.wavelengths.shape == (2, 4) for f in frames)
    assert dec.odd_records == 1 and dec.layout_changes == 0 and dec.sequence.lost_samples == 0
    # an odd record later on is dropped and counted; a new layout that persists is re-learned
    frames = dec.feed(rec_of(21, channels=3) + rec_of(22) + b"".join(rec_of(k, channels=5) for k in range(23, 30)))
    assert [f.sequence for f in frames] == [22, *range(23, 30)]
    assert frames[-1].wavelengths.shape == (2, 5)
    assert dec.odd_records == 2 and dec.layout_changes == 1


def test_held_records_are_released_by_settle_and_finish():
    dec = illumisense.StreamDecoder()
    assert dec.feed(rec_of(1) + rec_of(2, channels=3)) == [] and dec.holding == 2
    assert [f.sequence for f in dec.settle()] == [2]  # a tie goes to the latest layout
    assert dec.odd_records == 1
    dec = illumisense.StreamDecoder()
    assert dec.feed(rec_of(1)) == []
    assert [f.sequence for f in dec.finish()] == [1]


# ---------------------------------------------------------------------------------------- round trips


@st.composite
def random_frames(draw, max_gratings: int = 12, max_cores: int = 8, timestamps: bool = True) -> Frame:
    g = draw(st.integers(1, max_gratings))
    c = draw(st.integers(1, max_cores))
    w = draw(hnp.arrays(np.float64, (g, c), elements=st.floats(1000.0, 2000.0)))
    w[draw(hnp.arrays(np.bool_, (g, c)))] = np.nan
    powers = draw(hnp.arrays(np.float64, (g, c), elements=st.floats(-80.0, 20.0)))
    seq = draw(st.integers(0, 2**40))
    ts = draw(st.one_of(st.just(math.nan), st.floats(0.0, 4e9))) if timestamps else math.nan
    return Frame(w, timestamp=ts, sequence=seq, powers=powers)


@st.composite
def random_sensors(draw) -> list[VendorSensor]:
    out = []
    for _ in range(draw(st.integers(0, 3))):
        g, n = draw(st.integers(0, 6)), draw(st.integers(0, 12))
        k = draw(hnp.arrays(np.float64, g, elements=st.floats(-100, 100)))
        a = draw(hnp.arrays(np.float64, g, elements=st.floats(-4, 4)))
        p = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-0.5, 0.5)))
        out.append(VendorSensor(k, a, p))
    return out


@ROUND
@given(random_frames(), random_sensors(), st.booleans(), st.sampled_from([b"\r\n", b"\n", b""]))
def test_round_trip_at_the_protocol_quantisation(frame, sensors, single, ending):
    layout = "single" if single else "cores"
    rec = illumisense.encode_record(frame, sensors=sensors, channels_as=layout, line_ending=ending)
    (got,) = illumisense.StreamDecoder(channels_as=layout, n_cores=frame.wavelengths.shape[1]).feed_records(rec) \
        or [illumisense.decode_record(rec[4:], channels_as=layout, n_cores=frame.wavelengths.shape[1])]
    w = frame.wavelengths
    missing = np.isnan(w)
    f = got.frame
    np.testing.assert_array_equal(np.isnan(f.wavelengths), missing)
    np.testing.assert_array_equal(f.status, np.where(missing, MISSING, 0))
    expect = np.vectorize(lambda x: float(f"{x:.4f}"))(np.where(missing, 1.0, w))
    np.testing.assert_array_equal(f.wavelengths[~missing], expect[~missing])
    assert f.sequence == frame.sequence
    if math.isnan(frame.timestamp):
        assert math.isnan(f.timestamp)
    else:
        assert abs(f.timestamp - frame.timestamp) <= 2e-6
    # a block without gratings or shape points is absent, and so are those after it (issue 23 B4)
    usable = next((j for j, b in enumerate(sensors) if not (b.curvature.size and b.positions.size)), len(sensors))
    assert len(got.sensors) == usable and got.absent_sensors == len(sensors) - usable
    for a, b in zip(got.sensors, sensors[:usable], strict=True):
        np.testing.assert_allclose(a.curvature, b.curvature, rtol=0, atol=0.5e-4 + 1e-12)  # 1e-6 1/cm
        np.testing.assert_allclose(a.angle, b.angle, rtol=0, atol=0.5e-5 + 1e-12)
        np.testing.assert_allclose(a.positions, b.positions, rtol=0, atol=1e-7)


# ------------------------------------------------------------------------------------------------ fuzzing

_NUMCHARS = set(b"0123456789.+-eEnNaAiIfFtTyY")
_LABELS = {"Curvature": ("curvature", {"1/cm": 100.0, "1/m": 1.0, "1/mm": 1000.0}, "1/cm"),
           "Curvature angle": ("angle", {"rad": 1.0, "deg": math.pi / 180}, "rad"),
           "Shape x": ("x", {"cm": 0.01, "mm": 1e-3, "m": 1.0}, "cm"),
           "Shape y": ("y", {"cm": 0.01, "mm": 1e-3, "m": 1.0}, "cm"),
           "Shape z": ("z", {"cm": 0.01, "mm": 1e-3, "m": 1.0}, "cm")}


def _number(tok: bytes) -> float | None:
    if not tok or not set(tok) <= _NUMCHARS:
        return None
    try:
        return float(tok)
    except ValueError:
        return None


def _int(tok: bytes, long: bool = False) -> int | None:
    body = tok[1:] if tok[:1] in (b"+", b"-") else tok
    if not body.isdigit() or (len(body.lstrip(b"0")) > 15 and not long):
        return None
    return int(tok)


def _label(tok: bytes):
    if _number(tok) is not None or not tok:
        return None
    try:
        text = tok.decode("ascii").strip()
    except UnicodeDecodeError:
        return None
    name, _, unit = text.partition("[")
    spec = _LABELS.get(name.strip())
    if spec is None:
        return None
    unit = unit.rstrip("]").strip() if unit else spec[2]
    return (spec[0], spec[1][unit]) if unit in spec[1] else None


def reference(payload: bytes) -> dict:
    """A plain reading of the layout, independent of the codec; ValueError when it is not a record."""
    text = payload
    for end in (b"\n", b"\r", b"\t"):
        text = text.removesuffix(end)
    if any(c in text for c in (b"\n", b"\r", b"\x00")):
        raise ValueError("line break inside")
    f = text.split(b"\t")
    n = len(f)

    def need(ok, why="bad"):
        if ok is None or ok is False:
            raise ValueError(why)
        return ok

    if n < 4:
        raise ValueError("short")
    seq = need(_int(f[2], long=True))
    seq = min(seq, 2**63 - 1) if seq >= -(2**63) else -1  # beyond int64: as absurd as it was (twin.io.sequence)
    c = need(_int(f[3]))
    need(c >= 0)
    pos, chans = 4, []
    for _ in range(c):
        need(pos + 6 <= n)
        number, g = need(_int(f[pos])), need(_int(f[pos + 1]))
        need(g >= 0)
        status = [need(_int(f[pos + 2 + j])) for j in range(4)]
        vals = [need(_number(x)) for x in f[pos + 6 : pos + 6 + 2 * g]]
        need(len(vals) == 2 * g)
        chans.append((number, status, vals[:g], vals[g:]))
        pos += 6 + 2 * g
    sensors, eng = [], None
    while pos < n:
        lab = _label(f[pos])
        if lab is not None and lab[0] == "curvature":
            q = pos + 1
            while q < n and (_number(f[q]) is not None or f[q] == b""):
                q += 1
            curv = [need(_number(x)) for x in f[pos + 1 : q]]
            lab2 = need(_label(f[q]) if q < n else None)
            need(lab2[0] == "angle")
            ang = [need(_number(x)) for x in f[q + 1 : q + 1 + len(curv)]]
            need(len(ang) == len(curv))
            p, xyz, units, npts = q + 1 + len(curv), [], [], None
            for axis in "xyz":
                la = need(_label(f[p]) if p < n else None)
                need(la[0] == axis)
                m = need(_int(f[p + 1]) if p + 1 < n else None)
                need(0 <= m <= n - p - 2 and (npts is None or m == npts))
                npts = m
                xyz.append([need(_number(x)) for x in f[p + 2 : p + 2 + m]])
                units.append(la[1])
                p += 2 + m
            need(len(set(units)) == 1)
            sensors.append((np.array(curv) * lab[1], np.array(ang) * lab2[1],
                            np.array(xyz).reshape(3, -1).T * units[0]))
            pos = p
        elif _int(f[pos]) is not None and eng is None and not sensors:
            e = _int(f[pos])
            vals = [_number(x) for x in f[pos + 1 : pos + 1 + e]] if e >= 0 else []
            if e < 0 or len(vals) != e or any(v is None for v in vals):
                break
            eng = vals
            pos += 1 + e
        else:
            break
    return {"seq": seq, "channels": chans, "sensors": sensors, "eng": eng or [], "extra": n - pos}


def assert_matches_reference(rec: illumisense.Record, ref: dict) -> None:
    chans = ref["channels"]
    g = max((len(ch[2]) for ch in chans), default=0)
    lam = np.full((g, len(chans)), np.nan)
    pw = np.full((g, len(chans)), np.nan)
    st_ = np.zeros((g, len(chans)), dtype=np.uint8)
    for k, (_, status, wl, p) in enumerate(chans):
        st_[len(wl) :, k] = MISSING
        for j, (x, y) in enumerate(zip(wl, p, strict=True)):
            if x == 0:
                st_[j, k] |= MISSING
            elif not (math.isfinite(x) and x > 0):
                st_[j, k] |= INVALID
                pw[j, k] = y
            else:
                lam[j, k], pw[j, k] = x, y
        if any(status):
            st_[:, k] |= CHANNEL_ERROR
    f = rec.frame
    assert f.sequence == ref["seq"]
    np.testing.assert_array_equal(f.wavelengths, lam)
    np.testing.assert_array_equal(f.powers, pw)
    np.testing.assert_array_equal(f.status, st_)
    # the plain reading keeps every block; a block without gratings or shape points and those after it are
    # absent from the record (issue 23 B4)
    usable = next((j for j, (k, _, p) in enumerate(ref["sensors"]) if not (len(k) and len(p))), len(ref["sensors"]))
    assert len(rec.sensors) == usable and rec.absent_sensors == len(ref["sensors"]) - usable
    assert rec.extra_fields == ref["extra"]
    for a, (k, ang, p) in zip(rec.sensors, ref["sensors"][:usable], strict=True):
        np.testing.assert_array_equal(a.curvature, k)
        np.testing.assert_array_equal(a.angle, ang)
        np.testing.assert_array_equal(a.positions, p.reshape(-1, 3))
    np.testing.assert_array_equal(rec.engineering, ref["eng"])


_TOKENS = st.sampled_from(
    [b"0", b"1", b"2", b"3", b"-1", b"1530.1234", b"0.0", b"nan", b"inf", b"1e999", b"-2.5", b"x", b"", b"1_0",
     b" 1", b"99999999999999999999", b"\xff", b"+3", b"--1", b"5.", b".5", b"1e5", b"0.1234567890123456789",
     b"Curvature [1/cm]", b"Curvature angle [rad]", b"Shape x [cm]", b"Shape y [cm]", b"Shape z [cm]",
     b"Curvature [1/m]", b"Shape x [mm]", b"Curvature angle", b"Temperature [C]"]
)


@FUZZ
@given(
    st.one_of(
        st.binary(max_size=400),
        st.lists(_TOKENS, max_size=50).map(lambda t: b"2024/01/31\t13:45:12\t" + b"\t".join(t)),
        st.tuples(st.lists(_TOKENS, max_size=30), st.sampled_from([b"", b"\n", b"\r\n", b"\t\n"])).map(
            lambda a: TWO_SENSORS[: TWO_SENSORS.index(b"Curvature")] + b"\t".join(a[0]) + a[1]),
    )
)
@example(TWO_SENSORS + b"\r\n")
@example(ENGINEERING)
def test_fuzz_decode_matches_a_plain_reading(data):
    try:
        rec = illumisense.decode_record(data)
    except FramingError:
        with pytest.raises((ValueError, IndexError)):
            reference(data)
        return
    assert_matches_reference(rec, reference(data))


@st.composite
def corrupted(draw):
    frame = draw(random_frames(max_gratings=6, max_cores=3))
    payload = illumisense.encode_payload(frame, sensors=draw(random_sensors()))
    i = draw(st.integers(0, len(payload) - 1))
    return payload[:i] + bytes([draw(st.integers(0, 255))]) + payload[i + 1 :]


def assert_same_record(a: illumisense.Record, b: illumisense.Record) -> None:
    """Two decodings of the same payload hold the same values (NaN where NaN)."""
    for name in ("wavelengths", "powers", "status"):
        np.testing.assert_array_equal(getattr(a.frame, name), getattr(b.frame, name))
    assert a.frame.sequence == b.frame.sequence
    np.testing.assert_array_equal(a.frame.timestamp, b.frame.timestamp)
    for name in ("channel_numbers", "grating_counts", "channel_status", "engineering"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert (a.date, a.time, a.extra_fields, a.layout) == (b.date, b.time, b.extra_fields, b.layout)
    assert len(a.sensors) == len(b.sensors)
    for x, y in zip(a.sensors, b.sensors, strict=True):
        for name in ("curvature", "angle", "positions"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name))


@FUZZ
@given(corrupted())
@example(illumisense.encode_payload(Frame(np.full((2, 2), 1530.0), 0.0, 3)).replace(b"\t3\t", b"\t\n\t", 1))
def test_fuzz_corrupted_byte_decodes_only_to_what_the_bytes_say(bad):
    """One corrupted byte in a record: the single-record reading (decode_record), the stream decoder (the same
    payload as a wire record, its batch path) and the plain reading of the layout all accept it with the same
    values, or all refuse it."""
    stream = illumisense.StreamDecoder(layout_quorum=0)
    streamed = stream.feed_records(len(bad).to_bytes(4, "big") + bad)
    assert stream.finish() == []
    try:
        rec = illumisense.decode_record(bad)
    except FramingError:
        with pytest.raises((ValueError, IndexError)):
            reference(bad)
        assert streamed == [] and stream.framing_errors == 1
        return
    assert_matches_reference(rec, reference(bad))
    assert len(streamed) == 1 and stream.framing_errors == 0
    assert_same_record(streamed[0], rec)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(random_frames(max_gratings=5, max_cores=3, timestamps=False), min_size=3, max_size=3),
       st.binary(max_size=200), st.lists(st.integers(1, 300), max_size=20))
def test_fuzz_stream_garbage_and_chunking(frames, garbage, cuts):
    recs = [illumisense.encode_record(f) for f in frames]
    stream = recs[0] + garbage + recs[1] + recs[2]
    whole = illumisense.StreamDecoder(layout_quorum=0)
    got = whole.feed(stream)
    seqs = [f.sequence for f in got]
    assert seqs[0] == frames[0].sequence and seqs[-2:] == [frames[1].sequence, frames[2].sequence]
    chunked = illumisense.StreamDecoder(layout_quorum=0)
    out, pos = [], 0
    for c in cuts:
        out += chunked.feed(stream[pos : pos + c])
        pos += c
    out += chunked.feed(stream[pos:])
    assert [f.sequence for f in out] == seqs
    assert (chunked.framing_errors, chunked.bytes_discarded) == (whole.framing_errors, whole.bytes_discarded)


@FUZZ
@given(st.binary(max_size=600), st.lists(st.integers(1, 64), max_size=12))
def test_fuzz_stream_arbitrary_bytes_never_raise(data, cuts):
    dec = illumisense.StreamDecoder(max_payload=4096)
    pos = 0
    for c in [*cuts, len(data)]:
        for f in dec.feed(data[pos : pos + c]):
            assert f.wavelengths.ndim == 2
        pos += c
    dec.finish()
    assert dec.pending == 0


# ------------------------------------------------------------------------------ issue 23: faults of the attack

LONG_STREAM = [illumisense.encode_record(Frame(np.full((18, 4), 1550.0) + 1e-3 * k, 0.0, k)) for k in range(60)]


def _flip_prefix(recs: list[bytes], i: int, byte: int, xor: int) -> bytes:
    bad = bytearray(recs[i])
    bad[byte] ^= xor
    return b"".join(recs[:i]) + bytes(bad) + b"".join(recs[i + 1 :])


def _feed_chunked(dec, data: bytes, cuts) -> list:
    out, pos = [], 0
    for c in [*cuts, len(data)]:
        out += dec.feed(data[pos : pos + c])
        pos += c
    return out


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 9), st.integers(1, 3), st.integers(1, 255), st.lists(st.integers(1, 5000), max_size=8))
@example(5, 1, 0x0F, [])  # length + 983040: still under 1 MiB, more than the rest of the stream
@example(5, 2, 0x40, [100, 100])
def test_fuzz_a_corrupted_length_prefix_never_stalls_the_stream(i, byte, xor, cuts):
    """Issue 23 B1: in sync, a prefix still under the bound made the decoder wait for bytes that the NULs of the
    later prefixes already proved wrong; every good record after the damaged one must be delivered."""
    data = _flip_prefix(LONG_STREAM, i, byte, xor)
    dec = illumisense.StreamDecoder()
    got = {f.sequence for f in _feed_chunked(dec, data, cuts)}
    assert set(range(len(LONG_STREAM))) - {i} <= got
    assert dec.framing_errors >= 1 and dec.in_sync and dec.pending == 0


def test_a_long_bogus_prefix_is_refused_by_the_line_end_inside_it():
    """Issue 23 B1: the line ends inside a would-be payload prove it wrong too (a log of payloads with LF)."""
    payload = LONG_STREAM[1][4:]
    data = (200_000).to_bytes(4, "big") + payload + b"".join(LONG_STREAM[2:6])
    dec = illumisense.StreamDecoder(layout_quorum=0)
    assert dec.feed(data[: 4 + len(payload)]) == []
    assert not dec.in_sync and dec.framing_errors == 1 and "NUL or LF" in str(dec.last_error)
    assert [f.sequence for f in dec.feed(data[4 + len(payload) :])] == [2, 3, 4, 5]


def test_lost_samples_never_wrap_and_do_not_depend_on_chunking():
    """Issue 23 B2: gaps of 2**63 - 2 samples each summed in int64 wrapped to a negative count."""
    from twin.io.sequence import MAX_LOST, SequenceCounter

    # the longest gaps counted as loss (a longer jump is a reset since the look-back rule, twin/io/sequence.py)
    top = MAX_LOST + 1
    seqs = [0, top, top + 1, 0, top, top + 1, 2 * top + 1, 2 * top + 2, 5]
    exact = 3 * (top - 1)  # three forward jumps; the return to 0 and the 5 are resets
    c = SequenceCounter()
    c.count_many(seqs)
    assert (c.lost_samples, c.sequence_gaps, c.sequence_resets) == (exact, 3, 2)
    one = SequenceCounter()
    for s in seqs:
        one.count(s)
    assert one.as_dict() == c.as_dict()
    recs = [illumisense.encode_record(Frame(np.full((2, 2), 1550.0), 0.0, s)) for s in seqs]
    totals = set()
    for cuts in ([], [len(r) for r in recs], [7] * 200):
        dec = illumisense.StreamDecoder(layout_quorum=0)
        assert len(_feed_chunked(dec, b"".join(recs), cuts)) == len(seqs)
        totals.add(dec.sequence.lost_samples)
    assert totals == {exact}


def test_a_19_digit_time_fraction_reads_as_python_reads_it():
    """Issue 23 B3: the compiled scanner read 19 digits ≥ 2**63 into an int64 before its length check: NaN."""
    for frac in (b"9999999999999999999", b"9223372036854775808", b"99999999999999999999999"):
        t = b"13:45:12." + frac
        want = illumisense.parse_timestamp(b"2024/01/31", t)
        assert want == EXAMPLE_EPOCH - 12 + float(b"12." + frac)
        assert illumisense.decode_record(b"2024/01/31\t" + t + b"\t1\t0\n").frame.timestamp == want


def test_a_sensor_block_without_shape_points_is_absent_and_counted(tmp_path):
    """Issue 23 B4: a block with 0 shape points raised IndexError in the vendor-distance sink (and could not be
    recorded); such a block carries no shape, so the decoder leaves it (and the blocks after it) out."""
    from io_helpers import synthetic_frames

    from twin import FiberModel
    from twin.frames import Frame
    from twin.io.record import Recorder
    from twin.reconstruct import Reconstructor
    from twin.reference_errors import VendorDistance

    fiber = FiberModel.paper()
    frames = synthetic_frames(4)
    empty = VendorSensor(np.zeros(0), np.zeros(0), np.zeros((0, 3)))
    good = VendorSensor(np.full(3, 0.5), np.zeros(3), np.c_[np.arange(200) * 1e-3, np.zeros((200, 2))])
    data = b"".join(illumisense.encode_record(f, sensors=[empty, good]) for f in frames[:2])
    data += b"".join(illumisense.encode_record(f, sensors=[good, empty]) for f in frames[2:])
    dec = illumisense.StreamDecoder(layout_quorum=0)
    got = [f for item in dec.feed_batch(data) for f in (item if item.batch_shape else (item,))]
    assert [f.vendor is None for f in got] == [True, True, False, False]
    assert len(got[2].vendor) == 1 and got[2].vendor[0].positions.shape == (200, 3)
    assert dec.sensor_blocks_absent == 2 * 2 + 2 * 1
    rec = illumisense.decode_record(illumisense.encode_payload(frames[0], sensors=[empty]))
    assert rec.sensors == () and rec.absent_sensors == 1 and rec.frame.vendor is None
    shapes = Reconstructor(fiber)(np.stack([f.wavelengths for f in got]))
    sink = VendorDistance(per_second=None)
    sink(Frame.stack(got), shapes, None)  # raised IndexError
    assert sink.frames_compared == 2  # the two frames whose sensor 0 has a shape
    with Recorder(tmp_path / "r.h5", fiber=fiber) as recorder:  # raised on the empty block's chunk shape
        recorder(Frame.stack(got))
    assert recorder.frames_written == 4


@pytest.mark.timeout(120)  # a hang guard, not a speed limit (the decode takes about a second)
def test_a_megabyte_of_minimal_sensor_blocks_decodes_in_one_pass():
    """Issue 23, also seen: ~18,700 minimal sensor blocks in one 1 MiB record; the walk looked up the next label
    among all the record's labels per block (quadratic). The record decodes, its blocks absent and counted."""
    blk = b"\tCurvature\tCurvature angle\tShape x\t0\tShape y\t0\tShape z\t0"
    n = (illumisense.DEFAULT_MAX_PAYLOAD - 40) // len(blk)
    payload = b"2024/01/31\t13:45:12\t1\t0" + blk * n + b"\r\n"
    assert n > 18_000 and len(payload) <= illumisense.DEFAULT_MAX_PAYLOAD
    dec = illumisense.StreamDecoder(layout_quorum=0)
    (got,) = dec.feed_records(record(payload) + EXAMPLE)[:1]
    assert got.absent_sensors == n and got.sensors == () and dec.sensor_blocks_absent == n
