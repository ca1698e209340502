"""`twin demo` (`make demo`): the whole loop on one machine, with no hardware.

1. The simulated fibre is calibrated the way a lab would do it: the two-step calibration in the twin
   (straight, then an in-plane bend) and identification of [Δθ, g] on six library shapes.
2. The twin runs a scenario in real time — by default the catheter advancing through a curved sheath — and a
   simulated interrogator serves its peaks over the FBGS ILLumiSense TCP protocol on 127.0.0.1.
3. The project's own ILLumiSense driver reads that stream like hardware, the live loop reconstructs every frame
   with the calibration from step 1, and a meshcat viewer shows the reconstruction beside the truth (its URL
   is printed; ``--no-viewer`` for a headless run).
4. A live line shows the rate, lost samples and the current error; at the end, a table of errors against the
   truth, which the server side keeps by sequence number (the wire carries no truth, as with hardware).

Ctrl-C during the run ends it cleanly: the table covers the frames received and says the run was cut short, and
the exit status is 130. After a complete run the viewer's page stays served until Ctrl-C (exit status 0).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections import OrderedDict
from dataclasses import replace

import numpy as np

from models.catheter import collect_warnings
from scenarios._common.calibration import calibration_for
from sim_interrogator.optics import Optics, OpticsConfig
from sim_interrogator.servers.illumisense_server import IllumisenseServer
from sim_interrogator.sim_source import open_sim
from twin import FiberModel, Frame, Reconstructor, jsonout
from twin.frames import Truth
from twin.io.source import open_source
from twin.live import LiveLoop
from twin.reference_errors import TruthError

#: one-line help (read by `twin --help` without importing this module)
HELP = "the main job: reconstruct shapes from (simulated) interrogator data and compare"

DEFAULT_SCENARIO = "sim://sheath-cycle?cycles=3&segments=60&rate=50&realtime=1"
FALLBACK_SCENARIO = "sim://static?shape=mixed&fixture=tube&realtime=1&rate=100"


class TruthTap:
    """Keeps the truth of the frames the server sends, by sequence number (bounded)."""

    def __init__(self, keep: int = 20_000):
        self._truth: OrderedDict[int, Truth] = OrderedDict()
        self._lock = threading.Lock()
        self.keep = keep

    def __call__(self, frame: Frame) -> None:
        with self._lock:
            self._truth[frame.sequence] = frame.truth
            while len(self._truth) > self.keep:
                self._truth.popitem(last=False)

    def get(self, sequence: int) -> Truth | None:
        with self._lock:
            return self._truth.get(sequence)

    def batch(self, sequences: np.ndarray) -> Truth | None:
        """The truths of a batch of received frames as one batch :class:`~twin.frames.Truth` (rows whose truth
        is not kept, or of another layout than the first, absent); None when none is kept."""
        with self._lock:
            found = [self._truth.get(q) for q in sequences.tolist()]
        return Truth.stack(found, like=next((t for t in found if t is not None), None))


class ErrorSink:
    """The error of the received frames against the truth the server kept for their sequence numbers: the
    frames carry it into a :class:`twin.reference_errors.TruthError` (Kabsch on arc length, every complete
    frame compared; docs/figures.md); keeps the compared frames' wavelengths and truth for the paper's
    pipeline on the same frames."""

    def __init__(self, tap: TruthTap, viewer=None, viewer_rate: float = 20.0):
        self.tap, self.viewer = tap, viewer
        self.truth = TruthError(per_second=None)
        self.w: list[np.ndarray] = []  # per batch: the compared frames' wavelengths (k, G, C), nm
        self.truths: list[Truth] = []  # and their truth's positions
        self._next_view = 0.0
        self._period = 1.0 / viewer_rate

    def __call__(self, frames, shapes, status) -> None:
        if not len(frames) or shapes is None:
            return
        truth = self.tap.batch(frames.sequence)
        if truth is None:
            return
        self.truth(replace(frames, truth=truth), shapes, status)
        ok = np.flatnonzero(shapes.all_valid & truth.all_present)
        if not ok.size:
            return
        self.w.append(frames.wavelengths[ok])
        self.truths.append(Truth(s=truth.s, positions=truth.positions[ok]))
        if self.viewer is not None and time.monotonic() >= self._next_view:
            self._next_view = time.monotonic() + self._period
            i = int(ok[-1])
            self.viewer.info.update(rate_hz=status.rate_hz, lost=status.lost_samples, frames=status.frames)
            self.viewer.show(shapes[i], self.tap.get(int(frames.sequence[i])), vendor=frames[i].vendor)


class LinePrinter:
    """One status line, refreshed a few times a second."""

    def __init__(self, errors: ErrorSink, stream=sys.stderr, rate: float = 4.0):
        self.errors, self.stream, self.period, self._next = errors, stream, 1.0 / rate, 0.0

    def __call__(self, frames, shapes, status) -> None:
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + self.period
        e = self.errors.truth.latest
        err = f"error now {e.max * 1e3:5.2f} mm (max), {e.mean * 1e3:5.2f} mm (mean)" if e is not None else "…"
        self.stream.write(f"\r  {status.state:8s} {status.elapsed:6.1f} s  {status.frames:6d} frames "
                          f"{status.rate_hz:6.1f} Hz  lost {status.lost_samples:3d}  {err}   ")
        self.stream.flush()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default=None,
                        help=f"simulated source URL (default {DEFAULT_SCENARIO})")
    parser.add_argument("--duration", type=float, default=None,
                        help="seconds to run (default: the scenario's duration, or 20 s)")
    parser.add_argument("--no-viewer", action="store_true", help="headless: no 3D viewer")
    parser.add_argument("--port", type=int, default=0, help="ILLumiSense port on 127.0.0.1 (default: a free one)")
    parser.add_argument("--json", action="store_true", help="print one JSON object with the final figures")


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _open_viewer(enabled: bool):
    if not enabled:
        return None
    try:
        from twin.viewer import Viewer

        viewer = Viewer(announce=None, calibration="two-step + identified in the twin")
    except (ImportError, OSError) as exc:  # the viewer is optional for the demo: run headless instead
        _say(f"  (no viewer: {exc})")
        return None
    _say(f"viewer: open {viewer.url} in a browser")
    return viewer


def _warm_up(server: IllumisenseServer, fiber: FiberModel, cal) -> None:
    """Encode, decode and reconstruct a few records the way the live run will before its clock starts: on a
    fresh install the compiled kernels of the wire format (the batch framing, the sensor blocks, the scanner)
    and of the reconstruction are built on first use, seconds that would otherwise be taken from the live run
    (a loaded machine then saw no frame at all in a short run)."""
    from twin.io.illumisense.stream import StreamDecoder

    data = b"".join(server.encode(Frame(fiber.lambda0.copy(), 0.01 * k, k)) for k in range(4))
    for feed in ("feed", "feed_batch"):  # the single-record path (layout consensus) and the driver's batches
        decoder = StreamDecoder()
        getattr(decoder, feed)(data)
        decoder.finish()
    rec = Reconstructor(fiber, cal)
    for n in (1, 4):  # the loop's calls: strain once, then the shapes from it, on one frame and on a batch
        e, _ = rec.strain(np.broadcast_to(fiber.lambda0, (n, *fiber.lambda0.shape)).copy())
        rec.from_strain(e)


def run(args: argparse.Namespace) -> int:
    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be a positive number of seconds, got {args.duration}")
    fiber = FiberModel.paper()
    mujoco_warnings = collect_warnings()
    t_start = time.monotonic()
    _say("1/3 calibrating the simulated fibre as a lab would: two-step calibration (straight, bend), then Δθ and "
         "g = r·S_ε identified against the fixtures' geometry on six shapes (cached after the first run) …")
    used = calibration_for("lab", OpticsConfig(), fiber, progress=lambda msg: _say(f"    {msg}"))
    cal = used.calibration
    true = Optics(fiber, OpticsConfig()).describe()
    _say(f"    Δθ = {cal.delta_theta:.4f} rad (true {true['delta_theta']:.4f}), g = {cal.gain * 1e6:.3f} µm "
         f"(true {true['gain_m'] * 1e6:.3f})")

    url = args.scenario or DEFAULT_SCENARIO
    _say(f"2/3 starting the twin: {url}")
    try:
        sim = open_sim(url)
    except ValueError:
        if args.scenario:
            raise
        url = FALLBACK_SCENARIO
        sim = open_sim(url)
    duration = args.duration or (sim.setup.duration if sim.setup.duration else 20.0)
    tap = TruthTap()
    server = IllumisenseServer(sim, port=args.port)
    _warm_up(server, fiber, cal)
    server.pump.subscribe(tap)
    server.start()
    host, port = server.address
    _say(f"    simulated interrogator serving ILLumiSense on tcp://{host}:{port}")

    viewer = _open_viewer(not args.no_viewer)
    errors = ErrorSink(tap, viewer)
    rec = Reconstructor(fiber, cal)
    _say(f"3/3 reading illumisense://{host}:{port} with the driver and reconstructing live ({duration:g} s) …")
    try:
        loop = LiveLoop(lambda: open_source(f"illumisense://{host}:{port}"), rec, [errors, LinePrinter(errors)])
        summary = loop.run(duration=duration)
    finally:
        server.close()
    print(file=sys.stderr)
    result = _result(errors, summary, fiber, cal, url, time.monotonic() - t_start, true)
    result["mujoco_warnings"] = len(mujoco_warnings)
    result["run_s"] = round(summary.duration, 1)
    result["planned_s"] = duration
    result["cut_short"] = summary.reason == "interrupted"  # by Ctrl-C (the run always has a duration)
    if args.json:
        print(jsonout.dumps(result, indent=2))
    else:
        print(report(result))
    from twin.cli import interrupted_status

    status = interrupted_status(result["cut_short"], bounded=True)
    if viewer is not None:
        if status:  # Ctrl-C cut the run short: it ends the command, no page kept
            viewer.close()
        else:
            from twin.viewer import keep_open

            keep_open(viewer)  # the page stays live until Ctrl-C (exit 0: nothing is cut short)
    return status


def _result(errors: ErrorSink, summary, fiber, cal, url, wall, true) -> dict:
    st = summary.status
    out = {
        "scenario": url,
        "wall_s": round(wall, 1),
        "frames": st.frames,
        "lost_samples": st.lost_samples,
        "framing_errors": st.framing_errors,
        "frames_partial": st.frames_partial,
        "frames_per_s": round(summary.frames_per_s, 1),
        "calibration": "lab (two-step in the twin, Δθ and g identified against the fixtures' geometry)",
        "identified": {"delta_theta": cal.delta_theta, "g_um": cal.gain * 1e6},
        "true": {"delta_theta": true["delta_theta"], "g_um": true["gain_m"] * 1e6},
        "frames_compared": errors.truth.frames_compared,
    }
    if errors.w:
        # the paper's pipeline on the same received frames, compared by the same definition
        truth = Truth.stack(errors.truths)
        w = np.concatenate(errors.w)
        paper = TruthError(per_second=None)
        paper(Frame(w, truth=truth), Reconstructor.paper(fiber, cal)(w), None)
        out["default"] = _table(errors.truth)
        if paper.frames_compared:  # none when the paper's pipeline solved no frame whole
            out["paper"] = _table(paper)
    return out


def _table(errors: TruthError) -> dict:
    """A row of the demo's table (mm): the figures of docs/figures.md, and the 95th percentile of the per-frame
    max."""
    r = errors.result()
    return {"max_error_mm": r.max_error_mm, "mean_error_mm": r.mean_error_mm,
            "p95_max_error_mm": round(float(np.percentile(errors.per_frame()["max"], 95)) * 1e3, 4),
            "tip_error_mm": r.tip_error_mm_mean}


def report(r: dict) -> str:
    lines = [
        "",
        f"twin demo: {r['scenario']}"
        + (f" — cut short by Ctrl-C after {r['run_s']:.1f} s of {r['planned_s']:g} s" if r.get("cut_short") else ""),
        f"  {r['frames']} frames over ILLumiSense ({r['frames_per_s']:.1f} Hz), {r['lost_samples']} lost, "
        f"{r['framing_errors']} framing errors, {r['frames_partial']} with gratings dropped (lost peaks)",
        f"  calibration: Δθ = {r['identified']['delta_theta']:.4f} rad (twin's true {r['true']['delta_theta']:.4f}), "
        f"g = {r['identified']['g_um']:.3f} µm (true {r['true']['g_um']:.3f})",
    ]
    if "default" in r:
        lines += [
            "",
            f"  errors against the truth over {r['frames_compared']} frames (mm; Kabsch on arc length; "
            "docs/figures.md):",
            f"  {'pipeline':30s}{'max':>8s}{'p95 of max':>12s}{'mean':>8s}{'tip mean':>10s}",
        ]
        for key, label in (("default", "default (this project)"), ("paper", "the paper's pipeline")):
            e = r.get(key)
            if e is None:
                lines.append(f"  {label:30s}  no frame solved whole")
                continue
            lines.append(f"  {label:30s}{e['max_error_mm']:8.3f}{e['p95_max_error_mm']:12.3f}"
                         f"{e['mean_error_mm']:8.3f}{e['tip_error_mm']:10.3f}")
    lines.append(f"\n  total wall time {r['wall_s']:.0f} s; MuJoCo solver warnings: {r['mujoco_warnings']} "
                 "(ill-conditioned flex stiffness at start-up is expected)")
    return "\n".join(lines)
