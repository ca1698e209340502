"""Design studies: sweeps over scenario parameters and seeds, run as independent tasks on Dask distributed
(docs/studies.md).

* :mod:`scenarios.studies.runner` — the runner: per-task result files keyed by a hash of the parameters (a study
  resumes without recomputing finished tasks), retries, progress, one table (Parquet and CSV), a JSON summary
  and a markdown report;
* :mod:`scenarios.studies.definitions` — the studies (``integration``, ``sensor-design``, ``selftest``);
* :mod:`scenarios.studies.command` — ``twin study NAME`` (registered in the ``twin.commands`` group) and the
  ``study`` section of ``twin bench``.
"""
