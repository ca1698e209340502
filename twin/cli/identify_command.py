"""`twin identify --frames FILE --truth FILE … --out calibration.toml`: identify Δθ and g = r·S_ε.

Each ``--frames`` recording (a twin HDF5 recording or an ILLumiSense log) is paired with the ``--truth`` file
given after it: the centreline of the shape the catheter held, as a CSV or NPY of points in m, with arc lengths
when known (:func:`twin.calibration.identify.read_truth` documents the format). Use several shapes, planar
and spatial: from planar shapes alone Δθ is only weakly identifiable.
``twin run static-shapes --record DIR`` writes such pairs from the twin.

The default fits [Δθ, g] on the smooth registered residual with uncertainties; ``--formulation paper`` fits the
paper's [Δθ, r, S_ε] with the max-distance cost and reports why r and S_ε are not separately determined.
The result is written as a calibration that keeps the reference wavelengths and twist of ``--calibration``
(or of the first recording).

Validation: ``--validate-frames F --validate-truth T`` pairs (any number) are shapes the fit did not see; their
max error (the paper's metric: ICP + ±0.5 mm translation search) before and after identification is reported
beside the fitted shapes', in the text and in ``--json`` (``validation``). A fit that only improves the shapes it
saw has absorbed something else than Δθ and g.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from twin import jsonout
from twin.calibration import Calibration
from twin.calibration.identify import Observation, identify, paper_cost, read_truth
from twin.fiber import FiberModel
from twin.io.record import open_recording

#: one-line help (read by `twin --help` without importing this module)
HELP = "identify Δθ and g = r·S_ε from recordings of shapes of known geometry"

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=Path, action="append", required=True,
                        help="a recording of one shape (repeat, each followed by its --truth)")
    parser.add_argument("--truth", type=Path, action="append", required=True,
                        help="the ground-truth curve of the preceding --frames (CSV or NPY, m)")
    parser.add_argument("--out", type=Path, required=True, help="calibration TOML to write")
    parser.add_argument("--fiber", type=Path, help="fibre model TOML (default: the recording's, else the paper's)")
    parser.add_argument("--calibration", type=Path,
                        help="calibration whose λ0 and twist to keep (default: the recording's)")
    parser.add_argument("--validate-frames", type=Path, action="append", default=[],
                        help="a recording of a shape NOT used in the fit (repeat, each followed by its "
                             "--validate-truth): errors before and after identification")
    parser.add_argument("--validate-truth", type=Path, action="append", default=[],
                        help="the ground-truth curve of the preceding --validate-frames (CSV or NPY, m)")
    parser.add_argument("--formulation", choices=("lsq", "paper"), default="lsq")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def _observations(frames: list[Path], truths: list[Path], what: str):
    """Observations from recording/truth pairs, and the first recording's fibre and calibration."""
    if len(frames) != len(truths):
        raise ValueError(f"give one --{what}truth per --{what}frames ({len(frames)} recordings, {len(truths)} truths)")
    observations, fiber, base = [], None, None
    for frames_path, truth_path in zip(frames, truths, strict=True):
        with open_recording(frames_path) as rec:
            if rec.damaged:
                raise ValueError(rec.damage_line())
            w = rec.frames(truth=False).wavelengths
            fiber = fiber or rec.fiber
            base = base or rec.calibration
        if len(w) == 0:
            raise ValueError(f"{frames_path}: the recording holds no frames")
        points, s = read_truth(truth_path)
        observations.append(Observation(w, points, s, name=frames_path.stem))
    return observations, fiber, base


def run(args: argparse.Namespace) -> int:
    observations, fiber, base = _observations(args.frames, args.truth, "")
    held_out, _, _ = _observations(args.validate_frames, args.validate_truth, "validate-")
    fiber = FiberModel.load(args.fiber) if args.fiber else (fiber or FiberModel.paper())
    base = Calibration.load(args.calibration) if args.calibration else base
    result = identify(fiber, observations, base, formulation=args.formulation)
    cal = result.calibration(base)
    before = paper_cost(fiber, observations, base)
    after = paper_cost(fiber, observations, cal)
    if held_out:
        val_before = paper_cost(fiber, held_out, base)
        val_after = paper_cost(fiber, held_out, cal)
        cal = cal.replace(provenance={**cal.provenance, "validated_on": ", ".join(o.name for o in held_out),
                                      "validation_max_error_m": float(val_after.max())})
    cal.save(args.out)
    out = {
        "out": str(args.out),
        "formulation": result.formulation,
        "delta_theta": result.delta_theta,
        "delta_theta_std": result.delta_theta_std,
        "g_um": result.gain * 1e6,
        "g_std_um": result.gain_std * 1e6,
        "shapes": [o.name for o in observations],
        "max_error_before_mm": (before * 1e3).tolist(),
        "max_error_after_mm": (after * 1e3).tolist(),
        "nfev": result.nfev,
    }
    if held_out:
        out["validation"] = {"shapes": [o.name for o in held_out],
                             "max_error_before_mm": (val_before * 1e3).tolist(),
                             "max_error_after_mm": (val_after * 1e3).tolist(),
                             "worst_before_mm": float(val_before.max() * 1e3),
                             "worst_after_mm": float(val_after.max() * 1e3)}
    if result.degeneracy:
        out |= {"radius_um": result.radius * 1e6, "strain_sensitivity": result.strain_sensitivity,
                "degeneracy": result.degeneracy}
    if args.json:
        print(jsonout.dumps(out, indent=2))
        return 0
    print(f"identified ({result.formulation}) from {len(observations)} shapes, written to {args.out}")
    if result.formulation == "lsq":
        print(f"  Δθ = {result.delta_theta:.5f} ± {result.delta_theta_std:.5f} rad "
              f"({np.rad2deg(result.delta_theta):.3f}°), g = r·S_ε = {result.gain * 1e6:.4f} ± "
              f"{result.gain_std * 1e6:.4f} µm")
    else:
        print(f"  Δθ = {result.delta_theta:.5f} rad, g = r·S_ε = {result.gain * 1e6:.4f} µm")
        print(f"  {result.degeneracy}")
    print(f"  {'shape':20s}{'max error before (mm)':>24s}{'after':>10s}   (ICP + translation, the paper's metric)")
    for o, b, a in zip(observations, before, after, strict=True):
        print(f"  {o.name:20s}{b * 1e3:24.3f}{a * 1e3:10.3f}")
    if held_out:
        print("  validation, shapes not fitted:")
        for o, b, a in zip(held_out, val_before, val_after, strict=True):
            print(f"  {o.name:20s}{b * 1e3:24.3f}{a * 1e3:10.3f}")
        print(f"  worst validation error {val_after.max() * 1e3:.3f} mm after identification "
              f"({val_before.max() * 1e3:.3f} mm before)")
    else:
        print("  (no --validate-frames: errors on the fitted shapes alone say little about other shapes)")
    return 0
