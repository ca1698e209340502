"""rotation: the catheter rotated inside a pre-bent 8 Fr sheath (Al-Ahmad et al. §IV-B, docs/simulation.md §7).

The paper turned its catheter inside a pre-bent sheath and compared the shape-sensed tip with an EM sensor at the
tip: after registration the tip deviated by at most 0.36 mm. In the twin (``sim://sheath-rotate``) the catheter
runs through a 60°, 35 mm-radius pre-bent sheath of 2.8 mm bore (μ 0.2), the end of the sensed region 50 mm out
of the sheath's end; the hub turns it through one revolution in ``steps`` steps (a 1 s move, then a 2 s dwell).

What is measured, per step (the paper's "tip deviation after registration vs angle"):

1. each frame is reconstructed (the default pipeline, the paper's with θ_b held through low curvature and the
   paper's literal transcription; calibration ``lab`` unless ``--calibration`` says otherwise, see
   :mod:`scenarios._common.calibration`) and placed in the world with the fibre base's pose: ``tracked`` — the
   true pose of the fibre's s = 0 (a tracked base, :func:`scenarios._common.series.to_world`), or ``commanded`` — the
   sheath's centreline at the commanded insertion, rolled by the commanded hub angle (what an experimenter knows
   from the handle);
2. a static measurement is the mean over the last ``window`` (0.5 s) of each dwell, of the reconstructed tip and of
   the EM reading (true tip + 0.2 mm per-axis Gaussian noise, see :mod:`scenarios._common.sheath_experiments`);
3. registration: one translation maps the reconstructed tips onto the EM readings over all angles (the unknown
   offset between the FBG and EM frames; the tips move by < 1 mm, too little to fix a rotation), and the tip
   deviation at each angle is the distance left. ``max_deviation_mm`` is the largest over the angles;
4. the paper's own scoring (its Fig. 6b, "post registration"): each measured shape (mean over the window) is
   rigidly registered, whole curve on arc-length correspondences, onto the shape measured at 0°, and the tip
   deviation is the distance left between the tips (``registered_max_deviation_mm``). It measures how
   consistently a pipeline reports the same shape at every roll, with no external reference.

JSON ``summary``: ``max_deviation_mm`` (default pipeline, EM), ``paper_pipeline_max_deviation_mm`` (the paper's,
guarded), ``paper_literal_max_deviation_mm``, ``registered_max_deviation_mm`` (default, whole-curve registration),
``paper_pipeline_registered_max_deviation_mm``, ``paper_literal_registered_max_deviation_mm``; ``calibration``
says which calibration was used.

Why the sensed region sticks out of the sheath: the paper's EM sensor sat at the catheter's tip, outside the sheath,
and a free distal part turns any error in the sensed bend direction into tip motion, which is what the experiment
probes; inside the sheath the tip could not move at all.

The fibre here is glued in the catheter: it twists with it. While the hub turns, friction in the bend winds the
catheter up (tens of degrees over the sensed region) and the reconstruction, which cannot see mechanical twist,
swings away from the truth; during the dwell MuJoCo's soft friction lets the wind-up creep out. The report shows
both, and the wind-up (∫ τ ds over the gratings) beside the error.
"""

from __future__ import annotations

import math
import sys
from dataclasses import asdict, dataclass, field

import numpy as np

from scenarios._common import entry
from scenarios._common import sheath_experiments as common
from scenarios._common.calibration import calibration_for
from scenarios._common.calibration import label as calibration_label
from scenarios._common.entry import DEG, option
from scenarios._common.series import to_world
from scenarios.report import (
    Report,
    curvature_profiles,
    error_along_arc,
    error_over_time,
    overlay_panels,
    per_shape_errors,
    pyplot,
    shape_overlays,
    stamp,
    tip_trajectories,
)
from sim_interrogator.sheath_setups import SheathRotate
from twin import metrics

PAPER_MAX_DEVIATION_MM = 0.36
BASES = ("tracked", "commanded")


