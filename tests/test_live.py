"""The live loop: bookkeeping (lost samples, partial frames, stale state), recovery from sources that fail, a
server that dies mid-frame, sinks that fail, Ctrl-C, and the load run (ILLumiSense at 1 kHz, 7 × 18).

No timing asserts: waits are generous and only outcomes are checked (speed lives in `twin bench`).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from io_helpers import ScriptedServer, records, synthetic_frames, wait_until

from twin import FiberModel, Reconstructor, strain
from twin.frames import Frame
from twin.io.record import Recorder, open_recording
from twin.io.source import FrameByFrame, Source, SourceClosed, open_source
from twin.live import FrameFlag, LiveLoop, LiveStatus
from twin.synthetic import SyntheticSource

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg", "PYTHONUNBUFFERED": "1"}


class Collect:
    """A sink keeping every status and the frames' sequence numbers."""

    def __init__(self):
        self.statuses: list[LiveStatus] = []
        self.sequences: list[int] = []
        self.flags: list[int] = []
        self.closed = False

    def __call__(self, frames, shapes, status):
        self.statuses.append(status)
        self.sequences += frames.sequence.tolist()
        self.flags += status.flags.tolist()
        if frames:
            assert shapes is not None and shapes.positions.shape[0] == len(frames)

    def close(self):
        self.closed = True


class Skipping(FrameByFrame):
    """Wraps a source and drops the frames whose sequence is in ``skip`` (lost samples)."""

    def __init__(self, inner: Source, skip: set[int]):
        self.inner, self.skip, self.fiber, self.rate = inner, skip, inner.fiber, inner.rate

    def next_frame(self, timeout=None):
        while True:
            f = self.inner.read(timeout)
            if f is None or f.sequence not in self.skip:
                return f


def test_counts_missing_peaks_partial_frames_and_lost_samples():
    inner = SyntheticSource(rate=1000, pace=False, frames=3000, drop=0.08, seed=5)
    skip = {100, 101, 102, 2000}
    sink = Collect()
    loop = LiveLoop(Skipping(inner, skip), Reconstructor(inner.fiber), [sink], max_batch=64)
    summary = loop.run()
    s = summary.status
    assert summary.reason == "source ended" and sink.closed
    assert s.frames == 3000 - len(skip) and s.lost_samples == 4 and s.sequence_gaps == 2
    assert s.frames_complete + s.frames_partial + s.frames_unusable == s.frames
    # independent count: with the paper's layout (central core + 3 outer) a grating is solvable from any 3 of
    # its 4 peaks, and not from fewer
    frames = [f for f in synthetic_frames(3000, drop=0.08, seed=5) if f.sequence not in skip]
    present = np.stack([~np.isnan(f.wavelengths) for f in frames]).sum(axis=-1)  # (n, g)
    assert s.invalid_nodes == int(np.count_nonzero(present < 3))
    assert s.frames_missing_peaks == int(np.count_nonzero((present < 4).any(axis=1)))
    assert s.frames_partial == int(np.count_nonzero((present < 3).any(axis=1) & (present >= 3).any(axis=1)))
    assert s.frames_partial > 0 and s.frames_missing_peaks > s.frames_partial
    flags = np.array(sink.flags)
    assert np.count_nonzero(flags & FrameFlag.PARTIAL) == s.frames_partial
    assert np.count_nonzero(flags & FrameFlag.SEQUENCE_GAP) == 2
    assert sink.sequences == [f.sequence for f in frames]


class Pausing(FrameByFrame):
    """Frames until the sink has seen the loop ``live``, then nothing until it has seen it ``stale``, then frames
    again until ``total`` frames.

    The pause is driven by what the loop reports, not by a clock, so a slow first batch (a cold compile on a
    loaded machine) cannot eat the live phase; ``hang_guard`` s bounds the wait for a stale state that never comes.
    """

    def __init__(self, sink: Collect, total=600, hang_guard=60.0):
        self.inner = SyntheticSource(rate=500, pace=True)
        self.fiber, self.rate = self.inner.fiber, 500.0
        self.sink, self.total, self.hang_guard = sink, total, hang_guard
        self.paused_at = None
        self.resumed = False
        self.n = 0

    def next_frame(self, timeout=None):
        if self.n >= self.total:
            raise SourceClosed("done")
        seen = {s.state for s in self.sink.statuses}
        if not self.resumed and "live" in seen:
            self.paused_at = self.paused_at or time.monotonic()
            if "stale" not in seen:
                assert time.monotonic() - self.paused_at < self.hang_guard, "the loop never went stale"
                time.sleep(min(timeout or 0.05, 0.05))
                return None
            self.resumed = True
        f = self.inner.read(timeout)
        if f is not None:
            self.n += 1
        return f


