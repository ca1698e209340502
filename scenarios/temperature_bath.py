"""temperature-bath: a shaped catheter in a bath cooling from 60 °C to 30 °C (Al-Ahmad et al. §IV-B/V-B).

The paper put its shaped catheter in a 60 °C water bath and let it cool to 30 °C: the reconstructed tip varied by
at most **0.29 mm** over the 30 K. Here the catheter is held in a library shape (``sim://bath``: connect
constraints by default, or a 3 mm tube) while the bath follows a Newton cooling curve toward a 22 °C room
(:mod:`sim_interrogator.thermal_setup`; λ0 is referenced to room temperature, so the fibre sees ΔT = T − 22 °C, from
38 K down to 8 K). The temperature affects only the optics: each core shifts by S_T,i·ΔT·λ0 (≈ 0.3 nm over the
30 K at 1550 nm), a common mode that the central core removes; what leaks into the curvature comes from the per-core
S_T mismatch (``OpticsConfig.thermal_mismatch``, default 0.3 %, docs/math.md §6). The experiment therefore runs the
same bath twice, with the default mismatch and with none, otherwise identical (same fibre, same noise and drift
sequence, same static rod), so that their difference isolates the mismatch's effect.

Metrics (per run and pipeline; reconstructions in the fibre's base frame, which is fixed in a static fixture, so
no registration is needed or done):

* the interrogator runs at ``--rate`` and its wavelengths are averaged over ``--average`` s windows (as one
  averages a held reading; 1 pm of white noise alone would move the tip ≈ 0.1 mm per frame, docs/math.md §6);
* ``tip_variation_mm`` — the headline, compared with the paper's 0.29 mm: the largest distance of the (window)
  tip from its mean position over the run; ``tip_range_mm`` the largest distance between any two tip positions
  (max − min); ``tip_change_mm`` the distance from the first window's tip to the last one's (60 → 30 °C);
* ``mismatch_effect_mm`` — the largest displacement, relative to the start, of the tip difference between the
  run with mismatch and the run without: the per-core S_T mismatch's share alone (noise and drift cancel);
* ``common_mode_pm`` — the central core's Bragg shift over the run (mean over gratings): what the central core
  removes; ``uncompensated_tip_variation_mm`` — the tip variation when that removal is defeated (the central
  core's reading held at its first window), to show what the common mode would do;
* ``shape_error_max_mm`` — the largest shape error against the rod over the run (Kabsch, the algorithm's error);
* ``coverage_95``, ``mean_sigma_mm`` — the default pipeline's 95 % confidence tube against the rod (no
  registration; the white noise shrunk by the window's averaging; :mod:`scenarios._common.coverage`): the
  fraction of the rod's points (s > 0, every window) inside it (``coverage_95_by_quarter``: per quarter of the
  length) and its mean 1σ lateral radius.

Calibration: ``true`` (default) reconstructs with the twin's true fibre parameters (as-built λ0 at the reference
temperature, intrinsic twist, Δθ, g); ``lambda0`` with the as-built λ0 only (nominal Δθ, g, no twist);
``nominal`` with the datasheet; or a calibration TOML.

``--report DIR`` writes DIR/report.md with plots (temperature and common mode over time, tip deviation vs
temperature, shape error over time, tip scatter, curvature profiles at 60 and 30 °C).
"""

from __future__ import annotations

import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.distance import pdist

from scenarios._common import coverage, entry
from scenarios._common.calibration import calibration_field, calibration_for, check_calibration
from scenarios._common.calibration import label as calibration_label
from scenarios._common.entry import option
from scenarios._common.optics_presets import optics_config, optics_field
from scenarios._common.pipelines import MODES, reconstructors
from scenarios._common.series import Series, collect
from sim_interrogator.sim import SimInterrogator
from sim_interrogator.thermal_setup import PROFILES, Bath
from twin import FiberModel, Reconstructor, Shape, metrics, shapes
from twin.frames import Truth
from twin.uncertainty import truth_in_base

PAPER_TIP_VARIATION_MM = 0.29  #: Al-Ahmad et al.: tip variation over 30 K (60 → 30 °C)


