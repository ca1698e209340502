"""The one-pass reader of records of a known layout (``scan.parse_layout``, issue 24): it must decode exactly what
the general path (tokenizer, layout match, field-by-field walk) decodes, on valid and damaged records and
streams, and leave to the general path everything it does not read itself."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from twin.frames import Frame
from twin.io import illumisense
from twin.io.errors import FramingError
from twin.io.illumisense import codec, scan

# ------------------------------------------------------------------------------------------- helpers


def rec(seq: int, body: bytes | None = None, *, date: bytes = b"2024/01/31", time: bytes | None = None,
        end: bytes = b"\r\n", sensor: bool = False) -> bytes:
    """A payload of 3 channels × 2 gratings (``body`` replaces the channel blocks), optionally a sensor block."""
    if body is None:
        body = b"\t".join(b"%d\t2\t0\t0\t0\t0\t%d.5\t%d.25\t-1.5\t-2" % (k + 1, 1530 + k, 1540 + k) for k in range(3))
    tail = (b"\tCurvature [1/cm]\t0.05\t0.5\tCurvature angle [rad]\t1.5\t-1\tShape x [cm]\t2\t0\t0.1\t"
            b"Shape y [cm]\t2\t0\t0\tShape z [cm]\t2\t0\t0.001") if sensor else b""
    t = time if time is not None else b"13:45:%02d.%06d" % (seq % 60, seq)
    return date + b"\t" + t + b"\t%d\t3\t" % seq + body + tail + end


def framed(payload: bytes) -> bytes:
    return len(payload).to_bytes(4, "big") + payload


GOOD = rec(7)
# one channel block of GOOD, to vary: "1\t2\t0\t0\t0\t0\t1530.5\t1540.25\t-1.5\t-2"
VARIANTS = [
    # valid records the general path reads, some of them off the one-pass reader's grammar
    GOOD, rec(8, end=b"\n"), rec(9, end=b""), rec(10, end=b"\r"), rec(11, end=b"\t\r\n"), rec(12, time=b"13:45:12"),
    rec(13, date=b"2024-01-31"), rec(14, date=b"not a day"), rec(15, time=b"13:45:12.1234567890123456"),
    rec(16, time=b"25:00:00"), rec(17, date=b""), rec(2**70), rec(-3),
    GOOD.replace(b"1530.5", b"+1530.5"), GOOD.replace(b"1530.5", b"01530.50"), GOOD.replace(b"1530.5", b"1.5305e3"),
    GOOD.replace(b"1530.5", b"1530.500000000000000001"), GOOD.replace(b"1530.5", b"nan"),
    GOOD.replace(b"1530.5", b"inf"), GOOD.replace(b"1530.5", b"-1530.5"), GOOD.replace(b"1530.5", b"0"),
    GOOD.replace(b"1530.5", b"0.0"), GOOD.replace(b"-1.5", b"-0"), GOOD.replace(b"-1.5", b"1e400"),
    GOOD.replace(b"1530.5", b"1530."), GOOD.replace(b"1530.5", b".5"), GOOD.replace(b"1530.5", b"000000000000001530.5"),
    GOOD.replace(b"2\t0\t0\t0\t0", b"2\t1\t0\t0\t0", 1), GOOD.replace(b"2\t0\t0\t0\t0", b"2\t-0\t0\t0\t0", 1),
    GOOD.replace(b"2\t0\t0\t0\t0", b"+2\t0\t0\t0\t0", 1), rec(18, sensor=True),
    rec(19, sensor=True).replace(b"Shape y [cm]", b"Shape y [mm]"),
    # damaged or of another layout
    GOOD.replace(b"2\t0\t0\t0\t0", b"2\t0.0\t0\t0\t0", 1), GOOD.replace(b"2\t0\t0\t0\t0", b"2.0\t0\t0\t0\t0", 1),
    GOOD.replace(b"1\t2\t0", b"4\t2\t0", 1), GOOD.replace(b"\t3\t1\t2", b"\t-3\t1\t2", 1),
    GOOD.replace(b"1530.5", b"15x30.5"), GOOD.replace(b"1530.5", b""), GOOD.replace(b"1530.5", b"1530\x005"),
    GOOD.replace(b"1530.5", b"1530\n5"), GOOD.replace(b"1530.5", b"1530\r5"), GOOD.replace(b"1530.5\t", b""),
    GOOD.replace(b"-2\r\n", b"-2\t5\r\n"), GOOD.replace(b"-2\r\n", b"-2\t\t\r\n"), GOOD.replace(b"\t-2\r\n", b"\r\n"),
    GOOD[:40], GOOD[:-9], GOOD.replace(b"13:45", b"13\x0045"), GOOD.replace(b"2024/01", b"2024\r01"),
    rec(20, sensor=True).replace(b"Curvature angle", b"Curvature angel"),
    rec(21, sensor=True).replace(b"Shape z [cm]\t2", b"Shape z [cm]\t3"),
    rec(22, sensor=True).replace(b"Shape x [cm]", b"Shape x [c\x00]"), b"", b"\t\t\t", b"a\tb\tc\td",
]


def same_result(a, b) -> None:
    """The same decoded record (every field, floats bit for bit) or the same error."""
    assert type(a) is type(b), (a, b)
    if isinstance(a, FramingError):
        assert (a.what, a.offset, a.expected) == (b.what, b.offset, b.expected)
        return
    fa, fb = a.frame, b.frame
    for name in ("wavelengths", "powers"):
        x, y = getattr(fa, name), getattr(fb, name)
        assert x.shape == y.shape and np.array_equal(x.view(np.int64), y.view(np.int64)), name
    assert np.array_equal(fa.status, fb.status) and fa.status.dtype == fb.status.dtype == np.uint8
    assert fa.sequence == fb.sequence and type(fa.sequence) is type(fb.sequence) is int
    assert np.float64(fa.timestamp).view(np.int64) == np.float64(fb.timestamp).view(np.int64)
    for name in ("channel_numbers", "grating_counts", "channel_status", "engineering"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert (a.date, a.time, a.extra_fields, a.layout, a.absent_sensors) == \
           (b.date, b.time, b.extra_fields, b.layout, b.absent_sensors)
    assert len(a.sensors) == len(b.sensors)
    for sa, sb in zip(a.sensors, b.sensors, strict=True):
        for name in ("curvature", "angle", "positions"):  # bit for bit: a NaN sent is a NaN read by both
            x, y = getattr(sa, name), getattr(sb, name)
            assert x.shape == y.shape and np.array_equal(x.view(np.int64), y.view(np.int64)), name


@pytest.fixture
def general_only(monkeypatch):
    """Turn the one-pass reader off: every record goes through the tokenizer (the decoder before issue 24)."""
    def off():
        monkeypatch.setattr(codec._Layout, "roles", property(lambda self: None))
    return off


def decode(payloads: list[bytes], layouts: list) -> list:
    data = b"".join(payloads)
    ends = np.cumsum([len(p) for p in payloads])
    return codec.decode_many(data, ends - [len(p) for p in payloads], ends, layouts=layouts)


def learned(*payloads: bytes) -> list:
    layouts: list = []
    decode(list(payloads), layouts)
    return layouts


# ------------------------------------------------------------------------------------------- payloads


def test_one_pass_reader_reads_the_known_layout_and_nothing_else():
    lay = learned(GOOD)[0]
    role, want = lay.roles
    assert list(role[:4]) == [scan.ROLE_ANY, scan.ROLE_ANY, scan.ROLE_INT, scan.ROLE_FIXED]
    payloads = [rec(k) for k in range(5)] + [GOOD.replace(b"1530.5", b"1.5305e3"), GOOD[:-9],
                                              GOOD.replace(b"1530.5", b"1530\x005")]
    data = b"".join(payloads)
    ends = np.cumsum([len(p) for p in payloads])
    ok, values, stamp, dtb, lam, *_ = scan.parse_layout(
        np.frombuffer(data, np.uint8), ends - [len(p) for p in payloads], ends, role, want, lay.wl, lay.pw,
        lay.status, lay.wl.shape[0], 1, 4, 8)
    assert ok.tolist() == [True] * 5 + [False] * 3
    assert values[:5, 2].tolist() == [0, 1, 2, 3, 4]
    assert lam[1, :, 0].tolist() == [1530.5, 1540.25]
    assert data[dtb[2, 0] : dtb[2, 1]] == b"2024/01/31" and data[dtb[2, 2] : dtb[2, 3]] == b"13:45:02.000002"
    assert stamp[3] == pytest.approx(1706659200 + 13 * 3600 + 45 * 60 + 3.000003, abs=1e-6)  # 2024-01-31 UTC


@pytest.mark.parametrize("sensor", [False, True])
def test_one_pass_reader_decodes_exactly_what_the_general_path_decodes(general_only, sensor):
    layouts = learned(rec(0, sensor=sensor))
    assert layouts[0].roles is not None
    fast = decode(VARIANTS, [*layouts])
    general_only()
    slow = decode(VARIANTS, [*layouts])
    for k, (a, b) in enumerate(zip(fast, slow, strict=True)):
        try:
            same_result(a, b)
        except AssertionError as exc:
            raise AssertionError(f"variant {k}: {VARIANTS[k][:80]!r}") from exc
    # the variants hold both: records read, damaged ones refused
    assert sum(isinstance(r, FramingError) for r in fast) >= 15
    assert sum(not isinstance(r, FramingError) for r in fast) >= 25


def ragged(seq: int) -> bytes:  # G = 2 and 3: the short channel NaN-padded
    return rec(seq, body=b"1\t2\t0\t0\t0\t0\t1530.5\t1540.25\t-1\t-2\t2\t3\t0\t0\t0\t0\t1531\t1541\t1551\t-1\t-2\t-3\t"
                         b"3\t2\t0\t0\t0\t1\t1532\t1542\t-1\t-2")


LAYOUTS = {  # another layout's record (sample number seq) and how to decode it
    "no channel": (lambda seq: b"2024/01/31\t13:45:12\t%d\t0\r\n" % seq, {}),
    "ragged, channel error": (ragged, {}),
    "engineering values": (lambda seq: rec(seq)[:-2] + b"\t3\t1.5\t-2\t30\r\n", {}),
    "one channel for all cores": (
        lambda seq: rec(seq, body=b"1\t6\t0\t0\t0\t0\t1530\t1531\t1532\t1533\t1534\t0\t-1\t-1\t-1\t-1\t-1\t-1")
        .replace(b"\t3\t1\t6", b"\t1\t1\t6"), {"channels_as": "single", "n_cores": 3}),
}


@pytest.mark.parametrize("name", LAYOUTS)
def test_one_pass_reader_matches_the_general_path_on_other_layouts(general_only, name):
    make, kw = LAYOUTS[name]
    layouts: list = []
    base = [make(k) for k in range(6)]
    damaged = [base[1][:-7], base[2].replace(b"\t", b"\t\t", 3), base[3].replace(b"2024", b"2\x0024"), base[4] + b"x",
               base[5].replace(b"\t-1", b"\t-1e0", 1)]
    payloads = [*base, *damaged, GOOD]
    data = b"".join(payloads)
    ends = np.cumsum([len(p) for p in payloads])
    starts = ends - [len(p) for p in payloads]
    codec.decode_many(data, starts[:1], ends[:1], layouts=layouts, **kw)
    lay = layouts[0]
    ok, *_ = scan.parse_layout(np.frombuffer(data, np.uint8), starts, ends, *lay.roles, lay.wl, lay.pw, lay.status,
                               lay.single or lay.wl.shape[0], 1, 4, 8)
    # the one-pass reader reads the layout's records, not the damaged ones, nor a number off its path (-1e0)
    assert ok[:6].all() and not ok[6:10].any() and ok[10] == (b"\t-1" not in base[5]) and not ok[11]
    fast = codec.decode_many(data, starts, ends, layouts=[*layouts], **kw)
    general_only()
    slow = codec.decode_many(data, starts, ends, layouts=[*layouts], **kw)
    for a, b in zip(fast, slow, strict=True):
        same_result(a, b)
    assert not any(isinstance(r, FramingError) for r in fast[:6])


_ALPHABET = b"0123456789.+-eE\t\x00\r\nx [" + b"nai"


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, len(_ALPHABET) - 1), st.sampled_from("rid")),
                min_size=1, max_size=4), st.booleans())
def test_one_pass_reader_matches_the_general_path_on_damaged_records(general_only, edits, sensor):
    payload = bytearray(rec(5, sensor=sensor))
    for at, ch, how in edits:  # replace, insert or delete bytes
        i = at % (len(payload) + 1)
        if how == "r" and i < len(payload):
            payload[i] = _ALPHABET[ch]
        elif how == "i":
            payload[i:i] = _ALPHABET[ch : ch + 1]
        else:
            del payload[i : i + 1]
    payloads = [rec(1, sensor=sensor), bytes(payload), rec(2, sensor=sensor)]
    layouts = learned(rec(0, sensor=sensor))
    fast = decode(payloads, [*layouts])
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(codec._Layout, "roles", property(lambda self: None))
        slow = decode(payloads, [*layouts])
    for a, b in zip(fast, slow, strict=True):
        same_result(a, b)


# ------------------------------------------------------------------------------------------- the stream


def short_stream() -> bytes:
    """Records of one layout with a sensor-block record, garbage, a damaged record, a bad prefix, an odd layout and
    numbers off the one-pass reader's grammar."""
    odd = (rec(8)[:-2] + b"\t4\t2\t0\t0\t0\t0\t1533.5\t1543.25\t-1.5\t-2\r\n").replace(b"\t8\t3\t", b"\t8\t4\t")
    parts = [framed(rec(k)) for k in range(4)]
    parts += [framed(rec(4, sensor=True)), b"junk\x00\x00", framed(rec(5)), framed(GOOD[:30] + b"\x00" + GOOD[31:]),
              framed(rec(6).replace(b"1530.5", b"1.5305e3")), b"\x00\x00\x00\x03abc", framed(rec(7)),
              framed(odd), framed(rec(9)), framed(rec(10, end=b""))]
    return b"".join(parts)