@dataclass(frozen=True)
class Params:
    """Parameters of the experiment (SI units, plain values: picklable).

    Attributes
    ----------
    steps : int
        Equal rotation steps over ``total_angle``.
    total_angle : float
        rad.
    move_time, dwell, window : float
        s: each step's move, the dwell after it, and the end part of the dwell averaged as one measurement.
    protrusion : float
        End of the sensed region beyond the sheath's end, m.
    friction : float
    segments : int
    rate : float
        Interrogator frame rate, Hz.
    em_noise : float
        EM sensor noise per axis (1σ), m.
    optics, calibration : str
    seed : int
    """

    steps: int = field(default=8, metadata=option("rotation steps"))
    total_angle: float = field(default=2 * math.pi, metadata=option("total rotation, °", flag="--angle-deg",
                                                                    scale=DEG))
    move_time: float = field(default=1.0, metadata=option("s per step's turn"))
    dwell: float = field(default=2.0, metadata=option("s of dwell after each turn"))
    window: float = field(default=0.5, metadata=option("s at the end of a dwell averaged"))
    protrusion: float = field(default=0.05, metadata=option("end of the sensed region beyond the sheath's end, mm",
                                                            flag="--protrusion-mm", scale=1e-3))
    friction: float = field(default=0.2, metadata=option("Coulomb friction catheter–sheath"))
    segments: int = field(default=100, metadata=option("rod segments"))
    rate: float = field(default=20.0, metadata=option("interrogator frame rate, Hz"))
    em_noise: float = field(default=2e-4, metadata=option("EM sensor noise per axis, mm", flag="--em-noise-mm",
                                                          scale=1e-3))
    optics: str = common.optics_field()
    calibration: str = common.calibration_field()
    seed: int = common.seed_field()


@dataclass(frozen=True, eq=False)
class Result:
    """Outcome of a run (m, rad, s). ``deviation[mode][base]`` etc. are per step (k,), per-frame arrays (n,).

    Attributes
    ----------
    params : Params
    setup : dict
        The setup's description.
    angles : ndarray (k,)
        Hub angle held at each measurement, rad.
    deviation : dict
        Tip deviation after registration against the EM readings, per mode and base.
    registered : dict
        Per mode (k,): tip deviation after whole-curve rigid registration onto the shape measured at 0°.
    shapes : dict
        Measured shapes (k, p, 3) in the world (tracked base), per mode and ``truth``; ``s`` and ``truth_s``.
    calibration : dict
        Which calibration was used (:class:`scenarios._common.calibration.UsedCalibration`).
    deviation_truth : dict
        The same against the true tip (no EM noise).
    absolute : dict
        Unregistered distance of the reconstructed tip from the true tip.
    frame_error : dict
        Per frame: registered reconstructed tip − true tip distance (the translation of the dwell measurements).
    t, twist, turning, lost_peaks : ndarray (n,)
        Frame times, the catheter's wind-up over the sensed region (rad), frames while the hub turns, lost peaks.
    twist_at : ndarray (k,)
        Wind-up at each measurement, rad.
    tips : dict
        World tip trajectories (n, 3): ``truth``, ``em`` and, registered, each mode (tracked base).
    curvature : dict
        At the last measurement: ``truth`` and each mode's (k_x, k_y) at the gratings (n_gratings, 2), 1/m;
        ``grating_s``.
    bore : ndarray (n,)
        Largest distance of the sensed region inside the sheath from the sheath's centreline, m.
    settle_s, wall_s : float
    """

    params: Params
    setup: dict
    angles: np.ndarray
    deviation: dict
    registered: dict
    deviation_truth: dict
    absolute: dict
    frame_error: dict
    t: np.ndarray
    twist: np.ndarray
    turning: np.ndarray
    lost_peaks: np.ndarray
    twist_at: np.ndarray
    tips: dict = field(repr=False)
    curvature: dict = field(repr=False)
    bore: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    shapes: dict = field(default_factory=dict, repr=False)
    calibration: dict = field(default_factory=dict)
    settle_s: float = 0.0
    wall_s: float = 0.0

    def summary(self) -> dict:
        d, p, lit = (self.deviation[m] for m in common.MODES)
        fe = self.frame_error["default"]["tracked"]
        still = ~self.turning
        return {
            "paper_max_deviation_mm": PAPER_MAX_DEVIATION_MM,
            "max_deviation_mm": float(d["tracked"].max() * 1e3),
            "mean_deviation_mm": float(d["tracked"].mean() * 1e3),
            "max_deviation_truth_mm": float(self.deviation_truth["default"]["tracked"].max() * 1e3),
            "commanded_max_deviation_mm": float(d["commanded"].max() * 1e3),
            "paper_pipeline_max_deviation_mm": float(p["tracked"].max() * 1e3),
            "paper_literal_max_deviation_mm": float(lit["tracked"].max() * 1e3),
            "registered_max_deviation_mm": float(self.registered["default"].max() * 1e3),
            "paper_pipeline_registered_max_deviation_mm": float(self.registered["paper"].max() * 1e3),
            "paper_literal_registered_max_deviation_mm": float(self.registered["paper-literal"].max() * 1e3),
            "max_absolute_tip_error_mm": float(self.absolute["default"]["tracked"].max() * 1e3),
            "max_error_while_turning_mm": float(fe[self.turning].max() * 1e3) if self.turning.any() else 0.0,
            "max_error_while_dwelling_mm": float(fe[still].max() * 1e3) if still.any() else 0.0,
            "max_windup_deg": float(np.degrees(np.abs(self.twist).max())),
            "max_windup_at_measurement_deg": float(np.degrees(np.abs(self.twist_at).max())),
            "lost_peaks": int(self.lost_peaks.sum()),
            "max_bore_offset_mm": _nanmax_mm(self.bore),
        }

    def to_dict(self) -> dict:
        rows = []
        for k, a in enumerate(self.angles):
            row = {"angle_deg": float(np.degrees(a)), "windup_deg": float(np.degrees(self.twist_at[k]))}
            for mode in common.MODES:
                for base in BASES:
                    row[f"{mode}_{base}_deviation_mm"] = float(self.deviation[mode][base][k] * 1e3)
                row[f"{mode}_deviation_truth_mm"] = float(self.deviation_truth[mode]["tracked"][k] * 1e3)
                row[f"{mode}_registered_deviation_mm"] = float(self.registered[mode][k] * 1e3)
                row[f"{mode}_absolute_tip_error_mm"] = float(self.absolute[mode]["tracked"][k] * 1e3)
            rows.append(row)
        return {"experiment": "rotation", "params": asdict(self.params), "calibration": self.calibration,
                "setup": self.setup,
                "summary": self.summary(), "per_angle": rows, "settle_s": self.settle_s, "wall_s": self.wall_s}