@dataclass(frozen=True)
class Params:
    """Parameters of the experiment (plain values: picklable, so runs can fan out across processes).

    Temperatures in °C (absolute; differences are K), times in s, rates in Hz, ``gradient`` in K/m,
    ``mismatches`` as fractions (0.003 = 0.3 %) of the per-core S_T spread, one run each.
    """

    shape: str = field(default="helix", metadata=option("library shape"))
    fixture: str = field(default="connect", metadata=option(
        "connect constraints (exact), a 3 mm tube, or a groove (planar shapes)", choices=("connect", "tube", "groove")))
    start_celsius: float = field(default=60.0, metadata=option("bath temperature at the start, °C", flag="--start"))
    end_celsius: float = field(default=30.0, metadata=option("bath temperature at the end, °C", flag="--end"))
    room_celsius: float = field(default=22.0, metadata=option(
        "room temperature = λ0 reference and the cooling's asymptote, °C", flag="--room"))
    profile: str = field(default="exponential", metadata=option("cooling curve", choices=PROFILES))
    duration: float = field(default=60.0, metadata=option("simulated seconds"))
    gradient: float = field(default=0.0, metadata=option("temperature gradient along the fibre, K/m"))
    rate: float = field(default=25.0, metadata=option("interrogator rate, Hz"))
    average: float = field(default=1.0, metadata=option("averaging window, s (0: none)"))
    mismatches: tuple[float, ...] = (0.003, 0.0)  # --mismatch-percent, in add_arguments
    optics: str = optics_field()
    calibration: str = calibration_field()
    segments: int = field(default=100, metadata=option("rod segments"))
    seed: int = field(default=0, metadata=option("seed of the interrogator's noise and drift"))
    fiber_seed: int = field(default=0, metadata=option(
        "which as-built fibre (its λ0 spread and per-core S_T deviations)"))


@dataclass(frozen=True, eq=False)
class BathRun:
    """One run of the bath, averaged into windows (leading axis: windows).

    Attributes
    ----------
    mismatch : float
        Per-core S_T spread of the simulated fibre (fraction).
    s_t_deviation : ndarray (n_cores,)
        The realised relative S_T deviation of each core from the nominal.
    t : ndarray (n,)
        Window centre times, s.
    bath_celsius : ndarray (n,)
        Mean fibre temperature in each window, °C.
    tips : dict mode → ndarray (n, 3)
        Reconstructed tip (end of the sensed length) in the fibre's base frame, m.
    true_tip : ndarray (n, 3)
        The rod's own tip in the base frame, m.
    shape_error : dict mode → ndarray (n,)
        Max shape error against the rod per window (Kabsch), m.
    curvature : dict mode → ndarray (n, n_gratings, 2)
        Reconstructed curvature, 1/m.
    true_curvature : ndarray (n_gratings, 2)
        The rod's curvature at the gratings (first frame), 1/m.
    common_mode : ndarray (n,)
        Central core's wavelength shift from the first window, mean over gratings, nm.
    uncompensated_tips : ndarray (n, 3)
        Default-pipeline tip with the central core held at its first reading, m.
    mismatch_response : ndarray (n_cores, 3)
        Linearised tip displacement (base frame, m) from the first to the last window per unit relative S_T
        deviation of each core (:func:`mismatch_response`).
    lost_peaks : int
    wall_s : float
    shapes : dict mode → Shape
        Batched reconstructions (kept for the viewer; not in :meth:`Result.to_dict`).
    base_pose : tuple (R (3, 3), p (3,))
        The fibre's base frame in the world.
    truth : Truth
        The rod's centreline (world) at the first frame.
    uncertainty : dict
        The default pipeline's 95 % tube against the rod (:func:`scenarios._common.coverage.run_coverage`).
    """

    mismatch: float
    s_t_deviation: np.ndarray
    t: np.ndarray
    bath_celsius: np.ndarray
    tips: dict
    true_tip: np.ndarray
    shape_error: dict
    curvature: dict
    true_curvature: np.ndarray
    common_mode: np.ndarray
    uncompensated_tips: np.ndarray
    mismatch_response: np.ndarray
    lost_peaks: int
    wall_s: float
    shapes: dict = field(repr=False, default_factory=dict)
    base_pose: tuple = field(repr=False, default=())
    truth: Truth | None = field(repr=False, default=None)
    uncertainty: dict = field(default_factory=dict)


