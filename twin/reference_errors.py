"""The reconstruction against a reference the frames carry: the simulator's truth and the interrogator's own
shape (ILLumiSense sensor blocks). Both are live-loop sinks, so ``twin live``, ``twin replay`` (live over a file
source), the demo and the tests count the same frames the same way; docs/figures.md defines every figure.

- :class:`TruthError`: :func:`twin.metrics.shape_error` against the truth (registration ``register``): per frame
  the max, mean and RMS distance from the registered points to the true curve, and the tip error (the
  registered tip to the true point at the same arc length — a point-to-point distance, which may exceed the
  point-to-curve max).
- :class:`VendorDistance`: the same point-to-curve figures against the vendor's shape after a rigid (Kabsch)
  registration over their common arc length (:func:`vendor_distance`); the vendor frame convention is
  :data:`twin.io.illumisense.vendor.VENDOR_FROM_BASE`'s, and the registration makes the figures independent
  of it.

- :class:`TubeFigures`: the confidence tube (:mod:`twin.uncertainty`) on the same kind of sample of frames: its
  mean 1σ radius and, where the frames carry a truth, the fraction of the true points inside the 95 % tube
  (the truth placed by its own base pose, no registration). It costs one propagation per compared frame, and
  runs only where a command asks for the figures (``--json``).

Which frames: among the frames whose reconstruction is complete (all gratings solved) and which carry the
reference (a truth present; sensor ``sensor``'s block present), the first of each 1/``per_second`` s slot of the
source's timestamps (10 a second of source time by default: a comparison costs about as much as a
reconstruction, so every frame of a 1 kHz stream would not keep up); ``per_second=None`` takes every one. A frame
without a timestamp is a slot of its own. The rule depends on the frames only, never on how they were batched or
paced, so every path compares the same frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.frames import Frame, Shape
from twin.metrics import ErrorStats, kabsch, shape_error

__all__ = ["TruthError", "TruthErrors", "TubeFigures", "VendorDistance", "tube_figures", "vendor_distance",
           "vendor_in_base"]


def vendor_distance(positions: np.ndarray, s: np.ndarray, vendor_positions: np.ndarray, vendor_s: np.ndarray):
    """Distance from our reconstructions to the vendor's shapes after a rigid (Kabsch) registration.

    Parameters
    ----------
    positions : ndarray, shape (..., m, 3)
        Our reconstructions, m, at arc lengths ``s`` (m,).
    vendor_positions : ndarray, shape (..., N, 3)
        The vendor's shapes, m, at arc lengths ``vendor_s`` (N,) from the same base.
    s, vendor_s : ndarray

    Returns
    -------
    ErrorStats or None
        :func:`twin.metrics.shape_error` over the common arc length (pairs by arc length, Kabsch, exact
        point-to-polyline distances); None when fewer than 3 of our points lie on the vendor's shape.
    """
    if vendor_s.size < 2:  # a block with fewer than 2 shape points has no curve (nor a last point to index)
        return None
    keep = s <= vendor_s[-1] + 1e-9
    if np.count_nonzero(keep) < 3:
        return None
    return shape_error(positions[..., keep, :], vendor_positions, s=s[keep], truth_s=vendor_s, register="kabsch")


def vendor_in_base(positions: np.ndarray, s: np.ndarray, vendor_positions: np.ndarray, vendor_s: np.ndarray
                   ) -> tuple[np.ndarray, ErrorStats] | None:
    """The vendor's shape moved onto one reconstruction by the registration :func:`vendor_distance` makes.

    :func:`vendor_distance` moves our points onto the vendor's (Kabsch over the common arc length); this applies
    the inverse motion to the vendor's points instead, so the distances from our points to the moved vendor
    polyline are the reported ones (what the viewer draws is what is reported).

    Parameters
    ----------
    positions : ndarray, shape (m, 3)
        One reconstruction in its base frame, m, at arc lengths ``s`` (m,).
    vendor_positions : ndarray, shape (N, 3)
        The vendor's shape, m, vendor frame, at arc lengths ``vendor_s`` (N,).

    Returns
    -------
    (ndarray (N, 3), ErrorStats) or None
        The vendor's points in our base frame, m, and :func:`vendor_distance`'s figures; None when the two do
        not overlap over 3 points or the vendor's shape has NaN points.
    """
    v = np.asarray(vendor_positions, dtype=np.float64)
    vs = np.asarray(vendor_s, dtype=np.float64)
    if not np.isfinite(v).all():
        return None
    p = np.asarray(positions, dtype=np.float64)
    e = vendor_distance(p, s, v, vs)
    if e is None:
        return None
    keep = s <= vs[-1] + 1e-9
    paired = np.stack([np.interp(s[keep], vs, v[:, k]) for k in range(3)], axis=-1)
    R, t = kabsch(p[keep], paired)  # ours → vendor, the motion shape_error applies
    return (v - t) @ R, e


def _mm(x: float) -> float:
    return round(float(x) * 1e3, 4)


@dataclass(frozen=True)
class TruthErrors:
    """Shape error against the truth over ``frames_compared`` frames, mm (docs/figures.md).

    ``mean_error_mm`` is the mean over frames of each frame's mean point-to-curve distance, ``max_error_mm``
    the largest point-to-curve distance of any frame, ``rms_error_mm`` the RMS over all points of all frames,
    ``tip_error_mm_mean`` / ``_max`` the mean and largest tip error (point to the true point at the same arc
    length)."""

    frames_compared: int
    register: str
    mean_error_mm: float
    max_error_mm: float
    rms_error_mm: float
    tip_error_mm_mean: float
    tip_error_mm_max: float

    def line(self) -> str:
        """The one line every command prints for these errors."""
        return (f"vs truth ({self.frames_compared} frames, {self.register}): distance to the true curve mean "
                f"{self.mean_error_mm:.3f} mm, max {self.max_error_mm:.3f} mm; tip to the true tip mean "
                f"{self.tip_error_mm_mean:.3f} mm, max {self.tip_error_mm_max:.3f} mm")


def vendor_line(figures: dict) -> str:
    """The one line every command prints for :meth:`VendorDistance.as_dict`'s figures."""
    return (f"vs the interrogator's own shape ({figures['vendor_frames_compared']} frames, Kabsch): distance "
            f"max {figures['vendor_distance_max_mm']:.3f} mm, mean {figures['vendor_distance_mean_mm']:.3f} mm")


