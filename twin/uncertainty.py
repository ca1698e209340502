"""Calibrated uncertainty of a reconstruction: curvature covariance at the gratings and position covariance along
the centreline, linearised and batch-first (docs/math.md §8).

Three sources are propagated:

(a) **interrogator noise**: white wavelength noise σ_λ per peak (nm), through the per-grating least-squares
    inversion: Σ_x = P diag(σ_λ²/λ0²) Pᵀ for x = (c, k_x, k_y), P the (masked) pseudo-inverse;
(b) **the calibration's parameters**: the identified Δθ and g with their 1σ (:class:`~twin.Calibration`
    ``delta_theta_std``, ``gain_std``, taken as uncorrelated), through ∂x/∂p = −P (∂D/∂p) x; one error shared by
    every grating, so it enters the positions as a low-rank term with its correlation along the fibre;
(c) **the model error** (:class:`ModelError`): what the reconstruction's model leaves — the grating's length,
    drift of the reference — as a white per-grating curvature error of 1σ ``curvature`` + ``relative``·|k| per
    component; the interpolation error between gratings estimated per frame from the measured curvature's
    second (linear interpolant) or fourth (spline) differences (``interpolation``; a lost grating's gap widens
    it); the catheter's twist that the fibre cannot see, a constant twist rate shared by every grating
    (``twist``); and optionally an error of the base frame's angle and a factor on the stated parameter errors,
    calibrated on shapes of known truth with :func:`fit_model_error`.

A curvature error δk(s) rotates everything beyond s about p(s) by R(s) δu(s) ds, δu = (−δk_y, δk_x, 0), so to
first order δp(s_j) = ∫_0^{s_j} (R δu)(s) × (p(s_j) − p(s)) ds, with δk(s) the interpolation basis applied to
the gratings' δk (the reconstructor's own basis). A compiled pass per batch integrates it piece by piece
between gratings and interpolates the covariance between them (docs/math.md §8.2).

:class:`Uncertainty` wraps a :class:`~twin.Reconstructor` (public API only) and returns a
:class:`~twin.frames.Shape` carrying ``covariance`` and ``curvature_covariance``; :meth:`Shape.confidence` gives
the radius of the level-% tube from the lateral (2-D) part of the covariance. docs/math.md §8 has the equations
and the checks.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import numpy as np
from numba import njit

from twin import curve
from twin.calibration import Calibration, nominal_delta_theta, nominal_gain
from twin.frames import Shape
from twin.reconstruct import Reconstructor

__all__ = ["TWIN_INTERPOLATION", "TWIN_MODEL_ERROR", "ModelError", "Uncertainty", "coverage", "fit_model_error",
           "inside", "interpolation_order", "lateral_errors", "truth_in_base"]


@dataclass(frozen=True)
class ModelError:
    """The reconstruction model's own error, as a white curvature error per grating (1σ per component).

    Attributes
    ----------
    curvature : float
        Absolute part, 1/m.
    relative : float
        Part proportional to the measured |k| (dimensionless): σ = ``curvature`` + ``relative``·|k|.
    interpolation : float
        Constant c of the interpolation error between gratings (dimensionless; :meth:`interpolation_sigma`): per
        frame, the curvature's second (linear interpolant) or fourth (spline) divided difference over the valid
        gratings, times the pieces' lengths, gives each grating a white error that carries the interpolant's
        error over its pieces. For a linear interpolant and a quadratic curvature profile c = 1/12 is exact
        (docs/math.md §8.1); a lost grating leaves a piece of 2h, whose error is 8 (linear) or 32 (spline) times
        that of a piece h, so the tube widens there. The constant belongs to its interpolant.
    base_angle : float
        1σ of the base frame's orientation about each of its axes, rad: the reconstruction starts from the base
        frame as given (a clamp, a tracked hub), which sits off the fibre's true first tangent and roll by this
        much; it moves every point by δφ × p.
    twist : float
        1σ of the catheter's twist rate that the fibre does not measure, rad/m, taken as constant along the
        fibre: a fibre without a twist measurement reconstructs as if the material frame did not turn about the
        tangent, which is the true curvature rotated back by the twist angle ψ(s) = τ s, an error
        δk(s) = ψ(s) J k(s) (:meth:`twist_sensitivity`). One error shared by every grating, so it keeps its
        correlation along the fibre, and it grows with s and |k|: in a sheath, where friction twists the
        catheter, the distal tube's largest term.
    parameter_scale : float
        Factor on the calibration's stated 1σ of Δθ and g (1: as identified). :func:`fit_model_error` lowers it
        only when noise and the parameters alone already hold more than the level on the fitting shapes: an
        identification's jackknife can overstate its error (docs/math.md §8.4).
    source : str
        How the values were found (free text, for reports).
    """

    curvature: float = 0.0
    relative: float = 0.0
    base_angle: float = 0.0
    interpolation: float = 0.0
    parameter_scale: float = 1.0
    source: str = ""
    twist: float = 0.0

    def __post_init__(self) -> None:
        for name in ("curvature", "relative", "base_angle", "parameter_scale", "interpolation", "twist"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"ModelError.{name}: expected a finite value >= 0, got {v}")
            object.__setattr__(self, name, float(v))

    def sigma(self, curvature: np.ndarray, grating_s: np.ndarray | None = None,
              valid: np.ndarray | None = None, order: int = 2) -> np.ndarray:
        """1σ per component at each grating, 1/m, shape (..., n_gratings), from curvature (..., n_gratings, 2):
        the white part and, with the gratings' arc lengths ``grating_s`` (n_gratings,) m and ``valid``
        (..., n_gratings) bool, the interpolation part (:meth:`interpolation_sigma` of ``order``), added in
        variance."""
        white = self.curvature + self.relative * np.hypot(curvature[..., 0], curvature[..., 1])
        if not self.interpolation or grating_s is None:
            return np.broadcast_to(white, curvature.shape[:-1])
        if valid is None:
            valid = np.ones(curvature.shape[:-1], bool)
        return np.hypot(white, self.interpolation_sigma(curvature, grating_s, valid, order))

    def interpolation_sigma(self, curvature: np.ndarray, grating_s: np.ndarray, valid: np.ndarray,
                            order: int = 2) -> np.ndarray:
        """The interpolation part of the per-grating 1σ per component, 1/m (..., n_gratings); 0 at invalid
        gratings. ``order`` is the interpolant's: 2 for one exact for straight lines (linear: c = 1/12 is exact
        on a quadratic profile, below), 4 for the cubic spline, whose error on a piece H is ∝ k⁽⁴⁾ H⁴ and its
        angle error ∝ k⁽⁴⁾ H⁵: the same sharing, with k⁽⁴⁾_n (4! times the fourth divided difference over five
        valid gratings) and H⁵ in place of k'' and H³ (for gratings h apart σ_n = c |Δ⁴k_n| / √2; next to a
        lost grating √(½(1 + 2¹⁰))/1.5 ≈ 15 times an inner grating's at the same k⁽⁴⁾). A second difference
        charges the spline for a smooth bending it follows exactly: against the spline's actual error on the
        twin's exact truth it over-states 24 times more on static shapes than in a sheath, the fourth
        difference 3.3 times (docs/math.md §8.4).

        For order 2:

        Between valid gratings a and b (a piece of length H) an interpolant that is exact for straight lines errs
        by e(s) = k''/2 (s − s_a)(s − s_b) for a quadratic profile, so the piece's angle is off by
        ∫e ds = −k'' H³/12. Each piece's angle error is shared half-and-half (in variance) by its two end
        gratings and represented by a white error of the grating, whose angle is σ_n w_n with w_n the half-sum of
        its pieces (the basis' integral): σ_n = c |k''_n| √(½ Σ H⁶) / w_n · (1/√2 per component), c = 1/12.
        k''_n is the second divided difference of the measured curvature over the valid neighbours (the end
        gratings take their neighbour's), so for gratings h apart σ_n = c |Δ²k_n| / √2, and next to a lost
        grating (a piece of 2h) about 3.8 times that."""
        k = np.asarray(curvature, dtype=np.float64)
        valid = np.broadcast_to(np.asarray(valid, bool), k.shape[:-1])
        flat_k = np.ascontiguousarray(k.reshape(-1, *k.shape[-2:]))
        flat_v = np.ascontiguousarray(valid.reshape(-1, valid.shape[-1]))
        out = np.empty(flat_v.shape)
        if order not in (2, 4):
            raise ValueError(f"interpolation_sigma: order must be 2 or 4, got {order}")
        _interpolation_kernel(flat_k, flat_v, np.ascontiguousarray(grating_s, dtype=np.float64), order, out)
        return self.interpolation * out.reshape(valid.shape)

    def twist_sensitivity(self, curvature: np.ndarray, grating_s: np.ndarray) -> np.ndarray | None:
        """The curvature error at each grating per 1σ of the unmeasured twist rate (:attr:`twist`), 1/m,
        (..., n_gratings, 2, 1), from the measured curvature (..., n_gratings, 2) at arc lengths ``grating_s``
        (n_gratings,) m from the base; None without the term.

        Integrating the material frame's rates (k_x, k_y, τ) is, exactly, integrating (Rψ k, 0) with Rψ the
        rotation by ψ(s) = ∫_0^s τ about the tangent (the frame without twist keeps the same tangent), so a
        reconstruction that takes τ = 0 errs by δk = (Rψ − I) k ≈ ψ J k, J k = (−k_y, k_x); for a constant
        twist rate τ, ψ = τ s and ∂k_n/∂τ = s_n J k_n (docs/math.md §8.1)."""
        if not self.twist:
            return None
        k = np.asarray(curvature, dtype=np.float64)
        jk = np.stack([-k[..., 1], k[..., 0]], axis=-1)
        return (self.twist * np.asarray(grating_s, dtype=np.float64)[:, None] * jk)[..., None]

    def replace(self, **changes) -> ModelError:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return {"curvature_1_per_m": self.curvature, "relative": self.relative, "base_angle_rad": self.base_angle,
                "interpolation": self.interpolation, "twist_rad_per_m": self.twist,
                "parameter_scale": self.parameter_scale, "source": self.source}


#: The interpolation constant c of the default pipeline (the spline, gratings 10 mm apart; the fourth-difference
#: form, :meth:`ModelError.interpolation_sigma`) in the twin, derived from the rod's exact truth on a sheath run
#: other than the one scored (``python -m scenarios._common.coverage``,
#: :func:`scenarios._common.coverage.interpolation_constant`: the actual angle error of the spline through the
#: true curvature at the gratings on every piece, against the model's variance at c = 1), where bends of 8 mm
#: radius sampled every 10 mm make the interpolation a large error (docs/math.md §8.4; 0.042 on sheath-motion's
#: scored run, 0.013 on the static library shapes).
TWIN_INTERPOLATION = 0.0435

#: The model error of the default pipeline in the twin: the interpolation term (:data:`TWIN_INTERPOLATION`) and
#: a white curvature error of 0.056 1/m per component and grating fitted on top of it in ``twin run
#: static-shapes`` (12 library shapes held by connect constraints, realistic optics, lab calibration; the two
#: folds' fits, 0.051 and 0.061 1/m, in RMS; docs/math.md §8.4). No twist term: a catheter twisted in a sheath
#: needs the sheath's (``ModelError.twist``; 0.82 rad/m in the twin's, scenarios/_common/coverage.py). A real
#: sensor's white part is larger — the AMIRo needle's held-out curvature error in its jig is 0.13 1/m
#: (docs/jig.md) — so fit your own (:func:`fit_model_error`).
TWIN_MODEL_ERROR = ModelError(curvature=0.056, interpolation=TWIN_INTERPOLATION,
                              source="twin: interpolation derived on a sheath run, white part on static-shapes "
                                     "(docs/math.md §8.4)")


def interpolation_order(interpolation: str) -> int:
    """The difference order of the interpolation term (:meth:`ModelError.interpolation_sigma`) for a
    reconstructor's ``interpolation``: the cubic spline's error follows the curvature's fourth derivative (4),
    an interpolant exact only for straight lines its second (2)."""
    return 4 if interpolation == "spline" else 2


def lateral_errors(shape: Shape, truth: np.ndarray) -> np.ndarray:
    """Truth minus reconstruction at each point, projected on the plane normal to the reconstruction's tangent.

    ``truth`` (..., n_points, 3) is the true centreline at the shape's arc lengths in the shape's base frame, m.
    Returns (..., n_points, 3), m."""
    d = np.asarray(truth, dtype=np.float64) - shape.positions
    t = shape.frames[..., :, 2]
    return d - np.sum(d * t, axis=-1, keepdims=True) * t


class Uncertainty:
    """Reconstruction with its uncertainty (module docstring), for a :class:`~twin.Reconstructor`.

    Parameters
    ----------
    reconstructor : Reconstructor
        The material method with a linear interpolant (``spline``, ``linear``, ``knn``) and no twist
        measurement; the uncertainty of the paper's Frenet pipeline (κ, θ_b) is not linear in the curvature.
    wavelength_noise : float, optional
        1σ white wavelength noise per peak, nm; default the reconstructor's ``wavelength_noise``.
    model_error : ModelError, optional
        Default :data:`TWIN_MODEL_ERROR`, the twin's fit; calibrate your own sensor's with
        :func:`fit_model_error`.
    parameters : bool
        Include the calibration's parameter covariance (Δθ, g with their 1σ; a jig's design matrices carry none).

    Calling it on wavelengths (..., n_gratings, n_cores), a Frame or frames returns the reconstructor's
    :class:`~twin.frames.Shape` with ``covariance`` (..., n_points, 3, 3) m² and ``curvature_covariance``
    (..., n_gratings, 2, 2) (1/m)²; :meth:`propagate` adds them to a shape already reconstructed.
    """

    def __init__(self, reconstructor: Reconstructor, *, wavelength_noise: float | None = None,
                 model_error: ModelError | None = None, parameters: bool = True):
        rec = reconstructor
        if not isinstance(rec, Reconstructor):
            raise TypeError(f"Uncertainty needs a Reconstructor, got {type(rec).__name__}")
        if rec.method != "material" or rec.interpolation == "pchip" or rec.twist:
            raise ValueError("Uncertainty: the linearised propagation covers the material method with a linear "
                             f"interpolant and no twist measurement; got method={rec.method!r}, "
                             f"interpolation={rec.interpolation!r}, twist={rec.twist}")
        sigma = rec.wavelength_noise if wavelength_noise is None else float(wavelength_noise)
        if not (np.isfinite(sigma) and sigma >= 0):
            raise ValueError(f"wavelength_noise must be a number of nm >= 0, got {wavelength_noise}")
        self.reconstructor = rec
        self.wavelength_noise = sigma
        self.model_error = TWIN_MODEL_ERROR if model_error is None else model_error
        self.interpolation_order = interpolation_order(rec.interpolation)
        fiber, cal = rec.fiber, rec.calibration
        self._design = cal.design_for(fiber)  # (n_g, n_c, 3)
        self._var_e = (sigma / cal.reference_for(fiber)) ** 2  # (n_g, n_c): variance of the optical strain
        p_full, cov_full = _masked_inverse(self._design, np.ones(self._design.shape[:2], bool), self._var_e)
        self._p_full = p_full[:, 1:]  # (n_g, 2, n_c): the curvature rows
        self._ck_full = np.ascontiguousarray(cov_full[:, 1:, 1:])
        self._dd, self._par_sd = self._parameter_terms(cal) if parameters else (None, np.zeros(0))
        # ∂k/∂p = −P (∂D/∂p) x, x = (c, k): Δθ and g move the bending columns only, so the common mode drops out
        self._sens_full = (None if self._dd is None else
                           -np.einsum("nic,pncj->nipj", self._p_full, self._dd))  # (n_g, 2, n_par, 2)
        self._bases: dict[bytes, np.ndarray] = {}
        self._quad = _quadrature(rec)
        self._full_basis = self._basis(np.ones(fiber.n_gratings, bool))[None]

    def with_model_error(self, model_error: ModelError) -> Uncertainty:
        """The same propagation with another model error (cheap: everything else is shared)."""
        other = copy.copy(self)
        other.model_error = model_error
        return other

    # ------------------------------------------------------------------ the call
    def __call__(self, wavelengths) -> Shape:
        w = _wavelengths(wavelengths)
        return self.propagate(self.reconstructor(w), w)

    def propagate(self, shape: Shape, wavelengths=None) -> Shape:
        """``shape``, the reconstructor's result, with ``covariance`` and ``curvature_covariance`` added.

        ``wavelengths`` (array, Frame or frames; the shape's input) tell which peaks were missing, which
        changes the inversion's noise at those gratings; without them every peak of a valid grating counts as
        present."""
        k = np.nan_to_num(shape.curvature)
        valid = shape.valid
        batch, n_g = k.shape[:-2], k.shape[-2]
        ck = self._ck_full
        sens_op = self._sens_full
        if wavelengths is not None:
            w = _wavelengths(wavelengths)
            missing = np.isnan(w)
            outside = self.reconstructor.peaks_outside(w)
            if missing.any() or outside.any():
                ck, sens_op = self._masked(~(missing | outside))
        ck = np.broadcast_to(ck, (*batch, n_g, 2, 2))
        me = self.model_error
        sig_m = me.sigma(k, self.reconstructor.fiber.grating_s, valid, self.interpolation_order)
        if me.curvature or me.relative or me.interpolation:
            ck = ck + (sig_m**2)[..., None, None] * np.eye(2)
        sens = None
        sd = self._par_sd * me.parameter_scale
        if sens_op is not None:
            sens = np.einsum("...nipj,...nj->...nip", sens_op, k)  # (..., n_g, 2, n_par)
        twist = me.twist_sensitivity(k, self.reconstructor.fiber.grating_s)  # per 1σ: (..., n_g, 2, 1)
        if twist is None:
            cov = self.position_covariance(shape, ck, sens, valid)
        else:  # one more error shared by the gratings; it moves the positions, not the measured curvature
            shared = twist if sens is None else np.concatenate([sens, twist], axis=-1)
            cov = self.position_covariance(shape, ck, shared, valid, shared_sd=np.append(sd, 1.0))
        if sens is not None:
            ck = ck + np.einsum("...nip,p,...njp->...nij", sens, sd**2, sens)
        ck = np.where(valid[..., None, None], ck, np.nan)
        return dataclasses.replace(shape, covariance=cov, curvature_covariance=ck)

    # ------------------------------------------------------------------ curvature
    def _parameter_terms(self, cal: Calibration):
        """∂D/∂p of the bending columns for p = (Δθ, g) at the calibration (n_par, n_g, n_c, 2) and the
        parameters' 1σ (n_par,), for those the calibration gives a 1σ of."""
        if cal.design is not None:
            return None, np.zeros(0)
        fiber = self.reconstructor.fiber
        cols, sd = [], []
        dth = nominal_delta_theta(fiber) if cal.delta_theta is None else cal.delta_theta
        g = nominal_gain(fiber) if cal.gain is None else cal.gain
        for name, value, std in (("delta_theta", dth, cal.delta_theta_std), ("gain", g, cal.gain_std)):
            if not std:
                continue
            # the design is linear in g and smooth in Δθ: central differences are exact to ~1e-10 relative
            step = 1e-6 * (1.0 if name == "delta_theta" else value)
            hi = cal.replace(**{name: value + step}).design_for(fiber)
            lo = cal.replace(**{name: value - step}).design_for(fiber)
            cols.append((hi - lo)[..., 1:] / (2 * step))
            sd.append(std)
        if not cols:
            return None, np.zeros(0)
        return np.stack(cols), np.array(sd)

    def _masked(self, present: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Noise covariance of k (..., n_g, 2, 2) and the parameter operator (..., n_g, 2, n_par, 2) per frame
        for peak masks ``present`` (..., n_g, n_c): the inversion without the missing peaks where some are."""
        batch = present.shape[:-2]
        ck = np.array(np.broadcast_to(self._ck_full, (*batch, *self._ck_full.shape)))
        full = present.all(axis=-1)
        idx = np.nonzero(~full)
        g = idx[-1]
        p, cov = _masked_inverse(self._design[g], present[idx], self._var_e[g])
        ck[idx] = cov[:, 1:, 1:]
        sens = None
        if self._sens_full is not None:
            sens = np.array(np.broadcast_to(self._sens_full, (*batch, *self._sens_full.shape)))
            sens[idx] = -np.einsum("mic,pmcj->mipj", p[:, 1:], self._dd[:, g])
        return ck, sens

    # ------------------------------------------------------------------ positions
    def _basis(self, nodes: np.ndarray) -> np.ndarray:
        """Interpolation basis (n_points, n_gratings) of the reconstructor for the valid gratings ``nodes``
        (zero columns for the others), cached per pattern."""
        key = nodes.tobytes()
        b = self._bases.get(key)
        if b is None:
            rec = self.reconstructor
            b = np.zeros((rec.s.size, nodes.size))
            if nodes.any():
                b[:, nodes] = curve.basis(rec.fiber.grating_s[nodes], rec.s, rec.interpolation)
            self._bases[key] = b
        return b

    def position_covariance(self, shape: Shape, curvature_covariance: np.ndarray, sensitivity: np.ndarray | None,
                            valid: np.ndarray, shared_sd: np.ndarray | None = None) -> np.ndarray:
        """Position covariance (..., n_points, 3, 3), m², from the per-grating curvature covariance of the
        errors independent between gratings (noise, model error; (..., n_g, 2, 2)) and the curvature's
        sensitivity to the shared errors (..., n_g, 2, n_par) or None, whose 1σ are ``shared_sd`` (n_par,)
        (default the calibration's parameters' scaled by ``parameter_scale``); invalid gratings (not
        interpolated through) carry nothing. Frames without a usable grating get NaN.

        Exact first-order sensitivities J_n(s) = ∫_0^s B_n(u) (R E)(u) × (p(s) − p(u)) du at the breakpoints of
        the interpolant (the gratings and the ends), by the 3-point rule on each piece (Simpson's where the
        middle point is central: the basis is a cubic and R, p vary over 1/κ ≥ 15 mm, so its error is
        ~1e-4 relative), then the covariance C = Σ J V Jᵀ and its derivative C' (from J_n' = Φ_n × t, Φ_n the
        integral of B_n R E) there, and cubic Hermite interpolation of C between them (docs/math.md §8.2); on the
        first piece, where C grows as s⁴ from the base (s⁶ along the tangent), t⁴ (a + b t + c t²) through C
        and C' at its end and C at its middle point instead."""
        n_p = shape.positions.shape[-2]
        pos = np.ascontiguousarray(shape.positions.reshape(-1, n_p, 3))
        frames = np.ascontiguousarray(shape.frames.reshape(-1, n_p, 3, 3))
        n_f, n_g = pos.shape[0], valid.shape[-1]
        vf = valid.reshape(n_f, n_g)
        v = np.ascontiguousarray(np.broadcast_to(curvature_covariance, (*valid.shape, 2, 2)).reshape(n_f, n_g, 2, 2))
        sens = (np.zeros((n_f, n_g, 2, 0)) if sensitivity is None
                else np.ascontiguousarray(sensitivity.reshape(n_f, n_g, 2, -1)))
        all_valid = bool(vf.all())
        if all_valid:
            bases, which = self._full_basis, np.zeros(n_f, np.int64)
        else:
            patterns, which = _patterns(vf)
            bases = np.stack([self._basis(p) for p in patterns])
            # an invalid grating is not interpolated through: its column of the basis is zero already
        out = np.empty((n_f, n_p, 3, 3))
        q = self._quad
        if shared_sd is None:
            shared_sd = self._par_sd * self.model_error.parameter_scale
        _covariance_kernel(pos, frames, bases, which, v, sens, np.asarray(shared_sd, dtype=np.float64),
                           self.model_error.base_angle**2,
                           q["points"], q["weights"], q["breaks"], q["interval"], q["t"], q["h"], q["first"],
                           q["half_points"], q["half_weights"], out)
        if not all_valid:
            out[~vf.any(axis=-1)] = np.nan
        return out.reshape((*shape.positions.shape[:-1], 3, 3))


def _patterns(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``valid`` (F, n) bool and each row's index among them (F,) int64: as np.unique over
    rows, but with a row packed into one integer where it fits (~20 times faster than sorting rows)."""
    if valid.shape[-1] >= 63:
        patterns, which = np.unique(valid, axis=0, return_inverse=True)
        return patterns, which.ravel().astype(np.int64)
    key = valid @ (np.int64(1) << np.arange(valid.shape[-1], dtype=np.int64))
    _, first, which = np.unique(key, return_index=True, return_inverse=True)
    return valid[first], which.ravel().astype(np.int64)


@njit(cache=True, nogil=True)
def _interpolation_kernel(k, valid, s, order, out):  # pragma: no cover (compiled)
    """|k⁽ᵖ⁾_n| √(½ Σ H^(2p+2)) / (w_n √2) per frame and grating (:meth:`ModelError.interpolation_sigma`
    without c), p = ``order`` (2 or 4): k (F, n, 2), valid (F, n), s (n,), out (F, n); k⁽ᵖ⁾_n is p! times the
    p-th divided difference over p + 1 consecutive valid gratings centred on n (shifted inwards at the ends, so
    the end gratings share their neighbours' stencil); 0 at invalid gratings, and with fewer than p + 1 valid."""
    n_f, n = valid.shape
    idx = np.empty(n, np.int64)
    tab = np.empty((order + 1, 2))
    fact = 1.0
    for q in range(2, order + 1):
        fact *= q
    for f in range(n_f):
        m = 0
        for i in range(n):
            out[f, i] = 0.0
            if valid[f, i]:
                idx[m] = i
                m += 1
        if m < order + 1:
            continue
        for j in range(m):
            start = min(max(j - order // 2, 0), m - order - 1)
            for q in range(order + 1):
                tab[q, 0] = k[f, idx[start + q], 0]
                tab[q, 1] = k[f, idx[start + q], 1]
            for lev in range(1, order + 1):  # divided differences in place
                for q in range(order, lev - 1, -1):
                    d = s[idx[start + q]] - s[idx[start + q - lev]]
                    tab[q, 0] = (tab[q, 0] - tab[q - 1, 0]) / d
                    tab[q, 1] = (tab[q, 1] - tab[q - 1, 1]) / d
            dk = fact * np.sqrt(tab[order, 0] ** 2 + tab[order, 1] ** 2)
            i = idx[j]
            hm = s[i] - s[idx[j - 1]] if j > 0 else 0.0
            hp = s[idx[j + 1]] - s[i] if j < m - 1 else 0.0
            e = 2 * order + 2
            out[f, i] = dk * np.sqrt(0.5 * (hm**e + hp**e)) / (0.5 * (hm + hp)) / np.sqrt(2.0)


def _quadrature(rec: Reconstructor) -> dict:
    """Where the propagation evaluates: breakpoints (output indices of 0, the gratings, the end; knn's jumps
    between gratings), per piece a 3-point rule (start, the output point nearest the middle, end) exact for
    quadratics, and per output point its piece, local coordinate t ∈ [0, 1] and the piece's length."""
    s = rec.s
    marks = [0.0, *rec.fiber.grating_s, s[-1]]
    if rec.interpolation == "knn":
        g = rec.fiber.grating_s
        marks += list(0.5 * (g[1:] + g[:-1]))
    breaks = np.unique(np.clip(np.searchsorted(s, np.clip(marks, s[0], s[-1]) - 1e-12), 0, s.size - 1))
    breaks = np.unique(np.concatenate([[0], breaks, [s.size - 1]]))
    n_int = breaks.size - 1
    points = np.empty((n_int, 3), np.int64)
    weights = np.zeros((n_int, 3))
    for k in range(n_int):  # once per reconstructor: a handful of pieces
        a, b = breaks[k], breaks[k + 1]
        m = int(np.clip(np.rint(0.5 * (a + b)), a, b))
        points[k] = (a, m, b)
        x0, xm, x1 = s[a], s[m], s[b]
        if m in (a, b):  # a one-step piece: the trapezoid rule
            weights[k] = (0.5 * (x1 - x0), 0.0, 0.5 * (x1 - x0))
        else:  # ∫ of the quadratic through the three points (Simpson's rule when m is central)
            vander = np.vander(np.array([x0, xm, x1]) - x0, 3, increasing=True).T
            moments = np.array([(x1 - x0), (x1 - x0) ** 2 / 2, (x1 - x0) ** 3 / 3])
            weights[k] = np.linalg.solve(vander, moments)
    # the integral from the base to the first piece's middle point, by the same kind of rule (for C there)
    half_points = np.array([0, int(np.rint(0.5 * points[0, 1])), points[0, 1]], np.int64)
    x0, xm, x1 = s[half_points]
    if half_points[1] in (half_points[0], half_points[2]):
        half_weights = np.array([0.5 * (x1 - x0), 0.0, 0.5 * (x1 - x0)])
    else:
        vander = np.vander(np.array([x0, xm, x1]) - x0, 3, increasing=True).T
        half_weights = np.linalg.solve(vander, [(x1 - x0), (x1 - x0) ** 2 / 2, (x1 - x0) ** 3 / 3])
    interval = np.clip(np.searchsorted(breaks, np.arange(s.size), side="right") - 1, 0, n_int - 1)
    h = s[breaks[1:]] - s[breaks[:-1]]
    t = (s - s[breaks[interval]]) / h[interval]
    # the first piece's C = t⁴ (a + b t + c t²) from C(1), h C'(1) and C at the middle point t_m (exact for s⁴,
    # s⁵, s⁶); a one-step piece has no middle point: then c = 0 and C(t_m) is not used
    tm = (s[points[0, 1]] - s[0]) / h[0]
    if 0.0 < tm < 1.0:
        first = np.linalg.inv(np.array([[1.0, 1.0, 1.0], [4.0, 5.0, 6.0], [tm**4, tm**5, tm**6]]))
    else:
        first = np.zeros((3, 3))
        first[:2, :2] = np.linalg.inv(np.array([[1.0, 1.0], [4.0, 5.0]]))
    return {"points": points, "weights": weights, "breaks": breaks.astype(np.int64), "interval": interval,
            "t": t, "h": h[interval], "first": first, "half_points": half_points, "half_weights": half_weights}


@njit(cache=True, nogil=True, fastmath=True)
def _add_point(pos, frames, basis, f, i, w, ia, ic):  # pragma: no cover (compiled)
    """Add w · B_n(s_i) (R E, (R E) × p)(s_i) to the running integrals of every grating n."""
    p0, p1, p2 = pos[f, i, 0], pos[f, i, 1], pos[f, i, 2]
    # δk_x turns about d2, δk_y about −d1 (u = (−k_y, k_x, 0) in the body frame)
    for c in range(2):
        if c == 0:
            a0, a1, a2 = frames[f, i, 0, 1], frames[f, i, 1, 1], frames[f, i, 2, 1]
        else:
            a0, a1, a2 = -frames[f, i, 0, 0], -frames[f, i, 1, 0], -frames[f, i, 2, 0]
        x0 = a1 * p2 - a2 * p1
        x1 = a2 * p0 - a0 * p2
        x2 = a0 * p1 - a1 * p0
        for n in range(basis.shape[1]):
            b = w * basis[i, n]
            ia[n, c, 0] += b * a0
            ia[n, c, 1] += b * a1
            ia[n, c, 2] += b * a2
            ic[n, c, 0] += b * x0
            ic[n, c, 1] += b * x1
            ic[n, c, 2] += b * x2


@njit(cache=True, nogil=True, fastmath=True)
def _moments(pos, frames, var, sens, par_sd, f, i, ia, ic, x, y, z, am, ad, ay, dy, c_out, d_out):
    """C and C' (3 × 3 each) at output point i from the running integrals (see :func:`_covariance_kernel`)."""
    n_g, n_par = var.shape[1], sens.shape[3]
    y[:] = 0.0
    z[:] = 0.0
    for n in range(n_g):
        v00, v01, v11 = var[f, n, 0, 0], var[f, n, 0, 1], var[f, n, 1, 1]
        for r in range(3):
            x[r, 0], x[r, 1] = ia[n, 0, r], ia[n, 1, r]
            x[r + 3, 0], x[r + 3, 1] = ic[n, 0, r], ic[n, 1, r]
        for r in range(6):
            xv0 = x[r, 0] * v00 + x[r, 1] * v01
            xv1 = x[r, 0] * v01 + x[r, 1] * v11
            for c in range(r, 6):
                y[r, c] += xv0 * x[c, 0] + xv1 * x[c, 1]
        for q in range(n_par):
            sa, sb = sens[f, n, 0, q] * par_sd[q], sens[f, n, 1, q] * par_sd[q]
            for r in range(6):
                z[r, q] += x[r, 0] * sa + x[r, 1] * sb
    for r in range(6):
        for c in range(r):
            y[r, c] = y[c, r]
    p0, p1, p2 = pos[f, i, 0], pos[f, i, 1], pos[f, i, 2]
    t0, t1, t2 = frames[f, i, 0, 2], frames[f, i, 1, 2], frames[f, i, 2, 2]
    # A = (−[p]×, −I), A' = (−[t]×, 0)
    am[:] = 0.0
    ad[:] = 0.0
    am[0, 1], am[0, 2], am[1, 0], am[1, 2], am[2, 0], am[2, 1] = p2, -p1, -p2, p0, p1, -p0
    ad[0, 1], ad[0, 2], ad[1, 0], ad[1, 2], ad[2, 0], ad[2, 1] = t2, -t1, -t2, t0, t1, -t0
    am[0, 3], am[1, 4], am[2, 5] = -1.0, -1.0, -1.0
    for r in range(3):
        for c in range(6):
            sa = 0.0
            sb = 0.0
            for e in range(6):
                sa += am[r, e] * y[e, c]
                sb += ad[r, e] * y[e, c]
            ay[r, c] = sa
            dy[r, c] = sb
    for r in range(3):
        for c in range(3):
            sa = 0.0
            sb = 0.0
            for e in range(6):
                sa += ay[r, e] * am[c, e]
                sb += dy[r, e] * am[c, e] + ay[r, e] * ad[c, e]
            c_out[r, c] = sa
            d_out[r, c] = sb
    for q in range(n_par):
        for r in range(3):
            gr = 0.0
            gdr = 0.0
            for e in range(6):
                gr += am[r, e] * z[e, q]
                gdr += ad[r, e] * z[e, q]
            for c in range(3):
                gc = 0.0
                gdc = 0.0
                for e in range(6):
                    gc += am[c, e] * z[e, q]
                    gdc += ad[c, e] * z[e, q]
                c_out[r, c] += gr * gc
                d_out[r, c] += gdr * gc + gr * gdc


@njit(cache=True, nogil=True, fastmath=True)
def _covariance_kernel(pos, frames, bases, which, var, sens, par_sd, base_var, points, weights, breaks, interval,
                       tt, hh, first, half_points, half_weights, out):  # pragma: no cover (compiled)
    """Position covariance of every frame (see :meth:`Uncertainty.position_covariance`): ``var`` (F, n_g, 2, 2)
    the independent curvature covariance, ``sens`` (F, n_g, 2, n_par) ∂k/∂p, ``par_sd`` the parameters' 1σ,
    ``base_var`` the variance of the base frame's angle about each axis (δp = δφ × p: σ²(|p|² I − p pᵀ)),
    ``first`` (3, 3) the inverse of the first piece's interpolation conditions, ``half_points``,
    ``half_weights`` the rule integrating from the base to the first piece's middle point (see
    :func:`_quadrature`).

    With X_n = (Φ_n, Ψ_n) (6 × 2: the integrals of B_n R E and B_n (R E) × p), J_n = A X_n with
    A = (−[p]×, −I) and J_n' = A' X_n with A' = (−[t]×, 0), so C = A Y Aᵀ and C' = A' Y Aᵀ + A Y A'ᵀ with
    Y = Σ_n X_n V_n X_nᵀ (6 × 6) — per grating only the 6 × 6 update — plus the same with the parameters'
    columns Z = Σ_n X_n S_n σ_p."""
    n_f, n_p = pos.shape[0], pos.shape[1]
    n_g, n_par = var.shape[1], sens.shape[3]
    n_b = breaks.shape[0]
    cb = np.zeros((n_b, 3, 3))  # C at the breakpoints
    db = np.zeros((n_b, 3, 3))  # and C'
    cm = np.zeros((3, 3))  # C at the first piece's middle point
    dm = np.zeros((3, 3))
    ia = np.zeros((n_g, 2, 3))
    ic = np.zeros((n_g, 2, 3))
    ih = np.zeros((n_g, 2, 3))  # the integrals to the first piece's middle point
    jh = np.zeros((n_g, 2, 3))
    x = np.zeros((6, 2))
    y = np.zeros((6, 6))
    z = np.zeros((6, n_par))
    am = np.zeros((3, 6))
    ad = np.zeros((3, 6))
    ay = np.zeros((3, 6))
    dy = np.zeros((3, 6))
    coef = np.zeros((3, 3, 3))  # the first piece's C = t⁴ (a + b t + c t²), a b c per element
    for f in range(n_f):
        basis = bases[which[f]]
        ia[:] = 0.0
        ic[:] = 0.0
        for k in range(n_b):
            if k > 0:
                _add_point(pos, frames, basis, f, points[k - 1, 1], weights[k - 1, 1], ia, ic)
                _add_point(pos, frames, basis, f, points[k - 1, 2], weights[k - 1, 2], ia, ic)
            if k == 1:
                ih[:] = 0.0
                jh[:] = 0.0
                for e in range(3):
                    _add_point(pos, frames, basis, f, half_points[e], half_weights[e], ih, jh)
                _moments(pos, frames, var, sens, par_sd, f, half_points[2], ih, jh, x, y, z, am, ad, ay, dy, cm, dm)
            _moments(pos, frames, var, sens, par_sd, f, breaks[k], ia, ic, x, y, z, am, ad, ay, dy, cb[k], db[k])
            if k == 1:
                # conditions C(1), h C'(1), C(t_m) on t⁴ (a + b t + c t²): solved with the precomputed inverse
                for r in range(3):
                    for c in range(3):
                        rhs0, rhs1, rhs2 = cb[1, r, c], hh[0] * db[1, r, c], cm[r, c]
                        for e in range(3):
                            coef[e, r, c] = first[e, 0] * rhs0 + first[e, 1] * rhs1 + first[e, 2] * rhs2
            if k < n_b - 1:
                _add_point(pos, frames, basis, f, points[k, 0], weights[k, 0], ia, ic)
        # cubic Hermite between breakpoints: C and C' at both ends of each piece
        for j in range(n_p):
            q = interval[j]
            t = tt[j]
            h = hh[j]
            t2_ = t * t
            t3 = t2_ * t
            t4 = t2_ * t2_
            h00 = 2 * t3 - 3 * t2_ + 1
            h10 = (t3 - 2 * t2_ + t) * h
            h01 = -2 * t3 + 3 * t2_
            h11 = (t3 - t2_) * h
            q0, q1, q2 = pos[f, j, 0], pos[f, j, 1], pos[f, j, 2]
            pp = q0 * q0 + q1 * q1 + q2 * q2
            for r in range(3):
                for c in range(r, 3):
                    if q == 0:
                        # the first piece: C ~ s⁴ from the base (an angle error times an arm, both ∝ s; s⁶ along
                        # the tangent), which a cubic cannot follow
                        v = t4 * (coef[0, r, c] + t * coef[1, r, c] + t2_ * coef[2, r, c])
                    else:
                        v = h00 * cb[q, r, c] + h10 * db[q, r, c] + h01 * cb[q + 1, r, c] + h11 * db[q + 1, r, c]
                    v += base_var * ((pp if r == c else 0.0) - pos[f, j, r] * pos[f, j, c])
                    out[f, j, r, c] = v
                    out[f, j, c, r] = v


def _masked_inverse(design: np.ndarray, present: np.ndarray, var_e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares inverse P = (Dᵀ M D)⁺ Dᵀ M (..., 3, n_c) for peak masks M (..., n_c) and the covariance
    P diag(var_e) Pᵀ (..., 3, 3) of x = (c, k_x, k_y); equal weights, as :class:`~twin.strain.CurvatureSolver`."""
    dm = design * present[..., None]
    dt = np.swapaxes(dm, -1, -2)
    p = np.linalg.pinv(dt @ dm) @ dt
    return p, (p * var_e[..., None, :]) @ np.swapaxes(p, -1, -2)


def _wavelengths(data) -> np.ndarray:
    """Wavelengths (..., n_gratings, n_cores) nm from an array, a Frame or a sequence of Frames."""
    from twin.frames import Frame

    if isinstance(data, Frame):
        return data.wavelengths
    if isinstance(data, list | tuple) and data and isinstance(data[0], Frame):
        return Frame.stack(data).wavelengths
    return np.asarray(data, dtype=np.float64)


def truth_in_base(truth_s: np.ndarray, positions: np.ndarray, base_frames: np.ndarray, base_positions: np.ndarray,
                  s: np.ndarray) -> np.ndarray:
    """The true centreline (..., m, 3) world, m, at arc lengths ``truth_s`` (m,), in the base frame (R
    (..., 3, 3), p (..., 3)) at arc lengths ``s``: (..., len(s), 3), by a cubic spline in arc length (a linear
    one would cut a simulator's ~2 mm vertices' corners by h²κ/8, up to 0.03 mm). No registration: the tube is
    checked as it is used, from the base frame."""
    from scipy.interpolate import CubicSpline

    local = np.einsum("...mi,...ij->...mj", positions - base_positions[..., None, :], base_frames)
    return CubicSpline(truth_s, local, axis=-2)(s)


def inside(shape: Shape, truth: np.ndarray, level: float = 0.95) -> np.ndarray:
    """Whether each true point lies in the shape's level-% tube, bool (..., n_points).

    ``truth`` (..., n_points, 3): the true centreline at the shape's arc lengths in the shape's base frame, m.
    A point is inside when its lateral error (:func:`lateral_errors`) is within :meth:`Shape.confidence`."""
    d = np.linalg.norm(lateral_errors(shape, truth), axis=-1)
    return d <= shape.confidence(level)


def coverage(shape: Shape, truth: np.ndarray, level: float = 0.95, where: np.ndarray | None = None) -> float:
    """Fraction of the true points inside the level-% tube (:func:`inside`), over the points with s > 0 (the
    base point is exact by construction) whose reconstruction and truth are finite; ``where`` (n_points,) bool
    restricts the points further. NaN when none is left."""
    ok = inside(shape, truth, level)
    use = np.isfinite(shape.positions).all(axis=-1) & np.isfinite(truth).all(axis=-1) & (shape.s > 0)
    if where is not None:
        use = use & where
    return float(ok[use].mean()) if use.any() else float("nan")


def fit_model_error(uncertainty: Uncertainty, shape: Shape, wavelengths, truth: np.ndarray, *,
                    level: float = 0.95, template: ModelError | None = None, fixed: ModelError | None = None,
                    source: str = "") -> ModelError:
    """The model error that makes the level-% tube hold ``level`` of the true points of shapes of known truth
    (never the ones to be scored).

    One number is fitted, by bisection on the pooled coverage of all points with s > 0 (:func:`coverage`), which
    rises monotonically with it: the scale of ``template`` (default a white curvature error of 1 1/m per
    component); or, when noise and the calibration's parameters alone already hold more than ``level``, the
    ``parameter_scale`` (< 1) that brings the coverage down to it. A single number is what a handful of shapes
    can pin down: their errors are mostly systematic per shape, so the points of one shape are not independent
    draws.

    Parameters
    ----------
    uncertainty : Uncertainty
        With the calibration to be used (its noise term stays as it is).
    shape : Shape
        The reconstructions of ``wavelengths`` (a batch).
    wavelengths : ndarray (..., n_gratings, n_cores)
    truth : ndarray (..., n_points, 3)
        The true centreline at the shape's arc lengths in its base frame, m.
    level : float
    template : ModelError, optional
        The model error's form; its ``curvature``, ``relative``, ``base_angle``, ``interpolation`` and ``twist``
        are scaled together.
    fixed : ModelError, optional
        Terms held while the template's are fitted (those the template sets replace them): e.g. the
        interpolation constant fitted elsewhere, with the white part fitted here; its ``parameter_scale`` is
        kept unless the parameters alone over-cover.
    source : str
        A note for the result.
    """
    t = template or ModelError(curvature=1.0)
    base = fixed or ModelError()
    names = [n for n in ("curvature", "relative", "base_angle", "interpolation", "twist") if getattr(t, n)]

    def scaled(k: float, p: float | None = None) -> ModelError:
        return base.replace(**{n: k * getattr(t, n) for n in names}, source=source,
                            parameter_scale=base.parameter_scale if p is None else p)

    def cover(me: ModelError) -> float:
        return coverage(uncertainty.with_model_error(me).propagate(shape, wavelengths), truth, level)

    def bisect(make, lo: float, hi: float, rising: bool) -> float:
        for _ in range(40):  # to 1e-12 of the bracket
            mid = 0.5 * (lo + hi)
            low = cover(make(mid)) < level
            lo, hi = (mid, hi) if low == rising else (lo, mid)
        return hi if rising else lo

    if cover(scaled(0.0)) >= level:  # the parameters (and the fixed terms) over-cover: trust the stated 1σ less
        if cover(scaled(0.0, 0.0)) >= level:
            return scaled(0.0, 0.0)
        return scaled(0.0, bisect(lambda p: scaled(0.0, p), 0.0, 1.0, rising=True))
    hi = 1.0
    while cover(scaled(hi)) < level:  # the tube widens without bound as the scale grows, so this ends
        hi *= 4.0
        if hi > 1e6:
            raise ValueError("fit_model_error: no model error reaches the coverage (truth not in the base frame?)")
    return scaled(bisect(scaled, 0.0, hi, rising=True))
