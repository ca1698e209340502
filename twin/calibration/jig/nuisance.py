"""The ``nuisance`` jig model: the physical model with the jig's own errors estimated beside the sensor
(:func:`fit_nuisance`), weighted by the error covariance it fits, not by the interrogator's standard errors.

A real jig is far from the ideal one (docs/jig.md, "Error budget"): the sensor is re-seated at every rotation
(a roll error, and a different fraction of the groove it follows), the flat groove is not the zero of the bent
poses, and every groove seats it a little differently. The interrogator's noise is 10–100 times smaller than
these, so its standard errors are the wrong weights (χ²/dof ≈ 10⁴ on the AMIRo table). Per grating n, pose p of
rotation o and core i, in the common-mode-free coordinates y = qᵀe (q: an orthonormal basis orthogonal to
(1, …, 1), so the per-pose common mode drops out exactly),

    y_pn = A_n (z_o ⊙ j_p) + d_on + ε_pn,

* A_n, (n_cores − 1) × 2: the sensor (β_n = q A_n, as in the physical model);
* z_o: a complex gain per rotation, shared by all gratings — its phase is the roll error of that seating, its
  modulus how much of the groove the sensor follows there (``"roll"``, ``"gain"``). Gauge: what the rotations on
  one axis (ψ and ψ + π) have in common is the sensor's, not the jig's: a roll common to both is a shear of the
  map (core angles), a gain common to both its scale along that axis. So ln z_o has mean 0 over the rotations of
  each axis; only the differences between opposite rotations are the jig's (a rotation alone on its axis keeps
  z_o = 1). A jig at 0°/90°/180°/270° therefore cannot tell the sensor's shear from the part of the roll errors
  that differs between its two axes; no calibration from it can;
* d_on: the zero of rotation o (``"offset"``): the reference is not the zero of the bent poses;
* ε: a seating error shared by the trials of one groove (``"seating"``, a random effect: as a fixed effect it
  would absorb every groove's mean and leave nothing to fit) plus a per-pose error, with covariances Σ_seat,n
  and Σ_pose,n per grating fitted from the residuals.

Because the trials of one groove share their regressors, generalised least squares on the poses is least squares
on the groove means with weight (Σ_pose/T + Σ_seat)⁻¹ (T: the groove's trials). The fit alternates A, d | z
(one weighted linear solve per grating, batched) and z | A, d (a 2-unknown solve per rotation over all
gratings), and re-estimates the covariances from the residuals each time, until z settles.

The fitted error model predicts how far a new pose's curvature is from the jig's label (the 95 % intervals of
:func:`twin.calibration.jig.validate`): the jig's zero (the bent grooves' shortfall from their labels, docs/jig.md)
as a bias unless it is added to the curvature; Σ_pose + Σ_seat through the calibration's map; the scatter of the
rotations' zeros along and across the bend, and the jig zero's own error (:func:`median_variance`); κ² times the
seatings' shared roll and gain variances, and for the per-grating ones (κ − κ̄)² for the pose's own seating (each
rotation's zero holds its slope at the grooves' mean curvature κ̄) plus κ²/n for the map's, inherited from the n
fitted rotations on the pose's axis; and the parameters' own covariance. The variances at the rotation level rest
on 1–3 degrees of freedom and are pooled with the error budget as a prior.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy import special

#: The jig errors the nuisance model can estimate.
TERMS = frozenset({"roll", "gain", "offset", "seating"})
#: Those it estimates by default. A gain per rotation competes with the sensor's own anisotropy: a 4-rotation jig
#: bends the sensor along 2 axes only, so with a complex z_o per rotation the 2 × 2 map of each grating is left with
#: 2 redundant numbers, and with 3 rotations (leave one out) with none. On both real AMIRo tables and on the twin's
#: second sessions it made the calibration no better (docs/jig.md, "Which terms help"); it stays available.
DEFAULT_TERMS = frozenset({"roll", "offset", "seating"})
#: Alternating least squares converges linearly (≈ 0.7 per step on the AMIRo table): up to this many steps,
#: until no z_o moves by more than _TOL (rad, relative gain).
_MAX_ITER = 300
_TOL = 1e-9
#: Smallest error variance in strain², (0.01 pm / 1550 nm)².
_FLOOR = (1e-5 / 1550.0) ** 2
#: Prior 1σ of a seating's roll (rad) and relative gain: the AMIRo table's (docs/jig.md, error budget). With few
#: rotations the z_o compete with the sensor's own anisotropy (3 rotations leave 2 numbers per grating to
#: tell them apart); the prior keeps them at the size a jig's reseating has.
PRIOR_ROLL = float(np.deg2rad(3.0))
PRIOR_GAIN = 0.05
#: The rotation-level variances (roll, gain, a rotation's zero) rest on 1–3 degrees of freedom in a 4-rotation
#: table, too few to state intervals on. Each is combined with the jig's error budget (docs/jig.md) as a prior worth
#: PRIOR_DOF rotations: σ² = (ν s² + ν₀ σ₀²) / (ν + ν₀). σ₀: shared roll 3°; per grating, roll 1.2° (twist when
#: pressed in) and gain 4.5 % (conformity); the reference's curvature 0.10 1/m per component.
PRIOR_DOF = 3.0
BUDGET = {"roll": float(np.deg2rad(3.0)), "gain": 0.0, "local_roll": float(np.deg2rad(1.2)), "local_gain": 0.045,
          "reference": 0.10}


@functools.lru_cache(maxsize=64)
def median_variance(n: int) -> float:
    """Variance of the median of ``n`` independent standard normal samples (exact, by quadrature to ≈ 1e-12).

    The jig zero is the median of the fitted rotations' zeros, so its own error is this times one zero's variance.
    n = 1: 1; n = 2: 1/2 (the mean of both); n = 3: 1 − √3/π ≈ 0.449; for large n → π/2n (0.524 at n = 3, the
    asymptotic value, too large for the 2–4 rotations of a jig).

    Parameters
    ----------
    n : int
        Number of samples, ≥ 1.
    """
    if n < 1:
        raise ValueError(f"the median of {n} samples is undefined; need at least 1")
    m = n // 2
    # the trapezoid rule on the whole line is spectrally accurate for these smooth, Gaussian-decaying integrands
    x = np.linspace(-10.0, 10.0, 2001)
    h = x[1] - x[0]
    pdf = np.exp(-0.5 * x * x) / np.sqrt(2.0 * np.pi)
    if n % 2:  # the (m + 1)-th order statistic: density n!/(m!)² Φ^m (1 − Φ)^m φ
        c = math.exp(math.lgamma(n + 1) - 2.0 * math.lgamma(m + 1))
        return float(h * np.sum(x * x * c * (special.ndtr(x) * special.ndtr(-x)) ** m * pdf))
    # the mean of the m-th (x) and (m + 1)-th (y = x + t, t ≥ 0) order statistics, joint density
    # n!/((m − 1)!)² Φ(x)^(m−1) φ(x) φ(y) (1 − Φ(y))^(m−1); Gauss–Legendre in t, smooth on [0, 14]
    c = math.exp(math.lgamma(n + 1) - 2.0 * math.lgamma(m))
    t, w = np.polynomial.legendre.leggauss(96)
    t, w = 7.0 * (t + 1.0), 7.0 * w
    y = x[:, None] + t[None, :]
    f = (special.ndtr(x) ** (m - 1) * pdf)[:, None] * np.exp(-0.5 * y * y) / np.sqrt(2.0 * np.pi) \
        * special.ndtr(-y) ** (m - 1) * (0.5 * (x[:, None] + y)) ** 2
    return float(c * h * np.sum(f @ w))


def _pooled(s2: float, dof: float, prior: float) -> float:
    """Standard deviation from a sample variance on ``dof`` degrees of freedom and the budget's prior."""
    return float(np.sqrt((dof * s2 + PRIOR_DOF * prior**2) / (dof + PRIOR_DOF)))


