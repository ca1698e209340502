"""The README's results tables, rendered from the scenarios' own ``--json`` output (one command regenerates them).

    python -m scenarios.results_tables --rerun --write README.md     # `make results`: rerun every run, rewrite
    python -m scenarios.results_tables --check README.md             # do the README's tables match docs/results/?
    python -m scenarios.results_tables --rerun --only library        # rerun some runs, into docs/results/

Each run of :data:`RUNS` is one ``twin run …`` command whose JSON is kept in ``docs/results/NAME.json`` (the
published figures' source; a rerun overwrites it). Each table of :data:`TABLES` is rendered from those files
and stands in README.md between ``<!-- results: NAME -->`` and ``<!-- /results -->``; ``--write`` replaces
those blocks, ``--check`` reports the ones that differ (tests/test_readme.py runs it). Scenario runs are long
(minutes of physics each), so a rerun is deliberate: ``make results`` does all of them once.

What each figure means is said beside its table in the README (and max / mean / tip in docs/figures.md); this
module only picks the figures out of the JSON and formats them (3 significant digits, mm).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: where the runs' JSON is kept
RESULTS = ROOT / "docs" / "results"

#: run name → the `twin run` arguments (the README cites these commands)
RUNS: dict[str, list[str]] = {
    "static-shapes": ["static-shapes", "--fixture", "paper"],
    "paper-ablation": ["paper-ablation"],
    "rotation": ["rotation"],
    "repeatability": ["repeatability"],
    "temperature-bath": ["temperature-bath"],
    "tendon": ["tendon"],
    "sheath-motion": ["sheath-motion"],
    "spun-50": ["spun-twist"],
    "spun-100": ["spun-twist", "--spin", "100", "--noise", "0.1"],
    "spun-170": ["spun-twist", "--spin", "170", "--noise", "0.1"],
    "spun-100-drift": ["spun-twist", "--spin", "100", "--noise", "0.1", "--drift", "0.02"],
}

#: study name → the `twin study` arguments; its task results are kept as ``docs/results/NAME.json``
STUDIES: dict[str, list[str]] = {
    "integration-light": ["integration-light", "--seeds", "3", "--workers", "2"],
}


def rerun(names: list[str] | None = None, out: Path = RESULTS, say: Callable[[str], None] = print) -> None:
    """Run each of ``names`` (default: all of :data:`RUNS` and :data:`STUDIES`) into ``out/NAME.json``."""
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "MPLBACKEND": "Agg"}
    for name in names or [*RUNS, *STUDIES]:
        if name in STUDIES:
            with tempfile.TemporaryDirectory() as tmp:  # a fresh study: nothing reused from an earlier run
                argv = ["study", *STUDIES[name], "--out", tmp, "--json"]
                say(f"results: twin study {' '.join(STUDIES[name])} …")
                summary = json.loads(_twin(argv, env))
                (out / f"{name}.json").write_text(json.dumps(study_results(Path(tmp), summary, name), indent=1))
            continue
        say(f"results: twin run {' '.join(RUNS[name])} …")
        text = _twin(["run", *RUNS[name], "--json"], env)
        json.loads(text)  # one JSON object, or fail here rather than in the tables
        (out / f"{name}.json").write_text(text)


def _twin(argv: list[str], env: dict) -> str:
    done = subprocess.run([sys.executable, "-m", "twin.cli", *argv], capture_output=True, text=True, env=env)
    if done.returncode != 0:
        raise RuntimeError(f"twin {' '.join(argv)}: exit {done.returncode}: {done.stderr[-2000:]}")
    return done.stdout


def study_results(out: Path, summary: dict, name: str) -> dict:
    """What the tables need of a finished study in ``out``: its design points in the study's order, its task
    results (flat numbers and labels, by label and seed), counts and wall time."""
    from scenarios.studies.definitions import get

    order = list(dict.fromkeys(t["label"] for t in get(name).tasks))
    rows = []
    for path in sorted((out / "tasks").glob("*.json")):
        task = json.loads(path.read_text())
        if task.get("status") == "ok":
            rows.append({k: v for k, v in task["result"].items() if isinstance(v, int | float | str | bool)})
    rows.sort(key=lambda r: (str(r.get("label")), r.get("seed", 0)))
    return {"command": "twin study " + " ".join(STUDIES[name]), "order": order,
            "tasks": summary["tasks"], "failed": len(summary["failed"]), "wall_s": summary["wall_s"], "rows": rows}


def load(where: Path = RESULTS) -> dict[str, dict]:
    """Every run's JSON in ``where``, by run name."""
    names = [*RUNS, *STUDIES]
    missing = [n for n in names if not (where / f"{n}.json").exists()]
    if missing:
        raise FileNotFoundError(f"{where}: no results of {', '.join(missing)} (python -m scenarios.results_tables "
                                f"--rerun --only {' '.join(missing)})")
    return {n: json.loads((where / f"{n}.json").read_text()) for n in names}


