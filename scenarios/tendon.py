"""tendon: the distal section steered back and forth by pull-wires, tracked by an EM sensor (Al-Ahmad et al. §IV-B/V-B).

The paper steered its catheter's tip back and forth with the handle and compared the reconstructed tip with an
electromagnetic (EM) sensor at the tip: **max deviation 2.1 mm**. Here (``sim://tendon``,
:mod:`sim_interrogator.tendon_setup`) a bidirectional catheter hangs from a clamped base; its 60 mm deflectable section
is bent by the pull-wires' equivalent load (the internal moment T·r_t·d2(s) along the section, following its
material frame: in the plane, T·r_t at the tip and −T·r_t at the compression coil's end) with the tension
T(t) = ±10 N sweeping sinusoidally (10 s period, 2 cycles): the section reaches 0.45 1/cm and the end of the
sensed length sweeps ≈ ±28 mm. The wire's compression of the section puts up to −500 µε of common-mode axial
strain on the gratings there (EA = 20 kN, see the setup), which the central core removes.

The EM sensor. Its reading is the true position of the end of the sensed length (fibre s = 170 mm, where the
reconstruction ends, so no tip offset is needed) plus white Gaussian noise of ``--em-noise-mm`` per axis, default
0.3 mm (3D RMS 0.52 mm): between an NDI Aurora's static jitter (≈ 0.1–0.2 mm) and its stated RMS accuracy
(≈ 0.5–0.7 mm), as a sensor moving through the field sees; field distortion (a fixed bias) and the EM/FBG time
offset are not modelled — samples are synchronous with the interrogator's frames.

Placement. The reconstruction lives in the fibre's base frame; it is put in the world with the true base pose
(the rod's material frame at s = 0, :func:`scenarios._common.series.to_world` — a base tracked perfectly, as if the EM
tracker's frame had been registered to the catheter's clamp beforehand). The headline deviations are measured
that way (no fitting to the EM data). ``registered`` deviations additionally fit one rigid transform of the whole
reconstructed tip trajectory onto the EM trajectory (Kabsch; what one does when the frames are unknown), which
absorbs any constant offset.

Metrics per pipeline (default and the paper's), over all frames: ``max_deviation_mm``/``rms_deviation_mm`` of
the reconstructed tip from the EM reading; the same after registration; ``true_tip_error_*`` against the exact
tip (the reconstruction's own error, no EM noise); ``shape_error_max_mm`` against the rod (Kabsch).
Two things the run shows beyond the paper's number:

* the default pipeline's own tip error (≈ 0.5–0.6 mm) is mostly the curvature step at the coil's end, which lies
  between two gratings 10 mm apart: the spline puts the step at their midpoint, the rod has it 0.5 mm further
  (bound δs·κ·lever = 1.05 mm at the defaults);
* the paper's pipeline reconstructs the *shape* as well (Kabsch error ≈ 0.44 mm) but places the steered section
  in the wrong bend plane — 9° off in the median, up to 170° — because its bend-plane angle θ_b = atan2(k_y, k_x)
  is undefined along the straight shaft (|k| is noise there) and its forward-difference torsion carries that
  noise into the section (docs/math.md §3.2, §3.6): with the true base pose its tip is off by up to ≈ 17 mm.

Calibration: ``true`` (default: the twin's true fibre parameters), ``lambda0`` (as-built λ0 only), ``nominal`` or
a calibration TOML. ``--report DIR`` writes DIR/report.md with trajectory, deviation, curvature and load plots.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from scenarios._common import entry
from scenarios._common.calibration import calibration_field, calibration_for, check_calibration
from scenarios._common.calibration import label as calibration_label
from scenarios._common.entry import option
from scenarios._common.optics_presets import optics_config, optics_field
from scenarios._common.pipelines import MODES, reconstructors
from scenarios._common.series import Series, collect, em_readings, show_frames, to_world
from sim_interrogator.sim import SimInterrogator
from sim_interrogator.tendon_setup import Tendon
from twin import FiberModel, metrics

PAPER_MAX_DEVIATION_MM = 2.1  #: Al-Ahmad et al.: max deviation of the reconstructed tip from the EM sensor


@dataclass(frozen=True)
class Params:
    """Parameters of the experiment (plain values: picklable). SI units: N, s, m, Hz; ``em_noise`` is the EM
    sensor's per-axis noise (1σ), m; ``axial_stiffness`` the deflectable section's effective EA, N."""

    max_tension: float = field(default=10.0, metadata=option("largest wire tension, N"))
    period: float = field(default=10.0, metadata=option("steering period, s"))
    cycles: float = field(default=2.0, metadata=option("number of periods"))
    wires: int = field(default=2, metadata=option(
        "2: bidirectional sweep to both sides; 1: one wire pulled and released", choices=(1, 2)))
    deflectable_length: float = field(default=0.06, metadata=option("deflectable section, mm",
                                                                     flag="--deflectable-mm", scale=1e-3))
    tendon_offset: float = field(default=0.9e-3, metadata=option("pull-wire offset from the axis, mm",
                                                                 flag="--offset-mm", scale=1e-3))
    axial_stiffness: float = field(default=2.0e4, metadata=option(
        "effective EA of the section for the fibre's compression strain, N (0: none)"))
    rate: float = field(default=20.0, metadata=option("interrogator and EM rate, Hz"))
    em_noise: float = field(default=0.3e-3, metadata=option("EM sensor noise per axis, mm", flag="--em-noise-mm",
                                                            scale=1e-3))
    optics: str = optics_field()
    calibration: str = calibration_field()
    segments: int = field(default=100, metadata=option("rod segments"))
    seed: int = field(default=0, metadata=option("seed of the interrogator's and the EM sensor's noise"))
    fiber_seed: int = field(default=0, metadata=option("which as-built fibre"))


def _stats(d: np.ndarray) -> dict[str, float]:
    """Max and RMS of distances (n,) in m, ignoring frames without a reconstruction (NaN)."""
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {"max": float("nan"), "rms": float("nan")}
    return {"max": float(d.max()), "rms": float(np.sqrt(np.mean(d * d)))}


@dataclass(frozen=True, eq=False)
class Result:
    """The run's per-frame records (leading axis: frames) and its metrics.

    Attributes
    ----------
    params : Params
    setup : dict
        The setup's description (derived loads included).
    t, tension : ndarray (n,)
        s, N (signed: > 0 the wire at +d1).
    true_tip, em : ndarray (n, 3)
        The rod's tip (end of the sensed length) and the EM reading, world, m.
    tips, registered_tips : dict mode → ndarray (n, 3)
        Reconstructed tip placed with the true base pose, and after the trajectory registration, world, m.
    shape_error : dict mode → ndarray (n,)
        Max shape error against the rod per frame (Kabsch), m.
    curvature : dict mode → ndarray (n, n_gratings, 2)
        Reconstructed curvature, 1/m.
    true_curvature : ndarray (n, n_gratings, 2)
        1/m.
    axial_strain : ndarray (n, n_gratings)
        The compression strain fed to the optics.
    lost_peaks : int
    wall_s : float
    """

    params: Params
    setup: dict
    t: np.ndarray
    tension: np.ndarray
    true_tip: np.ndarray
    em: np.ndarray
    tips: dict
    registered_tips: dict
    shape_error: dict
    curvature: dict
    true_curvature: np.ndarray
    axial_strain: np.ndarray
    lost_peaks: int
    wall_s: float
    shapes: dict = field(repr=False, default_factory=dict)
    series: Series | None = field(repr=False, default=None)
    calibration: dict = field(default_factory=dict)

    def deviations(self, mode: str) -> dict[str, np.ndarray]:
        """Per-frame distances (m): ``em`` (from the EM reading, base-pose placement), ``registered`` (from the
        EM reading after registration) and ``truth`` (from the exact tip)."""
        return {"em": np.linalg.norm(self.tips[mode] - self.em, axis=1),
                "registered": np.linalg.norm(self.registered_tips[mode] - self.em, axis=1),
                "truth": np.linalg.norm(self.tips[mode] - self.true_tip, axis=1)}

    def metrics(self, mode: str) -> dict[str, float]:
        d = self.deviations(mode)
        em, reg, tr = _stats(d["em"]), _stats(d["registered"]), _stats(d["truth"])
        return {"max_deviation_mm": em["max"] * 1e3, "rms_deviation_mm": em["rms"] * 1e3,
                "registered_max_deviation_mm": reg["max"] * 1e3, "registered_rms_deviation_mm": reg["rms"] * 1e3,
                "true_tip_error_max_mm": tr["max"] * 1e3, "true_tip_error_rms_mm": tr["rms"] * 1e3,
                "shape_error_max_mm": float(np.nanmax(self.shape_error[mode]) * 1e3)}

    def em_noise_stats(self) -> dict[str, float]:
        """The EM reading's own error (its noise), mm: max and RMS distance from the exact tip."""
        st = _stats(np.linalg.norm(self.em - self.true_tip, axis=1))
        return {"em_error_max_mm": st["max"] * 1e3, "em_error_rms_mm": st["rms"] * 1e3}

    def motion(self) -> dict[str, float]:
        """How far the tip was steered: lateral sweep (largest distance between two tip positions), mm; the
        largest curvature at a grating, 1/cm; the largest compression strain, µε."""
        tip = self.true_tip
        sweep = float(np.max(np.linalg.norm(tip[:, None] - tip[None], axis=-1))) if len(tip) > 1 else 0.0
        return {"tip_sweep_mm": sweep * 1e3,
                "max_curvature_per_cm": float(np.hypot(*np.moveaxis(self.true_curvature, -1, 0)).max() / 100),
                "max_compression_microstrain": float(-self.axial_strain.min() * 1e6)}

    def summary(self) -> dict:
        m = self.metrics("default")
        return {"paper_max_deviation_mm": PAPER_MAX_DEVIATION_MM, "max_deviation_mm": m["max_deviation_mm"],
                "rms_deviation_mm": m["rms_deviation_mm"],
                "registered_max_deviation_mm": m["registered_max_deviation_mm"],
                "true_tip_error_max_mm": m["true_tip_error_max_mm"],
                "paper_pipeline_max_deviation_mm": self.metrics("paper")["max_deviation_mm"],
                "paper_literal_max_deviation_mm": self.metrics("paper-literal")["max_deviation_mm"],
                **self.em_noise_stats(), **self.motion()}

    def to_dict(self) -> dict:
        return {"experiment": "tendon", "params": asdict(self.params), "calibration": self.calibration,
                "setup": self.setup, "frames": int(self.t.size),
                "lost_peaks": self.lost_peaks, "wall_s": self.wall_s,
                "pipelines": {mode: self.metrics(mode) for mode in MODES}, "summary": self.summary()}


