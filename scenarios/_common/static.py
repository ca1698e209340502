"""Measuring a settled static shape: the errors of each pipeline against the catheter's own centreline (Kabsch on
arc length, then point-to-curve distances) and against the fixture's (the paper's ICP and ±0.5 mm translation
search), shared by ``static-shapes`` and ``paper-ablation``."""

from __future__ import annotations

import numpy as np

from scenarios._common.calibration import paper_fixture
from scenarios.report import register_onto
from sim_interrogator.sim import SimInterrogator
from twin import Reconstructor, metrics

__all__ = ["fixture_for", "measure"]


def fixture_for(name: str, fixture: str) -> str:
    return paper_fixture(name) if fixture == "paper" else fixture


def _stats(err: metrics.ErrorStats) -> dict:
    return {"max": np.atleast_1d(err.max), "mean": np.atleast_1d(err.mean), "tip": np.atleast_1d(err.tip)}


def measure(sim: SimInterrogator, frames, recs: dict[str, Reconstructor], curves: dict | None = None) -> dict:
    """Errors of each reconstructor on ``frames`` (all of one settled shape) against the rod and the fixture.

    With ``curves`` (a dict), also collects the last frame for overlays: per mode the reconstruction registered
    onto the rod and its error along the arc length (``MODE_along``), the rod and the fixture."""
    truth = frames[0].truth
    fixture_s = np.linspace(0.0, sim.fiber.sensed_length, len(truth.fixture))
    out = {}
    for mode, rec in recs.items():
        shape = rec(frames)
        rod = metrics.shape_error(shape.positions, truth.positions, s=shape.s, truth_s=truth.s)
        fix = metrics.shape_error(shape.positions, truth.fixture, s=shape.s, truth_s=fixture_s,
                                  register="icp+translation")
        out[mode] = {"rod": _stats(rod), "fixture": _stats(fix)}
        if curves is not None:
            registered, along = register_onto(shape.positions[-1], shape.s, truth.positions, truth.s)
            curves.setdefault(mode, []).append(registered)
            curves.setdefault(f"{mode}_along", []).append(along)
            curves["s"] = shape.s
    if curves is not None:
        for key, value in (("truth", truth.positions), ("truth_s", truth.s), ("fixture", truth.fixture)):
            curves.setdefault(key, []).append(value)
    return out
