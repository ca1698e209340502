"""Jig fits: the ``physical`` and ``matrix`` models and the gauge that fixes what a jig cannot tell
(:func:`fit`, :class:`JigFit`, :func:`gauge_layout`). The models are described in :mod:`twin.calibration.jig`.

One cohesive thing (the two estimators share the forward fit, its gauge and its statistics), hence its length."""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass

import numpy as np

from twin.calibration import Calibration
from twin.calibration.jig.nuisance import DEFAULT_TERMS, NuisanceFit, fit_nuisance
from twin.calibration.jig.poses import MODELS, JigPoses, _rot, _wrap, jig_curvature, match_orientations
from twin.fiber import FiberModel
from twin.strain import CurvatureSolver, design_matrix

#: A reference whose trials scatter this many times more than the table's grooves usually do is reported
#: (:meth:`~twin.calibration.jig.poses.JigPoses.reference_scatter`): on the two AMIRo tables every reference is
#: within 3 times, and needle_3CH_3AA's 270° reference, whose CH2 AA2 peak is disturbed, 14 times.
DISTURBED_REFERENCE = 10.0


@dataclass(frozen=True, eq=False)
class JigFit:
    """A jig calibration and what it found (per-grating arrays follow :attr:`gratings`).

    Attributes
    ----------
    model : {"physical", "matrix", "linear", "nuisance"}
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
    nuisance : NuisanceFit or None
        ``nuisance`` model only: the jig errors it estimated and the fitted error covariances.
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
    nuisance: NuisanceFit | None = None

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
            "jig_errors": None if self.nuisance is None else {
                "terms": sorted(self.nuisance.terms),
                "reseat_roll_deg": np.rad2deg(np.angle(self.nuisance.gain)).tolist(),
                "reseat_gain": np.abs(self.nuisance.gain).tolist(),
                "reseat_roll_std_deg": float(np.rad2deg(self.nuisance.roll_std)),
                "reseat_gain_std": self.nuisance.gain_std,
                "iterations": self.nuisance.iterations,
            },
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
    terms=DEFAULT_TERMS,
) -> JigFit:
    """Fit a jig calibration (see the module docstring for the models and conventions).

    Parameters
    ----------
    fiber : FiberModel
        The nominal sensor (core layout, gratings); its angles fix the frame, it is not otherwise trusted.
    poses : JigPoses
    model : {"physical", "matrix", "linear", "nuisance"}
        ``linear`` is the plain baseline: per grating, k = M e fitted by ordinary least squares on the bent poses
        (common mode removed, M·1 = 0, no weights, references taken as exact). ``nuisance`` estimates the jig's
        errors beside the sensor (:mod:`twin.calibration.jig.nuisance`).
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
    terms : iterable of str
        ``nuisance`` model only: the jig errors to estimate, some of :data:`~twin.calibration.jig.nuisance.TERMS`
        (default :data:`~twin.calibration.jig.nuisance.DEFAULT_TERMS`; ``trust_references`` drops ``"offset"``).

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
    trust = trust_references or model == "linear"  # the plain baseline takes the references as they are
    # the nuisance model's zero per rotation is free: the reference rows, which only define the strain's zero, would
    # pin it (their strain is 0 by construction), so they are left out and the zero rests on the bent poses alone
    free_zero = model == "nuisance" and "offset" in frozenset(terms)
    rows = bent if trust or free_zero else np.ones(poses.n_poses, bool)
    e, j = e_all[rows], jig_curvature(poses.orientation[rows], poses.curvature[rows])
    group = None if trust else poses.orientation_index[rows]
    n_groups = poses.orientations.size
    ev = np.linalg.eigvalsh(j.T @ j)
    if ev[0] < 1e-6 * ev[-1]:
        listed = ", ".join(f"{x:.4g}" for x in poses.orientations)
        raise ValueError(
            f"{poses.source}: the fit poses bend the sensor in one plane only (orientations {listed} rad are equal "
            "or opposite); fit on at least two orientations that are not 0 or π apart"
        )
    # the interrogator's standard errors weight the physical and matrix models; the linear baseline is unweighted
    # and the nuisance model weights by the error covariance it fits
    interrogator = sigma_all is not None and model in ("physical", "matrix")
    w = 1.0 / sigma_all[rows] ** 2 if interrogator else np.ones(e.shape)
    w = np.where(np.isfinite(e), w, 0.0)
    q = _centred_basis(fiber.n_cores)
    n_fit, n_c = fit_g.size, fiber.n_cores
    beta = np.zeros((n_fit, n_c, 2))
    cov = np.zeros((n_fit, 2 * n_c, 2 * n_c))
    chi2 = np.zeros(n_fit)
    inverse_model = model in ("matrix", "linear")
    matrix = np.zeros((n_fit, 2, n_c)) if inverse_model else None
    matrix_std = np.zeros((n_fit, 2, n_c)) if inverse_model else None
    rms, explained = np.zeros(n_fit), np.zeros(n_fit)
    nuisance = None
    if model == "nuisance":  # all gratings at once: the seating errors are shared by them
        o_idx = poses.orientation_index[rows]
        _, seat = np.unique(np.stack([o_idx, poses.curvature[rows]]), axis=1, return_inverse=True)
        nuisance = fit_nuisance(e[:, fit_g], j, o_idx, n_groups, np.ravel(seat), q,
                                terms=frozenset(terms) - ({"offset"} if trust else set()))
        if nuisance is None:
            raise ValueError(f"{poses.source}: too few usable poses to fit the nuisance model")
    for i, n in enumerate(fit_g):  # a few gratings; each fit is vectorised over poses and cores
        inverse = ()
        if model == "nuisance":
            out = (nuisance.beta[i], nuisance.beta_cov[i], nuisance.offsets[o_idx, i], np.nan)
        elif model == "linear":  # no forward fit: the map alone, its frame and layout from its inverse
            inverse = _fit_matrix(e[:, n], j, q, None, 0)
            out = None if inverse is None else (np.linalg.pinv(inverse[0]), np.full((2 * n_c, 2 * n_c), np.nan),
                                                np.zeros(e[:, n].shape), np.nan)
        else:  # the forward (physical) fit runs for both: it sets the frame, the layout and the fit statistics
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
        if inverse_model:
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
    if inverse_model:  # into the fibre frame: k = R(α) j
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
    scatter = poses.reference_scatter()[:, fit_g]  # (O, G)
    for o, i in zip(*np.nonzero(scatter > DISTURBED_REFERENCE), strict=True):
        warnings.append(f"orientation {np.rad2deg(poses.orientations[o]):.4g}°: the reference trials disagree at "
                        f"grating {int(fit_g[i])} {scatter[o, i]:.0f} times more than a groove's trials usually do "
                        "(common shift removed); a disturbed peak? That rotation's zero is uncertain")
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
    if not inverse_model:
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
    if inverse_model:
        provenance["jig_matrix_1_per_m"] = matrix.tolist()
        provenance["jig_matrix_std_1_per_m"] = matrix_std.tolist()
    if nuisance is not None:
        provenance.update(_error_model(fiber, nuisance, alpha))
    zeros = rotation_zeros(design[fit_g], alpha, e_all[bent][:, fit_g], poses.orientation[bent],
                           poses.curvature[bent], poses.orientation_index[bent], n_groups)
    provenance["jig_zero_1_per_m"] = np.nanmedian(zeros, axis=0).tolist()
    provenance["jig_rotation_zeros_1_per_m"] = zeros.tolist()
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
        chi2_reduced=chi2 if interrogator else None,
        orientations=poses.orientations,
        n_poses=int(bent.sum()),
        warnings=tuple(warnings),
        nuisance=nuisance,
    )


