"""static-shapes: the paper's static experiment in the twin (Al-Ahmad et al. §IV-A, docs/simulation.md §7).

The 12 library shapes (6 planar, 6 spatial, 170 mm) are imposed on the simulated 8 Fr catheter — exactly by
connect constraints, or by a rigid 3 mm tube like the paper's printed ones (``--fixture tube``; ``paper``: the
grooved plate for planar shapes and the tube for spatial ones) — and, once settled, read ``--repeats`` times
with fresh interrogator noise. Each frame is reconstructed by the default pipeline and by the paper's, and
compared

* with the rod's own centreline (the algorithm's error): Kabsch registration on arc-length correspondences,
  then point-to-curve distances;
* with the fixture's centreline (what an experimenter measures): the paper's ICP and ±0.5 mm translation
  search. In a tube the catheter cuts corners within the clearance, so this error includes that.

Summary (``--json``: ``summary``): over all shapes and repetitions, default mode, against the rod:
``max_error_mm`` is the largest per-frame max distance, ``mean_error_mm`` the mean of the per-frame mean
distances; ``paper_…`` the same for the paper's pipeline. ``coverage_95`` is the fraction of the rod's points
(s > 0, every frame) inside the default pipeline's 95 % confidence tube, the truth placed in its own pose at
s = 0 and no registration, ``coverage_95_by_quarter`` the same per quarter of the length, and ``mean_sigma_mm``
the tube's mean 1σ lateral radius (:mod:`scenarios._common.coverage`; the model error fitted on the other fold's
shapes, as the calibration is).

Calibration (``--calibration``, :mod:`scenarios._common.calibration`): ``lab`` (default) as a lab makes it — the
two-step calibration in the twin, then [Δθ, g] identified against the fixtures' geometry on shapes *other* than
those reported: with 4 or more shapes, two folds (every other shape of the list), each fold reconstructed with the
parameters identified on the other fold's frames; with fewer, on the paper's identification shapes not reported.
``true`` reconstructs with the twin's true fibre parameters (as-built λ0, intrinsic twist, Δθ, g), leaving
noise, drift, quantisation and the grating length; ``lambda0`` its as-built λ0 only; ``nominal`` the datasheet
only; a path loads a calibration TOML. ``--json`` says which (``calibration``).

``--record DIR`` writes, per shape, the frames (``DIR/SHAPE.h5``, a twin recording) and the ground truth
(``DIR/SHAPE_truth.csv``, arc length and points in m; by default the tube's or groove's centreline, as a mould's
CAD model gives it to a lab; ``--record-truth rod``: the catheter's own centreline, which no lab has): the inputs
of ``twin identify``.
"""

from __future__ import annotations

import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from scenarios._common import coverage, entry
from scenarios._common.calibration import (
    LAB_SHAPES,
    UsedCalibration,
    calibration_field,
    calibration_for,
    check_calibration,
    fixture_observation,
    identify_on_fixtures,
    lab_calibration,
    two_step,
)
from scenarios._common.calibration import label as calibration_label
from scenarios._common.entry import option
from scenarios._common.optics_presets import optics_config, optics_field
from scenarios._common.pipelines import MODES, reconstructors
from scenarios._common.static import fixture_for, measure
from sim_interrogator.optics import OpticsConfig
from sim_interrogator.setups import StaticShape
from sim_interrogator.sim import SimInterrogator
from twin import FiberModel, Reconstructor, shapes
from twin.uncertainty import Uncertainty
from twin.uncertainty import inside as inside_tube

FIXTURES = ("connect", "tube", "paper")
#: The paper's static results after identification (hardware, its pipeline), mm.
PAPER_MAX_MM, PAPER_MEAN_MM = 2.52, 0.70