@dataclass(frozen=True, eq=False)
class NuisanceFit:
    """What :func:`fit_nuisance` estimated (per-grating arrays follow the fitted gratings).

    Attributes
    ----------
    beta : ndarray, shape (G, C, 2)
        The cores' response in the jig frame (as the physical model's β).
    beta_cov : ndarray, shape (G, 2C, 2C)
        Its covariance (ordered core, component), from the weighted normal equations at the fitted error model.
    offsets : ndarray, shape (O, G, C)
        Each rotation's zero δ_o (strain; 0 without ``"offset"``).
    gain : ndarray of complex, shape (O,)
        z_o: phase = roll error of that seating (rad), modulus = fraction of the groove followed, relative.
    strain_cov_pose, strain_cov_seat, strain_cov_ref : ndarray, shape (G, C, C)
        Fitted error covariances in strain (rank C − 1, common mode excluded): per pose, per groove (shared by its
        trials), and the scatter of the rotations' zeros.
    reference : ndarray, shape (O, G, 2)
        Each rotation's zero as the curvature of its reference pose in the jig's frame (equivalently, how much less
        its bent grooves bend the sensor than labelled), 1/m: along the grooves'
        bend direction and across it (90° counter-clockwise). Its mean over the rotations is a property of the
        jig (bent grooves that hold the sensor less bent than labelled), its scatter that of the reseating.
    reference_std : ndarray, shape (G, 2)
        That scatter (along, across), 1/m, pooled with the budget's prior (:data:`PRIOR_DOF`).
    roll_std, gain_std : float
        Scatter of arg z_o (rad) and of ln|z_o| over the rotations, pooled with the budget's prior.
    local_roll_std, local_gain_std : float
        What each rotation adds at each grating (the sensor twisted when pressed in, following the groove
        differently at each grating): from the slopes with κ of the groove means' residual across and along the
        bend, about the rotation's mean groove curvature (its zero took the slope's value there). A rotation alone
        on its axis (no opposite rotation fitted) has its slope fitted away by the sensor's anisotropy; with n
        rotations on an axis a slope keeps 1 − 1/n of the variance, which is corrected for.
    mean_curvature : float
        κ̄, 1/m: the mean |κ| of the bent grooves, where each rotation's zero holds its seating's local slope (so the
        scatter of ``reference`` includes it there); 0 without ``"offset"``.
    iterations : int
    terms : frozenset of str
    """

    beta: np.ndarray
    beta_cov: np.ndarray
    offsets: np.ndarray
    gain: np.ndarray
    strain_cov_pose: np.ndarray
    strain_cov_seat: np.ndarray
    strain_cov_ref: np.ndarray
    reference: np.ndarray
    reference_std: np.ndarray
    roll_std: float
    gain_std: float
    local_roll_std: float
    local_gain_std: float
    mean_curvature: float
    iterations: int
    terms: frozenset


