"""`twin run real-jig`: the twin of the AMIRo needle beside the real jig table it must reproduce.

The real table (twin/data/jig/amiro/poses.csv, SOURCE.md beside it) is JHU AMIRo's needle_3CH_4AA_v2 in its
calibration jig: 4 rotations, 7 grooves (0–4 1/m), 3 trials each. The twin (``twin run jig --sensor amiro``,
:data:`sim_interrogator.needle_jig.AMIRO`) simulates that needle in that jig. Both tables are judged the same way
(:func:`twin.calibration.jig.leave_one_rotation_out`, physical model, the gratings in the groove):

* ``rms_strain_residual`` — RMS strain residual of the fit on all rotations (in-sample);
* ``loro_kappa_error_1_per_m`` — each rotation held out in turn: median over held-out rotations, gratings and bent
  curvature levels of the per-level RMS of Δκ = |k̂| − κ;
* ``loro_direction_error_deg`` — the same for the direction, levels ≥ 0.8 1/m, of |mean direction error|.

The twin's figures are medians over ``--seeds`` simulated sessions (one session scatters by a factor ~2, as one
real session would). ``ratio`` is twin / real; the twin reproduces the table when every ratio is within a factor
1.5 (exit status 1 otherwise). ``--budget`` turns each modelled effect off in turn: what each one explains.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from sim_interrogator.needle_jig import AMIRO, MIN_CURVATURE, JigParams, amiro_fiber, loro
from twin import FiberModel, jsonout
from twin.calibration.jig import leave_one_rotation_out, read_poses
from twin.data import jig_dir

__all__ = ["DATA", "EFFECTS", "FACTOR", "KEYS", "budget", "compare", "real_statistics"]

#: The real table and its fibre model.
DATA = jig_dir("amiro")  # package data (twin/data): there after a non-editable install too
#: The twin reproduces a figure when twin / real is within [1/FACTOR, FACTOR].
FACTOR = 1.5
KEYS = ("rms_strain_residual", "loro_kappa_error_1_per_m", "loro_direction_error_deg")
#: The modelled effects and the parameters that turn each off (docs/jig.md, "Error budget").
EFFECTS: dict[str, dict] = {
    "reference bent in the jig's frame": {"reference_bias": (0.0, 0.0)},
    "reference scatter between sessions": {"reference_curvature": 0.0},
    "roll error when re-seated": {"orientation_error_deg": 0.0},
    "twist when pressed in": {"seat_twist_deg": 0.0},
    "stiffness vs groove (conformity)": {"conformity_std": 0.0},
    "seating offsets per groove and trial": {"seat_curvature": 0.0, "pose_curvature": 0.0},
    "groove curvature tolerance": {"groove_tolerance": 0.0},
    "interrogator noise and drift, temperature": {"noise": 0.0, "drift": 0.0, "quantisation": 0.0,
                                                  "session_temperature_k": 0.0, "pose_temperature_k": 0.0,
                                                  "axial_strain": 0.0},
}


def real_statistics(poses_path: str | Path, fiber: FiberModel, gratings) -> dict:
    """The three figures (and the per-level arrays) of a real jig table."""
    poses = read_poses(poses_path, fiber=fiber)
    return leave_one_rotation_out(fiber, poses, gratings=gratings, min_curvature=MIN_CURVATURE).to_dict()


def compare(real: dict, twin: dict) -> dict:
    """``{"real", "twin", "ratio", "within_factor", "passes"}`` for the three figures (ratio = twin / real)."""
    ratio = {k: (twin[k] / real[k] if real[k] else None) for k in KEYS}
    passes = all(r is not None and 1.0 / FACTOR <= r <= FACTOR for r in ratio.values())
    return {"real": {k: real[k] for k in KEYS}, "twin": {k: twin[k] for k in KEYS}, "ratio": ratio,
            "within_factor": FACTOR, "passes": passes}


def budget(params: JigParams, fiber: FiberModel, seeds: int, twin: dict | None = None) -> list[dict]:
    """The twin's figures with every modelled effect on (``twin``, :func:`loro` of ``params``, when already
    computed), with each turned off in turn, with each alone, and with none (the as-built sensor alone, which the
    calibration absorbs: all three figures 0)."""
    rows = [{"effect": "all effects (the twin)", **_figures(twin or loro(params, fiber, seeds))}]
    for name, off in EFFECTS.items():
        rows.append({"effect": f"without {name}", **_figures(loro(replace(params, **off), fiber, seeds))})
    everything = {k: v for off in EFFECTS.values() for k, v in off.items()}
    for name, off in EFFECTS.items():
        others = {k: v for k, v in everything.items() if k not in off}
        rows.append({"effect": f"only {name}", **_figures(loro(replace(params, **others), fiber, seeds))})
    rows.append({"effect": "none of them", **_figures(loro(replace(params, **everything), fiber, seeds))})
    return rows


def _figures(d: dict) -> dict:
    return {k: d[k] for k in KEYS}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--poses", metavar="POSES.csv", default=str(DATA / "poses.csv"),
                        help="the real jig table (default twin/data/jig/amiro/poses.csv)")
    parser.add_argument("--fiber", metavar="FIBER.toml", default=str(DATA / "needle.toml"),
                        help="its fibre model (default twin/data/jig/amiro/needle.toml)")
    parser.add_argument("--gratings", default="0,1,2",
                        help="gratings in the groove, comma-separated (default 0,1,2: the tip grating is at the "
                        "groove's end)")
    parser.add_argument("--seeds", type=int, default=10, help="simulated sessions (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    parser.add_argument("--budget", action="store_true",
                        help="also turn each modelled effect off in turn (the error budget)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def run(args: argparse.Namespace) -> int:
    try:
        gratings = [int(x) for x in args.gratings.split(",")]
    except ValueError:
        raise ValueError(f"--gratings: expected indices like 0,1,2, got {args.gratings!r}") from None
    fiber = FiberModel.load(args.fiber)
    real = real_statistics(args.poses, fiber, gratings)
    params = replace(AMIRO, seed=args.seed)
    twin = loro(params, amiro_fiber(), args.seeds)
    result = compare(real, twin)
    result["seeds"] = args.seeds
    result["twin_sessions"] = twin["sessions"]
    if args.budget:
        result["budget"] = budget(params, amiro_fiber(), args.seeds, twin)
    status = 0 if result["passes"] else 1
    if args.json:
        print(jsonout.dumps(result, indent=2))
        return status
    out = sys.stdout
    print(f"Real jig table {args.poses} beside its twin (median of {args.seeds} sessions); gratings {gratings}",
          file=out)
    print(f"{'':34s}{'real':>10s}{'twin':>10s}{'ratio':>8s}", file=out)
    names = {"rms_strain_residual": "in-sample RMS strain residual (µε)",
             "loro_kappa_error_1_per_m": "LORO |Δκ| (1/m)",
             "loro_direction_error_deg": "LORO |Δdir| (deg)"}
    scale = {"rms_strain_residual": 1e6}
    for k in KEYS:
        f = scale.get(k, 1.0)
        print(f"{names[k]:34s}{result['real'][k] * f:10.4g}{result['twin'][k] * f:10.4g}{result['ratio'][k]:8.2f}",
              file=out)
    print(f"{'PASS' if result['passes'] else 'FAIL'}: every ratio within a factor {FACTOR:g}", file=out)
    if args.budget:
        print(f"\nError budget (twin, median of {args.seeds} sessions):", file=out)
        print(f"{'':48s}{'µε':>8s}{'|Δκ|':>9s}{'|Δdir|':>9s}", file=out)
        for row in result["budget"]:
            print(f"{row['effect']:48s}{row['rms_strain_residual'] * 1e6:8.2f}{row['loro_kappa_error_1_per_m']:9.4f}"
                  f"{row['loro_direction_error_deg']:8.2f}°", file=out)
    return status