def rotation_zeros(design: np.ndarray, roll: float, e: np.ndarray, orientation: np.ndarray, curvature: np.ndarray,
                   group: np.ndarray, n_groups: int) -> np.ndarray:
    """Each rotation's zero: the curvature of its reference pose in the jig's frame, seen through a calibration.

    A row's strain is taken against its rotation's reference, so the calibration reads the curvature *change*
    from that reference, k̂ = k − k_ref. Per rotation and grating the zero is the mean over the bent poses of
    k − k̂ (k: the jig's label), expressed along the rotation's bend direction and across it (90° counter-clockwise)
    — the same rule for every model (docs/jig.md, "The jig's zero").

    Parameters
    ----------
    design : ndarray, shape (G, C, 3)
        The calibration's design at the gratings of ``e``.
    roll : float
        α, rad.
    e : ndarray, shape (P, G, C)
        Strain of the bent poses against their rotation's reference (NaN: missing peak).
    orientation, curvature : ndarray, shape (P,)
        ψ (rad) and κ (1/m) of each bent pose.
    group : ndarray of int, shape (P,)
        Rotation of each pose, 0 … n_groups − 1.

    Returns
    -------
    ndarray, shape (n_groups, G, 2)
        (along, across), 1/m; NaN for a rotation without a solvable pose.
    """
    k_hat = CurvatureSolver(design).solve(e).curvature  # (P, G, 2), fibre frame
    # in the frame of each pose's bend direction: label k = κ e^{i(α − ψ)}, so divide by e^{i(α − ψ)}
    turn = np.exp(-1j * (roll - orientation))[:, None]
    # signed κ: a pose bent the other way (κ < 0) has its label along −e^{i(α − ψ)}, the frame stays that of ψ;
    # (P, G), along + i across
    rel = np.asarray(curvature, float)[:, None] - (k_hat[..., 0] + 1j * k_hat[..., 1]) * turn
    ok = np.isfinite(rel)
    onehot = np.eye(n_groups)[group]  # (P, O)
    n = np.einsum("po,pg->og", onehot, ok.astype(float))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.einsum("po,pg->og", onehot, np.where(ok, rel, 0.0)) / n
    return np.stack([mean.real, mean.imag], axis=-1)


