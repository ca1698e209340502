"""Is the confidence tube calibrated? The twin knows the truth: each reconstruction's 95 % tube
(:mod:`twin.uncertainty`) is checked against the catheter's own centreline, and the model-error term is fitted on
runs other than those scored.

The truth is placed in the reconstruction's base frame with the simulator's base pose (the rod's material frame
at s = 0, as a clamped or tracked base gives it): no registration is fitted to the data being scored, so the
tube is tested as it would be used. The truth is interpolated at the reconstruction's arc lengths with a cubic
spline (the rod's ~2 mm vertices; a linear one would cut corners by h²κ/8, up to 0.03 mm).

The model error is fitted (:func:`twin.uncertainty.fit_model_error`) on the lab's identification shapes
(:data:`LAB_SHAPES` in the paper's fixtures, with the lab session's own noise seeds), against their rods'
centrelines, and cached like the lab calibration; ``static-shapes`` fits it on the other fold of its shapes,
as it identifies the calibration.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
from collections.abc import Callable, Sequence

import numpy as np
from scipy.interpolate import CubicSpline

from scenarios._common.calibration import _LAB_SEED, LAB_SHAPES, cache_dir, paper_fixture
from sim_interrogator.optics import OpticsConfig
from sim_interrogator.setups import StaticShape
from sim_interrogator.sim import SimInterrogator
from twin import Calibration, FiberModel, Reconstructor, Shape
from twin.frames import Truth
from twin.uncertainty import TWIN_INTERPOLATION, ModelError, Uncertainty, coverage, fit_model_error

__all__ = ["LEVEL", "fit_on_frames", "lab_model_error", "summary", "truth_in_base", "truth_of_frames"]

#: The tube every report checks, and its acceptance band (issue 21): 92–98 % of the truth points inside.
LEVEL = 0.95
_CACHE_VERSION = 5  # 5: the interpolation term (TWIN_INTERPOLATION) held, the white part fitted on top

Say = Callable[[str], None]


def truth_in_base(truth_s: np.ndarray, positions: np.ndarray, base_frames: np.ndarray, base_positions: np.ndarray,
                  s: np.ndarray) -> np.ndarray:
    """The true centreline (..., m, 3) world, m, in the base frame (R (..., 3, 3), p (..., 3)) at arc lengths
    ``s`` (cubic spline in arc length): (..., len(s), 3)."""
    local = np.einsum("...mi,...ij->...mj", positions - base_positions[..., None, :], base_frames)
    return CubicSpline(truth_s, local, axis=-2)(s)


def truth_of_frames(frames, s: np.ndarray) -> np.ndarray:
    """:func:`truth_in_base` for frames of one settled shape (their truths, each with its base pose)."""
    truths: Sequence[Truth] = [f.truth for f in frames]
    t_s = truths[0].s
    i0 = int(np.argmin(np.abs(t_s)))
    pos = np.stack([t.positions for t in truths])
    return truth_in_base(t_s, pos, np.stack([t.frames[i0] for t in truths]), pos[:, i0], s)


def summary(shape: Shape, truth: np.ndarray) -> dict:
    """``coverage_95`` (fraction of true points in the 95 % tube, s > 0), ``mean_sigma_mm`` (mean 1σ lateral
    radius over points with s > 0 and frames), the coverage per quarter of the length and, for a batch with some
    frames that lost a grating, the coverage of the intact frames and of the others apart (a lost grating is
    interpolated over, and the interpolation term widens the tube over its gap)."""
    s = shape.s
    edges = np.linspace(0, s[-1], 5)
    quarters = [coverage(shape, truth, LEVEL, where=(s > lo) & (s <= hi)) for lo, hi in itertools.pairwise(edges)]
    sig = shape.sigma[..., s > 0]
    out = {"coverage_95": coverage(shape, truth, LEVEL), "mean_sigma_mm": float(np.nanmean(sig) * 1e3),
           "coverage_95_by_quarter": quarters}
    lost = ~shape.valid.all(axis=-1)
    if shape.batch_shape and lost.any() and not lost.all():
        out["coverage_95_intact_frames"] = coverage(shape[~lost], truth[~lost], LEVEL)
        out["coverage_95_frames_with_a_lost_grating"] = coverage(shape[lost], truth[lost], LEVEL)
        out["frames_with_a_lost_grating"] = int(lost.sum())
    return out


def fit_on_frames(fiber: FiberModel, cal: Calibration, frame_sets: Sequence, source: str) -> ModelError:
    """The model error fitted on settled shapes (a list of frame lists with truths) with calibration ``cal``:
    the interpolation term held at :data:`~twin.uncertainty.TWIN_INTERPOLATION` (fitted on a sheath run, where
    it is the largest error), a white curvature error fitted on top (or the parameters' 1σ scaled down)."""
    rec = Reconstructor(fiber, cal)
    w = np.concatenate([np.stack([f.wavelengths for f in frames]) for frames in frame_sets])
    truth = np.concatenate([truth_of_frames(frames, rec.s) for frames in frame_sets])
    unc = Uncertainty(rec)
    return fit_model_error(unc, rec(w), w, truth, level=LEVEL, fixed=ModelError(interpolation=TWIN_INTERPOLATION),
                           source=source)


def lab_model_error(fiber: FiberModel, optics: OpticsConfig, cal: Calibration, *, names: Sequence[str] = LAB_SHAPES,
                    repeats: int = 5, cache: bool = True, progress: Say | None = None) -> ModelError:
    """The model error of the default pipeline with ``cal``, fitted on the lab's identification shapes (module
    docstring), from the cache when it is there."""
    say = progress or (lambda msg: None)
    key = {"version": _CACHE_VERSION, "fiber": fiber.to_dict(), "calibration": cal.to_dict(),
           "optics": {k: v for k, v in optics.__dict__.items() if k not in ("seed", "thermal_mismatch")},
           "shapes": list(names), "repeats": repeats}
    digest = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:16]
    path = cache_dir() / f"lab-model-error-{digest}.json"
    if cache and path.is_file():
        say(f"model error: from the cache ({path})")
        return ModelError(**json.loads(path.read_text()))
    sets = []
    for i, name in enumerate(names):
        say(f"model error: identification shape {i + 1}/{len(names)}: {name} in the {paper_fixture(name)} …")
        sim = SimInterrogator(StaticShape(name, paper_fixture(name)), fiber, optics.replace(seed=_LAB_SEED + 1 + i))
        sets.append([sim.read() for _ in range(repeats)])
    me = fit_on_frames(fiber, cal, sets, f"fitted on the rods of {', '.join(names)} (lab identification shapes, "
                       "their fixtures and noise seeds)")
    if cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps({"curvature": me.curvature, "relative": me.relative, "base_angle": me.base_angle,
                                   "interpolation": me.interpolation, "parameter_scale": me.parameter_scale,
                                   "source": me.source}))
        tmp.replace(path)
    say(f"model error: {me.curvature:.3g} 1/m per component, interpolation {me.interpolation:.3g}, the "
        "calibration's parameter 1σ × "
        f"{me.parameter_scale:.3g} ({me.source})")
    return me


