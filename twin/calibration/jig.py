"""Jig calibration: known constant-curvature grooves at known rotations → a calibration you can trust (docs/jig.md).

A lab presses the sensor into grooves of known constant curvature κ on a plate, at several known rotations ψ of
the sensor about its own axis, with a zero-curvature (flat groove) reference at each rotation. One row per pose
(usually the mean of many frames) goes into a CSV (:func:`read_poses`). This module fits, per grating, how the
cores respond to bending, and checks the result on poses the fit did not see.

Conventions (docs/math.md §1, docs/jig.md)
-------------------------------------------
* ψ (``orientation_rad``) is the sensor's rotation about its own tangent +d3 (base → tip), counter-clockwise
  seen from the tip looking back to the base — the sense in which core angles are counted. A groove bends the
  sensor toward a fixed direction of the plate, so in the fibre's material frame

      k(ψ) = κ (cos(α − ψ), sin(α − ψ)),

  with α, the *roll*, the bend direction in the fibre frame at ψ = 0 (a property of how the sensor is mounted
  in the jig; fitted).
* Optical strain relative to the reference of the SAME orientation: e = (λ − λ_ref)/λ_ref, λ_ref the mean of
  that orientation's curvature-0 rows. Per grating and core (math.md §2.2)

      e_i = c − p_i · k,      p_i = g_i (cos θ_i, sin θ_i),   g_i = r_i S_ε,

  with c the common mode of the pose (temperature, axial strain: unknown and different for every pose).

Models
------
Both models estimate, per grating, the same object: the cores' response in the jig frame, e = c + β j + δ_o with
j = κ (cos ψ, −sin ψ) the curvature in the jig frame, β (n_cores × 2) = −(p_i rotated by −α), and δ_o a per-core
offset of orientation o: the error of that session's zero (reference noise, drift since it was taken, a
reference pose that was not quite straight). δ_o is fitted by default, the reference rows entering as κ = 0 poses
like any other, so the calibration rests on the differences between grooves; ``trust_references=True`` sets it
to 0 and fits the bent poses only.

* ``physical``: the forward model above, fitted in strain space by weighted least squares (weights from the
  ``std_`` columns), the per-pose common mode c eliminated exactly (variable projection). It is linear in β and
  δ, so the least-squares optimum is found in closed form, with no starting point; the core angles θ_i, gains
  g_i and the roll α follow from β, with uncertainties by the delta method from the fit covariance scaled by
  the residual variance. This is the maximum-likelihood fit for independent wavelength noise.
* ``matrix``: a general linear calibration k = M e (M: 2 × n_cores, M·1 = 0 so that the common mode is
  rejected, math.md §5.1), fitted in curvature space by ordinary least squares with one curvature intercept per
  orientation (the image of δ_o). It minimises the curvature error directly and needs no physical model. Its
  design for :class:`~twin.strain.CurvatureSolver` is [1, M⁺], which the solver inverts back to exactly M. With
  more than 3 cores, directions of M that only noise determines are taken at minimum norm. Its frame (roll), the
  reported layout and the fit statistics come from the forward fit, which it runs too, so both models share one
  fibre frame.

With free per-core angles and gains and an unknown common mode per pose the two span the same curvature maps
(both have 2(n_cores − 1) identifiable numbers per grating); they differ as estimators and in what they report.

What a jig cannot tell (and how it is fixed)
---------------------------------------------
* Rotation: rotating every core by δ and the roll by δ changes nothing. The *fibre frame* is fixed by the bearing
  of the first off-axis core from the anchor (below): at each grating the roll α_n puts it at its nominal bearing;
  the roll α is the circular mean of the α_n, and what is left, α − α_n, is the rotation of the cores at that
  grating (intrinsic twist, reported).
* Translation: with an unknown common mode per pose, shifting every p_i by the same vector t is the same as
  adding t·k to c, so the jig fixes the cores' positions relative to each other, not relative to the neutral
  axis. The curvature does not depend on it; only the common-mode estimate and the reported θ_i, g_i do. The
  anchor is the central core (on the neutral axis by definition) or, without one, the cores' centroid placed at
  its nominal position (the centroid of the nominal layout).

Everything is SI (rad, 1/m, m); wavelengths in nm.
"""

from __future__ import annotations

import csv
import datetime as _dt
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin.calibration import Calibration
from twin.fiber import FiberModel
from twin.strain import CurvatureSolver, design_matrix

__all__ = [
    "MODELS",
    "JigFit",
    "JigPoses",
    "JigValidation",
    "cross_validate",
    "fit",
    "gauge_layout",
    "jig_curvature",
    "match_orientations",
    "read_poses",
    "validate",
    "write_poses",
]

MODELS = ("physical", "matrix")
#: Rows whose orientations differ by less than this are one orientation (one session), rad.
ORIENTATION_TOL = 1e-6
#: Orientations named on the command line match the file's within this, rad.
MATCH_TOL = 1e-3
#: Floor of the wavelength uncertainty used as a weight, nm (a std of 0 must not give an infinite weight).
_STD_FLOOR = 1e-6

_WAVELENGTH_COL = re.compile(r"g(\d+)_c(\d+)")
_STD_COL = re.compile(r"std_g(\d+)_c(\d+)")
_REQUIRED = ("orientation_rad", "curvature_1_per_m")


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _rot(alpha: float) -> np.ndarray:
    c, s = np.cos(alpha), np.sin(alpha)
    return np.array([[c, -s], [s, c]])


def jig_curvature(orientation, curvature, roll: float = 0.0) -> np.ndarray:
    """Curvature vector the jig imposes, in the fibre's material frame: κ (cos(α − ψ), sin(α − ψ)).

    Parameters
    ----------
    orientation : array_like, shape (...)
        ψ, the sensor's rotation about +d3 in the jig, rad.
    curvature : array_like, shape (...)
        κ, the groove's curvature, 1/m.
    roll : float
        α, the bend direction in the fibre frame at ψ = 0, rad (``roll=0`` gives the jig frame).

    Returns
    -------
    ndarray, shape (..., 2)
        (k_x, k_y), 1/m.
    """
    a = roll - np.asarray(orientation, dtype=np.float64)
    kappa = np.asarray(curvature, dtype=np.float64)
    return np.stack([kappa * np.cos(a), kappa * np.sin(a)], axis=-1)


# ================================================================================================ poses


