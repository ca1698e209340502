"""The figures the tool prints follow docs/figures.md, whatever path the frames take: ``twin live replay://F`` and
``twin replay F`` report the same counts and errors, for an HDF5 and an MCAP recording of the same frames alike
(and the two files the same figures); the frames compared with a reference do not depend on how the frames were
batched; the tip error and the max error are what their definitions say (an analytic case where the tip error
exceeds the max distance to the true curve); ``twin live`` reports the error against a truth."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from io_helpers import synthetic_frames

from twin import Reconstructor
from twin.frames import Frame, Shape, Truth, VendorSensor
from twin.io.illumisense.vendor import vendor_sensors
from twin.io.record import Recorder, open_recording
from twin.io.rosbag import McapRecorder
from twin.io.source import open_source
from twin.live import Counts, LiveLoop
from twin.reference_errors import TruthError, TubeFigures, VendorDistance
from twin.synthetic import multicore_fiber
from twin.uncertainty import Uncertainty, inside, truth_in_base

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg"}
FIBER = multicore_fiber(4, 18)  # the synthetic source's default sensor
COUNTS = tuple(f.name for f in dataclasses.fields(Counts))  # every count, as the loop defines them


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """300 noisy frames at 100 Hz with their truth, dropped peaks, a gap, and the interrogator's own shape (ours
    moved by a smooth bend of up to 0.5 mm, so the distance is not zero) on most frames."""
    frames = synthetic_frames(310, rate=100, noise=0.003, drop=0.02, seed=3)
    frames = frames[:100] + frames[110:]  # 10 samples lost
    shapes = Reconstructor(FIBER)(np.stack([f.wavelengths for f in frames]))
    own = vendor_sensors(shapes)
    out = []
    for i, (f, v) in enumerate(zip(frames, own, strict=True)):
        s = v.s
        bent = v.positions + np.stack([0 * s, 0.5e-3 * (s / s[-1]) ** 2, 0 * s], axis=-1)
        blocks = None if i % 9 == 4 else (VendorSensor(v.curvature, v.angle, bent, v.spacing),)
        out.append(Frame(f.wavelengths, f.timestamp, f.sequence, f.powers, f.status, f.truth, blocks))
    path = tmp_path_factory.mktemp("figures") / "run.h5"
    with Recorder(path, fiber=FIBER, rate=100) as rec, McapRecorder(path.with_suffix(".mcap"), fiber=FIBER,
                                                                     rate=100) as mcap:
        for i in range(0, len(out), 37):
            rec.append(out[i : i + 37])
            mcap.append(out[i : i + 37])
    return path


def _live_and_replay(path, *options: str) -> tuple[dict, dict]:
    live = subprocess.run([*TWIN, "live", f"replay://{path}?speed=max", "--json", "--quiet", *options],
                          capture_output=True, text=True, env=ENV, timeout=300)
    replay = subprocess.run([*TWIN, "replay", str(path), "--json", *options], capture_output=True, text=True,
                            env=ENV, timeout=300)
    assert live.returncode == 0 and replay.returncode == 0, live.stderr + replay.stderr
    return json.loads(live.stdout), json.loads(replay.stdout)


@pytest.mark.parametrize("suffix", [".h5", ".mcap"])
def test_live_over_a_recording_and_replay_report_the_same_figures(recording, suffix):
    """For the HDF5 and the MCAP recording of the same frames alike: the figures of both paths agree, and
    (their frames being the same) with the other file's."""
    a, b = _live_and_replay(recording.with_suffix(suffix))
    assert {k: a[k] for k in COUNTS} == {k: b[k] for k in COUNTS}
    # a key both print means the same on both paths: only the wall-clock throughput may differ
    common = (set(a) & set(b)) - {"processing_frames_per_s"}
    assert {k: a[k] for k in common} == {k: b[k] for k in common}
    # no key names another command's different figure: `twin bench`'s stream figures (the live path's speed,
    # compiled, best window) are not this run's (first-call compilation and the machine's load included)
    import twin.stream_bench

    bench = set(re.findall(r"``(\w+_per_s)``", twin.stream_bench.__doc__))
    assert "reconstruct_frames_per_s" in bench and not bench & (set(a) | set(b))
    # the source rate over the last 2 s of timestamps (no gap there), and the whole recording's under its own name
    assert a["rate_hz"] == 100.0 and b["recorded_rate_hz"] == round(299 / 3.09, 3) and "rate_hz" not in b
    assert a["frames"] == 300 and a["lost_samples"] == 10 and a["frames_partial"] > 0
    # one frame per 0.1 s of the recording's 3.1 s (less the 0.1 s gap): about 30, the same on both paths
    assert a["truth"] == b["truth"] and 25 <= a["truth"]["frames_compared"] <= 32
    vendor = ("vendor_frames_compared", "vendor_distance_max_mm", "vendor_distance_mean_mm")
    assert {k: a[k] for k in vendor} == {k: b[k] for k in vendor}
    assert 0.05 < a["vendor_distance_max_mm"] < 0.5 and a["vendor_frames_compared"] >= 20
    # the confidence tube on the same frames, the same on both paths (docs/figures.md)
    tube = ("tube_frames", "mean_sigma_mm", "tube_truth_frames", "coverage_95", "tube_twist_rad_per_m", "tube_caveat")
    assert {k: a[k] for k in tube} == {k: b[k] for k in tube}
    assert 25 <= a["tube_frames"] <= 32 and a["tube_truth_frames"] == a["tube_frames"]
    assert a["mean_sigma_mm"] > 0 and 0.0 <= a["coverage_95"] <= 1.0
    assert a["tube_twist_rad_per_m"] == 0.0 and "states no 1σ" in a["tube_caveat"]  # no calibration recorded
    # the text says what its frames/s measure (docs/figures.md)
    text = subprocess.run([*TWIN, "replay", str(recording.with_suffix(suffix))], capture_output=True, text=True,
                          env=ENV, timeout=300)
    assert "reconstruction throughput" in text.stdout and "frames ÷ wall time spent reconstructing" in text.stdout
    assert "tip to the true tip" in text.stdout and "distance to the true curve" in text.stdout
    if suffix == ".mcap":
        other = json.loads(subprocess.run([*TWIN, "replay", str(recording), "--json"], capture_output=True,
                                          text=True, env=ENV, timeout=300).stdout)  # the HDF5 recording's
        figures = (*COUNTS, "truth", *vendor, "time_span", "recorded_rate_hz")
        assert {k: b[k] for k in figures} == {k: other[k] for k in figures}