def run_coverage(fiber: FiberModel, optics: OpticsConfig, cal: Calibration | None, shape: Shape, wavelengths,
                 truth: np.ndarray, progress: Say | None = None, averaged: int = 1) -> dict:
    """The 95 % tube of the default pipeline's ``shape`` (a batch, reconstructed with ``cal``) against ``truth``
    (base frame, at the shape's arc lengths): :func:`summary` with the model error fitted on the lab's
    identification shapes (:func:`lab_model_error`), which it names, and, as a diagnostic, the model error this
    run itself would have needed. ``averaged``: frames averaged into each of
    ``wavelengths`` (the white noise shrinks by its square root)."""
    cal = cal or Calibration()
    me = lab_model_error(fiber, optics, cal, progress=progress)
    rec = Reconstructor(fiber, cal)
    unc = Uncertainty(rec, model_error=me, wavelength_noise=rec.wavelength_noise / np.sqrt(averaged))
    out = unc.propagate(shape, wavelengths)
    # a diagnostic, not a calibration of this run: the interpolation constant that would have brought this run's
    # own points to 95 % with the other terms held (how far the error model is from this regime; on a run other
    # than the scored ones it is how TWIN_INTERPOLATION was fitted)
    needed = fit_model_error(unc, shape, wavelengths, truth, level=LEVEL, template=ModelError(interpolation=1.0),
                             fixed=me, source="fitted on this run (diagnostic)")
    return {**summary(out, truth), "model_error": me.to_dict(), "model_error_needed_in_sample": needed.to_dict()}