@dataclass(frozen=True)
class Params:
    """Parameters of the experiment (plain values: picklable, so runs can fan out across processes)."""

    shapes: tuple[str, ...] = field(default=tuple(shapes.names()), metadata=option("library shapes"))
    repeats: int = field(default=5, metadata=option("frames per shape, fresh noise each"))
    fixture: str = field(default="connect", metadata=option(
        "connect constraints (exact), a 3 mm tube, or paper (groove/tube)", choices=FIXTURES))
    optics: str = optics_field()
    calibration: str = calibration_field()
    segments: int = field(default=100, metadata=option("rod segments"))
    seed: int = field(default=0, metadata=option("noise seed"))
    record: str | None = field(default=None, metadata=option(
        "write each shape's frames and truth (twin identify's inputs) to this directory", metavar="DIR"))
    record_truth: str = field(default="fixture", metadata=option(
        "truth written by --record: the catheter's centreline or the fixture's", choices=("rod", "fixture")))


@dataclass(frozen=True)
class ShapeResult:
    """Errors for one shape, m: ``errors[mode][against]`` with mode in MODES and against in ("rod", "fixture"),
    each a dict of per-repetition arrays ``max``, ``mean``, ``tip``."""

    name: str
    planar: bool
    fixture: str
    settle_s: float
    errors: dict = field(repr=False)
    lost_peaks: int = 0


@dataclass(frozen=True)
class Result:
    """``shapes`` per shape; ``calibration`` which calibration was used (per fold for ``lab``); ``curves`` the
    last frame of each shape for overlays: ``s``, per mode the reconstruction registered onto the rod (Kabsch), the
    rod (``truth``, ``truth_s``) and the fixture (``fixture``), all (n_shapes, …, 3) m."""

    params: Params
    shapes: tuple[ShapeResult, ...]
    calibration: dict = field(default_factory=dict)
    curves: dict = field(default_factory=dict, repr=False)
    uncertainty: dict = field(default_factory=dict)

    def summary(self) -> dict:
        out = {k: self.uncertainty[k] for k in ("coverage_95", "coverage_95_by_quarter", "mean_sigma_mm")
               if k in self.uncertainty}
        for mode, prefix in (("default", ""), ("paper", "paper_"), ("paper-literal", "paper_literal_")):
            rod = [r.errors[mode]["rod"] for r in self.shapes]
            out[f"{prefix}max_error_mm"] = float(max(np.max(e["max"]) for e in rod) * 1e3)
            out[f"{prefix}mean_error_mm"] = float(np.mean([np.mean(e["mean"]) for e in rod]) * 1e3)
        return out

    def to_dict(self) -> dict:
        rows = []
        for r in self.shapes:
            row = {"shape": r.name, "planar": r.planar, "fixture": r.fixture, "settle_s": r.settle_s,
                   "lost_peaks": r.lost_peaks}
            for mode in MODES:
                row[mode] = {
                    against: {f"{k}_error_mm": float(np.mean(v) * 1e3) for k, v in stats.items()}
                    | {"max_over_repeats_mm": float(np.max(stats["max"]) * 1e3)}
                    for against, stats in r.errors[mode].items()
                }
            rows.append(row)
        return {"experiment": "static-shapes", "params": asdict(self.params), "calibration": self.calibration,
                "shapes": rows, "summary": self.summary(), "uncertainty": self.uncertainty}


def record(directory: Path, name: str, sim: SimInterrogator, frames, cal, which: str) -> None:
    """Write one shape's frames (twin HDF5) and its ground truth (CSV with arc lengths) into ``directory``."""
    from twin.calibration.identify import write_truth
    from twin.io.record import Recorder

    directory.mkdir(parents=True, exist_ok=True)
    with Recorder(directory / f"{name}.h5", fiber=sim.fiber, calibration=cal, source_url=sim.url,
                  rate=sim.rate) as rec:
        rec.append(frames)
    truth = frames[0].truth
    if which == "rod":
        write_truth(directory / f"{name}_truth.csv", truth.positions, truth.s)
    else:
        write_truth(directory / f"{name}_truth.csv", truth.fixture,
                    np.linspace(0.0, sim.fiber.sensed_length, len(truth.fixture)))