# ------------------------------------------------------------------------------------------------ the experiment
def check(params: Params) -> None:
    """Clear errors for bad parameters (before any physics runs)."""
    optics_config(params.optics)  # a clear error for an unknown name
    check_calibration(params.calibration)
    if not params.rate > 0:
        raise ValueError(f"rate must be > 0 Hz, got {params.rate}")
    if not params.em_noise >= 0:
        raise ValueError(f"em_noise must be >= 0 m, got {params.em_noise}")


def make_setup(params: Params) -> Tendon:
    return Tendon(max_tension=params.max_tension, period=params.period, cycles=params.cycles, wires=params.wires,
                  deflectable_length=params.deflectable_length, tendon_offset=params.tendon_offset,
                  axial_stiffness=params.axial_stiffness, segments=params.segments)


def run_experiment(params: Params, progress: Callable[[str], None] | None = None, viewer=None) -> Result:
    """Steer the simulated catheter, reconstruct every frame and compare the tip with the EM-like reading;
    ``progress(message)`` reports as it goes; a viewer replays the frames at the end."""
    check(params)
    say = progress or (lambda msg: None)
    t_wall = time.perf_counter()
    fiber = FiberModel.paper()
    setup = make_setup(params)
    cfg = optics_config(params.optics, params.seed).replace(fiber_seed=params.fiber_seed)
    sim = SimInterrogator(setup, fiber, cfg, rate=params.rate)
    n_frames = round(setup.duration * params.rate) + 1
    d = setup.describe()
    say(f"tendon: T up to ±{params.max_tension:g} N (κ up to {d['max_section_curvature'] / 100:.2f} 1/cm on the "
        f"{params.deflectable_length * 1e3:g} mm section), {params.cycles:g} × {params.period:g} s; {n_frames} frames "
        f"at {params.rate:g} Hz …")
    quarter = max(1, n_frames // 4)

    def tick(i: int, n: int) -> None:
        if i // quarter != (i - max(1, n // 20)) // quarter or i == n:
            say(f"    frame {i}/{n}, t = {sim.time:.1f} s ({time.perf_counter() - t_wall:.1f} s wall)")

    series = collect(sim, n_frames, progress=tick)
    t = series.t
    em = em_readings(series.tip, params.em_noise, [params.seed, 1])
    used = calibration_for(params.calibration, sim.optics, fiber, progress=progress)
    cal = used.calibration
    recs = reconstructors(fiber, cal)
    tips, reg, errors, curv, shp = {}, {}, {}, {}, {}
    for mode, rec in recs.items():
        shape = rec(series.wavelengths)
        tips[mode] = to_world(shape, series)[:, -1]
        ok = np.isfinite(shape.tip).all(axis=1)
        if ok.sum() >= 3:
            R, p = metrics.kabsch(shape.tip[ok], em[ok])
            reg[mode] = shape.tip @ R.T + p
        else:
            reg[mode] = np.full_like(shape.tip, np.nan)
        err = np.full(len(series), np.nan)
        if ok.any():
            e = metrics.shape_error(shape.positions[ok], series.truth_positions[ok], s=shape.s, truth_s=series.truth_s)
            err[ok] = e.max
        errors[mode], curv[mode], shp[mode] = err, shape.curvature, shape
    result = Result(params=params, setup=d, t=t, tension=setup.tension(t), true_tip=series.tip, em=em, tips=tips,
                    registered_tips=reg, shape_error=errors, curvature=curv, true_curvature=series.truth_curvature,
                    axial_strain=setup.axial_strain(t, fiber.grating_s), lost_peaks=int(series.lost_peaks.sum()),
                    wall_s=time.perf_counter() - t_wall, shapes=shp, series=series, calibration=used.to_dict())
    m = result.metrics("default")
    say(f"    max deviation from the EM sensor {m['max_deviation_mm']:.2f} mm (RMS {m['rms_deviation_mm']:.2f} mm), "
        f"{result.wall_s:.1f} s wall")
    if viewer is not None:
        show(viewer, result)
    return result


# ------------------------------------------------------------------------------------------------ output
def text_report(result: Result) -> str:
    p = result.params
    mo = result.motion()
    lines = [
        f"tendon: ±{p.max_tension:g} N on a {p.deflectable_length * 1e3:g} mm deflectable section "
        f"(r_t {p.tendon_offset * 1e3:g} mm, {p.wires} wire{'s' if p.wires > 1 else ''}), {p.cycles:g} × "
        f"{p.period:g} s at {p.rate:g} Hz; EM noise {p.em_noise * 1e3:g} mm per axis; optics {p.optics}, "
        f"calibration {result.calibration.get('name', p.calibration)}",
        f"steering: tip sweep {mo['tip_sweep_mm']:.1f} mm, curvature up to {mo['max_curvature_per_cm']:.3f} 1/cm, "
        f"compression up to {mo['max_compression_microstrain']:.0f} µε; {result.lost_peaks} peaks lost",
        "tip deviations in mm over all frames; 'EM' places the reconstruction with the true base pose, "
        "'registered' fits one rigid transform of the tip trajectory to the EM readings",
        "",
        f"{'pipeline':14s}{'EM max':>8s}{'EM rms':>8s}{'reg max':>9s}{'reg rms':>9s}{'true max':>10s}{'true rms':>10s}"
        f"{'shape max':>11s}",
    ]
    for mode in MODES:
        m = result.metrics(mode)
        lines.append(f"{mode:14s}{m['max_deviation_mm']:8.3f}{m['rms_deviation_mm']:8.3f}"
                     f"{m['registered_max_deviation_mm']:9.3f}{m['registered_rms_deviation_mm']:9.3f}"
                     f"{m['true_tip_error_max_mm']:10.3f}{m['true_tip_error_rms_mm']:10.3f}"
                     f"{m['shape_error_max_mm']:11.3f}")
    em = result.em_noise_stats()
    s = result.summary()
    lines += ["", f"the EM reading itself is off the true tip by up to {em['em_error_max_mm']:.3f} mm (RMS "
                  f"{em['em_error_rms_mm']:.3f} mm)",
              f"ours: max deviation {s['max_deviation_mm']:.2f} mm (default pipeline); paper: "
              f"{PAPER_MAX_DEVIATION_MM} mm"]
    return "\n".join(lines)


def _trajectory_figure(result: Result):
    """Tip trajectories in the steering plane (the plane of largest motion of the true tip), mm."""
    from scenarios.report import pyplot

    plt = pyplot()
    tip = result.true_tip * 1e3
    origin = tip.mean(axis=0)
    _, _, vt = np.linalg.svd(tip - origin, full_matrices=False)

    def proj(points_mm):
        return (points_mm - origin) @ vt[:2].T

    fig, ax = plt.subplots(figsize=(6.5, 5))
    e = proj(result.em * 1e3)
    ax.plot(e[:, 0], e[:, 1], ".", color="0.6", ms=3, label="EM sensor (noisy)")
    q = proj(tip)
    ax.plot(q[:, 0], q[:, 1], "k-", lw=2.5, alpha=0.5, label="true tip")
    for j, mode in enumerate(MODES):
        q = proj(result.tips[mode] * 1e3)
        ax.plot(q[:, 0], q[:, 1], "-", color=f"C{j}", lw=1, label=f"reconstructed ({mode})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("mm (steering direction)")
    ax.set_ylabel("mm (along the catheter)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("tip trajectory in the steering plane")
    return fig


def _load_figure(result: Result, grating: int):
    """Tension and the curvature at one grating in the section over time: truth, beam theory, reconstruction."""
    from scenarios.report import pyplot

    plt = pyplot()
    p = result.params
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 4.8), sharex=True)
    a1.plot(result.t, result.tension, "C3-")
    a1.set_ylabel("wire tension (N)")
    a1.grid(alpha=0.3)
    beam = result.tension * result.setup["max_section_curvature"] / p.max_tension  # T·r_t/EI
    a2.plot(result.t, result.true_curvature[:, grating, 0], "k-", lw=2, alpha=0.5, label="truth (rod)")
    a2.plot(result.t, beam, "k:", label="beam theory T·r_t/EI")
    for j, mode in enumerate(MODES):
        a2.plot(result.t, result.curvature[mode][:, grating, 0], "--", color=f"C{j}", lw=1, label=mode)
    a2.set_ylabel("k_x (1/m)")
    a2.set_xlabel("time (s)")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=7)
    return fig


