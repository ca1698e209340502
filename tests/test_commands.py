"""Commands that had no test of their own: `twin bench`, `twin study` and `twin run library`, each run as a user
runs it (a subprocess of the installed command line), with the smallest options that still exercise it."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

from twin import shapes

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg", "PYTHONUNBUFFERED": "1"}


def _twin(*args: str, cwd=None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([*TWIN, *args], capture_output=True, text=True, env=ENV, cwd=cwd, timeout=timeout)


def _finite_numbers(d: dict) -> dict:
    return {k: v for k, v in d.items() if isinstance(v, int | float) and not isinstance(v, bool)}


def test_twin_bench_quick_reconstruct_section_writes_json_and_compares(tmp_path):
    out_file = tmp_path / "bench.json"
    proc = _twin("bench", "--quick", "--sections", "reconstruct", "--json", "--out", str(out_file))
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert json.loads(out_file.read_text()) == result  # --out writes what --json prints
    assert {"cores", "python", "numpy", "numba"} <= set(result["machine"])
    figures = result["reconstruct"]
    speeds = ("latency_us_p50", "latency_us_p99", "batch_frames_per_s", "paper_latency_us_p50",
              "baseline_latency_us_p50", "speedup_vs_baseline")
    for key in speeds:  # measured figures: present, finite, positive (their size is the machine's)
        assert key in figures and math.isfinite(figures[key]) and figures[key] > 0, key
    assert figures["latency_us_p99"] >= figures["latency_us_p50"]
    # the set-up figures are the documented ones (README "Speed"): 171 points of the 170 mm fibre at 1 mm
    assert figures["points_per_shape"] == 171 and figures["step_m"] == 1e-3
    # --compare reads the file back and shows each figure beside the earlier one
    again = _twin("bench", "--quick", "--sections", "reconstruct", "--compare", str(out_file))
    assert again.returncode == 0, again.stderr
    lines = {line.split()[0]: line for line in again.stdout.splitlines() if line.startswith("  ")}
    for key, value in figures.items():
        assert key in lines and f"(was {value:g}, ×" in lines[key], lines.get(key)  # printed with :g
    assert "(was 171, ×1.00)" in lines["points_per_shape"]  # a set-up figure does not change between runs


def test_twin_study_selftest_on_one_worker_reports_its_failed_task_and_every_row(tmp_path):
    """selftest (docs/studies.md): task x computes x², task 3 fails on purpose; the quick study has 8 tasks."""
    proc = _twin("study", "selftest", "--quick", "--workers", "1", "--json", "--out", str(tmp_path / "s"))
    assert proc.returncode == 1, proc.stderr  # a failed task: status 1 (scenarios/studies/command.py)
    summary = json.loads(proc.stdout)
    assert summary["tasks"] == 8 and summary["ok"] == 7 and summary["computed"] == 8 and summary["skipped"] == 0
    (failed,) = summary["failed"]
    assert failed["params"]["x"] == 3 and "fails on purpose" in failed["error"]
    ys = {d["x"]: d["metrics"]["y"]["mean"] for d in summary["designs"]}
    assert ys == {x: float(x * x) for x in range(8) if x != 3}
    for name in ("results.parquet", "results.csv", "summary.json", "report.md"):
        assert (tmp_path / "s" / name).is_file(), name
    assert json.loads((tmp_path / "s" / "summary.json").read_text())["ok"] == 7


def test_twin_study_sensor_design_quick_on_one_worker(tmp_path):
    proc = _twin("study", "sensor-design", "--quick", "--workers", "1", "--json", "--out", str(tmp_path / "s"))
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["failed"] == []
    assert summary["ok"] == summary["tasks"] == summary["computed"] > 0
    for design in summary["designs"]:
        for metric in ("max_error_mm", "mean_error_mm", "tip_error_mm"):
            stats = design["metrics"][metric]
            assert all(math.isfinite(stats[k]) and stats[k] >= 0 for k in ("mean", "min", "max")), (design, metric)
        # the max error along the catheter bounds its mean, and the tip is a point of the catheter
        assert design["metrics"]["mean_error_mm"]["max"] <= design["metrics"]["max_error_mm"]["max"]
        assert design["metrics"]["tip_error_mm"]["max"] <= design["metrics"]["max_error_mm"]["max"]


def test_twin_run_library_noise_free_is_exact_where_the_maths_says_so():
    """Noise-free wavelengths from the nominal fibre: on the arc (constant curvature) every interpolant and the
    exponential integrators are exact, so both pipelines' errors are rounding (< 1e-6 mm, as in
    test_reconstruct.py's arc test); on the helix (constant κ and τ) the paper's Frenet pipeline is exact too."""
    proc = _twin("run", "library", "--json", "--repeats", "1", "--noise-pm", "0")
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    rows = {r["shape"]: r for r in result["shapes"]}
    assert set(rows) == set(shapes.names())
    for name, row in rows.items():
        for key, value in _finite_numbers(row).items():
            assert math.isfinite(value) and value >= 0, (name, key)
        assert row["default_mean_error_mm"] <= row["default_max_error_mm"]
    assert rows["arc"]["default_max_error_mm"] < 1e-6 and rows["arc"]["paper_max_error_mm"] < 1e-6
    assert rows["helix"]["paper_max_error_mm"] < 1e-6
    # …and where it is not exact, the paper's pipeline is the one that errs (its torsion from differences)
    assert rows["mixed"]["paper_max_error_mm"] > 100 * rows["mixed"]["default_max_error_mm"]