class _Slots:
    """The first eligible frame of each 1/``per_second`` s slot of the source's timestamps (module docstring)."""

    def __init__(self, per_second: float | None):
        if per_second is not None and not per_second > 0:
            raise ValueError(f"per_second must be positive (or None: every frame), got {per_second}")
        self.per_second = per_second
        self._last = np.nan  # slot of the last frame taken

    def take(self, eligible: np.ndarray, timestamps: np.ndarray) -> np.ndarray:
        """Indices of the frames to compare, of those ``eligible`` (bool per frame)."""
        idx = np.flatnonzero(eligible)
        if self.per_second is None or not idx.size:
            return idx
        slot = np.floor(np.asarray(timestamps, np.float64)[idx] * self.per_second)
        prev = np.concatenate([[self._last], slot[:-1]])
        new = ~(slot == prev)  # NaN (no timestamp) never equals: a slot of its own
        self._last = slot[-1]
        return idx[new]


class TruthError:
    """Live-loop sink: the shape error against the truth the frames carry (module docstring for which frames).

    Parameters
    ----------
    register : str
        Registration before comparing (:func:`twin.metrics.shape_error`).
    per_second : float or None
        Frames compared per second of source time (module docstring); None: every eligible frame.

    Attributes
    ----------
    latest : ErrorStats or None
        The last compared frame's figures (for status lines).
    note : str or None
        Why the comparison stopped (a truth that does not cover the reconstruction), once.
    seen_truth : bool
        Some frame carried a truth.
    """

    def __init__(self, register: str = "kabsch", per_second: float | None = 10.0):
        self.register = register
        self._slots = _Slots(per_second)
        self._parts: dict[str, list[np.ndarray]] = {"mean": [], "max": [], "rms": [], "tip": []}
        self.latest: ErrorStats | None = None
        self.note: str | None = None
        self.seen_truth = False

    def __call__(self, frames: Frame, shapes: Shape | None, status) -> None:
        truth = frames.truth
        if not len(frames) or truth is None:
            return
        self.seen_truth = True
        if shapes is None or self.note is not None:
            return
        sel = self._slots.take(shapes.all_valid & truth.all_present, frames.timestamp)
        if not sel.size:
            return
        try:
            e = shape_error(shapes.positions[sel], truth.positions[sel], s=shapes.s, truth_s=truth.s,
                            register=self.register)
        except ValueError as exc:
            self.note = f"truth comparison skipped: {exc}"
            return
        for k, parts in self._parts.items():
            parts.append(np.atleast_1d(getattr(e, k)))
        last = -1
        self.latest = ErrorStats(*(float(np.atleast_1d(getattr(e, k))[last]) for k in ("max", "mean", "rms", "tip")))

    @property
    def frames_compared(self) -> int:
        return int(sum(a.size for a in self._parts["mean"]))

    def result(self) -> TruthErrors | None:
        """The figures over every compared frame, or None when none was compared."""
        if not self._parts["mean"]:
            return None
        e = self.per_frame()
        return TruthErrors(
            frames_compared=int(e["mean"].size),
            register=self.register,
            mean_error_mm=_mm(e["mean"].mean()),
            max_error_mm=_mm(e["max"].max()),
            rms_error_mm=_mm(np.sqrt(np.mean(e["rms"] ** 2))),
            tip_error_mm_mean=_mm(e["tip"].mean()),
            tip_error_mm_max=_mm(e["tip"].max()),
        )

    def per_frame(self) -> dict[str, np.ndarray]:
        """Each compared frame's figures, m: ``max``, ``mean``, ``rms``, ``tip`` (k,) in the order compared."""
        return {k: np.concatenate(v) if v else np.zeros(0) for k, v in self._parts.items()}

    def status_text(self) -> str | None:
        """The latest frame's error, for a status line (None before the first comparison)."""
        e = self.latest
        if e is None:
            return None
        return f"vs truth max {e.max * 1e3:.2f} mm, tip {e.tip * 1e3:.2f} mm"


