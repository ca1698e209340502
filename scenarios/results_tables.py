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
import os
import re
import subprocess
import sys
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

MODES = ("paper", "paper-literal", "default")  # the columns' order: the paper's pipeline, literal, ours


def rerun(names: list[str] | None = None, out: Path = RESULTS, say: Callable[[str], None] = print) -> None:
    """Run each of ``names`` (default: all of :data:`RUNS`) with ``--json`` into ``out/NAME.json``."""
    out.mkdir(parents=True, exist_ok=True)
    for name in names or list(RUNS):
        argv = [sys.executable, "-m", "twin.cli", "run", *RUNS[name], "--json"]
        say(f"results: twin run {' '.join(RUNS[name])} …")
        done = subprocess.run(argv, capture_output=True, text=True, env={**os.environ, "MPLBACKEND": "Agg"})
        if done.returncode != 0:
            raise RuntimeError(f"twin run {' '.join(RUNS[name])}: exit {done.returncode}: {done.stderr[-2000:]}")
        json.loads(done.stdout)  # one JSON object, or fail here rather than in the tables
        (out / f"{name}.json").write_text(done.stdout)


def load(where: Path = RESULTS) -> dict[str, dict]:
    """Every run's JSON in ``where``, by run name."""
    missing = [n for n in RUNS if not (where / f"{n}.json").exists()]
    if missing:
        raise FileNotFoundError(f"{where}: no results of {', '.join(missing)} (python -m scenarios.results_tables "
                                f"--rerun --only {' '.join(missing)})")
    return {n: json.loads((where / f"{n}.json").read_text()) for n in RUNS}


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
         "from the mean tip / largest distance (hardware: sensing and mechanics; twin: sensing only, its true tip "
         f"returns within {f(rep['true_max_mm'])} mm)", pair(rep["paper_std_mm"], rep["paper_max_mm"], hw),
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


#: table name → renderer (results by run name → markdown)
TABLES: dict[str, Callable[[dict[str, dict]], str]] = {
    "static-shapes": static_shapes,
    "paper-ablation": paper_ablation,
    "dynamic": dynamic,
    "spun-twist": spun,
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
    parser.add_argument("--only", nargs="+", choices=list(RUNS), help="rerun only these")
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