@dataclass(frozen=True, eq=False)
class JigPoses:
    """Jig poses: one row per pose (typically the mean of many frames).

    Parameters
    ----------
    orientation : array_like, shape (n_poses,)
        ψ, the sensor's rotation about its axis in the jig, rad. Rows with equal ψ (within 1e-6 rad) form one
        orientation (one session, with its own reference).
    curvature : array_like, shape (n_poses,)
        κ of the groove, 1/m; 0 marks a reference row (flat groove).
    wavelengths : array_like, shape (n_poses, n_gratings, n_cores)
        Peak wavelengths, nm; NaN for a missing peak (the observation is dropped).
    std : array_like, shape (n_poses, n_gratings, n_cores), optional
        1σ uncertainty of each wavelength in the row, nm (for a mean of N frames: frame std / √N); weights.
    source : str
        Where the poses came from (file name), for messages.
    lines : array_like of int, shape (n_poses,), optional
        Line number of each row in ``source``, for messages.
    """

    orientation: np.ndarray
    curvature: np.ndarray
    wavelengths: np.ndarray
    std: np.ndarray | None = None
    source: str = "poses"
    lines: np.ndarray | None = None

    def __post_init__(self) -> None:
        src = self.source
        o = np.array(self.orientation, dtype=np.float64).ravel()
        k = np.array(self.curvature, dtype=np.float64).ravel()
        w = np.array(self.wavelengths, dtype=np.float64)
        if w.ndim != 3 or w.shape[0] != o.size or k.size != o.size:
            raise ValueError(
                f"{src}: expected orientation and curvature of shape (n_poses,) and wavelengths of shape "
                f"(n_poses, n_gratings, n_cores); got {o.shape}, {k.shape}, {w.shape}"
            )
        if o.size == 0:
            raise ValueError(f"{src}: no poses")
        lines = None if self.lines is None else np.array(self.lines, dtype=np.int64).ravel()
        object.__setattr__(self, "lines", lines)
        for name, a in (("orientation_rad", o), ("curvature_1_per_m", k)):
            if not np.all(np.isfinite(a)):
                i = int(np.argmax(~np.isfinite(a)))
                raise ValueError(f"{self._where(i)}, column {name}: expected a finite number, got {a[i]}")
        bad = np.isinf(w) | (np.isfinite(w) & ((w < 200) | (w > 3000)))
        if bad.any():
            i, n, c = (int(x) for x in np.argwhere(bad)[0])
            raise ValueError(
                f"{self._where(i)}, column g{n}_c{c}: {w[i, n, c]} is not a Bragg wavelength in nm (200–3000)"
            )
        s = None
        if self.std is not None:
            s = np.array(self.std, dtype=np.float64)
            if s.shape != w.shape:
                raise ValueError(f"{src}: std must have the wavelengths' shape {w.shape}, got {s.shape}")
            bad = np.isfinite(w) & ~(np.isfinite(s) & (s >= 0))
            if bad.any():
                i, n, c = (int(x) for x in np.argwhere(bad)[0])
                raise ValueError(
                    f"{self._where(i)}, column std_g{n}_c{c}: expected a wavelength std >= 0 in nm, got {s[i, n, c]}"
                )
        for name, a in (("orientation", o), ("curvature", k), ("wavelengths", w), ("std", s)):
            if a is not None:
                a.setflags(write=False)
            object.__setattr__(self, name, a)
        key = np.round(o / ORIENTATION_TOL).astype(np.int64)
        _, index = np.unique(key, return_inverse=True)
        index = index.ravel()
        n_o = int(index.max()) + 1
        object.__setattr__(self, "_index", index)
        object.__setattr__(self, "_orientations", np.bincount(index, o) / np.bincount(index))
        ref = k == 0
        has_ref = np.bincount(index[ref], minlength=n_o) > 0
        if not has_ref.all():
            g = int(np.argmax(~has_ref))
            rows = np.flatnonzero(index == g)
            raise ValueError(
                f"{src}: orientation {self._orientations[g]:.6g} rad ({self._span(rows)}) has no reference row "
                "(curvature_1_per_m = 0); every orientation needs its own zero-curvature reference"
            )
        counts = np.zeros((n_o, *w.shape[1:]))
        np.add.at(counts, index[ref], np.isfinite(w[ref]))
        if np.any(counts == 0):
            g, n, c = (int(x) for x in np.argwhere(counts == 0)[0])
            raise ValueError(
                f"{src}: orientation {self._orientations[g]:.6g} rad has no reference wavelength for g{n}_c{c} "
                "(missing in every curvature-0 row)"
            )
        object.__setattr__(self, "_ref_counts", counts)

    # ------------------------------------------------------------------ messages
    def _where(self, i: int) -> str:
        return f"{self.source} line {self.lines[i]}" if self.lines is not None else f"{self.source} pose {i}"

    def _span(self, rows: np.ndarray) -> str:
        if self.lines is not None:
            return f"lines {self.lines[rows].min()}–{self.lines[rows].max()}"
        return f"poses {rows.min()}–{rows.max()}"

    # ------------------------------------------------------------------ shape
    @property
    def n_poses(self) -> int:
        return self.orientation.size

    @property
    def n_gratings(self) -> int:
        return self.wavelengths.shape[1]

    @property
    def n_cores(self) -> int:
        return self.wavelengths.shape[2]

    @property
    def is_reference(self) -> np.ndarray:
        """Whether each row is a reference (κ = 0), shape (n_poses,)."""
        return self.curvature == 0

    @property
    def orientations(self) -> np.ndarray:
        """The distinct orientations, rad, sorted, shape (n_orientations,)."""
        return self._orientations.copy()

    @property
    def orientation_index(self) -> np.ndarray:
        """Index into :attr:`orientations` of each row, shape (n_poses,)."""
        return self._index.copy()

    def check(self, n_gratings: int, n_cores: int, what: str = "the fibre") -> None:
        """Raise a clear error when the poses do not have ``n_gratings`` × ``n_cores`` wavelengths."""
        if (self.n_gratings, self.n_cores) != (n_gratings, n_cores):
            raise ValueError(
                f"{self.source}: has {self.n_gratings} gratings × {self.n_cores} cores (columns g0_c0 … "
                f"g{self.n_gratings - 1}_c{self.n_cores - 1}) but {what} has {n_gratings} × {n_cores}"
            )

    def select(self, rows) -> JigPoses:
        """The poses at ``rows`` (a boolean mask or indices); every orientation kept must keep a reference."""
        rows = np.asarray(rows)
        return JigPoses(
            orientation=self.orientation[rows],
            curvature=self.curvature[rows],
            wavelengths=self.wavelengths[rows],
            std=None if self.std is None else self.std[rows],
            source=self.source,
            lines=None if self.lines is None else self.lines[rows],
        )

    # ------------------------------------------------------------------ strain
    def reference(self) -> np.ndarray:
        """Mean reference wavelengths of each orientation, nm, shape (n_orientations, n_gratings, n_cores)."""
        ref = self.is_reference
        w = self.wavelengths[ref]
        sums = np.zeros(self._ref_counts.shape)
        np.add.at(sums, self._index[ref], np.where(np.isfinite(w), w, 0.0))
        return sums / self._ref_counts

    def strain(self) -> tuple[np.ndarray, np.ndarray | None]:
        """Optical strain relative to the reference of each row's own orientation.

        Returns
        -------
        e : ndarray, shape (n_poses, n_gratings, n_cores)
            (λ − λ_ref)/λ_ref, dimensionless; NaN for a missing peak.
        sigma : ndarray of the same shape, or None
            1σ of ``e`` from the ``std`` columns (row and mean reference combined, their correlation ignored);
            None without them.
        """
        lam_ref = self.reference()[self._index]
        e = (self.wavelengths - lam_ref) / lam_ref
        if self.std is None:
            return e, None
        ref = self.is_reference
        s2 = np.where(np.isfinite(self.wavelengths[ref]), self.std[ref] ** 2, 0.0)
        var_ref = np.zeros(self._ref_counts.shape)
        np.add.at(var_ref, self._index[ref], s2)
        var_ref /= self._ref_counts**2
        sigma = np.sqrt(np.maximum(self.std, _STD_FLOOR) ** 2 + var_ref[self._index]) / lam_ref
        return e, sigma


