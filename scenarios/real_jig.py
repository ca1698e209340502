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

``--models`` compares the calibration models (the plain ``linear`` baseline, ``physical``, ``matrix`` and the
error-model ``nuisance`` fit, with each of its jig terms dropped in turn) by the one score
(:mod:`twin.calibration.jig.score`): on both real tables leave one rotation out, and on the twin over the sessions,
three ways — held-out rotations (leave one out), a second session of the same sensor in the same jig (one global
roll fitted) and the truth (exact bends of the true sensor, no jig at all: the calibration's own error). Poses
zeroed in the jig (the real tables, held-out rotations, the second session) are scored with the jig's zero added
to the curvature and without (docs/jig.md, "The jig's zero"); the truth session, zeroed straight, without. The
three figures of the twin beside the real table (and ``--budget``) are the jig's raw statistics: without it.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from sim_interrogator.needle_jig import AMIRO, MIN_CURVATURE, JigParams, amiro_fiber, loro, simulate
from twin import FiberModel, jsonout
from twin.calibration.jig import fit, leave_one_rotation_out, read_poses, validate
from twin.calibration.jig.nuisance import DEFAULT_TERMS, TERMS
from twin.calibration.jig.score import ALL_LEVELS, CLINICAL, difference
from twin.data import jig_dir

__all__ = ["DATA", "EFFECTS", "FACTOR", "KEYS", "REAL_TABLES", "VARIANTS", "budget", "compare", "model_scores",
           "model_study", "real_statistics"]

#: The real table and its fibre model.
DATA = jig_dir("amiro")  # package data (twin/data/jig/SENSOR): there after a non-editable install too
#: Both real jig tables (package data beside each other): (poses, fibre model, gratings in the groove); SOURCE.md
#: beside each.
REAL_TABLES = {
    "needle_3CH_4AA_v2": (DATA / "poses.csv", DATA / "needle.toml", (0, 1, 2)),
    "needle_3CH_3AA": (DATA.parent / "amiro-3aa" / "poses.csv", DATA.parent / "amiro-3aa" / "needle.toml", (0, 1)),
}
#: The calibrations compared by ``--models``: (name, model, nuisance terms or None).
VARIANTS = (("linear", "linear", None), ("physical", "physical", None), ("matrix", "matrix", None),
            ("nuisance", "nuisance", DEFAULT_TERMS), ("nuisance with gain", "nuisance", TERMS),
            *((f"nuisance without {t}", "nuisance", DEFAULT_TERMS - {t}) for t in sorted(DEFAULT_TERMS)),
            ("nuisance, no terms", "nuisance", frozenset()))
#: The twin reproduces a figure when twin / real is within [1/FACTOR, FACTOR].
FACTOR = 1.5
KEYS = ("rms_strain_residual", "loro_kappa_error_1_per_m", "loro_direction_error_deg")
#: The modelled effects and the parameters that turn each off (docs/jig.md, "Error budget").
EFFECTS: dict[str, dict] = {
    "jig's zero (grooves short of their label)": {"reference_bias": (0.0, 0.0)},
    "each rotation's zero (scatter between seatings)": {"reference_curvature": 0.0},
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
    """The three figures (and the per-level arrays) of a real jig table: its raw statistics, k̂ as the change from
    each rotation's reference (no jig zero added), as the twin's :func:`loro` computes them."""
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


def _score(st, key: str) -> dict:
    """The score of a validation or LORO in both bands, flat (1/m, deg), and its coverage."""
    out = {}
    for bands, tag in ((ALL_LEVELS, "all"), (CLINICAL, "clinical")):
        sc = st.score(bands)
        out[f"{key}_{tag}_kappa_1_per_m"] = sc.magnitude_error
        out[f"{key}_{tag}_direction_deg"] = None if sc.direction_error is None else float(
            np.rad2deg(sc.direction_error))
    out[f"{key}_coverage_95"] = st.coverage_95 if hasattr(st, "coverage_95") else st.coverage()[0]
    return out


def model_scores(poses_path: str | Path, fiber_path: str | Path, gratings, variants=VARIANTS) -> list[dict]:
    """Leave-one-rotation-out score of each calibration variant on a real table, with the jig's zero added to the
    held-out rotation's curvature (keys ``loro_*``) and without (``loro_raw_*``), and its difference from the first
    variant's (the linear baseline) with the range one rotation × grating moves it
    (``loro_all_vs_first``, ..., :func:`twin.calibration.jig.score.difference`)."""
    fiber = FiberModel.load(fiber_path)
    poses = read_poses(poses_path, fiber=fiber)
    rows, first = [], {}
    for name, model, terms in variants:
        extra = {} if terms is None else {"terms": terms}
        row = {"variant": name}
        for jig_zero, key in ((True, "loro"), (False, "loro_raw")):
            st = leave_one_rotation_out(fiber, poses, model=model, gratings=list(gratings),
                                        min_curvature=MIN_CURVATURE, jig_zero=jig_zero, **extra)
            row.update(_score(st, key))
            base = first.setdefault(key, st)
            for bands, tag in ((ALL_LEVELS, "all"), (CLINICAL, "clinical")):
                row[f"{key}_{tag}_vs_first"] = difference(st.levels, st.kappa_rms, st.direction_mean, base.kappa_rms,
                                                          base.direction_mean, bands).to_dict()
        rows.append(row)
    return rows


def model_study(params: JigParams, fiber: FiberModel, seeds: int, variants=VARIANTS) -> dict:
    """The calibration variants on ``seeds`` simulated sessions: per session (seed s) a second session of the same
    sensor (``session_seed`` 1000 + s) and a truth session (2000 + s: no jig effects and no noise, bends of
    0.5–2 1/m every 30°). Held-out rotations and the second session are scored with the jig's zero added (keys
    ``loro_*``, ``second_*``: they are zeroed in the jig) and without (``loro_raw_*``, ``second_raw_*``); the truth
    session, whose references are straight, without. Returns per variant the medians over the sessions and,
    against the first variant (the linear baseline), the fraction of sessions where it is better.
    """
    off = {k: v for effect in EFFECTS.values() for k, v in effect.items()}
    per: dict[str, list[dict]] = {name: [] for name, _, _ in variants}
    for i in range(seeds):
        s = params.seed + i
        first, truth = simulate(replace(params, seed=s), fiber)
        second, _ = simulate(replace(params, seed=s, session_seed=1000 + s), fiber)
        exact, _ = simulate(replace(params, seed=s, session_seed=2000 + s, **off,
                                    orientations_deg=tuple(range(0, 360, 30)), curvatures=(0.0, 0.5, 1.0, 2.0),
                                    trials=1), fiber)
        g = truth["gratings_in_groove"]
        for name, model, terms in variants:
            extra = {} if terms is None else {"terms": terms}
            cal = fit(fiber, first, model=model, gratings=g, **extra).calibration
            run = {}
            for jig_zero, tag in ((True, ""), (False, "_raw")):
                st = leave_one_rotation_out(fiber, first, model=model, gratings=g, min_curvature=MIN_CURVATURE,
                                            jig_zero=jig_zero, **extra)
                run.update(_score(st, f"loro{tag}"))
                run.update(_score(validate(cal, second, fiber=fiber, fit_roll=True, jig_zero=jig_zero),
                                  f"second{tag}"))
            # the truth session's references are straight (no jig): its curvature is k̂ itself
            run.update(_score(validate(cal, exact, fiber=fiber, fit_roll=True, jig_zero=False), "truth"))
            per[name].append(run)
    base = per[variants[0][0]]
    out = {}
    for name, runs in per.items():
        keys = [k for k in runs[0] if runs[0][k] is not None]
        med = {k: float(np.median([r[k] for r in runs])) for k in keys}
        wins = {k: float(np.mean([r[k] < b[k] for r, b in zip(runs, base, strict=True)]))
                for k in keys if not k.endswith("coverage_95")}
        out[name] = {"median": med, "better_than_linear": wins}
    return {"seeds": seeds, "variants": out}


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
    parser.add_argument("--models", action="store_true",
                        help="also compare the calibration models by the one score: both real tables (leave one "
                        "rotation out) and the twin (held-out rotations, a second session, the truth), with the "
                        "nuisance model's terms dropped in turn")
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
    if args.models:
        result["models"] = {"real": {name: model_scores(*table) for name, table in REAL_TABLES.items()},
                            "twin": model_study(params, amiro_fiber(), args.seeds)}
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
    if args.models:
        _print_models(result["models"], out)
    return status


def _f(x, spec: str) -> str:
    return "—" if x is None else format(x, spec)


def _print_models(models: dict, out) -> None:
    print("\nScore (docs/jig.md): median per-level RMS |Δκ| (1/m) / median |mean Δdir| (deg), all levels "
          "(direction κ ≥ 0.8 1/m); clinical: |Δκ| at 0.25–1.25 1/m; 95 % coverage of the stated intervals", file=out)
    for table, rows in models["real"].items():
        print(f"\nReal table {table}, leave one rotation out, with the jig's zero | without:", file=out)
        print(f"{'':28s}" + f"{'|Δκ|':>8s}{'|Δdir|':>8s}{'clinical':>10s}{'cover':>8s}" * 2, file=out)
        for r in rows:
            line = ""
            for key in ("loro", "loro_raw"):
                cover = r[f"{key}_coverage_95"]
                line += (f"{_f(r[f'{key}_all_kappa_1_per_m'], '8.4f')}{_f(r[f'{key}_all_direction_deg'], '7.2f')}°"
                         f"{_f(r[f'{key}_clinical_kappa_1_per_m'], '10.4f')}"
                         f"{'—' if cover is None else f'{100 * cover:.1f}%':>8s}")
            print(f"{r['variant']:28s}{line}", file=out)
        print(f"Difference from {rows[0]['variant']} with the jig's zero, all levels (in brackets: its range when one "
              "rotation × grating is left out; a range across 0 is not resolved by this table):", file=out)
        for r in rows[1:]:
            d = r["loro_all_vs_first"]
            m, dm = d["magnitude_1_per_m"], d["magnitude_range_1_per_m"]
            a, da = d["direction_deg"], d["direction_range_deg"]
            print(f"  {r['variant']:26s}|Δκ| {_f(m, '+8.4f')} ({_f(dm and dm[0], '+.4f')} … {_f(dm and dm[1], '+.4f')})"
                  f"   |Δdir| {_f(a, '+6.2f')}° ({_f(da and da[0], '+.2f')} … {_f(da and da[1], '+.2f')})", file=out)
    tw = models["twin"]
    print(f"\nTwin of needle_3CH_4AA_v2, median of {tw['seeds']} sessions (in brackets: fraction of sessions better "
          "than linear):", file=out)
    keys = ("loro", "second", "loro_raw", "second_raw", "truth")
    heads = ("held-out rotations", "second session", "held-out, no jig zero", "second, no jig zero",
             "truth (exact bends)")
    print(f"{'':28s}" + "".join(f"{h:>26s}" for h in heads) + f"{'coverage':>18s}", file=out)
    for name, v in tw["variants"].items():
        cells = []
        for key in keys:
            m, w = v["median"], v["better_than_linear"]
            k, d = f"{key}_all_kappa_1_per_m", f"{key}_all_direction_deg"
            cells.append(f"{m[k]:7.4f} ({w[k]:.0%}) {m[d]:5.2f}° ({w[d]:.0%})")
        cover = [v["median"].get(f"{key}_coverage_95") for key in ("loro", "second")]
        cover_txt = " / ".join("—" if c is None else f"{100 * c:.0f}%" for c in cover)
        print(f"{name:28s}" + "".join(f"{c:>26s}" for c in cells) + f"{cover_txt:>18s}", file=out)