class _Watched(StaticShape):
    """A static setup that keeps the MuJoCo model and data it builds, so the catheter can be drawn while it
    settles."""

    model_data = None

    def build(self):
        self.model_data = super().build()
        return self.model_data


def settling_drawer(viewer, setup: _Watched, fiber: FiberModel, optics: OpticsConfig, rec: Reconstructor, name: str):
    """A settle-progress callback that draws the catheter as it settles: the rod's curvature at the gratings
    through the optics (noise-free) and ``rec``, beside the rod itself and the fixture; the viewer's rate limiter
    decides how often."""
    from models.rod_state import RodReader
    from sim_interrogator.optics import Optics
    from twin.frames import Truth

    optics = Optics(fiber, optics.replace(noise=0.0, drift=0.0, seed=None))
    reader: list = []

    def draw(t: float, moved: float) -> None:
        if setup.model_data is None:
            return
        model, data = setup.model_data
        if not reader:
            reader.append(RodReader(model, setup.rod_name))
        st = reader[0].read(data)
        s_in = st.s[1:-1]
        k = np.stack([np.interp(fiber.grating_s, s_in, st.darboux[:, 1]),
                      np.interp(fiber.grating_s, s_in, -st.darboux[:, 0])], axis=-1)
        out = optics.wavelengths(k)
        shape = rec(out[0] if isinstance(out, tuple) else out)
        if not np.all(np.isfinite(shape.positions)):
            return
        e0 = int(np.argmin(np.abs(st.edge_s)))
        base = (st.edge_frames[e0], np.array([np.interp(0.0, st.s, st.positions[:, j]) for j in range(3)]))
        viewer.show(shape, Truth(s=st.s, positions=st.positions, fixture=setup.fixture_centreline()),
                    base_pose=base, label=f"{name}: settling, t = {t:.2f} s, still moving {moved * 1e6:.0f} µm")

    return draw


def run_experiment(params: Params, progress=None, viewer=None) -> Result:
    """Run the experiment; ``progress(message)`` is called as shapes settle and are measured; a
    :class:`twin.viewer.Viewer` shows each shape while it settles and then its last reconstruction with its truth
    and fixture."""
    if params.fixture not in FIXTURES:
        raise ValueError(f"fixture must be one of {', '.join(FIXTURES)}; got {params.fixture!r}")
    optics_config(params.optics)  # a clear error for an unknown name
    check_calibration(params.calibration)
    if params.repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {params.repeats}")
    for n in params.shapes:
        shapes.get(n)  # a clear error for an unknown shape
    fiber = FiberModel.paper()
    say = progress or (lambda msg: None)
    settled = []
    for i, name in enumerate(params.shapes):
        kind = fixture_for(name, params.fixture)
        say(f"[{i + 1}/{len(params.shapes)}] {name}: settling in the {kind} …")

        setup = _Watched(name, kind, segments=params.segments)
        cfg = optics_config(params.optics, params.seed + i)
        draw = settling_drawer(viewer, setup, fiber, cfg, Reconstructor(fiber), name) if viewer is not None else None

        def tick(t, moved, name=name, draw=draw):
            if progress:
                say(f"    {name}: t = {t:.2f} s, still moving {moved * 1e6:.1f} µm")
            if draw is not None:
                draw(t, moved)

        sim = SimInterrogator(setup, fiber, cfg, progress=tick if progress or draw else None)
        settle_s = sim.data.time
        settled.append((name, kind, sim, [sim.read() for _ in range(params.repeats)], float(settle_s)))
    used, per_shape = calibrations(params, fiber, settled, say)
    results, curves = [], {}
    for (name, kind, sim, frames, settle_s), cal in zip(settled, per_shape, strict=True):
        if params.record:
            record(Path(params.record), name, sim, frames, cal, params.record_truth)
        recs = reconstructors(fiber, cal)
        lost = int(sum(np.isnan(f.wavelengths).sum() for f in frames))
        results.append(ShapeResult(name, shapes.get(name).planar, kind, settle_s,
                                   measure(sim, frames, recs, curves), lost))
        if viewer is not None:
            viewer.show(recs["default"](frames[-1]), frames[-1].truth, label=name, force=True, reframe=True)
        e = results[-1].errors["default"]["rod"]
        say(f"    {name}: default max {np.max(e['max']) * 1e3:.3f} mm, mean {np.mean(e['mean']) * 1e3:.3f} mm")
    return Result(params, tuple(results), used, curves, tube_coverage(params, fiber, settled, per_shape, say))


