"""ILLumiSense's own reconstruction beside ours: building sensor blocks from a shape (the simulator) and the
distance between the vendor's shape and our reconstruction (``twin live``, ``twin replay``).

Frame convention (docs/protocols-illumisense.md, vendor frame): our reconstructions have the base at the
origin, tangent +z and d1 (the first core's bending direction) = +x; the vendor's shape has x along the fibre
axis. The simulator maps ours to the vendor's by the cyclic permutation (x, y, z)_vendor = (z, x, y)_ours — a
proper rotation, so handedness is kept, with d1 becoming the vendor's y. The reported distance is taken after
a rigid registration, so it does not depend on this choice.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from twin.frames import Frame, Shape
from twin.io.illumisense.codec import SHAPE_SPACING, VendorSensor
from twin.metrics import ErrorStats, kabsch, shape_error

__all__ = ["VENDOR_FROM_BASE", "VendorArrays", "VendorDistance", "frame_vendor", "vendor_distance",
           "vendor_in_base", "vendor_sensors"]

#: rows map our base-frame coordinates to the vendor's: vendor = VENDOR_FROM_BASE @ ours
VENDOR_FROM_BASE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def vendor_sensors(shapes: Shape, spacing: float = SHAPE_SPACING) -> list[VendorSensor]:
    """One :class:`VendorSensor` per reconstructed shape, as ILLumiSense would send it.

    Parameters
    ----------
    shapes : Shape
        A batch (n, …) of reconstructions.
    spacing : float
        Arc length between shape points, m (1 mm like the vendor's).

    Returns
    -------
    list of VendorSensor
        Curvature |κ| (1/m) and bending angle atan2(κ_y, κ_x) (rad, material frame) at the gratings; shape
        points every ``spacing`` from the base to the last whole step, in the vendor frame (module docstring).
    """
    k = np.asarray(shapes.curvature)
    if k.ndim == 2:
        k = k[None]
    s_end = float(shapes.s[-1])
    s_v = spacing * np.arange(int(np.floor(s_end / spacing + 1e-9)) + 1)
    if s_v.size == shapes.s.size and np.allclose(s_v, shapes.s, atol=1e-12):
        p = shapes.positions
    else:
        p = shapes.positions_at(s_v)
    p = np.asarray(p).reshape(-1, s_v.size, 3) @ VENDOR_FROM_BASE.T
    mag = np.hypot(k[..., 0], k[..., 1])
    ang = np.arctan2(k[..., 1], k[..., 0])
    return [VendorSensor(mag[i], ang[i], p[i], spacing) for i in range(p.shape[0])]


@dataclass(frozen=True, eq=False)
class VendorArrays:
    """One sensor's blocks over a run of frames (a recording, or rows of it), batch-first, SI.

    Attributes
    ----------
    curvature : ndarray, shape (n, G)
        |κ| at the sensor's G gratings, 1/m; NaN where absent.
    angle : ndarray, shape (n, G)
        Bending direction at the gratings, rad; NaN where absent.
    positions : ndarray, shape (n, N, 3)
        Shape points in the vendor frame, m, ``spacing`` apart from arc length 0; NaN where absent.
    present : ndarray of bool, shape (n,)
        Frames that carried this sensor's block with this G and N.
    spacing : float
        Arc length between shape points, m.
    """

    curvature: np.ndarray
    angle: np.ndarray
    positions: np.ndarray
    present: np.ndarray
    spacing: float = SHAPE_SPACING

    @property
    def s(self) -> np.ndarray:
        """Arc length of the shape points, m, shape (N,)."""
        return self.spacing * np.arange(self.positions.shape[1])

    def __len__(self) -> int:
        return len(self.present)

    def __getitem__(self, index) -> VendorArrays:
        """Rows of the batch: ``arrays[start:stop]``, ``arrays[mask]``."""
        return VendorArrays(self.curvature[index], self.angle[index], self.positions[index], self.present[index],
                            self.spacing)

    def sensor(self, i: int) -> VendorSensor | None:
        """Row ``i`` as a :class:`VendorSensor`, or None where absent."""
        if not self.present[i]:
            return None
        return VendorSensor(self.curvature[i], self.angle[i], self.positions[i], self.spacing)

    @classmethod
    def from_sensors(cls, blocks: Sequence[VendorSensor | None], like: VendorSensor | None = None
                     ) -> VendorArrays | None:
        """Stack one sensor's blocks of consecutive frames (None: the frame had none).

        The layout (G gratings, N points, spacing) is ``like``'s, else the first block's; blocks of another
        layout are left out (``present`` False). None when no block is given and no ``like``.
        """
        ref = like if like is not None else next((b for b in blocks if b is not None), None)
        if ref is None:
            return None
        n, g, m = len(blocks), len(ref.curvature), len(ref.positions)
        rows = [i for i, b in enumerate(blocks) if b is not None and len(b.curvature) == g and len(b.angle) == g
                and b.positions.shape == (m, 3) and b.spacing == ref.spacing]
        out = cls(np.full((n, g), np.nan), np.full((n, g), np.nan), np.full((n, m, 3), np.nan), np.zeros(n, bool),
                  float(ref.spacing))
        if rows:
            out.curvature[rows] = np.stack([blocks[i].curvature for i in rows])
            out.angle[rows] = np.stack([blocks[i].angle for i in rows])
            out.positions[rows] = np.stack([blocks[i].positions for i in rows])
            out.present[rows] = True
        return out


def frame_vendor(sensors: Sequence[VendorArrays], i: int) -> tuple[VendorSensor, ...] | None:
    """:attr:`twin.frames.Frame.vendor` of row ``i``: the sensors' blocks up to the first one absent there (a
    sensor's index keeps its meaning), or None when sensor 0 is absent."""
    out = []
    for arrays in sensors:
        block = arrays.sensor(i)
        if block is None:
            break
        out.append(block)
    return tuple(out) or None


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
    if vendor_s.size < 2:
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


class VendorDistance:
    """Accumulates :func:`vendor_distance` over a run; also a live-loop sink (``sink(frames, shapes, status)``).

    Parameters
    ----------
    sensor : int
        Which sensor block is the fibre we reconstruct (0: the first).
    rate : float or None
        As a sink, compare at most this many frames per second (the comparison is not on the hot path).
    """

    def __init__(self, sensor: int = 0, rate: float | None = 10.0):
        self.sensor = sensor
        self.rate = rate
        self._max: list[np.ndarray] = []
        self._mean: list[np.ndarray] = []
        self._last = -np.inf
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

    def add_chunk(self, vendor, shapes: Shape, select: np.ndarray) -> None:
        """Compare a chunk of a recording's frames with their vendor shapes ``vendor`` (:class:`VendorArrays`
        of the compared sensor, the chunk's rows; or None: nothing to do); ``select`` (bool per frame) picks
        the frames to compare."""
        if vendor is None:
            return
        m = len(shapes)
        sel = np.flatnonzero(select & vendor.present[:m])
        if sel.size:
            self.add(shapes.positions[sel], shapes.s, vendor.positions[sel], vendor.s)

    def __call__(self, frames: Sequence[Frame] | Frame, shapes: Shape | None, status) -> None:
        # a batch Frame (the batch decoder's output) never carries sensor blocks: nothing to walk
        if shapes is None or isinstance(frames, Frame) or not frames:
            return
        now = time.monotonic()
        if self.rate is not None and now - self._last < 1.0 / self.rate:
            return
        for i in range(len(frames) - 1, -1, -1):  # the latest frame of the batch that has a vendor shape
            v = frames[i].vendor
            if v and len(v) > self.sensor and bool(np.all(shapes.valid[i])):
                vs = v[self.sensor]
                self.add(shapes.positions[i : i + 1], shapes.s, vs.positions[None], vs.s)
                self._last = now
                return

    @property
    def frames_compared(self) -> int:
        return int(sum(a.size for a in self._max))

    def as_dict(self) -> dict:
        """``vendor_frames_compared``, ``vendor_distance_max_mm`` (largest over frames),
        ``vendor_distance_mean_mm`` (mean over frames of the mean distance); empty when nothing was compared."""
        if not self._max:
            return {}
        mx, mean = np.concatenate(self._max), np.concatenate(self._mean)
        return {"vendor_frames_compared": int(mx.size), "vendor_distance_max_mm": round(float(mx.max()) * 1e3, 4),
                "vendor_distance_mean_mm": round(float(mean.mean()) * 1e3, 4)}