def mismatch_response(rec: Reconstructor, w_ref: np.ndarray, lambda0: np.ndarray, s_t: float,
                      delta_t: np.ndarray, step: float = 1e-2) -> np.ndarray:
    """Tip displacement per unit relative S_T deviation of each core, linearised, m, shape (n_cores, 3).

    A core whose S_T is off by the fraction δ shifts by an extra δ·S_T·ΔT·λ0 beyond the common mode the central
    core removes. Adding that (with δ = ``step``) to each core of the reference wavelengths ``w_ref``
    (n_gratings, n_cores) in turn, for the temperature change ``delta_t`` (K, per grating), and differencing the
    reconstructed tips gives the response J (the reconstruction is smooth in the wavelengths). For a fibre with
    deviations δ_i the tip moves by ≈ Σ δ_i J_i; for independent deviations of spread σ its RMS over fibres is
    σ·(Σ|J_i|²)^½.
    """
    n_c = w_ref.shape[-1]
    shift = step * s_t * np.asarray(delta_t, dtype=np.float64)[:, None] * lambda0  # (n_g, n_c)
    w = np.concatenate([w_ref[None], w_ref[None] + shift[None] * np.eye(n_c)[:, None, :]])
    tips = rec(w).tip
    return (tips[1:] - tips[0]) / step


def tip_stats(tips: np.ndarray) -> dict[str, float]:
    """Variation of tip positions (n, 3) in m: ``variation`` (max distance from the mean), ``range`` (max
    distance between two positions) and ``change`` (last minus first)."""
    tips = np.asarray(tips, dtype=np.float64)
    return {
        "variation": float(np.linalg.norm(tips - tips.mean(axis=0), axis=1).max()),
        "range": float(pdist(tips).max()) if len(tips) > 1 else 0.0,
        "change": float(np.linalg.norm(tips[-1] - tips[0])),
    }


def predicted_effect(run: BathRun) -> float:
    """The tip displacement the run's realised S_T deviations should cause over the run (linearised), m."""
    return float(np.linalg.norm(run.s_t_deviation @ run.mismatch_response))


def expected_effect(run: BathRun) -> float:
    """RMS over as-built fibres of the tip displacement a per-core S_T spread of ``run.mismatch`` causes over the
    run (linearised; independent Gaussian deviations per core), m."""
    return float(run.mismatch * np.sqrt(np.sum(run.mismatch_response**2)))


@dataclass(frozen=True, eq=False)
class Result:
    params: Params
    runs: tuple[BathRun, ...]
    setup: dict
    calibration: dict = field(default_factory=dict)

    def run_for(self, mismatch: float) -> BathRun | None:
        return next((r for r in self.runs if r.mismatch == mismatch), None)

    def mismatch_effect(self, run: BathRun, mode: str = "default") -> float | None:
        """Largest displacement of the tip difference (this run − the run without mismatch) from its start, m;
        None without a mismatch-free run."""
        ref = self.run_for(0.0)
        if ref is None or run is ref:
            return None
        d = run.tips[mode] - ref.tips[mode]
        return float(np.linalg.norm(d - d[0], axis=1).max())

    def summary(self) -> dict:
        """The headline: the first run (default 0.3 % mismatch), default pipeline, next to the paper."""
        r = self.runs[0]
        st = tip_stats(r.tips["default"])
        out = {"paper_tip_variation_mm": PAPER_TIP_VARIATION_MM, "thermal_mismatch": r.mismatch,
               "tip_variation_mm": st["variation"] * 1e3, "tip_range_mm": st["range"] * 1e3,
               "paper_pipeline_tip_variation_mm": tip_stats(r.tips["paper"])["variation"] * 1e3,
               "paper_literal_tip_variation_mm": tip_stats(r.tips["paper-literal"])["variation"] * 1e3,
               "temperature_change_k": float(r.bath_celsius[0] - r.bath_celsius[-1])}
        out.update({k: r.uncertainty[k] for k in ("coverage_95", "coverage_95_by_quarter", "mean_sigma_mm")
                    if k in r.uncertainty})
        out["predicted_mismatch_effect_mm"] = predicted_effect(r) * 1e3
        out["expected_mismatch_effect_mm"] = expected_effect(r) * 1e3
        effect = self.mismatch_effect(r)
        if effect is not None:
            out["mismatch_effect_mm"] = effect * 1e3
            out["without_mismatch_tip_variation_mm"] = tip_stats(self.run_for(0.0).tips["default"])["variation"] * 1e3
        return out

    def to_dict(self) -> dict:
        runs = []
        for r in self.runs:
            row = {"thermal_mismatch": r.mismatch, "s_t_deviation": r.s_t_deviation.tolist(),
                   "windows": int(r.t.size), "lost_peaks": r.lost_peaks, "wall_s": r.wall_s,
                   "bath_start_celsius": float(r.bath_celsius[0]), "bath_end_celsius": float(r.bath_celsius[-1]),
                   "common_mode_pm": float(r.common_mode[-1] * 1e3),
                   "uncompensated_tip_variation_mm": tip_stats(r.uncompensated_tips)["variation"] * 1e3,
                   "true_tip_variation_mm": tip_stats(r.true_tip)["variation"] * 1e3,
                   "predicted_mismatch_effect_mm": predicted_effect(r) * 1e3,
                   "expected_mismatch_effect_mm": expected_effect(r) * 1e3, "uncertainty": r.uncertainty}
            for mode in MODES:
                st = tip_stats(r.tips[mode])
                row[mode] = {"tip_variation_mm": st["variation"] * 1e3, "tip_range_mm": st["range"] * 1e3,
                             "tip_change_mm": st["change"] * 1e3,
                             "shape_error_max_mm": float(r.shape_error[mode].max() * 1e3)}
                effect = self.mismatch_effect(r, mode)
                if effect is not None:
                    row[mode]["mismatch_effect_mm"] = effect * 1e3
            runs.append(row)
        return {"experiment": "temperature-bath", "params": asdict(self.params), "calibration": self.calibration,
                "setup": self.setup, "runs": runs, "summary": self.summary()}


