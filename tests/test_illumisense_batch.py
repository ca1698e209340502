"""The batch path of the ILLumiSense stream decoder (issue 13): ``StreamDecoder.feed_batch`` and what the live
loop does with it must give exactly what the per-record path gives."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from twin.fiber import FiberModel
from twin.frames import Frame, PeakStatus
from twin.io import illumisense
from twin.io.drivers import Driver
from twin.io.illumisense import scan
from twin.live import LiveLoop
from twin.reconstruct import Reconstructor
from twin.synthetic import SyntheticSource


def record(payload: bytes) -> bytes:
    return len(payload).to_bytes(4, "big") + payload


def rec_of(seq: int, channels: int = 4, lost: int | None = None, sensor: bool = False) -> bytes:
    """A record of ``channels`` channels × 2 gratings; peak ``lost`` of channel 1 is lost (wavelength 0)."""
    body = b"".join(b"%d\t2\t0\t0\t0\t0\t%d.5\t%d.25\t-1\t-2\t" % (k + 1, 1530 + k, 1540 + k) for k in range(channels))
    if lost is not None:
        body = body.replace(b"1530.5" if lost == 0 else b"1540.25", b"0", 1)
    tail = b"\tCurvature [1/cm]\t0.05\t0.5\tCurvature angle [rad]\t1.5\t-1\t" \
           b"Shape x [cm]\t2\t0\t0.1\tShape y [cm]\t2\t0\t0\tShape z [cm]\t2\t0\t0.001" if sensor else b""
    return record(b"2024/01/31\t13:45:%02d.%06d\t%d\t%d\t" % (seq % 60, seq, seq, channels) + body[:-1] + tail +
                  b"\r\n")


def mixed_stream() -> bytes:
    """Good records, an odd first record, a lost peak, garbage, a damaged record, a gap, records with sensor
    blocks, a persistent layout change and an odd record after it."""
    parts = [rec_of(0, channels=3), *(rec_of(k) for k in range(1, 12)), rec_of(12, lost=0), rec_of(13, lost=1),
             b"garbage\r\n\x00\x01", rec_of(14), rec_of(15)[:40] + b"\x00\n" + rec_of(15)[42:], rec_of(16),
             *(rec_of(k) for k in range(20, 30)), *(rec_of(k, sensor=True) for k in range(30, 34)),
             *(rec_of(k) for k in range(34, 40)), *(rec_of(k, channels=5) for k in range(40, 52)),
             rec_of(52, channels=4), *(rec_of(k, channels=5) for k in range(53, 60))]
    return b"".join(parts)


def flatten(items: list[Frame]) -> list[Frame]:
    return [g for f in items for g in (f if f.batch_shape else (f,))]


def same_frames(a: list[Frame], b: list[Frame]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert x.wavelengths.shape == y.wavelengths.shape
        for name in ("wavelengths", "powers"):
            # bit for bit, NaN included
            assert np.array_equal(getattr(x, name).view(np.int64), getattr(y, name).view(np.int64)), name
        assert np.array_equal(x.status, y.status) and x.status.dtype == np.uint8
        assert x.sequence == y.sequence and type(x.sequence) is int
        assert np.array_equal(x.timestamp, y.timestamp, equal_nan=True) and type(x.timestamp) is float
        assert (x.vendor is None) == (y.vendor is None)


def counters(dec: illumisense.StreamDecoder) -> tuple:
    return (dec.records, dec.framing_errors, dec.bytes_discarded, dec.odd_records, dec.layout_changes,
            dec.holding, dec.sequence.as_dict(), dec.pending, dec.in_sync)


def run(stream: bytes, cuts: list[int], how: str) -> tuple[list[Frame], tuple, list]:
    dec = illumisense.StreamDecoder()
    out, calls, pos = [], [], 0
    for c in [*cuts, len(stream)]:
        got = getattr(dec, how)(stream[pos : pos + c])
        calls.append(got)
        out += got
        pos += c
    out += dec.finish()
    if how == "feed_records":
        out = [r.frame for r in out]
    return flatten(out) if how == "feed_batch" else out, counters(dec), calls


@pytest.mark.parametrize("cuts", [[], [1000, 3000], [97] * 60, [1] * 300])
def test_batch_path_gives_exactly_the_per_record_frames_and_counters(cuts):
    stream = mixed_stream()
    frames, c_frames, _ = run(stream, cuts, "feed")
    batch, c_batch, calls = run(stream, cuts, "feed_batch")
    records, c_records, _ = run(stream, cuts, "feed_records")
    same_frames(frames, batch)
    same_frames(frames, records)
    assert c_frames == c_batch == c_records
    # what the stream holds: the odd records dropped, the damaged one (15) lost, the rest in order
    assert [f.sequence for f in frames] == [*range(1, 15), 16, *range(20, 52), *range(53, 60)]
    assert c_frames[1] >= 2 and c_frames[3] == 2 and c_frames[4] == 1
    lost = {f.sequence: f for f in frames}
    assert lost[12].status[0, 0] == PeakStatus.MISSING and np.isnan(lost[12].wavelengths[0, 0])
    assert lost[13].status[1, 0] == PeakStatus.MISSING and np.isnan(lost[13].powers[1, 0])
    assert all(lost[k].vendor is not None for k in range(30, 34))
    if not cuts:  # one piece: the records of a layout come as batches, sensor blocks riding along
        assert any(f.batch_shape and len(f) > 5 for f in calls[0])
        assert any(f.batch_shape and f.vendor is not None and len(f) == 4 for f in calls[0])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.integers(1, 2000), max_size=8))
def test_batch_path_matches_for_any_chunking(cuts):
    stream = mixed_stream()
    frames, c_frames, _ = run(stream, cuts, "feed")
    batch, c_batch, _ = run(stream, cuts, "feed_batch")
    same_frames(frames, batch)
    assert c_frames == c_batch


def test_one_piece_of_one_layout_is_one_batch_frame():
    dec = illumisense.StreamDecoder()
    # the records that decide the layout are released as single frames
    assert [f.batch_shape for f in dec.feed_batch(b"".join(rec_of(k) for k in range(3)))] == [(), (), ()]
    items = dec.feed_batch(b"".join(rec_of(k) for k in range(3, 43)))
    assert len(items) == 1 and items[0].batch_shape == (40,)
    b = items[0]
    assert b.wavelengths.dtype == np.float64 and b.status.dtype == np.uint8 and b.sequence.dtype == np.int64
    assert list(b.sequence) == list(range(3, 43)) and b.vendor is None and b.truth is None
    assert dec.records == 43


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.from_regex(r"[+-]?[0-9]{0,18}(\.[0-9]{0,18})?([eE][+-]?[0-9]{1,3})?", fullmatch=True))
def test_tokenizer_numbers_are_python_floats_bit_for_bit(tok):
    buf = np.frombuffer(b"a\t" + tok.encode() + b"\tb", np.uint8)
    _, kind, value, *_ = scan.scan(buf, np.zeros(1, np.int64), np.array([buf.size], np.int64))
    try:
        want = float(tok)
    except ValueError:
        want = None
    if kind[1] in (scan.INT, scan.DEC):
        assert want is not None and np.float64(want).view(np.int64) == value[1:2].view(np.int64)[0], tok
    elif want is not None:
        assert kind[1] == scan.SLOW or (kind[1] == scan.TEXT and tok.endswith(".")), tok


# ------------------------------------------------------------------------------------------- live loop


def test_live_loop_counts_a_batch_like_its_frames_one_by_one():
    src = SyntheticSource(rate=1000, pace=False, frames=64, cores=7, gratings=18, noise=0.001, truth=False)
    frames = list(src)

    def changed(f: Frame, at: tuple, value: float) -> Frame:
        w = f.wavelengths.copy()
        w[at] = value
        return Frame(w, f.timestamp, f.sequence, f.powers, f.status)

    frames[5] = changed(frames[5], (3, 2), 1e300)  # a peak outside the window
    frames[7] = changed(frames[7], (2, 1), np.nan)  # a missing peak
    frames = frames[:20] + frames[23:]  # a gap of 3 samples
    stacked = Frame.stack(frames)
    a, b = LiveLoop(None, Reconstructor(src.fiber), []), LiveLoop(None, Reconstructor(src.fiber), [])
    one_by_one = [a.process(Frame.stack([f])) for f in frames]  # batches of one
    flags_a = np.concatenate([x[2] for x in one_by_one])
    positions_a = np.concatenate([x[1].positions for x in one_by_one])
    good_b, shapes_b, flags_b = b.process(stacked)
    assert good_b is stacked and len(good_b) == 61
    assert np.array_equal(flags_a, flags_b)
    # the same shapes up to the last bits (a batch of one and one of 61 sum in other orders), 1e-12 m of ~0.2 m
    np.testing.assert_allclose(positions_a, shapes_b.positions, rtol=0, atol=1e-12)
    assert a.c.counts() == b.c.counts() and a.c.lost_samples == 3 and a.c.peaks_outside_window == 1
    assert a.c.frames_missing_peaks == 2
    # a batch of another layout is rejected whole (a configuration error when nothing ever matched)
    wrong = Frame(np.ones((4, 3, 2)) * 1550.0)
    with pytest.raises(ValueError, match="fibre model"):
        LiveLoop(None, Reconstructor(src.fiber), []).process(wrong)
    good, shapes, flags = b.process(wrong)
    assert len(good) == 0 and shapes is None and flags.size == 0 and b.c.frames_rejected == 4


class _Canned(Driver):
    """A driver whose 'transport' hands out prepared decoder outputs."""

    def __init__(self, pieces):
        self.pieces = list(pieces)
        super().__init__("canned://")

    def _connect(self):
        pass

    def _drop(self):
        pass

    def _pump(self, timeout):
        if self.pieces:
            self._push(self.pieces.pop(0))


def test_driver_keeps_batches_whole_and_read_gives_single_frames():
    dec = illumisense.StreamDecoder(layout_quorum=0)
    pieces = [dec.feed_batch(b"".join(rec_of(k) for k in range(a, a + 10))) for a in (0, 10, 20)]
    # one batch per piece once the layout is known (in the first piece, the record that taught the layout was
    # decoded on its own: a batch of 1, then one of 9; the driver joins them, read_batch below)
    assert [len(p) for p in pieces[1:]] == [1, 1] and [len(f) for f in pieces[0]] == [1, 9]
    first = flatten(pieces[0])
    src = _Canned(pieces)
    got = src.read_batch(6, 0.0)
    assert isinstance(got, Frame) and list(got.sequence) == list(range(6))  # the limit cuts the batch
    got = src.read_batch(256, 0.0)
    assert isinstance(got, Frame) and list(got.sequence) == list(range(6, 10))
    singles = [src.read(0.0) for _ in range(3)]
    assert [type(f) for f in singles] == [Frame] * 3 and [f.sequence for f in singles] == [10, 11, 12]
    assert all(not f.batch_shape for f in singles)
    same_frames(singles, flatten(pieces[1])[:3])
    assert src.stats()["frames"] == 20  # two pieces pumped so far
    # single frames and batches join into one batch, in order
    mixed = Frame.stack([first[0], pieces[2][0]])
    assert mixed.batch_shape == (11,) and list(mixed.sequence) == [0, *range(20, 30)]


def test_live_loop_runs_on_the_batch_path_of_the_driver():
    fiber = FiberModel.paper()
    frames = list(SyntheticSource(rate=1000, pace=False, frames=40, fiber=fiber, noise=0.001, truth=False))
    dec = illumisense.StreamDecoder()
    items = dec.feed_batch(b"".join(illumisense.encode_record(f) for f in frames))
    seen = []
    summary = LiveLoop(_Canned([items]), Reconstructor(fiber), [lambda fr, sh, s: seen.append(len(fr))]).run(
        max_frames=40, duration=20, handle_signals=False)
    assert summary.status.frames == 40 and summary.status.lost_samples == 0 and sum(seen) == 40