def f(x: float) -> str:
    """One of our figures in mm (or degrees) as the README prints it: 3 significant digits, trailing zeros kept."""
    return f"{x:#.3g}".rstrip(".")


def hw(x: float) -> str:
    """A figure of the paper's (hardware), as the paper gives it."""
    return f"{x:g}"


def pair(a: float, b: float, fmt: Callable[[float], str] = f) -> str:
    return f"{fmt(a)} / {fmt(b)}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- the tables
def static_shapes(r: dict[str, dict]) -> str:
    """Ours and the paper's pipeline against both truths of the same run; the paper's hardware beside the one it
    used (its fixtures)."""
    d = r["static-shapes"]
    shapes = d["shapes"]

    def cell(mode: str, truth: str) -> str:
        worst = max(s[mode][truth]["max_over_repeats_mm"] for s in shapes)
        mean = sum(s[mode][truth]["mean_error_mm"] for s in shapes) / len(shapes)
        return pair(worst, mean)

    paper = "2.52 / 0.7"  # Al-Ahmad et al., static shapes on hardware, against their fixtures
    rows = [
        ["the fixtures' centrelines (grooves' and tubes' CAD), the paper's metric (ICP + ±0.5 mm translation)",
         paper, cell("paper", "fixture"), cell("paper-literal", "fixture"), f"**{cell('default', 'fixture')}**"],
        ["the catheter's own centreline (the twin only), Kabsch on arc length", "–", cell("paper", "rod"),
         cell("paper-literal", "rod"), cell("default", "rod")],
    ]
    return _table(["truth (max / mean error, mm)", "the paper (hardware)", "paper's pipeline", "paper's, literal",
                   "ours"], rows)


def paper_ablation(r: dict[str, dict]) -> str:
    d = r["paper-ablation"]
    by = {(row["row"], row["mode"]): row for row in d["rows"]}
    labels = {"1": "(1) nominal, no twist compensation", "2": "(2) nominal, twist-compensated",
              "3": "(3) identified, compensated"}
    rows = []
    for k, label in labels.items():
        paper = d["paper"]["rows"][k]

        def v(mode: str, truth: str, k=k) -> str:
            e = by[(k, mode)][f"validation_{truth}"]
            return pair(e["max_error_mm"], e["mean_error_mm"])

        ours_fixture, ours_rod = v("default", "fixture"), v("default", "rod")
        if k == "3":
            ours_fixture, ours_rod = f"**{ours_fixture}**", f"**{ours_rod}**"
        rows.append([label, pair(paper["max_error_mm"], paper["mean_error_mm"], hw), v("paper", "fixture"),
                     ours_fixture, v("paper", "rod"), v("paper-literal", "rod"), ours_rod])
    return _table(["calibration", "the paper (hardware), its fixtures", "paper's pipeline, fixtures",
                   "ours, fixtures", "paper's pipeline, catheter", "paper's, literal, catheter", "ours, catheter"],
                  rows)