def match_orientations(poses: JigPoses, values, tol: float = MATCH_TOL) -> np.ndarray:
    """Rows of ``poses`` whose orientation is one of ``values`` (rad, within ``tol``), as a boolean mask.

    Raises
    ------
    ValueError
        When a value matches no orientation of the file (the message lists those it has).
    """
    values = np.atleast_1d(np.asarray(values, dtype=np.float64))
    have = poses.orientations
    hit = np.abs(have[None, :] - values[:, None]) < tol  # (n_values, n_orientations)
    if not hit.any(axis=1).all():
        v = values[int(np.argmax(~hit.any(axis=1)))]
        listed = ", ".join(f"{x:.6g}" for x in have)
        raise ValueError(f"{poses.source}: no orientation {v:.6g} rad (within {tol:g} rad); it has {listed} rad")
    return hit.any(axis=0)[poses._index]


# ------------------------------------------------------------------------------------------ CSV files


def read_poses(path: str | Path, *, fiber: FiberModel | None = None) -> JigPoses:
    """Read a jig pose CSV (format in docs/jig.md).

    Columns: ``orientation_rad``, ``curvature_1_per_m``, one ``g{n}_c{i}`` per grating n and core i (0-based,
    as in the fibre model) with the peak wavelength in nm, and optionally ``std_g{n}_c{i}`` (nm) for all of them.
    Blank lines and lines starting with ``#`` are skipped. An empty or ``nan`` wavelength cell is a missing peak.

    Parameters
    ----------
    path : str or Path
    fiber : FiberModel, optional
        When given, the file must have exactly its gratings and cores.

    Raises
    ------
    ValueError
        One line naming the file, line and column: missing, duplicate or unknown columns, rows of the wrong
        length, non-numeric cells, orientations without a reference.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such pose file") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text (CSV) file") from None
    content = [(no, line) for no, line in enumerate(text.splitlines(), 1)
               if line.strip() and not line.lstrip().startswith("#")]
    if not content:
        raise ValueError(f"{path}: empty; expected a header line ({', '.join(_REQUIRED)}, g0_c0, …)")
    table = list(csv.reader(line for _, line in content))
    header = [h.strip() for h in table[0]]
    header_line = content[0][0]
    columns = _parse_header(path, header_line, header, fiber)
    rows, lines = table[1:], np.array([no for no, _ in content[1:]], dtype=np.int64)
    if not rows:
        raise ValueError(f"{path}: a header but no poses")
    lengths = np.array([len(r) for r in rows])
    if np.any(lengths != len(header)):
        i = int(np.argmax(lengths != len(header)))
        raise ValueError(f"{path} line {lines[i]}: expected {len(header)} cells (as in the header), got {lengths[i]}")
    cells = np.char.strip(np.array(rows, dtype=str))
    n_g, n_c, wl_cols, std_cols = columns

    def numbers(cols: np.ndarray, allow_missing: bool) -> np.ndarray:
        sub = cells[:, cols]
        low = np.char.lower(sub)
        missing = (low == "") | (low == "nan")
        if not allow_missing and missing.any():
            i, j = (int(x) for x in np.argwhere(missing)[0])
            raise ValueError(f"{path} line {lines[i]}, column {header[cols[j]]}: {str(sub[i, j])!r}; expected a number")
        try:
            values = np.where(missing, "nan", sub).astype(np.float64)
        except ValueError:
            values = None
        if values is None or np.isinf(values).any():
            for i, j in np.ndindex(sub.shape):  # error path only: find the first bad cell
                if missing[i, j]:
                    continue
                try:
                    ok = bool(np.isfinite(float(sub[i, j])))
                except ValueError:
                    ok = False
                if not ok:
                    raise ValueError(
                        f"{path} line {lines[i]}, column {header[cols[j]]}: {str(sub[i, j])!r} is not a finite number"
                    )
        return values

    o = numbers(np.array([header.index("orientation_rad")]), False)[:, 0]
    k = numbers(np.array([header.index("curvature_1_per_m")]), False)[:, 0]
    w = numbers(wl_cols.ravel(), True).reshape(-1, n_g, n_c)
    s = None if std_cols is None else numbers(std_cols.ravel(), True).reshape(-1, n_g, n_c)
    return JigPoses(orientation=o, curvature=k, wavelengths=w, std=s, source=str(path), lines=lines)


def _parse_header(path: Path, line: int, header: list[str], fiber: FiberModel | None):
    where = f"{path} line {line} (header)"
    seen: dict[str, int] = {}
    for j, name in enumerate(header):
        if name in seen:
            raise ValueError(f"{where}: column {name!r} appears twice (columns {seen[name] + 1} and {j + 1})")
        seen[name] = j
    for name in _REQUIRED:
        if name not in seen:
            raise ValueError(f"{where}: missing column {name}; expected {', '.join(_REQUIRED)}, then g{{n}}_c{{i}}")
    wl: dict[tuple[int, int], int] = {}
    sd: dict[tuple[int, int], int] = {}
    for j, name in enumerate(header):
        if name in _REQUIRED:
            continue
        m_w, m_s = _WAVELENGTH_COL.fullmatch(name), _STD_COL.fullmatch(name)
        if m_w:
            wl[int(m_w[1]), int(m_w[2])] = j
        elif m_s:
            sd[int(m_s[1]), int(m_s[2])] = j
        else:
            raise ValueError(
                f"{where}: unknown column {name!r}; expected {', '.join(_REQUIRED)}, g{{n}}_c{{i}} (wavelength, nm) "
                "and optionally std_g{n}_c{i} (nm), n and i counted from 0"
            )
    if not wl:
        raise ValueError(f"{where}: no wavelength columns g{{n}}_c{{i}}")
    n_g = max(n for n, _ in wl) + 1 if fiber is None else fiber.n_gratings
    n_c = max(i for _, i in wl) + 1 if fiber is None else fiber.n_cores
    extra = sorted(key for key in wl if key[0] >= n_g or key[1] >= n_c)
    if extra:
        n, i = extra[0]
        raise ValueError(f"{where}: column g{n}_c{i} but the fibre has {n_g} gratings × {n_c} cores (g0_c0 … "
                         f"g{n_g - 1}_c{n_c - 1})")
    for n, i in np.ndindex(n_g, n_c):
        if (n, i) not in wl:
            raise ValueError(f"{where}: missing column g{n}_c{i} (grating {n}, core {i})")
    std_cols = None
    if sd:
        stray = sorted(set(sd) - set(wl))
        if stray:
            raise ValueError(f"{where}: column std_g{stray[0][0]}_c{stray[0][1]} has no wavelength column")
        for n, i in np.ndindex(n_g, n_c):
            if (n, i) not in sd:
                raise ValueError(f"{where}: missing column std_g{n}_c{i}; give a std column for every wavelength "
                                 "column or none")
        std_cols = np.array([[sd[n, i] for i in range(n_c)] for n in range(n_g)])
    wl_cols = np.array([[wl[n, i] for i in range(n_c)] for n in range(n_g)])
    return n_g, n_c, wl_cols, std_cols


def write_poses(path: str | Path, poses: JigPoses, comment: str = "") -> None:
    """Write poses as a CSV that :func:`read_poses` reads back (wavelengths to 1e-6 nm; NaN as ``nan``).

    ``comment`` lines are written first, each prefixed with ``#``.
    """
    n_g, n_c = poses.n_gratings, poses.n_cores
    names = [*_REQUIRED, *(f"g{n}_c{i}" for n in range(n_g) for i in range(n_c))]
    blocks = [poses.orientation[:, None], poses.curvature[:, None], poses.wavelengths.reshape(poses.n_poses, -1)]
    fmt = ["%.17g", "%.17g", *["%.6f"] * (n_g * n_c)]
    if poses.std is not None:
        names += [f"std_g{n}_c{i}" for n in range(n_g) for i in range(n_c)]
        blocks.append(poses.std.reshape(poses.n_poses, -1))
        fmt += ["%.4g"] * (n_g * n_c)
    head = "".join(f"# {line}\n" for line in comment.splitlines())
    with open(path, "w") as f:
        f.write(head)
        np.savetxt(f, np.hstack(blocks), fmt=fmt, delimiter=",", header=",".join(names), comments="")


# ================================================================================================ fits


@dataclass(frozen=True, eq=False)
class JigFit:
    """A jig calibration and what it found (per-grating arrays follow :attr:`gratings`).

    Attributes
    ----------
    model : {"physical", "matrix"}
    calibration : Calibration
        Usable by :class:`~twin.reconstruct.Reconstructor` and ``twin live``: per-grating ``design`` (nominal
        at gratings the jig did not fix), ``lambda0`` (mean of the fit orientations' references, nm) and the
        results below in ``provenance`` (keys ``jig_*``).
    fiber : FiberModel
        The nominal fibre the fit started from.
    roll, roll_std : float
        α, the bend direction in the fibre frame at jig orientation 0, and its 1σ from the fit's noise, rad.
    gratings : ndarray of int, shape (n_fit,)
        Gratings fitted (those the jig fixes).
    unfixed_gratings : ndarray of int
        Gratings left with the nominal design.
    core_angles, core_angles_std : ndarray, shape (n_fit, n_cores)
        Fitted core angles in the fibre's own sense (``fiber.handedness``) and 1σ, rad, from the forward
        (physical) fit, which both models run: it sets the frame of both. A central core shows its nominal angle.
    gains, gains_std : ndarray, shape (n_fit, n_cores)
        g_i = r_i S_ε, m, and 1σ (0 for a central core), from the forward fit.
    core_rotation : ndarray, shape (n_fit,)
        Rotation of the cores at each grating relative to the fibre frame, CCW, rad (intrinsic twist).
    matrix, matrix_std : ndarray, shape (n_fit, 2, n_cores), or None
        Matrix model only: k = M e in the fibre frame (1/m per unit optical strain) and 1σ.
    rms_strain_residual : ndarray, shape (n_fit,)
        RMS of the fit's strain residual (common mode removed), dimensionless.
    explained : ndarray, shape (n_fit,)
        Fraction of the (common-mode-free) strain variation the jig curvature explains (R²).
    chi2_reduced : ndarray, shape (n_fit,), or None
        Reduced χ² of the forward fit when the CSV had std columns (≈ 1 when they describe the scatter).
    orientations : ndarray
        Orientations fitted, rad.
    n_poses : int
        Bent (non-reference) poses fitted.
    warnings : tuple of str
    """

    model: str
    calibration: Calibration
    fiber: FiberModel
    roll: float
    roll_std: float
    gratings: np.ndarray
    unfixed_gratings: np.ndarray
    core_angles: np.ndarray
    core_angles_std: np.ndarray
    gains: np.ndarray
    gains_std: np.ndarray
    core_rotation: np.ndarray
    matrix: np.ndarray | None
    matrix_std: np.ndarray | None
    rms_strain_residual: np.ndarray
    explained: np.ndarray
    chi2_reduced: np.ndarray | None
    orientations: np.ndarray
    n_poses: int
    warnings: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        """JSON-ready summary (SI units)."""
        s = self.fiber.grating_s

        def lst(a, i):
            return None if a is None else a[i].tolist()

        return {
            "model": self.model,
            "roll_rad": self.roll,
            "roll_std_rad": self.roll_std,
            "orientations_rad": self.orientations.tolist(),
            "n_poses": self.n_poses,
            "gratings": [
                {
                    "index": int(n),
                    "s_m": float(s[n]),
                    "core_angles_rad": self.core_angles[i].tolist(),
                    "core_angles_std_rad": lst(self.core_angles_std, i),
                    "gains_m": self.gains[i].tolist(),
                    "gains_std_m": lst(self.gains_std, i),
                    "core_rotation_rad": float(self.core_rotation[i]),
                    "matrix_1_per_m": lst(self.matrix, i),
                    "matrix_std_1_per_m": lst(self.matrix_std, i),
                    "rms_strain_residual": float(self.rms_strain_residual[i]),
                    "explained": float(self.explained[i]),
                    "chi2_reduced": None if self.chi2_reduced is None else float(self.chi2_reduced[i]),
                }
                for i, n in enumerate(self.gratings)
            ],
            "unfixed_gratings": self.unfixed_gratings.tolist(),
            "warnings": list(self.warnings),
        }


def _anchor(fiber: FiberModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nominal core positions p_i = g_i u(θ_i) (CCW), the anchor weights a (Σ a = 1) and its nominal place."""
    th = fiber.ccw_angles
    p_nom = fiber.gains[:, None] * np.stack([np.cos(th), np.sin(th)], axis=-1)
    if fiber.central_core is not None:
        a = np.zeros(fiber.n_cores)
        a[fiber.central_core] = 1.0
    else:
        a = np.full(fiber.n_cores, 1.0 / fiber.n_cores)
    return p_nom, a, a @ p_nom


def _centred_basis(n: int) -> np.ndarray:
    """Orthonormal basis of the vectors orthogonal to (1, …, 1), shape (n, n − 1)."""
    q, _ = np.linalg.qr(np.column_stack([np.ones(n), np.eye(n)[:, : n - 1]]))
    return q[:, 1:]


def _fit_physical(e, w, j, q, group, n_groups):
    """Strain-space weighted LS of e_pi = c_p + β_i·j_p + δ_{o(p),i} for one grating, c_p eliminated.

    e, w : (P, C) strain and weights (0 for missing); j : (P, 2) jig-frame curvature; q : (C, C−1);
    group : (P,) orientation index, or None for no offsets δ (references trusted). δ_o = q d_o (its common part
    is c's). Returns β (C, 2), its covariance (2C, 2C) (ordered (core, component)), the offsets δ per pose
    (P, C) and the residual variance per unit weight; None when the poses do not determine β.
    """
    n_p, c_n = e.shape
    na = 2 * (c_n - 1)
    wsum = w.sum(axis=1)
    used = wsum > 0
    safe = np.where(used, wsum, 1.0)
    ebar = (w * e).sum(axis=1) / safe
    qr = q[None] - ((w @ q) / safe[:, None])[:, None, :]  # (P, C, C−1): cores' basis, centred per pose
    x = (qr[..., None] * j[:, None, None, :]).reshape(n_p, c_n, na)
    if group is not None:
        xd = np.zeros((n_p, c_n, n_groups, c_n - 1))
        xd[np.arange(n_p), :, group, :] = qr
        x = np.concatenate([x, xd.reshape(n_p, c_n, -1)], axis=-1)
    x = x.reshape(n_p * c_n, -1)
    sw = np.sqrt(w).ravel()
    xw, yw = x * sw[:, None], (e - ebar[:, None]).ravel() * sw
    normal = xw.T @ xw
    ev = np.linalg.eigvalsh(normal)
    if ev[0] <= 1e-12 * ev[-1]:
        return None
    sol = np.linalg.solve(normal, xw.T @ yw)
    rss = float(np.sum((yw - xw @ sol) ** 2))
    dof = int(np.count_nonzero(sw)) - int(used.sum()) - sol.size
    if dof <= 0:
        return None
    big = np.kron(q, np.eye(2))  # vec(β) = big @ vec(A)
    cov = big @ (np.linalg.inv(normal)[:na, :na] * (rss / dof)) @ big.T
    offsets = np.zeros(e.shape) if group is None else (sol[na:].reshape(n_groups, c_n - 1) @ q.T)[group]
    return q @ sol[:na].reshape(c_n - 1, 2), cov, offsets, rss / dof


def _fit_matrix(e, j, q, group, n_groups):
    """Curvature-space OLS of j_p = M e_p + m_{o(p)}, M = Aᵀ qᵀ (so M·1 = 0), for one grating; poses missing a
    peak drop. m_o (one per orientation, none if ``group`` is None) is the curvature the orientation's zero
    error would give. With more than 3 cores, strain patterns that no bend produces leave directions of M that
    only noise determines; where the data cannot tell, the minimum-norm M is taken (it ignores them).

    Returns M (2, C) and its std (2, C), or None.
    """
    ok = np.all(np.isfinite(e), axis=1)
    x = e[ok] @ q
    if group is not None:
        x = np.concatenate([x, np.eye(n_groups)[group[ok]]], axis=1)
    jj = j[ok]
    scale = np.linalg.norm(x, axis=0)  # strain columns ~1e-4, intercepts ~1: scale to O(1) before the rank test
    if x.shape[0] <= x.shape[1] or np.any(scale == 0):
        return None
    xs = x / scale
    sol, _, rank, _ = np.linalg.lstsq(xs, jj, rcond=1e-9)
    sol = sol / scale[:, None]  # (C−1 [+ O], 2)
    dof = x.shape[0] - rank
    s2 = np.sum((jj - x @ sol) ** 2, axis=0) / dof  # per component
    c1 = q.shape[1]
    inv = (np.linalg.pinv(xs.T @ xs, rcond=1e-9, hermitian=True) / np.outer(scale, scale))[:c1, :c1]
    m = sol[:c1].T @ q.T
    sv = np.linalg.svd(m, compute_uv=False)
    if sv[-1] <= 1e-9 * sv[0]:
        return None
    var = s2[:, None] * np.einsum("cj,jk,ck->c", q, inv, q)[None, :]
    return m, np.sqrt(var)


def _residual_stats(beta, offsets, e, w, j):
    """RMS strain residual and R² of e = c + β j + δ with c the weighted per-pose mean (one grating)."""
    w = np.where(np.isfinite(e), w, 0.0)
    e0 = np.where(w > 0, e, 0.0)
    r = e0 - j @ beta.T - offsets
    wsum = np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    r = r - (w * r).sum(axis=1, keepdims=True) / wsum
    er = e0 - (w * e0).sum(axis=1, keepdims=True) / wsum
    rss = float(np.sum(w * r**2))
    tss = float(np.sum(w * er**2))
    rms = float(np.sqrt(np.sum((w > 0) * r**2) / max(np.count_nonzero(w), 1)))
    return rms, 1.0 - rss / tss if tss > 0 else 0.0


def _anchored(fiber: FiberModel, beta: np.ndarray):
    """Jig-frame positions relative to the anchor d (G, C, 2), the per-grating rolls α_n (G,) that put the first
    off-axis core at its nominal bearing, and the anchor's nominal place t (2,)."""
    p_nom, a, t_nom = _anchor(fiber)
    k0 = int(fiber.bending_cores[0])
    d = -(beta - np.einsum("c,gcd->gd", a, beta)[:, None, :])
    phi_nom = np.arctan2(*(p_nom[k0] - t_nom)[::-1])
    alpha_n = _wrap(phi_nom - np.arctan2(d[:, k0, 1], d[:, k0, 0]))
    return d, alpha_n, t_nom


def _gauge(fiber: FiberModel, beta: np.ndarray, cov: np.ndarray | None):
    """Fix rotation and translation (module docstring): jig-frame β (G, C, 2) → fibre-frame core positions.

    Returns roll α, per-grating rolls α_n (G,), positions p (G, C, 2) (CCW frame), their covariances
    (G, C, 2, 2) or None, and the 1σ of each α_n (G,) or None.
    """
    d, alpha_n, t_nom = _anchored(fiber, beta)
    alpha = float(np.angle(np.exp(1j * alpha_n).sum()))
    r = _rot(alpha)
    p = d @ r.T + t_nom
    if cov is None:
        return alpha, alpha_n, p, None, None
    n_c = fiber.n_cores
    _, a, _ = _anchor(fiber)
    k0 = int(fiber.bending_cores[0])
    t = -np.einsum("ic,de->idce", np.eye(n_c) - a[None, :], np.eye(2)).reshape(n_c, 2, 2 * n_c)
    cov_d = np.einsum("iak,gkl,ibl->giab", t, cov, t)  # (G, C, 2, 2)
    cov_p = r @ cov_d @ r.T
    d0 = d[:, k0]
    perp = np.stack([-d0[:, 1], d0[:, 0]], axis=-1) / np.sum(d0**2, axis=-1, keepdims=True)
    alpha_std = np.sqrt(np.einsum("ga,gab,gb->g", perp, cov_d[:, k0], perp))
    return alpha, alpha_n, p, cov_p, alpha_std


def gauge_layout(fiber: FiberModel, core_angles, gains) -> tuple[np.ndarray, np.ndarray]:
    """A core layout as a jig calibration can know it: anchored and rotated (module docstring), per grating.

    The jig determines the cores' positions only relative to each other and up to a rotation (the roll); this
    puts any layout — a fit's or a simulator's true one — in the same gauge so the two can be compared: the
    anchor (central core, or the centroid of the cores) at its nominal place, and at each grating the first
    off-axis core at its nominal bearing from it (so per-grating rotation, e.g. twist, is removed too).

    Parameters
    ----------
    fiber : FiberModel
        The nominal fibre (its layout defines the gauge).
    core_angles : array_like, shape (n_cores,) or (n_gratings, n_cores)
        Angles in the fibre's own sense, rad.
    gains : array_like, same shape
        g_i = r_i S_ε, m.

    Returns
    -------
    angles, gains : ndarray, shape (n_gratings, n_cores)
        In the fibre's own sense (rad, near nominal) and m.
    """
    th = fiber.handedness * np.atleast_2d(np.asarray(core_angles, dtype=np.float64))
    g = np.atleast_2d(np.asarray(gains, dtype=np.float64))
    p = g[..., None] * np.stack([np.cos(th), np.sin(th)], axis=-1)
    d, alpha_n, t_nom = _anchored(fiber, -p)
    c, s = np.cos(alpha_n)[:, None], np.sin(alpha_n)[:, None]
    q = np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1]], axis=-1) + t_nom
    angles, gains_out, _, _ = _polar(fiber, q, None)
    return angles, gains_out