def _groove_means(y: np.ndarray, seat: np.ndarray, n_seat: int):
    """Per grating and groove: mean y (G, S, D), trial count (G, S), pooled within-groove covariance (G, D, D)."""
    ok = np.all(np.isfinite(y), axis=-1)  # (P, G)
    y0 = np.where(ok[..., None], y, 0.0)
    onehot = np.eye(n_seat)[seat]  # (P, S)
    count = np.einsum("ps,pg->gs", onehot, ok.astype(float))
    mean = np.einsum("ps,pgd->gsd", onehot, y0) / np.maximum(count, 1.0)[..., None]
    dev = np.where(ok[..., None], y0 - np.transpose(mean, (1, 0, 2))[seat], 0.0)  # (P, G, D)
    dof = np.sum(np.maximum(count - 1.0, 0.0), axis=1)  # (G,)
    pooled = np.einsum("pga,pgb->gab", dev, dev) / np.maximum(dof, 1.0)[:, None, None]
    pooled[dof == 0] = 0.0
    return mean, count, pooled


def _local_slopes(resid: np.ndarray, kap: np.ndarray, s_group: np.ndarray, used: np.ndarray, n_groups: int,
                  about_mean: bool = True):
    """Each rotation × grating's slope of the groove-mean residuals with κ, about that rotation's mean groove
    curvature κ̄_o: the rotation's zero (a free offset, the mean over its grooves) already took the slope's value at
    κ̄_o, so the residual holds only (κ − κ̄_o) × slope, and a regression through the origin would read a fraction
    Σ(κ − κ̄)²/Σκ² of it (0.19 on the AMIRo grooves). Without a free zero (``about_mean`` False) the residual keeps
    the whole slope and the regression is through the origin.

    Parameters
    ----------
    resid : ndarray, shape (G, S, D)
        Groove-mean residuals.
    kap : ndarray, shape (S,)
        Each groove's |κ|, 1/m.
    s_group : ndarray of int, shape (S,)
        Each groove's rotation.
    used : ndarray of bool, shape (G, S)
        Grooves with a valid trial.

    Returns
    -------
    slope : ndarray, shape (G, O, D)
        Residual per unit of κ (strain · m); 0 where a rotation has fewer than two distinct grooves at a grating.
    centred : ndarray, shape (G, S)
        κ − κ̄_o of each groove (0 where unused).
    has : ndarray of bool, shape (G, O)
        Where a slope was estimated.
    """
    onehot = np.eye(n_groups)[s_group] * used[..., None]  # (G, S, O)
    n = onehot.sum(axis=1)  # (G, O)
    mean_k = np.einsum("gso,s->go", onehot, kap) / np.maximum(n, 1.0) * about_mean
    centred = (kap[None, :] - np.einsum("gso,go->gs", onehot, mean_k)) * used
    sxx = np.einsum("gso,gs->go", onehot, centred**2)
    has = sxx > 1e-12 * np.maximum(np.einsum("gso,s->go", onehot, kap**2), 1e-300)
    slope = np.einsum("gso,gs,gsd->god", onehot, centred, resid) / np.where(has, sxx, np.inf)[..., None]
    return slope, centred, has


