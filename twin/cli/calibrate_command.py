"""`twin calibrate SOURCE_URL --out calibration.toml`: the two-step calibration as a guided workflow.

Step 1, straight: the catheter lies straight and unloaded; the mean wavelengths become the reference λ0.
Step 2, bend: the catheter is bent in one plane with a single-sign curvature (an arc of ≈ 0.16 1/cm, no
inflection) covering every grating; the bend angle measured along the fibre reveals the cores' intrinsic twist
(docs/math.md §4.2). Many frames are averaged in each step.

On hardware the command asks the user to put the catheter in each pose and press Enter; a simulated source
(``sim://calibration``) puts its catheter in each pose itself. A step that cannot be used — too little bend,
an inflection, a moving catheter, missing peaks — is refused with the reason.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from twin import jsonout
from twin.calibration import Calibration, CalibrationError, two_step
from twin.fiber import FiberModel
from twin.io.source import Source, SourceClosed, open_source

#: one-line help (read by `twin --help` without importing this module)
HELP = "two-step calibration (straight, then an in-plane bend) from a source"

INSTRUCTIONS = {
    "straight": "Lay the catheter straight and unloaded (no bend, no tension), at a steady temperature.",
    "bend": "Bend the catheter in one plane into a single arc (≈ 0.16 1/cm, radius ≈ 6 cm) covering every "
            "grating, with no inflection, and hold it still.",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("url", metavar="SOURCE_URL", help="where the frames come from, e.g. sim://calibration, "
                        "illumisense://127.0.0.1:2055")
    parser.add_argument("--out", type=Path, required=True, help="calibration TOML to write")
    parser.add_argument("--fiber", type=Path, help="fibre model TOML (default: the source's, else the paper's)")
    parser.add_argument("--base", type=Path, help="an existing calibration whose identified Δθ and g to keep")
    parser.add_argument("--frames", type=int, default=100, help="frames averaged per step (default 100)")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for a frame (default 5)")
    parser.add_argument("--min-curvature", type=float, default=5.0,
                        help="smallest usable bend curvature at any grating, 1/m (default 5)")
    parser.add_argument("--allow-sign-change", action="store_true",
                        help="accept a bend with an inflection (trust mod-π unwrapping)")
    parser.add_argument("--yes", action="store_true", help="do not wait for Enter before each step (scripts)")
    parser.add_argument("--json", action="store_true", help="print one JSON object with what was measured")


def record(source: Source, n: int, timeout: float, label: str) -> np.ndarray:
    """Read ``n`` frames, (n, n_gratings, n_cores) nm, with progress on stderr."""
    out = []
    while len(out) < n:
        try:
            frame = source.read(timeout)
        except SourceClosed:
            raise CalibrationError(f"{label} step: the source ended after {len(out)} of {n} frames") from None
        if frame is None:
            raise CalibrationError(f"{label} step: no frame within {timeout} s from {source.url}")
        out.append(frame.wavelengths)
        if len(out) % max(1, n // 10) == 0 or len(out) == n:
            print(f"\r  {label}: {len(out)}/{n} frames", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return np.stack(out)


def _pose(source: Source, step: str, args: argparse.Namespace) -> None:
    print(f"step {'1' if step == 'straight' else '2'} ({step}): {INSTRUCTIONS[step]}", file=sys.stderr)
    if step in getattr(source, "poses", ()):
        print("  the simulated catheter is put in this pose and settles …", file=sys.stderr)
        source.set_pose(step)
    elif not args.yes:
        if not sys.stdin.isatty():
            raise CalibrationError("cannot ask for the pose without a terminal; pass --yes to record at once")
        input("  press Enter when ready … ")


def run(args: argparse.Namespace) -> int:
    if args.frames < 2:
        raise ValueError(f"--frames must be at least 2 (noise and motion are measured), got {args.frames}")
    source = open_source(args.url)
    step = "straight"
    try:
        fiber = FiberModel.load(args.fiber) if args.fiber else (source.fiber or FiberModel.paper())
        base = Calibration.load(args.base) if args.base else None
        steps = {}
        for step in ("straight", "bend"):
            _pose(source, step, args)
            steps[step] = record(source, args.frames, args.timeout, step)
        truth = source.describe() if hasattr(source, "describe") else {}
    except KeyboardInterrupt:  # a bounded run cut short: say where, write nothing (twin.cli's rule: 130)
        from twin.cli import EXIT_INTERRUPTED

        print(f"\ntwin calibrate: interrupted during the {step} step; {args.out} not written", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        source.close()
    try:
        cal, rep = two_step(fiber, steps["straight"], steps["bend"], base=base, min_curvature=args.min_curvature,
                            allow_sign_change=args.allow_sign_change)
    except CalibrationError as exc:
        print(f"twin calibrate: refused: {exc}", file=sys.stderr)
        return 2
    cal = cal.replace(provenance={**cal.provenance, "source": args.url})
    cal.save(args.out)
    result = {
        "out": str(args.out),
        "frames_per_step": args.frames,
        "noise_pm": {k: float(np.nanmedian(np.nanstd(v, axis=0)) * 1e3) for k, v in steps.items()},
        "motion_1_per_m": {"straight": rep.motion[0], "bend": rep.motion[1]},
        "bend_curvature_1_per_m": np.hypot(*rep.bend_curvature.T).tolist(),
        "twist_rad": rep.twist.tolist(),
        "twist_std_rad": rep.twist_std.tolist(),
        "sign_changes": rep.sign_changes,
    }
    if "twist_rad" in truth:
        result["true_twist_rad"] = truth["twist_rad"]
    if args.json:
        print(jsonout.dumps(result, indent=2))
        return 0
    print(report(fiber, result))
    return 0


def report(fiber: FiberModel, r: dict) -> str:
    kap = np.asarray(r["bend_curvature_1_per_m"])
    lines = [
        f"calibration written to {r['out']}",
        f"  {r['frames_per_step']} frames per step; interrogator noise (median std) straight "
        f"{r['noise_pm']['straight']:.2f} pm, bend {r['noise_pm']['bend']:.2f} pm",
        f"  motion within a step (curvature std): straight {r['motion_1_per_m']['straight']:.3f} 1/m, bend "
        f"{r['motion_1_per_m']['bend']:.3f} 1/m",
        f"  bend curvature {kap.min():.1f}–{kap.max():.1f} 1/m at the gratings",
        "",
        f"  {'grating':>8s}{'s (mm)':>9s}{'twist (deg)':>13s}{'± (deg)':>9s}"
        + (f"{'true (deg)':>12s}" if "true_twist_rad" in r else ""),
    ]
    for n in range(fiber.n_gratings):
        row = (f"  {n:8d}{fiber.grating_s[n] * 1e3:9.1f}{np.rad2deg(r['twist_rad'][n]):13.3f}"
               f"{np.rad2deg(r['twist_std_rad'][n]):9.3f}")
        if "true_twist_rad" in r:
            row += f"{np.rad2deg(r['true_twist_rad'][n]):12.3f}"
        lines.append(row)
    return "\n".join(lines)
