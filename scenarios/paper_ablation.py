"""paper-ablation: the paper's Section V-A in the twin — calibration, identification and method comparisons.

The simulated fibre differs from its datasheet as the paper's did (outer-core spacing 1.039 rad instead of π/3,
gain g = r·S_ε 3.9 % low, as-built reference wavelengths scattered by 0.3 nm, intrinsic twist of 25° + 8° sin).
The experiment runs what a lab would:

1. the two-step calibration (``sim://calibration``: straight, then an in-plane bend of 0.16 1/cm);
2. the 12 static shapes in the paper's fixtures (grooved plate for planar shapes, 3 mm tubes for spatial ones),
   ``repeats`` frames each;
3. identification of [Δθ, g] on 3 planar + 3 spatial shapes (truth: the catheter's centreline with arc length,
   as a CT would give; ``--truth fixture`` uses the fixtures' centrelines instead), validation on the other 6.

Rows of the table, each for the paper's pipeline and the default one, on the identification and validation
sets: (1) nominal parameters, no twist compensation (λ0 from step 1 only); (2) nominal, twist-compensated;
(3) identified, compensated. Errors are max and mean distances against the catheter (Kabsch registration) and
against the fixture with the paper's metric (ICP + ±0.5 mm translation). Then, with the identified calibration
on the validation set, the paper's interpolation comparison (spline, PCHIP, kNN, linear; with HEM) and its
integrator comparison (HEM vs RK4, RMS of per-shape max errors) beside ours.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict, dataclass

import numpy as np

from scenarios.factory import two_step_in_twin
from scenarios.static_shapes import fixture_for, measure
from sim_interrogator.optics import OpticsConfig
from sim_interrogator.setups import StaticShape
from sim_interrogator.sim import SimInterrogator
from twin import Calibration, FiberModel, Reconstructor, jsonout, shapes
from twin.calibration.identify import Observation, identify

#: The paper's results (Al-Ahmad et al., §V-A; docs/simulation.md §7), mm.
PAPER = {
    "rows": {"1": {"max_error_mm": 10.43, "mean_error_mm": 2.33}, "2": {"max_error_mm": 4.37, "mean_error_mm": 0.85},
             "3": {"max_error_mm": 2.52, "mean_error_mm": 0.70}},
    "interpolation_max_error_mm": {"spline": 2.52, "pchip": 2.57, "knn": 2.71, "linear": 2.82},
    "integrator_rms_of_max_mm": {"hem": 1.53, "rk4": 1.40},
    "identified": {"delta_theta": 1.039, "r_m": 3.80e-5, "strain_sensitivity": 0.737},
}

IDENTIFY = ("arc", "s-curve", "hook", "helix", "rotating-bend", "two-plane")
VALIDATE = ("tightening", "wave", "clothoid", "through-zero", "mixed", "widening-helix")
ROWS = {"1": "nominal, no twist compensation", "2": "nominal, twist-compensated", "3": "identified, compensated"}


@dataclass(frozen=True)
class Params:
    identify_shapes: tuple[str, ...] = IDENTIFY
    validate_shapes: tuple[str, ...] = VALIDATE
    repeats: int = 5
    fixture: str = "paper"
    truth: str = "rod"
    calibration_frames: int = 100
    seed: int = 0


def _agg(stats: list[dict]) -> dict:
    """Max over shapes and repetitions of the per-frame max; mean of the per-frame means; mm."""
    return {"max_error_mm": float(max(np.max(s["max"]) for s in stats) * 1e3),
            "mean_error_mm": float(np.mean([np.mean(s["mean"]) for s in stats]) * 1e3)}


def _rms_of_max(stats: list[dict]) -> float:
    return float(np.sqrt(np.mean([np.mean(s["max"]) ** 2 for s in stats])) * 1e3)


def run_experiment(params: Params, progress=None) -> dict:
    say = progress or (lambda msg: None)
    fiber = FiberModel.paper()
    # 1. two-step calibration in the twin
    say("calibration: straight, then an in-plane bend …")
    cal_twist, report, true = two_step_in_twin(fiber, OpticsConfig(seed=params.seed), params.calibration_frames)
    cal_plain = Calibration(lambda0=cal_twist.lambda0, provenance={"method": "straight step only"})
    twist_error = float(np.max(np.abs(report.twist - np.asarray(true["twist_rad"]))))

    # 2. the static shapes
    recorded = {}
    names = params.identify_shapes + params.validate_shapes
    for i, name in enumerate(names):
        kind = fixture_for(name, params.fixture)
        say(f"[{i + 1}/{len(names)}] {name} in the {kind} …")
        s = SimInterrogator(StaticShape(name, kind), fiber, OpticsConfig(seed=params.seed + 1 + i))
        recorded[name] = (s, [s.read() for _ in range(params.repeats)])

    # 3. identification
    say("identification of [Δθ, g] …")
    obs = []
    for name in params.identify_shapes:
        s, frames = recorded[name]
        t = frames[0].truth
        if params.truth == "rod":
            obs.append(Observation(np.stack([f.wavelengths for f in frames]), t.positions, t.s, name))
        else:
            obs.append(Observation(np.stack([f.wavelengths for f in frames]), t.fixture,
                                   np.linspace(0, fiber.sensed_length, len(t.fixture)), name))
    ident = identify(fiber, obs, cal_twist)
    cal_id = ident.calibration(cal_twist)

    # 4. the ablation table, and the method comparisons on the validation set
    cals = {"1": cal_plain, "2": cal_twist, "3": cal_id}
    recs = {(row, "paper"): Reconstructor.paper(fiber, c) for row, c in cals.items()}
    recs |= {(row, "default"): Reconstructor(fiber, c) for row, c in cals.items()}
    for kind in ("pchip", "knn", "linear"):
        recs[("interp", kind)] = Reconstructor.paper(fiber, cal_id, interpolation=kind)
    recs[("integ", "rk4")] = Reconstructor.paper(fiber, cal_id, integrator="rk4")
    recs[("integ", "hem-mid")] = Reconstructor.paper(fiber, cal_id, integrator="hem-mid")
    errors = {}
    for name, (s, frames) in recorded.items():
        say(f"reconstructing {name} …")
        errors[name] = measure(s, frames, recs)

    def table(key, against, names):
        return _agg([errors[n][key][against] for n in names])

    sets = {"identification": params.identify_shapes, "validation": params.validate_shapes}
    rows = []
    for row in cals:
        for mode in ("paper", "default"):
            entry = {"row": row, "label": ROWS[row], "mode": mode}
            for set_name, set_names in sets.items():
                for against in ("rod", "fixture"):
                    entry[f"{set_name}_{against}"] = table((row, mode), against, set_names)
            rows.append(entry)
    val = params.validate_shapes
    interpolation = {"spline": table(("3", "paper"), "fixture", val)}
    interpolation |= {k: table(("interp", k), "fixture", val) for k in ("pchip", "knn", "linear")}
    integrator = {
        "hem_rms_of_max_mm": _rms_of_max([errors[n][("3", "paper")]["fixture"] for n in val]),
        "rk4_rms_of_max_mm": _rms_of_max([errors[n][("integ", "rk4")]["fixture"] for n in val]),
        "hem_mid_rms_of_max_mm": _rms_of_max([errors[n][("integ", "hem-mid")]["fixture"] for n in val]),
        "default_rms_of_max_mm": _rms_of_max([errors[n][("3", "default")]["fixture"] for n in val]),
    }
    return {
        "params": asdict(params),
        "calibration": {"twist_error_max_rad": twist_error, "bend_curvature_min_1_per_m":
                        float(np.hypot(*report.bend_curvature.T).min())},
        "identified": {"delta_theta": ident.delta_theta, "delta_theta_std": ident.delta_theta_std,
                       "g_um": ident.gain * 1e6, "g_std_um": ident.gain_std * 1e6, "nfev": ident.nfev},
        "true": {"delta_theta": true["delta_theta"], "g_um": true["gain_m"] * 1e6},
        "rows": rows,
        "interpolation": interpolation,
        "integrator": integrator,
        "paper": PAPER,
    }


# ------------------------------------------------------------------------------------------------ command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--identify-shapes", default=",".join(IDENTIFY), help="shapes to identify on")
    parser.add_argument("--validate-shapes", default=",".join(VALIDATE), help="shapes to validate on")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--fixture", choices=("paper", "tube", "connect"), default="paper",
                        help="paper: groove for planar shapes, tube for spatial ones (default)")
    parser.add_argument("--truth", choices=("rod", "fixture"), default="rod",
                        help="identification truth: the catheter's centreline (a CT) or the fixture's (CAD)")
    parser.add_argument("--calibration-frames", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--report", metavar="DIR", help="write PNG plots and a markdown summary to DIR")


def run(args: argparse.Namespace) -> int:
    def names(text):
        out = tuple(n.strip() for n in text.split(",") if n.strip())
        for n in out:
            shapes.get(n)
        return out

    params = Params(names(args.identify_shapes), names(args.validate_shapes), args.repeats, args.fixture,
                    args.truth, args.calibration_frames, args.seed)
    result = run_experiment(params, progress=lambda msg: print(msg, file=sys.stderr, flush=True))
    if args.report:
        print(f"report: {write_report(result, args.report)}", file=sys.stderr)
    print(jsonout.dumps(result, indent=2) if args.json else report(result))
    return 0


def write_report(r: dict, directory):
    """The ablation table as a chart and markdown in ``directory``; returns the report's path."""
    from scenarios.report import Report, pyplot

    rep = Report(directory, "The paper's ablation in the twin")
    i, t = r["identified"], r["true"]
    rep.text(f"Identified Δθ = {i['delta_theta']:.5f} ± {i['delta_theta_std']:.5f} rad (true {t['delta_theta']:.5f}), "
             f"g = {i['g_um']:.4f} ± {i['g_std_um']:.4f} µm (true {t['g_um']:.4f}).")
    rows = [[f"({row['row']}) {row['label']}", row["mode"], row["identification_rod"]["max_error_mm"],
             row["validation_rod"]["max_error_mm"], row["validation_rod"]["mean_error_mm"],
             row["validation_fixture"]["max_error_mm"], PAPER["rows"][row["row"]]["max_error_mm"]]
            for row in r["rows"]]
    rep.table(["calibration", "pipeline", "identification max mm", "validation max mm", "validation mean mm",
               "validation vs fixture max mm", "the paper max mm"], rows)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for mode, marker in (("paper", "o-"), ("default", "s-")):
        ys = [row["validation_rod"]["max_error_mm"] for row in r["rows"] if row["mode"] == mode]
        ax.plot([1, 2, 3], ys, marker, label=f"twin, {mode} pipeline")
    ax.plot([1, 2, 3], [PAPER["rows"][k]["max_error_mm"] for k in "123"], "k^--", label="the paper (hardware)")
    ax.set_xticks([1, 2, 3], ["(1) nominal", "(2) + twist", "(3) + identified"])
    ax.set_ylabel("max error, validation (mm)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    rep.figure("ablation", fig, "max error on the validation shapes after each calibration step")
    rep.table(["interpolation", "max mm (fixture)", "the paper max mm"],
              [[k, v["max_error_mm"], PAPER["interpolation_max_error_mm"][k]] for k, v in r["interpolation"].items()])
    g = r["integrator"]
    rep.table(["integrator", "RMS of max errors mm"],
              [["HEM (paper)", g["hem_rms_of_max_mm"]], ["RK4", g["rk4_rms_of_max_mm"]],
               ["HEM, midpoint samples", g["hem_mid_rms_of_max_mm"]],
               ["default (material frame, Magnus-4)", g["default_rms_of_max_mm"]]])
    return rep.write()


def report(r: dict) -> str:
    i, t = r["identified"], r["true"]
    lines = [
        "paper ablation in the twin (errors in mm; rod: against the catheter, Kabsch; fixture: the paper's metric)",
        f"identified Δθ = {i['delta_theta']:.5f} ± {i['delta_theta_std']:.5f} rad (true {t['delta_theta']:.5f}), "
        f"g = {i['g_um']:.4f} ± {i['g_std_um']:.4f} µm (true {t['g_um']:.4f})",
        "",
        f"{'row':4s}{'':34s}{'mode':9s}{'identification':>22s}{'validation':>22s}{'validation, fixture':>24s}",
        f"{'':47s}{'max':>11s}{'mean':>11s}{'max':>11s}{'mean':>11s}{'max':>12s}{'mean':>12s}",
    ]
    for row in r["rows"]:
        a, b, c = row["identification_rod"], row["validation_rod"], row["validation_fixture"]
        lines.append(f"({row['row']}) {row['label']:34s}{row['mode']:9s}{a['max_error_mm']:11.3f}"
                     f"{a['mean_error_mm']:11.3f}{b['max_error_mm']:11.3f}{b['mean_error_mm']:11.3f}"
                     f"{c['max_error_mm']:12.3f}{c['mean_error_mm']:12.3f}")
    p = r["paper"]
    lines += ["", "the paper (hardware, paper pipeline): " + ", ".join(
        f"({k}) max {v['max_error_mm']} / mean {v['mean_error_mm']}" for k, v in p["rows"].items())]
    lines += ["", "interpolation (paper pipeline, identified, validation, fixture):  " + ", ".join(
        f"{k} {v['max_error_mm']:.3f}" for k, v in r["interpolation"].items())
        + "   the paper: " + ", ".join(f"{k} {v}" for k, v in p["interpolation_max_error_mm"].items())]
    g = r["integrator"]
    lines += [f"integrator, RMS of max errors: HEM {g['hem_rms_of_max_mm']:.3f}, RK4 {g['rk4_rms_of_max_mm']:.3f}, "
              f"HEM-mid {g['hem_mid_rms_of_max_mm']:.3f}, default (material, Magnus-4) "
              f"{g['default_rms_of_max_mm']:.3f}   the paper: HEM 1.53, RK4 1.40"]
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="paper_ablation", description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
