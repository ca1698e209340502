"""Wire-protocol codecs (twin.io) of FiSpec and Hyperion: byte fixtures written out by hand from
docs/protocols.md, round trips of random frames at each protocol's quantisation, and fuzzing of every decoder
(the ILLumiSense codec has its own file, tests/test_illumisense.py).

Tolerances: ILLumiSense sends wavelengths with 4 decimals, so a round trip holds them to the decimal rounding
of the value (exactly ``float(f"{w:.4f}")``, hence within 5e-5 nm); FiSpec carries integers of 1e-4 nm
(exactly ``round(w·1e4)/1e4``); Hyperion carries float64 (exact). Timestamps: ILLumiSense writes microseconds
(≤ 0.5 µs plus float64 rounding at 4e9 s, ≈ 0.5 µs: 2 µs held); Hyperion writes nanoseconds (1 µs held, the
float64 resolution of an epoch time being ≈ 0.24 µs).

Fuzzing asserts that a decoder raises nothing but its documented FramingError, and — through a plain
reference reading of the spec written here, independent of the codec (``reference_fispec``,
``reference_hyperion_peaks``, ``reference_hyperion_stream``) — that it refuses exactly what the reference refuses
and that whatever it does decode is what the bytes say: a corrupted record may decode only to the record the
corrupted bytes spell.
"""

from __future__ import annotations

import math
import re
import struct
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from twin.frames import Frame, PeakStatus
from twin.io import fispec, hyperion
from twin.io.errors import FramingError, OversizeFrameError, TruncatedFrameError
from twin.io.sequence import SequenceCounter

