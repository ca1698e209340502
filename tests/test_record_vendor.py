"""The interrogator's own reconstruction in recordings and replays (issue 13): ILLumiSense sensor blocks
(`Frame.vendor`) stored in twin HDF5 recordings per sensor, read back exactly, delivered by replay:// (from a
recording and from a text log) so the live loop's vendor distance works there, compared by `twin replay`; a
layout change within a recording counted, damaged vendor chunks reported like damaged truth chunks. And the
replay's books kept by the live loop's (peaks outside the window counted).

Tolerances: the blocks are stored as float64 and must come back bit for bit; a text log holds 5 decimals of a
cm (shape) and 6 of 1/cm (curvature), so a logged block matches its decoded line exactly and the original within
half a unit of the last decimal. Vendor shapes built from our own reconstruction of the same wavelengths with
the same fibre are a rigid motion of ours, so their distance after registration is rounding (< 1e-9 mm).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from io_helpers import synthetic_frames

from twin import Reconstructor
from twin.frames import Frame
from twin.io import illumisense
from twin.io.errors import RecordingDamaged
from twin.io.illumisense import VendorSensor
from twin.io.illumisense.vendor import vendor_sensors
from twin.io.record import Recorder, open_recording
from twin.io.source import open_source
from twin.live import LiveLoop
from twin.reference_errors import VendorDistance
from twin.replay_summary import summarize
from twin.synthetic import multicore_fiber

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg"}
FIBER = multicore_fiber(4, 18)  # the synthetic source's default sensor


def second_sensor(i: int, g: int = 4, n: int = 30, spacing: float = 2e-3) -> VendorSensor:
    """Another sensor of another G, N and spacing (ragged across sensors), values unique per frame."""
    rng = np.random.default_rng(i)
    return VendorSensor(rng.normal(size=g), rng.uniform(-np.pi, np.pi, g), rng.normal(scale=0.05, size=(n, 3)),
                        spacing)


def with_vendor(frames: list[Frame], pattern=None) -> list[Frame]:
    """The frames with sensor blocks: sensor 0 our own reconstruction in the vendor frame, sensor 1 synthetic.
    ``pattern(i)`` says which: "both" (default), "first" (sensor 0 only), "none"."""
    shapes = Reconstructor(FIBER)(np.stack([f.wavelengths for f in frames]))
    own = vendor_sensors(shapes)
    out = []
    for i, f in enumerate(frames):
        kind = "both" if pattern is None else pattern(i)
        blocks = {"both": (own[i], second_sensor(i)), "first": (own[i],), "none": None}[kind]
        out.append(Frame(f.wavelengths, f.timestamp, f.sequence, f.powers, f.status, f.truth, blocks))
    return out


def pattern(i: int) -> str:
    return "none" if i % 7 == 3 else "first" if i % 5 == 1 else "both"


def record(path: Path, frames: list[Frame], step: int = 25, chunk: int = 16) -> Recorder:
    with Recorder(path, fiber=FIBER, rate=1000, chunk=chunk, flush_frames=step) as rec:  # a flush per append
        for i in range(0, len(frames), step):
            rec.append(frames[i : i + step])
    return rec


def assert_same_blocks(got, want) -> None:
    """Two Frame.vendor values are the same, bit for bit (None, or tuples of VendorSensor)."""
    assert (got is None) == (want is None)
    if want is None:
        return
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        assert a.spacing == b.spacing
        for name in ("curvature", "angle", "positions"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.shape == y.shape
            np.testing.assert_array_equal(x, y)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, list[Frame]]:
    path = tmp_path_factory.mktemp("vendor") / "v.h5"
    frames = with_vendor(synthetic_frames(200, rate=1000), pattern)
    rec = record(path, frames)
    assert rec.vendor_dropped == 0 and rec.stats()["vendor_dropped"] == 0
    return path, frames


def test_a_recording_keeps_every_sensor_block_exactly(recorded):
    path, frames = recorded
    with open_recording(path) as r:
        assert r.complete and not r.damaged and len(r) == 200 and r.has_vendor
        s0, s1 = r.vendor()
        kinds = np.array([pattern(i) for i in range(200)])
        np.testing.assert_array_equal(s0.present, kinds != "none")
        np.testing.assert_array_equal(s1.present, kinds == "both")
        assert s0.positions.shape == (200, 171, 3) and s0.curvature.shape == (200, 18) and s0.spacing == 1e-3
        assert s1.positions.shape == (200, 30, 3) and s1.curvature.shape == (200, 4) and s1.spacing == 2e-3
        for i, f in enumerate(frames):
            for k, arrays in enumerate((s0, s1)):
                want = f.vendor[k] if f.vendor and len(f.vendor) > k else None
                got = arrays.sensor(i)
                assert_same_blocks(None if got is None else (got,), None if want is None else (want,))
        assert np.isnan(s1.positions[~s1.present]).all()
        # any rows, from anywhere: the same
        mid = r.vendor(37, 90)
        assert len(mid[0]) == 53
        np.testing.assert_array_equal(mid[1].positions, s1.positions[37:90])


def test_replay_of_a_recording_delivers_the_vendor_blocks(recorded):
    path, frames = recorded
    got = list(open_source(f"replay://{path}?speed=max"))
    assert [f.sequence for f in got] == [f.sequence for f in frames]
    for g, f in zip(got, frames, strict=True):
        assert_same_blocks(g.vendor, f.vendor)


def test_the_live_loop_on_replay_compares_with_the_vendor_shape(recorded):
    path, _ = recorded
    vendor = VendorDistance(per_second=None)  # every frame
    summary = LiveLoop(open_source(f"replay://{path}?speed=max"), Reconstructor(FIBER), [vendor],
                       max_batch=16).run(duration=60, handle_signals=False)
    assert summary.reason == "source ended" and summary.status.frames == 200
    d = vendor.as_dict()
    assert d["vendor_frames_compared"] >= 5
    assert d["vendor_distance_max_mm"] < 1e-9


def test_twin_replay_compares_a_recording_with_its_vendor_shape(recorded):
    path, frames = recorded
    s = summarize(path, compare_rate=None)
    assert s.frames == 200 and s.vendor["vendor_frames_compared"] == sum(f.vendor is not None for f in frames)
    assert s.vendor["vendor_distance_max_mm"] < 1e-9
    assert s.truth is not None  # the truth is compared as before


def test_a_change_of_layout_is_counted_and_not_stored(tmp_path):
    frames = with_vendor(synthetic_frames(60, rate=1000))
    other_n = VendorSensor(frames[40].vendor[0].curvature, frames[40].vendor[0].angle,
                           frames[40].vendor[0].positions[:100])
    frames[40] = Frame(frames[40].wavelengths, sequence=40, vendor=(other_n, frames[40].vendor[1]))
    frames[41] = Frame(frames[41].wavelengths, sequence=41, vendor=(*frames[41].vendor, second_sensor(99)))
    rec = record(tmp_path / "change.h5", frames)
    assert rec.vendor_dropped == 2  # sensor 0 of frame 40, the third sensor of frame 41
    with open_recording(tmp_path / "change.h5") as r:
        s0, s1 = r.vendor()
        assert not s0.present[40] and s1.present[40] and s0.present[41] and s1.present[41]
        assert s0.present.sum() == 59 and s1.present.sum() == 60
    got = list(open_source(f"replay://{tmp_path / 'change.h5'}?speed=max"))
    assert got[40].vendor is None  # sensor 0 absent: a frame's sensors keep their indices
    assert_same_blocks(got[41].vendor, frames[41].vendor[:2])

    # blocks that first appear after the first chunk: no /vendor datasets (SWMR), all counted
    late = with_vendor(synthetic_frames(40, rate=1000), lambda i: "none" if i < 20 else "first")
    with Recorder(tmp_path / "late.h5", fiber=FIBER, rate=1000, chunk=16) as rec:
        rec.append(late[:20])
        rec.flush()
        rec.append(late[20:])
    assert rec.vendor_dropped == 20
    with open_recording(tmp_path / "late.h5") as r:
        assert len(r) == 40 and not r.has_vendor and r.vendor() == ()


def test_replay_of_a_log_with_sensor_blocks_delivers_them(tmp_path):
    frames = with_vendor(synthetic_frames(30, rate=1000), pattern)
    path = tmp_path / "log.txt"
    lines = [illumisense.encode_payload(f, sensors=f.vendor, line_ending=b"\r\n") for f in frames]
    path.write_bytes(b"".join(lines))
    got = list(open_source(f"replay://{path}?speed=max"))
    assert len(got) == 30
    for g, f, line in zip(got, frames, lines, strict=True):
        assert_same_blocks(g.vendor, illumisense.decode_record(line).frame.vendor)
        if f.vendor is not None:
            np.testing.assert_allclose(g.vendor[0].positions, f.vendor[0].positions, rtol=0, atol=0.5e-7 + 1e-12)
    s = summarize(path, fiber=FIBER, compare_rate=None)
    assert s.vendor["vendor_frames_compared"] == sum(f.vendor is not None for f in frames)
    assert s.vendor["vendor_distance_max_mm"] < 0.02  # the log's rounding (tests/test_illumisense_io.py)


# ------------------------------------------------------------------------------------------------ damage


def _flip_in_chunk(src: Path, dst: Path, dataset: str, row: int) -> int:
    """Copy with one byte flipped in the chunk of ``dataset`` holding ``row``; returns the chunk's first row."""
    with open_recording(src) as r:
        ds = r._file[dataset]
        step = ds.chunks[0]
        info = ds.id.get_chunk_info_by_coord((row // step * step, *(0,) * (ds.ndim - 1)))
    data = bytearray(src.read_bytes())
    data[info.byte_offset + info.size // 2] ^= 0x40
    dst.write_bytes(bytes(data))
    return info.chunk_offset[0]


def test_a_damaged_vendor_chunk_is_reported_and_salvaged_like_the_truth(recorded, tmp_path):
    path, frames = recorded
    bad = tmp_path / "bad.h5"
    first = _flip_in_chunk(path, bad, "vendor/sensor0/positions", 100)
    assert 0 < first <= 100
    with pytest.raises(RecordingDamaged, match=r"bad\.h5: damaged recording"):
        summarize(bad)
    with pytest.raises(RecordingDamaged):  # replay:// without salvage: the error after the frames
        list(open_source(f"replay://{bad}?speed=max"))
    s = summarize(bad, salvage=True)
    assert s.damaged and s.frames == 200 and any("vendor/sensor0/positions" in d for d in s.damage)
    with open_recording(bad) as r:
        s0, s1 = r.vendor()
        assert r.damaged and len(r) == 200
        # before the damaged chunk, exactly as recorded; from it on, absent (all sensors: one row count)
        np.testing.assert_array_equal(s0.present[:first], [f.vendor is not None for f in frames[:first]])
        assert not s0.present[first:].any() and not s1.present[first:].any()
        for i in range(first):
            assert_same_blocks(None if s0.sensor(i) is None else (s0.sensor(i),),
                               None if frames[i].vendor is None else frames[i].vendor[:1])
        np.testing.assert_array_equal(r.frames().wavelengths, np.stack([f.wavelengths for f in frames]))
    got = list(open_source(f"replay://{bad}?speed=max&salvage=1"))
    assert len(got) == 200 and all(g.vendor is None for g in got[first:])
    proc = subprocess.run([*TWIN, "replay", str(bad)], capture_output=True, text=True, env=ENV, timeout=120)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "bad.h5" in proc.stderr


def test_a_cut_recording_keeps_the_vendor_blocks_before_the_cut(recorded, tmp_path):
    path, frames = recorded
    cut = tmp_path / "cut.h5"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with open_recording(cut) as r:
        assert r.damaged
        n = len(r)
        s0, s1 = r.vendor()
        assert len(s0) == n
        assert n > 0 and s0.present.any() and s1.present.any()  # else the loops below check nothing
        for i in np.flatnonzero(s0.present):
            assert_same_blocks((s0.sensor(i),), frames[i].vendor[:1])
        for i in np.flatnonzero(s1.present):
            assert_same_blocks((s1.sensor(i),), frames[i].vendor[1:2])
        assert not (s0.present & np.array([f.vendor is None for f in frames[:n]])).any()


# ------------------------------------------------------------------------------------------------ books


def test_twin_replay_counts_like_the_live_loop(tmp_path):
    """The replay's books are the live loop's: a peak outside the physical window (a corrupted 1e300 nm, an
    infinity) is counted and treated as missing, as `twin live` does (before: not counted by `twin replay`)."""
    frames = synthetic_frames(50, rate=1000)
    w = np.stack([f.wavelengths for f in frames])
    w[10, 3, 1] = 1e300
    w[20, 0, 0] = np.inf
    w[30, 5, 2] = np.nan
    seq = np.arange(50)
    seq[40:] += 3  # three samples lost
    bad = [Frame(w[i], frames[i].timestamp, seq[i]) for i in range(50)]
    path = tmp_path / "books.h5"
    record(path, bad)
    s = summarize(path)
    live = LiveLoop(open_source(f"replay://{path}?speed=max"), Reconstructor(FIBER)).run(handle_signals=False)
    for key in ("frames_complete", "frames_partial", "frames_unusable", "frames_missing_peaks", "invalid_nodes",
                "peaks_outside_window", "lost_samples", "sequence_gaps", "sequence_resets"):
        assert getattr(s, key) == getattr(live.status, key), key
    assert s.peaks_outside_window == 2 and s.frames_missing_peaks == 3 and s.lost_samples == 3


def test_recording_an_illumisense_stream_keeps_its_sensor_blocks(tmp_path):
    """End to end: the twin's ILLumiSense server (sensor blocks by default) → driver → live loop → recorder;
    the recording replays with the blocks and `twin replay` compares ours with them."""
    from sim_interrogator.servers import IllumisenseServer
    from twin.synthetic import SyntheticSource

    fiber = multicore_fiber(7, 18)
    path = tmp_path / "stream.h5"
    with IllumisenseServer(SyntheticSource(rate=500, fiber=fiber, noise=0.002, seed=4), port=0) as server:
        src = open_source(f"illumisense://127.0.0.1:{server.address[1]}", fiber=fiber)
        recorder = Recorder(path, fiber=fiber, rate=500)
        summary = LiveLoop(src, Reconstructor(fiber), [recorder]).run(max_frames=200, duration=30,
                                                                       handle_signals=False)
    assert summary.status.frames >= 200 and recorder.vendor_dropped == 0
    with open_recording(path) as r:
        (s0,) = r.vendor()
        assert len(r) == recorder.frames_written and s0.present.all() and s0.positions.shape[1:] == (171, 3)
    first = next(iter(open_source(f"replay://{path}?speed=max")))
    assert first.vendor is not None and first.vendor[0].positions.shape == (171, 3)
    s = summarize(path, compare_rate=None)
    assert s.vendor["vendor_frames_compared"] == s.frames_complete
    assert s.vendor["vendor_distance_max_mm"] <= 0.02  # wire rounding only (tests/test_illumisense_io.py)