def dynamic(r: dict[str, dict]) -> str:
    rot, rep = r["rotation"]["summary"], r["repeatability"]["summary"]
    bath, ten, sh = r["temperature-bath"]["summary"], r["tendon"]["summary"], r["sheath-motion"]["summary"]
    rows = [
        ["rotation in a pre-bent sheath: tip deviation after one translation onto the EM readings, largest of the "
         f"{len(r['rotation']['per_angle'])} dwell means (0° to 360°)", f"≤ {hw(rot['paper_max_deviation_mm'])}",
         f(rot["paper_pipeline_max_deviation_mm"]), f(rot["paper_literal_max_deviation_mm"]),
         f(rot["max_deviation_mm"]), "`twin run rotation`"],
        ["rotation, scored the paper's way: whole-curve registration onto the 0° shape (its Fig. 6b), largest of "
         "the dwell means", f"≤ {hw(rot['paper_max_deviation_mm'])}",
         f(rot["paper_pipeline_registered_max_deviation_mm"]),
         f(rot["paper_literal_registered_max_deviation_mm"]), f(rot["registered_max_deviation_mm"]),
         "`twin run rotation`"],
        ["rotation, single frames: tip error against the true tip after the same one translation, worst while "
         "turning / while dwelling", "–", "–", "–",
         pair(rot["max_error_while_turning_mm"], rot["max_error_while_dwelling_mm"]),
         "`twin run rotation`"],
        [f"repeatability, {rep['cycles']} cycles in and out of a sheath: spread of the sensed tip, RMS distance "
         "from the mean tip / largest distance (hardware: sensing and mechanics; twin: sensing and the simulated "
         f"catheter's mechanics, its true tip returns within {f(rep['true_max_mm'])} mm)",
         pair(rep["paper_std_mm"], rep["paper_max_mm"], hw),
         pair(rep["paper_pipeline_std_mm"], rep["paper_pipeline_max_mm"]),
         pair(rep["paper_literal_std_mm"], rep["paper_literal_max_mm"]), pair(rep["std_mm"], rep["max_mm"]),
         "`twin run repeatability`"],
        ["temperature bath 60 → 30 °C: tip variation, the largest distance of the (window-averaged) tip from its "
         f"mean (range, largest distance between two tips: ours {f(bath['tip_range_mm'])}); one simulated fibre",
         f"≤ {hw(bath['paper_tip_variation_mm'])}", f(bath["paper_pipeline_tip_variation_mm"]),
         f(bath["paper_literal_tip_variation_mm"]), f(bath["tip_variation_mm"]), "`twin run temperature-bath`"],
        ["tendon steering, max tip deviation from an EM sensor (σ 0.3 mm)", hw(ten["paper_max_deviation_mm"]),
         f(ten["paper_pipeline_max_deviation_mm"]), f(ten["paper_literal_max_deviation_mm"]),
         f(ten["max_deviation_mm"]), "`twin run tendon`"],
        [f"510 mm sheath: mean of the frames' max error / worst frame, {sh['analysed_frames']} frames sampled at "
         "2 Hz (the paper's analysis)", pair(sh["paper_mean_max_error_mm"], sh["paper_worst_error_mm"], hw),
         pair(sh["paper_pipeline_mean_max_error_mm"], sh["paper_pipeline_max_error_mm"]),
         pair(sh["paper_literal_mean_max_error_mm"], sh["paper_literal_max_error_mm"]),
         pair(sh["mean_max_error_mm"], sh["max_error_mm"]), "`twin run sheath-motion`"],
        [f"510 mm sheath, the same over all {sh['frames']} frames (40 Hz)", "–",
         pair(sh["paper_pipeline_mean_max_error_40hz_mm"], sh["paper_pipeline_max_error_40hz_mm"]),
         pair(sh["paper_literal_mean_max_error_40hz_mm"], sh["paper_literal_max_error_40hz_mm"]),
         pair(sh["mean_max_error_40hz_mm"], sh["max_error_40hz_mm"]), "`twin run sheath-motion`"],
        [f"510 mm sheath, mean max error of the 2 Hz frames with lost peaks / without ({sh['lost_peaks']} peaks "
         f"lost in {sh['frames_with_lost_peaks']} of {sh['frames']} frames)", "–",
         pair(sh["paper_pipeline_lost_mean_max_error_mm"], sh["paper_pipeline_intact_mean_max_error_mm"]),
         pair(sh["paper_literal_lost_mean_max_error_mm"], sh["paper_literal_intact_mean_max_error_mm"]),
         pair(sh["lost_mean_max_error_mm"], sh["intact_mean_max_error_mm"]), "`twin run sheath-motion`"],
    ]
    return _table(["experiment (mm)", "the paper (hardware)", "paper's pipeline", "paper's, literal", "ours",
                   "command"], rows)


def spun(r: dict[str, dict]) -> str:
    """Every row from one run at its own interrogator noise; the straight cores beside each at the same noise."""

    def row(label: str, part: dict, which: str, twist: str) -> list[str]:
        g, rot = part["groove"], part["rotation"]
        return [label, f(g["max_error_mm"][which]), f(rot["max_error_mm"][which]),
                f(rot["held_max_error_mm"][which]), twist]

    out = []
    for name, label in (("spun-50", "50 turns/m, 1 pm"), ("spun-100", "100 turns/m, 0.1 pm"),
                        ("spun-170", "170 turns/m, 0.1 pm"),
                        ("spun-100-drift", "100 turns/m, 0.1 pm, drift 0.02 pm/√s")):
        d = r[name]
        noise = f"{d['params']['noise'] * 1e3:g} pm"
        if name in ("spun-50", "spun-100"):  # the straight cores at this noise (the same in every 0.1 pm run)
            out.append(row(f"straight cores (today's fibre), {noise}", d["parts"], "straight", "—"))
        out.append(row(f"spun, {label}", d["parts"], "measured", f"{d['summary']['tip_twist_rms_error_deg']:.2g}°"))
    return _table(["fibre, interrogator", "groove, worst frame", "rotation, worst frame",
                   "rotation, worst dwell mean", "tip twist error (RMS)"], out)


def _spread(values: list[float]) -> str:
    """mean ± standard deviation (over seeds, n − 1), the mean to 3 significant digits, the std to as many
    decimals."""
    n = len(values)
    mean = sum(values) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else 0.0
    decimals = max(0, 2 - math.floor(math.log10(abs(mean)))) if mean else 3
    return f"{mean:.{decimals}f} ± {std:.{decimals}f}"


