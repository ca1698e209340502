"""The confidence tube of a centreline from its position covariance (docs/math.md §8.3): numpy only, used by
:class:`twin.frames.Shape` (``sigma``, ``confidence``) and :mod:`twin.uncertainty`."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

__all__ = ["lateral_eigenvalues", "tube_radius"]


@lru_cache(maxsize=16)
def _radius_table(level: float, n: int = 257) -> tuple[np.ndarray, np.ndarray]:
    """Radius factors f(ρ) with P(X1² + ρ X2² ≤ f²) = level (X standard normal), on ρ = 0 … 1 (n values).

    In polar coordinates the 2-D normal of variances (1, ρ) gives P(R ≤ r) = (1/2π√ρ) ∫_0^{2π} (1 − e^{−r² a/2})/a dφ
    with a(φ) = cos²φ + sin²φ/ρ: a smooth periodic integrand, so the trapezoid rule on 1024 angles converges
    geometrically (to ~1e-12 for ρ ≥ 1/256); ρ = 0 is erf(r/√2). Bisection on all ρ at once, 64 halvings."""
    from scipy.special import erf

    rho = np.linspace(0.0, 1.0, n)
    phi = np.linspace(0.0, 2.0 * np.pi, 1024, endpoint=False)
    a = np.cos(phi) ** 2 + np.sin(phi)[None, :] ** 2 / np.maximum(rho[1:, None], 1e-300)

    def cdf(r: np.ndarray) -> np.ndarray:
        out = np.empty(n)
        out[0] = erf(r[0] / np.sqrt(2.0))
        inner = (1.0 - np.exp(-0.5 * r[1:, None] ** 2 * a)) / a
        out[1:] = inner.mean(axis=1) / np.sqrt(rho[1:])
        return out

    lo, hi = np.zeros(n), np.full(n, 40.0)
    for _ in range(64):
        mid = 0.5 * (lo + hi)
        below = cdf(mid) < level
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return rho, 0.5 * (lo + hi)


def tube_radius(covariance: np.ndarray, tangents: np.ndarray, level: float) -> np.ndarray:
    """Radius of the circle about each point, normal to the curve, that holds ``level`` of its lateral error.

    The lateral error is the position error projected on the plane normal to the tangent: a 2-D Gaussian with
    covariance Σ_⊥ = (I − t tᵀ) Σ (I − t tᵀ) and eigenvalues λ1 ≥ λ2. The radius r solves
    P(λ1 X1² + λ2 X2² ≤ r²) = level, i.e. r = √λ1 f(λ2/λ1) with f tabulated once per level (0.5 s) on 257
    ratios and interpolated linearly (within 1e-6 relative of a 2049-ratio table); for λ1 = λ2 it is
    σ √(−2 ln(1 − level)) (a Rayleigh radius), for λ2 = 0 the two-sided normal quantile.

    Parameters
    ----------
    covariance : ndarray, shape (..., 3, 3)
        Position covariance, m².
    tangents : ndarray, shape (..., 3)
        Unit tangents.
    level : float
        Probability in (0, 1).

    Returns
    -------
    ndarray, shape (...)
        m.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"confidence level must lie in (0, 1) (e.g. 0.95), got {level}")
    lam = lateral_eigenvalues(covariance, tangents)
    rho, f = _radius_table(round(float(level), 12))
    l1 = lam[..., 1]
    ratio = np.divide(lam[..., 0], l1, out=np.ones_like(l1), where=l1 > 0)
    return np.sqrt(l1) * np.interp(np.clip(ratio, 0.0, 1.0), rho, f)


def lateral_eigenvalues(covariance: np.ndarray, tangents: np.ndarray) -> np.ndarray:
    """Eigenvalues (λ2, λ1), ascending, of the lateral covariance Σ_⊥ (..., 2), m² (clipped at 0)."""
    t = np.asarray(tangents, dtype=np.float64)
    c = np.asarray(covariance, dtype=np.float64)
    proj = np.eye(3) - t[..., :, None] * t[..., None, :]
    lat = proj @ c @ proj
    # Σ_⊥ has the eigenvalue 0 along t; the other two are those of the 2x2 restriction: from trace and the
    # sum of principal 2x2 minors (the determinant of the 2x2 block)
    tr = np.trace(lat, axis1=-2, axis2=-1)
    m2 = 0.5 * (tr**2 - np.einsum("...ij,...ji->...", lat, lat))
    disc = np.sqrt(np.maximum(tr**2 / 4 - m2, 0.0))
    return np.maximum(np.stack([tr / 2 - disc, tr / 2 + disc], axis=-1), 0.0)