def _nanmax_mm(x: np.ndarray) -> float | None:
    return float(np.nanmax(x) * 1e3) if np.isfinite(x).any() else None


def run_experiment(params: Params, progress=None, viewer=None) -> Result:
    """Run the rotation experiment; ``progress(message)`` reports as it goes; ``viewer.show`` sees some frames."""
    if params.window <= 0 or params.window > params.dwell:
        raise ValueError(f"window must be in (0, dwell = {params.dwell}] s, got {params.window}")
    if params.em_noise < 0:
        raise ValueError(f"em_noise must be >= 0 m, got {params.em_noise}")
    setup = SheathRotate(protrusion=params.protrusion, total_angle=params.total_angle, steps=params.steps,
                         move_time=params.move_time, dwell=params.dwell, friction=params.friction,
                         segments=params.segments)
    run = common.run_setup(setup, optics=params.optics, seed=params.seed, rate=params.rate, label="rotation",
                           progress=progress)
    ser, sim = run.series, run.sim
    used = calibration_for(params.calibration, sim.optics, sim.fiber, progress=progress)
    recs = common.reconstructors(sim.fiber, used.calibration)
    t = ser.t
    win = common.windows(t, setup.dwell_ends, params.window)
    last = int(win[-1][-1])
    em = common.em_readings(ser.tip, params.em_noise, params.seed + common.EM_STREAM)

    def avg(x):
        return np.stack([x[w].mean(axis=0) for w in win])

    true_k, em_k = avg(ser.tip), avg(em)
    nominal = setup.nominal_base_pose(t)
    bases = {"tracked": (ser.base_positions, ser.base_frames), "commanded": nominal}
    deviation, deviation_truth, absolute, frame_error, registered = {}, {}, {}, {}, {}
    measured = {"truth": avg(ser.truth_positions), "truth_s": ser.truth_s}
    tips = {"truth": ser.tip, "em": em}
    curvature = {"grating_s": sim.fiber.grating_s, "truth": ser.truth_curvature[last]}
    for mode, rec in recs.items():
        shape = rec(ser.wavelengths)
        curvature[mode] = shape.curvature[last]
        if mode == "default":
            common.show_frames(viewer, shape, ser)
        measured["s"] = shape.s
        measured[mode] = avg(to_world(shape, ser))
        registered[mode] = registered_deviation(measured[mode])
        deviation[mode], deviation_truth[mode], absolute[mode], frame_error[mode] = {}, {}, {}, {}
        for base, (bp, bf) in bases.items():
            tip = np.einsum("nij,nj->ni", bf, shape.tip) + bp
            p_k = avg(tip)
            offset_em = (em_k - p_k).mean(axis=0)  # the FBG → EM registration (a translation)
            offset_true = (true_k - p_k).mean(axis=0)
            deviation[mode][base] = np.linalg.norm(p_k + offset_em - em_k, axis=1)
            deviation_truth[mode][base] = np.linalg.norm(p_k + offset_true - true_k, axis=1)
            absolute[mode][base] = np.linalg.norm(p_k - true_k, axis=1)
            frame_error[mode][base] = np.linalg.norm(tip + offset_true - ser.tip, axis=1)
            if base == "tracked":
                tips[mode] = tip + offset_em
    in_dwell = np.zeros(t.size, bool)
    for e in setup.dwell_ends:
        in_dwell |= (t >= e - params.dwell - 1e-9) & (t <= e + 1e-9)
    result = Result(
        params=params, setup=sim.describe(), angles=setup.step_angles, deviation=deviation, registered=registered,
        deviation_truth=deviation_truth, absolute=absolute, frame_error=frame_error, t=t,
        twist=run.twist, turning=~in_dwell, lost_peaks=ser.lost_peaks, twist_at=avg(run.twist),
        tips=tips, curvature=curvature, bore=run.bore, shapes=measured, calibration=used.to_dict(),
        settle_s=float(setup.settle_result.time), wall_s=run.wall_s,
    )
    if progress:
        s = result.summary()
        progress(f"rotation: tip deviation after registration ≤ {s['max_deviation_mm']:.3f} mm (paper "
                 f"{PAPER_MAX_DEVIATION_MM} mm); {run.wall_s:.0f} s wall")
    return result