def reference_bend(calibration: Calibration, poses: JigPoses, gratings=None) -> tuple[np.ndarray, np.ndarray]:
    """How bent the reference (flat-groove) poses are in the jig's frame, from their absolute wavelengths.

    Every rotation's strain is taken against its own reference, so its zero cannot tell a reference bent by the jig
    from bent grooves that hold the sensor less bent than their label: both give label − k̂ a fixed part along the
    bend (docs/jig.md, "The jig's zero"). The references' absolute wavelengths can: a reference bend b fixed in the
    jig's frame turns with the rotation in the sensor's, k_ref,o = c + b e^{i(α − ψ_o)}. Read through the
    calibration's map against the mean of the references (the common mode drops out), least squares over the
    rotations gives b; c is what all references share in the sensor's frame.

    Parameters
    ----------
    calibration : Calibration
        A jig calibration (design and ``jig_roll_rad``).
    poses : JigPoses
        At least 3 rotations, each with its reference rows (one session: the interrogator's absolute wavelengths
        must hold between the rotations).
    gratings : sequence of int, optional
        Default the calibration's fitted gratings.

    Returns
    -------
    bend : ndarray, shape (G, 2)
        b along and across the bend, 1/m.
    scatter : ndarray, shape (G,)
        RMS magnitude of what the references keep about c + b e^{i(α − ψ_o)}, 1/m (reseating, drift).
    """
    prov = calibration.provenance
    g = np.asarray(prov.get("jig_gratings", range(poses.n_gratings)) if gratings is None else gratings, dtype=int)
    if poses.orientations.size < 3:
        raise ValueError(f"{poses.source}: a reference bend needs references at 3 or more rotations, got "
                         f"{poses.orientations.size}")
    lam = poses.reference()  # (O, G, C)
    lam0 = np.mean(lam, axis=0)
    k = CurvatureSolver(np.asarray(calibration.design)[g]).solve(((lam - lam0) / lam0)[:, g]).curvature
    kc = k[..., 0] + 1j * k[..., 1]  # (O, G), sensor frame
    x = np.stack([np.ones(poses.orientations.size), np.exp(1j * (float(prov["jig_roll_rad"]) - poses.orientations))],
                 axis=1)
    coef = np.linalg.lstsq(x, kc, rcond=None)[0]  # (2, G)
    rest = kc - x @ coef
    return np.stack([coef[1].real, coef[1].imag], axis=-1), np.sqrt(np.mean(np.abs(rest) ** 2, axis=0))


def _error_model(fiber: FiberModel, nz: NuisanceFit, alpha: float) -> dict:
    """The calibration's error model as provenance entries (docs/jig.md, "The error model"): what a new pose's
    curvature is expected to deviate from the jig's, used for the 95 % intervals of :func:`validate`.

    * ``jig_error_strain_cov``: per fitted grating, the per-pose strain error covariance (C × C): pose + groove
      seating;
    * ``jig_reference_bias_1_per_m``, ``jig_reference_std_1_per_m``: per fitted grating, the mean and the scatter
      over the rotations of the reference pose's curvature in the jig's frame (along, across the bend);
    * ``jig_reseat_roll_std_rad``, ``jig_reseat_gain_std``: scatter of the roll and of ln(gain) between seatings,
      shared by the gratings; ``jig_local_roll_std_rad``, ``jig_local_gain_std``: what each grating adds, about
      ``jig_mean_curvature_1_per_m``, the bent grooves' mean |κ| (where the rotations' zeros hold it);
    * ``jig_positions_cov_m2``: the covariance of the design's bend columns (fibre frame; 2C × 2C, ordered core,
      component), the parameters' own uncertainty.
    """
    _, a, _ = _anchor(fiber)
    n_c = fiber.n_cores
    t = np.kron(np.eye(n_c) - a[None, :], np.eye(2))  # vec(β − aᵀβ): the anchored positions (sign irrelevant)
    rot = np.kron(np.eye(n_c), _rot(alpha))
    cov_p = np.einsum("ab,gbc,dc->gad", rot @ t, nz.beta_cov, rot @ t)
    return {
        "jig_error_terms": sorted(nz.terms),
        "jig_error_strain_cov": (nz.strain_cov_pose + nz.strain_cov_seat).tolist(),
        "jig_reference_bias_1_per_m": nz.reference.mean(axis=0).tolist(),
        "jig_reference_std_1_per_m": nz.reference_std.tolist(),
        "jig_reseat_roll_std_rad": nz.roll_std,
        "jig_reseat_gain_std": nz.gain_std,
        "jig_local_roll_std_rad": nz.local_roll_std,
        "jig_local_gain_std": nz.local_gain_std,
        "jig_mean_curvature_1_per_m": nz.mean_curvature,
        "jig_positions_cov_m2": cov_p.tolist(),
    }