def _psd(m: np.ndarray) -> np.ndarray:
    """The nearest positive semi-definite matrices (eigenvalues clipped at 0), batched (..., D, D)."""
    w, v = np.linalg.eigh(0.5 * (m + np.swapaxes(m, -1, -2)))
    return np.einsum("...ij,...j,...kj->...ik", v, np.maximum(w, 0.0), v)


def fit_nuisance(e: np.ndarray, j: np.ndarray, group: np.ndarray, n_groups: int, seat: np.ndarray,
                 q: np.ndarray, terms=DEFAULT_TERMS) -> NuisanceFit | None:
    """Fit the nuisance model (module docstring) to the gratings of ``e``.

    Parameters
    ----------
    e : ndarray, shape (P, G, C)
        Strain against each row's own reference (NaN: missing peak; that grating of that pose is left out).
    j : ndarray, shape (P, 2)
        The jig's curvature in the jig frame, 1/m (0 for reference rows).
    group : ndarray of int, shape (P,)
        Rotation (orientation) of each pose, in 0 … n_groups − 1.
    seat : ndarray of int, shape (P,)
        Groove seating of each pose (the poses of one rotation in one groove), 0-based, contiguous.
    q : ndarray, shape (C, C − 1)
        Orthonormal basis orthogonal to (1, …, 1).
    terms : iterable of str
        Subset of :data:`TERMS` to estimate (default :data:`DEFAULT_TERMS`).

    Returns
    -------
    NuisanceFit, or None when the poses do not determine the sensor.
    """
    terms = frozenset(terms)
    if not terms <= TERMS:
        raise ValueError(f"unknown nuisance terms {sorted(terms - TERMS)}; expected some of {sorted(TERMS)}")
    n_g, n_c = e.shape[1:]
    dim = n_c - 1
    y = np.einsum("pgc,cd->pgd", e, q)
    n_seat = int(seat.max()) + 1
    ybar, count, cov_pose = _groove_means(y, seat, n_seat)
    # each groove's rotation and label (constant within a groove)
    s_group = np.zeros(n_seat, dtype=np.int64)
    s_group[seat] = group
    s_j = np.zeros((n_seat, 2))
    s_j[seat] = j
    rot90 = np.array([[0.0, -1.0], [1.0, 0.0]])
    eye = np.eye(dim)
    n_off = n_groups * dim if "offset" in terms else 0
    n_par = 2 * dim + n_off
    z = np.ones(n_groups, dtype=complex)
    # each rotation's bend direction in the jig frame, and the rotations that share its axis (ψ, ψ + π)
    u = np.zeros((n_groups, 2))
    np.add.at(u, group, j / np.maximum(np.hypot(j[:, 0], j[:, 1]), 1e-300)[:, None])
    u /= np.maximum(np.hypot(u[:, 0], u[:, 1]), 1e-300)[:, None]
    same_axis = (np.abs(u @ u.T) > np.cos(np.deg2rad(10.0))).astype(float)
    axis_mean = same_axis / same_axis.sum(axis=1, keepdims=True)  # (O, O): mean over each rotation's axis
    n_axis = same_axis.sum(axis=1)  # fitted rotations on each one's axis
    kept = 1.0 - 1.0 / n_axis  # the part of a rotation's slope the map does not hold
    kap = np.hypot(s_j[:, 0], s_j[:, 1])
    onehot_s = np.eye(n_groups)[s_group]  # (S, O)
    cov_seat = np.zeros((n_g, dim, dim))
    # start without a seating part: the groove means weighted by their count (ordinary least squares on poses)
    scale0 = np.einsum("gaa->g", cov_pose) / dim
    # no error is smaller than 0.01 pm at 1550 nm: noise-free data converge instead of weighting ever harder
    floor = np.maximum(1e-6 * scale0, _FLOOR)
    for it in range(1, _MAX_ITER + 1):
        x_s = np.stack([z[s_group].real * s_j[:, 0] - z[s_group].imag * s_j[:, 1],
                        z[s_group].imag * s_j[:, 0] + z[s_group].real * s_j[:, 1]], axis=-1)  # (S, 2)
        design = np.zeros((n_seat, dim, n_par))
        design[:, :, :dim] = x_s[:, 0, None, None] * eye
        design[:, :, dim:2 * dim] = x_s[:, 1, None, None] * eye
        if n_off:
            col = 2 * dim + s_group[:, None] * dim + np.arange(dim)  # the groove's rotation's zero
            design[np.arange(n_seat)[:, None], np.arange(dim)[None, :], col] = 1.0
        # weight of a groove mean: (Σ_pose/T + Σ_seat)⁻¹, 0 where the groove has no valid trial
        tot = cov_pose[:, None] / np.maximum(count, 1.0)[..., None, None] + (cov_seat[:, None] if "seating" in terms
                                                                             else 0.0)
        tot = tot + floor[:, None, None, None] * eye
        weight = np.linalg.inv(tot) * (count > 0)[..., None, None]  # (G, S, D, D)
        normal = np.einsum("sak,gsab,sbl->gkl", design, weight, design)
        rhs = np.einsum("sak,gsab,gsb->gk", design, weight, ybar)
        ev = np.linalg.eigvalsh(normal)
        if np.any(ev[:, 0] <= 1e-12 * ev[:, -1]):
            return None
        theta = np.linalg.solve(normal, rhs[..., None])[..., 0]  # (G, K)
        a = np.stack([theta[:, :dim], theta[:, dim:2 * dim]], axis=-1)  # (G, D, 2)
        d = (theta[:, 2 * dim:].reshape(n_g, n_groups, dim) if n_off else np.zeros((n_g, n_groups, dim)))
        # z | A, d: per rotation, r = Re z · A j + Im z · A J j, summed over its grooves and every grating
        r = ybar - d[:, s_group]  # (G, S, D)
        f = np.stack([np.einsum("gdk,sk->gsd", a, s_j), np.einsum("gdk,kl,sl->gsd", a, rot90, s_j)], axis=-1)
        z_new = z
        if terms & {"roll", "gain"}:
            nz = np.einsum("so,gsak,gsab,gsbl->okl", onehot_s, f, weight, f)
            rz = np.einsum("so,gsak,gsab,gsb->ok", onehot_s, f, weight, r)
            prior = np.diag([1.0 / PRIOR_GAIN**2 if "gain" in terms else 0.0,
                             1.0 / PRIOR_ROLL**2 if "roll" in terms else 0.0])
            sol = np.linalg.solve(nz + prior, (rz + prior @ np.array([1.0, 0.0]))[..., None])[..., 0]
            zc = sol[:, 0] + 1j * sol[:, 1]
            log_z = (np.log(np.abs(zc)) if "gain" in terms else 0.0) + 1j * (np.angle(zc) if "roll" in terms else 0.0)
            z_new = np.exp(log_z - axis_mean @ log_z)  # gauge (module docstring): mean 0 on each axis
        # error covariances from the residuals of the groove means (their expectation: Σ_pose/T + Σ_seat)
        resid = ybar - np.einsum("sak,gk->gsa", design, theta)
        used = count > 0
        n_used = used.sum(axis=1)
        # with each rotation's zero free, the seatings' local slopes (about the rotation's mean groove curvature)
        # are a rotation-level effect with a variance of their own: taken out before the per-groove covariance is
        # estimated, so the intervals do not count them there too; each costs the degrees of freedom the map had
        # not already taken (1 − 1/n on an axis with n rotations: the map holds their mean slope). Without the
        # zero, the residuals also hold each rotation's zero, which a slope through the origin would partly take.
        resid_seat, dof_slopes = resid, 0.0
        if n_off:
            slope, centred, has = _local_slopes(resid, kap, s_group, used, n_groups)
            resid_seat = resid - centred[..., None] * np.einsum("so,god->gsd", onehot_s, slope)
            dof_slopes = np.sum(np.where(has, kept[None, :], 0.0), axis=1)
        dof = np.maximum(n_used - n_par / dim - dof_slopes, 1.0)
        outer = np.einsum("gsa,gsb->gab", resid_seat * used[..., None], resid_seat)
        expected_pose = np.einsum("gs,gab->gab", used / np.maximum(count, 1.0), cov_pose)
        cov_seat_new = _psd((outer - expected_pose) / dof[:, None, None])
        if "seating" not in terms:  # one covariance per grating for every pose, independent
            cov_pose_all = outer / dof[:, None, None] * (np.einsum("gs->g", used * count) / np.maximum(n_used, 1))[
                :, None, None]
            cov_pose = 0.5 * (cov_pose_all + np.swapaxes(cov_pose_all, 1, 2))
            cov_seat_new = np.zeros_like(cov_seat)
        change = float(np.max(np.abs(z_new - z)))
        z, cov_seat = z_new, cov_seat_new
        if change < _TOL and it > 1:
            break
    inv_normal = np.linalg.inv(normal)
    big = np.kron(q, np.eye(2))  # vec(β) (core, component) from vec(A) (dim, component)
    perm = np.arange(2 * dim).reshape(2, dim).T.ravel()  # θ is (component, dim); vec(A) is (dim, component)
    cov_a = inv_normal[:, :2 * dim, :2 * dim][:, perm][:, :, perm]
    beta = np.einsum("cd,gdk->gck", q, a)
    offsets = np.einsum("cd,god->ogc", q, d)
    # a rotation's zero as its reference pose's curvature (strain is taken against it: the zero is −A c_ref),
    # along and across the rotation's bend direction u_o
    c_ref = -np.einsum("gkd,god->ogk", np.linalg.pinv(a), d)
    reference = np.stack([np.einsum("ogk,ok->og", c_ref, u),
                          np.einsum("ogk,ok->og", c_ref, np.stack([-u[:, 1], u[:, 0]], axis=-1))], axis=-1)
    # per rotation and grating, the residual's slope with κ (about the rotation's mean groove curvature) along and
    # across the bend, in curvature through the map
    slope, _, have = _local_slopes(resid, kap, s_group, used, n_groups, bool(n_off))
    c_slope = np.einsum("gkd,god->gok", np.linalg.pinv(a), slope)
    w_o = np.stack([-u[:, 1], u[:, 0]], axis=-1)
    slopes = np.stack([np.einsum("gok,ok->go", c_slope, u), np.einsum("gok,ok->go", c_slope, w_o)], axis=-1)
    kept = np.broadcast_to(kept, slopes.shape[:2])
    dof_local = float(np.sum(kept[have]))
    s2_local = (np.sum(np.where(have[..., None], slopes, 0.0) ** 2, axis=(0, 1)) / dof_local if dof_local > 0
                else np.zeros(2))  # (along, across)
    ref = d - d.mean(axis=1, keepdims=True)
    cov_ref = (np.einsum("goa,gob->gab", ref, ref) / max(n_groups - 1, 1) if n_off
               else np.zeros((n_g, dim, dim)))
    return NuisanceFit(
        beta=beta,
        beta_cov=big @ cov_a @ big.T,
        offsets=offsets,
        gain=z,
        strain_cov_pose=np.einsum("cd,gde,fe->gcf", q, cov_pose, q),
        strain_cov_seat=np.einsum("cd,gde,fe->gcf", q, cov_seat, q),
        strain_cov_ref=np.einsum("cd,gde,fe->gcf", q, cov_ref, q),
        reference=reference,
        reference_std=np.array([[_pooled(v, n_groups - 1, BUDGET["reference"]) for v in row] for row in
                                (reference.var(axis=0, ddof=1) if n_groups > 1 else np.zeros(reference.shape[1:]))]),
        roll_std=_pooled(np.var(np.angle(z), ddof=1) if "roll" in terms and n_groups > 1 else 0.0,
                         n_groups - 1 if "roll" in terms else 0, BUDGET["roll"]),
        gain_std=_pooled(np.var(np.log(np.abs(z)), ddof=1) if "gain" in terms and n_groups > 1 else 0.0,
                         n_groups - 1 if "gain" in terms else 0, BUDGET["gain"]),
        local_roll_std=_pooled(s2_local[1], dof_local, BUDGET["local_roll"]),
        local_gain_std=_pooled(s2_local[0], dof_local, BUDGET["local_gain"]),
        mean_curvature=float(np.mean(kap)) if n_off else 0.0,
        iterations=it,
        terms=terms,
    )