def registered_deviation(curves: np.ndarray) -> np.ndarray:
    """Tip deviation (k,) of each curve (k, p, 3) after whole-curve rigid registration (Kabsch on arc-length
    correspondences) onto the first, m — the paper's Fig. 6b "post registration"."""
    ok = np.all(np.isfinite(curves), axis=(1, 2))
    out = np.full(len(curves), np.nan)
    if not ok[0]:
        return out
    r, t = metrics.kabsch(curves[ok], np.broadcast_to(curves[0], curves[ok].shape))
    tips = np.einsum("kij,kj->ki", r, curves[ok, -1]) + t
    out[ok] = np.linalg.norm(tips - curves[0, -1], axis=1)
    return out


# ------------------------------------------------------------------------------------------------ output
def text_report(result: Result) -> str:
    s, p = result.summary(), result.params
    lines = [
        f"rotation inside a pre-bent 8 Fr sheath: {p.steps} steps to {math.degrees(p.total_angle):.0f}°, "
        f"friction {p.friction:g}, sensed end {p.protrusion * 1e3:.0f} mm out of the sheath, optics {p.optics}, "
        f"calibration {result.calibration.get('name', p.calibration)}",
        "tip deviation after registration (translation onto the EM readings), mm; base = tracked fibre base pose;",
        "paper = the paper's pipeline with θ_b held through low curvature, literal = its literal transcription;",
        "whole-curve = each shape rigidly registered onto the 0° shape (the paper's Fig. 6b)",
        "",
        f"{'angle':>7s}{'default':>10s}{'vs truth':>10s}{'commanded':>11s}{'paper':>9s}{'literal':>9s}"
        f"{'unregistered':>14s}{'wind-up':>9s}{'whole-curve: default':>22s}{'paper':>8s}{'literal':>9s}",
    ]
    for k, a in enumerate(result.angles):
        lines.append(
            f"{math.degrees(a):6.0f}°{result.deviation['default']['tracked'][k] * 1e3:10.3f}"
            f"{result.deviation_truth['default']['tracked'][k] * 1e3:10.3f}"
            f"{result.deviation['default']['commanded'][k] * 1e3:11.3f}"
            f"{result.deviation['paper']['tracked'][k] * 1e3:9.3f}"
            f"{result.deviation['paper-literal']['tracked'][k] * 1e3:9.3f}"
            f"{result.absolute['default']['tracked'][k] * 1e3:14.3f}{math.degrees(result.twist_at[k]):8.2f}°"
            + "".join(f"{result.registered[m][k] * 1e3:{w}.3f}" for m, w in zip(common.MODES, (22, 8, 9), strict=True))
        )
    lines += [
        "",
        f"max tip deviation after registration: {s['max_deviation_mm']:.3f} mm (paper: ≤ {PAPER_MAX_DEVIATION_MM} mm); "
        f"paper's pipeline {s['paper_pipeline_max_deviation_mm']:.3f} mm (literal "
        f"{s['paper_literal_max_deviation_mm']:.3f} mm)",
        f"after whole-curve registration onto the 0° shape: {s['registered_max_deviation_mm']:.3f} mm; paper's "
        f"pipeline {s['paper_pipeline_registered_max_deviation_mm']:.3f} mm (literal "
        f"{s['paper_literal_registered_max_deviation_mm']:.3f} mm)",
        f"while turning the catheter winds up by up to {s['max_windup_deg']:.1f}° over the sensed region and the "
        f"tip error reaches {s['max_error_while_turning_mm']:.2f} mm (dwelling, before the wind-up creeps out: "
        f"{s['max_error_while_dwelling_mm']:.2f} mm)",
    ]
    return "\n".join(lines)


