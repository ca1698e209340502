"""Recording and replay: HDF5 round trip (frames, truth, fibre model, calibration), durability when the writer
is killed, ILLumiSense vendor logs, the replay:// source and `twin replay`.

Tolerances: wavelengths, sequences, timestamps and truth positions are stored as float64/int64 and must come
back exactly; powers are float32 (relative 6e-8); truth material frames float32 (6e-8 of a unit vector).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from io_helpers import singles, synthetic_frames, wait_until

from twin import Calibration, FiberModel, Reconstructor
from twin.frames import Frame
from twin.io import illumisense
from twin.io.record import Recorder, open_recording
from twin.io.source import SourceClosed, open_source
from twin.live import LiveLoop
from twin.replay_summary import summarize
from twin.synthetic import SyntheticSource

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg"}


def test_round_trip_of_frames_truth_fiber_and_calibration(tmp_path):
    frames = synthetic_frames(700, drop=0.05, noise=0.001, seed=2)
    fiber = FiberModel.paper()
    cal = Calibration(lambda0=fiber.lambda0 + 0.01, twist=np.linspace(0, 0.1, 18), provenance={"by": "test"})
    path = tmp_path / "rec.h5"
    with Recorder(path, fiber=fiber, calibration=cal, source_url="synthetic://?drop=0.05", rate=1000,
                  flush_frames=256) as rec:
        for i in range(0, 700, 33):
            rec.append(frames[i : i + 33], received=1000.0 + i)
    with open_recording(path) as r:
        assert r.kind == "twin-hdf5" and r.complete and len(r) == 700 and r.rate == 1000
        assert r.source_url == "synthetic://?drop=0.05"
        np.testing.assert_array_equal(r.fiber.lambda0, fiber.lambda0)
        np.testing.assert_array_equal(r.calibration.lambda0, cal.lambda0)
        np.testing.assert_array_equal(r.calibration.twist, cal.twist)
        a = r.frames()
        np.testing.assert_array_equal(a.wavelengths, np.stack([f.wavelengths for f in frames]))
        np.testing.assert_array_equal(a.sequence, np.arange(700))
        np.testing.assert_array_equal(a.timestamp, [f.timestamp for f in frames])
        np.testing.assert_array_equal(a.status, np.stack([f.status for f in frames]))
        np.testing.assert_allclose(a.powers, np.stack([f.powers for f in frames]), rtol=1e-7)
        received = r.received()
        assert received[0] == 1000.0 and received[-1] == 1000.0 + 693
        t = r.truth(10, 20)
        assert t.present.all()
        np.testing.assert_array_equal(t.positions, np.stack([f.truth.positions for f in frames[10:20]]))
        np.testing.assert_allclose(t.frames, np.stack([f.truth.frames for f in frames[10:20]]), atol=1e-7)
        np.testing.assert_array_equal(t.s, frames[0].truth.s)
        back = r.frames(5, 7)
        np.testing.assert_array_equal(back[1].wavelengths, frames[6].wavelengths)
        np.testing.assert_array_equal(back[1].truth.curvature, frames[6].truth.curvature)


def test_flushes_are_visible_to_a_reader_while_recording(tmp_path):
    path = tmp_path / "growing.h5"
    frames = synthetic_frames(300)
    rec = Recorder(path, flush_frames=100, flush_interval=3600)
    rec.append(frames[:50])
    assert rec.frames_written == 0  # buffered, not yet due
    rec.append(frames[50:150])
    assert rec.frames_written == 150
    with open_recording(path) as r:  # opened in SWMR mode while the writer is live
        assert len(r) == 150 and not r.complete
        rec.append(frames[150:300])
        assert r.refresh() == 300
        np.testing.assert_array_equal(r.frames(290, 300).sequence, np.arange(290, 300))
    rec.close()


def test_a_frame_of_another_shape_is_refused_after_flushing(tmp_path):
    path = tmp_path / "shape.h5"
    rec = Recorder(path)
    rec.append(synthetic_frames(10))
    with pytest.raises(ValueError, match="18 gratings × 7 cores, the recording 18 × 4"):
        rec.append(synthetic_frames(3, cores=7))
    rec.close()
    with open_recording(path) as r:
        assert len(r) == 10


@pytest.mark.parametrize("kill_after", [1500, 4000])
def test_a_killed_recorder_leaves_everything_up_to_its_last_flush(tmp_path, kill_after):
    """`twin live --record` in a subprocess, SIGKILLed mid-run: the file opens, and holds a contiguous run of
    frames from the first (at least all that a reader had seen before the kill) with nothing corrupt."""
    path = tmp_path / "killed.h5"
    proc = subprocess.Popen([*TWIN, "live", "synthetic://?rate=4000&cores=7", "--record", str(path), "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV)
    try:
        seen = 0

        def enough():
            nonlocal seen
            try:
                with open_recording(path) as r:
                    seen = len(r)
            except (OSError, ValueError, KeyError):
                return False
            return seen >= kill_after

        assert wait_until(enough, timeout=90), proc.stderr.read() if proc.poll() is not None else ""
        time.sleep(0.13)  # kill somewhere between flushes (or inside one)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    with open_recording(path) as r:
        n = len(r)
        assert not r.complete and n >= seen
        a = r.frames()
        np.testing.assert_array_equal(a.sequence, np.arange(n))
        assert np.isfinite(a.wavelengths).all()
        want = synthetic_frames(n, cores=7, rate=4000)
        np.testing.assert_array_equal(a.wavelengths, np.stack([f.wavelengths for f in want]))
        assert r.fiber.n_cores == 7
    out = summarize(path).as_dict()
    assert out["frames"] == n and out["lost_samples"] == 0 and not out["complete"]
    assert any("not closed cleanly" in note for note in out["notes"])


# ---------------------------------------------------------------------------------------- ILLumiSense logs

LOG_HEADER = "Date\tTime\tSample\tChannels\t(ILLumiSense export)\r\n"
EXAMPLE_LINE = ("2024-01-31\t13:45:12.345\t1042\t1\t1\t3\t0\t0\t0\t0\t1530.1234\t1535.5678\t1540.9012\t-20.50\t-21.00"
                "\t-19.75\t3\t12.3\t-4.5\t0.0\r\n")  # docs/protocols.md §1, as one log line


def test_vendor_log_with_header_bad_line_and_decimal_comma(tmp_path):
    frames = synthetic_frames(5, drop=0.2, seed=4)
    lines = [illumisense.encode_payload(f).decode() for f in frames]
    lines[3] = lines[3].replace(".", ",")  # a European-locale export
    bad = lines[1][:40] + "\tnot-a-number\r\n"
    text = LOG_HEADER + "".join([lines[0], bad, *lines[1:]])
    path = tmp_path / "export.txt"
    path.write_text(text)
    with open_recording(path) as r:
        assert r.kind == "illumisense-log" and len(r) == 5 and r.fiber is None
        assert len(r.errors) == 1 and r.errors[0].startswith("line 3:")
        a = r.frames()
        np.testing.assert_array_equal(a.sequence, np.arange(5))
        np.testing.assert_allclose(a.wavelengths, np.stack([f.wavelengths for f in frames]), atol=5e-5 + 1e-9,
                                   rtol=0)
        np.testing.assert_array_equal(np.isnan(a.wavelengths), np.stack([np.isnan(f.wavelengths) for f in frames]))
    out = summarize(path).as_dict()
    assert out["frames"] == 5 and out["skipped_lines"] == 1 and out["kind"] == "illumisense-log"


def test_vendor_log_hand_written_example(tmp_path):
    path = tmp_path / "one.txt"
    path.write_text(LOG_HEADER + EXAMPLE_LINE)
    with open_recording(path) as r:
        a = r.frames()
    assert a.wavelengths.shape == (1, 3, 1) and a.sequence.tolist() == [1042]
    np.testing.assert_array_equal(a.wavelengths[0, :, 0], [1530.1234, 1535.5678, 1540.9012])
    np.testing.assert_array_equal(a.powers[0, :, 0], [-20.5, -21.0, -19.75])
    with pytest.raises(ValueError, match="neither a twin HDF5 recording nor an ILLumiSense log"):
        (tmp_path / "junk.txt").write_text("hello\nworld\n")
        open_recording(tmp_path / "junk.txt")


# ------------------------------------------------------------------------------------------------ replay


def _record(path: Path, n: int = 400, **kw) -> list[Frame]:
    frames = synthetic_frames(n, **kw)
    with Recorder(path, fiber=FiberModel.paper(), rate=1000) as rec:
        rec.append(frames)
    return frames


def test_replay_source_at_max_and_recorded_speed(tmp_path):
    path = tmp_path / "r.h5"
    frames = _record(path)
    src = open_source(f"replay://{path}?speed=max")
    got = list(src)
    assert [f.sequence for f in got] == list(range(400))
    np.testing.assert_array_equal(got[17].truth.positions, frames[17].truth.positions)
    with pytest.raises(SourceClosed):
        src.read()
    src = open_source(f"replay://{path}?speed=4")
    assert src.fiber is not None and len(singles(src.read_batch(1000, timeout=5))) >= 1  # paced: only what is due
    src.close()
    with pytest.raises(ValueError, match="speed"):
        open_source(f"replay://{path}?speed=fast")


def test_live_loop_over_replay_reproduces_the_recording(tmp_path):
    path = tmp_path / "r.h5"
    _record(path, drop=0.03)
    src = open_source(f"replay://{path}?speed=max")
    summary = LiveLoop(src, Reconstructor(src.fiber), []).run()
    assert summary.status.frames == 400 and summary.reason == "source ended"
    out = summarize(path).as_dict()
    assert out["frames_partial"] == summary.status.frames_partial
    assert out["invalid_nodes"] == summary.status.invalid_nodes


def test_twin_replay_reports_errors_against_truth(tmp_path):
    path = tmp_path / "r.h5"
    _record(path, n=600)
    proc = subprocess.run([*TWIN, "replay", str(path), "--json", "--compare-rate", "0"], capture_output=True,
                          text=True, env=ENV, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["frames"] == 600 and out["complete"] and out["truth"]["frames_compared"] == 600
    # the synthetic frames are quantised to 0.1 pm: curvature noise ≈ 1e-4/1550/2.9e-5 ≈ 2e-3 1/m, a few µm
    # of position error over 170 mm; 0.02 mm allows ten times that
    assert out["truth"]["max_error_mm"] < 0.02
    bad = subprocess.run([*TWIN, "replay", str(path), "--fiber", str(tmp_path / "nope.toml")], capture_output=True,
                         text=True, env=ENV, timeout=120)
    assert bad.returncode == 2 and "no such fibre model file" in bad.stderr


def test_replay_with_the_wrong_fiber_is_a_clear_error(tmp_path):
    path = tmp_path / "r7.h5"
    with Recorder(path) as rec:
        rec.append(synthetic_frames(5, cores=7))
    with pytest.raises(ValueError, match="7 cores but the fibre model has 18 × 4"):
        summarize(path).as_dict()


def test_synthetic_source_recording_keeps_truth_shape(tmp_path):
    path = tmp_path / "t.h5"
    src = SyntheticSource(pace=False, frames=100, cores=7, gratings=10)
    with Recorder(path, fiber=src.fiber) as rec:
        rec.append(list(src))
    with open_recording(path) as r:
        assert r.truth().positions.shape == (100, 91, 3) and r.shape == (10, 7)


def test_replay_follows_a_recording_that_is_still_being_written(tmp_path):
    path = tmp_path / "growing.h5"
    frames = synthetic_frames(300)
    rec = Recorder(path, fiber=FiberModel.paper(), flush_frames=50)
    rec.append(frames[:100])
    src = open_source(f"replay://{path}?speed=max&follow=1")
    got = []
    try:
        while len(got) < 100:
            got += singles(src.read_batch(timeout=0.5))
        assert src.read(0.2) is None  # at the end of what was written: waits instead of ending
        rec.append(frames[100:])
        rec.close()  # complete: the source ends after the rest
        got += list(src)
    finally:
        src.close()
    assert [f.sequence for f in got] == list(range(300))