def test_stale_state_is_entered_reported_and_left():
    sink = Collect()
    loop = LiveLoop(Pausing(sink), Reconstructor(FiberModel.paper()), [sink], stale_after=0.5)
    summary = loop.run(duration=120)  # a hang guard: the run ends when the source has sent its 600 frames
    states = [s.state for s in sink.statuses]
    # live, then stale during the pause (heartbeats reach the sink without frames), then live again
    first_stale = states.index("stale")
    assert "live" in states[:first_stale] and "live" in states[first_stale:]
    stale = [s for s in sink.statuses if s.state == "stale"]
    assert all(s.last_valid_age > 0.5 for s in stale) and all(s.flags.size == 0 for s in stale)
    assert summary.status.stale_events == 1 and summary.status.frames == 600


class Flaky(FrameByFrame):
    """Raises OSError after ``fail_after`` frames (a transport error out of read)."""

    opened = 0

    def __init__(self, fail_after: int, start: int):
        Flaky.opened += 1
        self.inner = SyntheticSource(rate=1000, pace=False)
        self.inner._index = start
        self.fiber, self.rate, self.left = self.inner.fiber, 1000.0, fail_after

    def next_frame(self, timeout=None):
        if self.left == 0:
            raise OSError("link went down")
        self.left -= 1
        return self.inner.read(timeout)


def test_a_source_that_raises_is_reopened_with_backoff():
    Flaky.opened = 0
    starts = iter([0, 50, 100])
    sink = Collect()
    loop = LiveLoop(lambda: Flaky(40, next(starts)), Reconstructor(FiberModel.paper()), [sink])
    summary = loop.run(max_frames=100)
    s = summary.status
    assert Flaky.opened == 3 and s.source_errors == 2 and s.reconnects == 2
    assert s.frames == 100 and s.lost_samples == 20  # 40..49 and 90..99 never came
    assert sink.sequences == [*range(40), *range(50, 90), *range(100, 120)]


def test_a_failing_sink_is_dropped_and_the_recording_goes_on(tmp_path):
    class Bad:
        n = 0

        def __call__(self, frames, shapes, status):
            Bad.n += 1
            if Bad.n == 3:
                raise RuntimeError("viewer crashed")

    src = SyntheticSource(rate=1000, pace=False, frames=500)
    rec = Recorder(tmp_path / "r.h5", fiber=src.fiber)
    summary = LiveLoop(src, Reconstructor(src.fiber), [Bad(), rec], max_batch=50).run()
    assert summary.status.frames == 500 and len(summary.sink_errors) == 1 and "viewer crashed" in summary.sink_errors[0]
    with open_recording(tmp_path / "r.h5") as r:
        assert len(r) == 500 and r.complete


def test_frames_that_do_not_fit_the_fiber_are_a_clear_error():
    src = SyntheticSource(rate=1000, pace=False, frames=10, cores=7)
    loop = LiveLoop(src, Reconstructor(FiberModel.paper()), [])
    with pytest.raises(ValueError, match="18 gratings × 7 cores but the fibre model has 18 × 4"):
        loop.run()


def test_server_dying_mid_frame_live_loop_recovers_and_recorder_keeps_everything(tmp_path):
    frames = synthetic_frames(60)
    rec = records(frames)
    # connection 1: records 0–24 and half of 25, then the server dies; connection 2 (after a restart): 30–59
    server = ScriptedServer([b"".join(rec[:25]) + rec[25][:100],
                             lambda c: (time.sleep(0.3), c.sendall(b"".join(rec[30:])), time.sleep(3))])
    recorder = Recorder(tmp_path / "live.h5", fiber=FiberModel.paper())
    sink = Collect()
    src = open_source(f"illumisense://127.0.0.1:{server.port}")
    loop = LiveLoop(src, Reconstructor(FiberModel.paper()), [sink, recorder])
    summary = loop.run(max_frames=55, handle_signals=False)
    server.close()
    s = summary.status
    assert sink.sequences == [*range(25), *range(30, 60)]
    assert s.lost_samples == 5 and s.framing_errors == 1 and s.disconnects == 1 and s.reconnects == 1
    with open_recording(tmp_path / "live.h5") as r:
        a = r.frames()
        assert r.complete and list(a.sequence) == sink.sequences
        np.testing.assert_allclose(a.wavelengths, np.stack([frames[i].wavelengths for i in sink.sequences]),
                                   atol=5e-5 + 1e-9, rtol=0)


