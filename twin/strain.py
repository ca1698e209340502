"""Wavelengths ↔ strain ↔ curvature vectors (docs/math.md §2).

Everything works in *optical strain* e = Δλ/λ0, which is free of S_ε and of the core radius. At each grating n
the cores see (docs/math.md §2.2, with g_i = r_i S_ε)

    e_i = c − g_i (k_x cos θ_i + k_y sin θ_i),        c = S_ε ε_axial + S_T ΔT  (the common mode),

i.e. e = D x with x = (c, k_x, k_y) and the *design matrix* D, rows [1, −g_i cos θ_i, −g_i sin θ_i]. The
default inverse is the weighted least-squares solution of that system, exact for any core layout and with or
without a central core; a missing peak removes its row. ``method="paper"`` is Al-Ahmad et al. eqs. 5–7 (subtract
the central core, k_app = −Σ ε_i u_i / r, κ = 2|k_app|/N), exact only for layouts with Σ e^{2iθ} = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.fiber import FiberModel

__all__ = [
    "CurvatureSolver",
    "StrainSolution",
    "curvature",
    "design_matrix",
    "forward",
    "optical_strain",
]

METHODS = ("lstsq", "paper")


def _core_angles(fiber: FiberModel, core_angles, twist) -> np.ndarray:
    """Effective CCW core angles per grating, shape (..., n_gratings, n_cores)."""
    theta = fiber.ccw_angles if core_angles is None else fiber.handedness * np.asarray(core_angles, float)
    theta = np.broadcast_to(theta, (fiber.n_gratings, fiber.n_cores)) if theta.ndim < 2 else theta
    if fiber.spin_rate:
        # a spun fibre's cores advance by Ω s along it (docs/spun-fibers.md)
        theta = theta + fiber.spin_omega * fiber.grating_s[:, None]
    if twist is not None:
        theta = theta + np.asarray(twist, dtype=np.float64)[..., None]
    return theta


def design_matrix(fiber: FiberModel, *, core_angles=None, gains=None, twist=None) -> np.ndarray:
    """The per-grating design matrix D, shape (n_gratings, n_cores, 3), with e = D (c, k_x, k_y).

    Parameters
    ----------
    fiber : FiberModel
    core_angles : array_like, shape (n_cores,) or (n_gratings, n_cores), optional
        Core angles in the fibre's own sense (``fiber.handedness`` applies), rad; default the fibre's.
    gains : array_like, shape (n_cores,) or (n_gratings, n_cores), optional
        g_i = r_i S_ε, m; default ``fiber.gains``.
    twist : array_like, shape (n_gratings,), optional
        Intrinsic twist angle of the cores at each grating, rad (cores at θ_i + φ_n).

    A spun fibre (``fiber.spin_rate`` ≠ 0) has its cores at θ_i + Ω s_n + φ_n and its bending columns scaled by
    cos²α (the linear model of docs/spun-fibers.md; :func:`twin.spun.twist_design` adds the twist column).
    """
    theta = _core_angles(fiber, core_angles, twist)
    g = fiber.gains if gains is None else np.asarray(gains, dtype=np.float64)
    if fiber.spin_rate:
        g = g * fiber.helix_cos2  # a helical core feels cos²α of the bending strain (docs/spun-fibers.md)
    g = np.broadcast_to(g, theta.shape)
    d = np.empty((*theta.shape, 3))
    d[..., 0] = 1.0
    d[..., 1] = -g * np.cos(theta)
    d[..., 2] = -g * np.sin(theta)
    return d


def optical_strain(wavelengths, lambda0) -> np.ndarray:
    """e = (λ − λ0)/λ0, dimensionless; NaN stays NaN. Shapes broadcast: (..., n_gratings, n_cores)."""
    lambda0 = np.asarray(lambda0, dtype=np.float64)
    return (np.asarray(wavelengths, dtype=np.float64) - lambda0) / lambda0


def forward(
    fiber: FiberModel,
    curvature,
    axial_strain=0.0,
    delta_T=0.0,
    *,
    twist=None,
    core_angles=None,
    gains=None,
    lambda0=None,
    design=None,
) -> np.ndarray:
    """Bragg wavelengths for given curvature vectors (docs/math.md §2.1–2.2).

    Parameters
    ----------
    fiber : FiberModel
    curvature : array_like, shape (..., n_gratings, 2)
        Curvature vector (k_x, k_y) in the fibre's material frame at each grating, 1/m.
    axial_strain : float or array_like, shape (..., n_gratings)
        Mechanical strain of the neutral axis (common to all cores).
    delta_T : float or array_like, shape (..., n_gratings)
        Temperature change from the reference, K. Per-core S_T (``fiber.temperature_sensitivity``) applies.
    twist : array_like, shape (..., n_gratings), optional
        Intrinsic twist of the cores at each grating, rad: the cores sit at θ_i + φ_n.
    core_angles, gains : optional overrides of the fibre's core angles (rad) and gains g = r S_ε (m).
    lambda0 : array_like, shape (n_gratings, n_cores), optional
        Unstrained wavelengths, nm; default ``fiber.lambda0``.
    design : array_like, shape (n_gratings, n_cores, 3), optional
        Precomputed :func:`design_matrix` (replaces ``twist``, ``core_angles`` and ``gains``; saves the
        trigonometry when called at a sensor rate).

    Returns
    -------
    ndarray, shape (..., n_gratings, n_cores)
        Wavelengths, nm.
    """
    k = np.asarray(curvature, dtype=np.float64)
    if k.ndim < 2 or k.shape[-2:] != (fiber.n_gratings, 2):
        raise ValueError(f"forward: curvature must have shape (..., {fiber.n_gratings}, 2), got {k.shape}")
    d = design_matrix(fiber, core_angles=core_angles, gains=gains, twist=twist) if design is None else design
    e = d[..., 1] * k[..., 0:1] + d[..., 2] * k[..., 1:2]
    # zero common modes are skipped: this runs at the simulated interrogator's rate
    if np.ndim(axial_strain) or axial_strain != 0:
        e = e + fiber.strain_sensitivity * np.asarray(axial_strain, dtype=np.float64)[..., None]
    if np.ndim(delta_T) or delta_T != 0:
        e = e + np.asarray(delta_T, dtype=np.float64)[..., None] * np.asarray(fiber.temperature_sensitivity)
    lam0 = fiber.lambda0 if lambda0 is None else np.asarray(lambda0, dtype=np.float64)
    return lam0 * (1.0 + e)


@dataclass(frozen=True, eq=False)
class StrainSolution:
    """Per-grating inversion result (leading axes ``...`` follow the input).

    Attributes
    ----------
    curvature : ndarray, shape (..., n_gratings, 2)
        (k_x, k_y), 1/m; NaN where ``valid`` is False.
    common_mode : ndarray, shape (..., n_gratings)
        Common optical strain c = S_ε ε_axial + S_T ΔT (NaN where invalid or not estimated, e.g. paper mode).
    valid : ndarray of bool, shape (..., n_gratings)
        Whether enough cores remained to separate bending from the common mode.
    """

    curvature: np.ndarray
    common_mode: np.ndarray
    valid: np.ndarray


class CurvatureSolver:
    """Inverts optical strain to curvature vectors for one sensor configuration (precomputed, batch-first).

    Parameters
    ----------
    design : ndarray, shape (n_gratings, n_cores, 3)
        Design matrices (see :func:`design_matrix`); a jig calibration may supply fitted ones.
    method : {"lstsq", "paper"}
        Weighted least squares (default) or Al-Ahmad et al. eqs. 5–7 (needs ``central_core``).
    central_core : int or None
        Index of the central core (required by the paper method).
    weights : array_like, shape (n_cores,) or (n_gratings, n_cores), optional
        Inverse variances of the optical strains, any scale; default equal.
    rcond : float
        Nodes whose (scaled) normal matrix has a reciprocal condition number below this are invalid.
    """

    def __init__(self, design, *, method: str = "lstsq", central_core: int | None = None, weights=None,
                 rcond: float = 1e-6):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        d = np.array(design, dtype=np.float64)
        if d.ndim != 3 or d.shape[2] != 3:
            raise ValueError(f"design must have shape (n_gratings, n_cores, 3), got {d.shape}")
        if not np.all(np.isfinite(d)):
            raise ValueError("design contains non-finite values")
        self.method = method
        self.n_gratings, self.n_cores = d.shape[:2]
        self.rcond = float(rcond)
        w = np.ones((self.n_gratings, self.n_cores)) if weights is None else np.broadcast_to(
            np.asarray(weights, dtype=np.float64), (self.n_gratings, self.n_cores)).copy()
        if np.any(~np.isfinite(w)) or np.any(w <= 0):
            raise ValueError("weights must be finite and positive")
        self.weights = w
        # Scale the bending columns to O(1) so the conditioning test does not depend on units.
        bend = np.linalg.norm(d[..., 1:], axis=-1)
        self._scale = np.array([1.0, 1.0, 1.0])
        if np.any(bend > 0):
            g_typ = float(np.median(bend[bend > 0]))
            self._scale = np.array([1.0, 1.0 / g_typ, 1.0 / g_typ])
        self.design = d
        self._ds = d * self._scale  # columns scaled to O(1): unknowns (c, k_x g, k_y g)
        if method == "paper":
            if central_core is None:
                raise ValueError(
                    "the paper method (eqs. 5–7) subtracts the central core's strain; this fibre has no central "
                    "core — use method='lstsq', which estimates the common mode"
                )
            self.central_core = int(central_core)
            outer = np.flatnonzero(bend.min(axis=0) > 0)
            g = bend[:, outer]  # (n_g, n_outer)
            u = -d[:, outer, 1:] / g[..., None]  # unit core directions (n_g, n_outer, 2)
            p = np.zeros((self.n_gratings, 2, self.n_cores))
            # k = (2/N) k_app = -(2/N) Σ (e_i − e_c) u_i / g_i
            coef = -(2.0 / outer.size) * u / g[..., None]  # (n_g, n_outer, 2)
            p[:, :, outer] = np.swapaxes(coef, 1, 2)
            p[:, :, self.central_core] -= coef.sum(axis=1)
            self._p = p
            self._needed = np.zeros(self.n_cores, bool)
            self._needed[outer] = True
            self._needed[self.central_core] = True
        else:
            self.central_core = central_core
            dtw = np.swapaxes(self._ds, 1, 2) * w[:, None, :]  # (n_g, 3, n_c)
            normal = dtw @ self._ds
            if np.any(reciprocal_condition(normal) < self.rcond):
                n = int(np.argmax(reciprocal_condition(normal) < self.rcond))
                raise ValueError(
                    f"grating {n}: this core layout cannot separate bending (k_x, k_y) from the common mode; "
                    "it needs a central core and 2 off-axis cores at different angles, or 3 off-axis cores "
                    "not all on one line"
                )
            p = np.linalg.solve(normal, dtw) * self._scale[:, None]
            self._common = p[:, 0, :]
            self._p = p[:, 1:, :]
        # The whole inversion as one matrix on the flattened strains: columns (k_x nodes, k_y nodes, c nodes),
        # so a batch of frames is a single matrix product.
        n_g, n_c = self.n_gratings, self.n_cores
        big = np.zeros((n_g, n_c, 3, n_g))
        rows = np.arange(n_g)
        big[rows, :, 0, rows] = self._p[:, 0, :]
        big[rows, :, 1, rows] = self._p[:, 1, :]
        if method == "paper":
            big[:, :, 2, :] = 0.0
        else:
            big[rows, :, 2, rows] = self._common
        self._big = np.ascontiguousarray(big.reshape(n_g * n_c, 3 * n_g))

    @classmethod
    def for_fiber(cls, fiber: FiberModel, *, method: str = "lstsq", core_angles=None, gains=None, twist=None,
                  weights=None) -> CurvatureSolver:
        """A solver for a fibre model (optionally with calibrated angles, gains and twist)."""
        d = design_matrix(fiber, core_angles=core_angles, gains=gains, twist=twist)
        return cls(d, method=method, central_core=fiber.central_core, weights=weights)

    def fused_operator(self) -> tuple:
        """This solver as the tuple the fused kernel takes (:mod:`twin._fused`): (pseudo-inverse (n_g, 2, n_c),
        scaled design (n_g, n_c, 3), weights (n_g, n_c), column scale (3,), cores the paper method needs
        (n_c,), rcond, paper?). Cached: the same arrays on every call."""
        op = self.__dict__.get("_fused_op")
        if op is None:
            paper = self.method == "paper"
            needed = self._needed if paper else np.zeros(self.n_cores, bool)
            op = (np.ascontiguousarray(self._p), np.ascontiguousarray(self._ds), np.ascontiguousarray(self.weights),
                  np.ascontiguousarray(self._scale), np.ascontiguousarray(needed), self.rcond, paper)
            self._fused_op = op
        return op

    def solve(self, strain) -> StrainSolution:
        """Invert optical strain ``e`` of shape (..., n_gratings, n_cores); NaN (and infinite) entries are missing
        peaks (the physical window is :func:`outside_window`'s, applied by the caller)."""
        e = np.asarray(strain, dtype=np.float64)
        if e.ndim < 2 or e.shape[-2:] != (self.n_gratings, self.n_cores):
            raise ValueError(
                f"expected optical strain of shape (..., {self.n_gratings}, {self.n_cores}), got {e.shape}"
            )
        inf = np.isinf(e)
        if inf.any():
            e = np.where(inf, np.nan, e)
        missing = np.isnan(e)
        if not missing.any():
            n_g = self.n_gratings
            x = (e.reshape((*e.shape[:-2], -1)) @ self._big).reshape((*e.shape[:-2], 3, n_g))
            k = np.swapaxes(x[..., :2, :], -1, -2)  # a view: (k_x, k_y) contiguous per component
            c = np.full(e.shape[:-1], np.nan) if self.method == "paper" else x[..., 2, :]
            return StrainSolution(k, c, np.ones(e.shape[:-1], bool))
        return self._solve_missing(e, missing)

    def _solve_missing(self, e: np.ndarray, missing: np.ndarray) -> StrainSolution:
        batch = e.shape[:-2]
        k = np.full((*batch, self.n_gratings, 2), np.nan)
        c = np.full((*batch, self.n_gratings), np.nan)
        hit = missing.any(axis=-1)  # (..., n_g): nodes needing the slow path
        full = ~hit
        e0 = np.where(missing, 0.0, e)
        k_fast = np.einsum("nkc,...nc->...nk", self._p, e0)
        k[full] = k_fast[full]
        if self.method == "paper":
            # eqs. 5–7 need every core they use; a node missing one of them is invalid.
            usable = ~np.any(missing & self._needed, axis=-1)
            k[usable & hit] = k_fast[usable & hit]
            return StrainSolution(k, c, ~np.isnan(k[..., 0]))
        c_fast = np.einsum("nc,...nc->...n", self._common, e0)
        c[full] = c_fast[full]
        idx = np.nonzero(hit)
        node = idx[-1]
        w = self.weights[node] * ~missing[idx]  # (m, n_c)
        ds = self._ds[node]  # (m, n_c, 3)
        dtw = np.swapaxes(ds, 1, 2) * w[:, None, :]
        normal = dtw @ ds
        ok = reciprocal_condition(normal) >= self.rcond
        if ok.any():
            x = np.linalg.solve(normal[ok], (dtw[ok] @ e0[idx][ok][..., None]))[..., 0] * self._scale
            sel = tuple(a[ok] for a in idx)
            c[sel] = x[:, 0]
            k[sel] = x[:, 1:]
        return StrainSolution(k, c, ~np.isnan(k[..., 0]))


def curvature(
    fiber: FiberModel,
    wavelengths,
    reference=None,
    method: str = "lstsq",
    *,
    weights=None,
) -> np.ndarray:
    """Curvature vectors from peak wavelengths.

    Parameters
    ----------
    fiber : FiberModel
    wavelengths : array_like, shape (..., n_gratings, n_cores)
        Peak wavelengths, nm; NaN for a missing peak.
    reference : array_like, shape (n_gratings, n_cores), optional
        Reference (straight, unloaded) wavelengths, nm; default ``fiber.lambda0``.
    method : {"lstsq", "paper"}
        Weighted least squares for any layout (missing peaks drop out while the node stays solvable), or the
        paper's eqs. 5–7.
    weights : array_like, optional
        Relative inverse variances of the cores' optical strains (see :class:`CurvatureSolver`).

    Returns
    -------
    ndarray, shape (..., n_gratings, 2)
        (k_x, k_y) in the fibre's material frame, 1/m; NaN at nodes that could not be solved.
    """
    w = np.asarray(wavelengths, dtype=np.float64)
    if w.ndim < 2 or w.shape[-2:] != (fiber.n_gratings, fiber.n_cores):
        raise ValueError(
            f"wavelengths must have shape (..., {fiber.n_gratings}, {fiber.n_cores}) for this fibre, got {w.shape}"
        )
    lam0 = fiber.lambda0 if reference is None else np.asarray(reference, dtype=np.float64)
    if lam0.shape != (fiber.n_gratings, fiber.n_cores):
        raise ValueError(f"reference must have shape {(fiber.n_gratings, fiber.n_cores)}, got {lam0.shape}")
    solver = CurvatureSolver.for_fiber(fiber, method=method, weights=weights)
    return solver.solve(optical_strain(w, lam0)).curvature


def outside_window(strain, max_strain: float | None) -> np.ndarray:
    """Boolean mask, same shape: optical strains outside the physical window |e| ≤ ``max_strain`` (None: no
    window), or infinite. NaN (an absent peak) is not "outside": it is missing already."""
    e = np.asarray(strain, dtype=np.float64)
    if max_strain is None:
        return np.isinf(e)
    return np.abs(e) > max_strain  # NaN compares False


def reciprocal_condition(normal: np.ndarray) -> np.ndarray:
    """Smallest over largest eigenvalue of symmetric normal matrices (..., k, k): 0 for a singular one."""
    ev = np.linalg.eigvalsh(normal)
    return ev[..., 0] / np.maximum(ev[..., -1], 1e-300)