# ------------------------------------------------------------------------------------------------ the experiment
def check(params: Params) -> None:
    """Clear errors for bad parameters (before any physics runs)."""
    shapes.get(params.shape)
    if params.fixture not in ("connect", "tube", "groove"):
        raise ValueError(f"fixture must be connect, tube or groove; got {params.fixture!r}")
    if params.profile not in PROFILES:
        raise ValueError(f"profile must be one of {', '.join(PROFILES)}; got {params.profile!r}")
    optics_config(params.optics)  # a clear error for an unknown name
    check_calibration(params.calibration)
    if not (params.rate > 0 and params.average >= 0 and params.duration > 0):
        raise ValueError("rate and duration must be > 0 and average >= 0")
    if not params.mismatches or any(not 0 <= m < 0.1 for m in params.mismatches):
        raise ValueError(f"mismatches must be fractions in [0, 0.1) (0.003 = 0.3 %), got {params.mismatches}")


def _windows(series: Series, n_avg: int) -> tuple[np.ndarray, ...]:
    """Average wavelengths, times and temperatures over consecutive blocks of ``n_avg`` frames (a partial last
    block is dropped when there are full ones)."""
    n = len(series) // n_avg if len(series) >= n_avg else 1
    m = min(len(series), n * n_avg)
    w = series.wavelengths[:m].reshape(n, -1, *series.wavelengths.shape[1:])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a peak lost over a whole window stays NaN
        w = np.nanmean(w, axis=1)
    t = series.t[:m].reshape(n, -1).mean(axis=1)
    temp = series.temperature[:m].reshape(n, -1, series.temperature.shape[-1]).mean(axis=1)
    mid = np.minimum(np.arange(n) * n_avg + n_avg // 2, len(series) - 1)
    return w, t, temp, mid


def run_bath(params: Params, mismatch: float, fiber: FiberModel,
             say: Callable[[str], None] = lambda msg: None) -> BathRun:
    """One run of the bath with a given per-core S_T mismatch."""
    t_wall = time.perf_counter()
    cfg = optics_config(params.optics, params.seed).replace(thermal_mismatch=mismatch, fiber_seed=params.fiber_seed)
    setup = Bath(params.shape, params.fixture, params.start_celsius, params.end_celsius, params.room_celsius,
                 params.room_celsius, params.profile, params.duration, params.gradient, params.segments)
    label = f"mismatch {mismatch * 100:g} %"
    sim = SimInterrogator(setup, fiber, cfg, rate=params.rate)
    n_frames = round(params.duration * params.rate) + 1
    say(f"  {label}: {params.shape} settled in the {params.fixture} fixture; {n_frames} frames over "
        f"{params.duration:g} s ({params.start_celsius:g} → {params.end_celsius:g} °C) …")
    quarter = max(1, n_frames // 4)

    def tick(i: int, n: int) -> None:
        if i // quarter != (i - max(1, n // 20)) // quarter or i == n:
            say(f"    {label}: frame {i}/{n}, t = {sim.time:.1f} s")

    series = collect(sim, n_frames, progress=tick)
    n_avg = max(1, round(params.average * params.rate))
    w, t, temp, mid = _windows(series, n_avg)
    used = calibration_for(params.calibration, sim.optics, fiber, progress=say)
    cal = used.calibration
    recs = reconstructors(fiber, cal)
    rot, pos = series.base_frames[0], series.base_positions[0]
    true_tip = (series.tip[mid] - pos) @ rot
    tips, errors, curv, shp = {}, {}, {}, {}
    for mode, rec in recs.items():
        shape = rec(w)
        err = metrics.shape_error(shape.positions, series.truth_positions[mid], s=shape.s, truth_s=series.truth_s)
        tips[mode], errors[mode], curv[mode], shp[mode] = shape.tip, np.atleast_1d(err.max), shape.curvature, shape
    c = fiber.central_core
    if c is None:
        raise ValueError("temperature-bath needs a fibre with a central core (it shows the common-mode removal)")
    frozen = w.copy()
    frozen[..., c] = w[:1, :, c]
    common = np.nanmean(w[..., c] - w[:1, :, c], axis=-1)
    s_t = np.broadcast_to(sim.optics.true_fiber.temperature_sensitivity, (fiber.n_cores,))
    nominal_s_t = np.broadcast_to(fiber.temperature_sensitivity, (fiber.n_cores,))
    response = mismatch_response(recs["default"], w[0], recs["default"].calibration.reference_for(fiber),
                                 float(np.mean(nominal_s_t)), temp[-1] - temp[0])
    truth = Truth(s=series.truth_s, positions=series.truth_positions[0], curvature=series.truth_curvature[0],
                  fixture=series.fixture)
    # the 95 % tube of each window against the rod at the window's middle frame, in the (fixed) base frame
    tube = coverage.run_coverage(fiber, cfg, cal, shp["default"], w, truth_in_base(
        series.truth_s, series.truth_positions[mid], series.base_frames[mid], series.base_positions[mid],
        shp["default"].s), say, averaged=n_avg)
    return BathRun(mismatch=mismatch, s_t_deviation=s_t / nominal_s_t - 1.0, t=t,
                   bath_celsius=temp.mean(axis=1) + params.room_celsius, tips=tips, true_tip=true_tip,
                   shape_error=errors, curvature=curv, true_curvature=series.truth_curvature[0],
                   common_mode=common, uncompensated_tips=recs["default"](frozen).tip, mismatch_response=response,
                   lost_peaks=int(series.lost_peaks.sum()), wall_s=time.perf_counter() - t_wall, shapes=shp,
                   base_pose=(rot, pos), truth=truth, uncertainty=tube)


def run_experiment(params: Params, progress: Callable[[str], None] | None = None, viewer=None) -> Result:
    """Run the bath once per entry of ``params.mismatches``; ``progress(message)`` reports as it goes; a viewer
    replays the first run at the end."""
    check(params)
    say = progress or (lambda msg: None)
    fiber = FiberModel.paper()
    runs = []
    for i, m in enumerate(params.mismatches):
        say(f"[{i + 1}/{len(params.mismatches)}] bath with a per-core S_T mismatch of {m * 100:g} % …")
        runs.append(run_bath(params, m, fiber, say))
        st = tip_stats(runs[-1].tips["default"])
        say(f"    tip variation {st['variation'] * 1e3:.3f} mm (range {st['range'] * 1e3:.3f} mm), "
            f"{runs[-1].wall_s:.1f} s wall")
    setup = Bath(params.shape, params.fixture, params.start_celsius, params.end_celsius, params.room_celsius,
                 params.room_celsius, params.profile, params.duration, params.gradient, params.segments).describe()
    result = Result(params, tuple(runs), setup, calibration_for(params.calibration, optics_config(
        params.optics, params.seed).replace(fiber_seed=params.fiber_seed), fiber).to_dict())
    if viewer is not None:
        show(viewer, result)
    return result


# ------------------------------------------------------------------------------------------------ output
def text_report(result: Result) -> str:
    p = result.params
    lines = [
        f"temperature bath: {p.shape} in a {p.fixture} fixture, {p.start_celsius:g} → {p.end_celsius:g} °C "
        f"({p.profile}, {p.duration:g} s simulated, room/λ0 reference {p.room_celsius:g} °C), "
        f"{p.rate:g} Hz averaged over {p.average:g} s, optics {p.optics}, "
        f"calibration {result.calibration.get('name', p.calibration)}",
        "tip positions in the fibre's base frame (fixed); variation = max distance from the mean, range = max "
        "distance between two positions, change = first to last window",
        "",
        f"{'S_T mismatch':>12s} {'pipeline':9s}{'variation':>10s}{'range':>8s}{'change':>8s}{'mismatch':>11s}"
        f"{'shape err':>11s}",
        f"{'':>12s} {'':9s}{'mm':>10s}{'mm':>8s}{'mm':>8s}{'effect mm':>11s}{'max mm':>11s}",
    ]
    for r in result.runs:
        for mode in MODES:
            st = tip_stats(r.tips[mode])
            eff = result.mismatch_effect(r, mode)
            lines.append(f"{r.mismatch * 100:11.2f}% {mode:9s}{st['variation'] * 1e3:10.3f}{st['range'] * 1e3:8.3f}"
                         f"{st['change'] * 1e3:8.3f}{'–' if eff is None else f'{eff * 1e3:.3f}':>11s}"
                         f"{r.shape_error[mode].max() * 1e3:11.3f}")
    r0 = result.runs[0]
    lines += [
        "",
        f"common mode: the central core moved {r0.common_mode[-1] * 1e3:.0f} pm over the run (removed by the "
        f"central core); held at its first reading instead, the tip would vary by "
        f"{tip_stats(r0.uncompensated_tips)['variation'] * 1e3:.1f} mm",
        "realised per-core S_T deviations (centre, outer cores): "
        + ", ".join(f"{d * 100:+.2f} %" for d in r0.s_t_deviation)
        + f"; linearised, they move the tip {predicted_effect(r0) * 1e3:.3f} mm over the run, and a "
        f"{r0.mismatch * 100:g} % spread moves it {expected_effect(r0) * 1e3:.3f} mm RMS over as-built fibres",
    ]
    s = result.summary()
    lines.append(f"ours: tip variation {s['tip_variation_mm']:.3f} mm over {s['temperature_change_k']:.1f} K "
                 f"(S_T mismatch {s['thermal_mismatch'] * 100:g} %, default pipeline)"
                 + (f", of which the mismatch moved the tip {s['mismatch_effect_mm']:.3f} mm"
                    if "mismatch_effect_mm" in s else "")
                 + f"; paper: ≤ {PAPER_TIP_VARIATION_MM} mm over 30 K")
    return "\n".join(lines)


def write_report(result: Result, directory: str | Path) -> Path:
    """PNG plots and a markdown summary in ``directory``; returns the report's path."""
    from scenarios.report import Report, curvature_profiles, error_over_time, pyplot

    plt = pyplot()
    p = result.params
    rep = Report(directory, "Temperature bath: tip variation while the bath cools",
                 calibration_label(result.calibration))
    rep.text(f"The catheter is held in the **{p.shape}** shape ({p.fixture} fixture) while the bath cools from "
             f"{p.start_celsius:g} °C to {p.end_celsius:g} °C ({p.profile} curve toward a {p.room_celsius:g} °C "
             f"room, {p.duration:g} s simulated; λ0 referenced to {p.room_celsius:g} °C). The interrogator runs at "
             f"{p.rate:g} Hz, averaged over {p.average:g} s windows. The temperature acts on the optics only "
             "(thermal expansion neglected). Tip positions are in the fibre's base frame, which the fixture "
             "holds still.")
    s = result.summary()
    rows = [["tip variation over the cooling, mm", f"≤ {PAPER_TIP_VARIATION_MM}", f"{s['tip_variation_mm']:.3f}"]]
    if "mismatch_effect_mm" in s:
        rows.append(["  of which the per-core S_T mismatch, mm", "–", f"{s['mismatch_effect_mm']:.3f}"])
        rows.append(["  without S_T mismatch, mm", "–", f"{s['without_mismatch_tip_variation_mm']:.3f}"])
    rep.table(["", "paper", f"twin (mismatch {s['thermal_mismatch'] * 100:g} %)"], rows)
    rep.text("*Tip variation* is the largest distance of the window-averaged tip from its mean over the run; "
             "*range* the largest distance between two tip positions; *change* first to last window; *mismatch "
             "effect* the largest displacement, from the start, of the tip difference between this run and the "
             "mismatch-free run (same noise and drift): the mismatch's own share.")
    table = []
    for r in result.runs:
        for mode in MODES:
            st = tip_stats(r.tips[mode])
            eff = result.mismatch_effect(r, mode)
            table.append([f"{r.mismatch * 100:g} %", mode, st["variation"] * 1e3, st["range"] * 1e3,
                          st["change"] * 1e3, "–" if eff is None else eff * 1e3, r.shape_error[mode].max() * 1e3])
    rep.table(["S_T mismatch", "pipeline", "variation mm", "range mm", "change mm", "mismatch effect mm",
               "shape error max mm"], table)
    r0 = result.runs[0]
    rep.text(f"**Common mode.** The central core's Bragg shift over the run is {r0.common_mode[-1] * 1e3:.0f} pm "
             "(mean over gratings); the reconstruction removes it. Holding the central core at its first reading "
             f"(no compensation) would move the tip by up to {tip_stats(r0.uncompensated_tips)['variation'] * 1e3:.1f}"
             " mm. What remains comes from the per-core S_T mismatch (realised deviations: "
             + ", ".join(f"{d * 100:+.2f} %" for d in r0.s_t_deviation) + ") and from the interrogator's noise "
             "and drift.")

    fig, ax = plt.subplots(figsize=(8, 3.2))
    ax.plot(r0.t, r0.bath_celsius, "C3-", label="bath (mean over the fibre)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("temperature (°C)")
    ax2 = ax.twinx()
    ax2.plot(r0.t, r0.common_mode * 1e3, "C0--", label="central-core shift")
    ax2.set_ylabel("central-core shift from start (pm)")
    ax.grid(alpha=0.3)
    fig.legend(loc="upper right", fontsize=8)
    rep.figure("temperature", fig, "Bath temperature and the common-mode Bragg shift the central core removes")

    fig, ax = plt.subplots(figsize=(8, 3.6))
    for i, r in enumerate(result.runs):
        for mode, style in (("default", "-"), ("paper", ":")):
            tips = r.tips[mode]
            ax.plot(r.bath_celsius, np.linalg.norm(tips - tips[0], axis=1) * 1e3, style, color=f"C{i}",
                    label=f"{mode}, mismatch {r.mismatch * 100:g} %")
        eff = result.mismatch_effect(r)
        if eff is not None:
            ref = result.run_for(0.0)
            d = r.tips["default"] - ref.tips["default"]
            ax.plot(r.bath_celsius, np.linalg.norm(d - d[0], axis=1) * 1e3, "--", color=f"C{i}", lw=2,
                    label=f"mismatch {r.mismatch * 100:g} % effect alone")
    ax.axhline(PAPER_TIP_VARIATION_MM, color="k", lw=1, ls="-.", label="paper: 0.29 mm")
    ax.invert_xaxis()
    ax.set_xlabel("bath temperature (°C)")
    ax.set_ylabel("tip displacement from start (mm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    rep.figure("tip_vs_temperature", fig, "Tip displacement from its 60 °C position as the bath cools")

    curves = {f"{mode}, mismatch {r.mismatch * 100:g} %": r.shape_error[mode] * 1e3
              for r in result.runs for mode in MODES}
    rep.figure("error_over_time", error_over_time(r0.t, curves, ylabel="shape error max (mm)"),
               "Shape error against the rod (Kabsch) over time")
    rep.figure("tip_trajectories", _tip_scatter(result),
               "Reconstructed tip (default pipeline) during the run, relative to the true (still) tip")
    fiber = FiberModel.paper()
    rep.figure("curvature", curvature_profiles(
        fiber.grating_s, r0.true_curvature,
        {f"default at {r0.bath_celsius[0]:.0f} °C": r0.curvature["default"][0],
         f"default at {r0.bath_celsius[-1]:.0f} °C": r0.curvature["default"][-1],
         f"paper at {r0.bath_celsius[-1]:.0f} °C": r0.curvature["paper"][-1]},
        title="curvature along the fibre, truth vs reconstruction"), "Curvature profiles, start and end of the run")
    rep.text("Run: `twin run temperature-bath " + " ".join(_cli_args(p)) + "`")
    _overlays(rep, result)
    return rep.write()


def _overlays(rep, result: Result) -> None:
    """The first and last windows of the first run over the catheter, and the error along the arc."""
    from scenarios.report import error_along_arc, overlay_panels, shape_overlays

    r = result.runs[0]
    if not r.shapes or r.truth is None:
        return
    rot, pos = r.base_pose
    idx = np.array([0, r.t.size - 1])
    names = [f"bath {r.bath_celsius[i]:.1f} °C" for i in idx]
    recon = {m: r.shapes[m].positions[idx] @ rot.T + pos for m in ("default", "paper")}
    truth = np.repeat(r.truth.positions[None], idx.size, axis=0)
    fixture = None if r.truth.fixture is None else np.repeat(r.truth.fixture[None], idx.size, axis=0)
    panels, along = overlay_panels(names, truth, r.truth.s, recon, r.shapes["default"].s, fixture=fixture)
    rep.figure("shape_overlays", shape_overlays(panels, "Hot and cooled: reconstructions over the catheter "
                                                "(registered onto it; mm)", rep.calibration),
               "the first and last averaging windows of the first run, registered onto the catheter")
    fig = error_along_arc(r.shapes["default"].s, {n: along["default"][i] * 1e3 for i, n in enumerate(names)},
                          "Error along the arc length, default pipeline", rep.calibration)
    rep.figure("error_along_arc", fig, "distance of the registered reconstruction from the catheter")


def _tip_scatter(result: Result):
    """Default-pipeline tips minus the true tip (mm) in the plane of their largest spread, coloured by temperature
    (the paper pipeline's tips sit ≈ 2.7 mm away on the helix, its own systematic error, and would hide the
    spread)."""
    from scenarios.report import pyplot

    plt = pyplot()
    r0 = result.runs[0]
    rel = {f"default, mismatch {r.mismatch * 100:g} %": (r.tips["default"] - r.true_tip) * 1e3 for r in result.runs}
    allp = np.concatenate(list(rel.values()))
    _, _, vt = np.linalg.svd(allp - allp.mean(axis=0), full_matrices=False)
    fig, ax = plt.subplots(figsize=(5.5, 5))
    markers = "os^vD<>p"
    for j, (label, pts) in enumerate(rel.items()):
        q = pts @ vt[:2].T
        sc = ax.scatter(q[:, 0], q[:, 1], c=r0.bath_celsius[: len(q)], cmap="coolwarm", s=14,
                        marker=markers[j % len(markers)], label=label, vmin=r0.bath_celsius.min(),
                        vmax=r0.bath_celsius.max())
    ax.plot([0], [0], "k*", ms=12, label="true tip")
    fig.colorbar(sc, ax=ax, label="bath temperature (°C)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("mm (first principal direction)")
    ax.set_ylabel("mm (second principal direction)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return fig


def _cli_args(p: Params) -> list[str]:
    out = entry.command_line(p)
    if p.mismatches != Params().mismatches:
        out.append("--mismatch-percent " + ",".join(f"{m * 100:g}" for m in p.mismatches))
    return out


def show(viewer, result: Result, most: int = 60) -> None:
    """Replay up to ``most`` windows of the first run in a viewer (``viewer.show(shape, truth, base_pose=…)``),
    paced by the viewer's own rate limiter."""
    r = result.runs[0]
    shape: Shape = r.shapes["default"]
    for i in np.unique(np.linspace(0, r.t.size - 1, min(most, r.t.size)).round().astype(int)):
        ready = getattr(viewer, "ready", None)
        while ready is not None and not ready():
            time.sleep(0.005)
        viewer.show(shape[int(i)], r.truth, base_pose=r.base_pose, label=f"bath {r.bath_celsius[i]:.1f} °C")


# ------------------------------------------------------------------------------------------------ command line
def add_arguments(parser) -> None:
    entry.add_arguments(parser, Params)
    parser.add_argument("--mismatch-percent", default="0.3,0",
                        help="per-core S_T mismatch(es), %%, one run each; include 0 to isolate the mismatch's "
                             "effect (default 0.3,0)")


def params_from_args(args) -> Params:
    try:
        mismatches = tuple(float(v) / 100 for v in args.mismatch_percent.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"--mismatch-percent {args.mismatch_percent!r}: expected numbers like 0.3,0") from None
    params = entry.params_from_args(Params, args, mismatches=mismatches)
    check(params)
    return params


def run(args) -> int:
    return entry.run("temperature-bath", sys.modules[__name__], args)


if __name__ == "__main__":
    entry.main(sys.modules[__name__])
