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
import math
from dataclasses import dataclass

import numpy as np

from twin import _propagate, curve
from twin._propagate import interpolation_kernel as _interpolation_kernel
from twin._recycle import Recycler
from twin.calibration import Calibration, nominal_delta_theta, nominal_gain
from twin.frames import Shape
from twin.reconstruct import Reconstructor

__all__ = ["TWIN_INTERPOLATION", "TWIN_MODEL_ERROR", "TWIN_SHEATH_TWIST", "ModelError", "Uncertainty", "coverage",
           "fit_model_error", "inside", "interpolation_order", "lateral_errors", "truth_in_base"]


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
        much; it moves every point by δφ × p. 0 in the twin, whose base pose is exact (its truth's
        frame at s = 0 is the rod's smooth centreline's, models.rod_state.RodState.smooth_at).
    twist : float
        1σ of the catheter's twist rate that the fibre does not measure, rad/m, taken as constant along the
        fibre: a fibre without a twist measurement reconstructs as if the material frame did not turn about the
        tangent, which is the true curvature rotated back by the twist angle ψ(s) = τ s, an error
        δk(s) = ψ(s) J k(s) (:meth:`twist_sensitivity`). One error shared by every grating, so it keeps its
        correlation along the fibre, and it grows with s and |k|: in a sheath, where friction twists the
        catheter, the distal tube's largest term.
    parameter_scale : float
        Factor on the calibration's stated 1σ of Δθ and g (1: as identified). :func:`fit_model_error` lowers it
        only when noise and the parameters alone already hold more than the level on the fitting shapes: the
        stated 1σ is the spread of identifications over sets of shapes (its jackknife), while one calibration's
        own error can be much smaller (the twin's lab calibration: 0.18 mrad of Δθ against 8.4 stated, where
        six-shape sets of the library err by 11.5 mrad RMS; docs/math.md §8.4).
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
#: scored run with the sheath's former 4 mm rails, 0.013 on the static library shapes).
TWIN_INTERPOLATION = 0.0460

#: The model error of the default pipeline in the twin: the interpolation term (:data:`TWIN_INTERPOLATION`), with
#: the calibration's stated 1σ of Δθ and g × 0.291, fitted on top of it for the lab calibration on the library's
#: six shapes it was not identified on, held by connect constraints (scenarios/_common/coverage.py
#: ``lab_model_error``; realistic optics; no white part needed; docs/math.md §8.4). No base angle: the twin's base
#: pose is exact (the truth's pose at s = 0 is the rod's smooth centreline's, models/rod_state.py); a real clamp or
#: tracker sits off the fibre's tangent by its own tolerance, which ``base_angle`` carries. No twist term: the
#: fibre cannot measure the twist, and its size belongs to the setting — none under connect constraints,
#: 0.08 rad/m in the lab's grooves and tubes, :data:`TWIN_SHEATH_TWIST` in the twin's sheath — so a catheter in
#: a sheath needs ``TWIN_MODEL_ERROR.replace(twist=TWIN_SHEATH_TWIST)``. A real sensor's errors are larger — the
#: AMIRo needle's held-out curvature error in its jig is 0.13 1/m (docs/jig.md) — so fit your own
#: (:func:`fit_model_error`).
TWIN_MODEL_ERROR = ModelError(interpolation=TWIN_INTERPOLATION, parameter_scale=0.291,
                              source="twin: interpolation derived on a sheath run, parameter scale for the lab "
                                     "calibration on shapes it was not identified on (docs/math.md §8.4)")

