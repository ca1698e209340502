"""paper-ablation: the paper's Section V-A in the twin — calibration, identification and method comparisons.

The simulated fibre differs from its datasheet as the paper's did (outer-core spacing 1.039 rad instead of π/3,
gain g = r·S_ε 3.9 % low, as-built reference wavelengths scattered by 0.3 nm, intrinsic twist of 25° + 8° sin).
The experiment runs what a lab would:

1. the two-step calibration (``sim://calibration``: straight, then an in-plane bend of 0.16 1/cm);
2. the 12 static shapes in the paper's fixtures (grooved plate for planar shapes, 3 mm tubes for spatial ones),
   ``repeats`` frames each;
3. identification of [Δθ, g] on 3 planar + 3 spatial shapes against the fixtures' centrelines (the grooves' and
   tubes' CAD geometry, which is what the paper had; ``--truth rod`` uses the catheter's exact centreline
   instead, as a CT would give it and no lab has), validation on the other 6.

Rows of the table, each for the paper's pipeline (θ_b held through low curvature), its literal transcription
(κ_min = 0) and the default one, on the identification and validation
sets: (1) nominal parameters, no twist compensation (λ0 from step 1 only); (2) nominal, twist-compensated;
(3) identified, compensated. Errors are max and mean distances against the catheter (Kabsch registration) and
against the fixture with the paper's metric (ICP + ±0.5 mm translation). Then, with the identified calibration
on the validation set, the paper's interpolation comparison (spline, PCHIP, kNN, linear; with HEM) and its
integrator comparison (HEM vs RK4, RMS of per-shape max errors) beside ours.
"""

from __future__ import annotations

import sys
from dataclasses import asdict, dataclass, field

import numpy as np

from scenarios._common import entry
from scenarios._common.calibration import fixture_observation, two_step_in_twin
from scenarios._common.entry import option
from scenarios._common.static import fixture_for, measure
from sim_interrogator.optics import OpticsConfig
from sim_interrogator.setups import StaticShape
from sim_interrogator.sim import SimInterrogator
from twin import Calibration, FiberModel, Reconstructor, shapes
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
    identify_shapes: tuple[str, ...] = field(default=IDENTIFY, metadata=option("shapes to identify on"))
    validate_shapes: tuple[str, ...] = field(default=VALIDATE, metadata=option("shapes to validate on"))
    repeats: int = field(default=5, metadata=option("frames per shape"))
    fixture: str = field(default="paper", metadata=option(
        "paper: groove for planar shapes, tube for spatial ones", choices=("paper", "tube", "connect")))
    truth: str = field(default="fixture", metadata=option(
        "identification truth: the fixture's centreline (CAD, what a lab has) or the catheter's (a CT)",
        choices=("fixture", "rod")))
    calibration_frames: int = field(default=100, metadata=option("frames per pose of the two-step calibration"))
    seed: int = field(default=0, metadata=option("noise seed"))


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
            obs.append(fixture_observation(frames, fiber, name))
    ident = identify(fiber, obs, cal_twist)
    cal_id = ident.calibration(cal_twist)

    # 4. the ablation table, and the method comparisons on the validation set
    cals = {"1": cal_plain, "2": cal_twist, "3": cal_id}
    recs = {(row, "paper"): Reconstructor.paper(fiber, c) for row, c in cals.items()}
    recs |= {(row, "default"): Reconstructor(fiber, c) for row, c in cals.items()}
    recs |= {(row, "paper-literal"): Reconstructor.paper(fiber, c, kappa_min=0.0) for row, c in cals.items()}
    for kind in ("pchip", "knn", "linear"):
        recs[("interp", kind)] = Reconstructor.paper(fiber, cal_id, interpolation=kind)
    recs[("integ", "rk4")] = Reconstructor.paper(fiber, cal_id, integrator="rk4")
    recs[("integ", "hem-mid")] = Reconstructor.paper(fiber, cal_id, integrator="hem-mid")
    errors = {}
    curves: dict = {"names": [], "truth": [], "truth_s": None, "fixture": [], "default": [], "paper": []}
    for name, (s, frames) in recorded.items():
        say(f"reconstructing {name} …")
        errors[name] = measure(s, frames, recs)
        truth = frames[-1].truth  # the overlays: row (3), the last frame of each shape
        curves["names"].append(name)
        curves["truth"].append(truth.positions)
        curves["truth_s"] = truth.s
        curves["fixture"].append(truth.fixture)
        for mode in ("default", "paper"):
            shape = recs[("3", mode)](frames[-1])
            curves[mode].append(shape.positions)
            curves["s"] = shape.s
    per_shape = [{"shape": n, "set": "identification" if n in params.identify_shapes else "validation",
                  **{f"{key}_{against}_{stat}_error_mm": float(np.max(e[("3", m)][against]["max"]) * 1e3
                     if stat == "max" else np.mean(e[("3", m)][against]["mean"]) * 1e3)
                     for m, key in (("default", "default"), ("paper", "paper"), ("paper-literal", "paper_literal"))
                     for against in ("rod", "fixture") for stat in ("max", "mean")}}
                 for n, e in errors.items()]

    def table(key, against, names):
        return _agg([errors[n][key][against] for n in names])

    sets = {"identification": params.identify_shapes, "validation": params.validate_shapes}
    rows = []
    for row in cals:
        for mode in ("paper", "paper-literal", "default"):
            line = {"row": row, "label": ROWS[row], "mode": mode}
            for set_name, set_names in sets.items():
                for against in ("rod", "fixture"):
                    line[f"{set_name}_{against}"] = table((row, mode), against, set_names)
            rows.append(line)
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
        "experiment": "paper-ablation",
        "params": asdict(params),
        "calibration": {"name": "rows", "description": "each row its own calibration: (1) the two-step "
                        "calibration's λ0 only, (2) with its twist, (3) then [Δθ, g] identified against the "
                        f"{'fixtures' if params.truth == 'fixture' else 'catheter'}'s centrelines on "
                        f"{', '.join(params.identify_shapes)}"},
        "two_step": {"twist_error_max_rad": twist_error, "bend_curvature_min_1_per_m":
                        float(np.hypot(*report.bend_curvature.T).min())},
        "identified": {"delta_theta": ident.delta_theta, "delta_theta_std": ident.delta_theta_std,
                       "g_um": ident.gain * 1e6, "g_std_um": ident.gain_std * 1e6, "nfev": ident.nfev},
        "true": {"delta_theta": true["delta_theta"], "g_um": true["gain_m"] * 1e6},
        "rows": rows,
        "interpolation": interpolation,
        "integrator": integrator,
        "paper": PAPER,
        "per_shape_row3": per_shape,
        "_curves": curves,
    }