def test_ctrl_c_ends_cleanly_with_a_complete_recording(tmp_path):
    out = tmp_path / "c.h5"
    proc = subprocess.Popen([*TWIN, "live", "synthetic://?rate=1000", "--record", str(out), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        assert wait_until(lambda: _frames_in(out) > 500, timeout=60)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout)
    assert summary["reason"] == "interrupted" and summary["lost_samples"] == 0
    with open_recording(out) as r:
        assert r.complete and len(r) == summary["frames"] == summary["recorded_frames"]


def _frames_in(path: Path) -> int:
    try:
        with open_recording(path) as r:
            return len(r)
    except (OSError, ValueError, KeyError):
        return 0


# ------------------------------------------------------------------------------------------------------ load


def _rss_kib(pid: int) -> int | None:
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    m = re.search(r"VmRSS:\s+(\d+) kB", text)
    return int(m.group(1)) if m else None


def load_run(tmp_path: Path, duration: float, frames: int | None = None) -> dict:
    """ILLumiSense on loopback at 1 kHz, 7 cores × 18 gratings: `twin serve` and `twin live` as separate
    processes; the client's resident memory is sampled every 0.5 s. Returns the live summary plus memory.

    With ``frames`` the client stops after that many frames (``--frames``) rather than after ``duration`` s, so a
    slow start (imports, a cold compile on a loaded machine) cannot leave a short run with nothing to judge;
    ``duration`` then only sizes the hang guard."""
    fiber = tmp_path / "fiber7.toml"
    server = subprocess.Popen(
        [*TWIN, "serve", "illumisense", "--port", "0", "--rate", "1000", "--source", "synthetic://?cores=7&gratings=18",
         "--save-fiber", str(fiber), "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    client = None
    try:
        line = server.stdout.readline()
        m = re.search(r"tcp://127\.0\.0\.1:(\d+)", line)
        assert m, line + server.stderr.read()
        client = subprocess.Popen(
            [*TWIN, "live", f"illumisense://127.0.0.1:{m.group(1)}", "--fiber", str(fiber),
             *(["--frames", str(frames)] if frames else ["--duration", str(duration)]), "--json", "--quiet"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
        samples: list[tuple[float, int]] = []
        t0 = time.monotonic()
        reader = threading.Thread(target=lambda: samples_loop(client, samples, t0), daemon=True)
        reader.start()
        stdout, stderr = client.communicate(timeout=duration + 120)
        reader.join(timeout=5)
        assert client.returncode == 0, stderr
    finally:
        for p in (client, server):
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    p.kill()
    out = json.loads(stdout)
    # growth after the warm-up (imports, numba, first connection): from 1/3 of the run to the end
    later = [kib for t, kib in samples if t >= duration / 3]
    out["rss_mib_start"] = later[0] / 1024 if later else None
    out["rss_mib_end"] = later[-1] / 1024 if later else None
    out["rss_growth_mib"] = (later[-1] - later[0]) / 1024 if len(later) >= 2 else None
    return out


def samples_loop(proc, samples, t0):
    while proc.poll() is None:
        kib = _rss_kib(proc.pid)
        if kib:
            samples.append((time.monotonic() - t0, kib))
        time.sleep(0.5)


def _check_load(out: dict, duration: float, memory: bool) -> None:
    mem = "n/a" if out["rss_growth_mib"] is None else (
        f"{out['rss_mib_start']:.1f} → {out['rss_mib_end']:.1f} MiB (growth {out['rss_growth_mib']:+.2f} MiB)")
    print(f"\nload {duration:g} s at 1 kHz, 7 × 18: {out['frames']} frames, lost {out['lost_samples']}, framing "
          f"errors {out['framing_errors']}, client RSS from {duration / 3:.0f} s to the end: {mem}")
    # every frame sent after the client joined arrived, in order and whole: no gap, no reset, nothing unusable
    # (how fast the client keeps up is `twin bench`'s to measure, not a timed assertion's)
    if out["reason"] == "frames":  # a run bounded by its frame count: all of them arrived
        assert out["frames"] == round(duration * 1000)
    else:
        assert out["reason"] == "duration" and out["frames"] > 0
    assert out["lost_samples"] == 0 and out["sequence_gaps"] == 0 and out["sequence_resets"] == 0
    assert out["framing_errors"] == 0 and out["disconnects"] == 0
    assert out["frames_unusable"] == 0 and out["frames_complete"] == out["frames"]
    # the rate readout is the server's 1 kHz, read on its timestamps whatever the load
    assert out["rate_hz"] == pytest.approx(1000.0, rel=1e-4)
    if memory:
        # flat memory: nothing is kept per frame. 40 s of frames kept as Frame objects would take ~100 MiB;
        # 8 MiB allows for allocator noise. (A 3 s run would still measure its own warm-up on a loaded machine,
        # so only the long run is judged.)
        assert out["rss_growth_mib"] is not None and out["rss_growth_mib"] < 8.0


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="RSS sampled from /proc")
def test_load_short(tmp_path):
    _check_load(load_run(tmp_path, 3.0, frames=3000), 3.0, memory=False)


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="RSS sampled from /proc")
def test_load_60s_1khz_7x18(tmp_path):
    _check_load(load_run(tmp_path, 60.0), 60.0, memory=True)


def test_live_cli_runs_a_synthetic_source_and_prints_a_summary(tmp_path):
    proc = subprocess.run([*TWIN, "live", "synthetic://?rate=2000&frames=600&drop=0.02", "--json", "--quiet"],
                          capture_output=True, text=True, env=ENV, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["frames"] == 600 and out["reason"] == "source ended" and out["frames_missing_peaks"] > 0
    bad = subprocess.run([*TWIN, "live", "illumisense://127.0.0.1:1?start_wait=0"], capture_output=True, text=True,
                         env=ENV, timeout=60)
    assert bad.returncode == 2 and "illumisense://127.0.0.1:1?start_wait=0: cannot connect" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_frame_flags_of_a_hand_made_batch():
    fiber = FiberModel.paper()
    rec = Reconstructor(fiber)
    w = np.array(fiber.lambda0)
    one_missing = w.copy()
    one_missing[3, 1] = np.nan  # 3 of 4 cores left at grating 3: still solved
    two_missing = w.copy()
    two_missing[5, 1:3] = np.nan  # 2 left: grating 5 dropped and interpolated over
    none = np.full_like(w, np.nan)
    loop = LiveLoop(SyntheticSource(), rec, [])
    frames = [Frame(x, sequence=i) for i, x in enumerate([w, one_missing, two_missing, none])]
    _, shapes, flags = loop.process(Frame.stack(frames))
    assert flags.tolist() == [0, FrameFlag.MISSING_PEAKS, FrameFlag.MISSING_PEAKS | FrameFlag.PARTIAL,
                              FrameFlag.MISSING_PEAKS | FrameFlag.UNUSABLE]
    assert np.isfinite(shapes.positions[2]).all() and np.isnan(shapes.positions[3]).all()
    assert loop.c.invalid_nodes == 1 + 18


def test_sequence_counter():
    from twin.io.sequence import SequenceCounter

    c = SequenceCounter()
    lost = [c.count(s) for s in (5, 6, 9, -1, 10, 3, 4)]
    assert lost == [0, 0, 2, 0, 0, 0, 0]  # −1 unknown: skipped; 3 after 10: a reset, not loss
    assert (c.sequence_gaps, c.lost_samples, c.sequence_resets, c.last) == (1, 2, 1, 4)


def test_sequence_counter_batch_equals_one_by_one():
    from twin.io.sequence import SequenceCounter

    rng = np.random.default_rng(3)
    seqs = np.cumsum(rng.integers(-3, 5, 400))
    one, many = SequenceCounter(), SequenceCounter()
    lost_one = [one.count(int(s)) for s in seqs]
    lost_many = np.concatenate([many.count_many(chunk) for chunk in np.array_split(seqs, 7)])
    assert lost_many.tolist() == lost_one and one.as_dict() == many.as_dict()


# ------------------------------------------------------------------------------------ issue 11 and 14 regressions


def test_frames_missing_peaks_counts_only_frames_with_missing_peaks():
    """Issue 11 item 7: the sequence-gap flag was set on the same array before it was counted (gave 3)."""
    f = FiberModel.paper()
    loop = LiveLoop(lambda: None, Reconstructor(f))
    _, _, flags = loop.process(Frame.stack([Frame(f.lambda0.copy(), 0.0, s) for s in (0, 2, 4, 6)]))
    assert loop.c.frames_missing_peaks == 0 and loop.c.lost_samples == 3
    assert list(flags) == [0, FrameFlag.SEQUENCE_GAP, FrameFlag.SEQUENCE_GAP, FrameFlag.SEQUENCE_GAP]
    w = f.lambda0.copy()
    w[3, 2] = np.nan
    loop.process(Frame.stack([Frame(w, 0.0, 9)]))
    assert loop.c.frames_missing_peaks == 1


def test_an_absurd_peak_is_missing_not_a_nan_shape():
    """Issue 11 item 4: a finite impossible peak (1e300 nm, 1.5 × its reference) gave valid gratings and NaN
    positions; it is treated as missing, flagged and counted."""
    f = FiberModel.paper()
    rec = Reconstructor(f)
    k = np.tile([15.0, -4.0], (f.n_gratings, 1))
    good = strain.forward(f, k)
    for value in (1e300, 1.5 * good[5, 1], -1e300, 0.0):
        w = good.copy()
        w[5, 1] = value
        shape = rec(w)
        assert shape.valid.all() and np.isfinite(shape.positions).all()
        np.testing.assert_allclose(shape.positions, rec(good).positions, atol=1e-9)  # 3 cores remain: exact
        assert rec.peaks_outside(w).sum() == 1
    loop = LiveLoop(lambda: None, rec)
    w = good.copy()
    w[5, 1], w[7, 3] = 1e300, np.inf  # ±inf from a source is out of any window too
    _, shapes, flags = loop.process(Frame.stack([Frame(w, 0.0, 0), Frame(good, 0.0, 1)]))
    assert list(flags) == [FrameFlag.MISSING_PEAKS, 0] and np.isfinite(shapes.positions).all()
    assert loop.c.peaks_outside_window == 2 and loop.c.frames_missing_peaks == 1
    assert loop.c.frames_complete == 2
    assert Reconstructor(f, peak_window=None).peaks_outside(w).sum() == 1  # no window: only the inf


class _AbsurdSource(FrameByFrame):
    """Synthetic frames whose grating 5 of core 1 reads 1e300 nm, and whose stats hold a NaN."""

    def __init__(self, url: str, **_):
        self.inner = SyntheticSource(rate=1000, pace=False, frames=20)
        self.url, self.fiber, self.rate = url, self.inner.fiber, 1000.0

    def next_frame(self, timeout=None):
        f = self.inner.read(timeout)
        w = f.wavelengths.copy()
        w[5, 1] = 1e300
        return Frame(w, f.timestamp, f.sequence)

    def stats(self) -> dict:
        return {"temperature_K": float("nan"), "gain": float("inf")}


def open_absurd(url: str, **options) -> Source:
    return _AbsurdSource(url, **options)


def test_json_output_is_strict_json_even_with_absurd_peaks(capsys):
    """Issue 11 item 4: `--json` printed "tip_m": [NaN, NaN, NaN], which is not JSON."""
    from twin import registry
    from twin.cli import main

    registry.register("twin.sources", "absurd", "test_live:open_absurd")
    try:
        code = main(["live", "absurd://", "--json", "--quiet"])
    finally:
        registry.unregister("twin.sources", "absurd")
    out = capsys.readouterr().out

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    summary = json.loads(out, parse_constant=refuse)
    assert code == 0 and summary["frames"] == 20 and summary["peaks_outside_window"] == 20
    assert summary["frames_missing_peaks"] == 20 and summary["frames_complete"] == 20
    assert all(isinstance(x, float) for x in summary["tip_m"])
    assert summary["source"]["temperature_K"] is None and summary["source"]["gain"] is None


def test_jsonout_maps_every_non_finite_number_to_null():
    from twin import jsonout

    obj = {"a": [1.0, float("nan"), np.float32("inf")], "b": np.array([[np.nan, 2.0]]), "c": np.int64(3),
           "d": (np.bool_(True), -np.inf), "e": "NaN"}
    assert json.loads(jsonout.dumps(obj)) == {"a": [1.0, None, None], "b": [[None, 2.0]], "c": 3,
                                              "d": [True, None], "e": "NaN"}


class _BurstySource(Source):
    """A 100 Hz source whose frames reach the reader in irregular bursts (held back 0–0.3 s), as through a
    network or a simulator stepping in chunks; timestamps are the source's own clock."""

    def __init__(self, fiber, rate: float = 100.0, seed: int = 0):
        self.fiber, self.rate = fiber, None  # no nominal rate: the readout must come from the timestamps
        self.period = 1.0 / rate
        self.t0 = time.monotonic()
        self.next_release = self.t0
        self.sent = 0
        self.rng = np.random.default_rng(seed)
        self.w = fiber.lambda0.copy()

    def read_batch(self, max_frames=1024, timeout=None):
        now = time.monotonic()
        if now < self.next_release:
            time.sleep(min(timeout or 0.0, self.next_release - now))
            return None
        due = int((now - self.t0) / self.period) + 1
        out = [Frame(self.w, 1000.0 + i * self.period, i) for i in range(self.sent, min(due, self.sent + max_frames))]
        self.sent += len(out)
        self.next_release = now + self.rng.uniform(0.0, 0.3)
        return Frame.stack(out) if out else None


def test_rate_readout_matches_the_source_whatever_the_bursts():
    """Issue 14: the readout jumped between 122 and 246 Hz for a 100 Hz source."""
    f = FiberModel.paper()
    source = _BurstySource(f)
    seen: list[tuple[int, float]] = []
    sequences: list[int] = []

    def sink(frames, shapes, st):
        if frames:
            seen.append((st.frames, st.rate_hz))
            sequences.extend(fr.sequence for fr in frames)

    summary = LiveLoop(source, Reconstructor(f), [sink]).run(duration=3.0, handle_signals=False)
    # every frame the source released reached the sinks, in order, none lost
    assert sequences == list(range(source.sent)) and summary.status.frames == source.sent
    assert summary.status.lost_samples == 0
    # from the second frame on (two timestamps make a rate), over every burst after the first
    late = [r for n, r in seen if n >= 2]
    assert late
    assert max(abs(r - 100.0) for r in late) < 0.01  # the source's clock: exact up to float rounding
    assert not summary.status.behind and summary.status.behind_events == 0


class _SlowSource(FrameByFrame):
    """Says 100 Hz, stamps frames 10 ms apart, but delivers only 60 a second: behind real time."""

    def __init__(self, fiber, nominal: float | None = 100.0, actual: float = 60.0):
        self.fiber, self.rate, self.actual = fiber, nominal, actual
        self.t0, self.k = time.monotonic(), 0
        self.w = fiber.lambda0.copy()

    def next_frame(self, timeout=None):
        wait = self.t0 + self.k / self.actual - time.monotonic()
        if wait > (timeout or 0.0):
            time.sleep(timeout or 0.0)
            return None
        time.sleep(max(wait, 0.0))
        self.k += 1
        return Frame(self.w, self.k * 0.01, self.k)


def assert_arrival_matches_the_counts(seen: list[tuple[float, int, float]], window: float) -> None:
    """The arrival readout of each batch, ``seen`` = (elapsed s, frames, arrival Hz) as the sinks got them, is the
    frames counted since a batch about ``window`` s earlier over the elapsed time between the two
    (:class:`twin.io.rate.RateMeter`: the anchor is the last batch at or before the window's start).

    The sinks read the elapsed time a little after the meter read the clock, so the anchor may be a neighbour of
    the one found on the sinks' times, and the rates agree to the few ms of that lag over the window: 5 %."""
    e = np.array([x[0] for x in seen])
    n = np.array([x[1] for x in seen], float)
    checked = 0
    for j in np.flatnonzero(e >= e[0] + 1.2 * window):
        before = np.flatnonzero(e <= e[j] - window)
        a0 = int(before[-1]) if before.size else 0
        rates = [(n[j] - n[i]) / (e[j] - e[i]) for i in (a0 - 1, a0, a0 + 1) if 0 <= i < j]
        assert any(r == pytest.approx(seen[j][2], rel=0.05) for r in rates), (seen[j], rates)
        checked += 1
    assert checked


@pytest.mark.parametrize("nominal", [100.0, None])
def test_a_source_behind_real_time_is_said_once_and_counted(capsys, nominal):
    f = FiberModel.paper()
    seen: list[tuple[float, int, float]] = []
    sequences: list[int] = []

    def sink(frames, shapes, st):
        if frames:
            seen.append((st.elapsed, st.frames, st.arrival_hz))
            sequences.extend(fr.sequence for fr in frames)

    loop = LiveLoop(_SlowSource(f, nominal), Reconstructor(f), [sink], rate_window=1.0)
    summary = loop.run(duration=2.5, handle_signals=False)
    s = summary.status
    err = capsys.readouterr().err
    assert s.behind and s.behind_events == 1 and err.count("behind real time") == 1
    # nothing lost on the way: the frames the source gave, in order
    assert sequences == list(range(1, s.frames + 1)) and s.lost_samples == 0
    # the readouts: the source's own rate from its timestamps (10 ms apart), and the arrival rate as counted —
    # below what leaving the behind state needs, (1 + 0.9)/2 of the expected 100 Hz
    assert abs(s.rate_hz - 100.0) < 0.01
    assert 0 < s.arrival_hz < 95.0
    assert_arrival_matches_the_counts(seen, loop.rate_window)
    assert "arrive at" in err and ("nominal rate" if nominal else "timestamps advance") in err
    from twin.live import format_status

    assert "behind real time" in format_status(s)


def test_frame_pump_says_once_when_its_source_runs_behind(capsys):
    from sim_interrogator.servers.common import FramePump

    f = FiberModel.paper()
    pump = FramePump(_SlowSource(f, 100.0))
    pump.meter.window = 1.0
    pump.start()
    try:
        assert wait_until(lambda: pump.meter.behind_events == 1, timeout=10)
    finally:
        pump.stop()
    assert capsys.readouterr().err.count("runs behind real time") == 1


@pytest.mark.parametrize("argv", [["live", "synthetic://", "--duration", "-1"],
                                  ["live", "synthetic://", "--duration", "nan"],
                                  ["live", "synthetic://", "--frames", "0"],
                                  ["demo", "--duration", "-1", "--no-viewer"]])
def test_bad_durations_are_one_line_and_exit_2(argv):
    proc = subprocess.run([*TWIN, *argv], capture_output=True, text=True, env=ENV, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert len(proc.stderr.strip().splitlines()) == 1 and "must be" in proc.stderr


@pytest.mark.parametrize("delay", [0.1, 0.25, 0.4, 0.6])
def test_ctrl_c_at_start_up_is_one_line_and_exit_130(delay):
    """Issue 11 item 9: Ctrl-C 0.1–0.6 s after start gave a KeyboardInterrupt traceback (rc −2)."""
    twin = Path(sys.executable).parent / "twin"
    proc = subprocess.Popen([str(twin), "live", "synthetic://?rate=100", "--duration", "20", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        # The delay counts from the moment twin's own start-up has begun (numpy, which only main()'s handler
        # imports, is being mapped), not from the launch: on a loaded machine the interpreter alone can take
        # longer than 0.1 s to reach our code, and a Ctrl-C inside Python's own start-up is not ours to catch.
        maps = Path(f"/proc/{proc.pid}/maps")
        t_end = time.monotonic() + 60  # a hang guard, not a speed limit
        while proc.poll() is None and time.monotonic() < t_end and "numpy" not in maps.read_text(errors="replace"):
            time.sleep(0.002)
        time.sleep(delay - 0.1)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert "Traceback" not in stderr
    # a bounded run (--duration 20) cut short: 130 either way (tests/test_ctrl_c.py has the whole rule)
    assert proc.returncode == 130
    if stdout == "":  # still starting up
        assert stderr.strip() == "twin live: interrupted"
    else:  # the loop was already running (a fast machine): it ends cleanly with its summary
        assert "ended: interrupted" in stdout


@pytest.mark.parametrize("bad, got", [([[1510.0, 1515.0], [1520.0]], "a ragged sequence of 2 rows"),
                                      ("abc", "str 'abc'"),
                                      (np.zeros((4, 18)), "got (4, 18)"),
                                      (np.zeros(72), "got (72,)")])
def test_wavelengths_of_the_wrong_shape_name_expected_and_got(bad, got):
    """Issue 11 item 10: wavelengths of the wrong shape gave "not enough values to unpack" or numpy's text."""
    with pytest.raises(ValueError) as err:
        Reconstructor(FiberModel.paper())(bad)
    msg = str(err.value)
    assert "(..., 18, 4)" in msg and got in msg and "\n" not in msg


def _reference_books(rec, frames: Frame, raises: bool = False) -> tuple[dict, list[int]]:
    """The counts and flags of docs/figures.md for a batch, frame by frame from their definitions (numpy and the
    sequence counter one number at a time): what the live loop's one compiled pass must equal."""
    from twin.io.sequence import SequenceCounter

    e, outside = rec.strain(frames.wavelengths)
    g = rec.fiber.n_gratings
    valid = np.zeros((len(frames), g), bool) if raises else rec.from_strain(e).valid
    seq = SequenceCounter()
    flags, n = [], len(frames)
    for i in range(n):
        f = FrameFlag.MISSING_PEAKS if np.isnan(e[i]).any() else 0
        solved = int(valid[i].sum())
        f |= FrameFlag.UNUSABLE if solved == 0 else FrameFlag.PARTIAL if solved < g else 0
        f |= FrameFlag.SEQUENCE_GAP if seq.count(int(frames.sequence[i])) else 0
        flags.append(int(f))
    fl = np.array(flags)
    counts = {
        "frames": n, "peaks_outside_window": int(outside.sum()),
        "frames_missing_peaks": int(np.count_nonzero(fl & FrameFlag.MISSING_PEAKS)),
        "frames_partial": int(np.count_nonzero(fl & FrameFlag.PARTIAL)),
        "frames_unusable": int(np.count_nonzero(fl & FrameFlag.UNUSABLE)),
        "frames_complete": int(np.count_nonzero((fl & (FrameFlag.PARTIAL | FrameFlag.UNUSABLE)) == 0)),
        "invalid_nodes": int(g * n - valid.sum()),
        **seq.as_dict(),
    }
    return counts, flags


class _Failing(Reconstructor):
    def from_strain(self, strain, *, frames=True):
        raise RuntimeError("broken on purpose")


@pytest.mark.parametrize("raises", [False, True])
def test_the_loops_compiled_books_equal_the_definitions_over_a_damaged_stream(raises):
    """LiveLoop.process keeps its books in one compiled pass per batch (twin.live._batch_books); over a damaged
    stream (missing peaks, whole gratings and frames gone, absurd and infinite peaks, lost, repeated and unknown
    sequence numbers) cut into batches of every size, its counts and flags equal the per-frame definitions."""
    f = FiberModel.paper()
    rng = np.random.default_rng(24)
    n = 300
    w = np.broadcast_to(f.lambda0, (n, *f.lambda0.shape)).copy()
    w += rng.normal(0, 0.02, w.shape)
    w[rng.random(w.shape) < 0.03] = np.nan  # single peaks missing
    w[rng.random(n) < 0.05, 4, :] = np.nan  # a grating gone
    w[rng.random(n) < 0.03] = np.nan  # a frame gone
    hit = rng.random(w.shape) < 0.005
    w[hit] = rng.choice([1e300, -1e300, np.inf, -np.inf, 0.0], hit.sum())
    seq = np.cumsum(rng.choice([1, 1, 1, 2, 5, 0, -7], n))
    seq[rng.random(n) < 0.03] = -1  # unknown
    stream = Frame(w, np.arange(n) * 1e-3, seq)
    rec = (_Failing if raises else Reconstructor)(f)
    want, want_flags = _reference_books(rec, stream, raises)
    assert want["frames_missing_peaks"] and want["lost_samples"] and want["sequence_resets"]
    if not raises:
        assert want["frames_partial"] and want["frames_unusable"] and want["peaks_outside_window"]
    loop = LiveLoop(lambda: None, rec, quiet=True)
    cuts = np.sort(rng.choice(np.arange(1, n), 40, replace=False))
    flags, parts = [], np.split(np.arange(n), cuts)
    for part in parts:
        good, shapes, fl = loop.process(stream[part])
        assert len(good) == len(part) and (shapes is None) == raises
        flags += fl.tolist()
    got = {k: getattr(loop.c, k) for k in want}
    assert got == want and flags == want_flags
    assert loop.c.reconstruct_errors == (len(parts) if raises else 0)  # each batch counted once


def test_the_rate_meters_compiled_timestamp_check_equals_numpys():
    """RateMeter.add judges a batch's timestamps usable (all finite, none going back) in one compiled pass."""
    from twin.io.rate import _finite_and_ordered

    rng = np.random.default_rng(5)
    for _ in range(300):
        ts = np.cumsum(rng.choice([0.0, 1e-3, 1e-3, -1e-3], rng.integers(1, 6)))
        if rng.random() < 0.3:
            ts[rng.integers(ts.size)] = rng.choice([np.nan, np.inf, -np.inf])
        want = bool(np.isfinite(ts).all()) and bool((ts[1:] >= ts[:-1]).all())
        assert _finite_and_ordered(ts) == want


@pytest.mark.parametrize("batch", [1, 7, 150, 300])
def test_the_source_rate_is_over_the_last_window_whatever_the_batching(batch):
    """rate_hz is (frames − 1) / (newest − oldest timestamp) over the frames within the last ``window`` s of the
    newest (docs/figures.md), also when a batch straddles the window's start (a file read at full speed comes in
    batches of hundreds): 100 Hz with 10 samples lost 1 s in, over 3.1 s — the last 2 s hold no gap, so 100 Hz
    however the frames were batched (counting a whole straddling batch gave 299 / 3.09 s = 96.8 Hz)."""
    from twin.io.rate import RateMeter

    ts = np.delete(np.arange(310) * 0.01, np.s_[100:110])
    meter = RateMeter(window=2.0)
    for i in range(0, ts.size, batch):
        meter.add(ts[i : i + batch], now=0.0)
    assert meter.stamped_rate == pytest.approx(100.0, rel=1e-9)
    # a window that reaches back over the gap: 2.5 s back from 3.09 s holds 250 frames − the 10 lost
    wide = RateMeter(window=2.5)
    for i in range(0, ts.size, batch):
        wide.add(ts[i : i + batch], now=0.0)
    assert wide.stamped_rate == pytest.approx((ts[ts >= ts[-1] - 2.5].size - 1) / (ts[-1] - ts[ts >= ts[-1] - 2.5][0]))
