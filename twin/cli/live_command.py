"""`twin live URL`: reconstruct shapes live from any source of frames and report how the stream is doing.

    twin live illumisense://127.0.0.1:2055 [--fiber FILE] [--calibration FILE] [--record FILE]
              [--duration S] [--frames N] [--json] [--quiet] [--viewer [--viewer-rate HZ] [--keep-open]]
              [--igtl [HOST:]PORT [--igtl-rate HZ]] [--foxglove [HOST:]PORT [--foxglove-rate HZ]] [--twist RATE]

Prints a status line about once a second (state, frame rate, lost samples, framing errors, reconnects,
partial/unusable frames, tip position in mm, and the latest error against the truth or the interrogator's own
shape when the frames carry one; on stderr with ``--json``) and a summary at the end (with the errors over every
complete frame: docs/figures.md); ``--json`` prints the summary as one JSON object on stdout, with the confidence
tube's figures (``mean_sigma_mm``; ``coverage_95`` with a truth) on the compared frames; ``--twist RATE`` states
the 1σ of the catheter's twist rate the fibre does not measure, rad/m, which that tube (and the viewer's and
OpenIGTLink's) carries (:mod:`twin.cli.twist_option`; ``tube_twist_rad_per_m``). Ctrl-C ends the
run cleanly: the recording is flushed and marked complete, and the summary is printed. Exit status 0; 130 when
Ctrl-C cut a run with ``--duration`` or ``--frames`` short (without a bound, Ctrl-C is how a run ends: 0); 1 when
a sink failed (e.g. the recording could not be written) or the source failed for good (a damaged recording:
``replay://FILE?salvage=1`` replays the frames before the damage instead).

``--viewer`` shows the shapes live in a browser (meshcat, :mod:`twin.viewer`; the URL to open is printed on
stderr): the latest shape at most ``--viewer-rate`` times a second (30), the truth beside it when the source
carries one (the simulator), the interrogator's own shape when the frames carry one (ILLumiSense sensor blocks,
live or replayed), grey when the stream is stale. The viewer's server stops when the run ends, or
with ``--keep-open`` stays until Ctrl-C (not after a Ctrl-C that cut a bounded run short: that ends the command).

``--igtl [HOST:]PORT`` serves the shapes over OpenIGTLink for 3D Slicer (:mod:`twin.igtl`; 127.0.0.1 unless a
host is given; the address is printed on stderr): POLYDATA ``CatheterShape``, TRANSFORM ``CatheterTip`` and,
with a truth, POLYDATA ``CatheterTruth``, at most ``--igtl-rate`` times a second (30).

``--record FILE`` records the frames: a ``.mcap`` file is a rosbag2-compatible MCAP recording with the shapes,
tips, truth and wavelengths as ROS 2 messages (:mod:`twin.io.rosbag`), anything else twin HDF5; give it twice to
write both.

``--foxglove [HOST:]PORT`` serves the live shape to Foxglove over its WebSocket protocol (:mod:`twin.foxglove`;
127.0.0.1 unless a host is given): the reconstruction coloured by its error (or curvature), the truth, the
gratings, the tip pose and the figures, at most ``--foxglove-rate`` times a second, to at most
``--foxglove-clients`` clients.

The fibre model is ``--fiber FILE``, else the one the source knows (the simulator, a recording), else the
reference fibre :meth:`FiberModel.paper` (said on stderr). The calibration is ``--calibration FILE``, else the
one a recording carries, else none.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
from pathlib import Path

from twin import jsonout
from twin.calibration import Calibration
from twin.cli.twist_option import add_twist_argument, check_twist
from twin.fiber import FiberModel
from twin.io.source import open_source, parse_url
from twin.live import LiveLoop, LiveSummary, PrinterSink
from twin.reconstruct import Reconstructor
from twin.reference_errors import TruthError, TruthErrors, VendorDistance, tube_figures, vendor_line

#: one-line help (read by `twin --help` without importing this module)
HELP = "reconstruct shapes live from an interrogator, the simulator or a recording (URL)"

__all__ = ["add_arguments", "run"]

#: schemes whose opener takes the fibre model (to program peak windows, map peaks to gratings, …)
FIBER_AWARE = ("illumisense", "fispec", "hyperion", "synthetic")
#: schemes of real interrogators, which never know the fibre model themselves
HARDWARE = ("illumisense", "fispec", "hyperion")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("url", help="source URL: sim://SCENARIO, illumisense://HOST:PORT, fispec://PORT, "
                                    "hyperion://HOST, replay://FILE, synthetic://?rate=1000")
    parser.add_argument("--fiber", type=Path, help="fibre model (TOML); default: the source's, else the paper's")
    parser.add_argument("--calibration", type=Path, help="calibration (TOML)")
    parser.add_argument("--record", type=Path, metavar="FILE", action="append",
                        help="record the frames to FILE: .mcap a rosbag2-compatible MCAP file (frames, shapes, "
                             "truth; the 'ros' extra), else twin HDF5; may be given more than once")
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    parser.add_argument("--frames", type=int, default=None, help="stop after this many frames")
    parser.add_argument("--method", choices=("material", "paper"), default="material",
                        help="reconstruction method (default material)")
    parser.add_argument("--stale", type=float, default=0.5, help="seconds without a usable frame before 'stale'")
    parser.add_argument("--print-rate", type=float, default=1.0,
                        help="status lines per second (default 1; 0: on state changes only)")
    parser.add_argument("--json", action="store_true", help="print the final summary as one JSON object")
    parser.add_argument("--quiet", action="store_true", help="no status lines")
    parser.add_argument("--viewer", action="store_true", help="show the shapes live in a browser (meshcat)")
    parser.add_argument("--viewer-rate", type=float, default=30.0, metavar="HZ",
                        help="most frames the viewer draws per second (default 30)")
    parser.add_argument("--keep-open", action="store_true",
                        help="keep the viewer serving after the run, until Ctrl-C")
    parser.add_argument("--igtl", metavar="[HOST:]PORT", default=None,
                        help="serve the shapes over OpenIGTLink (3D Slicer) on HOST (127.0.0.1):PORT")
    parser.add_argument("--igtl-rate", type=float, default=30.0, metavar="HZ",
                        help="most OpenIGTLink updates per second (default 30)")
    parser.add_argument("--foxglove", metavar="[HOST:]PORT", default=None,
                        help="serve the shapes to Foxglove (WebSocket) on HOST (127.0.0.1):PORT; the 'ros' extra")
    parser.add_argument("--foxglove-rate", type=float, default=30.0, metavar="HZ",
                        help="most Foxglove updates per second (default 30)")
    parser.add_argument("--foxglove-clients", type=int, default=4, metavar="N",
                        help="most Foxglove clients at once (default 4)")
    add_twist_argument(parser)


def run(args: argparse.Namespace) -> int:
    if args.duration is not None and not args.duration > 0:  # NaN too
        raise ValueError(f"--duration must be a positive number of seconds, got {args.duration}")
    if args.frames is not None and args.frames < 1:
        raise ValueError(f"--frames must be at least 1, got {args.frames}")
    if not (math.isfinite(args.print_rate) and args.print_rate >= 0):
        raise ValueError(f"--print-rate must be a finite number of status lines per second >= 0 (0: on state "
                         f"changes only), got {args.print_rate}")
    if not args.stale > 0:
        raise ValueError(f"--stale must be a positive number of seconds, got {args.stale}")
    if args.viewer and not args.viewer_rate > 0:
        raise ValueError(f"--viewer-rate must be positive, got {args.viewer_rate}")
    if args.igtl is not None and not args.igtl_rate > 0:
        raise ValueError(f"--igtl-rate must be positive, got {args.igtl_rate}")
    if args.foxglove is not None and not args.foxglove_rate > 0:
        raise ValueError(f"--foxglove-rate must be positive, got {args.foxglove_rate}")
    if args.foxglove is not None and args.foxglove_clients < 1:
        raise ValueError(f"--foxglove-clients must be at least 1, got {args.foxglove_clients}")
    check_twist(args)
    fiber = FiberModel.load(args.fiber) if args.fiber else None
    scheme = parse_url(args.url)[0]
    if fiber is None and scheme in HARDWARE:
        # hardware does not know its fibre; the drivers need one to program peak windows and map peaks
        fiber = FiberModel.paper()
        print("twin live: using the reference fibre (FiberModel.paper()); give the sensor's with --fiber FILE",
              file=sys.stderr)
    options = {"fiber": fiber} if (fiber is not None and scheme in FIBER_AWARE) else {}
    first = open_source(args.url, **options)
    pending = [first]

    # a reopening inside the live loop must not block it for start_wait s (the first opening waits for the
    # interrogator to come up; a driver that lost it reconnects by itself)
    reopen = {**options, "start_wait": 0.0} if scheme in HARDWARE else options

    def factory():
        return pending.pop() if pending else open_source(args.url, **reopen)

    sinks: list = []
    viewer_sink = igtl_sink = foxglove_sink = None
    recorders: list = []
    try:
        if fiber is None:
            fiber = first.fiber
        if fiber is None:
            fiber = FiberModel.paper()
            print("twin live: using the reference fibre (FiberModel.paper()); give the sensor's with --fiber FILE",
                  file=sys.stderr)
        calibration = Calibration.load(args.calibration) if args.calibration else getattr(first, "calibration", None)
        rec = Reconstructor(fiber, calibration, method=args.method)
        # the references the frames may carry: the simulator's truth, the interrogator's own shape
        truth, vendor = TruthError(), VendorDistance()
        # the confidence tube for the viewer, OpenIGTLink and --json's figures (the default pipeline's)
        tubes = tube_figures(rec, twist=args.twist)
        uncertainty = None if tubes is None else tubes.uncertainty
        if not args.quiet:
            sinks.append(PrinterSink(sys.stderr if args.json else sys.stdout, rate=args.print_rate,
                                     extras=(truth.status_text, vendor.status_text)))
        for path in args.record or ():
            from twin.io.record import open_recorder

            recorders.append(open_recorder(path, fiber=fiber, calibration=calibration, source_url=args.url,
                                           rate=first.rate))
        sinks.extend(recorders)
        sinks += [truth, vendor]
        if args.json and tubes is not None:  # a propagation per compared frame: only when the figures are asked
            sinks.append(tubes)
        if args.viewer:
            from twin.viewer import Viewer, ViewerConfig, ViewerSink

            viewer = Viewer(ViewerConfig(max_fps=args.viewer_rate), calibration=calibration_label(args, calibration))
            viewer_sink = ViewerSink(viewer, rate=args.viewer_rate, close_viewer=not args.keep_open,
                                     uncertainty=uncertainty)
            sinks.append(viewer_sink)
        if args.igtl is not None:
            from twin.igtl import IgtlServer, IgtlSink, parse_address

            host, port = parse_address(args.igtl)
            try:
                server = IgtlServer(host, port)
            except OSError as exc:  # "[Errno 98] … ('127.0.0.1', 18944)" named neither the option nor the protocol
                reason = os.strerror(exc.errno).lower() if exc.errno else str(exc)
                raise OSError(f"--igtl {args.igtl}: cannot serve OpenIGTLink on {host}:{port}: {reason}") from None
            igtl_sink = IgtlSink(server, rate=args.igtl_rate, uncertainty=uncertainty)
            sinks.append(igtl_sink)
            print(f"twin live: OpenIGTLink on {server.address[0]}:{server.address[1]}", file=sys.stderr, flush=True)
        if args.foxglove is not None:
            from twin.foxglove import FoxgloveServer, FoxgloveSink
            from twin.igtl import parse_address

            fox = FoxgloveServer(*parse_address(args.foxglove), max_clients=args.foxglove_clients)
            try:
                foxglove_sink = FoxgloveSink(fox, rate=args.foxglove_rate,
                                             calibration=args.calibration.name if args.calibration else None)
            except BaseException:
                fox.close()
                raise
            sinks.append(foxglove_sink)
            print(f"twin live: Foxglove on ws://{fox.address[0]}:{fox.address[1]} (open connection, Foxglove "
                  "WebSocket)", file=sys.stderr, flush=True)
    except BaseException:
        first.close()
        for r in recorders:
            r.close()
        if foxglove_sink is not None:
            foxglove_sink.close()
        if viewer_sink is not None:
            viewer_sink.viewer.close()
        if igtl_sink is not None:
            igtl_sink.close()
        raise
    loop = LiveLoop(factory, rec, sinks, stale_after=args.stale)
    summary = loop.run(duration=args.duration, max_frames=args.frames)
    out = summary.as_dict()
    errors = truth.result()
    if errors is not None:
        out["truth"] = dataclasses.asdict(errors)
    elif truth.note is not None:
        out["truth_note"] = truth.note
    out.update(vendor.as_dict())
    if args.json and tubes is not None:
        out.update(tubes.as_dict())
    if recorders:  # the first recording's figures under the old keys; every recording's in "recordings"
        out["recordings"] = [{"file": str(r.path), "frames": r.frames_written, "vendor_dropped": r.vendor_dropped}
                             for r in recorders]
        out["record_file"] = str(recorders[0].path)
        out["recorded_frames"] = recorders[0].frames_written
        out["recorded_vendor_dropped"] = recorders[0].vendor_dropped
    if viewer_sink is not None:
        out["viewer_frames"] = viewer_sink.frames_shown
        out["viewer_calibration"] = viewer_sink.viewer.info.get("calibration")
        out["viewer_errors"] = viewer_sink.errors
        if viewer_sink.errors:
            print(f"twin live: viewer: {viewer_sink.errors} errors, last: {viewer_sink.last_error}", file=sys.stderr)
    if igtl_sink is not None:
        out["igtl_frames"] = igtl_sink.frames_sent
        out["igtl_clients"] = igtl_sink.server.clients_seen
        out["igtl_errors"] = igtl_sink.errors
        out["igtl_bundles_dropped"] = igtl_sink.server.bundles_dropped  # for clients that did not keep up
        out["igtl_evicted"] = igtl_sink.server.evicted
    if foxglove_sink is not None:
        out["foxglove_frames"] = foxglove_sink.frames_sent
        out["foxglove_clients"] = foxglove_sink.server.clients_seen
        out["foxglove_clients_refused"] = foxglove_sink.server.clients_refused
        out["foxglove_clients_forbidden"] = foxglove_sink.server.clients_forbidden  # foreign Host or Origin
        out["foxglove_errors"] = foxglove_sink.errors
    if args.json:
        print(jsonout.dumps(out))
    else:
        print(format_summary(summary, out))
    from twin.cli import interrupted_status

    # Ctrl-C is how an open-ended run ends (0); a run with --duration/--frames it cut short ends the command (130)
    cut_short = interrupted_status(summary.reason == "interrupted",
                                   args.duration is not None or args.frames is not None)
    if viewer_sink is not None and args.keep_open:
        if cut_short:
            viewer_sink.viewer.close()
        else:
            from twin.viewer import keep_open

            keep_open(viewer_sink.viewer)
    return 1 if summary.sink_errors or summary.reason == "source failed" else cut_short


def calibration_label(args: argparse.Namespace, calibration: Calibration | None) -> str | None:
    """How the viewer names the calibration in use: the file given, else the source's own (a recording stores
    the one it was made with), else None (the viewer says "none")."""
    if args.calibration:
        return args.calibration.name
    if calibration is not None:
        return f"the source's ({args.url})"
    return None


def format_summary(summary: LiveSummary, out: dict) -> str:
    s = summary.status
    lines = [
        f"twin live: {summary.duration:.1f} s, {s.frames} frames (arrived at {summary.frames_per_s:.1f} frames/s), "
        f"ended: {summary.reason}",
        f"  lost samples {s.lost_samples} in {s.sequence_gaps} gaps, sequence resets {s.sequence_resets}, "
        f"corrupt sequence numbers {s.sequence_corrupt}, framing errors {s.framing_errors}, "
        f"disconnects {s.disconnects}, reconnects {s.reconnects}, "
        f"stale {s.stale_events} times",
        f"  frames complete {s.frames_complete}, partial {s.frames_partial}, unusable {s.frames_unusable}, "
        f"with missing peaks {s.frames_missing_peaks}, rejected {s.frames_rejected}; invalid nodes "
        f"{s.invalid_nodes}; peaks outside their window {s.peaks_outside_window}",
        f"  source rate {s.rate_hz:.1f} Hz (its timestamps)"
        + (f"; fell behind real time {s.behind_events} times (last arrival rate {s.arrival_hz:.1f} Hz)"
           if s.behind_events else ""),
    ]
    if s.tip is not None:
        lines.append("  last tip (" + ", ".join(f"{1e3 * x:.2f}" for x in s.tip) + ") mm")
    if "truth" in out:
        lines.append("  " + TruthErrors(**out["truth"]).line())
    source = s.source
    if source.get("warnings"):  # e.g. the simulator's MuJoCo start-up notes, collected and explained by the source
        lines.append(f"  source warnings: {source['warnings']} ({source.get('warnings_note', 'see --json')})")
    if "vendor_distance_max_mm" in out:
        lines.append("  " + vendor_line(out))
    if "foxglove_frames" in out:
        lines.append(f"  Foxglove: {out['foxglove_frames']} updates, {out['foxglove_clients']} clients"
                     + (f", {out['foxglove_clients_refused']} refused (over the cap)" if out["foxglove_clients_refused"]
                        else "")
                     + (f", {out['foxglove_clients_forbidden']} forbidden (foreign Host or Origin)"
                        if out["foxglove_clients_forbidden"] else "")
                     + (f", {out['foxglove_errors']} errors" if out["foxglove_errors"] else ""))
    for r in out.get("recordings", ()):
        lines.append(f"  recorded {r['frames']} frames to {r['file']}"
                     + (f"; {r['vendor_dropped']} sensor blocks not stored (a layout other than the "
                        "recording's, docs/protocols-illumisense.md)" if r["vendor_dropped"] else ""))
    for err in summary.sink_errors:
        lines.append(f"  error: {err}")
    return "\n".join(lines)