def tube_coverage(params: Params, fiber: FiberModel, settled: list, per_shape: list, say) -> dict:
    """The default pipeline's 95 % tube against the rod, per shape and overall. The model error of each fold
    (the shapes sharing a calibration, or every other shape when one calibration serves all) is fitted with the
    fold's own calibration on the other fold's shapes — those it was identified on (against their fixtures'
    geometry; the model error against their rods): the only shapes left, and a tube describes the calibration it
    is used with, whose error another fold's calibration does not share (docs/math.md §8.4); a single fold uses
    the lab's fit (:mod:`scenarios._common.coverage`)."""
    groups: dict[int, list[int]] = {}
    for j, cal in enumerate(per_shape):
        groups.setdefault(id(cal), []).append(j)
    if len(groups) == 1 and len(settled) >= 2:  # one calibration for all: two folds all the same for the model error
        groups = {0: list(range(0, len(settled), 2)), 1: list(range(1, len(settled), 2))}
    inside, outs, truths, rows, models = [], [], [], {}, []
    for idx in groups.values():
        cal = per_shape[idx[0]]
        others = [j for j in range(len(settled)) if j not in idx]
        if others:
            names = ", ".join(settled[j][0] for j in others)
            me = coverage.fit_on_frames(fiber, cal, [settled[j][3] for j in others], f"fitted on the rods of {names}")
        else:
            me = coverage.lab_model_error(fiber, optics_config(params.optics), cal, progress=say)
        models.append({"reported": [settled[j][0] for j in idx], **me.to_dict()})
        unc = Uncertainty(Reconstructor(fiber, cal), model_error=me)
        for j in idx:
            frames = settled[j][3]
            out = unc(frames)
            truth = coverage.truth_of_frames(frames, out.s)
            rows[settled[j][0]] = coverage.summary(out, truth)
            inside.append(inside_tube(out, truth, coverage.LEVEL)[:, out.s > 0].ravel())
            outs.append(out)
            truths.append(truth)
    total = {"coverage_95": float(np.mean(np.concatenate(inside))), **coverage.width(outs, truths),
             "coverage_95_by_quarter": coverage.by_quarter(outs, truths)}
    say(f"    95 % tube: {total['coverage_95']:.1%} of the rod's points inside, mean 1σ "
        f"{total['mean_sigma_mm']:.3f} mm against an RMS lateral error of {total['rms_lateral_error_mm']:.3f} mm "
        f"(width ratio {total['width_ratio']:.2f})")
    return {**total, "model_error": models, "shapes": rows}


def calibrations(params: Params, fiber: FiberModel, settled: list, say) -> tuple[dict, list]:
    """What each shape is reconstructed with, and the description for ``--json`` (module docstring)."""
    names = [entry[0] for entry in settled]
    cfg = optics_config(params.optics, params.seed)
    if params.calibration != "lab":
        used = calibration_for(params.calibration, settled[0][2].optics, fiber, progress=say)
        return used.to_dict(), [used.calibration] * len(settled)
    if len(settled) < 4:
        others = tuple(n for n in LAB_SHAPES if n not in names)
        cal = lab_calibration(fiber, cfg, names=others, progress=say)
        used = UsedCalibration("lab", cal, "as a lab makes it: two-step calibration in the twin, then [Δθ, g] "
                               f"identified against the fixtures' geometry on {', '.join(others)}")
        return used.to_dict(), [cal] * len(settled)
    say("calibration: lab — two-step calibration in the twin, then identification on two folds of the shapes …")
    base = two_step(fiber, cfg)
    folds = [list(range(0, len(settled), 2)), list(range(1, len(settled), 2))]
    per_shape: list = [None] * len(settled)
    described = []
    for k, fold in enumerate(folds):
        other = folds[1 - k]
        cal = identify_on_fixtures(fiber, base, [fixture_observation(settled[j][3], fiber, names[j]) for j in other])
        for j in fold:
            per_shape[j] = cal
        described.append({"reported": [names[j] for j in fold], "identified_on": [names[j] for j in other],
                          "delta_theta": cal.delta_theta, "g_um": cal.gain * 1e6})
        say(f"    fold {k + 1}: identified on {', '.join(names[j] for j in other)}: Δθ = {cal.delta_theta:.4f} rad, "
            f"g = {cal.gain * 1e6:.3f} µm")
    return {"name": "lab", "description": "as a lab makes it: two-step calibration in the twin, then [Δθ, g] "
            "identified against the fixtures' geometry, in two folds: each shape reconstructed with the parameters "
            "identified on the other fold's shapes", "folds": described}, per_shape


