"""The sequence-number rule (twin/io/sequence.py): one absurd number amid a continuing run is one corrupt record,
not 4.6e18 lost samples; a genuine gap, restart or re-seed is reported as that; the figures never depend on the
batching; `twin live` and `twin replay` print the same figures over a recording holding a corrupt number."""

from __future__ import annotations

import numpy as np
import pytest
from io_helpers import synthetic_frames

from twin.io.record import Recorder
from twin.io.sequence import MAX_LOST, SequenceCounter
from twin.synthetic import multicore_fiber


def _books(seqs) -> tuple[int, int, int, int]:
    c = SequenceCounter()
    c.count_many(seqs)
    return c.lost_samples, c.sequence_gaps, c.sequence_resets, c.sequence_corrupt


def test_one_absurd_number_amid_a_run_is_one_corrupt_record_not_lost_samples():
    run = list(range(10, 21))
    # the defect: 2**62 booked 2**62 - 21 lost samples (≈ 4.6e18), then a reset
    assert _books([*run, 2 ** 62, *list(range(22, 30))]) == (0, 0, 0, 1)  # it stood for sample 21
    assert _books([*run, 2 ** 62, 21, 22]) == (0, 0, 0, 1)  # an extra record: still no loss
    assert _books([*run, 2 ** 62, 25, 26]) == (3, 1, 0, 1)  # it stood for 21; 22–24 lost
    assert _books([*run, 0, 22, 23]) == (0, 0, 0, 1)  # backwards and back: corrupt too
    assert _books([*run, 52, 22, 23]) == (0, 0, 0, 1)  # a plausible jump the next number refutes
    assert _books([5, 2**63 - 1, 7]) == (0, 0, 0, 1)


def test_a_genuine_gap_restart_or_reseed_is_reported_as_that():
    assert _books([10, 42, 43, 44]) == (31, 1, 0, 0)
    assert _books(list(range(10)) + list(range(10))) == (0, 0, 1, 0)  # a restarted acquisition
    assert _books([2**32 - 2, 2**32 - 1, 0, 1]) == (0, 0, 1, 0)  # a u32 counter that wrapped
    assert _books([0, 1, 2**62, 2**62 + 1]) == (0, 0, 1, 0)  # re-seeded: no outage is 4.6e18 samples long
    assert _books([0, MAX_LOST + 1, MAX_LOST + 2]) == (MAX_LOST, 1, 0, 0)  # the longest gap counted as loss
    assert _books([0, MAX_LOST + 2, MAX_LOST + 3]) == (0, 0, 1, 0)
    assert _books([5, 6, 9, -1, 10, 3, 4]) == (2, 1, 1, 0)  # unknown (−1) skipped; 10 continues 9


def test_the_lost_sample_of_each_number_is_decided_as_it_arrives():
    c = SequenceCounter()
    assert c.count_many([10, 12, 2**62, 13, 14]).tolist() == [0, 1, 0, 0, 0]
    assert (c.lost_samples, c.sequence_gaps, c.sequence_corrupt) == (1, 1, 1)


def _corrupted_run(rng, n: int) -> tuple[np.ndarray, int, int]:
    """0 … n−1 with lone numbers corrupted (never two in a row, nor the first or last), some samples dropped:
    the sequence, how many numbers were corrupted, how many samples were dropped."""
    seq = np.arange(n, dtype=np.int64)
    keep = rng.random(n) > 0.05
    keep[0] = keep[-1] = True
    dropped = int(n - keep.sum())
    seq = seq[keep]
    bad = np.flatnonzero(rng.random(seq.size) < 0.05)
    bad = bad[(bad > 0) & (bad < seq.size - 1)]
    bad = bad[np.r_[True, np.diff(bad) > 1]] if bad.size else bad
    # absurd values, backward values, plausible forward jumps: all refuted by the next number
    kinds = rng.integers(0, 3, bad.size)
    seq[bad] = np.where(kinds == 0, rng.integers(2**40, 2**63 - 1, bad.size),
                        np.where(kinds == 1, rng.integers(0, 3, bad.size), seq[bad] + rng.integers(3, 60, bad.size)))
    # a corrupt number stands for the sample it replaced, so a drop just after it would be counted from there
    return seq, bad.size, dropped