class VendorDistance:
    """Live-loop sink: the distance from our shapes to the interrogator's own (sensor ``sensor``'s blocks,
    :attr:`Frame.vendor <twin.frames.Frame.vendor>`), module docstring for which frames.

    Parameters
    ----------
    sensor : int
        Which sensor block is the fibre we reconstruct (0: the first).
    per_second : float or None
        Frames compared per second of source time (module docstring); None: every eligible frame.
    """

    def __init__(self, sensor: int = 0, per_second: float | None = 10.0):
        self.sensor = sensor
        self._slots = _Slots(per_second)
        self._max: list[np.ndarray] = []
        self._mean: list[np.ndarray] = []
        self.latest: ErrorStats | None = None
        self.skipped = 0

    def add(self, positions: np.ndarray, s: np.ndarray, vendor_positions: np.ndarray, vendor_s: np.ndarray) -> None:
        """Compare a batch: ours (n, m, 3) at ``s`` with the vendor's (n, N, 3) at ``vendor_s``."""
        if len(positions) == 0:
            return
        ok = np.isfinite(positions).all(axis=(1, 2)) & np.isfinite(vendor_positions).all(axis=(1, 2))
        if not ok.all():
            self.skipped += int(np.count_nonzero(~ok))
            positions, vendor_positions = positions[ok], vendor_positions[ok]
            if not len(positions):
                return
        e = vendor_distance(positions, s, vendor_positions, vendor_s)
        if e is None:
            self.skipped += len(positions)
            return
        self._max.append(np.atleast_1d(e.max))
        self._mean.append(np.atleast_1d(e.mean))
        self.latest = ErrorStats(*(float(np.atleast_1d(getattr(e, k))[-1]) for k in ("max", "mean", "rms", "tip")))

    def __call__(self, frames: Frame, shapes: Shape | None, status) -> None:
        v = frames.vendor
        if not len(frames) or shapes is None or not v or len(v) <= self.sensor:
            return
        arrays = v[self.sensor]
        sel = self._slots.take(arrays.present & shapes.all_valid, frames.timestamp)
        if sel.size:
            self.add(shapes.positions[sel], shapes.s, arrays.positions[sel], arrays.s)

    @property
    def frames_compared(self) -> int:
        return int(sum(a.size for a in self._max))

    def as_dict(self) -> dict:
        """``vendor_frames_compared``, ``vendor_distance_max_mm`` (largest over frames),
        ``vendor_distance_mean_mm`` (mean over frames of the mean distance); empty when nothing was compared."""
        if not self._max:
            return {}
        mx, mean = np.concatenate(self._max), np.concatenate(self._mean)
        return {"vendor_frames_compared": int(mx.size), "vendor_distance_max_mm": _mm(mx.max()),
                "vendor_distance_mean_mm": _mm(mean.mean())}

    def status_text(self) -> str | None:
        """The latest compared frame's distance, for a status line (None before the first comparison)."""
        e = self.latest
        return None if e is None else f"vs interrogator max {e.max * 1e3:.2f} mm"


