"""MCAP / rosbag2 recordings (issue 22): `twin live --record x.mcap` writes a file that two independent readers —
rosbags' rosbag2 reader and `mcap` with `mcap-ros2-support` — open as a ROS 2 bag, with every frame, monotonic
stamps and shapes equal to those `twin replay` reconstructs from the recorded wavelengths; `twin replay x.mcap`
and `twin replay x.h5` of one run print the same figures; damaged files are reported in one line, salvaged up
to the damage, never hang.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from twin import so3
from twin.cli import main
from twin.io.errors import RecordingDamaged
from twin.io.record import open_recording
from twin.io.rosbag import McapRecorder
from twin.reconstruct import Reconstructor
from twin.replay_summary import summarize

N = 240  # frames of the recorded run
URL = f"synthetic://?frames={N}&rate=400&drop=0"  # paced: batches of ~20 frames, several chunks
TOPICS = {"/fbg/wavelengths", "/catheter/shape", "/catheter/tip", "/catheter/truth"}


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """One `twin live` run recorded to MCAP and HDF5 at once."""
    d = tmp_path_factory.mktemp("run")
    code = main(["live", URL, "--record", str(d / "x.mcap"), "--record", str(d / "x.h5"), "--quiet", "--json"])
    assert code == 0
    return d


@pytest.fixture(scope="module")
def replayed(run) -> tuple:
    """What `twin replay` reconstructs from the MCAP recording's wavelengths (its fibre and calibration)."""
    with open_recording(run / "x.mcap") as r:
        frames = r.frames()
        rec = Reconstructor(r.fiber, r.calibration)
    return frames, rec(frames.wavelengths)


def _stamp(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _check_topics(by_topic: dict, frames, shapes) -> None:
    """Every frame on every topic, monotonic stamps equal to the frames' timestamps, shapes as replayed."""
    assert set(by_topic) == TOPICS
    for topic, msgs in by_topic.items():
        assert len(msgs) == N, topic
        stamps = np.array([_stamp(m.header) for m in msgs])
        assert np.all(np.diff(stamps) > 0), f"{topic}: stamps not increasing"
        want = np.rint(frames.timestamp * 1e9).astype(np.int64)
        assert np.array_equal(stamps, want), topic
    path = by_topic["/catheter/shape"]
    pos = np.array([[[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in m.poses] for m in path])
    quat = np.array([[[p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w]
                      for p in m.poses] for m in path])
    assert pos.shape == shapes.positions.shape
    assert np.max(np.abs(pos - shapes.positions)) <= 1e-9
    # the orientation is the material frame [d1 d2 d3]
    assert np.max(np.abs(so3.from_quaternion(quat) - shapes.frames)) <= 1e-9
    assert {m.header.frame_id for m in path} == {"fiber_base"}
    tip = by_topic["/catheter/tip"]
    assert np.max(np.abs(np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in tip])
                         - shapes.positions[:, -1])) <= 1e-9
    w = by_topic["/fbg/wavelengths"]
    assert np.array_equal(np.array([m.wavelengths for m in w]).reshape(frames.wavelengths.shape), frames.wavelengths)
    assert np.array_equal([m.sequence for m in w], frames.sequence)
    assert {m.n_gratings for m in w} == {frames.wavelengths.shape[1]}


def test_rosbags_reads_the_recording_as_a_rosbag2(run, replayed):
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    frames, shapes = replayed
    # rosbags' rosbag2 reader (the storage layer: profile, channels, QoS, counts)
    with Reader(run / "x.mcap") as bag:
        counts = {t: i.msgcount for t, i in bag.topics.items()}
        assert counts == dict.fromkeys(TOPICS, N)
        assert {c.ext.serialization_format for c in bag.connections} == {"cdr"}
        assert all(c.ext.offered_qos_profiles for c in bag.connections)
    # and its deserialiser, with the types taken from the file's own schemas (no type is known beforehand)
    by_topic: dict[str, list] = {}
    with AnyReader([run / "x.mcap"], default_typestore=get_typestore(Stores.EMPTY)) as r:
        for conn, _, raw in r.messages():
            by_topic.setdefault(conn.topic, []).append(r.deserialize(raw, conn.msgtype))
    _check_topics(by_topic, frames, shapes)


