"""`twin jig-calibrate` and `twin jig-validate`: the jig workflow on the command line (docs/jig.md).

Both commands live here; :mod:`twin.cli` registers this module for each and the command name (``args._command``,
set by the router before ``add_arguments``) picks the one to build and run.

* ``twin jig-calibrate POSES.csv --fiber FIBER.toml --out calibration.toml [--model physical|matrix|linear|nuisance]``
* ``twin jig-validate POSES.csv --calibration calibration.toml`` — the calibration's errors on these poses;
  ``twin jig-validate POSES.csv --fiber FIBER.toml --holdout-orientations 3.1416,4.7124`` — fit (every model by
  default, the plain linear baseline among them) on the other orientations and validate on these: how to judge a
  calibration. Every report ends with the one score (:mod:`twin.calibration.jig.score`) of each model.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from twin import jsonout
from twin.calibration import Calibration, jig
from twin.calibration.jig.score import ALL_LEVELS, CLINICAL
from twin.fiber import FiberModel

CALIBRATE, VALIDATE = "jig-calibrate", "jig-validate"


#: one-line help of each command this module serves (read by `twin --help` without importing it)
HELP = {
    "jig-calibrate": "fit a calibration from jig poses (grooves of known curvature)",
    "jig-validate": "curvature and bend-direction errors of a calibration on jig poses",
}

def add_arguments(parser: argparse.ArgumentParser) -> None:
    command = parser.get_default("_command") or parser.prog.rsplit(" ", 1)[-1]
    parser.add_argument("poses", metavar="POSES.csv", help="jig poses: orientation_rad, curvature_1_per_m, "
                        "g{n}_c{i} wavelengths in nm [, std_g{n}_c{i}] (docs/jig.md)")
    if command == VALIDATE:
        parser.add_argument("--calibration", metavar="CAL.toml", help="calibration to validate")
        parser.add_argument("--fiber", metavar="FIBER.toml",
                            help="fibre model (needed with --holdout-orientations, or for a non-jig calibration)")
        parser.add_argument("--holdout-orientations", metavar="LIST",
                            help="cross-validation: fit on the other orientations and validate on these (rad, or "
                            "with a deg suffix: 180deg,270deg)")
        parser.add_argument("--model", choices=(*jig.MODELS, "both", "all"), default="all",
                            help="with --holdout-orientations or --leave-one-rotation-out: the model(s) to fit "
                            "(default all; both = physical and matrix)")
        parser.add_argument("--leave-one-rotation-out", action="store_true",
                            help="hold out each orientation in turn (fit on the others): in-sample RMS strain "
                            "residual and the median curvature and direction errors (docs/jig.md)")
        parser.add_argument("--fit-roll", action="store_true",
                            help="fit the jig roll to these poses instead of using the calibration's (remounted)")
        parser.add_argument("--no-jig-zero", action="store_true",
                            help="score the curvature change from each rotation's reference as it is, without "
                            "adding the jig's zero (how much less its bent grooves bend the sensor than labelled) the "
                            "calibration carries "
                            "(docs/jig.md, \"The jig's zero\")")
        parser.add_argument("--max-error", type=float, metavar="1/m",
                            help="exit with status 1 if a curvature error (κ ≥ --min-curvature) exceeds this")
        parser.add_argument("--max-direction-error-deg", type=float, metavar="DEG",
                            help="exit with status 1 if a bend direction error (κ ≥ --min-curvature) exceeds this")
    else:
        parser.add_argument("--fiber", metavar="FIBER.toml", required=True, help="nominal fibre model")
        parser.add_argument("--out", metavar="CAL.toml", required=True, help="calibration file to write")
        parser.add_argument("--model", choices=jig.MODELS, default="physical",
                            help="physical: core angles and gains g = r·S_ε; matrix: k = M e; linear: the plain "
                            "baseline k = M e (least squares, unweighted, references as they are); nuisance: "
                            "physical with the jig's errors estimated beside it (default physical)")
        parser.add_argument("--orientations", metavar="LIST",
                            help="fit only these orientations (rad, or with a deg suffix); default all")
    parser.add_argument("--trust-references", action="store_true",
                        help="take each orientation's curvature-0 rows as exact instead of fitting its zero")
    parser.add_argument("--gratings", metavar="LIST",
                        help="gratings in the groove, e.g. 0,1,2 or 0-2 (default: all, or the calibration's)")
    parser.add_argument("--min-curvature", type=float, default=0.8, metavar="1/m",
                        help="summaries cover curvatures at or above this (default 0.8 1/m)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def run(args: argparse.Namespace) -> int:
    return _validate(args) if args._command == VALIDATE else _calibrate(args)


# ------------------------------------------------------------------------------------------ parsing


def _gratings(text: str | None) -> list[int] | None:
    if text is None:
        return None
    out: list[int] = []
    try:
        for part in text.split(","):
            lo, _, hi = part.strip().partition("-")
            out.extend(range(int(lo), int(hi) + 1) if hi else [int(lo)])
    except ValueError:
        raise ValueError(f"--gratings: expected indices like 0,1,2 or 0-2, got {text!r}") from None
    return out


def _angles(text: str | None, option: str) -> np.ndarray | None:
    if text is None:
        return None
    out = []
    for part in text.split(","):
        p = part.strip().lower()
        deg = p.endswith(("deg", "°"))
        p = p.removesuffix("deg").removesuffix("°").strip()
        try:
            v = float(p)
        except ValueError:
            raise ValueError(f"{option}: expected angles in rad (or with a deg suffix), got {part.strip()!r}") from None
        out.append(np.deg2rad(v) if deg else v)
    return np.array(out)


def _models(choice: str) -> tuple[str, ...]:
    return {"all": jig.MODELS, "both": ("physical", "matrix")}.get(choice, (choice,))


def _score_line(name: str, v) -> str:
    """One line: the score in both bands and, when the model states intervals, their 95 % coverage."""
    parts = []
    for bands in (CLINICAL, ALL_LEVELS):
        sc = v.score(bands)
        d = None if sc.direction_error is None else np.rad2deg(sc.direction_error)
        parts.append(f"{bands.name}: {_fmt(sc.magnitude_error, '.4f')} 1/m, {_fmt(d, '.2f')}°")
    cover = v.coverage_95 if hasattr(v, "coverage_95") else v.coverage()[0]
    tail = "" if cover is None else f"; 95 % coverage {cover:.1%}"
    return f"{name:>9s}  " + "; ".join(parts) + tail


def _zero_text(zero) -> str:
    if zero is None:
        return "no jig zero added"
    return "jig zero added (along/across, 1/m): " + ", ".join(f"{a:+.3f}/{b:+.3f}" for a, b in zero)


def _deg_list(values) -> str:
    return ", ".join(f"{np.rad2deg(v):.4g}°" for v in values)


def _fmt(x, spec: str) -> str:
    return "—" if x is None else format(x, spec)


# ------------------------------------------------------------------------------------------ calibrate


def _calibrate(args: argparse.Namespace) -> int:
    fiber = FiberModel.load(args.fiber)
    poses = jig.read_poses(args.poses, fiber=fiber)
    result = jig.fit(fiber, poses, model=args.model, gratings=_gratings(args.gratings),
                     orientations=_angles(args.orientations, "--orientations"),
                     trust_references=args.trust_references)
    used = poses if args.orientations is None else poses.select(
        jig.match_orientations(poses, _angles(args.orientations, "--orientations")))
    check = jig.validate(result.calibration, used, fiber=fiber, min_curvature=args.min_curvature, jig_zero=True)
    result.calibration.save(args.out)
    if args.json:
        print(jsonout.dumps({"poses": args.poses, "fiber": args.fiber, "out": args.out, "fit": result.to_dict(),
                          "in_sample": check.to_dict()}, indent=2))
        return 0
    out = sys.stdout
    levels = np.unique(np.abs(poses.curvature[~poses.is_reference]))
    print(f"Jig calibration ({result.model} model) of {args.fiber} from {args.poses}", file=out)
    print(f"  {poses.n_poses} rows; fitted {result.n_poses} bent poses at {result.orientations.size} orientations "
          f"({_deg_list(result.orientations)}), grooves {levels.min():g}–{levels.max():g} 1/m", file=out)
    roll_std = "" if not np.isfinite(result.roll_std) else f" ± {np.rad2deg(result.roll_std):.3f}°"
    print(f"  roll α = {np.rad2deg(result.roll):.3f}°{roll_std} (bend direction in the fibre frame at orientation 0)\n",
          file=out)
    s = fiber.grating_s
    forward = result.matrix is None  # physical, nuisance: angles and gains; matrix, linear: the map
    if forward:
        print(f"{'grating':>7s}{'s (mm)':>8s}{'core':>6s}{'angle (°)':>21s}{'g (µm)':>20s}{'R²':>10s}"
              f"{'rms e (ppm)':>12s}{'χ²/dof':>10s}", file=out)
    else:
        print(f"{'grating':>7s}{'s (mm)':>8s}{'core':>6s}{'M row k_x (1/m)':>22s}{'M row k_y (1/m)':>22s}"
              f"{'angle (°)':>11s}{'g (µm)':>9s}{'R²':>10s}", file=out)
    for i, n in enumerate(result.gratings):
        for c in range(fiber.n_cores):
            head = f"{n:7d}{s[n] * 1e3:8.1f}" if c == 0 else " " * 15
            ang, g = np.rad2deg(result.core_angles[i, c]), result.gains[i, c] * 1e6
            if forward:
                tail = ""
                if c == 0:
                    chi = "" if result.chi2_reduced is None else f"{result.chi2_reduced[i]:10.4g}"
                    tail = f"{result.explained[i]:10.6f}{result.rms_strain_residual[i] * 1e6:12.3f}{chi}"
                print(f"{head}{c:6d}{ang:11.3f} ± {np.rad2deg(result.core_angles_std[i, c]):6.3f}"
                      f"{g:10.2f} ± {result.gains_std[i, c] * 1e6:6.2f}{tail}", file=out)
            else:
                m, ms = result.matrix[i, :, c], result.matrix_std[i, :, c]
                tail = f"{result.explained[i]:10.6f}" if c == 0 else ""
                print(f"{head}{c:6d}{m[0]:12.1f} ± {ms[0]:7.1f}{m[1]:12.1f} ± {ms[1]:7.1f}{ang:11.3f}{g:9.2f}{tail}",
                      file=out)
    if result.nuisance is not None:
        nz = result.nuisance
        print(f"\nJig errors estimated ({', '.join(sorted(nz.terms))}): roll at each rotation "
              f"{', '.join(f'{x:+.2f}°' for x in np.rad2deg(np.angle(nz.gain)))}; gain "
              f"{', '.join(f'{x:.3f}' for x in np.abs(nz.gain))}; reference pose (jig frame, along/across the bend, "
              f"mean over rotations) {', '.join(f'{a:+.3f}/{b:+.3f}' for a, b in nz.reference.mean(axis=0))} 1/m",
              file=out)
    prov = result.calibration.provenance
    print("\nJig zero (the bent grooves' shortfall from their labels in the jig's frame, along/across the bend, 1/m; "
          "median over the rotations; added to curvatures zeroed in this jig): "
          + ", ".join(f"grating {int(n)} {a:+.3f}/{b:+.3f}" for n, (a, b) in
                      zip(result.gratings, prov["jig_zero_1_per_m"], strict=True)), file=out)
    for o, row in zip(result.orientations, prov["jig_rotation_zeros_1_per_m"], strict=True):
        print(f"  {np.rad2deg(o):6.4g}°: " + ", ".join(f"{a:+.3f}/{b:+.3f}" for a, b in row), file=out)
    summ = check.summary()
    print(f"\nIn-sample (the fit's own poses), κ ≥ {args.min_curvature:g} 1/m: max |Δκ| = "
          f"{_fmt(summ['max_abs_magnitude_error_1_per_m'], '.4f')} 1/m, max |Δdir| = "
          f"{_fmt(summ['max_abs_direction_error_deg'], '.3f')}°", file=out)
    if result.unfixed_gratings.size:
        print(f"Gratings not fixed by the jig (nominal design kept): "
              f"{', '.join(str(int(n)) for n in result.unfixed_gratings)}", file=out)
    for w in result.warnings:
        print(f"warning: {w}", file=out)
    print(f"Wrote {args.out}. Judge the calibration on poses it did not see: twin jig-validate {args.poses} "
          f"--fiber {args.fiber} --holdout-orientations <some of the orientations>", file=out)
    return 0


# ------------------------------------------------------------------------------------------ validate


def _validate(args: argparse.Namespace) -> int:
    fiber = FiberModel.load(args.fiber) if args.fiber else None
    poses = jig.read_poses(args.poses, fiber=fiber)
    gratings = _gratings(args.gratings)
    results = []
    if args.leave_one_rotation_out:
        return _leave_one_rotation_out(args, fiber, poses, gratings)
    if args.holdout_orientations is not None:
        if fiber is None:
            raise ValueError("--holdout-orientations refits the calibration: give the fibre model with --fiber")
        if args.calibration:
            raise ValueError("--holdout-orientations fits its own calibrations; drop --calibration (or validate it "
                             "without --holdout-orientations)")
        holdout = _angles(args.holdout_orientations, "--holdout-orientations")
        for model in _models(args.model):
            result, check = jig.cross_validate(fiber, poses, holdout, model=model, gratings=gratings,
                                               trust_references=args.trust_references,
                                               min_curvature=args.min_curvature, jig_zero=not args.no_jig_zero)
            if args.fit_roll:
                test = poses.select(jig.match_orientations(poses, holdout))
                check = jig.validate(result.calibration, test, fiber=fiber, fit_roll=True,
                                     min_curvature=args.min_curvature, jig_zero=not args.no_jig_zero)
            results.append({"model": model, "fit": result, "validation": check})
    else:
        if not args.calibration:
            raise ValueError("give --calibration CAL.toml to validate, or --fiber FIBER.toml with "
                             "--holdout-orientations to cross-validate")
        cal = Calibration.load(args.calibration)
        check = jig.validate(cal, poses, fiber=fiber, gratings=gratings, fit_roll=args.fit_roll,
                             min_curvature=args.min_curvature, jig_zero=not args.no_jig_zero)
        results.append({"model": cal.provenance.get("jig_model", "calibration"), "fit": None, "validation": check})

    tolerances = args.max_error is not None or args.max_direction_error_deg is not None
    max_err = np.inf if args.max_error is None else args.max_error
    max_dir = np.inf if args.max_direction_error_deg is None else args.max_direction_error_deg
    for r in results:
        r["passes"] = r["validation"].passes(max_err, max_dir) if tolerances else None
    ok = all(r["passes"] for r in results) if tolerances else None
    if args.json:
        print(jsonout.dumps({
            "poses": args.poses,
            "calibration": args.calibration,
            "holdout_orientations_rad": None if args.holdout_orientations is None else
            _angles(args.holdout_orientations, "--holdout-orientations").tolist(),
            "results": [{"model": r["model"], "fit": None if r["fit"] is None else r["fit"].to_dict(),
                         "validation": r["validation"].to_dict(), "passes": r["passes"]} for r in results],
            "passes": ok,
        }, indent=2))
        return 0 if ok in (None, True) else 1
    out = sys.stdout
    for r in results:
        v: jig.JigValidation = r["validation"]
        if r["fit"] is not None:
            head = (f"{r['model']} model — fit on {_deg_list(r['fit'].orientations)}; validated on "
                    f"{_deg_list(np.unique(v.orientation))} ({v.curvature.size} bent poses)")
        else:
            head = (f"{args.calibration} ({r['model']}) on {args.poses}: orientations "
                    f"{_deg_list(np.unique(v.orientation))} ({v.curvature.size} bent poses)")
        roll = f"roll {np.rad2deg(v.roll):.3f}°" + (" (fitted to these poses)" if v.roll_fitted else "")
        print(f"{head}; {roll}; {_zero_text(v.jig_zero)}", file=out)
        print(f"{'grating':>7s}{'s (mm)':>8s}{'κ (1/m)':>9s}{'n':>4s}{'Δκ mean':>10s}{'|Δκ| max':>10s}"
              f"{'Δdir mean':>11s}{'|Δdir| max':>12s}", file=out)
        for row in v.table():
            inv = f"  ({row['n_invalid']} unsolvable)" if row["n_invalid"] else ""
            print(f"{row['grating']:7d}{row['s_m'] * 1e3:8.1f}{row['curvature_1_per_m']:9.3f}{row['n']:4d}"
                  f"{_fmt(row['magnitude_error_mean_1_per_m'], '+10.4f')}"
                  f"{_fmt(row['magnitude_error_max_abs_1_per_m'], '10.4f')}"
                  f"{_fmt(row['direction_error_mean_deg'], '+10.3f')}°"
                  f"{_fmt(row['direction_error_max_abs_deg'], '11.3f')}°{inv}", file=out)
        s = v.summary()
        verdict = "" if r["passes"] is None else ("   PASS" if r["passes"] else "   FAIL")
        print(f"κ ≥ {v.min_curvature:g} 1/m: max |Δκ| = {_fmt(s['max_abs_magnitude_error_1_per_m'], '.4f')} 1/m, "
              f"max |Δdir| = {_fmt(s['max_abs_direction_error_deg'], '.3f')}°{verdict}", file=out)
        if r["fit"] is not None:
            for w in r["fit"].warnings:
                print(f"warning: {w}", file=out)
        print(file=out)
    if len(results) > 1:
        print(f"Comparison (κ ≥ {args.min_curvature:g} 1/m): " + "; ".join(
            f"{r['model']} {_fmt(r['validation'].summary()['max_abs_magnitude_error_1_per_m'], '.4f')} 1/m, "
            f"{_fmt(r['validation'].summary()['max_abs_direction_error_deg'], '.3f')}°" for r in results), file=out)
    print("Score (median over rotation × grating × level of the per-level RMS |Δκ|, and of |mean Δdir|; "
          "docs/jig.md):", file=out)
    for r in results:
        print(_score_line(r["model"], r["validation"]), file=out)
    return 0 if ok in (None, True) else 1


def _leave_one_rotation_out(args: argparse.Namespace, fiber: FiberModel | None, poses: jig.JigPoses,
                            gratings: list[int] | None) -> int:
    if fiber is None or args.calibration or args.holdout_orientations is not None:
        raise ValueError("--leave-one-rotation-out fits its own calibrations: give --fiber FIBER.toml, without "
                         "--calibration or --holdout-orientations")
    stats = {m: jig.leave_one_rotation_out(fiber, poses, model=m, gratings=gratings,
                                           trust_references=args.trust_references,
                                           min_curvature=args.min_curvature, jig_zero=not args.no_jig_zero)
             for m in _models(args.model)}
    if args.json:
        print(jsonout.dumps({"poses": args.poses, "results": {m: st.to_dict() for m, st in stats.items()}}, indent=2))
        return 0
    for model, st in stats.items():
        big = st.levels >= st.min_curvature
        print(f"{model} model, leave one rotation out ({_deg_list(st.orientations)}), gratings "
              f"{st.gratings.tolist()}: in-sample RMS strain residual {st.rms_strain_residual * 1e6:.2f} µε")
        print(f"{'held out':>9s}{'median RMS |Δκ| (1/m)':>24s}{'median |mean Δdir|':>20s}")
        for o, psi in enumerate(st.orientations):
            d = np.rad2deg(np.nanmedian(np.abs(st.direction_mean[o][:, big]))) if big.any() else float("nan")
            print(f"{np.rad2deg(psi):8.1f}°{np.nanmedian(st.kappa_rms[o]):24.4f}{d:19.2f}°")
        print(f"{'all':>9s}{st.kappa_error:24.4f}{np.rad2deg(st.direction_error):19.2f}°   "
              f"(direction: κ ≥ {st.min_curvature:g} 1/m)\n")
    added = "with" if not args.no_jig_zero else "without"
    print("Score, leave one rotation out (median over rotation × grating × level of the per-level RMS |Δκ|, and of "
          f"|mean Δdir|; {added} the jig's zero; docs/jig.md):")
    for model, st in stats.items():
        print(_score_line(model, st))
    return 0