def write_report(result: Result, directory: str | Path) -> Path:
    """PNG plots and a markdown summary in ``directory``; returns the report's path."""
    from scenarios.report import Report, curvature_profiles, error_over_time

    p = result.params
    s = result.summary()
    fiber = FiberModel.paper()
    rep = Report(directory, "Tendon steering: reconstructed tip vs an EM sensor",
                 calibration_label(result.calibration))
    rep.text(f"A bidirectional catheter hangs from a clamped base; pull-wires (r_t = {p.tendon_offset * 1e3:g} mm) "
             f"bend its {p.deflectable_length * 1e3:g} mm deflectable section back and forth with up to "
             f"{p.max_tension:g} N ({p.cycles:g} periods of {p.period:g} s; {s['tip_sweep_mm']:.0f} mm tip sweep, "
             f"curvature up to {s['max_curvature_per_cm']:.2f} 1/cm). The interrogator runs at {p.rate:g} Hz; the EM "
             f"sensor reads the true tip (end of the sensed length) with {p.em_noise * 1e3:g} mm of noise per axis. "
             "The reconstruction is placed with the true base pose (no fitting to the EM data).")
    rep.table(["", "paper", "twin (default pipeline)", "twin (paper pipeline)"],
              [["max tip deviation from the EM sensor, mm", PAPER_MAX_DEVIATION_MM, s["max_deviation_mm"],
                s["paper_pipeline_max_deviation_mm"]],
               ["RMS tip deviation from the EM sensor, mm", "–", s["rms_deviation_mm"],
                result.metrics("paper")["rms_deviation_mm"]]])
    rows = []
    for mode in MODES:
        m = result.metrics(mode)
        rows.append([mode, m["max_deviation_mm"], m["rms_deviation_mm"], m["registered_max_deviation_mm"],
                     m["registered_rms_deviation_mm"], m["true_tip_error_max_mm"], m["true_tip_error_rms_mm"],
                     m["shape_error_max_mm"]])
    rep.table(["pipeline", "EM max mm", "EM RMS mm", "registered max mm", "registered RMS mm", "true-tip max mm",
               "true-tip RMS mm", "shape error max mm"], rows)
    em = result.em_noise_stats()
    rep.text(f"The EM reading itself is off the true tip by up to {em['em_error_max_mm']:.2f} mm (RMS "
             f"{em['em_error_rms_mm']:.2f} mm): most of the deviation from the EM sensor is the sensor's noise; the "
             "*true-tip* columns are the reconstruction's own error. *Registered*: one rigid transform of the "
             "reconstructed tip trajectory fitted to the EM readings. The wire's compression of the section "
             f"(up to {s['max_compression_microstrain']:.0f} µε common mode) is removed by the central core. "
             f"{result.lost_peaks} peaks were lost.")
    mp, md = result.metrics("paper"), result.metrics("default")
    if mp["true_tip_error_max_mm"] > 3 * md["true_tip_error_max_mm"]:
        rep.text(f"**The paper's pipeline** gets the shape right (Kabsch error ≤ {mp['shape_error_max_mm']:.2f} mm) "
                 f"but its tip is off by up to {mp['true_tip_error_max_mm']:.1f} mm once placed with the true base "
                 "pose: the steered section lands in the wrong bend plane. Its bend-plane angle θ_b = atan2(k_y, k_x) "
                 "is undefined along the straight shaft, where |k| is only noise, and the forward-difference torsion "
                 "carries that noise into the section (docs/math.md §3.2, §3.6). The default (material-frame) "
                 "pipeline has no such angle.")
    rep.text("The default pipeline's own error is mostly the curvature step at the coil's end "
             f"(s = {result.setup['coil_end_s'] * 1e3:.1f} mm), between two gratings 10 mm apart: the spline "
             "through the gratings cannot tell where between them the step lies.")
    rep.figure("tip_trajectories", _trajectory_figure(result), "Tip trajectories: truth, EM readings, reconstructions")
    for mode in MODES:
        dev = result.deviations(mode)
        curves = {"vs EM sensor": dev["em"] * 1e3, "vs EM sensor, registered": dev["registered"] * 1e3,
                  "vs true tip": dev["truth"] * 1e3}
        rep.figure("error_over_time" if mode == "default" else "error_over_time_paper",
                   error_over_time(result.t, curves, ylabel="tip deviation (mm)"),
                   f"Tip deviation over time, {mode} pipeline")
    rep.figure("shape_error", error_over_time(result.t, {m: result.shape_error[m] * 1e3 for m in MODES},
                                              ylabel="shape error max (mm)"),
               "Shape error against the rod (Kabsch) over time")
    i = int(np.argmax(np.abs(result.tension)))
    rep.figure("curvature", curvature_profiles(
        fiber.grating_s, result.true_curvature[i], {m: result.curvature[m][i] for m in MODES},
        title=f"curvature at t = {result.t[i]:.1f} s (T = {result.tension[i]:+.1f} N)"),
        "Curvature profiles at the largest tension, truth vs reconstruction")
    g = int(np.argmin(np.abs(fiber.grating_s - 0.5 * (fiber.sensed_length + result.setup["coil_end_s"]))))
    rep.figure("load", _load_figure(result, g),
               f"Wire tension and curvature at the grating at {fiber.grating_s[g] * 1e3:.0f} mm (in the section)")
    if result.series is not None and result.shapes:
        _overlays(rep, result)
    rep.text("Run: `twin run tendon " + " ".join(entry.command_line(p)) + "`")
    return rep.write()


