"""The data that flows: interrogator samples (:class:`Frame`), reconstructions (:class:`Shape`) and the
simulator's ground truth (:class:`Truth`). All arrays SI (m, rad, 1/m, K, s) except wavelengths (nm).

All three are batch-first: one object holds one sample or a batch with leading axes ``...`` (a recording, a
burst read from a socket, the frames of a calibration step). A batch has ``len``, iterates over single items and
is indexed along its batch axes only (``frames[3]``, ``frames[100:200]``, ``frames[mask]``);
:meth:`Frame.stack` builds a batch from single frames (or concatenates batches).
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from twin._validate import frozen

__all__ = ["VENDOR_SHAPE_SPACING", "Frame", "PeakStatus", "Shape", "Truth", "VendorArrays", "VendorSensor",
           "frame_vendor", "vendor_rows"]

VENDOR_SHAPE_SPACING = 1e-3  #: m between an interrogator's own shape points (ILLumiSense's public client)


class PeakStatus(enum.IntFlag):
    """Per-peak status bits carried by :attr:`Frame.status` (0 = a good peak)."""

    OK = 0
    MISSING = 1  #: no peak reported (wavelength is NaN)
    OUT_OF_SLOT = 2  #: the peak left its grating's wavelength slot (overlap with a neighbour)
    CHANNEL_ERROR = 4  #: the interrogator flagged the whole channel
    INVALID_VALUE = 8  #: a value was reported but could not be used (non-numeric, non-finite)


#: Truth's per-sample fields and how many trailing (non-batch) axes each has
_TRUTH_FIELDS = {"positions": 2, "frames": 3, "curvature": 2, "twist": 1, "temperature": 1}


def _batch_index(index, batch_shape: tuple[int, ...], what: str) -> tuple:
    if not batch_shape:
        raise TypeError(f"a single {what} cannot be indexed; index a batch")
    idx = index if isinstance(index, tuple) else (index,)
    if len(idx) > len(batch_shape) or any(i is Ellipsis or i is None for i in idx):
        raise IndexError(f"{what}: index the batch axes {batch_shape} only (no Ellipsis, no new axes)")
    return idx


@dataclass(frozen=True, eq=False)
class Truth:
    """What the simulator knows exactly about one sample, or about a batch of samples (leading axes ``...``).

    Attributes
    ----------
    s : ndarray, shape (m,)
        Arc length of each centreline sample from the fibre base, m (shared by a batch).
    positions : ndarray, shape (..., m, 3)
        The fibre centreline in world coordinates, m.
    frames : ndarray, shape (..., m, 3, 3) or None
        Material frames [d1 d2 d3] (columns in world coordinates) at the same samples.
    curvature : ndarray, shape (..., n_gratings, 2) or None
        True curvature vector (k_x, k_y) at each grating in the fibre's material frame, 1/m.
    twist : ndarray, shape (..., n_gratings) or None
        Mechanical twist rate at each grating, rad/m.
    temperature : ndarray, shape (..., n_gratings) or None
        Temperature change from the reference at each grating, K.
    fixture : ndarray, shape (k, 3) or None
        Centreline of the fixture (tube, groove, sheath) that shapes the catheter, m, when there is one (a
        batch keeps its first sample's).
    present : ndarray of bool, shape (...) or None
        Batches only: which samples carry a truth (the arrays are NaN where not); None means all.
    """

    s: np.ndarray
    positions: np.ndarray
    frames: np.ndarray | None = None
    curvature: np.ndarray | None = None
    twist: np.ndarray | None = None
    temperature: np.ndarray | None = None
    fixture: np.ndarray | None = None
    present: np.ndarray | None = None

    def __post_init__(self) -> None:
        batch = self.batch_shape
        for name, trailing in _TRUTH_FIELDS.items():
            v = getattr(self, name)
            if v is not None and np.shape(v)[: max(0, np.ndim(v) - trailing)] != batch:
                raise ValueError(f"Truth.{name}: expected the batch shape {batch} of the positions, got "
                                 f"{np.shape(v)}")
        if self.present is not None:
            p = np.asarray(self.present, dtype=bool)
            if p.shape != batch:
                raise ValueError(f"Truth.present: expected shape {batch}, got {p.shape}")
            object.__setattr__(self, "present", None if not batch else p)

    @classmethod
    def _trusted(cls, s: np.ndarray, positions: np.ndarray, frames: np.ndarray, curvature: np.ndarray,
                 twist: np.ndarray, temperature: np.ndarray, fixture: np.ndarray | None) -> Truth:
        """A single Truth built WITHOUT the checks of ``__post_init__`` (private, for the simulator's hot path,
        :class:`models.rod_state.RodTruth`, where they cost as much as the arithmetic). The caller guarantees
        one sample: ``positions`` (m, 3), ``frames`` (m, 3, 3), ``curvature`` (n_g, 2), ``twist`` and
        ``temperature`` (n_g,), float64; no ``present``. Nothing is checked."""
        obj = object.__new__(cls)
        # a frozen dataclass refuses setattr; its fields live in the instance dict all the same
        obj.__dict__.update(s=s, positions=positions, frames=frames, curvature=curvature, twist=twist,
                            temperature=temperature, fixture=fixture, present=None)
        return obj

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(np.shape(self.positions)[:-2])

    def __len__(self) -> int:
        if not self.batch_shape:
            raise TypeError("a single Truth has no length; index a batch")
        return self.batch_shape[0]

    def __getitem__(self, index) -> Truth:
        """Index the batch axes: ``truth[3]``, ``truth[10:20]`` (a single item of an absent row is all NaN)."""
        idx = _batch_index(index, self.batch_shape, "Truth")
        kw = {name: None if getattr(self, name) is None else getattr(self, name)[idx] for name in _TRUTH_FIELDS}
        present = None if self.present is None else self.present[idx]
        return Truth(s=self.s, fixture=self.fixture, present=present if np.ndim(present) else None, **kw)

    @property
    def all_present(self) -> np.ndarray | bool:
        """Whether each sample carries a truth, shape (...) (True for a single truth)."""
        if self.present is None:
            return np.ones(self.batch_shape, bool) if self.batch_shape else True
        return self.present

    def same_layout(self, other: Truth) -> bool:
        """Same arc lengths and the same fields with the same per-sample shapes (batch axes aside)."""
        if other is self:
            return True
        if np.shape(self.s) != np.shape(other.s) or not np.array_equal(self.s, other.s):
            return False
        for name, trailing in _TRUTH_FIELDS.items():
            a, b = getattr(self, name), getattr(other, name)
            if (a is None) != (b is None):
                return False
            if a is not None and np.shape(a)[np.ndim(a) - trailing:] != np.shape(b)[np.ndim(b) - trailing:]:
                return False
        return True

    @classmethod
    def stack(cls, truths: Sequence[Truth | None], counts: Sequence[int] | None = None, *,
              like: Truth | None = None) -> Truth | None:
        """Concatenate truths (single ones, or 1-D batches) into one 1-D batch; None entries become absent rows.

        Parameters
        ----------
        truths : sequence of Truth or None
        counts : sequence of int, optional
            Rows each entry stands for (needed for None entries that stand for batches; default 1 or the
            entry's length).
        like : Truth, optional
            The layout to keep (:meth:`same_layout`): entries of another layout become absent rows instead of
            raising. Default: the first entry's, and another layout is an error.

        Returns
        -------
        Truth or None
            None when no entry carries a truth.
        """
        ref = like if like is not None else next((t for t in truths if t is not None), None)
        if ref is None:
            return None
        if counts is None:
            counts = [1 if t is None or not t.batch_shape else len(t) for t in truths]
        n = int(sum(counts))
        present = np.zeros(n, bool)
        out = {}
        for name, trailing in _TRUTH_FIELDS.items():
            v = getattr(ref, name)
            if v is not None:
                tail = np.shape(v)[np.ndim(v) - trailing:]
                out[name] = np.full((n, *tail), np.nan, dtype=np.result_type(np.asarray(v).dtype, np.float32))
        row = 0
        for i, (t, k) in enumerate(zip(truths, counts, strict=True)):
            if t is not None:
                if not t.same_layout(ref):
                    if like is None:
                        raise ValueError(f"Truth.stack: truth {i} has another layout (arc lengths or fields) than "
                                         "the first")
                else:
                    sl = slice(row, row + k) if t.batch_shape else row
                    for name in out:
                        out[name][sl] = getattr(t, name)
                    present[sl] = t.all_present
            row += k
        return cls(s=ref.s, fixture=ref.fixture, present=present, **out)


@dataclass(frozen=True, eq=False)
class VendorSensor:
    """One sensor of one frame as the interrogator's own software reconstructed it (ILLumiSense sensor
    blocks), in SI.

    Attributes
    ----------
    curvature : ndarray, shape (G,)
        Curvature magnitude at the sensor's gratings, 1/m.
    angle : ndarray, shape (G,)
        Bending direction at the gratings, rad.
    positions : ndarray, shape (N, 3)
        Shape points in the vendor's frame (x along the fibre axis), m, ``spacing`` apart in arc length from
        the sensor's start.
    spacing : float
        Arc length between shape points, m (1 mm, as the public client assumes).
    """

    curvature: np.ndarray
    angle: np.ndarray
    positions: np.ndarray
    spacing: float = VENDOR_SHAPE_SPACING

    @property
    def s(self) -> np.ndarray:
        """Arc length of each shape point, m, shape (N,)."""
        return self.spacing * np.arange(self.positions.shape[0])


@dataclass(frozen=True, eq=False)
class VendorArrays:
    """One sensor's blocks over a batch of frames (a burst, a recording, rows of it), batch-first, SI: what
    :attr:`Frame.vendor` holds for a batch, one per sensor.

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
    spacing: float = VENDOR_SHAPE_SPACING

    @property
    def s(self) -> np.ndarray:
        """Arc length of the shape points, m, shape (N,)."""
        return self.spacing * np.arange(self.positions.shape[1])

    @property
    def layout(self) -> tuple[int, int, float]:
        """(G gratings, N shape points, spacing): blocks of one layout stack into one array."""
        return self.curvature.shape[1], self.positions.shape[1], float(self.spacing)

    def __len__(self) -> int:
        return len(self.present)

    def __getitem__(self, index) -> VendorArrays:
        """Rows of the batch: ``arrays[start:stop]``, ``arrays[mask]`` (:meth:`sensor` for one row)."""
        return VendorArrays(self.curvature[index], self.angle[index], self.positions[index], self.present[index],
                            self.spacing)

    def sensor(self, i: int) -> VendorSensor | None:
        """Row ``i`` as a :class:`VendorSensor`, or None where absent."""
        if not self.present[i]:
            return None
        return VendorSensor(self.curvature[i], self.angle[i], self.positions[i], self.spacing)

    @classmethod
    def absent(cls, n: int, layout: tuple[int, int, float]) -> VendorArrays:
        """n rows without a block, of the given :attr:`layout`."""
        g, m, spacing = layout
        return cls(np.full((n, g), np.nan), np.full((n, g), np.nan), np.full((n, m, 3), np.nan), np.zeros(n, bool),
                   float(spacing))

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
        out = cls.absent(n, (g, m, ref.spacing))
        if rows:
            out.curvature[rows] = np.stack([blocks[i].curvature for i in rows])
            out.angle[rows] = np.stack([blocks[i].angle for i in rows])
            out.positions[rows] = np.stack([blocks[i].positions for i in rows])
            out.present[rows] = True
        return out

    @classmethod
    def concat(cls, parts: Sequence[VendorArrays | None], counts: Sequence[int],
               layout: tuple[int, int, float] | None = None) -> VendorArrays | None:
        """Rows of consecutive batches (``counts`` rows each) as one, in ``layout`` (default: the first part's);
        a part that is None or of another layout gives absent rows. None when no part has one and no layout
        is given."""
        ref = next((p for p in parts if p is not None), None)
        if ref is None and layout is None:
            return None
        lay = layout if layout is not None else ref.layout
        pieces = [p if p is not None and p.layout == lay else cls.absent(k, lay)
                  for p, k in zip(parts, counts, strict=True)]
        if len(pieces) == 1:
            return pieces[0]
        return cls(*(np.concatenate([getattr(p, k) for p in pieces]) for k in ("curvature", "angle", "positions",
                                                                                 "present")), lay[2])


def frame_vendor(sensors: Sequence[VendorArrays], i: int) -> tuple[VendorSensor, ...] | None:
    """:attr:`Frame.vendor` of row ``i`` of a batch: the sensors' blocks up to the first one absent there (a
    sensor's index keeps its meaning), or None when sensor 0 is absent."""
    out = []
    for arrays in sensors:
        block = arrays.sensor(i)
        if block is None:
            break
        out.append(block)
    return tuple(out) or None


def vendor_rows(frame: Frame) -> tuple[VendorArrays, ...]:
    """A single frame's (one row) or a 1-D batch's sensor blocks as one :class:`VendorArrays` per sensor
    (empty when it carries none)."""
    if not frame.vendor:
        return ()
    if frame.batch_shape:
        return tuple(frame.vendor)
    return tuple(VendorArrays.from_sensors([b]) for b in frame.vendor)



@dataclass(frozen=True, eq=False)
class Frame:
    """One interrogator sample, or a batch of samples (leading axes ``...``, like :class:`Shape`).

    Attributes
    ----------
    wavelengths : ndarray, shape (..., n_gratings, n_cores)
        Peak wavelengths, nm; NaN where a peak is missing.
    timestamp : float, or ndarray shape (...)
        Acquisition time, s (the source's clock; NaN when unknown).
    sequence : int, or ndarray of int64 shape (...)
        Sample number from the source; a gap means lost samples (−1 when unknown).
    powers : ndarray, shape (..., n_gratings, n_cores) or None
        Peak powers as the interrogator reports them (dBm or arbitrary units).
    status : ndarray of uint8, shape (..., n_gratings, n_cores) or None
        :class:`PeakStatus` bits per peak.
    truth : Truth or None
        Ground truth, when the source is the simulator (a batched :class:`Truth` for a batch).
    vendor : tuple of VendorSensor, tuple of VendorArrays, or None
        The interrogator software's own reconstruction, when it sends one (ILLumiSense sensor blocks:
        curvature 1/m, angle rad, shape m), one item per sensor: a :class:`VendorSensor` each for a single
        frame, a :class:`VendorArrays` each (rows with ``present``) for a 1-D batch, which indexing and
        :meth:`stack` carry along like the truth.
    """

    wavelengths: np.ndarray
    timestamp: float | np.ndarray = float("nan")
    sequence: int | np.ndarray = -1
    powers: np.ndarray | None = None
    status: np.ndarray | None = None
    truth: Truth | None = None
    vendor: tuple[VendorSensor, ...] | tuple[VendorArrays, ...] | None = None

    def __post_init__(self) -> None:
        w = np.asarray(self.wavelengths, dtype=np.float64)
        if w.ndim < 2:
            raise ValueError(f"Frame.wavelengths: expected shape (..., n_gratings, n_cores), got {w.shape}")
        object.__setattr__(self, "wavelengths", w)
        batch = w.shape[:-2]
        if batch:
            t = np.broadcast_to(np.asarray(self.timestamp, dtype=np.float64), batch)
            q = np.broadcast_to(np.asarray(self.sequence, dtype=np.int64), batch)
            object.__setattr__(self, "timestamp", t)
            object.__setattr__(self, "sequence", q)
        else:
            object.__setattr__(self, "timestamp", float(self.timestamp))
            object.__setattr__(self, "sequence", int(self.sequence))
        for name in ("powers", "status"):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=np.uint8 if name == "status" else np.float64)
                if v.shape != w.shape:
                    raise ValueError(f"Frame.{name}: expected shape {w.shape} like the wavelengths, got {v.shape}")
                object.__setattr__(self, name, v)
        if self.truth is not None and self.truth.batch_shape != batch:
            raise ValueError(f"Frame.truth: expected the batch shape {batch} of the wavelengths, got "
                             f"{self.truth.batch_shape}")

    @classmethod
    def _trusted(cls, wavelengths: np.ndarray, timestamp, sequence, powers: np.ndarray | None = None,
                 status: np.ndarray | None = None, vendor: tuple | None = None, truth: Truth | None = None) -> Frame:
        """A Frame built WITHOUT the checks and conversions of ``__post_init__`` (private, for decoders and the
        simulator).

        The caller guarantees what ``__post_init__`` would establish: ``wavelengths`` float64 of shape
        (..., n_gratings, n_cores); ``powers`` float64 and ``status`` uint8 of the same shape, or None; for a
        single frame ``timestamp`` a Python float and ``sequence`` a Python int, for a batch float64 and int64
        arrays of the batch shape; a ``truth`` of the same batch shape, or None. The ILLumiSense decoder and the
        simulator (:class:`sim_interrogator.sim.SimInterrogator`) use it on their hot paths (the checks cost
        1.5–4 µs a frame, more than decoding the record); nothing here catches a wrong argument.
        """
        f = object.__new__(cls)
        # a frozen dataclass refuses setattr; its fields live in the instance dict all the same
        f.__dict__.update(wavelengths=wavelengths, timestamp=timestamp, sequence=sequence, powers=powers,
                          status=status, truth=truth, vendor=vendor)
        return f

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self.wavelengths.shape[:-2]

    @property
    def missing(self) -> np.ndarray:
        """Boolean (..., n_gratings, n_cores): peaks that are absent."""
        return np.isnan(self.wavelengths)

    @property
    def status_or_missing(self) -> np.ndarray:
        """:attr:`status`, or (without one) :attr:`PeakStatus.MISSING` where a peak is NaN; uint8 like the
        wavelengths."""
        if self.status is not None:
            return self.status
        return np.where(self.missing, np.uint8(PeakStatus.MISSING), np.uint8(0))

    def __len__(self) -> int:
        if not self.batch_shape:
            raise TypeError("a single Frame has no length; index a batch")
        return self.batch_shape[0]

    def __bool__(self) -> bool:
        # a single frame is something; a batch is something when it is not empty
        return not self.batch_shape or self.batch_shape[0] > 0

    def __iter__(self) -> Iterator[Frame]:
        """The single frames of a 1-D batch, in order."""
        if len(self.batch_shape) != 1:
            raise TypeError(f"iterate a 1-D batch of frames (batch shape {self.batch_shape})")
        return (self[i] for i in range(len(self)))

    def __getitem__(self, index) -> Frame:
        """Index the batch axes (never gratings or cores): ``frames[3]``, ``frames[::10]``, ``frames[mask]``.

        A single frame of a batch whose truth is absent there (:attr:`Truth.present`) has ``truth`` None.
        """
        idx = _batch_index(index, self.batch_shape, "Frame")
        truth = None
        if self.truth is not None:
            truth = self.truth[idx]
            if not truth.batch_shape and self.truth.present is not None and not self.truth.present[idx]:
                truth = None
        w = self.wavelengths[idx]
        vendor = None
        if self.vendor:  # a batch's VendorArrays per sensor: rows for a batch, the blocks of one frame
            vendor = frame_vendor(self.vendor, idx[0]) if w.ndim == 2 else tuple(a[idx] for a in self.vendor)
        return Frame(
            wavelengths=w,
            timestamp=self.timestamp[idx],
            sequence=self.sequence[idx],
            powers=None if self.powers is None else self.powers[idx],
            status=None if self.status is None else self.status[idx],
            truth=truth,
            vendor=vendor,
        )

    @classmethod
    def stack(cls, frames: Sequence[Frame], *, truth_like: Truth | None = None) -> Frame:
        """One 1-D batch from single frames (or from 1-D batches, concatenated in order).

        Parameters
        ----------
        frames : sequence of Frame
            All with the same (n_gratings, n_cores).
        truth_like : Truth, optional
            Keep truths of this layout and leave the others out (their rows absent in ``truth.present``);
            default: all truths must share the first one's layout.

        Returns
        -------
        Frame
            Batch shape (n,). Powers are NaN and status :attr:`status_or_missing` for frames given without;
            ``truth`` is None when no frame carries one; ``vendor`` (one :class:`VendorArrays` per sensor,
            in the layout of each sensor's first block; rows of frames without it, or of another layout,
            absent) is None when no frame carries one.

        Raises
        ------
        ValueError
            No frames, frames of different (n_gratings, n_cores), or (without ``truth_like``) truths of
            different layouts.
        """
        if isinstance(frames, Frame):
            return frames
        if len(frames) == 0:
            raise ValueError("Frame.stack: no frames given")
        if len(frames) == 1 and len(frames[0].batch_shape) == 1 and truth_like is None:
            return frames[0]  # one 1-D batch: already what is asked for (frames are immutable)
        shapes = {f.wavelengths.shape[-2:] for f in frames}
        if len(shapes) != 1:
            raise ValueError(f"Frame.stack: frames disagree on (n_gratings, n_cores): {sorted(shapes)}")
        if any(len(f.batch_shape) > 1 for f in frames):
            raise ValueError("Frame.stack: frames must be single frames or 1-D batches")

        def rows(get):
            return [get(f) if f.batch_shape else get(f)[None] for f in frames]

        w = np.concatenate(rows(lambda f: f.wavelengths))
        t = np.concatenate([np.atleast_1d(f.timestamp) for f in frames])
        q = np.concatenate([np.atleast_1d(f.sequence) for f in frames])
        powers = status = truth = None
        if any(f.powers is not None for f in frames):
            powers = np.concatenate(rows(lambda f: f.powers if f.powers is not None
                                         else np.full(f.wavelengths.shape, np.nan)))
        if any(f.status is not None for f in frames):
            status = np.concatenate(rows(lambda f: f.status_or_missing))
        if any(f.truth is not None for f in frames):
            counts = [len(f) if f.batch_shape else 1 for f in frames]
            truth = Truth.stack([f.truth for f in frames], counts, like=truth_like)
        vendor = None
        if any(f.vendor for f in frames):
            counts = [len(f) if f.batch_shape else 1 for f in frames]
            rows = [vendor_rows(f) for f in frames]
            n_sensors = max(len(r) for r in rows)
            vendor = tuple(VendorArrays.concat([r[k] if k < len(r) else None for r in rows], counts)
                           for k in range(n_sensors))
        return cls(w, t, q, powers, status, truth, vendor)


