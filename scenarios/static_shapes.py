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
distances; ``paper_…`` the same for the paper's pipeline.

Calibration (``--calibration``): ``true`` reconstructs with the twin's true fibre parameters (as-built λ0,
intrinsic twist, Δθ, g), leaving noise, drift, quantisation and the grating length; ``lambda0`` its as-built λ0
only; ``nominal`` the datasheet only; a path loads a calibration TOML.

``--record DIR`` writes, per shape, the frames (``DIR/SHAPE.h5``, a twin recording) and the ground truth
(``DIR/SHAPE_truth.csv``, arc length and points in m; ``--record-truth rod``: the catheter's own centreline,
as a CT would give it; ``fixture``: the tube's or groove's centreline, as a mould's CAD model would): the
inputs of ``twin identify``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from scenarios.series import CALIBRATIONS, calibration_for
from sim_interrogator.optics import OpticsConfig
from sim_interrogator.setups import StaticShape
from sim_interrogator.sim import SimInterrogator
from twin import FiberModel, Reconstructor, jsonout, metrics, shapes

FIXTURES = ("connect", "tube", "paper")
MODES = ("default", "paper")


@dataclass(frozen=True)
class Params:
    """Parameters of the experiment (plain values: picklable, so runs can fan out across processes)."""

    shapes: tuple[str, ...] = tuple(shapes.names())
    repeats: int = 5
    fixture: str = "connect"
    optics: str = "realistic"
    calibration: str = "true"
    segments: int = 100
    seed: int = 0
    record: str | None = None
    record_truth: str = "rod"


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
    params: Params
    shapes: tuple[ShapeResult, ...]

    def summary(self) -> dict:
        out = {}
        for mode, prefix in (("default", ""), ("paper", "paper_")):
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
        return {"params": asdict(self.params), "shapes": rows, "summary": self.summary()}


def fixture_for(name: str, fixture: str) -> str:
    if fixture == "paper":
        return "groove" if shapes.get(name).planar else "tube"
    return fixture


def _stats(err: metrics.ErrorStats) -> dict:
    return {"max": np.atleast_1d(err.max), "mean": np.atleast_1d(err.mean), "tip": np.atleast_1d(err.tip)}


def measure(sim: SimInterrogator, frames, recs: dict[str, Reconstructor]) -> dict:
    """Errors of each reconstructor on ``frames`` (all of one settled shape) against the rod and the fixture."""
    truth = frames[0].truth
    fixture_s = np.linspace(0.0, sim.fiber.sensed_length, len(truth.fixture))
    out = {}
    for mode, rec in recs.items():
        shape = rec(frames)
        rod = metrics.shape_error(shape.positions, truth.positions, s=shape.s, truth_s=truth.s)
        fix = metrics.shape_error(shape.positions, truth.fixture, s=shape.s, truth_s=fixture_s,
                                  register="icp+translation")
        out[mode] = {"rod": _stats(rod), "fixture": _stats(fix)}
    return out


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


def run_experiment(params: Params, progress=None, viewer=None) -> Result:
    """Run the experiment; ``progress(message)`` is called as shapes settle and are measured; a
    :class:`twin.viewer.Viewer` shows each shape's last reconstruction with its truth and fixture."""
    if params.fixture not in FIXTURES:
        raise ValueError(f"fixture must be one of {', '.join(FIXTURES)}; got {params.fixture!r}")
    if params.optics not in ("realistic", "ideal"):
        raise ValueError(f"optics must be realistic or ideal; got {params.optics!r}")
    if params.repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {params.repeats}")
    fiber = FiberModel.paper()
    results = []
    say = progress or (lambda msg: None)
    for i, name in enumerate(params.shapes):
        kind = fixture_for(name, params.fixture)
        cfg = OpticsConfig(seed=params.seed + i) if params.optics == "realistic" else OpticsConfig.ideal()
        say(f"[{i + 1}/{len(params.shapes)}] {name}: settling in the {kind} …")

        def tick(t, moved, name=name):
            say(f"    {name}: t = {t:.2f} s, still moving {moved * 1e6:.1f} µm")

        setup = StaticShape(name, kind, segments=params.segments)
        sim = SimInterrogator(setup, fiber, cfg, progress=tick if progress else None)
        settle_s = sim.data.time
        frames = [sim.read() for _ in range(params.repeats)]
        cal = calibration_for(params.calibration, sim)
        if params.record:
            record(Path(params.record), name, sim, frames, cal, params.record_truth)
        recs = {"default": Reconstructor(fiber, cal), "paper": Reconstructor.paper(fiber, cal)}
        lost = int(sum(np.isnan(f.wavelengths).sum() for f in frames))
        results.append(ShapeResult(name, shapes.get(name).planar, kind, float(settle_s),
                                   measure(sim, frames, recs), lost))
        if viewer is not None:
            viewer.show(recs["default"](frames[-1]), frames[-1].truth, label=name, force=True, reframe=True)
        e = results[-1].errors["default"]["rod"]
        say(f"    {name}: default max {np.max(e['max']) * 1e3:.3f} mm, mean {np.mean(e['mean']) * 1e3:.3f} mm")
    return Result(params, tuple(results))


# ------------------------------------------------------------------------------------------------ command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--shapes", default="all", help="comma-separated shape names (default: all 12)")
    parser.add_argument("--repeats", type=int, default=5, help="frames per shape, fresh noise each (default 5)")
    parser.add_argument("--fixture", choices=FIXTURES, default="connect",
                        help="connect constraints (exact), a 3 mm tube, or paper (groove/tube) (default connect)")
    parser.add_argument("--optics", choices=("realistic", "ideal"), default="realistic")
    parser.add_argument("--calibration", default="true",
                        help="true (the twin's true parameters), lambda0, nominal or a calibration TOML (default true)")
    parser.add_argument("--segments", type=int, default=100, help="rod segments (default 100)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--record", metavar="DIR", help="write each shape's frames and truth (twin identify's inputs)")
    parser.add_argument("--record-truth", choices=("rod", "fixture"), default="rod",
                        help="truth written by --record: the catheter's centreline or the fixture's (default rod)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--report", metavar="DIR", help="write PNG plots and a markdown summary to DIR")


def params_from_args(args: argparse.Namespace) -> Params:
    names = tuple(shapes.names()) if args.shapes == "all" else tuple(s.strip() for s in args.shapes.split(","))
    for n in names:
        shapes.get(n)  # a clear error for an unknown shape
    if args.calibration not in CALIBRATIONS and not Path(args.calibration).exists():
        raise ValueError(f"--calibration {args.calibration}: no such file (or one of {', '.join(CALIBRATIONS)})")
    return Params(names, args.repeats, args.fixture, args.optics, args.calibration, args.segments, args.seed,
                  args.record, args.record_truth)


def run(args: argparse.Namespace) -> int:
    params = params_from_args(args)
    result = run_experiment(params, progress=lambda msg: print(msg, file=sys.stderr, flush=True),
                            viewer=getattr(args, "viewer", None))
    if args.report:
        print(f"report: {write_report(result, args.report)}", file=sys.stderr)
    if args.json:
        print(jsonout.dumps(result.to_dict(), indent=2))
        return 0
    print(report(result))
    return 0


def write_report(result: Result, directory) -> Path:
    """A bar chart of the per-shape errors (both pipelines, against the rod and the fixture) and a markdown
    summary in ``directory``; returns the report's path."""
    from scenarios.report import Report, pyplot

    p, s = result.params, result.summary()
    rep = Report(directory, "Static shapes in the twin")
    rep.text(f"{len(result.shapes)} shapes, {p.repeats} frames each; fixture {p.fixture}, optics {p.optics}, "
             f"calibration {p.calibration}. Against the rod: Kabsch on arc length, then point-to-curve distances; "
             "against the fixture: the paper's ICP and ±0.5 mm translation search. The paper (hardware, after "
             "identification): max 2.52 mm, mean 0.70 mm.")
    rows = []
    for r in result.shapes:
        d, pp = r.errors["default"], r.errors["paper"]
        rows.append([r.name, r.fixture, float(np.max(d["rod"]["max"]) * 1e3), float(np.mean(d["rod"]["mean"]) * 1e3),
                     float(np.max(d["fixture"]["max"]) * 1e3), float(np.max(pp["rod"]["max"]) * 1e3), r.lost_peaks])
    rep.table(["shape", "fixture", "default max mm", "default mean mm", "default vs fixture max mm",
               "paper max mm", "lost peaks"], rows)
    rep.text(f"All shapes, against the rod: default max {s['max_error_mm']:.3f} mm, mean {s['mean_error_mm']:.3f} mm; "
             f"paper's pipeline max {s['paper_max_error_mm']:.3f} mm, mean {s['paper_mean_error_mm']:.3f} mm.")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 3.5))
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r[2] for r in rows], 0.4, label="default pipeline")
    ax.bar(x + 0.2, [r[5] for r in rows], 0.4, label="paper's pipeline")
    ax.set_xticks(x, [r[0] for r in rows], rotation=45, ha="right")
    ax.set_ylabel("max error against the rod (mm)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8)
    rep.figure("errors_per_shape", fig, "max error per shape (log scale), both pipelines")
    return rep.write()


def report(result: Result) -> str:
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
                  f"{s['paper_mean_error_mm']:.3f} mm"]
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="static_shapes", description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