def write_report(result: Result, directory: str) -> str:
    """``directory``/report.md with plots: deviation vs angle, error over time, tip trajectories, curvature."""
    s, p = result.summary(), result.params
    rep = Report(directory, "Rotation inside a pre-bent 8 Fr sheath",
                 calibration_label(result.calibration))
    rep.text(
        f"The catheter was turned {p.steps} × {math.degrees(p.total_angle / p.steps):.0f}° inside a pre-bent 8 Fr "
        f"sheath (60° bend, radius 35 mm, bore 2.8 mm, friction μ = {p.friction:g}); the end of the sensed region "
        f"stuck out of the sheath by {p.protrusion * 1e3:.0f} mm. Each step: a {p.move_time:g} s turn, a "
        f"{p.dwell:g} s dwell; the last {p.window:g} s of each dwell (FBG and EM sensor alike) is one measurement. "
        "The reconstruction is placed with the fibre base's tracked pose and registered to the EM readings by one "
        "translation; the deviation is what is left."
    )
    def each(get):
        return tuple(f"{get(m) * 1e3:.2f} mm" for m in common.MODES)

    rep.text(f"Calibration: {result.calibration.get('name')} — {result.calibration.get('description', '')}.")
    rep.table(*common.paper_table([
        ("tip deviation after registration onto the EM readings (max)", f"{PAPER_MAX_DEVIATION_MM} mm",
         *each(lambda m: result.deviation[m]["tracked"].max())),
        ("tip deviation after whole-curve registration onto the 0° shape (max; the paper's Fig. 6b)",
         f"{PAPER_MAX_DEVIATION_MM} mm", *each(lambda m: np.nanmax(result.registered[m]))),
        ("same as the first, against the true tip (no EM noise)", "–",
         *each(lambda m: result.deviation_truth[m]["tracked"].max())),
        ("same, base pose from the commanded roll", "–", *each(lambda m: result.deviation[m]["commanded"].max())),
        ("tip error while turning (max)", "–",
         *each(lambda m: result.frame_error[m]["tracked"][result.turning].max(initial=0))),
    ]))
    rep.text(
        f"While the hub turns, friction in the bend winds the catheter up by up to {s['max_windup_deg']:.1f}° over "
        "the sensed region. A fibre glued in the catheter twists with it, and a 3-core fibre cannot tell mechanical "
        "twist from a rotated bend, so the reconstructed tip swings away while turning "
        f"({s['max_error_while_turning_mm']:.1f} mm); during the dwell the wind-up creeps out (at the measurements "
        f"≤ {s['max_windup_at_measurement_deg']:.2f}°)."
    )
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    deg = np.degrees(result.angles)
    for mode, style in (("default", "o-"), ("paper", "s--")):
        ax.plot(deg, result.deviation[mode]["tracked"] * 1e3, style, label=f"{mode} pipeline (vs EM)")
    ax.plot(deg, result.deviation["paper-literal"]["tracked"] * 1e3, "x:", label="paper-literal pipeline (vs EM)")
    ax.plot(deg, result.deviation_truth["default"]["tracked"] * 1e3, "^:", label="default (vs true tip)")
    ax.axhline(PAPER_MAX_DEVIATION_MM, color="k", lw=0.8, ls="--", label="paper: max 0.36 mm")
    if result.deviation["paper-literal"]["tracked"].max() > 30 * result.deviation["default"]["tracked"].max():
        ax.set_yscale("log")
    ax.set_xlabel("hub angle (°)")
    ax.set_ylabel("tip deviation (mm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    cal = calibration_label(result.calibration)
    fig.suptitle("Tip deviation after registration onto the EM readings", fontsize=10)
    stamp(fig, cal)
    rep.figure("deviation_vs_angle", fig, "Tip deviation after registration at each angle")
    names = [f"{math.degrees(a):.0f}°" for a in result.angles]
    fig = per_shape_errors(names[1:], {m: result.registered[m][1:] * 1e3 for m in common.MODES}, None,
                           "Tip deviation after whole-curve registration onto the 0° shape (the paper's Fig. 6b)",
                           cal, paper_max_mm=PAPER_MAX_DEVIATION_MM, xlabel="hub angle",
                           ylabel="tip deviation (mm)")
    rep.figure("registered_deviation", fig, "Each measured shape rigidly registered onto the one measured at 0°; "
               "what is left at the tip, per pipeline (dashed: the paper's largest, on hardware)")
    sh = result.shapes
    if sh:
        panels, along = overlay_panels(names, sh["truth"], sh["truth_s"], {m: sh[m] for m in ("default", "paper")},
                                       sh["s"])
        rep.figure("shape_overlays", shape_overlays(panels, "Measured shapes at each angle over the catheter "
                                                    "(registered onto it; mm)", cal),
                   "The shape at each angle (mean over the measurement window), registered onto the catheter")
        fig = error_along_arc(sh["s"], {n: along["default"][i] * 1e3 for i, n in enumerate(names)},
                              "Error along the arc length at each angle, default pipeline", cal)
        rep.figure("error_along_arc", fig, "distance of the registered reconstruction from the catheter, per angle")
    fig = error_over_time(result.t, {
        "default: tip error (mm)": result.frame_error["default"]["tracked"] * 1e3,
        "paper's pipeline, guarded (mm)": result.frame_error["paper"]["tracked"] * 1e3,
        "wind-up over the sensed region (°)": np.degrees(np.abs(result.twist)),
    }, ylabel="mm  /  °", marks=result.turning, mark_label="hub turning")
    if result.frame_error["paper"]["tracked"].max() > 30 * result.frame_error["default"]["tracked"].max():
        fig.axes[0].set_yscale("log")
    stamp(fig, cal)
    rep.figure("error_over_time", fig, "Registered tip error against the true tip, and the catheter's wind-up")
    mm_tips = {k: v * 1e3 for k, v in result.tips.items()}
    fig = tip_trajectories(mm_tips["truth"], {"EM sensor": mm_tips["em"], "default": mm_tips["default"]},
                           "tip in the world (registered)")
    rep.figure("tip_trajectories", fig, "Tip trajectories, truth vs reconstruction (registered) and EM (the paper's "
               "pipeline is left out: its tip wanders by centimetres)")
    c = result.curvature
    fig = curvature_profiles(c["grating_s"], c["truth"], {"default": c["default"], "paper's pipeline": c["paper"]},
                             "curvature at the last measurement")
    rep.figure("curvature_profiles", fig, "Curvature at the gratings, truth vs reconstruction")
    rep.text("```\n" + text_report(result) + "\n```")
    return str(rep.write())


# ------------------------------------------------------------------------------------------------ command line
def add_arguments(parser) -> None:
    entry.add_arguments(parser, Params)


def run(args) -> int:
    return entry.run("rotation", sys.modules[__name__], args)


if __name__ == "__main__":
    entry.main(sys.modules[__name__])