@pytest.mark.parametrize("seed", range(8))
def test_corrupt_numbers_counted_the_same_whatever_the_batching(seed):
    rng = np.random.default_rng(seed)
    seq, n_bad, _ = _corrupted_run(rng, 3000)
    one = SequenceCounter()
    lost_one = [one.count(int(s)) for s in seq]
    assert one.sequence_corrupt >= n_bad - 2 and one.lost_samples < 3000 and one.sequence_resets <= 2
    for parts in (2, 7, 300):
        many = SequenceCounter()
        cuts = np.sort(rng.choice(np.arange(1, seq.size), parts - 1, replace=False))
        lost = np.concatenate([many.count_many(c) for c in np.split(seq, cuts)])
        assert lost.tolist() == lost_one and many.as_dict() == one.as_dict()


def test_lone_corrupt_numbers_in_an_unbroken_run_are_exactly_counted():
    rng = np.random.default_rng(11)
    seq = np.arange(5000, dtype=np.int64)
    bad = np.arange(3, 4990, 37)
    seq[bad] = rng.integers(0, 2**63 - 1, bad.size)
    assert _books(seq) == (0, 0, 0, bad.size)


def test_live_and_replay_print_the_same_figures_over_a_corrupt_number(tmp_path):
    from test_figures import COUNTS, _live_and_replay

    fiber = multicore_fiber(4, 18)
    frames = synthetic_frames(120, rate=100, fiber=fiber)
    frames[50] = frames[50].__class__(frames[50].wavelengths, frames[50].timestamp, 2**62)
    path = tmp_path / "corrupt.h5"
    with Recorder(path, fiber=fiber, rate=100) as rec:
        for i in range(0, 120, 17):  # batches that do not line up with the corrupt number
            rec.append(frames[i : i + 17])
    live, replay = _live_and_replay(path)
    assert {k: live[k] for k in COUNTS} == {k: replay[k] for k in COUNTS}
    assert (live["lost_samples"], live["sequence_gaps"], live["sequence_resets"], live["sequence_corrupt"]) == (
        0, 0, 0, 1)


def test_one_corrupt_counter_is_one_corrupt_record_on_every_protocol(tmp_path):
    """The same frames, one of which carries a counter beyond int64 (20 digits on ILLumiSense, a u64 on Hyperion):
    every protocol delivers every frame and books one corrupt number, no loss (an ILLumiSense record with such a
    sample number was refused whole, its frame lost and counted as a lost sample)."""
    from twin.frames import Frame
    from twin.io import hyperion, illumisense
    from twin.io.illumisense.log import read_log

    big = 2**64 - 1
    frames = [Frame(np.full((3, 2), 1550.0 + 0.01 * s), 1.7e9 + s, s) for s in range(10, 20)]
    records = [illumisense.encode_record(f) for f in frames]
    payload = records[5][4:].replace(b"\t15\t", f"\t{big}\t".encode(), 1)
    records[5] = len(payload).to_bytes(4, "big") + payload
    books = {}
    dec = illumisense.StreamDecoder(layout_quorum=0)
    books["illumisense stream"] = ([f.sequence for f in dec.feed(b"".join(records))], dec.sequence)
    log = tmp_path / "log.txt"
    log.write_bytes(b"".join(r[4:] for r in records))
    c = SequenceCounter()
    seq = read_log(log).sequences
    c.count_many(seq)
    books["illumisense log"] = (seq.tolist(), c)
    stream = b"".join(hyperion.encode_stream_frame(f, serial_number=big if f.sequence == 15 else None)
                      for f in frames)
    c = SequenceCounter()
    got = hyperion.PeakStreamDecoder().feed(stream)
    c.count_many([f.sequence for f in got])
    books["hyperion"] = ([f.sequence for f in got], c)
    want = [*range(10, 15), 2**63 - 1, *range(16, 20)]
    for name, (sequences, counter) in books.items():
        assert sequences == want, name
        assert counter.as_dict() == {"sequence_gaps": 0, "lost_samples": 0, "sequence_resets": 0,
                                     "sequence_corrupt": 1}, name