def _overlays(rep, result: Result, count: int = 5) -> None:
    """Shape overlays at a few frames (the extremes of the sweep among them) and the error along the arc."""
    from scenarios.report import error_along_arc, overlay_panels, shape_overlays

    series = result.series
    idx = np.unique(np.append(np.linspace(0, len(series) - 1, count - 2).round().astype(int),
                              [int(np.argmax(result.tension)), int(np.argmin(result.tension))]))
    idx = np.array([i for i in idx if all(np.isfinite(result.shapes[m].positions[i]).all() for m in ("default",
                                                                                                    "paper"))])
    if idx.size == 0:
        return
    names = [f"t = {result.t[i]:.1f} s, T = {result.tension[i]:+.1f} N" for i in idx]
    recon = {m: to_world(result.shapes[m][idx], series, idx) for m in ("default", "paper")}
    panels, along = overlay_panels(names, series.truth_positions[idx], series.truth_s, recon,
                                   result.shapes["default"].s)
    rep.figure("shape_overlays", shape_overlays(panels, "Reconstructions over the catheter (registered onto it; mm)",
                                                rep.calibration), "a few frames of the sweep, registered")
    fig = error_along_arc(result.shapes["default"].s, {n: along["default"][i] * 1e3 for i, n in enumerate(names)},
                          "Error along the arc length, default pipeline", rep.calibration)
    rep.figure("error_along_arc", fig, "distance of the registered reconstruction from the catheter")


def show(viewer, result: Result, most: int = 150) -> None:
    """Replay up to ``most`` frames in a viewer (``viewer.show(shape, truth, base_pose=…)``), paced by its rate
    limiter."""
    show_frames(viewer, result.shapes["default"], result.series, count=min(most, len(result.series)), pause=None,
                label=lambda i: f"tendon T = {result.tension[i]:+.1f} N")


# ------------------------------------------------------------------------------------------------ command line
def add_arguments(parser) -> None:
    entry.add_arguments(parser, Params)


def params_from_args(args) -> Params:
    params = entry.params_from_args(Params, args)
    check(params)
    make_setup(params)  # the setup's own checks (tension, section length, offset) before any physics
    return params


def run(args) -> int:
    return entry.run("tendon", sys.modules[__name__], args)


if __name__ == "__main__":
    entry.main(sys.modules[__name__])
