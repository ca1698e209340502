"""Parameter identification from shapes of known geometry (docs/math.md §5).

The shape depends on the fibre parameters only through the outer-core spacing Δθ and the gain g = r·S_ε
(docs/math.md §5.1), so the default fits Θ = [Δθ, g] by trust-region least squares on a smooth residual: for each
shape, the reconstruction at the ground truth's arc lengths, rigidly registered to it (Kabsch), minus the
ground truth (docs/math.md §5.3, formulation D). Ground truths without arc lengths use point-to-curve distances after
ICP (formulation B). The paper's formulation — Θ = [Δθ, r, S_ε] minimising Σ_shapes max distance — is available
and reports the r–S_ε degeneracy instead of returning an arbitrary point of the valley r·S_ε = const.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from twin import metrics
from twin.calibration import Calibration, nominal_delta_theta, nominal_gain
from twin.fiber import FiberModel
from twin.reconstruct import Reconstructor

__all__ = [
    "Identification",
    "Observation",
    "identify",
    "paper_cost",
    "parameter_jacobian",
    "read_truth",
    "write_truth",
]

FORMULATIONS = ("lsq", "paper")


@dataclass(frozen=True, eq=False)
class Observation:
    """One shape of known geometry and what the sensor reported in it.

    Attributes
    ----------
    wavelengths : ndarray, shape (n_frames, n_gratings, n_cores) or (n_gratings, n_cores)
        Peak wavelengths recorded in the shape, nm; frames are averaged (missing peaks ignored).
    truth : ndarray, shape (m, 3)
        Ground-truth centreline points, m, in any frame (registration removes the rigid motion).
    truth_s : ndarray, shape (m,), optional
        Arc length of each truth point from the fibre base, m, when known (a CAD model, a simulation); without
        it the fit uses point-to-curve distances.
    name : str
    """

    wavelengths: np.ndarray
    truth: np.ndarray
    truth_s: np.ndarray | None = None
    name: str = ""

    def __post_init__(self) -> None:
        w = np.asarray(self.wavelengths, dtype=np.float64)
        if w.ndim == 3:
            with warnings.catch_warnings():  # a peak lost in every frame stays NaN: that grating drops out
                warnings.simplefilter("ignore", RuntimeWarning)
                w = np.nanmean(w, axis=0)
        if w.ndim != 2:
            raise ValueError(f"observation {self.name!r}: wavelengths must be (n_frames, n_gratings, n_cores)")
        g = np.asarray(self.truth, dtype=np.float64)
        if g.ndim != 2 or g.shape[1] != 3 or len(g) < 3 or not np.isfinite(g).all():
            raise ValueError(f"observation {self.name!r}: truth must be ≥ 3 finite points of shape (m, 3) in m")
        s = self.truth_s
        if s is not None:
            s = np.asarray(s, dtype=np.float64)
            if s.shape != (len(g),) or not np.isfinite(s).all():
                raise ValueError(f"observation {self.name!r}: truth_s must be {len(g)} finite arc lengths in m")
        object.__setattr__(self, "wavelengths", w)
        object.__setattr__(self, "truth", g)
        object.__setattr__(self, "truth_s", s)


@dataclass(frozen=True, eq=False)
class Identification:
    """Result of :func:`identify`.

    Attributes
    ----------
    delta_theta : float
        Outer-core spacing, rad.
    gain : float
        g = r·S_ε, m.
    delta_theta_std, gain_std : float
        1σ uncertainties (rad, m): the larger of the residual-based and the leave-one-shape-out (jackknife)
        estimates, since residuals along a curve are strongly correlated.
    covariance : ndarray (2, 2)
        Residual-based covariance of (Δθ, g), rad and m.
    formulation : str
    radius, strain_sensitivity : float or None
        The paper formulation's r (m) and S_ε — one arbitrary point of the r·S_ε valley.
    degeneracy : str or None
        What the paper formulation could not determine, and why.
    singular_values : ndarray
        Of the smooth residual's Jacobian w.r.t. the fitted parameters (log-parameters for r, S_ε).
    rms_start, rms_end : float
        RMS registered residual before and after, m.
    shape_max_error : ndarray (n_shapes,)
        Max registered distance per shape at the result, m.
    nfev : int
    """

    delta_theta: float
    gain: float
    delta_theta_std: float
    gain_std: float
    covariance: np.ndarray
    formulation: str
    rms_start: float
    rms_end: float
    shape_max_error: np.ndarray
    nfev: int
    singular_values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    radius: float | None = None
    strain_sensitivity: float | None = None
    degeneracy: str | None = None

    def calibration(self, base: Calibration | None = None) -> Calibration:
        """``base`` (reference wavelengths, twist) with these parameters."""
        base = base or Calibration()
        provenance = dict(base.provenance)
        provenance.update({"identified_by": f"twin.calibration.identify ({self.formulation})",
                           "identification_rms_m": self.rms_end})
        return base.replace(delta_theta=self.delta_theta, gain=self.gain, delta_theta_std=self.delta_theta_std,
                            gain_std=self.gain_std, provenance=provenance)


class _Problem:
    """Residuals for a set of observations with one reconstructor and calibration base."""

    def __init__(self, fiber, observations, calibration, reconstructor_options):
        self.obs = list(observations)
        if not self.obs:
            raise ValueError("identify: no observations")
        for o in self.obs:
            if o.wavelengths.shape != (fiber.n_gratings, fiber.n_cores):
                raise ValueError(f"observation {o.name!r}: wavelengths are {o.wavelengths.shape}, the fibre has "
                                 f"{fiber.n_gratings} gratings × {fiber.n_cores} cores")
            if o.truth_s is not None and (o.truth_s.min() < -1e-9 or o.truth_s.max() > fiber.sensed_length + 1e-9):
                raise ValueError(f"observation {o.name!r}: truth_s runs outside the sensed length "
                                 f"[0, {fiber.sensed_length}] m")
        self.base = calibration or Calibration()
        self.rec = Reconstructor(fiber, self.base, **(reconstructor_options or {}))
        self.w = np.stack([o.wavelengths for o in self.obs])

    def shapes(self, delta_theta: float, gain: float):
        rec = self.rec.with_calibration(self.base.replace(delta_theta=delta_theta, gain=gain, design=None))
        return rec(self.w)

    def residual(self, delta_theta: float, gain: float) -> np.ndarray:
        """Smooth registered residuals of all shapes, m (formulation D, or B without arc lengths)."""
        shape = self.shapes(delta_theta, gain)
        out = []
        for i, o in enumerate(self.obs):
            if not np.isfinite(shape.positions[i]).all():
                raise ValueError(f"observation {o.name!r}: no usable gratings at Δθ = {delta_theta}, g = {gain}")
            if o.truth_s is not None:
                x = shape[i].positions_at(np.clip(o.truth_s, 0.0, self.rec.s[-1]))
                r, t = metrics.kabsch(x, o.truth)
                out.append((x @ r.T + t - o.truth).ravel())
            else:
                out.append(self.truth_distances(shape, i))
        return np.concatenate(out)

    def _icp_start(self, shape, i: int):
        """Initial registration of truth ``i`` onto its reconstruction: Kabsch on arc-length correspondences, or
        on equally spaced samples of both curves when the truth has no arc lengths (docs/math.md §5.2)."""
        o = self.obs[i]
        if o.truth_s is not None:
            return metrics.kabsch(o.truth, shape[i].positions_at(np.clip(o.truth_s, 0.0, self.rec.s[-1])))
        x = shape.positions[i]
        idx = np.linspace(0, len(o.truth) - 1, 20).round().astype(int)
        jdx = np.linspace(0, len(x) - 1, 20).round().astype(int)
        return metrics.kabsch(o.truth[idx], x[jdx])

    def truth_distances(self, shape, i: int, translation: bool = False) -> np.ndarray:
        """Distances d_j of the truth points of shape ``i`` to its reconstruction after ICP (the paper's d_j),
        and with ``translation`` after the brute-force translation search too; m."""
        o, x = self.obs[i], shape.positions[i]
        r, t, d = metrics.icp(o.truth, x, *self._icp_start(shape, i))
        if translation:
            # moving the truth by −t' is moving the reconstruction by +t'
            _, dmax = metrics.translation_search(o.truth @ r.T + t, x)
            return np.atleast_1d(dmax)
        return d

    def max_distances(self, delta_theta: float, gain: float) -> np.ndarray:
        """The paper's per-shape max distance of truth points to the reconstruction after ICP, m."""
        shape = self.shapes(delta_theta, gain)
        return np.array([self.truth_distances(shape, i).max() for i in range(len(self.obs))])


def identify(
    fiber: FiberModel,
    observations: Sequence[Observation],
    calibration: Calibration | None = None,
    *,
    formulation: str = "lsq",
    x0: Sequence[float] | None = None,
    bounds: tuple[Sequence[float], Sequence[float]] | None = None,
    reconstructor_options: dict | None = None,
    jackknife: bool = True,
) -> Identification:
    """Fit the fibre parameters to shapes of known geometry.

    Parameters
    ----------
    fiber : FiberModel
        Nominal fibre (its core layout fixes what Δθ means: :func:`twin.calibration.scaled_core_angles`).
    observations : sequence of Observation
        Include 3D shapes: from planar shapes alone Δθ is only weakly identifiable (docs/math.md §5.1).
    calibration : Calibration, optional
        Reference wavelengths and twist to keep (calibrate before identifying).
    formulation : {"lsq", "paper"}
        ``lsq``: Θ = [Δθ, g] on the smooth residual with uncertainties. ``paper``: Θ = [Δθ, r, S_ε] minimising
        Σ max distance (ICP), as in the paper; the result reports the r–S_ε degeneracy.
    x0 : sequence of float, optional
        Start: [Δθ (rad), g (µm)] or, for ``paper``, [Δθ (rad), r (µm), S_ε]; default the nominal fibre.
    bounds : (lower, upper), optional
        In the same units as ``x0``; default Δθ ± 0.15 rad, g (or r) ± 30 %, S_ε in [0.6, 0.95].
    reconstructor_options : dict, optional
        Passed to :class:`~twin.reconstruct.Reconstructor` (identify with the best forward model: the default
        material pipeline; model errors are absorbed into the parameters otherwise, docs/math.md §5.3).
    jackknife : bool
        Also estimate the uncertainty by refitting without each shape in turn (needs ≥ 3 shapes).

    Returns
    -------
    Identification
    """
    if formulation not in FORMULATIONS:
        raise ValueError(f"formulation must be one of {', '.join(FORMULATIONS)}; got {formulation!r}")
    problem = _Problem(fiber, observations, calibration, reconstructor_options)
    dth0 = nominal_delta_theta(fiber) if calibration is None or calibration.delta_theta is None \
        else calibration.delta_theta
    g0 = nominal_gain(fiber) if calibration is None or calibration.gain is None else calibration.gain
    if formulation == "paper":
        return _identify_paper(problem, fiber, dth0, g0, x0, bounds)

    # Parameters kept O(1): Δθ in rad, g in µm.
    x_start = np.array([dth0, g0 * 1e6] if x0 is None else x0, dtype=float)
    lo, hi = bounds or ([x_start[0] - 0.15, x_start[1] * 0.7], [x_start[0] + 0.15, x_start[1] * 1.3])

    def fun(z, prob=problem):
        return prob.residual(z[0], z[1] * 1e-6)

    res0 = fun(x_start)
    sol = least_squares(fun, x_start, bounds=(lo, hi), method="trf", x_scale="jac")
    m, p = sol.fun.size, 2
    jtj = sol.jac.T @ sol.jac
    cov = np.linalg.pinv(jtj) * (2 * sol.cost / max(m - p, 1))
    cov_si = cov * np.outer([1.0, 1e-6], [1.0, 1e-6])
    std = np.sqrt(np.diag(cov_si))
    if jackknife and len(problem.obs) >= 3:
        std = np.maximum(std, _jackknife_std(fiber, problem, sol.x, (lo, hi), reconstructor_options))
    return Identification(
        delta_theta=float(sol.x[0]),
        gain=float(sol.x[1] * 1e-6),
        delta_theta_std=float(std[0]),
        gain_std=float(std[1]),
        covariance=cov_si,
        formulation="lsq",
        rms_start=float(np.sqrt(np.mean(res0**2))),
        rms_end=float(np.sqrt(np.mean(sol.fun**2))),
        shape_max_error=problem.max_distances(sol.x[0], sol.x[1] * 1e-6),
        nfev=int(sol.nfev),
        singular_values=np.linalg.svd(sol.jac, compute_uv=False),
    )


def _jackknife_std(fiber, problem: _Problem, x, bounds, options) -> np.ndarray:
    n = len(problem.obs)
    est = []
    for i in range(n):
        sub = _Problem(fiber, [o for j, o in enumerate(problem.obs) if j != i], problem.base, options)
        sol = least_squares(lambda z, prob=sub: prob.residual(z[0], z[1] * 1e-6), x, bounds=bounds,
                            method="trf", x_scale="jac")
        est.append(sol.x)
    est = np.array(est)
    var = (n - 1) / n * np.sum((est - est.mean(axis=0)) ** 2, axis=0)
    return np.sqrt(var) * np.array([1.0, 1e-6])


def _identify_paper(problem: _Problem, fiber, dth0, g0, x0, bounds) -> Identification:
    s_nom = fiber.strain_sensitivity
    x_start = np.array([dth0, g0 / s_nom * 1e6, s_nom] if x0 is None else x0, dtype=float)
    lo, hi = bounds or ([x_start[0] - 0.15, x_start[1] * 0.7, 0.6], [x_start[0] + 0.15, x_start[1] * 1.3, 0.95])

    def fun(z, prob=problem):
        # residual_k = √max_k so that the sum of squares is the paper's cost Σ_k max_j d_j (eq. 10)
        return np.sqrt(prob.max_distances(z[0], z[1] * 1e-6 * z[2]))

    sol = least_squares(fun, x_start, bounds=(lo, hi), method="trf")
    dth, r_um, s_eps = sol.x
    gain = r_um * 1e-6 * s_eps
    # The degeneracy, from the smooth residual's Jacobian in (Δθ, ln r, ln S_ε) at the result.
    jac = _jacobian(problem, dth, r_um * 1e-6, s_eps)
    _, sv, vt = np.linalg.svd(jac, full_matrices=False)
    null = vt[-1] * np.sign(vt[-1][1] or 1.0)
    note = (
        f"r and S_ε are not separately identifiable: the Jacobian in (Δθ, ln r, ln S_ε) has singular values "
        f"{', '.join(f'{v:.3g}' for v in sv)}, null direction ({null[0]:.3f}, {null[1]:.3f}, {null[2]:.3f}); only "
        f"g = r·S_ε = {gain * 1e6:.4f} µm is determined, and (r = {r_um:.3f} µm, S_ε = {s_eps:.4f}) is one "
        f"arbitrary point of the valley r·S_ε = const (it depends on the start)."
    )
    res_smooth = problem.residual(dth, gain)
    return Identification(
        delta_theta=float(dth),
        gain=float(gain),
        delta_theta_std=float("nan"),
        gain_std=float("nan"),
        covariance=np.full((2, 2), np.nan),
        formulation="paper",
        rms_start=float(np.sqrt(np.mean(problem.residual(x_start[0], x_start[1] * 1e-6 * x_start[2]) ** 2))),
        rms_end=float(np.sqrt(np.mean(res_smooth**2))),
        shape_max_error=sol.fun**2,
        nfev=int(sol.nfev),
        singular_values=sv,
        radius=float(r_um * 1e-6),
        strain_sensitivity=float(s_eps),
        degeneracy=note,
    )


def parameter_jacobian(fiber: FiberModel, observations: Sequence[Observation], delta_theta: float, radius: float,
                       strain_sensitivity: float, calibration: Calibration | None = None,
                       rel_step: float = 1e-6) -> np.ndarray:
    """Jacobian of the smooth residual (m) w.r.t. (Δθ, ln r, ln S_ε), by central differences.

    The ln r and ln S_ε columns coincide: the shape depends on r·S_ε only (docs/math.md §5.1).
    """
    return _jacobian(_Problem(fiber, observations, calibration, None), delta_theta, radius, strain_sensitivity,
                     rel_step)


def _jacobian(problem: _Problem, delta_theta, radius, strain_sensitivity, rel_step: float = 1e-6) -> np.ndarray:
    def f(z):
        return problem.residual(z[0], np.exp(z[1]) * np.exp(z[2]))

    z = np.array([delta_theta, np.log(radius), np.log(strain_sensitivity)])
    cols = []
    for j in range(3):
        dz = np.zeros(3)
        dz[j] = rel_step
        cols.append((f(z + dz) - f(z - dz)) / (2 * rel_step))
    return np.stack(cols, axis=1)


def paper_cost(fiber: FiberModel, observations: Sequence[Observation], calibration: Calibration | None = None,
               *, translation: bool = True, reconstructor_options: dict | None = None) -> np.ndarray:
    """The paper's evaluation metric per shape: max distance of the truth points to the reconstruction after
    ICP and (optionally) the brute-force translation search of ±0.5 mm, m."""
    problem = _Problem(fiber, observations, calibration, reconstructor_options)
    shape = problem.rec(problem.w)
    return np.array([problem.truth_distances(shape, i, translation).max() for i in range(len(problem.obs))])


# ------------------------------------------------------------------------------------------ truth files
TRUTH_COLUMNS = ("s_m", "x_m", "y_m", "z_m")


def write_truth(path, points, s=None) -> None:
    """Write a ground-truth curve: CSV with a header ``s_m,x_m,y_m,z_m`` (``s_m`` only when arc lengths are
    known), one point per row, m; or ``.npy`` of shape (m, 3) points or (m, 4) rows (s, x, y, z)."""
    from pathlib import Path

    path = Path(path)
    pts = np.asarray(points, dtype=np.float64)
    table = pts if s is None else np.column_stack([np.asarray(s, dtype=np.float64), pts])
    if path.suffix == ".npy":
        np.save(path, table)
        return
    header = ",".join(TRUTH_COLUMNS if s is not None else TRUTH_COLUMNS[1:])
    np.savetxt(path, table, delimiter=",", header=header, comments="", fmt="%.9e")


def read_truth(path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a ground-truth curve written as :func:`write_truth` describes (a lab's CT, stereo camera or mould
    model): returns (points (m, 3) in m, arc lengths (m,) in m or None). Errors name the file and line."""
    from pathlib import Path

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such truth file")
    if path.suffix == ".npy":
        a = np.load(path, allow_pickle=False)
        if a.ndim != 2 or a.shape[1] not in (3, 4):
            raise ValueError(f"{path}: expected an array of shape (m, 3) points or (m, 4) rows (s, x, y, z) in m, "
                             f"got {a.shape}")
        a = a.astype(np.float64)
        s, pts = (a[:, 0], a[:, 1:]) if a.shape[1] == 4 else (None, a)
    else:
        lines = path.read_text().splitlines()
        if not lines:
            raise ValueError(f"{path}: empty truth file")
        header = [h.strip() for h in lines[0].split(",")]
        missing = [c for c in TRUTH_COLUMNS[1:] if c not in header]
        if missing:
            raise ValueError(f"{path}: line 1: missing column(s) {', '.join(missing)}; expected a header "
                             f"{','.join(TRUTH_COLUMNS)} (s_m optional), values in m")
        cols = [header.index(c) for c in TRUTH_COLUMNS if c in header]
        rows = []
        for n, line in enumerate(lines[1:], start=2):
            if not line.strip():
                continue
            cells = line.split(",")
            if len(cells) != len(header):
                raise ValueError(f"{path}: line {n}: {len(cells)} cells, the header has {len(header)}")
            try:
                rows.append([float(cells[c]) for c in cols])
            except ValueError:
                raise ValueError(f"{path}: line {n}: a value is not a number: {line.strip()!r}") from None
        a = np.array(rows, dtype=np.float64).reshape(-1, len(cols))
        s, pts = (a[:, 0], a[:, 1:]) if "s_m" in header else (None, a)
    if len(pts) < 3 or not np.isfinite(pts).all() or (s is not None and not np.isfinite(s).all()):
        raise ValueError(f"{path}: expected at least 3 finite points")
    if s is not None and np.any(np.diff(s) <= 0):
        raise ValueError(f"{path}: s_m must increase strictly along the curve")
    if np.abs(pts).max() > 10:
        raise ValueError(f"{path}: coordinates up to {np.abs(pts).max():g}: truth files are in m, not mm")
    return pts, s
