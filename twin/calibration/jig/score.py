"""The one figure of merit every jig report uses (:func:`score`), and the coverage of stated intervals
(:func:`coverage`). docs/jig.md, "Judging a calibration", defines both in words.

A jig validation gives, per held-out rotation o, grating n and curvature level κ_l, the trials of that cell.
Each cell is summarised as

* ``kappa_rms[o, n, l]``: the RMS over its trials of Δκ = |k̂| − κ, 1/m;
* ``direction_mean[o, n, l]``: the mean over its trials of the signed direction error, rad (a systematic
  rotation; trial scatter averages out). The roll used is the calibration's, or one roll fitted to the whole
  validated session (``--fit-roll``: "after one global roll").

The score is two medians over the cells: the **magnitude error**, the median of ``kappa_rms`` over the cells whose
level lies in the magnitude band, and the **direction error**, the median of |``direction_mean``| over the cells
whose level lies in the direction band. Medians, so that one bad rotation or grating does not decide it.
:func:`difference` compares two calibrations on the same cells and says how far leaving one rotation × grating
out moves the comparison (whether a difference is resolved by the table).

Bands (1/m, both ends included):

* :data:`CLINICAL` — magnitude 0.25–1.25, direction 0.8–1.25: the curvatures a needle meets in tissue. Use it
  when the grooves include them.
* :data:`ALL_LEVELS` — magnitude every bent level, direction ≥ 0.8: the figures a calibration table gives
  (the AMIRo tables' grooves are 0.5–4 1/m, so only one of their levels is clinical, and none in the
  direction band).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: z of a two-sided 95 % normal interval.
Z95 = 1.959963984540054


@dataclass(frozen=True)
class Bands:
    """Curvature bands of the score, 1/m, both ends included."""

    name: str
    magnitude: tuple[float, float]
    direction: tuple[float, float]


CLINICAL = Bands("clinical", (0.25, 1.25), (0.8, 1.25))
ALL_LEVELS = Bands("all levels", (0.0, np.inf), (0.8, np.inf))


@dataclass(frozen=True)
class JigScore:
    """The score of one validation (module docstring).

    Attributes
    ----------
    magnitude_error : float or None
        Median per-cell RMS |Δκ| over the magnitude band, 1/m (None: no cell in the band).
    direction_error : float or None
        Median per-cell |mean Δdir| over the direction band, rad.
    bands : Bands
    n_magnitude, n_direction : int
        Cells in each median.
    """

    magnitude_error: float | None
    direction_error: float | None
    bands: Bands
    n_magnitude: int
    n_direction: int

    def to_dict(self) -> dict:
        """JSON-ready (1/m, deg)."""
        return {
            "bands": self.bands.name,
            "magnitude_band_1_per_m": list(self.bands.magnitude),
            "direction_band_1_per_m": list(self.bands.direction),
            "magnitude_error_1_per_m": self.magnitude_error,
            "direction_error_deg": None if self.direction_error is None else float(np.rad2deg(self.direction_error)),
            "n_magnitude_cells": self.n_magnitude,
            "n_direction_cells": self.n_direction,
        }


def cells(orientation, curvature, magnitude_error, direction_error, orientations=None, levels=None):
    """Per rotation × grating × level summaries of a validation's poses.

    Parameters
    ----------
    orientation, curvature : array_like, shape (P,)
        ψ (rad) and κ (1/m) of each bent pose.
    magnitude_error, direction_error : array_like, shape (P, G)
        Δκ (1/m) and signed direction error (rad); NaN where unsolved.
    orientations, levels : array_like, optional
        The rotations and levels to tabulate (default: those present); a missing cell is NaN.

    Returns
    -------
    orientations (O,), levels (L,), kappa_rms (O, G, L), direction_mean (O, G, L)
    """
    orientation = np.asarray(orientation, dtype=np.float64)
    kappa = np.abs(np.asarray(curvature, dtype=np.float64))
    mag = np.asarray(magnitude_error, dtype=np.float64)
    ang = np.asarray(direction_error, dtype=np.float64)
    o_all = np.unique(orientation) if orientations is None else np.asarray(orientations, dtype=np.float64)
    l_all = np.unique(kappa) if levels is None else np.asarray(levels, dtype=np.float64)
    oi = np.argmin(np.abs(orientation[:, None] - o_all[None, :]), axis=1)
    li = np.argmin(np.abs(kappa[:, None] - l_all[None, :]), axis=1)
    cell = oi * l_all.size + li
    n_cells = o_all.size * l_all.size
    ok = np.isfinite(mag)
    onehot = np.eye(n_cells)[cell]  # (P, O·L)
    n = np.einsum("pc,pg->cg", onehot, ok.astype(float))
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.einsum("pc,pg->cg", onehot, np.where(ok, mag**2, 0.0)) / n)
        mean = np.einsum("pc,pg->cg", onehot, np.where(ok, ang, 0.0)) / n
    shape = (o_all.size, l_all.size, mag.shape[1])
    return (o_all, l_all, np.transpose(rms.reshape(shape), (0, 2, 1)),
            np.transpose(mean.reshape(shape), (0, 2, 1)))


def score(levels, kappa_rms, direction_mean, bands: Bands = CLINICAL) -> JigScore:
    """The score of per-cell summaries (:func:`cells`): two medians over the cells in the bands.

    Parameters
    ----------
    levels : array_like, shape (L,)
        1/m.
    kappa_rms, direction_mean : array_like, shape (..., L)
        Per-cell RMS |Δκ| (1/m) and mean direction error (rad); NaN cells are skipped.
    bands : Bands
    """
    levels = np.asarray(levels, dtype=np.float64)
    k = np.asarray(kappa_rms, dtype=np.float64)
    d = np.asarray(direction_mean, dtype=np.float64)

    def median(values, band):
        inside = (levels >= band[0]) & (levels <= band[1])
        v = values[..., inside]
        v = v[np.isfinite(v)]
        return (float(np.median(v)) if v.size else None), int(v.size)

    m, n_m = median(k, bands.magnitude)
    a, n_a = median(np.abs(d), bands.direction)
    return JigScore(magnitude_error=m, direction_error=a, bands=bands, n_magnitude=n_m, n_direction=n_a)


def coverage(error, sigma, z: float = Z95) -> tuple[float | None, int]:
    """Fraction of errors inside their stated interval ±z·σ, and how many were judged.

    Parameters
    ----------
    error, sigma : array_like, same shape
        Signed errors and their stated 1σ (same unit); pairs with a NaN or a non-positive σ are skipped.
    z : float
        Interval half-width in σ (default: the two-sided 95 % normal one).
    """
    error = np.asarray(error, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    ok = np.isfinite(error) & np.isfinite(sigma) & (sigma > 0)
    n = int(ok.sum())
    if n == 0:
        return None, 0
    return float(np.mean(np.abs(error[ok]) <= z * sigma[ok])), n


@dataclass(frozen=True)
class ScoreDifference:
    """The score of one calibration minus another's on the same validation cells (:func:`difference`), and how
    far one cluster moves it.

    Attributes
    ----------
    magnitude, direction : float or None
        Difference of the magnitude errors (1/m) and of the direction errors (rad); negative: the first is better.
    magnitude_range, direction_range : (float, float) or None
        Smallest and largest difference when the cells of one rotation × grating (a cluster: one zero, one roll)
        are left out in turn. A difference whose range straddles 0 is not resolved by this table.
    n_clusters : int
    """

    magnitude: float | None
    direction: float | None
    magnitude_range: tuple[float, float] | None = None
    direction_range: tuple[float, float] | None = None
    n_clusters: int = 0

    def to_dict(self) -> dict:
        """JSON-ready (1/m, deg)."""
        def deg(x):
            return None if x is None else float(np.rad2deg(x))

        return {
            "magnitude_1_per_m": self.magnitude,
            "direction_deg": deg(self.direction),
            "magnitude_range_1_per_m": None if self.magnitude_range is None else list(self.magnitude_range),
            "direction_range_deg": None if self.direction_range is None else [deg(x) for x in self.direction_range],
            "n_clusters": self.n_clusters,
        }


def difference(levels, a_rms, a_mean, b_rms, b_mean, bands: Bands = CLINICAL) -> ScoreDifference:
    """Score of calibration a minus that of b (per-cell summaries of :func:`cells` on the same poses, shape
    (O, G, L)), with its range over leaving one rotation × grating out.

    The cells of one rotation and grating share that rotation's zero and roll, so they are not independent: one such
    cluster can move a median by a few tenths of a degree. The range says whether a difference outlives that.
    """
    a_rms, a_mean, b_rms, b_mean = (np.asarray(x, dtype=np.float64) for x in (a_rms, a_mean, b_rms, b_mean))

    # only cells both calibrations scored: medians over different cells would compare different poses
    rms_both = np.isfinite(a_rms) & np.isfinite(b_rms)
    mean_both = np.isfinite(a_mean) & np.isfinite(b_mean)

    def diff(keep):
        kr, km = keep & rms_both, keep & mean_both
        sa = score(levels, np.where(kr, a_rms, np.nan), np.where(km, a_mean, np.nan), bands)
        sb = score(levels, np.where(kr, b_rms, np.nan), np.where(km, b_mean, np.nan), bands)
        return tuple(None if x is None or y is None else x - y for x, y in
                     ((sa.magnitude_error, sb.magnitude_error), (sa.direction_error, sb.direction_error)))

    n_o, n_g = a_rms.shape[:2]
    full = diff(np.ones(a_rms.shape, bool))
    left = []
    for o in range(n_o):  # a few rotations × gratings
        for n in range(n_g):
            keep = np.ones(a_rms.shape, bool)
            keep[o, n] = False
            left.append(diff(keep))
    ranges = []
    for i in range(2):
        v = [x[i] for x in left if x[i] is not None]
        ranges.append((float(min(v)), float(max(v))) if v and full[i] is not None else None)
    return ScoreDifference(magnitude=full[0], direction=full[1], magnitude_range=ranges[0],
                           direction_range=ranges[1], n_clusters=n_o * n_g)
