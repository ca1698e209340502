"""Time series from the twin, shared by the dynamic experiments: collect frames with their truth, reconstruct
them in one batch, and measure errors frame by frame.

The reconstruction lives in the fibre's base frame (origin at the first grating's arc length s = 0, tangent
+z). The simulator knows where that frame is in the world — the rod's material frame at s = 0 — so
:func:`to_world` can place a reconstruction in the world as a tracked catheter base would, and an EM-sensor-like
tip truth can be compared with it directly.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sim_interrogator.sim import SimInterrogator
from twin import Reconstructor, Shape, metrics
from twin.frames import Truth

__all__ = ["Series", "collect", "em_readings", "errors", "show_frames", "to_world"]


@dataclass(frozen=True, eq=False)
class Series:
    """Frames of one run and their truth (leading axis: frames).

    Attributes
    ----------
    t : ndarray (n,)
        Simulated time, s.
    wavelengths : ndarray (n, n_gratings, n_cores)
        nm, NaN where a peak was lost.
    lost_peaks : ndarray of int (n,)
    truth_s : ndarray (m,)
        Arc length of the truth samples, m.
    truth_positions : ndarray (n, m, 3)
        The catheter's centreline, world, m.
    base_positions, base_frames : ndarray (n, 3), (n, 3, 3)
        The fibre's base frame (the rod's material frame at s = 0) in the world.
    truth_curvature : ndarray (n, n_gratings, 2)
        True curvature at the gratings, 1/m.
    temperature : ndarray (n, n_gratings)
        K.
    fixture : ndarray (k, 3) or None
        The fixture's centreline at the start, world, m.
    """

    t: np.ndarray
    wavelengths: np.ndarray
    lost_peaks: np.ndarray
    truth_s: np.ndarray
    truth_positions: np.ndarray
    base_positions: np.ndarray
    base_frames: np.ndarray
    truth_curvature: np.ndarray
    temperature: np.ndarray
    fixture: np.ndarray | None = None

    def __len__(self) -> int:
        return self.t.size

    @property
    def tip(self) -> np.ndarray:
        """True tip (end of the sensed length) in the world, (n, 3) m."""
        return self.truth_positions[:, -1]


def collect(sim: SimInterrogator, n_frames: int, every: int = 1,
            progress: Callable[[int, int], None] | None = None) -> Series:
    """Read ``n_frames`` frames, keeping every ``every``-th (e.g. 40 Hz data analysed at 2 Hz: every = 20).

    ``progress(done, total)`` is called every ~5 % of the frames.
    """
    keep = []
    step = max(1, n_frames // 20)
    for i in range(n_frames):
        f = sim.read()
        if i % every == 0:
            keep.append(f)
        if progress and (i + 1) % step == 0:
            progress(i + 1, n_frames)
    truths = [f.truth for f in keep]
    s = truths[0].s
    if any(tr.s.shape != s.shape for tr in truths):
        raise ValueError("truth samples changed during the run; a fixed sampling is needed for a series")
    i0 = int(np.argmin(np.abs(s)))
    return Series(
        t=np.array([f.sequence / sim.rate for f in keep]),
        wavelengths=np.stack([f.wavelengths for f in keep]),
        lost_peaks=np.array([int(np.isnan(f.wavelengths).sum()) for f in keep]),
        truth_s=s,
        truth_positions=np.stack([tr.positions for tr in truths]),
        base_positions=np.stack([tr.positions[i0] for tr in truths]),
        base_frames=np.stack([tr.frames[i0] for tr in truths]),
        truth_curvature=np.stack([tr.curvature for tr in truths]),
        temperature=np.stack([np.broadcast_to(tr.temperature, tr.curvature.shape[:1]) for tr in truths]),
        fixture=truths[0].fixture,
    )


def to_world(shape: Shape, series: Series, index=None) -> np.ndarray:
    """Reconstructed positions (n, n_points, 3) placed in the world with the true base pose of each frame.

    ``index``: the series' frames ``shape`` holds (an index array of n frames); default all of them, in order."""
    frames, positions = series.base_frames, series.base_positions
    if index is not None:
        frames, positions = frames[index], positions[index]
    return np.einsum("nij,npj->npi", frames, shape.positions) + positions[:, None, :]


def errors(rec: Reconstructor, series: Series, register: str = "kabsch") -> tuple[Shape, metrics.ErrorStats]:
    """Reconstruct every frame and compare with the catheter's own centreline, frame by frame.

    ``register``: ``"kabsch"`` (rigid registration on arc-length correspondences, the shape error alone) or
    ``"base"`` (no registration: the reconstruction placed with the true base pose, :func:`to_world`, so the
    error includes what a tracked base would see). Returns the batched shape and per-frame statistics (m).
    """
    if register not in ("kabsch", "base"):
        raise ValueError(f"register must be kabsch or base, got {register!r}")
    shape = rec(series.wavelengths)
    if register == "base":
        err = metrics.shape_error(to_world(shape, series), series.truth_positions, s=shape.s,
                                  truth_s=series.truth_s, register="none")
    else:
        err = metrics.shape_error(shape.positions, series.truth_positions, s=shape.s, truth_s=series.truth_s)
    return shape, err


def em_readings(tip: np.ndarray, sigma: float, seed) -> np.ndarray:
    """EM-sensor-like tip readings: ``tip`` (n, 3) m plus white Gaussian noise of ``sigma`` m per axis.

    ``seed``: anything :func:`numpy.random.default_rng` takes; each experiment keeps the EM sensor's noise
    stream apart from the interrogator's with its own seed."""
    return tip + sigma * np.random.default_rng(seed).standard_normal(tip.shape)


def show_frames(viewer, shapes: Shape, series: Series, count: int = 40, pause: float | None = 0.1,
                label: Callable[[int], str] | None = None) -> None:
    """Replay about ``count`` evenly spaced frames in a viewer (:class:`twin.viewer.Viewer` or anything with its
    ``show(shape, truth, *, base_pose, label[, force])``), each placed with the fibre base's tracked pose; nothing
    without a viewer. Frames with no usable grating (NaN shape) are skipped.

    ``pause``: seconds between frames, each forced past the viewer's rate limiter; None: paced by the viewer's
    own rate limiter (``viewer.ready()``). ``label(i)``: the text for frame ``i`` (default its time)."""
    if viewer is None:
        return
    for i in np.unique(np.linspace(0, len(series) - 1, count).round().astype(int)):
        i = int(i)
        if not np.all(np.isfinite(shapes.positions[i])):
            continue
        if pause is None:
            ready = getattr(viewer, "ready", None)
            while ready is not None and not ready():
                time.sleep(0.005)
        truth = Truth(s=series.truth_s, positions=series.truth_positions[i], frames=None,
                      curvature=series.truth_curvature[i], fixture=series.fixture)
        viewer.show(shapes[i], truth, base_pose=(series.base_frames[i], series.base_positions[i]),
                    label=label(i) if label else f"t = {series.t[i]:.1f} s", **({} if pause is None else
                                                                                {"force": True}))
        if pause is not None:
            time.sleep(pause)
