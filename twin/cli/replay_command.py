"""`twin replay FILE`: reconstruct a recording and print its summary (:func:`twin.replay_summary.summarize`).

    twin replay run.h5 [--fiber FILE] [--calibration FILE] [--json [--twist RATE]] [--register kabsch]
                       [--compare-rate HZ]
    twin replay illumisense_log.txt --fiber sensor.toml
    twin replay cut.h5 --salvage

Reads a twin HDF5 recording (``twin live --record``; also one still being written or left by a killed
process) or an ILLumiSense log file (:mod:`twin.io.illumisense.log`), reconstructs every frame in
batches — the live loop over the file at full speed, so it reports what ``twin live replay://FILE`` reports —
frames, time span, lost samples, partial and unusable frames, invalid nodes and the reconstruction throughput of
the run. When the recording holds the simulator's truth, it also reports the shape error against it (after
``--register``; on the first complete frame of each 0.1 s of the recording's time, as ``twin live`` compares,
or on ``--compare-rate`` frames a second, 0 for every complete frame; in mm). When the recording (a
twin HDF5 recording or an ILLumiSense log) carries the interrogator's own shape (sensor blocks), it reports the
distance between that shape and ours after a rigid registration (``vendor_distance_*_mm``,
:mod:`twin.reference_errors`). With ``--json`` it also reports the confidence tube on the same frames
(``mean_sigma_mm``; ``coverage_95`` with a truth), with the catheter's unmeasured twist rate ``--twist RATE``
states (rad/m, :mod:`twin.cli.twist_option`). docs/figures.md defines every figure.

A damaged recording (cut short, or with chunks that fail their checksum) is an error (one line: how many frames
are readable, what is damaged; exit status 2) unless ``--salvage`` is given: then the frames before the damage
are reconstructed and the damage is reported with them (exit status 0).

The fibre model and calibration are the ones stored in the recording unless ``--fiber`` / ``--calibration``
are given; a vendor log stores none, so ``--fiber`` is needed unless the sensor is the reference fibre.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from twin import jsonout
from twin.calibration import Calibration
from twin.cli.twist_option import add_twist_argument, check_twist
from twin.fiber import FiberModel
from twin.metrics import REGISTRATIONS
from twin.reference_errors import vendor_line
from twin.replay_summary import ReplaySummary, summarize

#: one-line help (read by `twin --help` without importing this module)
HELP = "reconstruct a recording (twin HDF5 or MCAP, ILLumiSense log) and summarise it"

__all__ = ["add_arguments", "format_summary", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, help="twin HDF5 recording or ILLumiSense log file")
    parser.add_argument("--fiber", type=Path, help="fibre model (TOML); default: the recording's")
    parser.add_argument("--calibration", type=Path, help="calibration (TOML); default: the recording's")
    parser.add_argument("--method", choices=("material", "paper"), default="material")
    parser.add_argument("--register", choices=REGISTRATIONS, default="kabsch",
                        help="registration before comparing with the truth (default kabsch)")
    parser.add_argument("--compare-rate", type=float, default=10.0, metavar="HZ",
                        help="frames compared with the truth and the interrogator's shape per second of the "
                             "recording's time, as twin live compares them (default 10; 0: every complete frame)")
    parser.add_argument("--channels", choices=("cores", "single"), default="cores",
                        help="log files: one channel per core (default) or all cores on one channel")
    parser.add_argument("--cores", type=int, default=None, help="log files with --channels single: core count")
    parser.add_argument("--salvage", action="store_true",
                        help="a damaged recording: reconstruct the frames before the damage and report it "
                             "(default: a damaged recording is an error, exit status 2)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    add_twist_argument(parser)


def run(args: argparse.Namespace) -> int:
    if not args.compare_rate >= 0:  # NaN too
        raise ValueError(f"--compare-rate must be a number of frames per second >= 0, got {args.compare_rate}")
    check_twist(args)
    if args.twist and not args.json:
        raise ValueError(f"--twist {args.twist:g}: the confidence tube it widens is reported with --json only")
    fiber = FiberModel.load(args.fiber) if args.fiber else None
    calibration = Calibration.load(args.calibration) if args.calibration else None
    summary = summarize(args.file, fiber=fiber, calibration=calibration, method=args.method, register=args.register,
                        compare_rate=args.compare_rate or None, channels_as=args.channels, n_cores=args.cores,
                        salvage=args.salvage, handle_signals=True, tube=args.json,
                        twist=args.twist)
    if args.json:
        print(jsonout.dumps(summary.as_dict()))
    else:
        print(format_summary(summary))
    for note in summary.notes:
        print(f"  note: {note}", file=sys.stderr)
    return 0


def format_summary(s: ReplaySummary) -> str:
    """The summary as a few human lines (lengths in mm)."""
    span = "?" if s.time_span is None else f"{s.time_span:.2f} s"
    rate = "" if s.recorded_rate_hz is None else f" ({s.recorded_rate_hz:.1f} Hz)"
    state = ""
    if s.damaged:
        state = f", DAMAGED: {s.frames} of {s.frames_recorded} frames readable"
    elif not s.complete:
        state = ", NOT closed cleanly"
    lines = [
        f"{s.file}: {s.kind}, {s.frames} frames over {span}{rate}{state}",
        f"  lost samples {s.lost_samples} in {s.sequence_gaps} gaps, sequence resets {s.sequence_resets}, "
        f"corrupt sequence numbers {s.sequence_corrupt}",
        f"  frames complete {s.frames_complete}, partial {s.frames_partial}, unusable {s.frames_unusable}, "
        f"with missing peaks {s.frames_missing_peaks}; invalid nodes {s.invalid_nodes}; peaks outside their window "
        f"{s.peaks_outside_window}",
    ]
    if s.processing_frames_per_s:
        lines.append(f"  reconstruction throughput {s.processing_frames_per_s:.0f} frames/s (frames ÷ wall time "
                     "spent reconstructing in this run, first-call compilation included; speed: twin bench)")
    if s.truth is not None:
        lines.append("  " + s.truth.line())
    if s.vendor:
        lines.append("  " + vendor_line(s.vendor))
    for d in s.damage:
        lines.append(f"  damage: {d}")
    return "\n".join(lines)
