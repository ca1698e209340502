"""Run a study's tasks on Dask distributed and gather their results (docs/studies.md).

A :class:`Study` is a list of tasks, each a JSON-ready parameter dict, and one task function named
``"module:function"`` that takes the dict and returns a flat JSON-ready dict (a row). :func:`run_study`

1. hashes each task's parameters (SHA-256 of canonical JSON, with the function's name) into its key;
2. skips tasks whose result file ``OUT/tasks/KEY.json`` says ``ok`` (a resumed study recomputes nothing that
   finished; a task that failed before is tried again);
3. submits the others to a Dask client — a :class:`distributed.LocalCluster` of ``workers`` single-threaded
   processes on this machine, or an existing scheduler's address — with ``retries`` automatic retries each;
4. writes each task's result file as soon as it completes (on the client: workers need not share a disk),
   printing progress; a task still failing after its retries is recorded with its error, never dropped;
5. gathers every task's file into one table ``OUT/results.parquet`` (and ``results.csv``), the JSON summary
   ``OUT/summary.json`` and ``OUT/report.md``.

Workers import the task function by name, so on a cluster they need the project installed (``pip install
'.[study]'`` from a checkout); results travel back to the client as small dicts.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import import_module
from pathlib import Path

from twin.extras import require

__all__ = ["Study", "StudyResult", "read_rows", "run_study", "run_task", "task_key"]


@dataclass(frozen=True)
class Study:
    """A sweep: ``function`` ("module:function") applied to each of ``tasks`` (parameter dicts).

    ``group_by`` names the parameters that make a design (the summary groups the rows by them; the rest, e.g. a
    seed, are repetitions); ``metrics`` the result columns the summary aggregates.
    """

    name: str
    function: str
    tasks: tuple[dict, ...]
    group_by: tuple[str, ...] = ()
    metrics: tuple[str, ...] = ()
    description: str = ""


@dataclass(frozen=True)
class StudyResult:
    """What a run produced: the table's rows (one per task, in task order), counts and paths."""

    rows: list[dict] = field(repr=False)
    computed: int
    skipped: int
    failed: int
    wall_s: float
    out: Path
    summary: dict = field(repr=False)


def _canonical(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def task_key(function: str, params: dict) -> str:
    """The task's identity: the first 16 hex digits of SHA-256 over the function's name and its parameters."""
    return hashlib.sha256(_canonical({"function": function, "params": params}).encode()).hexdigest()[:16]


def run_task(function: str, params: dict) -> dict:
    """Import ``function`` ("module:function") and apply it to ``params`` (what a worker runs)."""
    module, _, name = function.partition(":")
    return getattr(import_module(module), name)(dict(params))


def _clean(value):
    """JSON-ready: NaN and infinities become None (the project's files never hold NaN)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    return value


def _write_json(path: Path, obj) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(_clean(obj), indent=1, allow_nan=False) + "\n")
    tmp.replace(path)  # atomic: a killed study never leaves a half-written result


def _load(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _client(workers: int, scheduler: str | None):
    distributed = require("distributed", "design studies (twin study)")
    if scheduler:
        return distributed.Client(scheduler, timeout="20s"), None
    # A terminal's Ctrl-C reaches the whole process group: the local workers must ignore it (they inherit SIG_IGN
    # when they start, and asyncio then installs no handler of its own) so that this process alone stops the
    # study and closes them, instead of each printing its traceback.
    ignore = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if ignore else None
    try:
        cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                           dashboard_address=None, host="127.0.0.1", silence_logs=40)
    finally:
        if ignore:
            signal.signal(signal.SIGINT, previous)
    return distributed.Client(cluster), cluster


def run_study(study: Study, out: str | Path, *, workers: int = 2, scheduler: str | None = None, retries: int = 1,
              progress: Callable[[str], None] | None = None, client=None) -> StudyResult:
    """Run ``study`` into directory ``out`` (see the module docstring); returns the gathered result.

    ``client``: an existing :class:`distributed.Client` to use (then ``workers`` and ``scheduler`` are ignored).
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if retries < 0:
        raise ValueError(f"retries must be >= 0, got {retries}")
    say = progress or (lambda msg: None)
    out = Path(out)
    tasks_dir = out / "tasks"
    tasks_dir.mkdir(parents=True, exist_ok=True)
    keys = [task_key(study.function, p) for p in study.tasks]
    if len(set(keys)) != len(keys):
        raise ValueError(f"study {study.name!r}: two tasks have the same parameters")
    todo = [i for i, k in enumerate(keys) if (_load(tasks_dir / f"{k}.json") or {}).get("status") != "ok"]
    skipped = len(keys) - len(todo)
    say(f"study {study.name}: {len(keys)} tasks, {skipped} already done, {len(todo)} to run")
    t0 = time.perf_counter()
    failed = 0
    if todo:
        own = client is None
        cluster = None
        if own:
            client, cluster = _client(workers, scheduler)
        try:
            distributed = require("distributed", "design studies (twin study)")
            futures = {}
            for i in todo:
                f = client.submit(run_task, study.function, study.tasks[i], key=f"{study.name}-{keys[i]}",
                                  retries=retries, pure=False)
                futures[f] = i
            done = 0
            for f in distributed.as_completed(list(futures)):
                i = futures[f]
                rec = {"key": keys[i], "function": study.function, "params": study.tasks[i]}
                if f.status == "finished":
                    rec |= {"status": "ok", "result": f.result()}
                else:
                    exc = f.exception()
                    rec |= {"status": "error", "error": f"{type(exc).__name__}: {exc}", "retries": retries}
                    failed += 1
                _write_json(tasks_dir / f"{keys[i]}.json", rec)
                done += 1
                state = "ok" if rec["status"] == "ok" else f"FAILED after {retries} retries: {rec['error']}"
                say(f"  [{done}/{len(todo)}] {keys[i]} {state} ({time.perf_counter() - t0:.1f} s)")
                f.release()
        finally:
            if own:
                client.close()
                if cluster is not None:
                    cluster.close()
    wall = time.perf_counter() - t0
    rows = read_rows(study, out)
    summary = summarise(study, rows, computed=len(todo), skipped=skipped, wall_s=wall)
    write_table(rows, out)
    _write_json(out / "summary.json", summary)
    (out / "report.md").write_text(report(study, summary))
    return StudyResult(rows, len(todo), skipped, sum(r["status"] != "ok" for r in rows), wall, out, summary)


def read_rows(study: Study, out: str | Path) -> list[dict]:
    """One row per task in task order: ``key``, ``status``, the parameters, then the result (or ``error``).
    A task without a result file is a row with status ``missing``, so the table is always complete."""
    out = Path(out)
    rows = []
    for params in study.tasks:
        key = task_key(study.function, params)
        rec = _load(out / "tasks" / f"{key}.json") or {"status": "missing"}
        row = {"key": key, "status": rec["status"], **params}
        if rec["status"] == "ok":
            row |= {k: v for k, v in rec["result"].items() if not isinstance(v, list | dict)}
        else:
            row["error"] = rec.get("error", "not run")
        rows.append(row)
    return rows


def write_table(rows: list[dict], out: Path) -> None:
    """``results.csv`` always; ``results.parquet`` too (pyarrow, the ``study`` extra)."""
    columns = list(dict.fromkeys(k for r in rows for k in r))
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, columns)
        w.writeheader()
        w.writerows([{k: _clean(r.get(k)) for k in columns} for r in rows])
    pa = require("pyarrow", "the study's Parquet table")
    pq = require("pyarrow.parquet", "the study's Parquet table")
    table = pa.Table.from_pylist([{k: _clean(r.get(k)) for k in columns} for r in rows])
    pq.write_table(table, out / "results.parquet")