@dataclass(frozen=True, eq=False)
class Shape:
    """A reconstructed fibre centreline (one frame, or a batch with leading axes ``...``).

    Attributes
    ----------
    s : ndarray, shape (n_points,)
        Arc length of each point from the base, m.
    positions : ndarray, shape (..., n_points, 3)
        Centreline in the fibre's base frame (base at the origin, tangent +z, d1 = +x), m.
    frames : ndarray, shape (..., n_points, 3, 3), or None
        Material frames [d1 d2 d3] as columns, in the base frame; None when the reconstruction was asked for
        positions only (``Reconstructor(...)(w, frames=False)``).
    curvature : ndarray, shape (..., n_gratings, 2)
        Curvature vector (k_x, k_y) at each grating, 1/m, after calibration (NaN where invalid).
    grating_s : ndarray, shape (n_gratings,)
        Arc length of each grating, m.
    valid : ndarray of bool, shape (..., n_gratings)
        Gratings whose curvature could be computed; invalid ones were interpolated over.
    covariance : ndarray, shape (..., n_points, 3, 3) or None
        Position covariance of each point, m², when the shape carries its uncertainty
        (:class:`twin.uncertainty.Uncertainty`); see :attr:`sigma` and :meth:`confidence`.
    curvature_covariance : ndarray, shape (..., n_gratings, 2, 2) or None
        Covariance of the curvature vector at each grating, (1/m)², with ``covariance``.
    """

    s: np.ndarray
    positions: np.ndarray
    frames: np.ndarray | None
    curvature: np.ndarray
    grating_s: np.ndarray
    valid: np.ndarray
    covariance: np.ndarray | None = None
    curvature_covariance: np.ndarray | None = None

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if getattr(self, f.name) is not None:
                frozen(getattr(self, f.name))

    @classmethod
    def _trusted(cls, s, positions, frames, curvature, grating_s, valid) -> Shape:
        """A Shape built without the dataclass machinery (private, for the reconstructor's hot path, where the
        dataclass's init cost as much as the arithmetic): ``positions``, ``frames`` (or None), ``curvature`` and
        ``valid`` are new arrays of the documented shapes and get frozen here; ``s`` and ``grating_s`` are read-only
        already; other fields take their defaults. Nothing is checked."""
        obj = object.__new__(cls)
        d = obj.__dict__
        d.update(_SHAPE_DEFAULTS)
        d["s"] = s
        d["positions"] = positions
        d["frames"] = frames
        d["curvature"] = curvature
        d["grating_s"] = grating_s
        d["valid"] = valid
        positions.setflags(write=False)
        curvature.setflags(write=False)
        valid.setflags(write=False)
        if frames is not None:
            frames.setflags(write=False)
        return obj

    def _with_uncertainty(self, covariance: np.ndarray, curvature_covariance: np.ndarray) -> Shape:
        """This Shape with ``covariance`` and ``curvature_covariance`` (new arrays of the documented shapes,
        frozen here), built as :meth:`_trusted` is (private, for :class:`twin.uncertainty.Uncertainty`'s hot
        path). Nothing is checked."""
        obj = object.__new__(type(self))
        obj.__dict__.update(self.__dict__)
        obj.__dict__["covariance"] = covariance
        obj.__dict__["curvature_covariance"] = curvature_covariance
        covariance.setflags(write=False)
        curvature_covariance.setflags(write=False)
        return obj

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
            frames=None if self.frames is None else self.frames[idx],
            curvature=self.curvature[idx],
            grating_s=self.grating_s,
            valid=self.valid[idx],
            covariance=None if self.covariance is None else self.covariance[idx],
            curvature_covariance=None if self.curvature_covariance is None else self.curvature_covariance[idx],
        )

    @property
    def sigma(self) -> np.ndarray:
        """1σ lateral radius of each point, m, shape (..., n_points): √(tr Σ_⊥ / 2), the per-axis standard
        deviation of the position error in the plane normal to the curve (Σ_⊥, :meth:`confidence`). Needs
        :attr:`covariance`."""
        from twin.tube import lateral_eigenvalues

        return np.sqrt(lateral_eigenvalues(self._covariance(), self.frames[..., :, 2]).mean(axis=-1))

    def confidence(self, level: float = 0.95) -> np.ndarray:
        """Radius of the level-% confidence tube at each point, m, shape (..., n_points).

        The tube's cross-section at a point is the circle, normal to the curve, that holds ``level`` of the
        point's lateral error: the position error projected on the normal plane, a 2-D Gaussian of covariance
        Σ_⊥ (the linearised propagation; :func:`twin.tube.tube_radius`). The error along the tangent does
        not move a point out of a tube, so it is left out. Needs :attr:`covariance`."""
        from twin.tube import tube_radius

        return tube_radius(self._covariance(), self.frames[..., :, 2], level)

    def _covariance(self) -> np.ndarray:
        if self.covariance is None:
            raise ValueError("this Shape carries no uncertainty; reconstruct with twin.uncertainty.Uncertainty")
        return self.covariance

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
        if self.frames is None:
            raise ValueError("positions_at needs the tangents: reconstruct with frames=True")
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


#: the defaults of Shape's optional fields, for :meth:`Shape._trusted`
_SHAPE_DEFAULTS = {f.name: f.default for f in dataclasses.fields(Shape) if f.default is not dataclasses.MISSING}
