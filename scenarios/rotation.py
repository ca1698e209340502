"""rotation: the catheter rotated inside a pre-bent 8 Fr sheath (Al-Ahmad et al. §IV-B, docs/simulation.md §7).

The paper turned its catheter inside a pre-bent sheath and compared the shape-sensed tip with an EM sensor at the
tip: after registration the tip deviated by at most 0.36 mm. In the twin (``sim://sheath-rotate``) the catheter
runs through a 60°, 35 mm-radius pre-bent sheath of 2.8 mm bore (μ 0.2), the end of the sensed region 50 mm out
of the sheath's end; the hub turns it through one revolution in ``steps`` steps (a 1 s move, then a 2 s dwell).

What is measured, per step (the paper's "tip deviation after registration vs angle"):

1. each frame is reconstructed (default pipeline and the paper's, calibration = the twin's true fibre parameters
   unless ``--calibration`` says otherwise) and placed in the world with the fibre base's pose: ``tracked`` — the
   true pose of the fibre's s = 0 (a tracked base, :func:`scenarios.series.to_world`), or ``commanded`` — the
   sheath's centreline at the commanded insertion, rolled by the commanded hub angle (what an experimenter knows
   from the handle);
2. a static measurement is the mean over the last ``window`` (0.5 s) of each dwell, of the reconstructed tip and of
   the EM reading (true tip + 0.2 mm per-axis Gaussian noise, see :mod:`scenarios._sheath_common`);
3. registration: one translation maps the reconstructed tips onto the EM readings over all angles (the unknown
   offset between the FBG and EM frames; the tips move by < 1 mm, too little to fix a rotation), and the tip
   deviation at each angle is the distance left. ``max_deviation_mm`` is the largest over the angles.

Why the sensed region sticks out of the sheath: the paper's EM sensor sat at the catheter's tip, outside the sheath,
and a free distal part turns any error in the sensed bend direction into tip motion, which is what the experiment
probes; inside the sheath the tip could not move at all.

The fibre here is glued in the catheter: it twists with it. While the hub turns, friction in the bend winds the
catheter up (tens of degrees over the sensed region) and the reconstruction, which cannot see mechanical twist,
swings away from the truth; during the dwell MuJoCo's soft friction lets the wind-up creep out. The report shows
both, and the wind-up (∫ τ ds over the gratings) beside the error.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import asdict, dataclass, field

import numpy as np

from scenarios import _sheath_common as common
from scenarios.report import Report, curvature_profiles, error_over_time, tip_trajectories
from scenarios.series import calibration_for
from sim_interrogator.sheath import SheathRotate

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

    steps: int = 8
    total_angle: float = 2 * math.pi
    move_time: float = 1.0
    dwell: float = 2.0
    window: float = 0.5
    protrusion: float = 0.05
    friction: float = 0.2
    segments: int = 100
    rate: float = 20.0
    em_noise: float = 2e-4
    optics: str = "realistic"
    calibration: str = "true"
    seed: int = 0


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
    settle_s: float = 0.0
    wall_s: float = 0.0

    def summary(self) -> dict:
        d, p = self.deviation["default"], self.deviation["paper"]
        fe = self.frame_error["default"]["tracked"]
        still = ~self.turning
        return {
            "paper_max_deviation_mm": PAPER_MAX_DEVIATION_MM,
            "max_deviation_mm": float(d["tracked"].max() * 1e3),
            "mean_deviation_mm": float(d["tracked"].mean() * 1e3),
            "max_deviation_truth_mm": float(self.deviation_truth["default"]["tracked"].max() * 1e3),
            "commanded_max_deviation_mm": float(d["commanded"].max() * 1e3),
            "paper_pipeline_max_deviation_mm": float(p["tracked"].max() * 1e3),
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
                row[f"{mode}_absolute_tip_error_mm"] = float(self.absolute[mode]["tracked"][k] * 1e3)
            rows.append(row)
        return {"experiment": "rotation", "params": asdict(self.params), "setup": self.setup,
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
    recs = common.reconstructors(sim.fiber, calibration_for(params.calibration, sim))
    t = ser.t
    win = common.windows(t, setup.dwell_ends, params.window)
    last = int(win[-1][-1])
    em = common.em_readings(ser.tip, params.em_noise, params.seed)

    def avg(x):
        return np.stack([x[w].mean(axis=0) for w in win])

    true_k, em_k = avg(ser.tip), avg(em)
    nominal = setup.nominal_base_pose(t)
    bases = {"tracked": (ser.base_positions, ser.base_frames), "commanded": nominal}
    deviation, deviation_truth, absolute, frame_error = {}, {}, {}, {}
    tips = {"truth": ser.tip, "em": em}
    curvature = {"grating_s": sim.fiber.grating_s, "truth": ser.truth_curvature[last]}
    for mode, rec in recs.items():
        shape = rec(ser.wavelengths)
        curvature[mode] = shape.curvature[last]
        if mode == "default":
            common.show_frames(viewer, shape, ser)
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
        params=params, setup=sim.describe(), angles=setup.step_angles, deviation=deviation,
        deviation_truth=deviation_truth, absolute=absolute, frame_error=frame_error, t=t,
        twist=run.twist, turning=~in_dwell, lost_peaks=ser.lost_peaks, twist_at=avg(run.twist),
        tips=tips, curvature=curvature, bore=run.bore, settle_s=float(setup.settle_result.time),
        wall_s=run.wall_s,
    )
    if progress:
        s = result.summary()
        progress(f"rotation: tip deviation after registration ≤ {s['max_deviation_mm']:.3f} mm (paper "
                 f"{PAPER_MAX_DEVIATION_MM} mm); {run.wall_s:.0f} s wall")
    return result


# ------------------------------------------------------------------------------------------------ output
def text_report(result: Result) -> str:
    s, p = result.summary(), result.params
    lines = [
        f"rotation inside a pre-bent 8 Fr sheath: {p.steps} steps to {math.degrees(p.total_angle):.0f}°, "
        f"friction {p.friction:g}, sensed end {p.protrusion * 1e3:.0f} mm out of the sheath, optics {p.optics}, "
        f"calibration {p.calibration}",
        "tip deviation after registration (translation onto the EM readings), mm; base = tracked fibre base pose",
        "",
        f"{'angle':>7s}{'default':>10s}{'vs truth':>10s}{'commanded':>11s}{'paper':>9s}{'unregistered':>14s}"
        f"{'wind-up':>9s}",
    ]
    for k, a in enumerate(result.angles):
        lines.append(
            f"{math.degrees(a):6.0f}°{result.deviation['default']['tracked'][k] * 1e3:10.3f}"
            f"{result.deviation_truth['default']['tracked'][k] * 1e3:10.3f}"
            f"{result.deviation['default']['commanded'][k] * 1e3:11.3f}"
            f"{result.deviation['paper']['tracked'][k] * 1e3:9.3f}"
            f"{result.absolute['default']['tracked'][k] * 1e3:14.3f}{math.degrees(result.twist_at[k]):8.2f}°"
        )
    lines += [
        "",
        f"max tip deviation after registration: {s['max_deviation_mm']:.3f} mm (paper: ≤ {PAPER_MAX_DEVIATION_MM} mm); "
        f"paper's pipeline {s['paper_pipeline_max_deviation_mm']:.3f} mm",
        f"while turning the catheter winds up by up to {s['max_windup_deg']:.1f}° over the sensed region and the "
        f"tip error reaches {s['max_error_while_turning_mm']:.2f} mm (dwelling, before the wind-up creeps out: "
        f"{s['max_error_while_dwelling_mm']:.2f} mm)",
    ]
    return "\n".join(lines)


def write_report(result: Result, directory: str) -> str:
    """``directory``/report.md with plots: deviation vs angle, error over time, tip trajectories, curvature."""
    s, p = result.summary(), result.params
    rep = Report(directory, "Rotation inside a pre-bent 8 Fr sheath")
    rep.text(
        f"The catheter was turned {p.steps} × {math.degrees(p.total_angle / p.steps):.0f}° inside a pre-bent 8 Fr "
        f"sheath (60° bend, radius 35 mm, bore 2.8 mm, friction μ = {p.friction:g}); the end of the sensed region "
        f"stuck out of the sheath by {p.protrusion * 1e3:.0f} mm. Each step: a {p.move_time:g} s turn, a "
        f"{p.dwell:g} s dwell; the last {p.window:g} s of each dwell (FBG and EM sensor alike) is one measurement. "
        "The reconstruction is placed with the fibre base's tracked pose and registered to the EM readings by one "
        "translation; the deviation is what is left."
    )
    rep.table(*common.paper_table([
        ("tip deviation after registration (max)", f"{PAPER_MAX_DEVIATION_MM} mm",
         f"{s['max_deviation_mm']:.2f} mm", f"{s['paper_pipeline_max_deviation_mm']:.2f} mm"),
        ("same, against the true tip (no EM noise)", "–", f"{s['max_deviation_truth_mm']:.2f} mm",
         f"{result.deviation_truth['paper']['tracked'].max() * 1e3:.2f} mm"),
        ("same, base pose from the commanded roll", "–", f"{s['commanded_max_deviation_mm']:.2f} mm",
         f"{result.deviation['paper']['commanded'].max() * 1e3:.2f} mm"),
        ("tip error while turning (max)", "–", f"{s['max_error_while_turning_mm']:.2f} mm",
         f"{result.frame_error['paper']['tracked'][result.turning].max(initial=0) * 1e3:.2f} mm"),
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
    ax.plot(deg, result.deviation_truth["default"]["tracked"] * 1e3, "^:", label="default (vs true tip)")
    ax.axhline(PAPER_MAX_DEVIATION_MM, color="k", lw=0.8, ls="--", label="paper: max 0.36 mm")
    if result.deviation["paper"]["tracked"].max() > 30 * result.deviation["default"]["tracked"].max():
        ax.set_yscale("log")
    ax.set_xlabel("hub angle (°)")
    ax.set_ylabel("tip deviation (mm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    rep.figure("deviation_vs_angle", fig, "Tip deviation after registration at each angle")
    fig = error_over_time(result.t, {
        "default: tip error (mm)": result.frame_error["default"]["tracked"] * 1e3,
        "paper's pipeline (mm)": result.frame_error["paper"]["tracked"] * 1e3,
        "wind-up over the sensed region (°)": np.degrees(np.abs(result.twist)),
    }, ylabel="mm  /  °", marks=result.turning, mark_label="hub turning")
    if result.frame_error["paper"]["tracked"].max() > 30 * result.frame_error["default"]["tracked"].max():
        fig.axes[0].set_yscale("log")
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


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# ------------------------------------------------------------------------------------------------ command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--steps", type=int, default=8, help="rotation steps (default 8)")
    parser.add_argument("--angle-deg", type=float, default=360.0, help="total rotation, degrees (default 360)")
    parser.add_argument("--move-time", type=float, default=1.0, help="s per step's turn (default 1)")
    parser.add_argument("--dwell", type=float, default=2.0, help="s of dwell after each turn (default 2)")
    parser.add_argument("--window", type=float, default=0.5, help="s at the end of a dwell averaged (default 0.5)")
    parser.add_argument("--protrusion-mm", type=float, default=50.0,
                        help="end of the sensed region beyond the sheath's end, mm (default 50)")
    parser.add_argument("--em-noise-mm", type=float, default=0.2, help="EM sensor noise per axis, mm (default 0.2)")
    common.add_common_arguments(parser, rate=20.0, friction=0.2)


def params_from_args(args: argparse.Namespace) -> Params:
    return Params(steps=args.steps, total_angle=math.radians(args.angle_deg), move_time=args.move_time,
                  dwell=args.dwell, window=args.window, protrusion=args.protrusion_mm * 1e-3,
                  friction=args.friction, segments=args.segments, rate=args.rate, em_noise=args.em_noise_mm * 1e-3,
                  optics=args.optics, calibration=args.calibration, seed=args.seed)


def run(args: argparse.Namespace) -> int:
    return common.run_cli("rotation", args, sys.modules[__name__])


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="rotation", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
