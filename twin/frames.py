"""The data that flows: one interrogator sample (:class:`Frame`), one reconstruction (:class:`Shape`) and the
simulator's ground truth (:class:`Truth`). All arrays SI (m, rad, 1/m, K, s) except wavelengths (nm)."""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from twin._validate import frozen

if TYPE_CHECKING:
    from twin.io.illumisense import VendorSensor

__all__ = ["Frame", "PeakStatus", "Shape", "Truth", "stack_frames"]


class PeakStatus(enum.IntFlag):
    """Per-peak status bits carried by :attr:`Frame.status` (0 = a good peak)."""

    OK = 0
    MISSING = 1  #: no peak reported (wavelength is NaN)
    OUT_OF_SLOT = 2  #: the peak left its grating's wavelength slot (overlap with a neighbour)
    CHANNEL_ERROR = 4  #: the interrogator flagged the whole channel
    INVALID_VALUE = 8  #: a value was reported but could not be used (non-numeric, non-finite)


@dataclass(frozen=True, eq=False)
class Truth:
    """What the simulator knows exactly about one sample.

    Attributes
    ----------
    s : ndarray, shape (m,)
        Arc length of each centreline sample from the fibre base, m.
    positions : ndarray, shape (m, 3)
        The fibre centreline in world coordinates, m.
    frames : ndarray, shape (m, 3, 3) or None
        Material frames [d1 d2 d3] (columns in world coordinates) at the same samples.
    curvature : ndarray, shape (n_gratings, 2) or None
        True curvature vector (k_x, k_y) at each grating in the fibre's material frame, 1/m.
    twist : ndarray, shape (n_gratings,) or None
        Mechanical twist rate at each grating, rad/m.
    temperature : ndarray, shape (n_gratings,) or None
        Temperature change from the reference at each grating, K.
    fixture : ndarray, shape (k, 3) or None
        Centreline of the fixture (tube, groove, sheath) that shapes the catheter, m, when there is one.
    """

    s: np.ndarray
    positions: np.ndarray
    frames: np.ndarray | None = None
    curvature: np.ndarray | None = None
    twist: np.ndarray | None = None
    temperature: np.ndarray | None = None
    fixture: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Frame:
    """One interrogator sample.

    Attributes
    ----------
    wavelengths : ndarray, shape (n_gratings, n_cores)
        Peak wavelengths, nm; NaN where a peak is missing.
    timestamp : float
        Acquisition time, s (the source's clock; NaN when unknown).
    sequence : int
        Sample number from the source; a gap means lost samples (−1 when unknown).
    powers : ndarray, shape (n_gratings, n_cores) or None
        Peak powers as the interrogator reports them (dBm or arbitrary units).
    status : ndarray of uint8, shape (n_gratings, n_cores) or None
        :class:`PeakStatus` bits per peak.
    truth : Truth or None
        Ground truth, when the source is the simulator.
    vendor : tuple of VendorSensor or None
        The interrogator software's own reconstruction, when it sends one (ILLumiSense sensor blocks:
        curvature 1/m, angle rad, shape m; :class:`twin.io.illumisense.VendorSensor`).
    """

    wavelengths: np.ndarray
    timestamp: float = float("nan")
    sequence: int = -1
    powers: np.ndarray | None = None
    status: np.ndarray | None = None
    truth: Truth | None = None
    vendor: tuple[VendorSensor, ...] | None = None

    def __post_init__(self) -> None:
        w = np.asarray(self.wavelengths, dtype=np.float64)
        if w.ndim != 2:
            raise ValueError(f"Frame.wavelengths: expected shape (n_gratings, n_cores), got {w.shape}")
        object.__setattr__(self, "wavelengths", w)
        for name in ("powers", "status"):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=np.uint8 if name == "status" else np.float64)
                if v.shape != w.shape:
                    raise ValueError(f"Frame.{name}: expected shape {w.shape} like the wavelengths, got {v.shape}")
                object.__setattr__(self, name, v)

    @property
    def missing(self) -> np.ndarray:
        """Boolean (n_gratings, n_cores): peaks that are absent."""
        return np.isnan(self.wavelengths)