class TubeFigures:
    """Live-loop sink: the confidence tube's figures (docs/figures.md) on the first complete frame of each
    1/``per_second`` s slot of the source's timestamps (the module docstring's rule; with or without a truth).

    Parameters
    ----------
    uncertainty : twin.uncertainty.Uncertainty
        For the loop's reconstructor (its model error: the twin's default unless given).
    per_second : float or None
        Frames per second of source time; None: every complete frame.
    level : float
        The tube whose coverage is counted.
    """

    def __init__(self, uncertainty, per_second: float | None = 10.0, level: float = 0.95):
        self.uncertainty = uncertainty
        self.level = level
        self._slots = _Slots(per_second)
        self._sigma: list[np.ndarray] = []  # per frame: the sum of σ over its points with s > 0
        self._points = 0
        self._inside: list[np.ndarray] = []  # per frame with a truth: true points inside the tube
        self._truth_points = 0
        self.note: str | None = None

    def __call__(self, frames: Frame, shapes: Shape | None, status) -> None:
        if not len(frames) or shapes is None:
            return
        sel = self._slots.take(shapes.all_valid, frames.timestamp)
        if not sel.size:
            return
        from twin.uncertainty import inside, truth_in_base

        out = self.uncertainty.propagate(shapes[sel], frames.wavelengths[sel])
        distal = out.s > 0  # the base point is exact by construction
        self._sigma.append(out.sigma[:, distal].sum(axis=-1))
        self._points += int(distal.sum()) * sel.size
        truth = frames.truth
        if truth is None or self.note is not None:
            return
        if truth.frames is None:
            self.note = "coverage skipped: the truth carries no material frames (its base pose)"
            return
        have = np.flatnonzero(np.broadcast_to(truth.all_present, (len(frames),))[sel])
        if not have.size:
            return
        i0 = int(np.argmin(np.abs(truth.s)))
        if abs(truth.s[i0]) > 1e-9 or truth.s[-1] < out.s[-1] - 1e-9:
            self.note = "coverage skipped: the truth does not cover the reconstruction from its base"
            return
        rows = sel[have]
        try:
            t = truth_in_base(truth.s, truth.positions[rows], truth.frames[rows, i0], truth.positions[rows, i0], out.s)
        except ValueError as e:  # too few samples for a spline through them
            self.note = f"coverage skipped: {e}"
            return
        self._inside.append(inside(out[have], t, self.level)[:, distal].sum(axis=-1))
        self._truth_points += int(distal.sum()) * have.size

    @property
    def frames(self) -> int:
        return int(sum(a.size for a in self._sigma))

    def as_dict(self) -> dict:
        """``tube_frames``, ``mean_sigma_mm`` (mean 1σ lateral radius over their points with s > 0) and, over
        those carrying a truth, ``tube_truth_frames`` and ``coverage_95`` (fraction of the true points inside
        the 95 % tube); ``tube_twist_rad_per_m`` the model error's twist term (1σ of the unmeasured twist rate,
        rad/m: ``--twist``); ``tube_note`` why coverage was skipped, ``tube_caveat`` the uncertainty's
        (:attr:`twin.uncertainty.Uncertainty.caveat`); empty when no frame was taken."""
        if not self._sigma:
            return {}
        out = {"tube_frames": self.frames, "mean_sigma_mm": _mm(np.concatenate(self._sigma).sum() / self._points),
               "tube_twist_rad_per_m": self.uncertainty.model_error.twist}
        if self._inside:
            n = np.concatenate(self._inside)
            out.update({"tube_truth_frames": int(n.size),
                        f"coverage_{round(self.level * 100)}": round(float(n.sum()) / self._truth_points, 4)})
        if self.note is not None:
            out["tube_note"] = self.note
        if self.uncertainty.caveat:
            out["tube_caveat"] = self.uncertainty.caveat
        return out


def tube_figures(rec, per_second: float | None = 10.0, twist: float = 0.0) -> TubeFigures | None:
    """:class:`TubeFigures` for the reconstructor ``rec`` with the twin's default model error, its twist term set
    to ``twist`` (1σ of the catheter's unmeasured twist rate, rad/m; :meth:`twin.uncertainty.Uncertainty.with_twist`),
    or None where the linearised propagation does not apply (:class:`twin.uncertainty.Uncertainty` says which
    methods it covers)."""
    from twin.uncertainty import Uncertainty

    try:
        uncertainty = Uncertainty(rec)
    except ValueError:
        return None
    return TubeFigures(uncertainty.with_twist(twist) if twist else uncertainty, per_second=per_second)
