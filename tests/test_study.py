"""The design-study runner on a real Dask LocalCluster (2 worker processes), and the sensor-design task.

The runner's tasks here are tiny (``selftest``: square a number, one raises on purpose), so the cost is the
cluster's start-up. Checked: a failing task is retried, then reported with its error and still has its row; the
table (Parquet and CSV) has one row per task; a resumed study recomputes only what did not finish.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")

from scenarios.studies.definitions import selftest_study, sensor_design_study, sensor_design_task  # noqa: E402
from scenarios.studies.runner import Study, run_study, task_key  # noqa: E402


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                           host="127.0.0.1", silence_logs=40)
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


def test_task_key_depends_on_parameters_and_function_only():
    a = task_key("m:f", {"x": 1, "y": 2.0})
    assert a == task_key("m:f", {"y": 2.0, "x": 1})  # order does not matter
    assert a != task_key("m:f", {"x": 1, "y": 2.5})
    assert a != task_key("m:g", {"x": 1, "y": 2.0})


def test_failures_are_reported_the_table_is_complete_and_a_resume_skips_finished_tasks(tmp_path, client):
    study = selftest_study(n=6, fail=(3,))
    messages = []
    first = run_study(study, tmp_path, retries=1, client=client, progress=messages.append)
    assert first.computed == 6 and first.skipped == 0 and first.failed == 1
    assert [r["x"] for r in first.rows] == list(range(6))  # one row per task, in task order
    bad = [r for r in first.rows if r["status"] != "ok"]
    assert len(bad) == 1 and bad[0]["x"] == 3 and "fails on purpose" in bad[0]["error"]
    assert all(r["y"] == r["x"] ** 2 for r in first.rows if r["status"] == "ok")
    assert any("FAILED after 1 retries" in m for m in messages)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["ok"] == 5 and len(summary["failed"]) == 1 and "fails on purpose" in summary["failed"][0]["error"]
    table = pq.read_table(tmp_path / "results.parquet").to_pylist()
    assert len(table) == 6 and [r["status"] for r in table].count("error") == 1
    with open(tmp_path / "results.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 6
    assert "Failed tasks" in (tmp_path / "report.md").read_text()

    # resume: the five finished tasks are read back, the failed one is tried again (and fails again)
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "tasks").iterdir()}
    second = run_study(study, tmp_path, retries=0, client=client)
    assert second.skipped == 5 and second.computed == 1 and second.failed == 1
    after = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "tasks").iterdir()}
    changed = [k for k in before if before[k] != after[k]]
    assert changed == [f"{task_key(study.function, study.tasks[3])}.json"]

    # a study whose tasks all finished recomputes nothing
    ok_only = Study(study.name, study.function, tuple(t for t in study.tasks if not t["fail"]), ("x",), ("y",))
    third = run_study(ok_only, tmp_path, client=client)
    assert third.computed == 0 and third.skipped == 5 and third.failed == 0


def test_duplicate_tasks_are_refused(tmp_path):
    s = Study("dup", "scenarios.studies.definitions:selftest_task", ({"x": 1}, {"x": 1}))
    with pytest.raises(ValueError, match="same parameters"):
        run_study(s, tmp_path)


def test_sensor_design_task_error_grows_with_noise_and_core_angle_error():
    base = {"noise_pm": 0.0, "n_gratings": 18, "spacing_mm": 10.0, "core_angle_error_deg": 0.0,
            "temperature_k": 0.0, "seed": 0}
    exact = sensor_design_task(base)
    # exact curvature at the gratings, no effects: only interpolation between gratings is left (the library
    # reconstructs within 0.033 mm from exact curvatures, README "Reconstruction from exact curvatures")
    assert exact["shapes"] == 12 and exact["max_error_mm"] < 0.05
    noisy = sensor_design_task(base | {"noise_pm": 5.0})
    angled = sensor_design_task(base | {"core_angle_error_deg": 3.0})
    assert noisy["max_error_mm"] > 2 * exact["max_error_mm"]
    assert angled["max_error_mm"] > 2 * exact["max_error_mm"]
    assert np.isfinite([noisy["mean_error_mm"], angled["tip_error_mm"]]).all()


def test_sensor_design_study_groups_seeds_into_designs():
    s = sensor_design_study(seeds=2, quick=True)
    designs = {tuple(t[k] for k in s.group_by) for t in s.tasks}
    assert len(s.tasks) == 2 * len(designs) and len({task_key(s.function, t) for t in s.tasks}) == len(s.tasks)