@pytest.mark.parametrize(("max_batch", "per_second"), [(1, None), (7, None), (256, None), (1, 10.0), (7, 10.0)])
def test_the_frames_compared_do_not_depend_on_the_batching(recording, max_batch, per_second):
    truth, vendor = TruthError(per_second=per_second), VendorDistance(per_second=per_second)
    reference = TruthError(per_second=per_second), VendorDistance(per_second=per_second)
    LiveLoop(open_source(f"replay://{recording}?speed=max"), Reconstructor(FIBER), [truth, vendor],
             max_batch=max_batch).run(handle_signals=False)
    LiveLoop(open_source(f"replay://{recording}?speed=max"), Reconstructor(FIBER), list(reference),
             max_batch=300).run(handle_signals=False)
    assert truth.result() == reference[0].result()
    assert vendor.as_dict() == reference[1].as_dict()
    # every complete frame carrying sensor 0's block: an independent count from the recording itself
    with open_recording(recording) as r:
        frames = r.frames()
        present = r.vendor()[0].present
    complete = Reconstructor(FIBER)(frames.wavelengths).all_valid
    eligible = complete & present
    if per_second is None:
        assert vendor.frames_compared == int(np.count_nonzero(eligible))
    else:  # the first eligible frame of each 0.1 s slot of the timestamps
        slots = np.floor(frames.timestamp[eligible] * per_second)
        assert vendor.frames_compared == np.unique(slots).size