# ------------------------------------------------------------------------------------------------ command line
def add_arguments(parser) -> None:
    entry.add_arguments(parser, Params)


def params_from_args(args) -> Params:
    params = entry.params_from_args(Params, args)
    if params.shapes == ("all",):
        params = Params(**{**asdict(params), "shapes": tuple(shapes.names())})
    for n in params.shapes:
        shapes.get(n)  # a clear error for an unknown shape
    check_calibration(params.calibration)
    return params


def run(args) -> int:
    return entry.run("static-shapes", sys.modules[__name__], args)


def write_report(result: Result, directory) -> Path:
    """``directory``/report.md: the shapes overlaid with their truth and fixture, the error along the arc length,
    max and mean error per shape with the paper's figures, and the table; returns the report's path."""
    from scenarios.report import Report, error_along_arc, per_shape_errors, shape_overlays

    p, s = result.params, result.summary()
    cal = calibration_label(result.calibration)
    rep = Report(directory, "Static shapes in the twin",
                 calibration_label(result.calibration))
    rep.text(f"{len(result.shapes)} shapes, {p.repeats} frames each; fixture {p.fixture}, optics {p.optics}. "
             "Against the rod: Kabsch on arc length, then point-to-curve distances; against the fixture: the "
             f"paper's ICP and ±0.5 mm translation search. The paper (hardware, after identification, its pipeline): "
             f"max {PAPER_MAX_MM} mm, mean {PAPER_MEAN_MM} mm.")
    rep.text(f"Calibration: {result.calibration.get('name')} — {result.calibration.get('description', '')}.")
    rows = []
    for r in result.shapes:
        e = r.errors
        rows.append([r.name, r.fixture, *(float(np.max(e[m]["rod"]["max"]) * 1e3) for m in MODES),
                     float(np.mean(e["default"]["rod"]["mean"]) * 1e3),
                     float(np.max(e["default"]["fixture"]["max"]) * 1e3),
                     float(np.max(e["paper"]["fixture"]["max"]) * 1e3), r.lost_peaks])
    rep.table(["shape", "fixture", "default max mm", "paper (guarded) max mm", "paper literal max mm",
               "default mean mm", "default vs fixture max mm", "paper vs fixture max mm", "lost peaks"], rows)
    rep.text(f"All shapes, against the rod: default max {s['max_error_mm']:.3f} mm, mean {s['mean_error_mm']:.3f} mm; "
             f"paper's pipeline max {s['paper_max_error_mm']:.3f} mm, mean {s['paper_mean_error_mm']:.3f} mm; "
             f"literal max {s['paper_literal_max_error_mm']:.3f} mm, mean {s['paper_literal_mean_error_mm']:.3f} mm.")
    c = result.curves
    names = [r.name for r in result.shapes]
    if c:
        panels = [{"name": f"{r.name} ({r.fixture})", "truth": c["truth"][i], "fixture": c["fixture"][i],
                   "recon": {m: c[m][i] for m in ("default", "paper")},
                   "note": f"max {np.nanmax(c['default_along'][i]) * 1e3:.2f} mm (default), "
                           f"{np.nanmax(c['paper_along'][i]) * 1e3:.2f} mm (paper's)"} for i, r in
                  enumerate(result.shapes)]
        rep.figure("shape_overlays", shape_overlays(panels, "Reconstructions over the catheter and the fixture "
                                                    "(registered onto the catheter; mm)", cal),
                   "Each shape's last frame: the reconstruction (registered onto the catheter by Kabsch on arc "
                   "length), the catheter's centreline and the fixture's, in the plane of the shape's largest spread")
        for m in ("default", "paper"):
            fig = error_along_arc(c["s"], {n: c[f"{m}_along"][i] * 1e3 for i, n in enumerate(names)},
                                  f"Error along the arc length, {m} pipeline, against the catheter", cal,
                                  paper_max_mm=PAPER_MAX_MM)
            rep.figure(f"error_along_arc_{m}", fig, f"distance of each point of the {m} pipeline's reconstruction "
                       "(last frame, registered) from the catheter's centreline")
    for against, suffix, title, caption in (
        ("rod", "", "against the catheter (over the repetitions)",
         "max (left) and mean (right) error per shape, each pipeline; dashed: the paper's figures on hardware"),
        ("fixture", "_fixture", "against the fixture (the paper's metric)",
         "the same against the fixture's centreline (ICP + translation search, as the paper measured): includes "
         "the catheter's play in the tube or groove"),
    ):
        fig = per_shape_errors(
            names, {m: [float(np.max(r.errors[m][against]["max"]) * 1e3) for r in result.shapes] for m in MODES},
            {m: [float(np.mean(r.errors[m][against]["mean"]) * 1e3) for r in result.shapes] for m in MODES},
            f"Max and mean error per shape {title}", cal, paper_max_mm=PAPER_MAX_MM, paper_mean_mm=PAPER_MEAN_MM)
        rep.figure(f"errors_per_shape{suffix}", fig, caption)
    rep.text("```\n" + text_report(result) + "\n```")
    return rep.write()


