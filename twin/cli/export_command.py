"""`twin export REC OUT`: write a recording in another format, with the shapes reconstructed from its frames.

    twin export run.h5 run.mcap            # a rosbag2-compatible MCAP file (ROS 2 messages; the 'ros' extra)
    twin export log.txt run.h5 --fiber sensor.toml

Reads any recording ``twin replay`` reads (twin HDF5, twin MCAP, an ILLumiSense log), reconstructs every frame
with the recording's fibre model and calibration (or ``--fiber`` / ``--calibration``) as ``twin replay`` does,
and writes frames, truth, the interrogator's own shape and (MCAP) the shapes and tips to OUT, whose format its
extension chooses (``.mcap``, else twin HDF5; :func:`twin.io.record.open_recorder`). The messages keep the
frames' receive times. A damaged recording is refused unless ``--salvage`` (then the frames before the damage
are exported).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from twin.calibration import Calibration
from twin.fiber import FiberModel
from twin.frames import frame_vendor
from twin.io.errors import RecordingDamaged
from twin.io.record import Recorder, open_recorder, open_recording
from twin.reconstruct import Reconstructor

__all__ = ["HELP", "add_arguments", "run"]

HELP = "write a recording as MCAP (ROS 2) or HDF5, with its reconstructed shapes"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", type=Path, help="twin HDF5 or MCAP recording, or ILLumiSense log")
    parser.add_argument("out", type=Path, help="file to write: .mcap (MCAP, ROS 2), else twin HDF5")
    parser.add_argument("--fiber", type=Path, help="fibre model (TOML); default: the recording's")
    parser.add_argument("--calibration", type=Path, help="calibration (TOML); default: the recording's")
    parser.add_argument("--salvage", action="store_true", help="a damaged recording: export the frames before it")
    parser.add_argument("--batch", type=int, default=1024, help="frames per batch (default 1024)")


def run(args: argparse.Namespace) -> int:
    if args.out.resolve() == args.recording.resolve():
        raise ValueError(f"{args.out}: the output would replace the recording")
    with open_recording(args.recording) as reader:
        if reader.damaged and not args.salvage:
            raise RecordingDamaged(reader.damage_line())
        fiber = FiberModel.load(args.fiber) if args.fiber else reader.fiber or FiberModel.paper()
        calibration = Calibration.load(args.calibration) if args.calibration else reader.calibration
        rec = Reconstructor(fiber, calibration)
        recorder = open_recorder(args.out, fiber=fiber, calibration=calibration, source_url=reader.source_url,
                                 rate=reader.rate)
        try:
            for start, frames in reader.chunks(max(1, args.batch)):
                m = len(frames)
                shapes = _shapes(rec, frames.wavelengths)
                blocks = reader.vendor(start, start + m)
                received = reader.received(start, start + m)
                if isinstance(recorder, Recorder):  # frames only; the sensor blocks ride on the batch
                    batch = replace(frames, vendor=tuple(blocks)) if blocks else frames
                    recorder.append(batch, received=float(received[0]) if len(received) else None)
                else:
                    vendor = [frame_vendor(blocks, i) for i in range(m)] if blocks else None
                    recorder.append(frames, shapes, received=received, vendor=vendor)
        finally:
            recorder.close()
    print(f"twin export: {recorder.frames_written} frames of {args.recording} to {args.out}")
    return 0


def _shapes(rec: Reconstructor, wavelengths):
    """The shapes as the live loop makes them (peaks outside their window missing; None if the reconstruction
    fails: the frames are still exported)."""
    try:
        return rec.from_strain(rec.strain(wavelengths)[0])
    except Exception:
        return None