def summarise(study: Study, rows: list[dict], *, computed: int, skipped: int, wall_s: float) -> dict:
    """Counts, failures (each with its error) and, per design, the distribution of each metric over its rows."""
    ok = [r for r in rows if r["status"] == "ok"]
    designs: dict[str, dict] = {}
    for r in ok:
        label = ", ".join(f"{k}={r.get(k)}" for k in study.group_by) or "all"
        designs.setdefault(label, {"params": {k: r.get(k) for k in study.group_by}, "rows": []})["rows"].append(r)
    per_design = []
    for label, d in designs.items():
        stats = {}
        for m in study.metrics:
            vals = sorted(float(r[m]) for r in d["rows"] if isinstance(r.get(m), int | float) and r[m] is not None)
            if vals:
                n = len(vals)
                stats[m] = {"mean": sum(vals) / n, "min": vals[0], "max": vals[-1],
                            "p50": vals[n // 2], "p90": vals[min(n - 1, int(0.9 * n))], "n": n}
        per_design.append({"design": label, **d["params"], "n": len(d["rows"]), "metrics": stats})
    return {"study": study.name, "function": study.function, "tasks": len(rows), "ok": len(ok),
            "failed": [{"key": r["key"], "error": r.get("error"), "params": {k: r.get(k) for k in study.tasks[0]}}
                       for r in rows if r["status"] != "ok"],
            "computed": computed, "skipped": skipped, "wall_s": wall_s,
            "tasks_per_min": computed / wall_s * 60 if computed and wall_s > 0 else None,
            "designs": per_design}


def report(study: Study, summary: dict) -> str:
    lines = [f"# Study {study.name}", "", study.description, "",
             f"{summary['tasks']} tasks: {summary['ok']} ok, {len(summary['failed'])} failed; "
             f"{summary['computed']} computed in this run ({summary['wall_s']:.1f} s), {summary['skipped']} reused.",
             ""]
    if study.metrics and summary["designs"]:
        head = ["design", "n"] + [f"{m} mean / p90 / max" for m in study.metrics]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for d in summary["designs"]:
            cells = [d["design"], str(d["n"])]
            for m in study.metrics:
                s = d["metrics"].get(m)
                cells.append("–" if s is None else f"{s['mean']:.4g} / {s['p90']:.4g} / {s['max']:.4g}")
            lines.append("| " + " | ".join(cells) + " |")
    if summary["failed"]:
        lines += ["", "## Failed tasks", ""] + [f"- `{f['key']}` {f['params']}: {f['error']}"
                                                  for f in summary["failed"]]
    lines += ["", "Table: `results.parquet` / `results.csv`; per-task results: `tasks/KEY.json`."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":  # pragma: no cover
    print("use `twin study NAME`", file=sys.stderr)
