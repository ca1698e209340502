"""Spun (helical) multi-core fibres: the strain of a helical core and the per-grating twist inversion.

docs/spun-fibers.md derives both models. In the material frame (d1, d2, d3) of the fibre, whose Darboux vector
is u = (κ1, κ2, τ) with the curvature vector k = (k_x, k_y) = (κ2, −κ1) (twin/_kernels.py, docs/math.md §1),
an outer core at radius r sits at angle φ_i(s) = θ_i + Ω s. Its position is X = x + r (cos φ d1 + sin φ d2), and

    |X'|² = (1 + ε_0 − r (k_x cos φ + k_y sin φ))² + r² (Ω + τ)²,

so the core's strain against the unloaded helix (|X'|² = 1 + r²Ω²) is the exact path-length strain

    ε_i = |X'| / √(1 + r²Ω²) − 1                                                     (:func:`exact_strain`)

and to first order in ε_0, r k and τ/Ω (cos²α = 1/(1 + r²Ω²), α the helix angle)

    ε_i = ε_0 + cos²α [ −r (k_x cos φ + k_y sin φ) + r² Ω τ ]                       (:func:`linear_strain`).

The twin's optics use the exact form; the reconstruction inverts the linear one, per grating, for
x = (c, k_x, k_y, τ) with the design row [1, −g c²_α cos φ, −g c²_α sin φ, g r c²_α Ω] (g = r S_ε; the centre core's
row is [1, 0, 0, 0]) by weighted least squares (Moore & Rogge, Opt. Express 20:2967 (2012); US 8,531,655).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.fiber import FiberModel
from twin.strain import StrainSolution, design_matrix, reciprocal_condition

__all__ = [
    "TwistSolution",
    "TwistSolver",
    "exact_strain",
    "exact_twist",
    "helix_of",
    "linear_strain",
    "twist_design",
    "twist_sensitivity",
]


def _phase(fiber: FiberModel, s, twist) -> np.ndarray:
    s = fiber.grating_s if s is None else np.asarray(s, dtype=np.float64)
    phi = fiber.core_phase(s)
    if twist is not None:
        phi = phi + np.asarray(twist, dtype=np.float64)[..., None]
    return phi


def _bend_projection(curvature, phi) -> np.ndarray:
    k = np.asarray(curvature, dtype=np.float64)
    return k[..., 0:1] * np.cos(phi) + k[..., 1:2] * np.sin(phi)


def exact_strain(fiber: FiberModel, curvature, twist_rate, axial_strain=0.0, *, s=None, twist=None) -> np.ndarray:
    """Mechanical strain of every core from its helical path length (the twin's optics).

    Parameters
    ----------
    fiber : FiberModel
    curvature : array_like, shape (..., n_s, 2)
        Curvature vector (k_x, k_y) in the material frame, 1/m.
    twist_rate : array_like, shape (..., n_s)
        Mechanical twist rate τ (the Darboux vector's tangential component), rad/m.
    axial_strain : float or array_like, shape (..., n_s)
        Strain of the neutral axis ε_0.
    s : array_like, shape (n_s,), optional
        Arc lengths, m; default the gratings.
    twist : array_like, shape (n_s,), optional
        Intrinsic (fabrication) twist of the cores, rad, added to θ_i + Ω s.

    Returns
    -------
    ndarray, shape (..., n_s, n_cores)
        Strain along each core (the central core's is ε_0).
    """
    phi = _phase(fiber, s, twist)
    r = fiber.core_radii
    omega = fiber.spin_omega
    e0 = np.asarray(axial_strain, dtype=np.float64)[..., None]
    tau = np.asarray(twist_rate, dtype=np.float64)[..., None]
    axial = 1.0 + e0 - r * _bend_projection(curvature, phi)
    return np.sqrt((axial**2 + (r * (omega + tau)) ** 2) / (1.0 + (r * omega) ** 2)) - 1.0


def linear_strain(fiber: FiberModel, curvature, twist_rate, axial_strain=0.0, *, s=None, twist=None) -> np.ndarray:
    """The linearised strain ε_0 + cos²α (−r k·u_φ + r²Ωτ) the reconstruction inverts; arguments as
    :func:`exact_strain`."""
    phi = _phase(fiber, s, twist)
    r = fiber.core_radii
    tau = np.asarray(twist_rate, dtype=np.float64)[..., None]
    e0 = np.asarray(axial_strain, dtype=np.float64)[..., None]
    return e0 + fiber.helix_cos2 * (-r * _bend_projection(curvature, phi) + r * r * fiber.spin_omega * tau)


def twist_sensitivity(fiber: FiberModel) -> np.ndarray:
    """∂ε_i/∂τ of the linear model, cos²α r_i² Ω per core, m/rad (strain per rad/m; 0 for the central core)."""
    return fiber.helix_cos2 * fiber.core_radii**2 * fiber.spin_omega


def exact_twist(tau_linear, omega: float, radius: float) -> np.ndarray:
    """The twist rate τ whose exact helical path length gives the linear model's estimate ``tau_linear``, rad/m.

    Solves √(1 + c r²(2Ωτ + τ²)) − 1 = c r² Ω τ_lin (c = cos²α = 1/(1 + r²Ω²)) for the root near τ_lin:
    τ = −Ω + sign(Ω) √(Ω² + q), q = ((1 + c r²Ω τ_lin)² − 1)/(c r²).
    """
    c = 1.0 / (1.0 + (radius * omega) ** 2)
    m = c * radius**2 * omega * np.asarray(tau_linear, dtype=np.float64)
    q = ((1.0 + m) ** 2 - 1.0) / (c * radius**2)
    return -omega + np.sign(omega) * np.sqrt(np.maximum(omega**2 + q, 0.0))


def helix_of(fiber: FiberModel, calibration=None) -> tuple[float, float]:
    """(Ω rad/m, mean outer-core radius m) of a spun fibre, with a calibration's spin rate when it has one."""
    rate = fiber.spin_rate if getattr(calibration, "spin_rate", None) is None else calibration.spin_rate
    return fiber.handedness * 2 * np.pi * rate, float(fiber.core_radii[fiber.bending_cores].mean())


def twist_design(fiber: FiberModel, calibration=None) -> np.ndarray:
    """Design matrices with a twist column, shape (n_gratings, n_cores, 4): e = D (c, k_x, k_y, τ).

    The first three columns are the (calibrated) bending design of :func:`twin.strain.design_matrix`; the
    fourth is S_ε cos²α r_i² Ω with the calibration's spin rate and gain scale when it has them.
    """
    if calibration is None:
        d3 = design_matrix(fiber)
        spun = fiber
        scale = 1.0
    else:
        d3 = calibration.design_for(fiber)
        spun = fiber if getattr(calibration, "spin_rate", None) is None else fiber.replace(
            spin_rate=calibration.spin_rate)
        nominal = float(fiber.core_radii[fiber.bending_cores].mean() * fiber.strain_sensitivity)
        scale = 1.0 if calibration.gain is None else calibration.gain / nominal
    col = fiber.strain_sensitivity * scale * twist_sensitivity(spun)
    d = np.empty((*d3.shape[:2], 4))
    d[..., :3] = d3
    d[..., 3] = col
    return d


@dataclass(frozen=True, eq=False)
class TwistSolution(StrainSolution):
    """A :class:`~twin.strain.StrainSolution` with the twist rate and 1σ uncertainties per grating.

    Attributes
    ----------
    twist_rate : ndarray, shape (..., n_gratings)
        Mechanical twist rate τ, rad/m (NaN where invalid; interpolated where ``twist_filled``).
    curvature_std : ndarray, shape (n_gratings, 2)
        1σ of (k_x, k_y) from the assumed wavelength noise with every peak present, 1/m.
    twist_rate_std : ndarray, shape (n_gratings,)
        1σ of τ likewise, rad/m.
    twist_filled : ndarray of bool, shape (..., n_gratings)
        Gratings that lost a peak the twist needs but not bending: τ there is interpolated from the frame's
        other gratings (and its term removed before the curvature was solved).
    """

    twist_rate: np.ndarray
    curvature_std: np.ndarray
    twist_rate_std: np.ndarray
    twist_filled: np.ndarray


class TwistSolver:
    """Per-grating weighted least squares for (c, k_x, k_y, τ) (batch-first; missing peaks drop their rows).

    Parameters
    ----------
    design : ndarray, shape (n_gratings, n_cores, 4)
        See :func:`twist_design`.
    strain_std : float or array_like, shape (n_cores,) or (n_gratings, n_cores)
        1σ of each optical strain Δλ/λ0 (the wavelength noise over λ0); the weights are its inverse squares and
        the reported uncertainties follow from it.
    rcond : float
        Gratings whose scaled normal matrix is worse conditioned than this are invalid (for instance a lost
        centre-core peak: twist and the common mode are then inseparable).
    helix : tuple of float (Ω rad/m, r m), optional
        Undo the helix's second-order path length: the linear twist estimate τ_lin is mapped through the exact
        pure-twist relation √(1 + cos²α r²(2Ωτ + τ²)) − 1 = cos²α r² Ω τ_lin (docs/spun-fibers.md), which
        removes the τ/(2Ω) relative bias (1.6 % at 10 rad/m and 50 turns/m). None: the linear estimate.
    s : array_like, shape (n_gratings,), optional
        Grating positions, m, for interpolating τ into gratings that lost a peak the twist needs (default:
        equally spaced).
    """

    def __init__(self, design, strain_std=1e-3 / 1550.0, *, rcond: float = 1e-9, helix=None, s=None):
        d = np.array(design, dtype=np.float64)
        if d.ndim != 3 or d.shape[2] != 4:
            raise ValueError(f"design must have shape (n_gratings, n_cores, 4), got {d.shape}")
        self.n_gratings, self.n_cores = d.shape[:2]
        sd = np.broadcast_to(np.asarray(strain_std, dtype=np.float64), (self.n_gratings, self.n_cores))
        if np.any(~np.isfinite(sd)) or np.any(sd <= 0):
            raise ValueError("strain_std must be finite and positive")
        self.weights = 1.0 / sd**2
        # columns scaled to O(1) so the conditioning test is unit-free
        self._scale = 1.0 / np.maximum(np.abs(d).max(axis=(0, 1)), 1e-300)
        self._ds = d * self._scale
        self.design = d
        self.rcond = float(rcond)
        self.helix = None if helix is None else (float(helix[0]), float(helix[1]))
        self.s = np.arange(self.n_gratings, dtype=np.float64) if s is None else np.asarray(s, dtype=np.float64)
        normal, dtw = self._normal(np.ones((self.n_gratings, self.n_cores), bool), np.arange(self.n_gratings))
        bad = reciprocal_condition(normal) < self.rcond
        if bad.any():
            n = int(np.argmax(bad))
            raise ValueError(
                f"grating {n}: this spun fibre cannot separate twist from the common mode and bending; it needs a "
                "central core (or a core at another radius) and 3 outer cores not all on one line"
            )
        inv = np.linalg.inv(normal)
        self._p = (inv @ dtw) * self._scale[:, None]  # (n_g, 4, n_c): x = P e
        cov = inv * np.outer(self._scale, self._scale)
        self.std = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))  # (n_g, 4): c, k_x, k_y, τ

    def _normal(self, present: np.ndarray, nodes: np.ndarray):
        ds = self._ds[nodes]
        w = self.weights[nodes] * present
        dtw = np.swapaxes(ds, -1, -2) * w[..., None, :]
        return dtw @ ds, dtw

    def solve(self, strain) -> TwistSolution:
        """Invert optical strain of shape (..., n_gratings, n_cores); NaN entries are missing peaks."""
        e = np.asarray(strain, dtype=np.float64)
        if e.ndim < 2 or e.shape[-2:] != (self.n_gratings, self.n_cores):
            raise ValueError(
                f"expected optical strain of shape (..., {self.n_gratings}, {self.n_cores}), got {e.shape}")
        missing = np.isnan(e)
        e0 = np.where(missing, 0.0, e)
        x = np.einsum("nkc,...nc->...nk", self._p, e0)
        hit = missing.any(axis=-1)
        filled = np.zeros(hit.shape, bool)
        if hit.any():
            x[hit] = np.nan
            idx = np.nonzero(hit)
            normal, dtw = self._normal(~missing[idx], idx[-1])
            ok = reciprocal_condition(normal) >= self.rcond
            if ok.any():
                sol = np.linalg.solve(normal[ok], dtw[ok] @ e0[idx][ok][..., None])[..., 0] * self._scale
                x[tuple(a[ok] for a in idx)] = sol
            # Too few rows for the twist (a 4-core fibre that lost a peak): τ there is interpolated from the
            # frame's other gratings and its term removed before solving for bending and the common mode alone.
            if (~ok).any():
                rest = tuple(a[~ok] for a in idx)
                n3, d3 = normal[~ok][:, :3, :3], dtw[~ok][:, :3, :]
                ok3 = reciprocal_condition(n3) >= self.rcond
                if ok3.any():
                    sel = tuple(a[ok3] for a in rest)
                    tau = self._fill(x[..., 3], sel)
                    rhs = e0[sel] - self.design[sel[-1], :, 3] * tau[:, None]
                    sol = np.linalg.solve(n3[ok3], d3[ok3] @ rhs[..., None])[..., 0] * self._scale[:3]
                    x[(*sel, slice(0, 3))] = sol
                    x[(*sel, 3)] = tau
                    filled[sel] = True
        valid = ~np.isnan(x[..., 1])
        if self.helix is not None and self.helix[0] != 0:
            x[..., 3] = exact_twist(x[..., 3], *self.helix)
        return TwistSolution(
            curvature=x[..., 1:3],
            common_mode=x[..., 0],
            valid=valid,
            twist_rate=x[..., 3],
            curvature_std=self.std[:, 1:3],
            twist_rate_std=self.std[:, 3],
            twist_filled=filled,
        )

    def _fill(self, tau: np.ndarray, sel: tuple) -> np.ndarray:
        """τ at the gratings ``sel`` interpolated linearly in s from the same frame's measured ones (0 when the
        frame has none); a loop over the affected frames only: a lost peak is the exception."""
        tf = tau.reshape(-1, self.n_gratings)
        frame = np.ravel_multi_index(sel[:-1], tau.shape[:-1]) if tau.ndim > 1 else np.zeros(sel[-1].size, int)
        out = np.zeros(sel[-1].size)
        for f in np.unique(frame):
            good = ~np.isnan(tf[f])
            here = frame == f
            if good.any():
                out[here] = np.interp(self.s[sel[-1][here]], self.s[good], tf[f, good])
        return out
