"""Jig poses: the pose table (:class:`JigPoses`), its CSV form (:func:`read_poses`, :func:`write_poses`) and the
jig's curvature in the fibre frame (:func:`jig_curvature`). Conventions: :mod:`twin.calibration.jig`, docs/jig.md."""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin.fiber import FiberModel

MODELS = ("physical", "matrix", "linear", "nuisance")
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

    def reference_scatter(self) -> np.ndarray:
        """How far the trials of each orientation's reference disagree, against the table's usual trial scatter.

        Per orientation and grating: the scatter over the reference rows of the wavelengths less their mean over
        the cores (a common shift, temperature or axial strain, is no bend and does not move the zero), root-sum-
        square over the cores, divided by the median of the same over every groove (reference or bent) of every
        orientation with two or more trials. A reference whose trials disagree ten times more than the grooves'
        usually do has a disturbed peak (docs/jig.md, "The jig's zero"); its zero is uncertain.

        Returns
        -------
        ndarray, shape (n_orientations, n_gratings)
            NaN where an orientation has a single reference row or the table has no groove with two trials.
        """
        _, groove = np.unique(np.stack([self._index, self.curvature]), axis=1, return_inverse=True)
        groove = np.ravel(groove)
        onehot = np.eye(int(groove.max()) + 1)[groove]  # (P, S)
        with np.errstate(invalid="ignore", divide="ignore"):
            lam = self.wavelengths - np.mean(self.wavelengths, axis=2, keepdims=True)  # NaN: a lost peak
            ok = np.all(np.isfinite(lam), axis=2)  # (P, G): rows with every peak of the grating
            lam = np.where(ok[..., None], lam, 0.0)
            n = np.einsum("ps,pg->sg", onehot, ok.astype(float))
            mean = np.einsum("ps,pgc->sgc", onehot, lam) / n[..., None]
            dev2 = np.where(ok, np.sum((lam - mean[groove]) ** 2, axis=2), 0.0)
            sd = np.where(n >= 2, np.sqrt(np.einsum("ps,pg->sg", onehot, dev2) / (n - 1)), np.nan)
            usual = np.nanmedian(sd, axis=0) if np.isfinite(sd).any() else np.full(sd.shape[1], np.nan)
            ref_groove = np.zeros(self._orientations.size, dtype=np.int64)
            ref_groove[self._index[self.is_reference]] = groove[self.is_reference]
            return sd[ref_groove] / usual

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
