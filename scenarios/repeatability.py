"""repeatability: in and out of the same pre-bent sheath to a reference point (Al-Ahmad et al. §IV-B,
docs/simulation.md §7).

The paper pulled its catheter out of a sheath and pushed it back to a reference point repeatedly; the sensed tip
came back within ±0.82 mm (std), 2.84 mm at most. In the twin (``sim://sheath-cycle``) the catheter sits in the
pre-bent 8 Fr sheath of the rotation experiment (60°, R 35 mm, bore 2.8 mm, μ 0.2) with the end of the sensed
region 50 mm out of the sheath; each cycle the hub withdraws it by 80 mm (the tip goes back inside the sheath) at
50 mm/s, pauses, pushes it back to the reference and dwells. The last ``window`` of each dwell is one measurement
(mean of its frames).

Spread of the tip over the cycles, each as the RMS distance from the mean tip (``std``; per-axis standard
deviations in the JSON too) and the largest distance from it (``max``):

* ``fibre frame``: the reconstructed tip in the fibre's own base frame — what the shape sensor alone reports,
  no tracking or registration involved; the headline, like the paper's;
* ``true``: the catheter's true tip in its true base frame (how repeatable the physical catheter is);
* ``world``: the reconstruction placed with the tracked base pose, and the EM sensor's readings.

By default the hub returns exactly to the reference (a motorised stage); ``--depth-jitter-mm`` and
``--roll-jitter-deg`` make the return vary like a hand's, which the paper's figure includes.
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
from sim_interrogator.sheath_setups import SheathCycle

PAPER_STD_MM = 0.82
PAPER_MAX_MM = 2.84


@dataclass(frozen=True)
class Params:
    """Parameters of the experiment (SI units, plain values: picklable).

    Attributes
    ----------
    cycles : int
        In-and-out cycles (≥ 2 for a spread).
    protrusion, withdraw, speed : float
        m, m, m/s.
    dwell, window : float
        s at the reference, and the end part of it averaged as one measurement.
    depth_jitter, roll_jitter : float
        1σ of the return to the reference, m and rad.
    friction : float
    segments : int
    rate : float
        Hz.
    em_noise : float
        m per axis.
    optics, calibration : str
    seed : int
    """

    cycles: int = field(default=10, metadata=option("in-and-out cycles"))
    protrusion: float = field(default=0.05, metadata=option(
        "end of the sensed region beyond the sheath's end at the reference, mm", flag="--protrusion-mm", scale=1e-3))
    withdraw: float = field(default=0.08, metadata=option("withdrawal per cycle, mm", flag="--withdraw-mm",
                                                          scale=1e-3))
    speed: float = field(default=0.05, metadata=option("hub speed, mm/s", flag="--speed-mm-s", scale=1e-3))
    dwell: float = field(default=1.0, metadata=option("s at the reference"))
    window: float = field(default=0.3, metadata=option("s at the end of a dwell averaged"))
    depth_jitter: float = field(default=0.0, metadata=option("1σ of the return depth, mm", flag="--depth-jitter-mm",
                                                             scale=1e-3))
    roll_jitter: float = field(default=0.0, metadata=option("1σ of the return roll, °", flag="--roll-jitter-deg",
                                                            scale=DEG))
    friction: float = field(default=0.2, metadata=option("Coulomb friction catheter–sheath"))
    segments: int = field(default=100, metadata=option("rod segments"))
    rate: float = field(default=20.0, metadata=option("interrogator frame rate, Hz"))
    em_noise: float = field(default=2e-4, metadata=option("EM sensor noise per axis, mm", flag="--em-noise-mm",
                                                          scale=1e-3))
    optics: str = common.optics_field()
    calibration: str = common.calibration_field()
    seed: int = common.seed_field()


def spread(points: np.ndarray) -> dict:
    """Spread of points (k, 3) about their mean, m: ``std`` (RMS distance), ``max`` (largest distance) and
    ``axis_std`` (per-axis standard deviations)."""
    d = np.linalg.norm(points - points.mean(axis=0), axis=1)
    return {"std": float(np.sqrt(np.mean(d**2))), "max": float(d.max()), "axis_std": points.std(axis=0)}


@dataclass(frozen=True, eq=False)
class Result:
    """Outcome of a run (m, s).

    Attributes
    ----------
    params : Params
    setup : dict
    tips : dict
        Tip at each return to the reference (cycles, 3): ``fibre`` (per mode: reconstructed, fibre base frame),
        ``true`` (true tip, true base frame), ``world`` (per mode, tracked base), ``true_world``, ``em``.
    tip_error : dict
        Per mode, the reconstructed tip's distance from the true one at each return (fibre frame), m.
    t : ndarray (n,)
    frame_error : dict
        Per mode, per frame: reconstructed tip − true tip (fibre frame), m.
    at_reference : ndarray of bool (n,)
        Frames inside the measurement windows.
    trajectories : dict
        World tip over the run (n, 3): ``truth`` and per mode (tracked base).
    curvature : dict
        At the last return: ``truth`` and per mode (n_gratings, 2), 1/m; ``grating_s``.
    lost_peaks : ndarray (n,)
    bore : ndarray (n,)
        Largest distance of the sensed region inside the sheath from the sheath's centreline, m.
    settle_s, wall_s : float
    """

    params: Params
    setup: dict
    tips: dict = field(repr=False)
    tip_error: dict = field(repr=False)
    t: np.ndarray = field(repr=False)
    frame_error: dict = field(repr=False)
    at_reference: np.ndarray = field(repr=False)
    trajectories: dict = field(repr=False)
    curvature: dict = field(repr=False)
    lost_peaks: np.ndarray = field(repr=False)
    bore: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    shapes: dict = field(default_factory=dict, repr=False)
    calibration: dict = field(default_factory=dict)
    settle_s: float = 0.0
    wall_s: float = 0.0

    def spreads(self) -> dict:
        t = self.tips
        out = {f"fiber_{m}": spread(t["fiber"][m]) for m in common.MODES}
        out |= {f"world_{m}": spread(t["world"][m]) for m in common.MODES}
        out |= {"true": spread(t["true"]), "true_world": spread(t["true_world"]), "em": spread(t["em"])}
        return out

    def summary(self) -> dict:
        sp = self.spreads()
        return {
            "paper_std_mm": PAPER_STD_MM,
            "paper_max_mm": PAPER_MAX_MM,
            "std_mm": sp["fiber_default"]["std"] * 1e3,
            "max_mm": sp["fiber_default"]["max"] * 1e3,
            "paper_pipeline_std_mm": sp["fiber_paper"]["std"] * 1e3,
            "paper_pipeline_max_mm": sp["fiber_paper"]["max"] * 1e3,
            "paper_literal_std_mm": sp["fiber_paper-literal"]["std"] * 1e3,
            "paper_literal_max_mm": sp["fiber_paper-literal"]["max"] * 1e3,
            "true_std_mm": sp["true"]["std"] * 1e3,
            "true_max_mm": sp["true"]["max"] * 1e3,
            "world_std_mm": sp["world_default"]["std"] * 1e3,
            "em_std_mm": sp["em"]["std"] * 1e3,
            "max_tip_error_mm": float(self.tip_error["default"].max() * 1e3),
            "paper_pipeline_max_tip_error_mm": float(self.tip_error["paper"].max() * 1e3),
            "paper_literal_max_tip_error_mm": float(self.tip_error["paper-literal"].max() * 1e3),
            "cycles": int(self.params.cycles),
            "lost_peaks": int(self.lost_peaks.sum()),
            "max_bore_offset_mm": float(np.nanmax(self.bore) * 1e3) if np.isfinite(self.bore).any() else None,
        }

    def to_dict(self) -> dict:
        sp = self.spreads()
        spreads = {k: {"std_mm": v["std"] * 1e3, "max_mm": v["max"] * 1e3,
                       "axis_std_mm": (np.asarray(v["axis_std"]) * 1e3).tolist()} for k, v in sp.items()}
        cycles = [{"cycle": k + 1,
                   "fiber_tip_mm": (self.tips["fiber"]["default"][k] * 1e3).tolist(),
                   "true_tip_mm": (self.tips["true"][k] * 1e3).tolist(),
                   "tip_error_mm": float(self.tip_error["default"][k] * 1e3),
                   "paper_tip_error_mm": float(self.tip_error["paper"][k] * 1e3)}
                  for k in range(len(self.tips["true"]))]
        return {"experiment": "repeatability", "params": asdict(self.params), "calibration": self.calibration,
                "setup": self.setup,
                "summary": self.summary(), "spreads": spreads, "cycles": cycles, "settle_s": self.settle_s,
                "wall_s": self.wall_s}


def run_experiment(params: Params, progress=None, viewer=None) -> Result:
    """Run the repeatability experiment; ``progress(message)`` reports as it goes."""
    if params.cycles < 2:
        raise ValueError(f"cycles must be at least 2 for a spread, got {params.cycles}")
    if params.window <= 0 or params.window > params.dwell:
        raise ValueError(f"window must be in (0, dwell = {params.dwell}] s, got {params.window}")
    setup = SheathCycle(cycles=params.cycles, protrusion=params.protrusion, withdraw=params.withdraw,
                        speed=params.speed, dwell=params.dwell, depth_jitter=params.depth_jitter,
                        roll_jitter=params.roll_jitter, seed=params.seed, friction=params.friction,
                        segments=params.segments)
    run = common.run_setup(setup, optics=params.optics, seed=params.seed, rate=params.rate, label="repeatability",
                           progress=progress)
    ser, sim = run.series, run.sim
    used = calibration_for(params.calibration, sim.optics, sim.fiber, progress=progress)
    recs = common.reconstructors(sim.fiber, used.calibration)
    t = ser.t
    win = common.windows(t, setup.reference_times[1:], params.window)  # each return (not the settled start)
    last = int(win[-1][-1])
    at_ref = np.zeros(t.size, bool)
    for w in win:
        at_ref[w] = True

    def avg(x):
        return np.stack([x[w].mean(axis=0) for w in win])

    rel = ser.tip - ser.base_positions
    true_fiber = np.einsum("nji,nj->ni", ser.base_frames, rel)  # true tip in the true base frame
    em = common.em_readings(ser.tip, params.em_noise, params.seed + common.EM_STREAM)
    tips = {"fiber": {}, "world": {}, "true": avg(true_fiber), "true_world": avg(ser.tip), "em": avg(em)}
    tip_error, frame_error = {}, {}
    trajectories = {"truth": ser.tip}
    curvature = {"grating_s": sim.fiber.grating_s, "truth": ser.truth_curvature[last]}
    # the catheter's centreline in the true base frame at each return, and each pipeline's shape in its own
    rel = ser.truth_positions - ser.base_positions[:, None, :]
    measured = {"truth": avg(np.einsum("nji,npj->npi", ser.base_frames, rel)), "truth_s": ser.truth_s}
    for mode, rec in recs.items():
        shape = rec(ser.wavelengths)
        measured[mode], measured["s"] = avg(shape.positions), shape.s
        if mode == "default":
            common.show_frames(viewer, shape, ser)
        world = np.einsum("nij,nj->ni", ser.base_frames, shape.tip) + ser.base_positions
        tips["fiber"][mode] = avg(shape.tip)
        tips["world"][mode] = avg(world)
        tip_error[mode] = np.linalg.norm(tips["fiber"][mode] - tips["true"], axis=1)
        frame_error[mode] = np.linalg.norm(shape.tip - true_fiber, axis=1)
        trajectories[mode] = world
        curvature[mode] = shape.curvature[last]
    result = Result(params, sim.describe(), tips, tip_error, t, frame_error, at_ref, trajectories, curvature,
                    ser.lost_peaks, run.bore, measured, used.to_dict(), float(setup.settle_result.time), run.wall_s)
    if progress:
        s = result.summary()
        progress(f"repeatability: tip std {s['std_mm']:.3f} mm, max {s['max_mm']:.3f} mm over {params.cycles} "
                 f"cycles (paper ±{PAPER_STD_MM} mm, max {PAPER_MAX_MM} mm); {run.wall_s:.0f} s wall")
    return result


# ------------------------------------------------------------------------------------------------ output
def text_report(result: Result) -> str:
    s, p = result.summary(), result.params
    sp = result.spreads()
    lines = [
        f"repeatability: {p.cycles} cycles out of a pre-bent 8 Fr sheath by {p.withdraw * 1e3:.0f} mm and back to "
        f"the reference (sensed end {p.protrusion * 1e3:.0f} mm out), friction {p.friction:g}, optics {p.optics}, "
        f"calibration {result.calibration.get('name', p.calibration)}, return jitter {p.depth_jitter * 1e3:g} mm / "
        f"{math.degrees(p.roll_jitter):g}°",
        "spread of the tip at the reference over the cycles, mm (std = RMS distance from the mean tip)",
        "",
        f"{'':34s}{'std':>8s}{'max':>8s}",
        f"{'paper':34s}{PAPER_STD_MM:8.2f}{PAPER_MAX_MM:8.2f}",
    ]
    for key, label in (("fiber_default", "reconstructed, fibre frame"), ("fiber_paper", "  paper's pipeline (guarded)"),
                       ("fiber_paper-literal", "  paper's pipeline, literal"),
                       ("true", "true catheter, its base frame"), ("world_default", "reconstructed, world"),
                       ("true_world", "true catheter, world"), ("em", "EM sensor")):
        lines.append(f"{label:34s}{sp[key]['std'] * 1e3:8.3f}{sp[key]['max'] * 1e3:8.3f}")
    lines += ["", f"reconstructed tip error at the reference: ≤ {s['max_tip_error_mm']:.3f} mm (default), "
                  f"≤ {s['paper_pipeline_max_tip_error_mm']:.3f} mm (paper's pipeline), "
                  f"≤ {s['paper_literal_max_tip_error_mm']:.3f} mm (literal)"]
    return "\n".join(lines)


def write_report(result: Result, directory: str) -> str:
    """``directory``/report.md with plots: tip scatter, error over time, tip trajectories, curvature."""
    s, p = result.summary(), result.params
    rep = Report(directory, "Repeatability: in and out of the same sheath",
                 calibration_label(result.calibration))
    rep.text(
        f"The catheter was withdrawn {p.cycles} times by {p.withdraw * 1e3:.0f} mm at {p.speed * 1e3:.0f} mm/s "
        f"from a pre-bent 8 Fr sheath (60°, R 35 mm, bore 2.8 mm, μ = {p.friction:g}) and pushed back to the "
        f"reference, where the end of the sensed region sticks out by {p.protrusion * 1e3:.0f} mm; each return is "
        f"measured over the last {p.window:g} s of a {p.dwell:g} s dwell. The spread is the RMS (std) and largest "
        "distance of the tip from its mean over the returns, in the fibre's own base frame (what the sensor reports "
        "without any tracking)."
    )
    rep.text(f"Calibration: {result.calibration.get('name')} — {result.calibration.get('description', '')}.")
    sp = result.spreads()
    rep.table(*common.paper_table([
        ("tip spread, std", f"±{PAPER_STD_MM} mm", *(f"{sp['fiber_' + m]['std'] * 1e3:.2f} mm" for m in common.MODES)),
        ("tip spread, max", f"{PAPER_MAX_MM} mm", *(f"{sp['fiber_' + m]['max'] * 1e3:.2f} mm" for m in common.MODES)),
        ("true catheter tip spread, std / max", "–", f"{s['true_std_mm']:.2f} / {s['true_max_mm']:.2f} mm", "–", "–"),
        ("tip error at the reference (max)", "–", *(f"{result.tip_error[m].max() * 1e3:.2f} mm"
                                                    for m in common.MODES)),
    ]))
    rep.text(
        "The paper moved its catheter by hand and measured with its own pipeline; here the hub returns exactly "
        f"(return jitter {p.depth_jitter * 1e3:g} mm, {math.degrees(p.roll_jitter):g}°), so the spread is the "
        "sensor's (noise, drift) plus the catheter's own (friction history in the sheath)."
    )
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 5))
    true, recon = result.tips["true"], result.tips["fiber"]["default"]
    _, _, vt = np.linalg.svd(np.concatenate([recon - recon.mean(axis=0), true - true.mean(axis=0)]))
    for label, pts, style in (("true tip", true, "ko"), ("reconstructed (default)", recon, "C0x")):
        q = (pts - pts.mean(axis=0)) @ vt[:2].T * 1e3
        ax.plot(q[:, 0], q[:, 1], style, label=label)
    ax.add_patch(plt.Circle((0, 0), PAPER_STD_MM, fill=False, ls="--", color="0.5", label="paper's std"))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("mm (largest spread)")
    ax.set_ylabel("mm")
    ax.set_title("tip at each return, about each set's mean")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    offset = np.linalg.norm(recon.mean(axis=0) - true.mean(axis=0)) * 1e3
    cal = calibration_label(result.calibration)
    stamp(fig, cal)
    rep.figure("tip_scatter", fig, "Tip at each return to the reference, fibre base frame, each set about its own "
               f"mean (the reconstruction's mean is {offset:.2f} mm from the true one: its static error)")
    fig = error_over_time(result.t, {"default": result.frame_error["default"] * 1e3,
                                     "paper's pipeline, guarded": result.frame_error["paper"] * 1e3,
                                     "paper's pipeline, literal": result.frame_error["paper-literal"] * 1e3},
                          ylabel="tip error, fibre frame (mm)", marks=result.at_reference,
                          mark_label="measured at the reference")
    if result.frame_error["paper-literal"].max() > 30 * max(result.frame_error["default"].max(), 1e-6):
        fig.axes[0].set_yscale("log")
    stamp(fig, cal)
    rep.figure("error_over_time", fig, "Reconstructed tip error over the cycles")
    names = [f"cycle {k + 1}" for k in range(len(result.tips["true"]))]
    dist = {m: np.linalg.norm(result.tips["fiber"][m] - result.tips["fiber"][m].mean(axis=0), axis=1) * 1e3
            for m in common.MODES}
    fig = per_shape_errors(names, dist, None, "Distance of the tip from its mean tip at each return (fibre frame)",
                           cal, paper_max_mm=PAPER_MAX_MM, xlabel="return", ylabel="distance from the mean tip (mm)")
    rep.figure("spread_per_cycle", fig, "Each return's distance from the mean tip, per pipeline (dashed: the "
               "paper's largest, on hardware)")
    sh = result.shapes
    if sh:
        panels, along = overlay_panels(names, sh["truth"], sh["truth_s"], {m: sh[m] for m in ("default", "paper")},
                                       sh["s"])
        rep.figure("shape_overlays", shape_overlays(panels, "Shape at each return over the catheter (registered "
                                                    "onto it; mm)", cal), "The shape at each return to the "
                   "reference (mean over the window), registered onto the catheter")
        fig = error_along_arc(sh["s"], {n: along["default"][i] * 1e3 for i, n in enumerate(names)},
                              "Error along the arc length at each return, default pipeline", cal)
        rep.figure("error_along_arc", fig, "distance of the registered reconstruction from the catheter")
    tr = {k: v * 1e3 for k, v in result.trajectories.items()}
    fig = tip_trajectories(tr["truth"], {"default": tr["default"]}, "tip in the world over the cycles")
    rep.figure("tip_trajectories", fig, "Tip trajectory over the cycles, truth vs reconstruction (tracked base)")
    c = result.curvature
    fig = curvature_profiles(c["grating_s"], c["truth"], {"default": c["default"], "paper's pipeline": c["paper"]},
                             "curvature at the last return")
    rep.figure("curvature_profiles", fig, "Curvature at the gratings, truth vs reconstruction")
    rep.text("```\n" + text_report(result) + "\n```")
    return str(rep.write())


# ------------------------------------------------------------------------------------------------ command line
def add_arguments(parser) -> None:
    entry.add_arguments(parser, Params)


def run(args) -> int:
    return entry.run("repeatability", sys.modules[__name__], args)


if __name__ == "__main__":
    entry.main(sys.modules[__name__])
