"""Corruption fuzz of recordings (issue 11): twin HDF5 recordings (with and without the interrogator's sensor
blocks, issue 13) and ILLumiSense text logs, truncated at random points and with random bytes flipped. For
every case:

- nothing hangs: opening and reading all frames ends within a hang guard (reading these small files takes a
  fraction of a second; the faults guarded against — HDF5's SWMR retries, a reader that loops — take minutes or
  forever; speed is `twin bench`'s, not this test's);
- nothing is "complete" that is damaged: an HDF5 recording read back as complete must equal the original
  exactly, sensor blocks included (a flip can land in bytes HDF5 never reads, e.g. free space; then nothing was
  damaged), and a cut one is never complete; a log cut inside a line is never complete (a log has no checksum:
  a flipped digit that leaves a valid number cannot be detected, so flipped logs are checked for consistent
  accounting only);
- nothing raises but one line: the only errors are ValueError/OSError whose message is one line naming the
  file; the CLI gives exit status 2 with one line, or 0 with ``--salvage``.

The fast suite runs a few dozen seeded cases; ``-m slow`` runs a few hundred.
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from io_helpers import synthetic_frames

from twin import FiberModel
from twin.frames import Frame
from twin.io import illumisense
from twin.io.illumisense import VendorSensor
from twin.io.record import Recorder, open_recording

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg"}
#: s, a hang guard, not a speed limit: HDF5's default SWMR retries on a damaged file sleep for minutes; a normal
#: read of these files takes well under a second even on a loaded machine
LIMIT_S = 60.0


@pytest.fixture(scope="module")
def originals(tmp_path_factory):
    d = tmp_path_factory.mktemp("orig")
    frames = synthetic_frames(300, rate=100, drop=0.02)
    h5 = d / "r.h5"
    with Recorder(h5, fiber=FiberModel.paper(), rate=100) as rec:
        for i in range(0, 300, 40):
            rec.append(frames[i : i + 40])
    rng = np.random.default_rng(5)
    with_blocks = [Frame(f.wavelengths, f.timestamp, f.sequence, f.powers, f.status, f.truth,
                         None if i % 9 == 4 else (VendorSensor(rng.normal(size=18), rng.normal(size=18),
                                                               rng.normal(size=(171, 3))),))
                   for i, f in enumerate(frames)]
    h5v = d / "v.h5"
    with Recorder(h5v, fiber=FiberModel.paper(), rate=100) as rec:
        for i in range(0, 300, 40):
            rec.append(with_blocks[i : i + 40])
    log = d / "r.txt"
    log.write_bytes(b"Date\tTime\tSample\tChannels\r\n" + b"".join(illumisense.encode_payload(f) for f in frames[:60]))
    logv = d / "v.txt"  # with the interrogator's sensor blocks (issue 23: the fuzz extended to the log reader's)
    logv.write_bytes(b"Date\tTime\tSample\tChannels\r\n" + b"".join(
        illumisense.encode_payload(f, sensors=f.vendor or ()) for f in with_blocks[:60]))
    with open_recording(h5) as r:
        full = r.frames()
    with open_recording(h5v) as r:
        (vendor,) = r.vendor()
        assert vendor.present.sum() == 300 - 33
    clean = {}
    for name, path in (("log", log), ("logv", logv)):
        with open_recording(path) as r:
            assert r.complete
            clean[name] = (r.frames(), r.vendor())
    return {"h5": h5, "h5v": h5v, "log": log, "logv": logv, "frames": full, "vendor": vendor, "clean": clean}


def _assert_log_prefix(frames, vendor, clean, info) -> None:
    """Every record read from a cut log is a record of the sound log, in order (issue 23 B5: the cut last record
    was kept, its last number cut short)."""
    want, want_vendor = clean
    k = len(frames)
    assert k <= len(want), info
    for name in ("wavelengths", "sequence", "timestamp", "powers"):
        np.testing.assert_array_equal(getattr(frames, name), getattr(want, name)[:k], err_msg=str(info))
    assert len(vendor) == (len(want_vendor) if k else len(vendor)), info
    for got, ref in zip(vendor, want_vendor, strict=False):
        for name in ("present", "curvature", "angle", "positions"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref[:k], name), err_msg=str(info))


def _damage(src: Path, dst: Path, rng: random.Random, how: str) -> tuple[Path, dict]:
    data = bytearray(src.read_bytes())
    info: dict = {"how": how}
    if how == "cut":
        k = rng.randrange(0, len(data))
        data = data[:k]
        info["cut_at"] = k
    else:
        for _ in range(rng.choice([1, 3, 20, 200])):
            i = rng.randrange(len(data))
            data[i] ^= rng.randrange(1, 256)
    dst.write_bytes(bytes(data))
    info["ends_in_newline"] = bytes(data[-1:]) in (b"\n", b"\r")
    return dst, info


def _check_error(exc: BaseException, path: Path) -> None:
    assert isinstance(exc, ValueError | OSError), f"{type(exc).__name__}: {exc}"
    msg = str(exc)
    assert "\n" not in msg and str(path) in msg, msg


def _read_all(path: Path):
    with open_recording(path) as r:
        frames = r.frames()
        vendor = r.vendor()  # read it all too (damage found there is noted in r.damage)
        return r, frames, vendor


def _case(originals, tmp_path: Path, kind: str, how: str, seed: int) -> None:
    rng = random.Random(seed)
    src = originals[kind]
    path, info = _damage(src, tmp_path / f"case{seed}{src.suffix}", rng, how)
    t0 = time.monotonic()
    try:
        r, frames, vendor = _read_all(path)
    except Exception as exc:  # checked to be a one-line user error
        assert time.monotonic() - t0 < LIMIT_S
        _check_error(exc, path)
        return
    assert time.monotonic() - t0 < LIMIT_S, info
    if kind in ("h5", "h5v"):
        if how == "cut":
            assert not r.complete, info
        if r.complete:
            orig = originals["frames"]
            assert len(frames) == len(orig), info
            np.testing.assert_array_equal(frames.wavelengths, orig.wavelengths)
            np.testing.assert_array_equal(frames.sequence, orig.sequence)
            np.testing.assert_array_equal(frames.timestamp, orig.timestamp)
            np.testing.assert_array_equal(frames.status, orig.status)
            if kind == "h5v":
                (got,), want = vendor, originals["vendor"]
                np.testing.assert_array_equal(got.present, want.present)
                np.testing.assert_array_equal(got.positions, want.positions)
                np.testing.assert_array_equal(got.curvature, want.curvature)
                np.testing.assert_array_equal(got.angle, want.angle)
        else:
            assert r.damaged or not r._closed_cleanly, info
    else:
        if how == "cut" and not info["ends_in_newline"]:
            assert not r.complete and r.damaged, info
        assert len(frames) == len(r)
        if how == "cut":
            _assert_log_prefix(frames, vendor, originals["clean"][kind], info)


FAST = [(kind, how, seed) for kind in ("h5", "log") for how in ("cut", "flip") for seed in range(8)] + [
    (kind, how, seed) for kind in ("h5v", "logv") for how in ("cut", "flip") for seed in range(4)]


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("kind", "how", "seed"), FAST)
def test_damaged_recordings_fail_fast_and_say_so(originals, tmp_path, kind, how, seed):
    _case(originals, tmp_path, kind, how, seed)


@pytest.mark.slow
@pytest.mark.timeout(1200)
@pytest.mark.parametrize(("kind", "how"), [(k, h) for k in ("h5", "h5v", "log", "logv") for h in ("cut", "flip")])
def test_damaged_recordings_many(originals, tmp_path, kind, how):
    for seed in range(100, 250):
        _case(originals, tmp_path, kind, how, seed)


@pytest.mark.parametrize("seed", [1])
def test_cli_on_damaged_files_one_line_or_salvage(originals, tmp_path, seed):
    rng = random.Random(seed)
    for kind, how in (("h5", "cut"), ("h5", "flip"), ("log", "cut")):
        path, info = _damage(originals[kind], tmp_path / f"c{kind}{how}{originals[kind].suffix}", rng, how)
        for extra in ([], ["--salvage"]):
            proc = subprocess.run([*TWIN, "replay", str(path), "--json", *extra], capture_output=True, text=True,
                                  env=ENV, timeout=60)
            assert "Traceback" not in proc.stderr, proc.stderr
            if proc.returncode == 2:
                assert proc.stderr.count("\n") == 1 and path.name in proc.stderr, proc.stderr
            else:
                assert proc.returncode == 0, (info, proc.stderr)
                if not extra:  # without --salvage only a sound file passes
                    assert '"damaged": false' in proc.stdout


@pytest.mark.parametrize("kind", ["log", "logv"])
def test_a_cut_log_never_keeps_its_cut_last_record(originals, tmp_path, kind):
    """Issue 23 B5: a log cut inside its last line kept that record, its last number cut short (with sensor
    blocks, the vendor distance moved from 0.0001 to 0.94 mm). Every cut point of the last two lines."""
    data = originals[kind].read_bytes()
    start = data.rindex(b"\n", 0, data.rindex(b"\n", 0, len(data) - 1)) + 1
    n = len(originals["clean"][kind][0])
    path = tmp_path / "cut.txt"
    for cut in range(start, len(data), 7):
        path.write_bytes(data[:cut])
        with open_recording(path) as r:
            frames, vendor = r.frames(), r.vendor()
            assert r.damaged or data[cut - 1 : cut] in (b"\n", b"\r"), cut
            assert len(frames) in (n - 2, n - 1), cut
        _assert_log_prefix(frames, vendor, originals["clean"][kind], cut)


def test_a_log_with_a_bom_or_mixed_line_ends_reads_as_the_sound_one(originals, tmp_path):
    """Issue 23 B6: a UTF-8 BOM gave the first record a NaN timestamp, no note; CR line ends after an LF-ended
    header line refused the whole file."""
    data = originals["logv"].read_bytes()
    header, _, body = data.partition(b"\r\n")
    lines = body.split(b"\r\n")[:-1]
    variants = {
        "bom": b"\xef\xbb\xbf" + data,
        "bom-no-header": b"\xef\xbb\xbf" + body,
        "cr-after-lf-header": header + b"\n" + b"".join(x + b"\r" for x in lines),
        "mixed": header + b"\r" + b"".join(x + (b"\n", b"\r\n", b"\r")[i % 3] for i, x in enumerate(lines)),
    }
    want, want_vendor = originals["clean"]["logv"]
    for name, content in variants.items():
        path = tmp_path / f"{name}.txt"
        path.write_bytes(content)
        with open_recording(path) as r:
            assert r.complete and not r.errors, (name, r.errors)
            _assert_log_prefix(r.frames(), r.vendor(), (want, want_vendor), name)
            assert len(r) == len(want) and np.isfinite(r.frames().timestamp).all(), name


def _chunks_of(path: Path, prefix: str) -> list[tuple[str, int, int, int]]:
    """(dataset, first row, byte offset, size) of every stored chunk of the datasets under ``prefix``."""
    import h5py

    out = []
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and obj.chunks:
                obj.id.chunk_iter(lambda c: out.append((name, c.chunk_offset[0], c.byte_offset, c.size)))
        f[prefix].visititems(lambda n, o: visit(f"{prefix}/{n}", o))
    return out


@pytest.mark.parametrize("prefix", ["vendor", "truth"])
@pytest.mark.parametrize("seed", range(6))
def test_flips_confined_to_vendor_or_truth_chunks_keep_every_frame(originals, tmp_path, prefix, seed):
    """Issue 23 B7, the fuzz extended to the /vendor groups: bytes flipped inside the chunks of /vendor (or
    /truth) datasets only. Every frame stays readable and exact; the damaged part's rows are the original ones up
    to the damage and absent after it; the damage names a dataset of that part."""
    src = originals["h5v"] if prefix == "vendor" else originals["h5"]
    rng = random.Random(seed)
    name, row, off, size = rng.choice(_chunks_of(src, prefix))
    data = bytearray(src.read_bytes())
    for _ in range(rng.choice([1, 5, 50])):
        data[off + rng.randrange(size)] ^= rng.randrange(1, 256)
    path = tmp_path / "flip.h5"
    path.write_bytes(bytes(data))
    with open_recording(path) as r:
        frames, vendor, truth = r.frames(), r.vendor(), r.truth()
        assert len(frames) == len(originals["frames"]) == len(r)
        np.testing.assert_array_equal(frames.wavelengths, originals["frames"].wavelengths)
        np.testing.assert_array_equal(frames.sequence, originals["frames"].sequence)
        if prefix == "vendor":
            (got,), want = vendor, originals["vendor"]
            keep = got.present
            assert keep.sum() <= want.present.sum()
            np.testing.assert_array_equal(got.positions[keep], want.positions[keep])
            np.testing.assert_array_equal(got.curvature[keep], want.curvature[keep])
        else:
            want = originals["frames"].truth
            assert truth is not None and len(truth.present) == len(frames)
            keep = truth.present
            assert keep.sum() <= want.present.sum()
            np.testing.assert_array_equal(truth.positions[keep], want.positions[keep])
        if r.damaged:  # a flip can leave a chunk's checksum valid only by missing the bytes read: never here
            assert all(d.startswith(f"{prefix}/") for d in r.damage), r.damage
        else:
            pytest.fail(f"{name} chunk at row {row} flipped but nothing was found damaged")