FUZZ = settings(max_examples=2000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
ROUND = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
MISSING, CHANNEL_ERROR, INVALID = (
    int(PeakStatus.MISSING),
    int(PeakStatus.CHANNEL_ERROR),
    int(PeakStatus.INVALID_VALUE),
)

# --------------------------------------------------------------------------------------------------- fixtures

# docs/protocols.md §3: the #GetPeaks request
HYPERION_GETPEAKS = bytes.fromhex("00 00 09 00 00 00 00 00 23 47 65 74 50 65 61 6b 73")

# peak content: 2 channels with 2 and 1 peaks, serial number 5, t = 100.25 s, version 1
HYPERION_PEAKS = bytes.fromhex(
    "1c 00 01 00"  # header length 28 = 24 + 2·2, version 1
    "00 00 00 00"  # reserved
    "05 00 00 00 00 00 00 00"  # serial number 5
    "64 00 00 00"  # 100 s
    "80 b2 e6 0e"  # 250 000 000 ns
    "02 00 01 00"  # peak counts 2, 1
    "00 00 00 00 00 ea 97 40"  # 1530.5
    "00 00 00 00 00 25 98 40"  # 1545.25
    "00 00 00 00 80 38 98 40"  # 1550.125
)



def reference_hyperion_peaks(content: bytes) -> tuple[int, int, int, list[list[float]]]:
    """Plain reading of docs/protocols.md §3 peak content; ValueError (or struct.error) when inconsistent."""
    hl, _, _, serial, sec, ns = struct.unpack_from("<HHIQII", content, 0)
    n_ch = (hl - 24) // 2
    if hl < 24 or (hl - 24) % 2 or hl > len(content):
        raise ValueError("header length")
    counts = struct.unpack_from(f"<{n_ch}h", content, 24)
    if any(c < 0 for c in counts) or len(content) - hl != 8 * sum(counts):
        raise ValueError("counts")
    values = struct.unpack_from(f"<{sum(counts)}d", content, hl)
    out, i = [], 0
    for c in counts:
        out.append(list(values[i : i + c]))
        i += c
    return serial, sec, ns, out



# ==================================================================================================== FiSpec


def test_fispec_reply_fixtures():
    assert fispec.encode_identity() == b"FiSpec FBG X150"
    assert fispec.decode_identity(b"FiSpec FBG X100\r\n") == "FiSpec FBG X100"
    params = fispec.parameter_items(pixels=2048, channels=18, integration_time_us=50000)
    assert (
        fispec.encode_parameters(params)
        == b"Pixel_2048#Kanalanzahl_18#tInt_50000#Mittelungen_1#OBBerechnen_0"
    )
    assert fispec.decode_parameters(b"#Pixel_512#Kanalanzahl_3#tInt_1000_us#Name#OBBerechnen_1") == {
        "Pixel": 512,
        "Kanalanzahl": 3,
        "tInt": 1000,
        "OBBerechnen": 1,
    }
    assert fispec.encode_spectrum([1, 258, 65535]) == b"\x01\x00\x02\x01\xff\xffEnde"
    np.testing.assert_array_equal(fispec.decode_spectrum(b"\x01\x00\x02\x01\xff\xffEnde", 3), [1, 258, 65535])
    wll = bytes.fromhex("c0 e1 e4 00 a9 e3 e4 00") + b"Ende"
    assert fispec.encode_pixel_wavelengths([1500.0, 1500.0489]) == wll
    np.testing.assert_array_equal(fispec.decode_pixel_wavelengths(wll, 2), [1500.0, 1500.0489])
    peaks = (
        bytes.fromhex(
            "72 7a e9 00 e8 03 00 00"  # 1530.1234 nm, amplitude 1000
            "00 00 00 00 00 00 00 00"  # a missing peak
            "0e 99 ec 00 fb ff ff ff"  # 1550.5678 nm, amplitude -5
            "29 09 00 00 00 00 00 00"
        )  # 23.45 °C, int16 0, 4 reserved
        + b"Ende"
    )
    assert len(peaks) == 8 * 3 + 12
    assert (
        fispec.encode_peaks([1530.1234, np.nan, 1550.5678], [1000, 7, -5], device_temperature=23.45) == peaks
    )
    r = fispec.decode_peaks(peaks, 3)
    np.testing.assert_array_equal(r.wavelengths, [1530.1234, np.nan, 1550.5678])
    np.testing.assert_array_equal(r.second, [1000, np.nan, -5])
    assert r.device_temperature == 23.45
    on = fispec.decode_peaks(peaks, 3, onboard=True)
    np.testing.assert_allclose(on.first, [1530.1234, 0.0, 1550.5678])
    np.testing.assert_allclose(on.second, [10.0, 0.0, -0.05])
    f = fispec.peaks_to_frame(r, sequence=3)
    assert f.wavelengths.shape == (3, 1) and f.status[1, 0] == MISSING and f.sequence == 3


@pytest.mark.parametrize(
    ("decoder", "reply"),
    [
        (lambda b: fispec.decode_spectrum(b, 3), b"\x01\x00\x02\x01\xff\xffEnde"),
        (lambda b: fispec.decode_pixel_wavelengths(b, 2), bytes(8) + b"Ende"),
        (lambda b: fispec.decode_peaks(b, 2), bytes(16 + 8) + b"Ende"),
    ],
)
def test_fispec_binary_replies_must_have_the_exact_length(decoder, reply):
    decoder(reply)
    for bad in (reply[:-1], reply + b"\x00", b"\x00" + reply[:-1], reply[:-4] + b"ende", reply[1:]):
        with pytest.raises(FramingError):
            decoder(bad)


def test_fispec_command_parser_reads_the_clients_start_up_sequence():
    # what myfbgcommunication 2.0.2 sends from init() through its first read, with a stray CR LF and a NUL
    stream = (
        b"?>p?>a>LED,1>s>s>\r\niz,50000>a>WLL>Ke,0,15085000,15115000>Ke,1,15135000,15165000>KA,2>m,1>"
        b"OBsTyp,0,0>OBsTyp,1,0>OBN>OBsaT0,2100>\x00PeM,0>OBB,1>p?>P>P>"
    )
    parser = fispec.CommandParser()
    cmds = [c for i in range(0, len(stream), 7) for c in parser.feed(stream[i : i + 7])]
    assert [c.name for c in cmds] == [
        "?",
        "p?",
        "a",
        "LED",
        "s",
        "s",
        "iz",
        "a",
        "WLL",
        "Ke",
        "Ke",
        "KA",
        "m",
        "OBsTyp",
        "OBsTyp",
        "OBN",
        "OBsaT0",
        "PeM",
        "OBB",
        "p?",
        "P",
        "P",
    ]
    assert cmds[9].args == (0, 15085000, 15115000) and cmds[16].args == (2100,)
    replying = [c.name for c in cmds if not c.silent]
    assert replying == ["?", "p?", "s", "s", "WLL", "p?", "P", "P"]
    assert parser.errors == 0
    assert stream[cmds[9].offset :].startswith(b"Ke,0")
    assert fispec.encode_command("Ke", 0, 15085000, 15115000) == b"Ke,0,15085000,15115000>"
    assert fispec.SILENT_COMMANDS >= {
        "a",
        "LED",
        "iz",
        "Ke",
        "KA",
        "m",
        "OBsTyp",
        "OBN",
        "OBsaT0",
        "PeM",
        "OBB",
    }


def test_fispec_command_parser_drops_and_counts_garbage():
    parser = fispec.CommandParser(max_length=32)
    cmds = parser.feed(b"hello>KA,x>Ke,1,2>\xff\xfeP>" + b"z" * 40)
    assert cmds == [] and parser.errors == 5
    cmds = parser.feed(b"y>P>KA,18>")
    assert [c.name for c in cmds] == ["P", "KA"] and parser.errors == 6


def test_synthetic_spectrum_is_read_back_by_the_clients_peak_detection():
    from scipy.signal import find_peaks

    wll = fispec.default_pixel_wavelengths()
    assert wll.size == 2048 and wll[0] == 1500.0 and wll[-1] == 1600.0
    wll = fispec.decode_pixel_wavelengths(fispec.encode_pixel_wavelengths(wll), 2048)
    peaks = 1510.0 + 5.0 * np.arange(18) + 0.01234
    rng = np.random.default_rng(7)
    # exactly the client's init(): average 10 spectra, pixels 0-2 := pixel 3, minus pixel 0, drop first peak
    spectra = [
        fispec.decode_spectrum(
            fispec.encode_spectrum(fispec.synthetic_spectrum(peaks, wll, noise_counts=5.0, rng=rng)), 2048
        ).astype(float)
        for _ in range(10)
    ]
    spectra = [np.concatenate([[s[3]] * 3, s[3:]]) for s in spectra]
    proc = np.average(np.array(spectra), axis=0)
    proc -= proc[0]
    found, _ = find_peaks(proc, height=10, distance=50, prominence=100)
    found = found[1:]
    assert found.size == 18
    pixel_nm = wll[1] - wll[0]
    np.testing.assert_allclose(wll[found], peaks, atol=pixel_nm)  # the client sees pixel wavelengths
    with pytest.raises(ValueError, match="50 pixels"):
        fispec.synthetic_spectrum([1510.0, 1511.0], wll)
    with pytest.raises(ValueError, match="50 pixels"):
        fispec.synthetic_spectrum([1501.0], wll)  # too close to the leading reference peak


@ROUND
@given(
    hnp.arrays(
        np.float64, st.integers(0, 40), elements=st.one_of(st.floats(1000.0, 2000.0), st.just(np.nan))
    ),
    st.floats(-300.0, 300.0),
)
def test_fispec_peaks_round_trip_at_1e_4_nm(w, temp):
    r = fispec.decode_peaks(fispec.encode_peaks(w, np.full(w.shape, 123.0), device_temperature=temp), w.size)
    np.testing.assert_array_equal(r.wavelengths, np.round(w * 1e4) / 1e4)
    assert np.all(np.abs(r.wavelengths[~np.isnan(w)] - w[~np.isnan(w)]) <= 5e-5 + 1e-9)
    assert r.device_temperature == round(temp * 100) / 100


_PRINTABLE = re.compile(rb"[\x20-\x7e]*")


def reference_fispec(kind: str, reply: bytes, n: int):
    """Plain reading of docs/protocols.md §2.2, independent of the codec: what a reply says, or None when it is not
    a well-formed reply of that kind.

    Binary replies have exactly their length and end in ``Ende``. ``P>``: a wavelength of 0 is a missing peak
    (§2.3), and so is a negative one (no wavelength is negative), its amplitude then missing too. ``p?>``:
    printable ASCII, ``#``-separated items; an item with a ``_`` is ``Name_<int>[_…]``, the integer after the
    first ``_`` (an optional minus, decimal digits); ``Pixel`` must be among them. ``?>``: printable ASCII
    starting with ``FiSpec`` once the trailing CR, LF, NUL and spaces are removed.
    """
    size = {"s": 2 * n + 4, "WLL": 4 * n + 4, "P": 8 * n + 12, "OBB1": 8 * n + 12}.get(kind)
    if size is not None and (len(reply) != size or reply[-4:] != b"Ende"):
        return None
    if kind == "s":
        return [float(v) for v in struct.unpack(f"<{n}H", reply[: 2 * n])]
    if kind == "WLL":
        return [v / 1e4 for v in struct.unpack(f"<{n}I", reply[: 4 * n])]
    if kind in ("P", "OBB1"):
        values = struct.unpack(f"<{2 * n}i", reply[: 8 * n])
        temperature = struct.unpack_from("<h", reply, 8 * n)[0] / 100
        pairs = list(zip(values[0::2], values[1::2], strict=True))
        if kind == "OBB1":
            return [v / 1e4 for v, _ in pairs], [a / 100 for _, a in pairs], temperature
        return ([v / 1e4 if v > 0 else math.nan for v, _ in pairs],
                [float(a) if v > 0 else math.nan for v, a in pairs], temperature)
    if kind == "params":
        if not _PRINTABLE.fullmatch(reply):
            return None
        out = {}
        for item in reply.decode("ascii").split("#"):
            if "_" in item:
                m = re.fullmatch(r"([^_]*)_(-?[0-9]+)(?:_.*)?", item, re.DOTALL)
                if m is None:
                    return None
                out[m.group(1)] = int(m.group(2))
        return out if "Pixel" in out else None
    if kind == "identity":
        text = reply.rstrip(b"\r\n\x00 ")
        return text.decode("ascii") if text.startswith(b"FiSpec") and _PRINTABLE.fullmatch(text) else None
    raise AssertionError(kind)


def _fispec_decoded(kind: str, reply: bytes, n: int):
    """The codec's reading in the reference's form, or None when it raised its FramingError."""
    try:
        if kind == "s":
            return [float(v) for v in fispec.decode_spectrum(reply, n)]
        if kind == "WLL":
            return [float(v) for v in fispec.decode_pixel_wavelengths(reply, n)]
        if kind in ("P", "OBB1"):
            r = fispec.decode_peaks(reply, n, onboard=kind == "OBB1")
            return [float(v) for v in r.first], [float(v) for v in r.second], r.device_temperature
        if kind == "params":
            return fispec.decode_parameters(reply)
        return fispec.decode_identity(reply)
    except FramingError:
        return None


def _same(a, b) -> bool:
    """Equal, NaN equal to NaN (nested lists and tuples of floats, dicts, strings)."""
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    return a == b


_PARAM_TEXT = st.text(alphabet="Pixel_Kanalanzahl#tInt_0123456789-x²\x00 ", max_size=60)


@FUZZ
@given(st.binary(max_size=300), st.integers(0, 40), _PARAM_TEXT, st.integers(0, 7))
def test_fuzz_fispec_reply_decoders(data, n, text, cut):
    """Every decoder on random bytes, on well-formed replies with random content (random body of the exact
    length, then ``Ende``) and those one byte short or long, and on random item text: it raises nothing but its
    FramingError, refuses exactly what the reference refuses, and decodes exactly what the reference reads."""
    replies = {"params": [data, text.encode("utf-8"), b"Pixel_" + text.encode("utf-8")],
               "identity": [data, b"FiSpec" + text.encode("utf-8"), b"FiSpec" + data[:cut] + b"\r\n"]}
    for kind, width in (("s", 2), ("WLL", 4), ("P", 8), ("OBB1", 8)):
        body = (data * (1 + width * n // max(len(data), 1)))[: width * n + (8 if kind in ("P", "OBB1") else 0)]
        body = body.ljust(width * n + (8 if kind in ("P", "OBB1") else 0), b"\x00")
        well_formed = body + b"Ende"
        replies[kind] = [data, well_formed, well_formed[:-1], well_formed + b"\x00", well_formed[1:] + b"E"]
    for kind, candidates in replies.items():
        for reply in candidates:
            ours, ref = _fispec_decoded(kind, reply, n), reference_fispec(kind, reply, n)
            assert _same(ours, ref), (kind, reply, ours, ref)


@FUZZ
@given(st.binary(max_size=300), st.lists(st.integers(1, 50), max_size=10))
def test_fuzz_fispec_command_parser(garbage, cuts):
    valid = b"?>Ke,0,15085000,15115000>KA,1>OBB,0>P>"
    stream = garbage + b">" + valid
    parser = fispec.CommandParser()
    cmds, pos = [], 0
    for c in [*cuts, len(stream)]:
        cmds += parser.feed(stream[pos : pos + c])
        pos += c
    for c in cmds:
        assert len(c.args) == fispec.COMMAND_ARITY[c.name]
    assert [c.name for c in cmds[-5:]] == ["?", "Ke", "KA", "OBB", "P"]


# ================================================================================================== Hyperion


def test_hyperion_getpeaks_request_bytes():
    assert hyperion.encode_request("#GetPeaks") == HYPERION_GETPEAKS
    assert hyperion.decode_request(HYPERION_GETPEAKS) == hyperion.Request("#GetPeaks")
    req = bytes.fromhex("00 00 12 00 04 00 00 00") + b"#SetLaserScanSpeed" + b"1000"
    assert hyperion.encode_request("#SetLaserScanSpeed", "1000") == req
    assert hyperion.decode_request(req) == hyperion.Request("#SetLaserScanSpeed", "1000")


def test_hyperion_peak_content_fixture():
    f = hyperion.decode_peaks(HYPERION_PEAKS)
    np.testing.assert_array_equal(f.wavelengths, [[1530.5, 1550.125], [1545.25, np.nan]])
    np.testing.assert_array_equal(f.status, [[0, 0], [0, MISSING]])
    assert f.sequence == 5 and f.timestamp == 100.25
    assert hyperion.encode_peaks(f) == HYPERION_PEAKS
    assert hyperion.decode_peaks(HYPERION_PEAKS, n_gratings=3).wavelengths.shape == (3, 2)
    with pytest.raises(FramingError, match="more than n_gratings"):
        hyperion.decode_peaks(HYPERION_PEAKS, n_gratings=1)
    resp = bytes.fromhex("00 00 00 00") + struct.pack("<I", len(HYPERION_PEAKS)) + HYPERION_PEAKS
    assert hyperion.encode_stream_frame(f) == resp
    assert hyperion.decode_response(resp) == hyperion.Response(0, 0, "", HYPERION_PEAKS)


def test_hyperion_start_up_replies():
    state = hyperion.InstrumentState(
        channel_count=4,
        max_peaks_per_channel=40,
        laser_scan_speed=1000,
        available_scan_speeds=(100, 1000),
        serial_number="HYP123",
    )
    ok = bytes.fromhex("00 00 00 00")

    def ask(cmd, arg=""):
        return hyperion.respond(hyperion.Request(cmd, arg), state)

    assert ask("#GetDutChannelCount") == ok + bytes.fromhex("04 00 00 00 04 00 00 00")
    assert ask("#GetMaximumPeakCountPerDutChannel") == ok + bytes.fromhex("04 00 00 00 28 00 00 00")
    assert ask("#isready") == ok + bytes.fromhex("01 00 00 00 01")
    assert ask("#GetSerialNumber") == ok + bytes.fromhex("06 00 00 00") + b"HYP123"
    assert ask("#GetLaserScanSpeed") == ok + bytes.fromhex("04 00 00 00 e8 03 00 00")
    assert ask("#GetAvailableLaserScanSpeeds") == ok + bytes.fromhex("08 00 00 00 64 00 00 00 e8 03 00 00")
    for cmd in ("#GetFirmwareVersion", "#GetFPGAVersion", "#GetInstrumentName"):
        assert hyperion.decode_ascii(hyperion.decode_response(ask(cmd)).content)
    r = hyperion.decode_response(ask("#SetLaserScanSpeed", "100"))
    assert r.ok and state.laser_scan_speed == 100
    assert not hyperion.decode_response(ask("#SetLaserScanSpeed", "7")).ok and state.laser_scan_speed == 100
    bad = hyperion.decode_response(ask("#NoSuchCommand"))
    assert bad.status == 1 and "NoSuchCommand" in bad.message
    assert hyperion.decode_response(ask("#GetPeaks")).status == 3
    peaks = hyperion.respond(
        hyperion.Request("#GetPeaks"), state, frame=hyperion.decode_peaks(HYPERION_PEAKS)
    )
    assert hyperion.decode_response(peaks).content == HYPERION_PEAKS
    assert hyperion.decode_u32(bytes.fromhex("04 00 00 00")) == 4
    assert hyperion.decode_u8(b"\x01") == 1
    np.testing.assert_array_equal(
        hyperion.decode_i32_array(bytes.fromhex("64 00 00 00 e8 03 00 00")), [100, 1000]
    )
    for dec, content in (
        (hyperion.decode_u32, b"\x04\x00\x00"),
        (hyperion.decode_u8, b""),
        (hyperion.decode_i32_array, b"\x00" * 5),
        (hyperion.decode_ascii, b"\xff"),
    ):
        with pytest.raises(FramingError):
            dec(content)


def test_hyperion_stream_any_split_and_resync_after_an_oversize_header():
    f = hyperion.decode_peaks(HYPERION_PEAKS)
    stream = hyperion.encode_stream_frame(f) + hyperion.encode_stream_frame(f, serial_number=8)
    for cut in range(len(stream) + 1):
        dec = hyperion.PeakStreamDecoder()
        frames = dec.feed(stream[:cut]) + dec.feed(stream[cut:])
        assert [x.sequence for x in frames] == [5, 8]
    dec = hyperion.PeakStreamDecoder(max_content=1000)
    good = hyperion.encode_stream_frame(f)
    assert len(dec.feed(good + b"\x00\x00\x00\x00\xff\xff\xff\x7f")) == 1  # delivered; then refused unbuffered
    assert not dec.in_sync and dec.framing_errors == 1 and isinstance(dec.last_error, OversizeFrameError)
    assert dec.pending < 32
    assert len(dec.feed(good)) == 1 and dec.in_sync and dec.framing_errors == 1  # resynchronised
    reqs = hyperion.ResponseDecoder(max_content=1000)  # the command port's decoder: no resync, reconnect
    assert len(reqs.feed(good + b"\x00\x00\x00\x00\xff\xff\xff\x7f")) == 1
    with pytest.raises(OversizeFrameError):
        reqs.feed(b"")
    with pytest.raises(FramingError, match="out of sync"):
        reqs.feed(good)
    reqs.reset()
    assert len(reqs.feed(good)) == 1
    reqs = hyperion.RequestDecoder()
    assert (
        reqs.feed(HYPERION_GETPEAKS[:5]) == []
        and reqs.feed(HYPERION_GETPEAKS[5:] + HYPERION_GETPEAKS) == [hyperion.Request("#GetPeaks")] * 2
    )
    with pytest.raises(FramingError, match="reserved"):
        reqs.feed(b"\x00\x01\x09\x00\x00\x00\x00\x00")


@st.composite
def trailing_nan_frames(draw) -> Frame:
    g, c = draw(st.integers(0, 12)), draw(st.integers(0, 6))
    w = draw(hnp.arrays(np.float64, (g, c), elements=st.floats(1000.0, 2000.0)))
    for k in range(c):  # the instrument reports found peaks only: gaps can only be trailing after decoding
        w[draw(st.integers(0, g)) :, k] = np.nan
    return Frame(w, timestamp=draw(st.floats(0.0, 4e9)), sequence=draw(st.integers(0, 2**63)))


@ROUND
@given(trailing_nan_frames())
def test_hyperion_round_trip_is_exact(frame):
    g = frame.wavelengths.shape[0]
    (got,) = hyperion.PeakStreamDecoder(n_gratings=g).feed(hyperion.encode_stream_frame(frame))
    np.testing.assert_array_equal(got.wavelengths, frame.wavelengths)
    np.testing.assert_array_equal(got.status, np.where(np.isnan(frame.wavelengths), MISSING, 0))
    assert got.sequence == min(frame.sequence, 2**63 - 1)  # a u64 beyond int64 is clamped (twin.io.sequence)
    assert abs(got.timestamp - frame.timestamp) <= 1e-6


def test_hyperion_gaps_inside_a_channel_come_back_compacted():
    f = Frame(np.array([[1530.0], [np.nan], [1550.0]]))
    np.testing.assert_array_equal(
        hyperion.decode_peaks(hyperion.encode_peaks(f), n_gratings=3).wavelengths[:, 0],
        [1530.0, 1550.0, np.nan],
    )


@FUZZ
@given(
    st.one_of(
        st.binary(max_size=200),
        st.builds(
            lambda h, rest: h + rest,
            st.sampled_from([HYPERION_PEAKS[:24], HYPERION_PEAKS[:28]]),
            st.binary(max_size=80),
        ),
    )
)
def test_fuzz_hyperion_peak_content(data):
    try:
        f = hyperion.decode_peaks(data)
    except FramingError:
        try:
            _, _, _, chans = reference_hyperion_peaks(data)
        except (ValueError, struct.error):
            return  # the reference reading refuses it too
        # consistent framing: refused only for a value that is not a wavelength (checked whole)
        assert not all(plausible(v) for vals in chans for v in vals)
        return
    serial, _, _, chans = reference_hyperion_peaks(data)
    assert f.sequence == min(serial, 2**63 - 1) and f.wavelengths.shape[1] == len(chans)
    for k, vals in enumerate(chans):
        assert all(plausible(v) for v in vals)
        np.testing.assert_array_equal(f.wavelengths[: len(vals), k], vals)
        assert np.all(np.isnan(f.wavelengths[len(vals) :, k]))


def plausible(v: float) -> bool:
    """A wavelength a Hyperion frame may carry (docs/protocols.md §3 decisions: 200–3000 nm)."""
    return math.isfinite(v) and 200.0 <= v <= 3000.0


def test_hyperion_truncated_messages_are_framing_errors():
    resp = hyperion.encode_response(HYPERION_PEAKS, "msg")
    for cut in range(len(HYPERION_PEAKS)):
        with pytest.raises(FramingError):
            hyperion.decode_peaks(HYPERION_PEAKS[:cut])
    for cut in range(len(resp)):
        with pytest.raises(FramingError):
            hyperion.decode_response(resp[:cut])
    for cut in range(len(HYPERION_GETPEAKS)):
        with pytest.raises(FramingError):
            hyperion.decode_request(HYPERION_GETPEAKS[:cut])
    with pytest.raises(OversizeFrameError):
        hyperion.decode_response(resp + b"\x00")


@FUZZ
@given(st.integers(0, len(HYPERION_PEAKS) - 1), st.integers(0, 255), st.binary(max_size=40))
def test_fuzz_hyperion_corrupted_peaks_and_requests(i, b, request_garbage):
    bad = HYPERION_PEAKS[:i] + bytes([b]) + HYPERION_PEAKS[i + 1 :]
    try:
        f = hyperion.decode_peaks(bad)
    except FramingError:
        # a wavelength byte cannot break the framing (only the header or the counts can), but it can make the
        # value implausible, and then the whole frame is refused
        assert i < 28 or not all(plausible(v) for c in reference_hyperion_peaks(bad)[3] for v in c)
    else:
        serial, _, _, chans = reference_hyperion_peaks(bad)
        reported = [int(np.sum(~np.isnan(f.wavelengths[:, k]))) for k in range(f.wavelengths.shape[1])]
        assert f.sequence == min(serial, 2**63 - 1) and reported == [len(c) for c in chans]
        assert not np.any(f.status & INVALID)
    req = (
        HYPERION_GETPEAKS[: i % len(HYPERION_GETPEAKS)]
        + bytes([b])
        + HYPERION_GETPEAKS[i % len(HYPERION_GETPEAKS) + 1 :]
    )
    for data in (req, request_garbage):
        try:
            r = hyperion.decode_request(data)
        except FramingError:
            continue
        assert hyperion.encode_request(r.command, r.argument, options=r.options) == data


def reference_hyperion_stream(data: bytes, max_content: int = 4096, max_channels: int = 128):
    """Plain reading of a peak stream (docs/protocols.md §3.1, §3.2, §3.4): (frames, failed). A frame is a response
    (``<BBHI`` header, ASCII message, content) with status 0 whose content is peak content; each frame is
    (serial, seconds, nanoseconds, peaks per channel). The stream fails at the first response that is not one
    (a content length over ``max_content``, a non-ASCII message, a non-zero status, inconsistent peak content,
    nanoseconds ≥ 1e9, a peak header's reserved u32 that is not 0, a peak that is not a wavelength in
    200–3000 nm); an incomplete last response is pending."""
    frames, pos = [], 0
    while len(data) - pos >= 8:
        status, _, n_msg, n_content = struct.unpack_from("<BBHI", data, pos)
        if n_content > max_content:
            return frames, True
        end = pos + 8 + n_msg + n_content
        if len(data) < end:
            return frames, False
        message, content = data[pos + 8: pos + 8 + n_msg], data[pos + 8 + n_msg: end]
        if any(b > 0x7F for b in message) or status != 0:
            return frames, True
        try:
            serial, sec, ns, channels = reference_hyperion_peaks(content)
        except (ValueError, struct.error):
            return frames, True
        n_channels = (struct.unpack_from("<H", content)[0] - 24) // 2
        reserved = struct.unpack_from("<I", content, 4)[0]
        if n_channels > max_channels or ns >= 1_000_000_000 or reserved != 0 or not all(
                200.0 <= v <= 3000.0 for c in channels for v in c):
            return frames, True
        frames.append((serial, sec, ns, channels))
        pos = end
    return frames, False


@st.composite
def peak_streams(draw) -> bytes:
    """Responses of peak content, mostly well formed, some with one field wrong, sometimes a flipped byte."""
    out = b""
    for _ in range(draw(st.integers(0, 4))):
        counts = draw(st.lists(st.integers(0, 3), max_size=4))
        values = draw(st.lists(st.one_of(st.floats(1500.0, 1600.0), st.floats(allow_nan=True)),
                               min_size=sum(counts), max_size=sum(counts)))
        header_length = 24 + 2 * len(counts) + draw(st.sampled_from([0, 0, 0, 0, 1, 2, -2]))
        ns = draw(st.sampled_from([0, 250_000_000, 999_999_999, 1_000_000_000]))
        content = (struct.pack("<HHIQII", max(header_length, 0), 1, 0, draw(st.integers(0, 2**64 - 1)),
                               draw(st.integers(0, 2**32 - 1)), ns)
                   + struct.pack(f"<{len(counts)}h", *counts) + struct.pack(f"<{len(values)}d", *values))
        message = draw(st.sampled_from([b"", b"", b"", b"ok", b"\xff"]))
        status = draw(st.sampled_from([0, 0, 0, 0, 1]))
        out += struct.pack("<BBHI", status, 0, len(message), len(content)) + message + content
    if out and draw(st.booleans()):
        i = draw(st.integers(0, len(out) - 1))
        out = out[:i] + bytes([out[i] ^ draw(st.integers(1, 255))]) + out[i + 1:]
    return out + draw(st.binary(max_size=draw(st.sampled_from([0, 0, 8, 40]))))


@FUZZ
@given(st.one_of(st.binary(max_size=400), peak_streams()), st.lists(st.integers(1, 64), max_size=10))
def test_fuzz_hyperion_stream_decoders(data, cuts):
    """Fed in any chunks, the stream decoder delivers first exactly the frames the reference reads before any
    bad response, in order; it loses sync when the reference finds a bad response (or refutes an incomplete
    frame early), and then delivers only frames that decode whole; and what it delivers and counts does not depend
    on the chunking."""
    expected, bad = reference_hyperion_stream(data)
    dec, whole = hyperion.PeakStreamDecoder(max_content=4096), hyperion.PeakStreamDecoder(max_content=4096)
    frames, pos = [], 0
    for c in [*cuts, len(data)]:
        frames += dec.feed(data[pos: pos + c])
        pos += c
    once = whole.feed(data)
    assert [(f.sequence, f.timestamp) for f in frames] == [(f.sequence, f.timestamp) for f in once]
    assert (dec.framing_errors, dec.pending) == (whole.framing_errors, whole.pending)
    assert dec.framing_errors >= bad  # (more: the decoder refutes an incomplete frame before its end)
    assert len(frames) >= len(expected)
    for f in frames[len(expected):]:  # after a loss of sync: frames that decoded whole
        w = f.wavelengths[np.isfinite(f.wavelengths)]
        assert np.all((w >= 200) & (w <= 3000))
    for f, (serial, sec, ns, channels) in zip(frames, expected, strict=False):
        assert f.sequence == min(serial, 2**63 - 1) and f.timestamp == sec + ns * 1e-9
        rows = max((len(c) for c in channels), default=0)
        want = np.full((rows, len(channels)), np.nan)
        for k, c in enumerate(channels):
            want[: len(c), k] = c
        np.testing.assert_array_equal(f.wavelengths, want)
    # the request side: whatever decodes is the request the bytes spell (reference: §3.1's <BBHI header)
    req = hyperion.RequestDecoder(max_argument=4096)
    try:
        got = req.feed(data)
    except FramingError:
        got = None
    if got:
        options, zero, n_cmd, n_arg = struct.unpack_from("<BBHI", data)
        assert zero == 0 and n_cmd > 0
        assert (got[0].options, got[0].command, got[0].argument) == (
            options, data[8: 8 + n_cmd].decode("ascii"), data[8 + n_cmd: 8 + n_cmd + n_arg].decode("ascii"))


def test_hyperion_peak_header_with_reserved_bits_set_is_refused():
    """docs/protocols.md §3.4: the reserved fields must be 0 (the only way to notice lost framing on this stream)."""
    content = bytearray(HYPERION_PEAKS)
    content[4] = 1  # the reserved u32 after the version
    with pytest.raises(FramingError):
        hyperion.decode_peaks(bytes(content))


def test_hyperion_half_a_frame_then_a_good_one_is_refused_whole():
    """Issue 11 item 5: the decoder took the good frame's headers as the half frame's wavelengths (3.9e-305 nm,
    2.0e6 nm) and delivered it before noticing. A frame is checked whole: no frame with absurd peaks."""
    w = 1510.0 + 5.0 * np.arange(18)[:, None] + np.zeros((1, 4))
    frames = [Frame(w + 0.01 * k, timestamp=10.0 + k, sequence=k) for k in range(3)]
    stream = [hyperion.encode_stream_frame(f) for f in frames]
    cut = stream[1][: len(stream[1]) // 2]
    dec = hyperion.PeakStreamDecoder(n_gratings=18)
    got = dec.feed(stream[0] + cut + stream[2])
    assert [f.sequence for f in got] == [0, 2]  # the frames around the damage are kept (resynchronised)
    for f in got:
        assert np.all((f.wavelengths > 1500) & (f.wavelengths < 1600))
    assert dec.in_sync and dec.framing_errors == 1 and "nm" in str(dec.last_error)
    assert dec.bytes_discarded == len(cut)


def test_hyperion_implausible_wavelength_refuses_the_frame():
    f = hyperion.decode_peaks(HYPERION_PEAKS)
    for value in (3.9e-305, 2.0e6, -1530.0, 0.0, math.inf, math.nan, 199.0, 3001.0):
        content = bytearray(HYPERION_PEAKS)
        content[-8:] = struct.pack("<d", value)
        with pytest.raises(FramingError, match="wavelength in 200–3000 nm"):
            hyperion.decode_peaks(bytes(content))
    assert hyperion.decode_peaks(HYPERION_PEAKS).sequence == f.sequence


def _corrupted_peak_contents():
    """Peak content with one byte of its header or counts set to each of a few values, and cut at every length."""
    for i in range(28):  # the 24-byte header and the two counts
        for value in {0x00, 0x01, 0x7F, 0x80, 0xFF, HYPERION_PEAKS[i] ^ 0x01}:
            yield HYPERION_PEAKS[:i] + bytes([value]) + HYPERION_PEAKS[i + 1:]
    for cut in range(len(HYPERION_PEAKS)):
        yield HYPERION_PEAKS[:cut]


#: the rules of codec.peak_content_fault, by what their errors say
RULES = {"peak content of": "short content", "peak header length": "header length", "reserved field": "reserved",
         "timestamp nanoseconds": "nanoseconds", "peak count -": "negative count",
         "more than n_gratings": "too many peaks", "bytes of wavelengths": "wavelength bytes"}


def _fields(err: FramingError | None, shift: int = 0):
    return None if err is None else (type(err), err.what, err.offset - shift, err.expected)


def test_hyperion_stream_and_codec_refuse_the_same_peak_headers_naming_the_same_field():
    """One definition of the peak header's rules (codec.peak_content_fault): for each corrupted header or counts,
    the stream decoder, fed the frame in pieces, refuses exactly what decode_peaks_header refuses, with the same
    error (class, field and value, offset within the content, expectation), and what decode_peaks refuses whole."""
    hit = set()
    cases = [(content, n_gratings) for n_gratings in (None, 1, 2) for content in _corrupted_peak_contents()]
    for k, (content, n_gratings) in enumerate(cases):
        try:
            hyperion.decode_peaks_header(content, n_gratings=n_gratings)
            header_err = None
        except FramingError as exc:
            header_err = exc
        try:
            whole = hyperion.decode_peaks(content, n_gratings=n_gratings)
            frame_err = None
        except FramingError as exc:
            whole, frame_err = None, exc
        dec = hyperion.PeakStreamDecoder(n_gratings=n_gratings)
        wire, step, got = hyperion.encode_response(content), 1 + k % 7, []
        for pos in range(0, len(wire), step):
            got += dec.feed(wire[pos: pos + step])
        stream_err = dec.last_error if dec.framing_errors else None
        where = f"content {content.hex()}, n_gratings {n_gratings}"
        # the stream's offsets count from the stream's start: the frame is first, its content after 8 header bytes
        assert _fields(stream_err, shift=8) == _fields(frame_err), where
        if header_err is not None:
            assert _fields(stream_err, shift=8) == _fields(header_err), where
            hit.add((next(rule for key, rule in RULES.items() if key in header_err.what), type(header_err)))
        else:  # only a peak that is not a wavelength can refuse a frame whose header and counts are valid
            assert stream_err is None or stream_err.offset - 8 >= struct.unpack_from("<H", content)[0], where
        if whole is not None:
            assert len(got) == 1 and got[0].sequence == whole.sequence, where
            np.testing.assert_array_equal(got[0].wavelengths, whole.wavelengths)
    # every rule was broken by some corruption: the comparison above is not vacuous
    want = {("short content", TruncatedFrameError), ("header length", FramingError),
            ("header length", TruncatedFrameError), ("reserved", FramingError), ("nanoseconds", FramingError),
            ("negative count", FramingError), ("wavelength bytes", TruncatedFrameError),
            ("wavelength bytes", OversizeFrameError)}
    assert hit == want | {("too many peaks", FramingError)}, hit


def test_hyperion_stream_that_ends_inside_a_frame_is_one_framing_error():
    """Issue 11 item 11: one meaning per counter; ILLumiSense counts a stream that ends mid-record."""
    f = hyperion.decode_peaks(HYPERION_PEAKS)
    good = hyperion.encode_stream_frame(f)
    dec = hyperion.PeakStreamDecoder()
    assert len(dec.feed(good + good[:13])) == 1
    dec.finish()
    assert dec.framing_errors == 1 and dec.pending == 0
    clean = hyperion.PeakStreamDecoder()
    clean.feed(good)
    clean.finish()  # ended between frames: nothing to count
    assert clean.framing_errors == 0
    # a u64 serial number beyond int64 is taken as 2**63 − 1 (it stacked into a batch as a float cast to int64
    # with a warning, rounding the other frames' numbers), and judged as one corrupt number amid its run
    tops = hyperion.PeakStreamDecoder().feed(b"".join(
        hyperion.encode_stream_frame(f, serial_number=s) for s in (2**62 + 1, 2**64 - 1, 2**62 + 3)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        batch = Frame.stack(tops)
    assert batch.sequence.dtype == np.int64 and batch.sequence.tolist() == [2**62 + 1, 2**63 - 1, 2**62 + 3]
    c = SequenceCounter()
    c.count_many(batch.sequence)
    assert (c.lost_samples, c.sequence_corrupt) == (0, 1)
    assert SequenceCounter().count_many([5, 2**64 - 1, 7]).tolist() == [0, 0, 0]