# ------------------------------------------------------------------------------------------------ command line
def add_arguments(parser) -> None:
    entry.add_arguments(parser, Params)


def params_from_args(args) -> Params:
    params = entry.params_from_args(Params, args)
    for n in params.identify_shapes + params.validate_shapes:
        shapes.get(n)  # a clear error for an unknown shape
    return params


def run(args) -> int:
    return entry.run("paper-ablation", sys.modules[__name__], args)


def write_report(r: dict, directory):
    """The ablation table as a chart and markdown in ``directory``; returns the report's path."""
    from scenarios.report import Report, pyplot

    truth = "fixtures'" if r["params"]["truth"] == "fixture" else "catheter's"
    rep = Report(directory, "The paper's ablation in the twin", "calibration: per row (the two-step calibration, "
                 f"then [Δθ, g] identified against the {truth} centrelines)")
    i, t = r["identified"], r["true"]
    rep.text(f"Identified Δθ = {i['delta_theta']:.5f} ± {i['delta_theta_std']:.5f} rad (true {t['delta_theta']:.5f}), "
             f"g = {i['g_um']:.4f} ± {i['g_std_um']:.4f} µm (true {t['g_um']:.4f}).")
    from scenarios.report import error_along_arc, overlay_panels, per_shape_errors, shape_overlays

    cal = rep.calibration
    ps = r["per_shape_row3"]
    names = [f"{e['shape']} ({e['set'][:5]}.)" for e in ps]
    for against, what in (("rod", "the catheter"), ("fixture", "the fixture (the paper's metric)")):
        fig = per_shape_errors(
            names, {m: [e[f"{k}_{against}_max_error_mm"] for e in ps] for m, k in
                    (("default", "default"), ("paper", "paper"), ("paper-literal", "paper_literal"))},
            {m: [e[f"{k}_{against}_mean_error_mm"] for e in ps] for m, k in
             (("default", "default"), ("paper", "paper"), ("paper-literal", "paper_literal"))},
            f"Row (3), identified and compensated: error per shape against {what}", cal,
            paper_max_mm=PAPER["rows"]["3"]["max_error_mm"], paper_mean_mm=PAPER["rows"]["3"]["mean_error_mm"])
        rep.figure(f"errors_per_shape_{against}", fig, f"row (3): max and mean error per shape against {what}; "
                   "dashed: the paper's figures on hardware")
    c = r.get("_curves")
    if c:
        panels, along = overlay_panels(c["names"], np.stack(c["truth"]), c["truth_s"],
                                       {m: np.stack(c[m]) for m in ("default", "paper")}, c["s"],
                                       fixture=np.stack(c["fixture"]))
        rep.figure("shape_overlays", shape_overlays(panels, "Row (3): reconstructions over the catheter and the "
                                                    "fixture (registered onto the catheter; mm)", cal),
                   "each shape's last frame with the identified calibration")
        for m in ("default", "paper"):
            fig = error_along_arc(c["s"], {n: along[m][i] * 1e3 for i, n in enumerate(c["names"])},
                                  f"Row (3): error along the arc length, {m} pipeline, against the catheter", cal,
                                  paper_max_mm=PAPER["rows"]["3"]["max_error_mm"])
            rep.figure(f"error_along_arc_{m}", fig, f"{m} pipeline, last frame of each shape, registered")
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


def text_report(r: dict) -> str:
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
    entry.main(sys.modules[__name__])
