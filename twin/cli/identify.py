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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=Path, action="append", required=True,
                        help="a recording of one shape (repeat, each followed by its --truth)")
    parser.add_argument("--truth", type=Path, action="append", required=True,
                        help="the ground-truth curve of the preceding --frames (CSV or NPY, m)")
    parser.add_argument("--out", type=Path, required=True, help="calibration TOML to write")
    parser.add_argument("--fiber", type=Path, help="fibre model TOML (default: the recording's, else the paper's)")
    parser.add_argument("--calibration", type=Path,
                        help="calibration whose λ0 and twist to keep (default: the recording's)")
    parser.add_argument("--formulation", choices=("lsq", "paper"), default="lsq")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def run(args: argparse.Namespace) -> int:
    if len(args.frames) != len(args.truth):
        raise ValueError(f"give one --truth per --frames ({len(args.frames)} recordings, {len(args.truth)} truths)")
    observations, fiber, base = [], None, None
    for frames_path, truth_path in zip(args.frames, args.truth, strict=True):
        with open_recording(frames_path) as rec:
            w = rec.arrays().wavelengths
            fiber = fiber or rec.fiber
            base = base or rec.calibration
        if len(w) == 0:
            raise ValueError(f"{frames_path}: the recording holds no frames")
        points, s = read_truth(truth_path)
        observations.append(Observation(w, points, s, name=frames_path.stem))
    fiber = FiberModel.load(args.fiber) if args.fiber else (fiber or FiberModel.paper())
    base = Calibration.load(args.calibration) if args.calibration else base
    result = identify(fiber, observations, base, formulation=args.formulation)
    cal = result.calibration(base)
    before = paper_cost(fiber, observations, base)
    after = paper_cost(fiber, observations, cal)
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
    return 0
