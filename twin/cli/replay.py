"""`twin replay FILE`: reconstruct a recording and summarise it.

    twin replay run.h5 [--fiber FILE] [--calibration FILE] [--json] [--register kabsch] [--max-compare N]
    twin replay illumisense_log.txt --fiber sensor.toml

Reads a twin HDF5 recording (``twin live --record``; also one still being written or left by a killed
process) or an ILLumiSense log file (columns assumed: :mod:`twin.io.record`), reconstructs every frame in
batches, and reports frames, time span, lost samples, partial and unusable frames, invalid nodes and the
reconstruction speed. When the recording holds the simulator's truth, it also reports the shape error against
it (:func:`twin.metrics.shape_error`, after ``--register``; on at most ``--max-compare`` frames spread evenly
over the recording, in mm).

The fibre model and calibration are the ones stored in the recording unless ``--fiber`` / ``--calibration``
are given; a vendor log stores none, so ``--fiber`` is needed unless the sensor is the reference fibre.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from twin import jsonout
from twin.calibration import Calibration
from twin.fiber import FiberModel
from twin.io.record import open_recording
from twin.metrics import REGISTRATIONS, shape_error
from twin.reconstruct import Reconstructor

__all__ = ["add_arguments", "replay", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, help="twin HDF5 recording or ILLumiSense log file")
    parser.add_argument("--fiber", type=Path, help="fibre model (TOML); default: the recording's")
    parser.add_argument("--calibration", type=Path, help="calibration (TOML); default: the recording's")
    parser.add_argument("--method", choices=("material", "paper"), default="material")
    parser.add_argument("--register", choices=REGISTRATIONS, default="kabsch",
                        help="registration before comparing with the truth (default kabsch)")
    parser.add_argument("--max-compare", type=int, default=1000,
                        help="frames compared with the truth, spread evenly (default 1000)")
    parser.add_argument("--channels", choices=("cores", "single"), default="cores",
                        help="log files: one channel per core (default) or all cores on one channel")
    parser.add_argument("--cores", type=int, default=None, help="log files with --channels single: core count")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def replay(path: Path, *, fiber: FiberModel | None = None, calibration: Calibration | None = None,
           method: str = "material", register: str = "kabsch", max_compare: int = 1000,
           channels_as: str = "cores", n_cores: int | None = None, batch: int = 2048) -> dict:
    """Reconstruct a recording; return the summary (JSON-ready, lengths in mm where keyed so).

    Raises
    ------
    ValueError
        Unreadable file, or frames that do not fit the fibre model.
    """
    with open_recording(path, channels_as=channels_as, n_cores=n_cores) as reader:
        notes = []
        if fiber is None:
            fiber = reader.fiber
        if fiber is None:
            fiber = FiberModel.paper()
            notes.append("no fibre model in the recording: using the reference fibre (FiberModel.paper())")
        if calibration is None:
            calibration = reader.calibration
        n = len(reader)
        if n and reader.shape != (fiber.n_gratings, fiber.n_cores):
            g, c = reader.shape
            raise ValueError(f"{path}: frames have {g} gratings × {c} cores but the fibre model has "
                             f"{fiber.n_gratings} × {fiber.n_cores}; give the sensor's model with --fiber")
        rec = Reconstructor(fiber, calibration, method=method)
        stride = max(1, math.ceil(n / max(1, max_compare)))
        counts = dict.fromkeys(("frames_complete", "frames_partial", "frames_unusable", "frames_missing_peaks",
                                "invalid_nodes"), 0)
        seqs, t_first, t_last = [], math.nan, math.nan
        errors: dict[str, list[np.ndarray]] = {"mean": [], "max": [], "rms": [], "tip": []}
        truth_note = None
        t_rec = 0.0
        for start, a in reader.chunks(batch):
            m = len(a)
            t0 = time.perf_counter()
            shapes = rec(a.wavelengths)
            t_rec += time.perf_counter() - t0
            n_valid = np.count_nonzero(shapes.valid, axis=-1)
            g = fiber.n_gratings
            counts["frames_complete"] += int(np.count_nonzero(n_valid == g))
            counts["frames_partial"] += int(np.count_nonzero((n_valid < g) & (n_valid > 0)))
            counts["frames_unusable"] += int(np.count_nonzero(n_valid == 0))
            counts["frames_missing_peaks"] += int(np.count_nonzero(np.isnan(a.wavelengths).any(axis=(1, 2))))
            counts["invalid_nodes"] += int(g * m - n_valid.sum())
            seqs.append(a.sequences)
            ts = a.timestamps[np.isfinite(a.timestamps)]
            if ts.size:
                t_first = ts[0] if math.isnan(t_first) else t_first
                t_last = ts[-1]
            truth = reader.truth(start, start + m)
            if truth is not None and truth_note is None:
                idx = np.arange(start, start + m)
                sel = np.flatnonzero((idx % stride == 0) & truth.present & (n_valid == g))
                if sel.size:
                    try:
                        e = shape_error(shapes.positions[sel], truth.positions[sel], s=rec.s, truth_s=truth.s,
                                        register=register)
                    except ValueError as exc:
                        truth_note = f"truth comparison skipped: {exc}"
                    else:
                        for k in errors:
                            errors[k].append(np.atleast_1d(getattr(e, k)))
        seq = np.concatenate(seqs) if seqs else np.zeros(0, np.int64)
        seq = seq[seq >= 0]
        d = np.diff(seq)
        out = {
            "file": str(path),
            "kind": reader.kind,
            "complete": reader.complete,
            "source_url": reader.source_url,
            "fiber": fiber.name,
            "frames": n,
            "time_span": None if math.isnan(t_first) else round(float(t_last - t_first), 6),
            "rate_hz": None if math.isnan(t_first) or t_last <= t_first or n < 2
            else round((n - 1) / float(t_last - t_first), 3),
            "lost_samples": int((d[d > 1] - 1).sum()),
            "sequence_gaps": int(np.count_nonzero(d > 1)),
            "sequence_resets": int(np.count_nonzero(d <= 0)),
            **counts,
            "reconstruct_frames_per_s": round(n / t_rec, 1) if t_rec > 0 else None,
            "skipped_lines": len(reader.errors),
        }
        if reader.has_truth:
            if errors["mean"]:
                e = {k: np.concatenate(v) for k, v in errors.items()}
                out["truth"] = {
                    "frames_compared": int(e["mean"].size),
                    "register": register,
                    "mean_error_mm": round(float(e["mean"].mean()) * 1e3, 4),
                    "max_error_mm": round(float(e["max"].max()) * 1e3, 4),
                    "rms_error_mm": round(float(np.sqrt(np.mean(e["rms"] ** 2))) * 1e3, 4),
                    "tip_error_mm_mean": round(float(e["tip"].mean()) * 1e3, 4),
                    "tip_error_mm_max": round(float(e["tip"].max()) * 1e3, 4),
                }
            else:
                notes.append(truth_note or "truth present but no complete frame to compare")
        if reader.errors:
            notes.append(f"{len(reader.errors)} line(s) skipped, first: {reader.errors[0]}")
        if not reader.complete:
            notes.append("the recording was not closed cleanly (killed writer, or still being written)")
        out["notes"] = notes
        return out


def run(args: argparse.Namespace) -> int:
    fiber = FiberModel.load(args.fiber) if args.fiber else None
    calibration = Calibration.load(args.calibration) if args.calibration else None
    out = replay(args.file, fiber=fiber, calibration=calibration, method=args.method, register=args.register,
                 max_compare=args.max_compare, channels_as=args.channels, n_cores=args.cores)
    if args.json:
        print(jsonout.dumps(out))
        return 0
    span = "?" if out["time_span"] is None else f"{out['time_span']:.2f} s"
    rate = "" if out["rate_hz"] is None else f" ({out['rate_hz']:.1f} Hz)"
    print(f"{out['file']}: {out['kind']}, {out['frames']} frames over {span}{rate}"
          f"{'' if out['complete'] else ', NOT closed cleanly'}")
    print(f"  lost samples {out['lost_samples']} in {out['sequence_gaps']} gaps, sequence resets "
          f"{out['sequence_resets']}")
    print(f"  frames complete {out['frames_complete']}, partial {out['frames_partial']}, unusable "
          f"{out['frames_unusable']}, with missing peaks {out['frames_missing_peaks']}; invalid nodes "
          f"{out['invalid_nodes']}")
    if out["reconstruct_frames_per_s"]:
        print(f"  reconstructed at {out['reconstruct_frames_per_s']:.0f} frames/s")
    if "truth" in out:
        t = out["truth"]
        print(f"  vs truth ({t['frames_compared']} frames, {t['register']}): mean {t['mean_error_mm']:.3f} mm, "
              f"max {t['max_error_mm']:.3f} mm, tip mean {t['tip_error_mm_mean']:.3f} mm, "
              f"max {t['tip_error_mm_max']:.3f} mm")
    for note in out["notes"]:
        print(f"  note: {note}", file=sys.stderr)
    return 0
