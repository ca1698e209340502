"""Frame and Truth are batch-first like Shape: one sample or a batch, stacked, indexed, iterated; the
reconstructor and the recorder take a batch as it is."""

from __future__ import annotations

import numpy as np
import pytest
from io_helpers import synthetic_frames

from twin import FiberModel, Reconstructor
from twin.frames import Frame, PeakStatus, Truth
from twin.io.record import Recorder, open_recording


def test_stack_index_iterate_round_trip():
    frames = synthetic_frames(6, drop=0.1, seed=1)
    batch = Frame.stack(frames)
    assert batch.batch_shape == (6,) and len(batch) == 6 and batch.wavelengths.shape == (6, 18, 4)
    np.testing.assert_array_equal(batch.sequence, [f.sequence for f in frames])
    assert batch.sequence.dtype == np.int64 and batch.timestamp.dtype == np.float64
    one = batch[4]
    assert one.batch_shape == () and isinstance(one.sequence, int) and isinstance(one.timestamp, float)
    np.testing.assert_array_equal(one.wavelengths, frames[4].wavelengths)
    np.testing.assert_array_equal(one.truth.positions, frames[4].truth.positions)
    assert [f.sequence for f in batch] == [f.sequence for f in frames]
    part = batch[1:3]
    assert len(part) == 2 and part.truth.batch_shape == (2,)
    odd = batch[np.array([True, False] * 3)]
    np.testing.assert_array_equal(odd.sequence, [0, 2, 4])
    again = Frame.stack([batch[:2], frames[2], batch[3:]])  # batches and single frames concatenate
    np.testing.assert_array_equal(again.wavelengths, batch.wavelengths)
    np.testing.assert_array_equal(again.truth.frames, batch.truth.frames)


def test_a_single_frame_has_no_length_and_is_not_indexed():
    f = synthetic_frames(1)[0]
    assert bool(f)
    with pytest.raises(TypeError, match="no length"):
        len(f)
    with pytest.raises(TypeError, match="cannot be indexed"):
        f[0]
    b = Frame.stack([f, f])
    with pytest.raises(IndexError, match="batch axes"):
        b[0, 1]
    assert not b[0:0]


def test_truth_present_only_for_some_frames():
    frames = synthetic_frames(4)
    mixed = [frames[0], Frame(frames[1].wavelengths, 1.0, 1), frames[2], Frame(frames[3].wavelengths, 3.0, 3)]
    b = Frame.stack(mixed)
    np.testing.assert_array_equal(b.truth.present, [True, False, True, False])
    assert b[1].truth is None and b[2].truth is not None
    assert np.isnan(b.truth.positions[1]).all()
    assert Frame.stack([Frame(f.wavelengths) for f in frames]).truth is None


def test_stack_refuses_mixed_layouts():
    frames = synthetic_frames(2)
    with pytest.raises(ValueError, match="disagree on"):
        Frame.stack([frames[0], synthetic_frames(1, cores=7)[0]])
    with pytest.raises(ValueError, match="no frames"):
        Frame.stack([])
    other = Truth(s=np.arange(5.0), positions=np.zeros((5, 3)))
    odd = Frame(frames[1].wavelengths, truth=other)
    with pytest.raises(ValueError, match="another layout"):
        Frame.stack([frames[0], odd])
    kept = Frame.stack([frames[0], odd], truth_like=frames[0].truth)  # the recorder's choice: drop it
    np.testing.assert_array_equal(kept.truth.present, [True, False])


def test_status_and_powers_filled_for_frames_given_without():
    w = FiberModel.paper().lambda0.copy()
    w[2, 1] = np.nan
    b = Frame.stack([Frame(w, 0.0, 0), Frame(w, 0.1, 1, powers=np.ones_like(w), status=np.zeros(w.shape))])
    assert b.status[0, 2, 1] == PeakStatus.MISSING and b.status[1, 2, 1] == 0
    assert np.isnan(b.powers[0]).all() and (b.powers[1] == 1).all()


def test_batch_shapes_are_checked():
    w = np.full((3, 18, 4), 1550.0)
    with pytest.raises(ValueError, match="expected shape"):
        Frame(np.zeros(4))
    with pytest.raises(ValueError, match="batch shape"):
        Frame(w, truth=Truth(s=np.arange(5.0), positions=np.zeros((2, 5, 3))))
    b = Frame(w, 0.0, np.arange(3))  # a scalar timestamp is broadcast over the batch
    np.testing.assert_array_equal(b.timestamp, [0.0, 0.0, 0.0])


def test_reconstructor_and_recorder_take_a_batch(tmp_path):
    frames = synthetic_frames(50, drop=0.05)
    batch = Frame.stack(frames)
    rec = Reconstructor(FiberModel.paper())
    np.testing.assert_array_equal(rec(batch).positions, rec(frames).positions)
    path = tmp_path / "b.h5"
    with Recorder(path, fiber=FiberModel.paper()) as r:
        r.append(batch[:20])
        r.append(frames[20:])
    with open_recording(path) as r:
        back = r.frames()
    np.testing.assert_array_equal(back.wavelengths, batch.wavelengths)
    np.testing.assert_array_equal(back.truth.positions, batch.truth.positions)
    np.testing.assert_array_equal(back.status, batch.status)
