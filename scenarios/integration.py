"""integration: how the fibre is built into the catheter, as an experiment (Al-Ahmad et al. §III-B, Fig. 2–3;
docs/integration.md).

The reference paper's first contribution is a set of guidelines for integrating the fibre: (a) minimal
clearance between fibre and lumen, preferably with a low-friction lining; (b) one, preferably two fixations at
the fibre's base, the first grating Δx_prox ≥ 15 mm beyond the most distal one; (c) the tip free, Δx_dist
1–2 mm short of the lumen's end (tip contact disrupts the wavelengths); a constant offset of the fibre from the
catheter's axis is allowed. Here the fibre is its own body in the catheter's lumen (:mod:`models.lumen_fiber`) and
each guideline is a design parameter:

* **static shapes** (``sim://fiber-static``: library shapes held exactly by connect constraints): max and mean
  distance of the reconstruction (default pipeline, the twin's true calibration) from the catheter's own
  centreline, Kabsch-registered, over shapes and frames — the catheter is where the shape is, the fibre is what
  reads it;
* **repeatability** (``sim://fiber-sheath-cycle``: in and out of the pre-bent sheath): the spread of the
  reconstructed tip over the returns to the reference (RMS distance from the mean, and the largest);
* peaks lost or disturbed by tip contact, the fibre's largest slide along the lumen, and its tip gap.

Design points: one factor at a time about a baseline (clearance 0.1 mm, μ 0.2, two fixations, Δx_prox 15 mm,
Δx_dist 2 mm, lead tension 0.02 N), plus the glued fibre (the welded reference): clearance 0–0.3 mm, a
low-friction lining, 0/1/2 fixations, Δx_prox 0/5/15/25 mm (also at lead tensions of 0 and 0.1 N), Δx_dist
0 / −0.5 (pressed) / 2 mm. ``--json`` prints one row per design point (``rows``), with the guidelines derived
from them. ``twin study integration`` runs the same points in parallel
on Dask (docs/studies.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass

import numpy as np

from sim_interrogator.fiber_setups import FiberSheathCycle, FiberStatic
from sim_interrogator.optics import OpticsConfig
from sim_interrogator.sim import SimInterrogator
from twin import FiberModel, Reconstructor, metrics, shapes

#: The paper's guidelines (§III-B), quoted for the report.
PAPER = ("(a) minimal clearance, preferably a low-friction lining; (b) one, preferably two base fixations, "
         "Δx_prox ≥ 15 mm; (c) tip free, Δx_dist 1–2 mm from the lumen's end; a constant offset is allowed")

BASELINE = {"clearance": 1e-4, "friction": 0.2, "fixations": 2, "dx_prox": 0.015, "dx_dist": 0.002,
            "offset": 0.0, "glued": False, "lead_tension": 0.02}
#: N, the lead tensions of the Δx_prox sensitivity (the baseline's 0.02 N is an assumption: docs/integration.md)
LEAD_TENSIONS = (0.0, 0.1)
#: relative 1σ of the sheath's friction coefficient between seeds (one catheter, sheath and hand are never quite
#: the same twice)
SHEATH_FRICTION_SPREAD = 0.1
DEFAULT_SHAPES = ("arc", "s-curve", "helix", "two-plane")


@dataclass(frozen=True)
class Params:
    """What every design point shares (plain values: picklable for Dask).

    Attributes
    ----------
    shapes : tuple of str
        Library shapes of the static part (empty: skip it).
    repeats : int
        Frames per static shape.
    cycles : int
        Sheath cycles (0: skip the repeatability part).
    rate : float
        Frames per simulated second in the cycles, Hz.
    window : float
        End of each dwell averaged as one return, s.
    segments : int
        Catheter segments in the static shapes.
    cycle_segments : int
        Catheter segments in the sheath cycles (fewer: the sheath's contacts make each step ≈ 3× dearer).
    seed : int
    """

    shapes: tuple[str, ...] = DEFAULT_SHAPES
    repeats: int = 3
    cycles: int = 3
    rate: float = 20.0
    window: float = 0.2
    segments: int = 100
    cycle_segments: int = 50
    seed: int = 0


def design_points(kind: str = "guidelines") -> list[dict]:
    """The design points: ``guidelines`` (one factor at a time about :data:`BASELINE`, and the glued fibre) or
    ``quick`` (four points, for tests and smoke runs)."""
    def point(label, **change):
        return {"label": label, **BASELINE, **change}

    if kind == "quick":
        return [point("glued", clearance=0.0, glued=True), point("baseline"),
                point("clearance 0.3 mm", clearance=3e-4), point("pressed tip", dx_dist=-5e-4)]
    if kind != "guidelines":
        raise ValueError(f"design points: expected guidelines or quick, got {kind!r}")
    pts = [point("glued", clearance=0.0, glued=True)]
    pts += [point(f"clearance {c * 1e3:g} mm", clearance=c) for c in (0.0, 5e-5, 1e-4, 2e-4, 3e-4)]
    pts += [point("clearance 0.1 mm, lining μ 0.05", friction=0.05)]
    pts += [point(f"{n} fixation(s)", fixations=n) for n in (0, 1)]
    pts += [point(f"dx_prox {d * 1e3:g} mm", dx_prox=d) for d in (0.0, 0.005, 0.025)]
    pts += [point(f"dx_prox {d * 1e3:g} mm, lead {t:g} N", dx_prox=d, lead_tension=t)
            for t in LEAD_TENSIONS for d in (0.0, 0.005, 0.015, 0.025)]
    # a tip cut flush with the lumen's end retracts from it in a bend (the load-free fibre rides the outer wall,
    # the longer path): contact needs a tip pressed into the end
    pts += [point("dx_dist 0 mm", dx_dist=0.0), point("dx_dist -0.5 mm (pressed)", dx_dist=-5e-4)]
    # the baseline itself is "clearance 0.1 mm" (2 fixations, dx_prox 15 mm, dx_dist 2 mm)
    return pts


def _fiber_kw(point: dict) -> dict:
    return {k: point[k] for k in ("clearance", "friction", "dx_prox", "dx_dist", "offset", "glued")} | {
        "fixations": int(point["fixations"]),
        "lead_tension": float(point.get("lead_tension", BASELINE["lead_tension"]))}


def static_part(point: dict, params: Params, fiber: FiberModel) -> dict:
    """Max/mean error over the static shapes (m), lost peaks, tip contacts and the largest slide."""
    maxima, means, tips, dk_base, lost, contact, slide, unsettled = [], [], [], [], 0, 0, 0.0, 0
    for i, name in enumerate(params.shapes):
        setup = FiberStatic(name, "connect", segments=params.segments, seed=params.seed + i, **_fiber_kw(point))
        sim = SimInterrogator(setup, fiber, OpticsConfig(seed=params.seed + i))
        frames = [sim.read() for _ in range(params.repeats)]
        rec = Reconstructor(fiber, sim.optics.true_calibration())
        shape = rec(frames)
        truth = frames[0].truth
        err = metrics.shape_error(shape.positions, truth.positions, s=shape.s, truth_s=truth.s)
        maxima.append(float(np.max(err.max)))
        means.append(float(np.mean(err.mean)))
        # the tip in the base frame at s = 0, unregistered: an angle error at the first gratings (the fibre's
        # transition out of the glue) moves the tip, which the Kabsch registration above absorbs
        true_tip = truth.frames[0].T @ (truth.positions[-1] - truth.positions[0])
        tips.append(float(np.linalg.norm(shape.positions[:, -1] - true_tip, axis=-1).max()))
        # what the fibre's mechanics add to the curvature at the gratings nearest the fixation (0 and 10 mm)
        dk_base.append(setup.curvature_error(fiber.grating_s[:2]))
        lost += int(sum(np.isnan(f.wavelengths).sum() for f in frames))
        contact += setup.contact_frames
        slide = max(slide, float(np.abs(setup.coupler.slide()).max()))
        unsettled += not setup.settled
    return {"max_error": max(maxima), "mean_error": float(np.mean(means)), "per_shape_max": maxima,
            "tip_error": max(tips), "base_dk": np.max(dk_base, axis=0).tolist(), "lost_peaks": lost,
            "contact_frames": contact, "slide_max": slide,
            "unsettled": unsettled}


def cycle_part(point: dict, params: Params, fiber: FiberModel) -> dict:
    """Spread of the reconstructed tip over the returns to the reference (m), peaks lost in the run."""
    mu = 0.2 * max(0.5, 1.0 + SHEATH_FRICTION_SPREAD * np.random.default_rng([params.seed, 2]).standard_normal())
    setup = FiberSheathCycle(cycles=params.cycles, segments=params.cycle_segments, seed=params.seed,
                             sheath_friction=mu, **_fiber_kw(point))
    sim = SimInterrogator(setup, fiber, OpticsConfig(seed=params.seed), rate=params.rate)
    n = round(setup.duration * params.rate) + 1
    frames = [sim.read() for _ in range(n)]
    t = np.arange(n) / params.rate
    rec = Reconstructor(fiber, sim.optics.true_calibration())
    tips = rec(frames).positions[:, -1]
    true_tips = []
    for f in frames:
        tr = f.truth  # the catheter's tip in its base frame at s = 0
        true_tips.append(tr.frames[0].T @ (tr.positions[-1] - tr.positions[0]))
    true_tips = np.array(true_tips)
    per, per_true = [], []
    for ref in setup.reference_times[1:]:
        w = (t > ref - params.window) & (t <= ref + 1e-9)
        per.append(tips[w].mean(axis=0))
        per_true.append(true_tips[w].mean(axis=0))
    per, per_true = np.array(per), np.array(per_true)
    d = np.linalg.norm(per - per.mean(axis=0), axis=1)
    dt = np.linalg.norm(per_true - per_true.mean(axis=0), axis=1)
    return {"repeat_std": float(np.sqrt(np.mean(d**2))), "repeat_max": float(d.max()),
            "true_repeat_std": float(np.sqrt(np.mean(dt**2))),
            "tip_error_max": float(np.linalg.norm(per - per_true, axis=1).max()),
            "lost_peaks": int(sum(np.isnan(f.wavelengths).sum() for f in frames)),
            "contact_frames": setup.contact_frames, "slide_max": float(np.abs(setup.coupler.slide()).max())}


def run_point(point: dict, params: Params | None = None) -> dict:
    """One design point: a flat row, lengths in mm (JSON-ready). What ``twin study integration`` runs per task."""
    params = params or Params()
    fiber = FiberModel.paper()
    t0 = time.perf_counter()
    row = {"label": point.get("label", ""), "clearance_mm": point["clearance"] * 1e3, "friction": point["friction"],
           "fixations": int(point["fixations"]), "dx_prox_mm": point["dx_prox"] * 1e3,
           "dx_dist_mm": point["dx_dist"] * 1e3, "offset_mm": point["offset"] * 1e3, "glued": bool(point["glued"]),
           "lead_tension_n": float(point.get("lead_tension", BASELINE["lead_tension"])), "seed": params.seed}
    if params.shapes:
        s = static_part(point, params, fiber)
        row |= {"max_error_mm": s["max_error"] * 1e3, "mean_error_mm": s["mean_error"] * 1e3,
                "static_tip_error_mm": s["tip_error"] * 1e3, "grating0_dk": s["base_dk"][0],
                "grating1_dk": s["base_dk"][1],
                "static_lost_peaks": s["lost_peaks"], "static_contact_frames": s["contact_frames"],
                "static_slide_max_mm": s["slide_max"] * 1e3, "static_still_sliding": s["unsettled"]}
    if params.cycles:
        c = cycle_part(point, params, fiber)
        row |= {"repeat_std_mm": c["repeat_std"] * 1e3, "repeat_max_mm": c["repeat_max"] * 1e3,
                "true_repeat_std_mm": c["true_repeat_std"] * 1e3, "cycle_tip_error_max_mm": c["tip_error_max"] * 1e3,
                "cycle_lost_peaks": c["lost_peaks"], "cycle_contact_frames": c["contact_frames"],
                "cycle_slide_max_mm": c["slide_max"] * 1e3}
    row["wall_s"] = time.perf_counter() - t0
    return row


def guidelines(rows: list[dict]) -> list[str]:
    """The guidelines the rows support, in words, each with the numbers behind it."""
    by = {r["label"]: r for r in rows}
    out = []

    def val(label, key):
        r = by.get(label)
        return None if r is None or r.get(key) is None else r[key]

    cl = sorted((r["clearance_mm"], r) for r in rows if r["label"].startswith("clearance") and "lining" not in
                r["label"])
    if len(cl) >= 2 and "max_error_mm" in cl[0][1]:
        lo, hi = cl[0][1], cl[-1][1]
        grows = hi["max_error_mm"] > 1.2 * lo["max_error_mm"] or hi["mean_error_mm"] > 1.2 * lo["mean_error_mm"]
        out.append(f"(a) clearance: max error {lo['max_error_mm']:.2f} mm at {cl[0][0]:g} mm → "
                   f"{hi['max_error_mm']:.2f} mm at {cl[-1][0]:g} mm (mean {lo['mean_error_mm']:.3f} → "
                   f"{hi['mean_error_mm']:.3f} mm): " + ("the error grows with the clearance — keep it minimal."
                                                          if grows else "no clear growth over this range."))
    lin, base = val("clearance 0.1 mm, lining μ 0.05", "repeat_std_mm"), val("clearance 0.1 mm", "repeat_std_mm")
    if lin is not None and base is not None:
        out.append(f"(a) lining: repeatability std {base:.3f} mm at μ 0.2 vs {lin:.3f} mm at μ 0.05 "
                   + ("(the lining helps)." if lin < 0.9 * base else "(no clear gain from the lining here)."))
    fx = [(n, val(f"{n} fixation(s)", "repeat_std_mm")) for n in (0, 1)] + [(2, base)]
    slides = [val(f"{n} fixation(s)", "cycle_slide_max_mm") for n in (0, 1)] + [
        val("clearance 0.1 mm", "cycle_slide_max_mm")]
    if all(v is not None for _, v in fx) and all(v is not None for v in slides):
        best = min(fx, key=lambda nv: nv[1])[0]
        out.append("(b) fixations: repeatability std " + ", ".join(f"{v:.3f} mm with {n}" for n, v in fx)
                   + "; largest slide along the lumen " + ", ".join(f"{v:.2f} mm" for v in slides)
                   + f" — best with {best}.")
    for key, what, unit in (("grating0_dk", "curvature added at the first grating", "1/m"),
                            ("max_error_mm", "max error", "mm")):
        dp = [(d, val(f"dx_prox {d:g} mm", key)) for d in (0, 5, 25)]
        dp.insert(2, (15, val("clearance 0.1 mm", key)))
        if all(v is not None for _, v in dp):
            best = min(v for _, v in dp)
            ok = [d for d, v in dp if v <= 1.1 * best]
            out.append(f"(b) Δx_prox: {what} " + ", ".join(f"{v:.2f} {unit} at {d} mm" for d, v in dp)
                       + f" — within 10 % of the best at Δx_prox ∈ {ok} mm.")
            break
    for label, what in (("dx_dist 0 mm", "Δx_dist = 0"), ("dx_dist -0.5 mm (pressed)", "the tip pressed 0.5 mm")):
        c_lost = val(label, "static_lost_peaks")
        if c_lost is None:
            continue
        cf = (val(label, "static_contact_frames") or 0) + (val(label, "cycle_contact_frames") or 0)
        out.append(f"(c) tip: with {what} the tip touched the lumen's end in {cf} frames, flagging the distal "
                   f"grating's peaks ({c_lost} peaks lost in the static shapes, max error "
                   f"{val(label, 'max_error_mm'):.2f} mm) against "
                   f"{(val('clearance 0.1 mm', 'static_contact_frames') or 0)} contact frames at 2 mm.")
    return out


# ------------------------------------------------------------------------------------------------ command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--points", choices=("guidelines", "quick"), default="guidelines",
                        help="design points: one factor at a time about the baseline, or four for a smoke run")
    parser.add_argument("--shapes", default=",".join(DEFAULT_SHAPES),
                        help=f"static shapes, comma-separated, 'all' or 'none' (default {','.join(DEFAULT_SHAPES)})")
    parser.add_argument("--repeats", type=int, default=3, help="frames per static shape (default 3)")
    parser.add_argument("--cycles", type=int, default=3, help="sheath cycles per point, 0 to skip (default 3)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print one JSON object: a row per design point")
    parser.add_argument("--report", metavar="DIR", help="write plots and a markdown summary to DIR")


def params_from_args(args: argparse.Namespace) -> Params:
    if args.shapes == "all":
        names = tuple(shapes.names())
    elif args.shapes == "none":
        names = ()
    else:
        names = tuple(s.strip() for s in args.shapes.split(",") if s.strip())
    for n in names:
        shapes.get(n)
    if args.repeats < 1 or args.cycles < 0:
        raise ValueError("--repeats must be >= 1 and --cycles >= 0")
    if args.cycles == 1:
        raise ValueError("--cycles 1 gives no spread; use 0 to skip or >= 2")
    return Params(shapes=names, repeats=args.repeats, cycles=args.cycles, seed=args.seed)


def run(args: argparse.Namespace) -> int:
    params = params_from_args(args)
    rows = []
    points = design_points(args.points)
    for i, p in enumerate(points):
        print(f"[{i + 1}/{len(points)}] {p['label']} …", file=sys.stderr, flush=True)
        rows.append(run_point(p, params))
    result = {"params": asdict(params), "rows": rows, "guidelines": guidelines(rows), "paper": PAPER}
    if args.report:
        print(f"report: {write_report(result, args.report)}", file=sys.stderr)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(text_report(result))
    return 0


COLUMNS = (("label", "design point", "{}"), ("max_error_mm", "max mm", "{:.3f}"),
           ("mean_error_mm", "mean mm", "{:.3f}"), ("static_tip_error_mm", "tip mm (base)", "{:.3f}"),
           ("grating0_dk", "Δk g0 1/m", "{:.2f}"),
           ("repeat_std_mm", "repeat std mm", "{:.3f}"), ("repeat_max_mm", "repeat max mm", "{:.3f}"),
           ("static_lost_peaks", "lost (static)", "{}"), ("cycle_slide_max_mm", "slide mm", "{:.2f}"))


def _cell(row, key, fmt):
    v = row.get(key)
    return "–" if v is None else fmt.format(v)


def text_report(result: dict) -> str:
    lines = ["fibre integration: errors against the catheter's centreline (static shapes), tip spread over sheath "
             "cycles", ""]
    lines.append("".join(f"{h:>16s}" if i else f"{h:36s}" for i, (_, h, _) in enumerate(COLUMNS)))
    for r in result["rows"]:
        lines.append("".join(f"{_cell(r, k, f):>16s}" if i else f"{_cell(r, k, f):36s}"
                             for i, (k, _, f) in enumerate(COLUMNS)))
    lines += ["", "guidelines from the twin:"] + [f"  {g}" for g in result["guidelines"]]
    lines += ["", f"the paper's: {result['paper']}"]
    return "\n".join(lines)


def write_report(result: dict, directory) -> object:
    """Markdown table, guidelines beside the paper's, and plots of error against each factor."""
    from scenarios.report import Report, pyplot

    rows = result["rows"]
    rep = Report(directory, "Fibre integration in the twin")
    rep.text("Each design point changes one factor from the baseline (clearance 0.1 mm, μ 0.2, two fixations, "
             "Δx_prox 15 mm, Δx_dist 2 mm). Static error: reconstruction against the catheter's centreline (Kabsch); "
             "repeatability: spread of the reconstructed tip over returns to the reference in the pre-bent sheath.")
    rep.table([h for _, h, _ in COLUMNS], [[_cell(r, k, f) for k, _, f in COLUMNS] for r in rows])
    rep.text("**Guidelines from the twin**\n\n" + "\n".join(f"- {g}" for g in result["guidelines"]))
    rep.text(f"**The paper's** (§III-B): {result['paper']}.")
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    groups = (("clearance", "clearance_mm", "clearance (mm)"),
              ("dx_prox", "dx_prox_mm", "Δx_prox (mm)"), ("fixation", "fixations", "base fixations"))
    for ax, (prefix, key, xlabel) in zip(axes, groups, strict=True):
        sel = [r for r in rows if (r["label"].startswith(prefix) and "lining" not in r["label"])
               or r["label"] == "clearance 0.1 mm"]
        sel = sorted({r["label"]: r for r in sel}.values(), key=lambda r: r[key])
        x = [r[key] for r in sel]
        if sel and "max_error_mm" in sel[0]:
            ax.plot(x, [r["max_error_mm"] for r in sel], "o-", label="max error")
            ax.plot(x, [r["mean_error_mm"] for r in sel], "s-", label="mean error")
        if sel and "repeat_std_mm" in sel[0]:
            ax.plot(x, [r["repeat_std_mm"] for r in sel], "^-", label="repeatability std")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("mm")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    rep.figure("factors", fig, "errors against clearance, Δx_prox and the number of base fixations")
    return rep.write()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="integration", description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
