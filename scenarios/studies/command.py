"""run a design study (a sweep of a scenario's parameters and seeds) on Dask distributed

``twin study NAME [--workers N | --scheduler ADDRESS] [--out DIR] [--seeds K] [--retries R] [--quick]``:
the study's tasks run in parallel on a LocalCluster of N single-threaded worker processes on this machine
(default 2), or on an existing Dask cluster; each finished task's result is written at once to
``DIR/tasks/KEY.json`` (KEY: a hash of its parameters), so a study interrupted or run again recomputes only
what did not finish. The results gather into ``DIR/results.parquet`` (and ``.csv``), ``DIR/summary.json``
(per design: the distribution of each metric over seeds; failures with their errors) and ``DIR/report.md``.
Studies: ``integration`` (the fibre-integration guidelines in the twin), ``sensor-design`` (noise, gratings,
core-angle error, temperature; no MuJoCo) and ``selftest``. docs/studies.md says how to start a cluster.
Ctrl-C stops the study (the finished tasks stay, a later run resumes), says how far it got and exits with 130.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

#: one-line help (read by `twin --help` without importing this module)
HELP = "run a design study (a sweep over parameters and seeds) on Dask distributed"

def add_arguments(parser: argparse.ArgumentParser) -> None:
    from scenarios.studies.definitions import STUDIES

    parser.add_argument("name", metavar="NAME", help="study: " + ", ".join(STUDIES))
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    where.add_argument("--scheduler", metavar="ADDRESS", help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786")
    parser.add_argument("--out", metavar="DIR", help="results directory (default studies/NAME)")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per design (default: the study's)")
    parser.add_argument("--retries", type=int, default=1, help="automatic retries of a failing task (default 1)")
    parser.add_argument("--quick", action="store_true", help="a small version of the study (a smoke run)")
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON object")


def run(args: argparse.Namespace) -> int:
    from scenarios.studies.definitions import get
    from scenarios.studies.runner import run_study

    kw = {"quick": args.quick} | ({"seeds": args.seeds} if args.seeds is not None else {})
    if args.seeds is not None and args.seeds < 1:
        raise ValueError(f"--seeds must be >= 1, got {args.seeds}")
    study = get(args.name, **kw)
    out = args.out or os.path.join("studies", args.name)
    try:
        result = run_study(study, out, workers=args.workers, scheduler=args.scheduler, retries=args.retries,
                           progress=lambda msg: print(msg, file=sys.stderr, flush=True))
    except KeyboardInterrupt:  # a bounded run cut short (twin.cli's rule: 130); finished tasks are on disk
        from scenarios.studies.runner import read_rows
        from twin.cli import EXIT_INTERRUPTED

        done = sum(r["status"] == "ok" for r in read_rows(study, out))
        print(f"twin study: interrupted: {done} of {len(study.tasks)} tasks done, kept in {out}/tasks (run the "
              "same command again to resume)", file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    print(f"study {study.name}: {len(result.rows)} tasks, {result.failed} failed; table {out}/results.parquet, "
          f"report {out}/report.md", file=sys.stderr)
    if args.json:
        print(json.dumps(result.summary, allow_nan=False))
    else:
        print((result.out / "report.md").read_text())
    return 1 if result.failed else 0


def integration_seconds_per_task(quick: bool = False) -> dict:
    """Wall seconds of one task of the integration study at its standard point, in this process (one core).

    The standard point is the study's baseline design (clearance 0.1 mm, μ 0.2, two fixations, Δx_prox 15 mm,
    Δx_dist 2 mm) with the study's own task parameters: four static shapes × three frames and three sheath cycles
    (:class:`scenarios.integration.Params`); ``quick`` runs one shape and one cycle. The task is what ``twin study
    integration`` runs per design point and seed, MuJoCo physics almost all of it.
    """
    from scenarios.integration import BASELINE
    from scenarios.studies.definitions import integration_task

    task = {"label": "clearance 0.1 mm", **BASELINE, "seed": 0}
    if quick:
        task |= {"shapes": ["helix"], "cycles": 1}
    t0 = time.perf_counter()
    integration_task(task)
    return {"seconds_per_task_integration": round(time.perf_counter() - t0, 2),
            "integration_task": "quick" if quick else "standard"}


def bench_study(quick: bool = False) -> dict:
    """``twin bench`` section ``study``: one integration task at the standard point on the pinned core
    (:func:`integration_seconds_per_task`), then sensor-design tasks per minute with 1 and 2 local workers.

    ``twin bench`` pins its measuring process to one CPU; the workers must not inherit that, so the affinity is
    widened to every CPU this process may use before the clusters start (after the single-core figure).
    """
    import tempfile

    from scenarios.studies.definitions import sensor_design_study
    from scenarios.studies.runner import run_study

    single = integration_seconds_per_task(quick)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, range(os.cpu_count() or 1))
    study = sensor_design_study(seeds=1 if quick else 2, quick=False)
    tasks = study.tasks[: 12 if quick else 36]
    out = {}
    for workers in (1, 2):
        # a fresh study per run (seed offset): nothing is reused from the other run's files
        s = type(study)(study.name, study.function, tuple({**t, "seed": t["seed"] + 100 * workers} for t in tasks))
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            from scenarios.studies.runner import _client

            client, cluster = _client(workers, None)
            try:
                client.run(lambda: __import__("scenarios.studies.definitions") and None)  # warm the imports
                client.submit(lambda: None).result()
                t1 = time.perf_counter()
                r = run_study(s, tmp, client=client)
                t2 = time.perf_counter()
            finally:
                client.close()
                cluster.close()
        if r.failed:
            raise RuntimeError(f"bench study: {r.failed} tasks failed")
        out[f"tasks_per_min_{workers}"] = round(len(tasks) / (t2 - t1) * 60, 1)
        out[f"startup_s_{workers}"] = round(t1 - t0, 2)
    out["scaling_2"] = round(out["tasks_per_min_2"] / out["tasks_per_min_1"], 3)
    out["tasks"] = len(tasks)
    return out | single
