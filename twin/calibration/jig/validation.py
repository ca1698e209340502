"""Jig validation: a calibration's curvature against the jig's on poses (:func:`validate`), cross-validation on
held-out orientations (:func:`cross_validate`) and leave-one-rotation-out statistics
(:func:`leave_one_rotation_out`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.calibration import Calibration
from twin.calibration.jig.fits import JigFit, fit
from twin.calibration.jig.nuisance import median_variance
from twin.calibration.jig.poses import JigPoses, _rot, jig_curvature, match_orientations
from twin.calibration.jig.score import ALL_LEVELS, CLINICAL, Bands, JigScore, cells, coverage, score
from twin.fiber import FiberModel
from twin.strain import CurvatureSolver


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
    magnitude_sigma : ndarray, shape (P, G), or None
        Stated 1σ of |k̂| about its expected value, 1/m, from the calibration's error model (``nuisance``
        calibrations; None otherwise).
    magnitude_bias : ndarray, shape (G,), or None
        Expected |k̂| − κ in this jig, 1/m: 0 when the jig's zero was added, else minus the jig's zero along the
        bend (the bent grooves hold the sensor less bent than labelled). The 95 % interval of κ is |k̂| − bias ± 1.96σ.
    jig_zero : ndarray, shape (G, 2), or None
        The jig's zero (along, across the bend, 1/m) added to every k̂ (docs/jig.md, "The jig's zero"): the
        poses are labelled by this jig's grooves, whose shortfall the calibration carries; None when not
        added (``jig_zero=False``, or a calibration without one). ``measured`` includes it.
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
    magnitude_sigma: np.ndarray | None = None
    magnitude_bias: np.ndarray | None = None
    jig_zero: np.ndarray | None = None

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
        cover, n_cover = self.coverage()
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
            "coverage_95": cover,
            "n_coverage": n_cover,
            "score": self.score(CLINICAL).to_dict(),
            "score_all_levels": self.score(ALL_LEVELS).to_dict(),
        }

    def score(self, bands: Bands = CLINICAL) -> JigScore:
        """The one figure of merit (:mod:`twin.calibration.jig.score`) over rotation × grating × level cells."""
        _, levels, rms, mean = cells(self.orientation, self.curvature, self.magnitude_error, self.direction_error)
        return score(levels, rms, mean, bands)

    def coverage(self) -> tuple[float | None, int]:
        """Fraction of bent poses × gratings whose κ lies in the stated 95 % interval, and how many were judged
        (None, 0 without an error model)."""
        if self.magnitude_sigma is None:
            return None, 0
        return coverage(self.magnitude_error - self.magnitude_bias, self.magnitude_sigma)

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
            "jig_zero_1_per_m": None if self.jig_zero is None else self.jig_zero.tolist(),
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
    jig_zero: bool = False,
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
    jig_zero : bool
        Add the jig's zero the calibration carries (``provenance['jig_zero_1_per_m']``) to every k̂, turned into
        the sensor's frame by the pose's rotation: this jig's bent grooves hold the sensor less bent than their labels
        by that much, so k̂ + zero is the curvature the label states (docs/jig.md,
        "The jig's zero"). False (default): k̂ is the change from each rotation's reference, as if that reference
        were straight. Only for poses zeroed in the jig the calibration was made in.
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
    kappa = np.abs(poses.curvature[bent])
    zero = _jig_zero(prov, g) if jig_zero else None
    zc = np.zeros(g.size, complex) if zero is None else zero[:, 0] + 1j * zero[:, 1]  # along + i across
    if fit_roll:  # the roll that best maps k̂ + zero onto the labels: k̂ ≈ (κ − zero) e^{i(α − ψ)}
        jc = (j[:, 0] + 1j * j[:, 1])[:, None] * (1.0 - zc[None, :] / kappa[:, None])
        z = (k_hat[..., 0] + 1j * k_hat[..., 1]) * np.conj(jc)
        alpha = float(np.angle(np.nansum(z)))
    elif roll is not None:
        alpha = float(roll)
    elif "jig_roll_rad" in prov:
        alpha = float(prov["jig_roll_rad"])
    else:
        raise ValueError("this calibration records no jig roll; pass the roll (rad) or fit it (--fit-roll)")
    k = j @ _rot(alpha).T
    sigma = _magnitude_sigma(prov, design, g, k_hat, k) if "jig_error_strain_cov" in prov else None
    if zero is not None:  # the zero turns with the sensor: along and across the pose's bend direction
        bend = (k[:, 0] + 1j * k[:, 1]) / kappa
        shift = zc[None, :] * bend[:, None]
        k_hat = k_hat + np.stack([shift.real, shift.imag], axis=-1)
    mag = np.hypot(k_hat[..., 0], k_hat[..., 1]) - kappa[:, None]
    z = (k_hat[..., 0] + 1j * k_hat[..., 1]) * np.conj(k[:, None, 0] + 1j * k[:, None, 1])
    direction = np.angle(z)
    direction = np.where(np.isnan(mag), np.nan, direction)
    bias = None
    if sigma is not None:  # the interval's centre: what is left of the jig's zero along the bend
        carried = _jig_zero(prov, g)
        bias = np.zeros(g.size) if zero is not None or carried is None else -carried[:, 0]
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
        magnitude_sigma=sigma,
        magnitude_bias=bias,
        jig_zero=zero,
    )


def _jig_zero(prov: dict, g: np.ndarray) -> np.ndarray | None:
    """The calibration's jig zero at gratings ``g`` (G, 2: along, across), 1/m; 0 at gratings it did not fit (their
    nominal design knows no jig), None when it carries none. Older ``nuisance`` calibrations carry only their
    fitted mean reference curvature, ``jig_reference_bias_1_per_m``, which is the same quantity."""
    key = "jig_zero_1_per_m" if "jig_zero_1_per_m" in prov else "jig_reference_bias_1_per_m"
    if key not in prov:
        return None
    fitted = [int(n) for n in prov.get("jig_gratings", [])]
    zero = np.asarray(prov[key], dtype=np.float64)
    out = np.zeros((g.size, 2))
    for i, n in enumerate(g):  # a few gratings
        if int(n) in fitted:
            out[i] = zero[fitted.index(int(n))]
    return np.where(np.isfinite(out), out, 0.0)


def _magnitude_sigma(prov: dict, design: np.ndarray, g: np.ndarray, k_hat: np.ndarray, k: np.ndarray):
    """1σ of |k̂| (P, G) about the jig's label from a calibration's error model (``jig_*`` provenance of a
    ``nuisance`` fit), 1/m.

    The curvature error covariance of a pose at grating n, in the fibre frame, is

        C = M Σ_e Mᵀ + (1 + v_n_o)(σ_along² u uᵀ + σ_across² w wᵀ) + κ² (σ_roll² w wᵀ + σ_gain² u uᵀ)
            + ((κ − κ̄)² + κ²/n) (σ_roll,n² w wᵀ + σ_gain,n² u uᵀ) + M (I ⊗ k̂ᵀ) Σ_p (I ⊗ k̂) Mᵀ,

    with M the calibration's strain → curvature map (rows 1–2 of the design's pseudo-inverse), Σ_e the per-pose
    strain error covariance (pose + groove seating), u the jig's bend direction and w ⟂ u, σ_along, σ_across the
    scatter of the rotations' reference curvature (a new rotation's zero about the jig's zero, the median of the
    n_o fitted rotations', whose own variance is v_n_o times theirs: :func:`~twin.calibration.jig.nuisance.
    median_variance`), σ_roll and σ_gain that of the seatings' roll and gain shared by the gratings, σ_roll,n and
    σ_gain,n what each grating adds — twice: the pose's own seating, about the calibration's mean groove curvature
    κ̄ (``jig_mean_curvature_1_per_m``; each rotation's zero, whose scatter is σ_along, σ_across, holds the slope's
    value there), and the map, which took it from the n fitted rotations on the pose's axis (1 when none is) — and
    Σ_p the covariance of the design's bend columns (the parameters). The stated σ is that of the radial
    component, ûᵀ C û with û = k̂/|k̂|. Gratings the error model does not cover get NaN. A calibration without
    κ̄ (made before it was recorded) takes κ̄ = 0.
    """
    fit_g = list(prov.get("jig_gratings", []))
    strain_cov = np.asarray(prov["jig_error_strain_cov"], dtype=np.float64)
    pos_cov = np.asarray(prov["jig_positions_cov_m2"], dtype=np.float64)
    s_roll, s_gain = float(prov["jig_reseat_roll_std_rad"]), float(prov["jig_reseat_gain_std"])
    ref_std = np.asarray(prov["jig_reference_std_1_per_m"], dtype=np.float64)
    l_roll, l_gain = float(prov["jig_local_roll_std_rad"]), float(prov["jig_local_gain_std"])
    fitted = np.asarray(prov["jig_orientations_rad"], dtype=np.float64)
    # a new rotation's zero scatters about the jig's zero, itself the median of the fitted rotations' zeros
    zero_err = 1.0 + median_variance(fitted.size)
    kappa_mean = float(prov.get("jig_mean_curvature_1_per_m", 0.0))
    psi = float(prov["jig_roll_rad"]) - np.arctan2(k[:, 1], k[:, 0])  # each pose's rotation, from its label
    n_axis = np.maximum(np.sum(np.abs(np.sin(psi[:, None] - fitted[None, :])) < np.sin(np.deg2rad(10.0)), axis=1),
                        1)
    n_c = design.shape[1]
    out = np.full(k_hat.shape[:2], np.nan)
    kappa = np.hypot(k[:, 0], k[:, 1])
    u = k / np.maximum(kappa, 1e-300)[:, None]
    w = np.stack([-u[:, 1], u[:, 0]], axis=-1)
    loc = (kappa - kappa_mean) ** 2 + kappa**2 / n_axis  # own seating about κ̄, the map's inherited about 0
    jig_part = ((kappa**2 * s_roll**2 + loc * l_roll**2)[:, None, None] * np.einsum("pa,pb->pab", w, w)
                + (kappa**2 * s_gain**2 + loc * l_gain**2)[:, None, None] * np.einsum("pa,pb->pab", u, u))
    for i, n in enumerate(g):  # a few gratings
        if int(n) not in fit_g:
            continue
        f = fit_g.index(int(n))
        ref_part = (ref_std[f, 0] ** 2 * np.einsum("pa,pb->pab", u, u)
                    + ref_std[f, 1] ** 2 * np.einsum("pa,pb->pab", w, w))
        m = np.linalg.pinv(design[n])[1:]  # (2, C)
        kh = k_hat[:, i]
        lift = np.einsum("ce,pk->pcek", np.eye(n_c), kh).reshape(-1, n_c, 2 * n_c)  # (I ⊗ k̂ᵀ)
        ml = np.einsum("ac,pcx->pax", m, lift)
        pose_cov = m @ strain_cov[f] @ m.T + np.einsum("pax,xy,pby->pab", ml, pos_cov[f], ml)
        r = np.hypot(kh[:, 0], kh[:, 1])
        uh = kh / np.where(r > 0, r, np.nan)[:, None]
        cov = pose_cov + zero_err * ref_part + jig_part
        out[:, i] = np.sqrt(np.einsum("pa,pab,pb->p", uh, cov, uh))
    return out


def cross_validate(
    fiber: FiberModel,
    poses: JigPoses,
    holdout,
    *,
    model: str = "physical",
    gratings=None,
    trust_references: bool = False,
    min_curvature: float = 0.8,
    jig_zero: bool = False,
) -> tuple[JigFit, JigValidation]:
    """Fit on the orientations not in ``holdout`` and validate on those in it — how to judge a calibration.

    Parameters
    ----------
    holdout : sequence of float
        Orientations to validate on, rad (matched within 1e-3 rad); the rest are fitted.
    model, gratings, trust_references : see :func:`fit`.
    jig_zero : bool
        See :func:`validate`.
    """
    test = match_orientations(poses, holdout)
    if test.all():
        raise ValueError(f"{poses.source}: every orientation is held out; leave at least two to fit on")
    result = fit(fiber, poses.select(~test), model=model, gratings=gratings, trust_references=trust_references)
    check = validate(result.calibration, poses.select(test), fiber=fiber, min_curvature=min_curvature,
                     jig_zero=jig_zero)
    return result, check


@dataclass(frozen=True, eq=False)
class LoroStatistics:
    """A jig table's own statistics: the in-sample strain residual and the leave-one-rotation-out errors.

    Each orientation in turn is held out: the calibration is fitted on the others and validated on it. The errors
    are summarised per held-out orientation o, grating n and curvature level κ over the trials of that level:

    * ``kappa_rms[o, n, l]`` — RMS of Δκ = |k̂| − κ, 1/m;
    * ``direction_mean[o, n, l]`` — mean signed direction error, rad (a systematic rotation; the trial scatter
      averages out).

    The scalar figures are medians over o, n and the bent levels (direction: levels ≥ ``min_curvature``), so one
    bad rotation or grating does not dominate them, and they compare a twin with a real table (``twin run
    real-jig``).

    Attributes
    ----------
    gratings : ndarray of int, shape (G,)
    orientations : ndarray, shape (O,)
        Held-out orientations, rad.
    levels : ndarray, shape (L,)
        Bent curvature levels, 1/m.
    kappa_rms, direction_mean : ndarray, shape (O, G, L)
    rms_strain_residual : float
        RMS strain residual of the fit on all orientations, over the gratings (dimensionless).
    min_curvature : float
        1/m.
    model : str
    coverage_95 : float or None
        Fraction of held-out poses × gratings whose κ lies in the calibration's stated 95 % interval (models with
        an error model: ``nuisance``; None otherwise).
    n_coverage : int
        How many were judged.
    jig_zero : bool
        Whether the jig's zero was added to the held-out curvatures (:func:`validate`).
    """

    gratings: np.ndarray
    orientations: np.ndarray
    levels: np.ndarray
    kappa_rms: np.ndarray
    direction_mean: np.ndarray
    rms_strain_residual: float
    min_curvature: float
    model: str = "physical"
    coverage_95: float | None = None
    n_coverage: int = 0
    jig_zero: bool = False

    @property
    def kappa_error(self) -> float:
        """Median of the per-level RMS |κ| error, 1/m."""
        return float(np.nanmedian(self.kappa_rms))

    @property
    def direction_error(self) -> float:
        """Median |mean direction error| over levels ≥ ``min_curvature``, rad."""
        big = self.levels >= self.min_curvature
        return float(np.nanmedian(np.abs(self.direction_mean[:, :, big])))

    def score(self, bands: Bands = CLINICAL) -> JigScore:
        """The one figure of merit (:mod:`twin.calibration.jig.score`) over held-out rotation × grating × level."""
        return score(self.levels, self.kappa_rms, self.direction_mean, bands)

    def to_dict(self) -> dict:
        """The three figures (strain dimensionless, 1/m, deg) and the per-level arrays, JSON-ready."""
        return {
            "rms_strain_residual": self.rms_strain_residual,
            "loro_kappa_error_1_per_m": _stat(np.nanmedian, self.kappa_rms),
            "loro_direction_error_deg": _stat(lambda d: np.rad2deg(np.nanmedian(np.abs(d))),
                                              self.direction_mean[:, :, self.levels >= self.min_curvature]),
            "gratings": self.gratings.tolist(),
            "orientations_rad": self.orientations.tolist(),
            "levels_1_per_m": self.levels.tolist(),
            "min_curvature_1_per_m": self.min_curvature,
            "model": self.model,
            "jig_zero": self.jig_zero,
            "score": self.score(CLINICAL).to_dict(),
            "score_all_levels": self.score(ALL_LEVELS).to_dict(),
            "coverage_95": self.coverage_95,
            "n_coverage": self.n_coverage,
            "kappa_rms_1_per_m": _json_array(np.round(self.kappa_rms, 6)),
            "direction_mean_deg": _json_array(np.round(np.rad2deg(self.direction_mean), 4)),
        }


def _json_array(a: np.ndarray) -> list:
    """Nested lists with None where a level had no valid pose (JSON has no NaN)."""
    return np.where(np.isnan(a), None, a).tolist()


def leave_one_rotation_out(
    fiber: FiberModel,
    poses: JigPoses,
    *,
    model: str = "physical",
    gratings=None,
    trust_references: bool = False,
    min_curvature: float = 0.8,
    terms=None,
    jig_zero: bool = False,
) -> LoroStatistics:
    """Fit on all orientations but one, validate on that one, for each orientation in turn (and once on all).

    Parameters
    ----------
    fiber, poses, model, gratings, trust_references, terms : see :func:`fit`.
    min_curvature : float
        Direction errors are summarised over levels ≥ this, 1/m.
    jig_zero : bool
        Add the jig's zero the calibration fitted on the other rotations to the held-out one's curvature
        (:func:`validate`).
    """
    extra = {} if terms is None else {"terms": terms}
    orientations = np.unique(poses.orientation)
    if orientations.size < 3:
        raise ValueError(f"{poses.source}: leave-one-rotation-out needs at least 3 orientations, "
                         f"got {orientations.size}")
    full = fit(fiber, poses, model=model, gratings=gratings, trust_references=trust_references, **extra)
    levels = np.unique(np.abs(poses.curvature[~poses.is_reference]))
    g = full.gratings
    checks = []
    for psi in orientations:
        result = fit(fiber, poses.select(~match_orientations(poses, [psi])), model=model, gratings=g,
                     trust_references=trust_references, **extra)
        checks.append(validate(result.calibration, poses.select(match_orientations(poses, [psi])), fiber=fiber,
                               min_curvature=min_curvature, jig_zero=jig_zero))
    _, _, kappa_rms, direction = cells(np.concatenate([c.orientation for c in checks]),
                                       np.concatenate([c.curvature for c in checks]),
                                       np.concatenate([c.magnitude_error for c in checks]),
                                       np.concatenate([c.direction_error for c in checks]),
                                       orientations=orientations, levels=levels)
    judged = [c for c in checks if c.magnitude_sigma is not None]
    cover, n_cover = (coverage(np.concatenate([c.magnitude_error - c.magnitude_bias for c in judged]),
                               np.concatenate([c.magnitude_sigma for c in judged])) if judged else (None, 0))
    return LoroStatistics(
        gratings=g,
        orientations=orientations,
        levels=levels,
        kappa_rms=kappa_rms,
        direction_mean=direction,
        rms_strain_residual=float(np.sqrt(np.mean(full.rms_strain_residual**2))),
        min_curvature=float(min_curvature),
        model=model,
        coverage_95=cover,
        n_coverage=n_cover,
        jig_zero=bool(jig_zero),
    )