def _polar(fiber: FiberModel, p: np.ndarray, cov_p: np.ndarray | None):
    """Core angles (fibre's own sense, near nominal) and gains from positions (G, C, 2); 1σ by the delta method."""
    g = np.hypot(p[..., 0], p[..., 1])
    theta = np.arctan2(p[..., 1], p[..., 0])
    nominal = fiber.ccw_angles
    theta = nominal + _wrap(theta - nominal)
    central = g < 1e-15
    theta = np.where(central, nominal, theta)
    angles = fiber.handedness * theta
    if cov_p is None:
        return angles, g, None, None
    safe = np.where(central, 1.0, g)
    u = p / safe[..., None]
    perp = np.stack([-u[..., 1], u[..., 0]], axis=-1)
    g_std = np.sqrt(np.einsum("...a,...ab,...b->...", u, cov_p, u))
    th_std = np.sqrt(np.einsum("...a,...ab,...b->...", perp, cov_p, perp)) / safe
    return angles, g, np.where(central, 0.0, th_std), np.where(central, 0.0, g_std)


def _grating_list(fiber: FiberModel, gratings) -> np.ndarray:
    if gratings is None:
        return np.arange(fiber.n_gratings)
    g = np.unique(np.asarray(gratings, dtype=np.int64).ravel())
    if g.size == 0:
        raise ValueError("no gratings to fit")
    if g.min() < 0 or g.max() >= fiber.n_gratings:
        bad = g[(g < 0) | (g >= fiber.n_gratings)][0]
        raise ValueError(f"grating {bad} does not exist; the fibre has gratings 0–{fiber.n_gratings - 1}")
    return g