def integration(r: dict[str, dict]) -> str:
    """One row per design point of the study, in the study's order, mean ± std over its seeds."""
    d = r["integration-light"]
    by: dict[str, list[dict]] = {}
    for row in d["rows"]:
        by.setdefault(row["label"], []).append(row)
    out = []
    for name in d["order"]:
        rows = by.get(name)
        if not rows:
            continue

        def cell(key: str, rows=rows) -> str:
            vals = [float(x[key]) for x in rows if isinstance(x.get(key), int | float)]
            return _spread(vals) if vals else "–"

        label = name + (" (baseline)" if name == "clearance 0.1 mm" else "")
        out.append([label, str(len(rows)), cell("max_error_mm"), cell("static_tip_error_mm"), cell("grating0_dk"),
                    cell("repeat_std_mm"), cell("true_repeat_std_mm"), cell("cycle_slide_max_mm")])
    table = _table(["design point (mm; mean ± sample std over seeds)", "seeds", "static max error",
                    "static tip (base)", "static: curvature added at the first grating (1/m)",
                    "tip spread over cycles, sensed (std)", "the catheter's own tip spread (std)",
                    "fibre's largest slide in the cycles"], out)
    # the clearance's share: least-squares slope of the static max error over the clearance points
    pts = [(float(x["clearance_mm"]), float(x["max_error_mm"])) for label, rows in by.items()
           if label.startswith("clearance ") and "," not in label for x in rows]
    if len({c for c, _ in pts}) < 2:
        return table
    mc, me = (sum(v) / len(pts) for v in zip(*pts, strict=True))
    slope = sum((c - mc) * (e - me) for c, e in pts) / sum((c - mc) ** 2 for c, _ in pts)
    return table + (f"\n\nStatic max error against clearance: {f(slope)} mm per mm (least squares over "
                    f"{min(c for c, _ in pts):g}–{max(c for c, _ in pts):g} mm); {d['tasks']} tasks, "
                    f"{d['failed']} failed.")


#: table name → renderer (results by run name → markdown)
TABLES: dict[str, Callable[[dict[str, dict]], str]] = {
    "static-shapes": static_shapes,
    "paper-ablation": paper_ablation,
    "dynamic": dynamic,
    "spun-twist": spun,
    "integration-light": integration,
}

#: a marked table: the opening marker, the table (empty in a fresh README), the closing marker
_BLOCK = re.compile(r"(<!-- results: ([\w-]+) -->\n)((?:(?!<!-- results)[^\n]*\n)*?)(<!-- /results -->)")


def render(results: dict[str, dict]) -> dict[str, str]:
    return {name: fn(results) for name, fn in TABLES.items()}


def readme_tables(text: str) -> dict[str, str]:
    """The tables README.md holds between its ``results`` markers, by name."""
    return {m.group(2): m.group(3).rstrip("\n") for m in _BLOCK.finditer(text)}


def write(text: str, tables: dict[str, str]) -> str:
    """``text`` with every marked table replaced by ``tables``' (a marker without a table is an error)."""
    unknown = set(readme_tables(text)) - set(tables)
    if unknown:
        raise KeyError(f"README marks unknown tables: {', '.join(sorted(unknown))}")
    return _BLOCK.sub(lambda m: m.group(1) + tables[m.group(2)] + "\n" + m.group(4), text)


def differences(text: str, tables: dict[str, str]) -> list[str]:
    """Names of the tables that are missing from ``text`` or differ from ``tables``."""
    have = readme_tables(text)
    return [name for name in tables if have.get(name) != tables[name]]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m scenarios.results_tables", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rerun", action="store_true", help="rerun the scenarios first (minutes each)")
    parser.add_argument("--only", nargs="+", choices=[*RUNS, *STUDIES], help="rerun only these")
    parser.add_argument("--results", type=Path, default=RESULTS, help=f"the runs' JSON (default {RESULTS})")
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--write", type=Path, metavar="README", help="replace the marked tables in this file")
    what.add_argument("--check", type=Path, metavar="README", help="exit 1 when the file's tables differ")
    args = parser.parse_args(argv)
    if args.rerun or args.only:
        rerun(args.only, args.results)
    tables = render(load(args.results))
    if args.write:
        args.write.write_text(write(args.write.read_text(encoding="utf-8"), tables), encoding="utf-8")
    elif args.check:
        bad = differences(args.check.read_text(encoding="utf-8"), tables)
        if bad:
            print(f"{args.check}: tables differ from {args.results}: {', '.join(bad)}", file=sys.stderr)
            return 1
    else:
        for name, table in tables.items():
            print(f"<!-- results: {name} -->\n{table}\n<!-- /results -->\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