def test_tip_error_and_max_error_follow_their_definitions():
    """A straight reconstruction 10 % too short against a straight truth: every registered point lies on the
    true line (max distance to the true curve 0), but the tip is 5 % of the length from the true tip at the same
    arc length (Kabsch centres the two: the shift is 0.05 L)."""
    L, n = 0.2, 201
    s = np.linspace(0.0, L, n)
    line = np.stack([0 * s, 0 * s, s], axis=-1)
    short = np.stack([0 * s, 0 * s, 0.9 * s], axis=-1)
    frames_ = np.broadcast_to(np.eye(3), (n, 3, 3))
    shapes = Shape(s=s, positions=short[None], frames=frames_[None], curvature=np.zeros((1, 3, 2)),
                   grating_s=s[[0, 100, 200]], valid=np.ones((1, 3), bool))
    truth = Truth(s=s, positions=line[None], frames=frames_[None], curvature=np.zeros((1, 3, 2)),
                  twist=np.zeros((1, 3)), temperature=np.zeros((1, 3)))
    batch = Frame(np.full((1, 3, 1), 1550.0), truth=truth)
    sink = TruthError()
    sink(batch, shapes, None)
    r = sink.result()
    assert r.frames_compared == 1
    assert r.max_error_mm == pytest.approx(0.0, abs=1e-9) and r.mean_error_mm == pytest.approx(0.0, abs=1e-9)
    assert r.tip_error_mm_max == pytest.approx(0.05 * L * 1e3, rel=1e-9)


def test_twin_live_reports_the_error_against_the_truth():
    out = subprocess.run([*TWIN, "live", "synthetic://?pace=max&frames=400&rate=100&noise=0.002", "--json",
                          "--print-rate", "1000"], capture_output=True, text=True, env=ENV, timeout=300)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    t = summary["truth"]
    # 400 frames at 100 Hz: 4 s of source time, one frame per 0.1 s slot (41 when the first starts mid-slot)
    assert summary["frames_complete"] == 400 and t["frames_compared"] in (40, 41) and t["register"] == "kabsch"
    assert 0 < t["mean_error_mm"] <= t["max_error_mm"] < 1.0
    assert "vs truth max" in out.stderr  # the status lines (on stderr with --json)
    text = subprocess.run([*TWIN, "live", "synthetic://?pace=max&frames=100&rate=5", "--quiet"],
                          capture_output=True, text=True, env=ENV, timeout=300)
    assert "vs truth (100 frames, kabsch)" in text.stdout  # 5 Hz: each frame in its own 0.1 s slot


def test_the_tube_figures_are_what_their_definitions_say(recording):
    """mean_sigma_mm and coverage_95 recomputed from the recording itself: the first complete frame of each 0.1 s
    slot, propagated by Uncertainty, σ averaged over the points with s > 0, the truth placed by its own base pose
    (no registration) and counted inside the 95 % tube point by point; batching does not change them."""
    got = []
    for max_batch in (1, 300):
        sink = TubeFigures(Uncertainty(Reconstructor(FIBER)))
        LiveLoop(open_source(f"replay://{recording}?speed=max"), Reconstructor(FIBER), [sink],
                 max_batch=max_batch).run(handle_signals=False)
        got.append(sink.as_dict())
    assert got[0] == got[1]
    with open_recording(recording) as r:
        frames = r.frames()
    rec = Reconstructor(FIBER)
    shapes = rec(frames.wavelengths)
    slots = np.floor(frames.timestamp * 10.0)
    ok = np.flatnonzero(shapes.all_valid)
    first = ok[np.concatenate([[True], slots[ok][1:] != slots[ok][:-1]])]
    out = Uncertainty(rec).propagate(shapes[first], frames.wavelengths[first])
    distal = out.s > 0
    t = frames.truth
    truth = truth_in_base(t.s, t.positions[first], t.frames[first, 0], t.positions[first, 0], out.s)
    assert got[0]["tube_frames"] == first.size
    assert got[0]["mean_sigma_mm"] == pytest.approx(out.sigma[:, distal].mean() * 1e3, abs=1e-4)
    assert got[0]["coverage_95"] == pytest.approx(inside(out, truth)[:, distal].mean(), abs=1e-4)


