"""Curvature at the gratings → centreline (docs/math.md §3): interpolants, torsion schemes and SE(3) integrators.

Two formulations share one integrator:

* **material** (default): interpolate the curvature vector (k_x, k_y) and integrate the material (Bishop) frame
  R' = R û with u = (−k_y, k_x, 0); no |k|, no atan2, no unwrapping.
* **Frenet** (the paper's): κ = |k|, θ_b = atan2(k_y, k_x), torsion τ from θ_b, and F' = F ω̂ with ω = (τ, 0, κ).

Integrators (``h`` is the step): ``magnus4`` (2-point Gauss Magnus, order 4), ``hem-mid`` (exact helix step
with κ, τ at the step's midpoint, order 2), ``hem-left`` (the same sampled at the step's start, the paper's
literal HEM, order 1), ``rk4`` (classical RK4 on the 12-dim system, order 4, frames drift ~h⁴).

Curvature beyond the first and last grating is held at the end values (no polynomial extrapolation).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline, PchipInterpolator

from twin import _kernels

__all__ = [
    "INTEGRATORS",
    "INTERPOLATIONS",
    "TORSIONS",
    "basis",
    "hold_bend_angle",
    "integrate",
    "interpolate",
    "sample_points",
    "step_grid",
    "torsion_nodes",
]

INTERPOLATIONS = ("spline", "pchip", "knn", "linear")
INTEGRATORS = ("magnus4", "hem-mid", "hem-left", "rk4")
TORSIONS = ("forward", "centred", "theta-spline")

_GAUSS = (0.5 - np.sqrt(3.0) / 6.0, 0.5 + np.sqrt(3.0) / 6.0)
#: Where each integrator samples u inside a step, as fractions of h.
_OFFSETS = {"magnus4": _GAUSS, "hem-mid": (0.5,), "hem-left": (0.0,), "rk4": (0.0, 0.5, 1.0)}


def _check(name: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {', '.join(allowed)}; got {value!r}")


#: most integration steps of one reconstruction (20 m in 0.2 mm steps): every frame of a batch holds a point and
#: a frame per step, so a length or step in the wrong unit must fail here, before anything is allocated
MAX_STEPS = 100_000


def step_grid(s_start: float, s_end: float, step: float) -> tuple[np.ndarray, float]:
    """Output arc lengths from ``s_start`` to ``s_end`` with equal steps no longer than ``step`` (m)."""
    if not (step > 0 and np.isfinite(step)):
        raise ValueError(f"step must be a positive length in m, got {step}")
    if not (s_end > s_start and np.isfinite(s_end - s_start)):
        raise ValueError(f"nothing to reconstruct between {s_start} and {s_end} m")
    if (s_end - s_start) / step > MAX_STEPS:
        raise ValueError(f"step {step:g} m over {s_end - s_start:g} m makes more than {MAX_STEPS} steps; expected "
                         "lengths and steps in m")
    n = max(1, int(np.ceil((s_end - s_start) / step - 1e-9)))
    h = (s_end - s_start) / n
    return s_start + h * np.arange(n + 1), h


def sample_points(s_points: np.ndarray, h: float, integrator: str) -> np.ndarray:
    """Arc lengths where ``integrator`` needs u, shape (n_steps, m) (m = 2 for magnus4, 1 for HEM, 3 for rk4)."""
    _check("integrator", integrator, INTEGRATORS)
    return s_points[:-1, None] + h * np.asarray(_OFFSETS[integrator])[None, :]


def basis(s_nodes, s_eval, kind: str, derivative: bool = False) -> np.ndarray:
    """Linear interpolation operator B with values(s_eval) = B @ values(s_nodes), shape (n_eval, n_nodes).

    ``kind`` is one of "spline" (not-a-knot cubic, MATLAB's ``spline``), "linear" or "knn" (nearest node).
    Evaluation points outside the nodes are clamped to the end nodes. ``derivative`` gives d/ds instead (spline
    and linear only; zero outside the nodes).
    """
    if kind == "pchip":
        raise ValueError("pchip is not linear in the node values; use interpolate()")
    _check("interpolation", kind, INTERPOLATIONS)
    s_nodes = np.asarray(s_nodes, dtype=np.float64)
    s_eval = np.asarray(s_eval, dtype=np.float64)
    n = s_nodes.size
    outside = (s_eval < s_nodes[0]) | (s_eval > s_nodes[-1])
    x = np.clip(s_eval, s_nodes[0], s_nodes[-1])
    if n == 1:
        return np.zeros((x.size, 1)) if derivative else np.ones((x.size, 1))
    eye = np.eye(n)
    if kind == "spline":
        cs = CubicSpline(s_nodes, eye, axis=0, bc_type="not-a-knot")
        b = cs(x, 1) if derivative else cs(x)
    elif kind == "linear":
        j = np.clip(np.searchsorted(s_nodes, x, side="right") - 1, 0, n - 2)
        w = (x - s_nodes[j]) / (s_nodes[j + 1] - s_nodes[j])
        b = np.zeros((x.size, n))
        rows = np.arange(x.size)
        if derivative:
            d = 1.0 / (s_nodes[j + 1] - s_nodes[j])
            b[rows, j] = -d
            b[rows, j + 1] = d
        else:
            b[rows, j] = 1.0 - w
            b[rows, j + 1] = w
    else:  # knn: the nearest node (ties go to the lower node)
        if derivative:
            raise ValueError("knn interpolation has no derivative")
        j = np.clip(np.searchsorted(s_nodes, x, side="left"), 1, n - 1)
        nearest = np.where(x - s_nodes[j - 1] <= s_nodes[j] - x, j - 1, j)
        b = eye[nearest]
    if derivative:
        b = np.where(outside[:, None], 0.0, b)
    return np.ascontiguousarray(b)


def piecewise(s_nodes, s_eval, kind: str):
    """:func:`basis` as polynomials per node interval, for an evaluation in O(degree) instead of O(n_nodes).

    Returns ``(segment, t, coef)`` with values(s_eval[q]) = Σ_d t[q]^d · (coef[segment[q], d] @ values(s_nodes)):
    ``segment`` (n_eval,) int, the node interval of each (clamped) point, ``t`` (n_eval,) its distance from the
    interval's left node (m), ``coef`` (n_intervals, 4, n_nodes) the coefficients of t⁰ … t³. None for the
    kinds that are not polynomial between nodes (knn) and for fewer than two nodes. The caller may check it
    against :func:`basis`; it matches to rounding.
    """
    s_nodes = np.asarray(s_nodes, dtype=np.float64)
    n = s_nodes.size
    if kind not in ("spline", "linear") or n < 2:
        return None
    x = np.clip(np.asarray(s_eval, dtype=np.float64), s_nodes[0], s_nodes[-1])
    segment = np.clip(np.searchsorted(s_nodes, x, side="right") - 1, 0, n - 2)
    t = x - s_nodes[segment]
    coef = np.zeros((n - 1, 4, n))
    if kind == "spline":
        c = CubicSpline(s_nodes, np.eye(n), axis=0, bc_type="not-a-knot").c  # (4, n - 1, n), t³ first
        coef[:] = np.transpose(c[::-1], (1, 0, 2))
    else:
        i = np.arange(n - 1)
        slope = 1.0 / np.diff(s_nodes)
        coef[i, 0, i] = 1.0
        coef[i, 1, i] = -slope
        coef[i, 1, i + 1] = slope
    return segment, t, coef


def apply_basis(b: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``b @ values`` along the node axis (-2) of a batch (..., n_nodes, c), as a single matrix product."""
    n, c = values.shape[-2:]
    batch = values.shape[:-2]
    if not batch:
        return b @ values
    v = np.moveaxis(values, -2, 0).reshape(n, -1)
    out = (b @ v).reshape((b.shape[0], *batch, c))
    return np.moveaxis(out, 0, -2)


def interpolate(s_nodes, values, s_eval, kind: str) -> np.ndarray:
    """Interpolate node values (..., n_nodes, c) to ``s_eval`` (flattened), clamped outside the nodes.

    Returns (..., n_eval, c).
    """
    s_nodes = np.asarray(s_nodes, dtype=np.float64)
    s_eval = np.asarray(s_eval, dtype=np.float64).ravel()
    values = np.asarray(values, dtype=np.float64)
    if kind == "pchip" and s_nodes.size >= 2:
        x = np.clip(s_eval, s_nodes[0], s_nodes[-1])
        return PchipInterpolator(s_nodes, values, axis=-2)(x)
    return apply_basis(basis(s_nodes, s_eval, "linear" if kind == "pchip" else kind), values)


def integrate(rates: np.ndarray, h: float, integrator: str, frenet: bool = False, r0=None):
    """Chain the steps of one or many curves.

    Parameters
    ----------
    rates : ndarray, shape (..., C, n_steps, m)
        Curvature samples at the integrator's sample points (see :func:`sample_points`): for material frames
        (k_x, k_y) or (k_x, k_y, γ) in 1/m and rad/m; for Frenet frames (τ, κ).
    h : float
        Step, m.
    integrator : str
        One of :data:`INTEGRATORS`.
    frenet : bool
        Integrate a Frenet frame (tangent = first axis) instead of a material frame (tangent = third axis).
    r0 : ndarray, shape (..., 3, 3), optional
        Initial frames; identity by default.

    Returns
    -------
    positions : ndarray, shape (..., n_steps + 1, 3)
    frames : ndarray, shape (..., n_steps + 1, 3, 3)
    """
    _check("integrator", integrator, INTEGRATORS)
    rates = np.asarray(rates, dtype=np.float64)
    m = len(_OFFSETS[integrator])
    c_ok = (2,) if frenet else (2, 3)
    if rates.ndim < 3 or rates.shape[-1] != m or rates.shape[-3] not in c_ok:
        raise ValueError(f"{integrator} needs rates of shape (..., {'|'.join(map(str, c_ok))}, n_steps, {m}), "
                         f"got {rates.shape}")
    batch, n = rates.shape[:-3], rates.shape[-2]
    rf = np.ascontiguousarray(rates.reshape((-1, *rates.shape[-3:])))
    n_f = rf.shape[0]
    if r0 is None:
        r0f = np.broadcast_to(np.eye(3), (n_f, 3, 3))
    else:
        r0f = np.broadcast_to(np.asarray(r0, dtype=np.float64), (*batch, 3, 3)).reshape(n_f, 3, 3)
    r0f = np.ascontiguousarray(r0f)
    pos = np.empty((n_f, n + 1, 3))
    frames = np.empty((n_f, n + 1, 3, 3))
    kernel = _kernels.rk4_chain if integrator == "rk4" else _kernels.exp_chain
    kernel(rf, bool(frenet), float(h), r0f, pos, frames)
    return pos.reshape((*batch, n + 1, 3)), frames.reshape((*batch, n + 1, 3, 3))


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def torsion_nodes(theta: np.ndarray, s_nodes: np.ndarray, scheme: str) -> tuple[np.ndarray, np.ndarray]:
    """Torsion samples from bend angles θ_b at the nodes (the paper's Frenet pipeline, docs/math.md §3.2).

    Parameters
    ----------
    theta : ndarray, shape (..., n_nodes)
        Bend-plane angles atan2(k_y, k_x), rad.
    s_nodes : ndarray, shape (n_nodes,)
    scheme : {"forward", "centred"}
        ``forward``: τ[n] = wrap(θ[n+1] − θ[n]) / l_n placed at node n, the last value linearly extrapolated
        (the paper). ``centred``: the same differences placed at the interval midpoints.

    Returns
    -------
    s_tau : ndarray, shape (n_tau,)
        Where the torsion values sit.
    tau : ndarray, shape (..., n_tau)
        Torsion, rad/m.
    """
    _check("torsion", scheme, ("forward", "centred"))
    n = s_nodes.size
    if n < 2:
        return s_nodes.copy(), np.zeros(theta.shape)
    l = np.diff(s_nodes)
    d = _wrap(np.diff(theta, axis=-1))
    if scheme == "centred":
        return 0.5 * (s_nodes[:-1] + s_nodes[1:]), d / l
    last = 2 * d[..., -1:] - d[..., -2:-1] if n >= 3 else d[..., -1:]
    # the paper's last node: Δθ_b[N-1] = 2Δθ_b[N-2] − Δθ_b[N-3], over the last spacing
    return s_nodes.copy(), np.concatenate([d, last], axis=-1) / np.append(l, l[-1])


def hold_bend_angle(theta: np.ndarray, kappa: np.ndarray, kappa_min: float) -> np.ndarray:
    """Bend-plane angles held through low curvature: where κ < ``kappa_min`` the last reliable θ_b is kept,
    and gratings before the first reliable one take that one's angle.

    The paper's pipeline (docs/math.md §3.2) is silent about near-zero curvature, where θ_b = atan2(k_y, k_x) is
    noise (atan2(0, 0) = 0 even without noise). Its wrapped differences there become torsion spikes that carry
    the Frenet frame into the next bend rolled by up to π. Holding θ_b gives zero torsion through the
    unreliable stretch, so the frame is carried through straight parts unchanged and the whole change of bend
    plane across the stretch is taken at its far end. This is our addition, not the paper's;
    ``kappa_min = 0`` returns ``theta`` unchanged (the literal transcription).

    Parameters
    ----------
    theta : ndarray, shape (..., n_nodes)
        Bend-plane angles, rad.
    kappa : ndarray, shape (..., n_nodes)
        Curvature magnitudes at the same nodes, 1/m.
    kappa_min : float
        Smallest curvature whose bend-plane angle is trusted, 1/m.

    Returns
    -------
    ndarray, shape (..., n_nodes)
        θ_b with every unreliable node replaced; a curve with no reliable node keeps its first angle everywhere.
    """
    theta = np.asarray(theta, dtype=np.float64)
    if not kappa_min > 0:
        return theta
    reliable = np.asarray(kappa) >= kappa_min
    n = theta.shape[-1]
    idx = np.where(reliable, np.arange(n), -1)
    last = np.maximum.accumulate(idx, axis=-1)
    first = np.argmax(reliable, axis=-1)[..., None]  # 0 when no node is reliable
    src = np.where(last < 0, first, last)
    return np.take_along_axis(theta, src, axis=-1)


def unwrap_nodes(theta: np.ndarray) -> np.ndarray:
    """Unwrap node angles along the last axis by wrapped increments (any jump is taken as the shortest turn)."""
    return theta[..., :1] + np.concatenate(
        [np.zeros((*theta.shape[:-1], 1)), np.cumsum(_wrap(np.diff(theta, axis=-1)), axis=-1)], axis=-1
    )