def stack_frames(frames: Sequence[Frame]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stack frames into batch arrays: (timestamps (n,), sequences (n,), wavelengths (n, n_gratings, n_cores))."""
    if len(frames) == 0:
        raise ValueError("stack_frames: no frames given")
    shapes = {f.wavelengths.shape for f in frames}
    if len(shapes) != 1:
        raise ValueError(f"stack_frames: frames disagree on (n_gratings, n_cores): {sorted(shapes)}")
    t = np.array([f.timestamp for f in frames], dtype=np.float64)
    seq = np.array([f.sequence for f in frames], dtype=np.int64)
    w = np.stack([f.wavelengths for f in frames])
    return t, seq, w


@dataclass(frozen=True, eq=False)
class Shape:
    """A reconstructed fibre centreline (one frame, or a batch with leading axes ``...``).

    Attributes
    ----------
    s : ndarray, shape (n_points,)
        Arc length of each point from the base, m.
    positions : ndarray, shape (..., n_points, 3)
        Centreline in the fibre's base frame (base at the origin, tangent +z, d1 = +x), m.
    frames : ndarray, shape (..., n_points, 3, 3)
        Material frames [d1 d2 d3] as columns, in the base frame.
    curvature : ndarray, shape (..., n_gratings, 2)
        Curvature vector (k_x, k_y) at each grating, 1/m, after calibration (NaN where invalid).
    grating_s : ndarray, shape (n_gratings,)
        Arc length of each grating, m.
    valid : ndarray of bool, shape (..., n_gratings)
        Gratings whose curvature could be computed; invalid ones were interpolated over.
    """

    s: np.ndarray
    positions: np.ndarray
    frames: np.ndarray
    curvature: np.ndarray
    grating_s: np.ndarray
    valid: np.ndarray

    def __post_init__(self) -> None:
        for name in ("s", "positions", "frames", "curvature", "grating_s", "valid"):
            frozen(getattr(self, name))

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self.positions.shape[:-2]

    def __len__(self) -> int:
        if not self.batch_shape:
            raise TypeError("a single Shape has no length; index a batch")
        return self.batch_shape[0]

    def __getitem__(self, index) -> Shape:
        """Index the batch axes (never the points): ``shapes[3]``, ``shapes[::10]``."""
        if not self.batch_shape:
            raise TypeError("a single Shape cannot be indexed; index a batch")
        idx = index if isinstance(index, tuple) else (index,)
        if len(idx) > len(self.batch_shape):
            raise IndexError(f"too many indices for a batch of shape {self.batch_shape}")
        return Shape(
            s=self.s,
            positions=self.positions[idx],
            frames=self.frames[idx],
            curvature=self.curvature[idx],
            grating_s=self.grating_s,
            valid=self.valid[idx],
        )

    @property
    def tip(self) -> np.ndarray:
        """Position of the last point, shape (..., 3), m."""
        return self.positions[..., -1, :]

    @property
    def all_valid(self) -> np.ndarray:
        """True where every grating of the frame was usable, shape (...)."""
        return np.all(self.valid, axis=-1)

    def positions_at(self, s) -> np.ndarray:
        """Positions at arbitrary arc lengths, shape (..., len(s), 3), m.

        Cubic Hermite interpolation between the reconstructed points, using their tangents (d3): the error is
        O(h⁴κ³) for point spacing h, far below a micrometre at the default 1 mm. ``s`` outside the reconstructed
        range is an error.
        """
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        lo, hi = self.s[0], self.s[-1]
        if np.any((s < lo - 1e-12) | (s > hi + 1e-12)):
            raise ValueError(f"positions_at: arc lengths must lie in [{lo}, {hi}] m")
        j = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, self.s.size - 2)
        h = self.s[j + 1] - self.s[j]
        t = ((s - self.s[j]) / h)[:, None]
        p0, p1 = self.positions[..., j, :], self.positions[..., j + 1, :]
        m0 = self.frames[..., j, :, 2] * h[:, None]
        m1 = self.frames[..., j + 1, :, 2] * h[:, None]
        t2, t3 = t * t, t * t * t
        return (
            (2 * t3 - 3 * t2 + 1) * p0 + (t3 - 2 * t2 + t) * m0 + (-2 * t3 + 3 * t2) * p1 + (t3 - t2) * m1
        )