def test_mcap_with_ros2_support_reads_the_recording(run, replayed):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    frames, shapes = replayed
    by_topic: dict[str, list] = {}
    with open(run / "x.mcap", "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for _, channel, _, msg in reader.iter_decoded_messages(log_time_order=False):
            by_topic.setdefault(channel.topic, []).append(msg)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = {a.name for a in reader.iter_attachments()}
    _check_topics(by_topic, frames, shapes)
    bag = json.loads(meta["rosbag2"]["serialized_metadata"])["rosbag2_bagfile_information"]
    assert bag["storage_identifier"] == "mcap" and bag["message_count"] == 4 * N
    assert meta["catheter_twin"]["format"] == "twin-mcap"
    assert "fiber.toml" in attachments


def test_recorded_frames_equal_the_hdf5_recording_of_the_same_run(run):
    with open_recording(run / "x.mcap") as m, open_recording(run / "x.h5") as h:
        assert m.complete and not m.damaged and len(m) == len(h) == N
        a, b = m.frames(), h.frames()
        for name in ("wavelengths", "timestamp", "sequence", "status"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert np.array_equal(a.truth.positions, b.truth.positions)
        assert np.array_equal(m.truth().s, h.truth().s)
        assert m.fiber.to_dict() == h.fiber.to_dict()
        assert m.rate == h.rate


def _figures(path: Path, capsys) -> list[str]:
    assert main(["replay", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    # the first line names the file and its kind; the speed line is the machine's, not the run's
    return [lines[0].split(",", 1)[1]] + [x for x in lines[1:] if "reconstruction throughput" not in x]


def test_twin_replay_prints_the_same_figures_for_mcap_and_hdf5(run, capsys):
    m, h = _figures(run / "x.mcap", capsys), _figures(run / "x.h5", capsys)
    assert m == h
    assert any("vs truth" in x for x in m)
    sm, sh = summarize(run / "x.mcap").as_dict(), summarize(run / "x.h5").as_dict()
    for k in ("file", "kind", "processing_frames_per_s"):
        sm.pop(k), sh.pop(k)
    assert sm == sh


def test_replay_url_plays_an_mcap_recording(run, capsys):
    assert main(["live", f"replay://{run / 'x.mcap'}?speed=max", "--quiet", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == N and out["reason"] == "source ended" and out["frames_complete"] == N


def test_export_writes_the_hdf5_recording_as_mcap(run, tmp_path, capsys):
    out = tmp_path / "e.mcap"
    assert main(["export", str(run / "x.h5"), str(out)]) == 0
    capsys.readouterr()
    assert _figures(out, capsys) == _figures(run / "x.h5", capsys)
    with open_recording(out) as r, open_recording(run / "x.mcap") as live:
        assert np.array_equal(r.frames().wavelengths, live.frames().wavelengths)


# ------------------------------------------------------------------------------------------------ damage
def _twin(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twin.cli", *args], capture_output=True, text=True, timeout=120)


def _inside_chunk(path: Path, k: int) -> int:
    """A byte offset in the middle of the k-th chunk record of an MCAP file."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as fh:
        start, seen = fh.tell(), 0
        for rec in StreamReader(fh, emit_chunks=True).records:
            end = fh.tell()
            if isinstance(rec, Chunk):
                if seen == k:
                    return (start + end) // 2
                seen += 1
            start = end
    raise AssertionError(f"{path}: fewer than {k + 1} chunks")


def test_a_cut_file_is_reported_in_one_line_and_salvaged_up_to_the_damage(run, tmp_path):
    data = (run / "x.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: _inside_chunk(run / "x.mcap", 1)])  # inside the second chunk: later frames are lost
    out = _twin("replay", str(cut))
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and str(cut) in lines[0] and "cut short at byte" in lines[0], out.stderr
    out = _twin("replay", str(cut), "--salvage", "--json")
    assert out.returncode == 0, out.stderr
    s = json.loads(out.stdout)
    assert s["damaged"] and 0 < s["frames"] < N and s["truth"]["frames_compared"] > 0
    # replay:// ends with "source failed" instead of replaying it as complete
    out = _twin("live", f"replay://{cut}?speed=max", "--quiet", "--json")
    assert out.returncode in (1, 2) and "damaged recording" in out.stderr


def test_a_chunk_failing_its_crc_is_damage_at_its_byte(run, tmp_path):
    with open_recording(run / "x.mcap") as good:
        n_good = len(good)
    data = bytearray((run / "x.mcap").read_bytes())
    mid = _inside_chunk(run / "x.mcap", 1)  # flip bytes inside the second chunk's compressed data
    data[mid:mid + 16] = bytes(b ^ 0xFF for b in data[mid:mid + 16])
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with open_recording(bad) as r:
        assert r.damaged and not r.complete and len(r) < n_good
        assert "chunk at byte" in r.damage[0] or "unreadable record at byte" in r.damage[0]
    with pytest.raises(RecordingDamaged, match=str(bad)):
        summarize(bad)


def test_a_killed_writer_leaves_a_readable_file_not_closed_cleanly(run, tmp_path):
    with open_recording(run / "x.mcap") as r:
        frames, fiber = r.frames(), r.fiber
    path = tmp_path / "killed.mcap"
    rec = McapRecorder(path, fiber=fiber, rate=200)
    rec.append(frames[:100])
    rec.flush()
    snapshot = tmp_path / "snapshot.mcap"
    shutil.copyfile(path, snapshot)  # the file as a kill at this instant leaves it
    rec.append(frames[100:])
    rec.close()
    with open_recording(snapshot) as r:
        assert not r.damaged and not r.complete and len(r) == 100
    s = summarize(snapshot)
    assert s.frames == 100 and any("not closed cleanly" in n for n in s.notes)


def test_truncation_anywhere_never_hangs_or_tracebacks(run, tmp_path):
    data = (run / "x.mcap").read_bytes()
    rng = np.random.default_rng(7)
    offsets = sorted({0, 1, 7, 8, 9, 40, *rng.integers(10, len(data), 24).tolist()})
    for cut in offsets:
        p = tmp_path / f"c{cut}.mcap"
        p.write_bytes(data[:cut])
        try:
            with open_recording(p) as r:
                assert r.damaged or not r.complete or cut == len(data)
                r.frames()
        except (ValueError, OSError) as exc:  # not a recording at all: one line naming the file
            assert str(exc).startswith(str(p)) and "\n" not in str(exc), (cut, exc)


def test_an_mcap_file_that_is_not_a_twin_recording_is_one_line(tmp_path):
    from mcap.writer import Writer

    p = tmp_path / "other.mcap"
    with open(p, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        w.finish()
    out = _twin("replay", str(p))
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and "not a twin recording" in out.stderr


def test_the_interrogators_own_shape_round_trips_and_is_compared_like_hdf5s(run, tmp_path):
    """Sensor blocks (two sensors, on every other frame) come back per sensor, and replay reports the same
    vendor distance for the MCAP and the HDF5 recording of the same frames."""
    from dataclasses import replace

    from twin.io.illumisense.vendor import vendor_sensors
    from twin.io.record import Recorder

    with open_recording(run / "x.mcap") as r:
        frames, fiber = r.frames(0, 60), r.fiber
        shapes = Reconstructor(fiber, r.calibration)(frames.wavelengths)
    blocks = vendor_sensors(shapes)
    singles = [replace(f, vendor=(blocks[i], blocks[i]) if i % 2 == 0 else None) for i, f in enumerate(frames)]
    with McapRecorder(tmp_path / "v.mcap", fiber=fiber) as m:
        m.append(singles, shapes)
    with Recorder(tmp_path / "v.h5", fiber=fiber) as h:
        h.append(singles)
    with open_recording(tmp_path / "v.mcap") as r, open_recording(tmp_path / "v.h5") as h:
        assert r.has_vendor and len(r.vendor()) == 2
        for a, b in zip(r.vendor(), h.vendor(), strict=True):
            assert np.array_equal(a.present, b.present) and a.present.sum() == 30
            assert np.array_equal(a.positions, b.positions, equal_nan=True)
            assert np.array_equal(a.curvature, b.curvature, equal_nan=True) and a.spacing == b.spacing
    vm, vh = summarize(tmp_path / "v.mcap").vendor, summarize(tmp_path / "v.h5").vendor
    assert vm and vm == vh
    # twin export carries the HDF5 recording's sensor blocks into the bag, per sensor and frame
    assert main(["export", str(tmp_path / "v.h5"), str(tmp_path / "e.mcap"), "--batch", "16"]) == 0
    with open_recording(tmp_path / "e.mcap") as e, open_recording(tmp_path / "v.h5") as h:
        assert len(e.vendor()) == 2
        for a, b in zip(e.vendor(), h.vendor(), strict=True):
            assert np.array_equal(a.present, b.present)
            assert np.array_equal(a.positions, b.positions, equal_nan=True)


# ------------------------------------------------------------------------------------------------ bounded memory
def _records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, offset, length) of an MCAP file's top-level records, from their headers alone."""
    out, at = [], 8
    while at + 9 <= len(data):
        opcode, length = data[at], int.from_bytes(data[at + 1:at + 9], "little")
        out.append((opcode, at, length))
        if opcode == 0x02:  # footer
            break
        at += 9 + length
    return out


@pytest.fixture(scope="module")
def big(run, tmp_path_factory) -> tuple[Path, object]:
    """The run three times over in chunks of 8 KiB: a file about a hundred times the 64 KiB bound the reader
    is given below."""
    with open_recording(run / "x.mcap") as r:
        frames, fiber = r.frames(), r.fiber
    path = tmp_path_factory.mktemp("big") / "big.mcap"
    with McapRecorder(path, fiber=fiber, chunk_size=1 << 13) as w:
        for _ in range(3):
            w.append(frames)
    return path, frames


def test_reading_a_recording_takes_memory_bounded_by_the_record_bound_and_the_slice(big):
    """Opening indexes the file record by record and reading takes a slice at a time: the memory either takes
    stays a small part of the file (the reader held all of it in memory before), and the frames come back
    whole and in order."""
    import tracemalloc

    from twin.io.rosbag import McapRecording

    path, frames = big
    size, bound = path.stat().st_size, 1 << 16
    assert size > 50 * bound
    tracemalloc.start()
    try:
        with McapRecording(path, max_record=bound) as r:
            opened = tracemalloc.get_traced_memory()[1]
            tracemalloc.reset_peak()
            assert r.complete and len(r) == 3 * len(frames)
            n = 0
            for start, batch in r.chunks(4):  # a 4-frame slice takes about 0.3 MB decoded (171 truth points)
                want = frames[np.arange(start, start + len(batch)) % len(frames)]
                assert np.array_equal(batch.wavelengths, want.wavelengths)
                assert np.array_equal(batch.truth.positions, want.truth.positions)
                assert len(r.received(start, start + len(batch))) == len(batch)
                n += len(batch)
            read = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert n == 3 * len(frames)
    assert opened < size / 20 and read < size / 8, (opened, read, size)  # measured: 0.19 and 0.61 MB of 7.1


def _patched(data: bytes, at: int, value: bytes) -> bytes:
    return data[:at] + value + data[at + len(value):]


def test_hostile_lengths_are_damage_at_their_byte_and_allocate_nothing(big, tmp_path):
    """A record claiming more than the file, a chunk claiming an absurd uncompressed size, a record longer than
    the reader's bound, and a chunk that decompresses to more than it declares (an LZ4 bomb): each is damage
    naming its byte, the frames before it are kept, and reading takes no more memory than the bound."""
    import tracemalloc

    import lz4.frame
    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk

    from twin.io.rosbag import McapRecording

    path, _ = big
    data = path.read_bytes()
    chunks = [(at, length) for op, at, length in _records(data) if op == 0x06]
    at, length = chunks[5]
    with McapRecording(path) as whole, McapRecording(_write(tmp_path / "cut.mcap", data[:at + 30])) as cut:
        before = len(cut)  # frames wholly in the first five chunks
        assert 0 < before < len(whole)
    builder = RecordBuilder()
    Chunk(compression="lz4", data=lz4.frame.compress(bytes(100 << 20)), message_start_time=0,
          message_end_time=0, uncompressed_crc=0, uncompressed_size=1000).write(builder)
    bomb = builder.end()
    cases = {
        "absurd.mcap": (_patched(data, at + 1, (1 << 62).to_bytes(8, "little")),
                        f"record at byte {at} claims {1 << 62} bytes, more than the file's"),
        "inflated.mcap": (_patched(data, at + 9 + 16, (1 << 40).to_bytes(8, "little")),
                          f"chunk at byte {at} claims {1 << 40} bytes uncompressed"),
        "bomb.mcap": (data[:at] + bomb + data[at + 9 + length:], f"chunk at byte {at} unreadable (decompresses to"),
    }
    for name, (content, why) in cases.items():
        p = _write(tmp_path / name, content)
        tracemalloc.start()
        try:
            with McapRecording(p) as r:
                assert r.damaged and not r.complete and len(r) == before, (name, r.damage)
                assert r.damage[0].startswith(why), (name, r.damage)
                r.frames()
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 4 * len(data), (name, peak)  # the bomb alone would be 100 MiB
        out = _twin("replay", str(p))
        assert out.returncode == 2 and out.stderr.count("\n") == 1 and str(p) in out.stderr and why in out.stderr
    # a record longer than the reader's bound: damage there, not an allocation of its size
    with McapRecording(path, max_record=4096) as r:
        assert r.damaged and len(r) == 0 and r.damage[0].startswith(f"record at byte {chunks[0][0]} holds")


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def test_sensor_blocks_of_another_layout_are_counted_not_stored(run, tmp_path):
    """A sensor keeps the layout of its first block (G gratings, N points, spacing), as in HDF5 recordings:
    later blocks of another layout are counted in vendor_dropped, and the file reads back undamaged."""
    from dataclasses import replace

    from twin.frames import VendorSensor
    from twin.io.illumisense.vendor import vendor_sensors

    with open_recording(run / "x.mcap") as r:
        frames, fiber = r.frames(0, 40), r.fiber
        shapes = Reconstructor(fiber, r.calibration)(frames.wavelengths)
    blocks = vendor_sensors(shapes)
    short = [VendorSensor(b.curvature, b.angle, b.positions[:-5], b.spacing) for b in blocks]
    first = [replace(f, vendor=(blocks[i],)) for i, f in enumerate(frames[:20])]
    later = [replace(f, vendor=(short[i],)) for i, f in enumerate(frames[20:], 20)]
    with McapRecorder(tmp_path / "v.mcap", fiber=fiber) as m:
        m.append(first)
        m.append(later)  # one batch of the other layout
    assert m.vendor_written == 20 and m.vendor_dropped == 20
    with open_recording(tmp_path / "v.mcap") as r:
        assert not r.damaged and len(r) == 40
        (a,) = r.vendor()
        assert a.present.tolist() == [True] * 20 + [False] * 20
        assert np.array_equal(a.positions[:20], np.stack([b.positions for b in blocks[:20]]))