#: 1σ of the constant twist rate the twin's catheter takes in its sheath, rad/m (the fibre does not measure it):
#: the RMS over frames of the least-squares τ in ψ(s) = τ s fitted to the rod's true twist angle on a sheath run
#: other than the one scored (scenarios/_common/coverage.py ``sheath_terms``: hub from 40 mm, 150 mm in,
#: friction 0.2, seed 1, no return; 344 frames; sheath-motion's scored run, pushed further with more friction,
#: had 1.45 rad/m before the sheath's straight runs became one capsule). Not in :data:`TWIN_MODEL_ERROR`: on
#: the static library shapes it would widen the tube from 0.045 to 0.95 mm mean 1σ, 21 times as wide as needed
#: (99.97 % inside, with c = 0.0435; docs/math.md §8.4).
TWIN_SHEATH_TWIST = 0.818


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
        self._dd, self._par_sd = self._parameter_terms(cal) if parameters else (None, np.zeros(0))
        # a large batch's covariances on the memory of results let go, as the reconstructor's positions (their
        # fresh pages cost about a seventh of the propagation of 5000 frames)
        self._outputs = Recycler()
        #: why this tube is narrower than its errors are likely to be, or None: the twin's default model error is
        #: a multiple of the calibration's stated 1σ of Δθ and g, so without them it carries noise and
        #: interpolation only
        self.caveat: str | None = None
        if model_error is None and self.model_error.parameter_scale and not self._par_sd.size:
            self.caveat = ("the calibration states no 1σ of delta_theta or gain, which the default model error "
                           "scales: the tube carries the wavelength noise and the interpolation only (fit the "
                           "sensor's own: twin.uncertainty.fit_model_error)")
        self._ck_table, self._sens_table = self._peak_tables()
        self._bases: dict[bytes, np.ndarray] = {}
        self._quad = _quadrature(rec)
        self._full_weights = self._weights(np.ones(fiber.n_gratings, bool))[None]
        self._const_for: tuple | None = None
        self._no_wavelengths = np.empty((0, fiber.n_gratings, fiber.n_cores))

    def with_model_error(self, model_error: ModelError) -> Uncertainty:
        """The same propagation with another model error (cheap: everything else is shared)."""
        other = copy.copy(self)
        other.model_error = model_error
        other.caveat = None  # a model error the caller chose is the caller's statement
        return other

    def with_twist(self, twist: float) -> Uncertainty:
        """The same propagation with the model error's twist term (:attr:`ModelError.twist`) set to ``twist``,
        the 1σ of the catheter's unmeasured twist rate, rad/m (a finite number >= 0; 0: no term).

        Only the twist is the caller's statement here; the rest of the model error stays what it was, and so
        does :attr:`caveat` (which is about that rest)."""
        other = self.with_model_error(self.model_error.replace(twist=twist))
        other.caveat = self.caveat
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
        k = shape.curvature
        valid = shape.valid
        batch, n_g = k.shape[:-2], k.shape[-2]
        n_p = shape.positions.shape[-2]
        n_f = math.prod(batch)
        if shape.frames is None:
            raise ValueError("Uncertainty.propagate needs the material frames: reconstruct with frames=True")
        if wavelengths is None:
            w = self._no_wavelengths
        else:
            w = _wavelengths(wavelengths)
            n_c = self._no_wavelengths.shape[-1]
            if w.size != n_f * n_g * n_c:  # the compiled pass reads (n_f, n_g, n_c) without checking
                raise ValueError(f"Uncertainty.propagate: wavelengths of shape {w.shape} do not match the shape's "
                                 f"batch {batch} × ({n_g} gratings, {n_c} cores)")
            w = w.reshape(n_f, n_g, n_c)
        vf = np.ascontiguousarray(valid.reshape(n_f, n_g))
        args = (np.ascontiguousarray(shape.positions.reshape(n_f, n_p, 3)),
                np.ascontiguousarray(shape.frames.reshape(n_f, n_p, 3, 3)),
                np.ascontiguousarray(k.reshape(n_f, n_g, 2)), vf, np.ascontiguousarray(w, dtype=np.float64))
        cov = self._outputs.empty((n_f, n_p, 3, 3))
        ck = self._outputs.empty((n_f, n_g, 2, 2))
        const = self._const()
        # intact frames with the intact pattern; those that lost a grating, if any, again with their patterns
        if _propagate.propagate(const, *args, self._full_weights, _NO_FRAMES, cov, ck):
            lost = np.flatnonzero(~vf.all(axis=1))
            bases, which = self._patterns(vf[lost])
            sub = [a[lost] if a.shape[0] else a for a in args]
            sub_cov, sub_ck = np.empty((lost.size, n_p, 3, 3)), np.empty((lost.size, n_g, 2, 2))
            _propagate.propagate(const, *sub, bases, which, sub_cov, sub_ck)
            cov[lost] = sub_cov
        return shape._with_uncertainty(cov.reshape(*batch, n_p, 3, 3), ck.reshape(*batch, n_g, 2, 2))

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

    def _peak_tables(self) -> tuple[np.ndarray, np.ndarray]:
        """The inversion's curvature covariance (n_g, 2^n_c, 2, 2) and the parameter operator k ↦ ∂k/∂p
        (n_g, 2^n_c, 2, n_par, 2) for every pattern of present peaks (bit c: core c present), so that a frame's
        missing peaks are a look-up in the compiled pass: the inversion without them (:func:`_masked_inverse`);
        ∂k/∂p = −P (∂D/∂p) x, where Δθ and g move the bending columns only, so the common mode drops out."""
        n_g, n_c = self._design.shape[:2]
        if n_c > 12:
            raise ValueError(f"Uncertainty: at most 12 cores are supported, got {n_c}")
        codes = np.arange(2**n_c)
        present = ((codes[:, None] >> np.arange(n_c)) & 1).astype(bool)  # (2^n_c, n_c)
        p, cov = _masked_inverse(self._design[:, None], present[None], self._var_e[:, None])
        ck = np.ascontiguousarray(cov[..., 1:, 1:])
        n_par = self._par_sd.size
        if self._dd is None:
            return ck, np.zeros((n_g, codes.size, 2, n_par, 2))
        return ck, np.ascontiguousarray(-np.einsum("nkic,pncj->nkipj", p[..., 1:, :], self._dd))

    def _const(self) -> np.ndarray:
        """The constants of the compiled pass (:func:`twin._propagate.pack`) for the current model error."""
        me = self.model_error
        key = (me.curvature, me.relative, me.interpolation, me.base_angle, me.parameter_scale, me.twist)
        if self._const_for != key:
            rec = self.reconstructor
            self._packed = _propagate.pack(
                self._quad, rec.fiber.grating_s, rec.calibration.reference_for(rec.fiber), rec.peak_window,
                self._ck_table, self._sens_table, self._par_sd * me.parameter_scale, me.curvature, me.relative,
                me.interpolation, me.base_angle**2, me.twist, self.interpolation_order)
            self._const_for = key
        return self._packed

    # ------------------------------------------------------------------ positions
    def _weights(self, nodes: np.ndarray) -> np.ndarray:
        """The quadrature's weights times the interpolation basis for the valid gratings ``nodes`` (zero columns
        for the others; :func:`twin._propagate.pattern_weights`), cached per pattern."""
        key = nodes.tobytes()
        b = self._bases.get(key)
        if b is None:
            rec = self.reconstructor
            basis = np.zeros((rec.s.size, nodes.size))
            if nodes.any():
                basis[:, nodes] = curve.basis(rec.fiber.grating_s[nodes], rec.s, rec.interpolation)
            b = self._bases[key] = _propagate.pattern_weights(self._quad, basis)
        return b

    def _patterns(self, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The weights of each pattern of valid gratings in ``valid`` (F, n_g) and each frame's pattern (F,)."""
        if valid.all():
            return self._full_weights, np.zeros(valid.shape[0], np.int64)
        patterns, which = _patterns(valid)
        return np.stack([self._weights(p) for p in patterns]), which

    def position_covariance(self, shape: Shape, curvature_covariance: np.ndarray, sensitivity: np.ndarray | None,
                            valid: np.ndarray, shared_sd: np.ndarray | None = None) -> np.ndarray:
        """Position covariance (..., n_points, 3, 3), m², from the per-grating curvature covariance of the
        errors independent between gratings (noise, model error; (..., n_g, 2, 2)) and the curvature's
        sensitivity to the shared errors (..., n_g, 2, n_par) or None, whose 1σ are ``shared_sd`` (n_par,)
        (default the calibration's parameters' scaled by ``parameter_scale``); invalid gratings (not
        interpolated through) carry nothing. Frames without a usable grating get NaN. (:meth:`propagate` does
        the same in one compiled pass with the covariance it forms itself.)

        Exact first-order sensitivities J_n(s) = ∫_0^s B_n(u) (R E)(u) × (p(s) − p(u)) du at the breakpoints of
        the interpolant (the gratings and the ends), by the 3-point rule on each piece (Simpson's where the
        middle point is central: the basis is a cubic and R, p vary over 1/κ ≥ 15 mm, so its error is
        ~1e-4 relative), then the covariance C = Σ J V Jᵀ and its derivative C' (from J_n' = Φ_n × t, Φ_n the
        integral of B_n R E) there, and cubic Hermite interpolation of C between them (docs/math.md §8.2); on the
        first piece, where C grows as s⁴ from the base (s⁶ along the tangent), t⁴ (a + b t + c t²) through C
        and C' at its end and C at its middle point instead."""
        n_p = shape.positions.shape[-2]
        n_f, n_g = int(np.prod(valid.shape[:-1], dtype=np.int64)), valid.shape[-1]
        vf = np.ascontiguousarray(valid.reshape(n_f, n_g))
        v = np.ascontiguousarray(np.broadcast_to(curvature_covariance, (*valid.shape, 2, 2)).reshape(n_f, n_g, 2, 2),
                                 dtype=np.float64)
        sd = self._par_sd * self.model_error.parameter_scale if shared_sd is None else np.asarray(shared_sd, float)
        sp = (np.zeros((n_f, n_g, 2, 0)) if sensitivity is None
              else np.ascontiguousarray(sensitivity.reshape(n_f, n_g, 2, -1) * sd, dtype=np.float64))
        bases, which = self._patterns(vf)
        out = np.empty((n_f, n_p, 3, 3))
        _propagate.covariance(self._const(), np.ascontiguousarray(shape.positions.reshape(n_f, n_p, 3)),
                              np.ascontiguousarray(shape.frames.reshape(n_f, n_p, 3, 3)), v, sp, vf, bases, which,
                              out)
        return out.reshape((*shape.positions.shape[:-1], 3, 3))


_NO_FRAMES = np.zeros(0, np.int64)


def _patterns(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``valid`` (F, n) bool and each row's index among them (F,) int64: as np.unique over
    rows, but with a row packed into one integer where it fits (~20 times faster than sorting rows)."""
    if valid.shape[-1] >= 63:
        patterns, which = np.unique(valid, axis=0, return_inverse=True)
        return patterns, which.ravel().astype(np.int64)
    key = valid @ (np.int64(1) << np.arange(valid.shape[-1], dtype=np.int64))
    _, first, which = np.unique(key, return_index=True, return_inverse=True)
    return valid[first], which.ravel().astype(np.int64)


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


def _masked_inverse(design: np.ndarray, present: np.ndarray, var_e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares inverse P = (Dᵀ M D)⁺ Dᵀ M (..., 3, n_c) for peak masks M (..., n_c) and the covariance
    P diag(var_e) Pᵀ (..., 3, 3) of x = (c, k_x, k_y); equal weights, as :class:`~twin.strain.CurvatureSolver`."""
    dm = design * present[..., None]
    dt = np.swapaxes(dm, -1, -2)
    p = np.linalg.pinv(dt @ dm) @ dt
    return p, (p * var_e[..., None, :]) @ np.swapaxes(p, -1, -2)


def _wavelengths(data) -> np.ndarray:
    """Wavelengths (..., n_gratings, n_cores) nm from an array, a Frame or a sequence of Frames."""
    if isinstance(data, np.ndarray):
        return data if data.dtype == np.float64 else data.astype(np.float64)
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