def fed(stream: bytes, cut: int, how: str) -> tuple:
    dec = illumisense.StreamDecoder()
    out = getattr(dec, how)(stream[:cut]) + getattr(dec, how)(stream[cut:]) + dec.finish()
    frames = [g for f in out for g in (f if isinstance(f, Frame) and f.batch_shape else (f,))]
    if how == "feed_records":
        frames = [r.frame for r in frames]
    rows = [(f.sequence, f.timestamp, f.wavelengths.tobytes(), f.powers.tobytes(), f.status.tobytes(),
             f.vendor is not None) for f in frames]
    return rows, (dec.records, dec.framing_errors, dec.bytes_discarded, dec.odd_records, dec.layout_changes,
                  dec.sequence.as_dict(), dec.sensor_blocks_absent, dec.pending, dec.in_sync,
                  dec.last_error and (dec.last_error.what, dec.last_error.offset))


def test_stream_split_at_every_byte_gives_what_the_general_path_gives(general_only):
    stream = short_stream()
    cuts = range(len(stream) + 1)
    fast = {how: [fed(stream, c, how) for c in cuts] for how in ("feed_batch", "feed_records")}
    general_only()
    slow = [fed(stream, c, "feed_batch") for c in cuts]
    whole = slow[0]
    assert [r[0] for r in whole[0]] == [0, 1, 2, 3, 4, 5, 6, 7, 9, 10]  # 8 is of another layout: odd
    assert whole[1][1] >= 2 and whole[1][3] == 1
    for c in cuts:
        assert fast["feed_batch"][c] == slow[c] == whole, f"cut at byte {c}"
        assert fast["feed_records"][c] == whole, f"cut at byte {c}"