def test_twist_states_the_unmeasured_twist_of_the_tube_on_both_paths(recording):
    """``--twist RATE`` sets the tube's model error's twist term, rad/m: shown as ``tube_twist_rad_per_m``, the
    same tube on both paths, as wide as Uncertainty.with_twist makes it (wider than without: the arcs bend), and
    the calibration's caveat kept (the rest of the model error is still the default's)."""
    a, b = _live_and_replay(recording, "--twist", "0.82")
    tube = ("tube_frames", "mean_sigma_mm", "tube_truth_frames", "coverage_95", "tube_twist_rad_per_m", "tube_caveat")
    assert {k: a[k] for k in tube} == {k: b[k] for k in tube}
    assert a["tube_twist_rad_per_m"] == 0.82 and "states no 1σ" in a["tube_caveat"]
    sink = TubeFigures(Uncertainty(Reconstructor(FIBER)).with_twist(0.82))
    LiveLoop(open_source(f"replay://{recording}?speed=max"), Reconstructor(FIBER), [sink]).run(handle_signals=False)
    assert a["mean_sigma_mm"] == sink.as_dict()["mean_sigma_mm"]
    plain = json.loads(subprocess.run([*TWIN, "replay", str(recording), "--json"], capture_output=True, text=True,
                                      env=ENV, timeout=300).stdout)
    assert a["mean_sigma_mm"] > 1.5 * plain["mean_sigma_mm"]


@pytest.mark.parametrize("command", ["live", "replay"])
@pytest.mark.parametrize(("options", "says"), [
    (["--twist", "-1"], "--twist must be a finite twist rate in rad/m >= 0 (0.82: the twin's sheath), got -1.0"),
    (["--twist", "nan"], "--twist must be a finite twist rate in rad/m >= 0 (0.82: the twin's sheath), got nan"),
    (["--twist", "inf"], "--twist must be a finite twist rate in rad/m >= 0 (0.82: the twin's sheath), got inf"),
    (["--twist", "1", "--method", "paper"],
     "--twist 1: the confidence tube it widens covers the material method only, not --method paper"),
])
def test_a_bad_twist_is_one_clear_line(recording, command, options, says):
    where = f"replay://{recording}?speed=max" if command == "live" else str(recording)
    quiet = ["--quiet"] if command == "live" else []
    out = subprocess.run([*TWIN, command, where, "--json", *quiet, *options],
                         capture_output=True, text=True, env=ENV, timeout=300)
    assert out.returncode == 2 and not out.stdout
    assert out.stderr.strip() == f"twin {command}: error: {says}"
    # not a number: argparse's own message for every number option, naming the option
    out = subprocess.run([*TWIN, command, where, "--json", *quiet, "--twist", "fast"], capture_output=True, text=True,
                         env=ENV, timeout=300)
    assert out.returncode == 2 and out.stderr.strip().splitlines()[-1] == (
        f"twin {command}: error: argument --twist: invalid float value: 'fast'")


def test_twist_on_replay_without_json_is_refused(recording):
    """Without --json twin replay computes no tube: a --twist there would be ignored, so it is an error."""
    out = subprocess.run([*TWIN, "replay", str(recording), "--twist", "0.5"], capture_output=True, text=True,
                         env=ENV, timeout=300)
    assert out.returncode == 2 and out.stderr.strip() == (
        "twin replay: error: --twist 0.5: the confidence tube it widens is reported with --json only")