def _mirror_check(fiber: FiberModel, p: np.ndarray) -> bool:
    """Whether the fitted layout (G, C, 2) matches the mirror image of the nominal one better than itself."""
    p_nom, _, _ = _anchor(fiber)
    x = p[..., 0] + 1j * p[..., 1]
    x = x - x.mean(axis=-1, keepdims=True)
    y = p_nom[:, 0] + 1j * p_nom[:, 1]
    y = y - y.mean()
    direct = np.abs(np.sum(x * np.conj(y), axis=-1))
    mirror = np.abs(np.sum(x * y, axis=-1))
    return bool(np.median(mirror - direct) > 0)


def fit(
    fiber: FiberModel,
    poses: JigPoses,
    *,
    model: str = "physical",
    gratings=None,
    orientations=None,
    trust_references: bool = False,
    min_explained: float = 0.5,
) -> JigFit:
    """Fit a jig calibration (see the module docstring for the models and conventions).

    Parameters
    ----------
    fiber : FiberModel
        The nominal sensor (core layout, gratings); its angles fix the frame, it is not otherwise trusted.
    poses : JigPoses
    model : {"physical", "matrix"}
    gratings : sequence of int, optional
        Gratings lying in the groove (whose curvature the jig fixes); default all. The others keep the nominal
        design and are listed in the result.
    orientations : sequence of float, optional
        Fit only on these orientations (rad, matched within 1e-3 rad); default all.
    trust_references : bool
        False (default): each orientation's zero is fitted (a per-core strain offset), its reference rows
        entering as κ = 0 poses like any other, so the calibration rests on the differences between grooves and
        a reference's noise, drift or residual bend does not bias it. True: the references are taken as exact
        and only the bent poses are fitted.
    min_explained : float
        A fitted grating whose strain the jig curvature explains less than this (R²) is an error: it is most
        likely not in the groove. Below 0.99 a warning is given.

    Raises
    ------
    ValueError
        Bad model or gratings, poses that do not match the fibre, poses that bend the sensor in one plane only,
        too few poses, a grating the jig does not fix.
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {', '.join(MODELS)}; got {model!r}")
    poses.check(fiber.n_gratings, fiber.n_cores, "the fibre model")
    fit_g = _grating_list(fiber, gratings)
    if orientations is not None:
        poses = poses.select(match_orientations(poses, orientations))
    bent = ~poses.is_reference
    if not bent.any():
        raise ValueError(f"{poses.source}: only reference rows (curvature 0); the fit needs bent poses")
    e_all, sigma_all = poses.strain()
    rows = bent if trust_references else np.ones(poses.n_poses, bool)
    e, j = e_all[rows], jig_curvature(poses.orientation[rows], poses.curvature[rows])
    group = None if trust_references else poses.orientation_index[rows]
    n_groups = poses.orientations.size
    ev = np.linalg.eigvalsh(j.T @ j)
    if ev[0] < 1e-6 * ev[-1]:
        listed = ", ".join(f"{x:.4g}" for x in poses.orientations)
        raise ValueError(
            f"{poses.source}: the fit poses bend the sensor in one plane only (orientations {listed} rad are equal "
            "or opposite); fit on at least two orientations that are not 0 or π apart"
        )
    w = np.ones(e.shape) if sigma_all is None else 1.0 / sigma_all[rows] ** 2
    w = np.where(np.isfinite(e), w, 0.0)
    q = _centred_basis(fiber.n_cores)
    n_fit, n_c = fit_g.size, fiber.n_cores
    beta = np.zeros((n_fit, n_c, 2))
    cov = np.zeros((n_fit, 2 * n_c, 2 * n_c))
    chi2 = np.zeros(n_fit)
    matrix = np.zeros((n_fit, 2, n_c)) if model == "matrix" else None
    matrix_std = np.zeros((n_fit, 2, n_c)) if model == "matrix" else None
    rms, explained = np.zeros(n_fit), np.zeros(n_fit)
    for i, n in enumerate(fit_g):  # a few gratings; each fit is vectorised over poses and cores
        # the forward (physical) fit always runs: it sets the frame, the layout and the fit statistics
        out = _fit_physical(np.where(w[:, n] > 0, e[:, n], 0.0), w[:, n], j, q, group, n_groups)
        inverse = _fit_matrix(e[:, n], j, q, group, n_groups) if model == "matrix" else ()
        if inverse is None:
            out = None
        if out is None:
            raise ValueError(
                f"{poses.source}: grating {n} (s = {fiber.grating_s[n] * 1e3:.1f} mm): too few usable poses to fit "
                f"the {model} model ({int(np.all(np.isfinite(e[:, n]), axis=1).sum())} poses with all peaks)"
            )
        beta[i], cov[i], offsets, chi2[i] = out
        if model == "matrix":
            matrix[i], matrix_std[i] = inverse
        rms[i], explained[i] = _residual_stats(beta[i], offsets, e[:, n], w[:, n], j)
    warnings: list[str] = []
    low = explained < min_explained
    if low.any():
        n = int(fit_g[np.argmax(low)])
        others = ",".join(str(int(x)) for x in fit_g[~low]) or "…"
        raise ValueError(
            f"{poses.source}: grating {n} (s = {fiber.grating_s[n] * 1e3:.1f} mm): the jig curvature explains only "
            f"{explained[np.argmax(low)]:.0%} of its strain; is it outside the groove? Fit only the gratings in "
            f"the groove (--gratings {others})"
        )
    for i in np.flatnonzero(explained < 0.99):
        n = int(fit_g[i])
        warnings.append(f"grating {n}: the jig curvature explains only {explained[i]:.1%} of its strain variation; "
                        "is it fully in the groove?")
    alpha, alpha_n, p, cov_p, alpha_n_std = _gauge(fiber, beta, cov)
    angles, gains, angles_std, gains_std = _polar(fiber, p, cov_p)
    roll_std = float(np.sqrt(np.sum(alpha_n_std**2)) / n_fit)
    core_rotation = _wrap(alpha - alpha_n)
    if model == "matrix":  # into the fibre frame: k = R(α) j
        c, s = np.cos(alpha), np.sin(alpha)
        m_j, s_j = matrix.copy(), matrix_std.copy()
        matrix = np.einsum("ab,gbc->gac", _rot(alpha), m_j)
        matrix_std = np.sqrt(np.stack([c**2 * s_j[:, 0] ** 2 + s**2 * s_j[:, 1] ** 2,
                                       s**2 * s_j[:, 0] ** 2 + c**2 * s_j[:, 1] ** 2], axis=1))
    if _mirror_check(fiber, p):
        warnings.append(
            "the fitted core layout is the mirror image of the nominal one: is the sense of orientation_rad "
            "reversed? ψ counts counter-clockwise about +d3 (the tangent from base to tip), like the core angles"
        )
    dev = np.abs(_wrap(angles - fiber.core_angles))[:, fiber.bending_cores]
    if np.any(dev > np.deg2rad(15)):
        i, c = np.unravel_index(int(np.argmax(dev)), dev.shape)
        warnings.append(f"grating {int(fit_g[i])} core {int(fiber.bending_cores[c])}: fitted angle is "
                        f"{np.rad2deg(dev[i, c]):.1f}° from nominal; check the core numbering")
    ratio = gains[:, fiber.bending_cores] / fiber.gains[fiber.bending_cores]
    if np.any(np.abs(np.log(ratio)) > np.log(1.3)):
        i, c = np.unravel_index(int(np.argmax(np.abs(np.log(ratio)))), ratio.shape)
        warnings.append(f"grating {int(fit_g[i])} core {int(fiber.bending_cores[c])}: fitted gain is "
                        f"{ratio[i, c]:.2f}× nominal; check the fibre model's radii and S_ε")
    design = design_matrix(fiber).copy()
    if model == "physical":
        design[fit_g, :, 1:] = -p
    else:  # [1, M⁺]: the solver's inverse is exactly M; anchored like the physical layout (only c changes)
        _, a, t_nom = _anchor(fiber)
        b = np.linalg.pinv(matrix)  # (G, C, 2)
        design[fit_g, :, 1:] = b - np.einsum("c,gcd->gd", a, b)[:, None, :] - t_nom
    unfixed = np.setdiff1d(np.arange(fiber.n_gratings), fit_g)
    lam0 = poses.reference().mean(axis=0)
    levels = np.unique(np.abs(poses.curvature[bent]))
    provenance = {
        "method": f"jig ({model} model)",
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "jig_source": poses.source,
        "jig_model": model,
        "jig_roll_rad": alpha,
        "jig_roll_std_rad": roll_std,
        "jig_orientations_rad": poses.orientations.tolist(),
        "jig_curvatures_1_per_m": levels.tolist(),
        "jig_poses": int(bent.sum()),
        "jig_trust_references": bool(trust_references),
        "jig_gratings": fit_g.tolist(),
        "jig_grating_s_m": fiber.grating_s.tolist(),
        "jig_unfixed_gratings": unfixed.tolist(),
        "jig_core_angles_rad": angles.tolist(),
        "jig_gains_m": gains.tolist(),
        "jig_core_rotation_rad": core_rotation.tolist(),
        "jig_rms_strain_residual": rms.tolist(),
        "jig_explained": explained.tolist(),
    }
    provenance["jig_core_angles_std_rad"] = angles_std.tolist()
    provenance["jig_gains_std_m"] = gains_std.tolist()
    if model == "matrix":
        provenance["jig_matrix_1_per_m"] = matrix.tolist()
        provenance["jig_matrix_std_1_per_m"] = matrix_std.tolist()
    calibration = Calibration(lambda0=lam0, design=design, provenance=provenance)
    calibration.check(fiber)
    return JigFit(
        model=model,
        calibration=calibration,
        fiber=fiber,
        roll=alpha,
        roll_std=roll_std,
        gratings=fit_g,
        unfixed_gratings=unfixed,
        core_angles=angles,
        core_angles_std=angles_std,
        gains=gains,
        gains_std=gains_std,
        core_rotation=core_rotation,
        matrix=matrix,
        matrix_std=matrix_std,
        rms_strain_residual=rms,
        explained=explained,
        chi2_reduced=chi2 if sigma_all is not None else None,
        orientations=poses.orientations,
        n_poses=int(bent.sum()),
        warnings=tuple(warnings),
    )


# ========================================================================================== validation


@dataclass(frozen=True, eq=False)
class JigValidation:
    """How well a calibration reproduces the jig's curvature on a set of poses.

    Per bent pose p and validated grating n, the calibrated curvature k̂ (own-orientation reference) is compared
    with the jig's k = κ (cos(α − ψ), sin(α − ψ)).

    Attributes
    ----------
    gratings : ndarray of int, shape (G,)
    grating_s : ndarray, shape (G,)
        m.
    orientation, curvature : ndarray, shape (P,)
        ψ (rad) and κ (1/m) of each bent pose.
    measured : ndarray, shape (P, G, 2)
        k̂, 1/m (NaN where it could not be solved).
    magnitude_error : ndarray, shape (P, G)
        |k̂| − |κ|, 1/m.
    direction_error : ndarray, shape (P, G)
        Signed angle from the jig's direction to k̂, rad.
    roll : float
        α used, rad.
    roll_fitted : bool
        Whether α was fitted to these poses (a rotation only) instead of taken from the calibration.
    min_curvature : float
        The summary covers poses with |κ| ≥ this, 1/m.
    source : str
    """

    gratings: np.ndarray
    grating_s: np.ndarray
    orientation: np.ndarray
    curvature: np.ndarray
    measured: np.ndarray
    magnitude_error: np.ndarray
    direction_error: np.ndarray
    roll: float
    roll_fitted: bool
    min_curvature: float
    source: str = ""

    @property
    def levels(self) -> np.ndarray:
        """Distinct |κ| of the bent poses, 1/m."""
        return np.unique(np.abs(self.curvature))

    def table(self) -> list[dict]:
        """One row per grating and curvature level (JSON-ready, SI; directions in deg)."""
        lv = np.abs(self.curvature)
        rows = []
        for i, n in enumerate(self.gratings):
            for level in self.levels:
                sel = lv == level
                m, d = self.magnitude_error[sel, i], np.rad2deg(self.direction_error[sel, i])
                rows.append({
                    "grating": int(n),
                    "s_m": float(self.grating_s[i]),
                    "curvature_1_per_m": float(level),
                    "n": int(sel.sum()),
                    "n_invalid": int(np.isnan(m).sum()),
                    "magnitude_error_mean_1_per_m": _stat(np.nanmean, m),
                    "magnitude_error_max_abs_1_per_m": _stat(np.nanmax, np.abs(m)),
                    "magnitude_error_rms_1_per_m": _stat(lambda x: np.sqrt(np.nanmean(x**2)), m),
                    "direction_error_mean_deg": _stat(np.nanmean, d),
                    "direction_error_max_abs_deg": _stat(np.nanmax, np.abs(d)),
                })
        return rows

    def summary(self) -> dict:
        """Worst errors over poses with |κ| ≥ ``min_curvature`` (and over all bent poses), JSON-ready."""
        big = np.abs(self.curvature) >= self.min_curvature
        m, d = self.magnitude_error, np.rad2deg(self.direction_error)
        return {
            "min_curvature_1_per_m": self.min_curvature,
            "n_poses": int(big.sum()),
            "n_invalid": int(np.isnan(m[big]).sum()),
            "max_abs_magnitude_error_1_per_m": _stat(np.nanmax, np.abs(m[big])),
            "rms_magnitude_error_1_per_m": _stat(lambda x: np.sqrt(np.nanmean(x**2)), m[big]),
            "max_abs_direction_error_deg": _stat(np.nanmax, np.abs(d[big])),
            "rms_direction_error_deg": _stat(lambda x: np.sqrt(np.nanmean(x**2)), d[big]),
            "all_levels_max_abs_magnitude_error_1_per_m": _stat(np.nanmax, np.abs(m)),
            "all_levels_max_abs_direction_error_deg": _stat(np.nanmax, np.abs(d)),
        }

    def passes(self, max_error: float, max_direction_error_deg: float) -> bool:
        """Whether every pose with |κ| ≥ ``min_curvature`` is within both tolerances (invalid poses fail)."""
        s = self.summary()
        if s["n_poses"] == 0 or s["n_invalid"]:
            return False
        return (s["max_abs_magnitude_error_1_per_m"] <= max_error
                and s["max_abs_direction_error_deg"] <= max_direction_error_deg)

    def to_dict(self) -> dict:
        return {
            "source": self.source,
            "roll_rad": self.roll,
            "roll_fitted": self.roll_fitted,
            "orientations_rad": np.unique(self.orientation).tolist(),
            "gratings": self.gratings.tolist(),
            "n_poses": int(self.curvature.size),
            "levels": self.table(),
            "summary": self.summary(),
        }


def _stat(fn, x) -> float | None:
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0 or np.all(np.isnan(x)):
        return None
    return float(fn(x))


def validate(
    calibration: Calibration,
    poses: JigPoses,
    *,
    fiber: FiberModel | None = None,
    gratings=None,
    roll: float | None = None,
    fit_roll: bool = False,
    min_curvature: float = 0.8,
) -> JigValidation:
    """Compare a calibration's curvature with the jig's on ``poses``.

    Parameters
    ----------
    calibration : Calibration
        A jig calibration (its design and roll are used), or any calibration together with ``fiber``.
    poses : JigPoses
        Each row is referenced to its own orientation's curvature-0 rows.
    fiber : FiberModel, optional
        Needed when the calibration has no ``design``.
    gratings : sequence of int, optional
        Gratings to validate; default those the jig calibration fitted (``provenance['jig_gratings']``), or all.
    roll : float, optional
        α, rad; default the calibration's (``provenance['jig_roll_rad']``).
    fit_roll : bool
        Fit α to these poses instead (a single rotation: use it when the sensor was remounted in the jig).
    min_curvature : float
        The summary covers |κ| ≥ this, 1/m.
    """
    prov = calibration.provenance
    if calibration.design is not None:
        design = np.array(calibration.design)
        if fiber is not None:
            calibration.check(fiber)
    elif fiber is not None:
        design = calibration.design_for(fiber)
    else:
        raise ValueError("this calibration has no jig design matrices; give the fibre model it was made for")
    n_g, n_c = design.shape[:2]
    poses.check(n_g, n_c, "the calibration")
    if gratings is None:
        gratings = prov.get("jig_gratings")
    g = np.arange(n_g) if gratings is None else np.unique(np.asarray(gratings, dtype=np.int64).ravel())
    if g.size == 0 or g.min() < 0 or g.max() >= n_g:
        raise ValueError(f"gratings to validate must be in 0–{n_g - 1}, got {g.tolist()}")
    bent = ~poses.is_reference
    if not bent.any():
        raise ValueError(f"{poses.source}: only reference rows (curvature 0); nothing to validate")
    e, _ = poses.strain()
    k_hat = CurvatureSolver(design[g]).solve(e[bent][:, g]).curvature  # (P, G, 2)
    j = jig_curvature(poses.orientation[bent], poses.curvature[bent])  # jig frame
    if fit_roll:
        z = (k_hat[..., 0] + 1j * k_hat[..., 1]) * np.conj(j[:, None, 0] + 1j * j[:, None, 1])
        alpha = float(np.angle(np.nansum(z)))
    elif roll is not None:
        alpha = float(roll)
    elif "jig_roll_rad" in prov:
        alpha = float(prov["jig_roll_rad"])
    else:
        raise ValueError("this calibration records no jig roll; pass the roll (rad) or fit it (--fit-roll)")
    k = j @ _rot(alpha).T
    kappa = np.abs(poses.curvature[bent])
    mag = np.hypot(k_hat[..., 0], k_hat[..., 1]) - kappa[:, None]
    z = (k_hat[..., 0] + 1j * k_hat[..., 1]) * np.conj(k[:, None, 0] + 1j * k[:, None, 1])
    direction = np.angle(z)
    direction = np.where(np.isnan(mag), np.nan, direction)
    s = prov.get("jig_grating_s_m")
    if fiber is not None:
        grating_s = fiber.grating_s[g]
    else:
        grating_s = np.asarray(s, dtype=np.float64)[g] if s is not None else np.full(g.size, np.nan)
    return JigValidation(
        gratings=g,
        grating_s=grating_s,
        orientation=poses.orientation[bent],
        curvature=poses.curvature[bent],
        measured=k_hat,
        magnitude_error=mag,
        direction_error=direction,
        roll=alpha,
        roll_fitted=bool(fit_roll),
        min_curvature=float(min_curvature),
        source=poses.source,
    )


def cross_validate(
    fiber: FiberModel,
    poses: JigPoses,
    holdout,
    *,
    model: str = "physical",
    gratings=None,
    trust_references: bool = False,
    min_curvature: float = 0.8,
) -> tuple[JigFit, JigValidation]:
    """Fit on the orientations not in ``holdout`` and validate on those in it — how to judge a calibration.

    Parameters
    ----------
    holdout : sequence of float
        Orientations to validate on, rad (matched within 1e-3 rad); the rest are fitted.
    model, gratings, trust_references : see :func:`fit`.
    """
    test = match_orientations(poses, holdout)
    if test.all():
        raise ValueError(f"{poses.source}: every orientation is held out; leave at least two to fit on")
    result = fit(fiber, poses.select(~test), model=model, gratings=gratings, trust_references=trust_references)
    check = validate(result.calibration, poses.select(test), fiber=fiber, min_curvature=min_curvature)
    return result, check