def text_report(result: Result) -> str:
    p = result.params
    lines = [
        f"static shapes: fixture {p.fixture}, optics {p.optics}, calibration {p.calibration}, {p.repeats} "
        "repetitions",
        "errors in mm; rod = against the catheter's own centreline (Kabsch), fixture = against the fixture's "
        "centreline (ICP + translation)",
        "",
        f"{'shape':16s}{'fixture':9s}{'default rod max':>16s}{'mean':>7s}{'tip':>7s}{'fixture max':>12s}"
        f"{'paper rod max':>15s}{'mean':>7s}{'fixture max':>12s}",
    ]
    for r in result.shapes:
        d, pp = r.errors["default"], r.errors["paper"]
        lines.append(
            f"{r.name:16s}{r.fixture:9s}{np.max(d['rod']['max']) * 1e3:16.3f}{np.mean(d['rod']['mean']) * 1e3:7.3f}"
            f"{np.mean(d['rod']['tip']) * 1e3:7.3f}{np.max(d['fixture']['max']) * 1e3:12.3f}"
            f"{np.max(pp['rod']['max']) * 1e3:15.3f}{np.mean(pp['rod']['mean']) * 1e3:7.3f}"
            f"{np.max(pp['fixture']['max']) * 1e3:12.3f}"
        )
    s = result.summary()
    lines += ["", f"all shapes, against the rod: default max {s['max_error_mm']:.3f} mm, mean "
                  f"{s['mean_error_mm']:.3f} mm; paper max {s['paper_max_error_mm']:.3f} mm, mean "
                  f"{s['paper_mean_error_mm']:.3f} mm; paper literal max {s['paper_literal_max_error_mm']:.3f} mm, "
                  f"mean {s['paper_literal_mean_error_mm']:.3f} mm",
              f"calibration: {result.calibration.get('name')} — {result.calibration.get('description', '')}"]
    return "\n".join(lines)


if __name__ == "__main__":
    entry.main(sys.modules[__name__])
