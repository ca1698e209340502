"""The Reconstructor: peak wavelengths → curvature at the gratings → 3D centreline, batch-first.

Everything that depends only on the sensor and the options (pseudo-inverses, interpolation matrices, sample
points) is computed once in the constructor; a call does a handful of array operations and one compiled chain.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import numpy as np

from twin import _fused, curve
from twin._recycle import Recycler
from twin.calibration import Calibration
from twin.fiber import FiberModel
from twin.frames import Frame, Shape
from twin.strain import CurvatureSolver, outside_window

_QUADRATURE = {1: [1.0], 2: [0.5, 0.5], 3: [1 / 6, 4 / 6, 1 / 6]}  # weights of the m samples of one step

__all__ = ["METHODS", "PAPER_KAPPA_MIN", "Reconstructor"]

METHODS = ("material", "paper")
#: The paper pipeline's default κ_min, 1/m: 30 × the noise of κ (≈ 0.03 1/m per component at 1 pm of wavelength
#: noise on this fibre) and far below the bends a catheter is steered through (tens of 1/m).
PAPER_KAPPA_MIN = 1.0
#: default physical window of a peak, |optical strain| (see :class:`Reconstructor`)
PEAK_WINDOW = 0.03


class Reconstructor:
    """Reconstructs fibre shapes from peak wavelengths.

    Parameters
    ----------
    fiber : FiberModel
    calibration : Calibration, optional
        Reference wavelengths, intrinsic twist, identified parameters or jig design matrices.
    method : {"material", "paper"}
        ``material`` (default): least-squares curvature vectors, interpolated and integrated as a material
        (Bishop) frame — no κ = |k|, no angle unwrapping (docs/math.md §3.5). ``paper``: Al-Ahmad et al.'s Frenet
        pipeline: κ = |k|, θ_b = atan2, torsion from θ_b (docs/math.md §3.2).
    interpolation : {"spline", "pchip", "knn", "linear"}
        How node values are interpolated along the fibre (not-a-knot cubic spline, PCHIP, nearest node, linear).
    integrator : {"magnus4", "hem-mid", "hem-left", "rk4"}, optional
        Default ``magnus4`` for the material method and ``hem-left`` (the paper's literal HEM, κ and τ taken at
        the start of each step) for the paper method.
    torsion : {"forward", "centred", "theta-spline"}
        Paper method only (an error with the material method): the paper's forward difference placed at node n
        (default), the same difference placed at the interval midpoints, or the derivative of a spline through
        the unwrapped θ_b.
    step : float
        Largest integration step and output point spacing, m (the actual step divides the length evenly).
    inversion : {"lstsq", "paper"}, optional
        Curvature-vector inversion; default ``lstsq`` for the material method and the paper's eqs. 5–7 for
        the paper method.
    kappa_min : float, optional
        Paper method only: where κ < ``kappa_min`` (1/m) the bend-plane angle θ_b is held at its last reliable
        value, leading gratings taking the first reliable one (:func:`twin.curve.hold_bend_angle`); torsion is
        then zero there. Default 1 1/m (30 × the noise of κ at 1 pm). Our addition: the paper does not say
        what it does at near-zero curvature, and its literal transcription (``kappa_min=0``) rolls the frame by
        up to π wherever part of the length is nearly straight (docs/math.md §3.6).
    twist : bool, optional
        Measure the mechanical twist rate at each grating and carry the material frame with it (a spun fibre,
        docs/spun-fibers.md). Default: when the fibre is spun (``spin_rate`` ≠ 0) and the method is
        ``material``; False reconstructs a spun fibre with the twist ignored.
    wavelength_noise : float
        1σ wavelength noise per peak assumed by the twist inversion's weights and reported uncertainties, nm.
    peak_window : float or None
        Physical window around the reference wavelengths: a peak whose optical strain |Δλ/λ0| exceeds it is
        treated as missing (see :meth:`peaks_outside`). Default :data:`PEAK_WINDOW` = 0.03, i.e. ±45 nm at
        1510 nm: beyond the breaking strain of silica fibre (a few %) and ten times the largest bending
        strain of a catheter fibre (g·κ ≈ 3e-3 at a 1 cm radius); only a corrupted or mis-assigned value lands
        there. None: no window.
    fused : bool, optional
        Run the fused compiled path (see below). Default: whenever the options allow it; False forces the
        general path (the reference the fused path is tested against); True where it cannot run is an error.

    Calling the reconstructor on wavelengths of shape (..., n_gratings, n_cores) (nm; NaN for a missing peak),
    a :class:`~twin.frames.Frame` or a sequence of Frames returns a :class:`~twin.frames.Shape`. A grating
    whose curvature cannot be solved is dropped from the interpolation and marked in ``Shape.valid``; a frame
    with no usable grating has NaN positions. ``frames=False`` leaves the material frames out of the Shape
    (``Shape.frames`` None), saving their memory (72 bytes a point) when only positions are wanted.

    The common case — the material method without twist, a linear interpolant (spline, linear, knn), any
    integrator, either inversion — runs as one compiled call per batch (:mod:`twin._fused`, docs/math.md §3.8);
    the attribute ``fused`` tells whether this reconstructor does. The paper's Frenet pipeline, PCHIP and the
    twist of a spun fibre take the general path of numpy steps. A large batch's positions and frames (≥ 4 MiB)
    may reuse the memory of an earlier result that nothing refers to any more (:mod:`twin._recycle`); results
    alive at the same time never share memory.

    Examples
    --------
    >>> rec = Reconstructor(FiberModel.paper())
    >>> shape = rec(wavelengths)            # (n_gratings, n_cores) or (n_frames, n_gratings, n_cores)
    >>> shape.positions.shape               # (n_frames, 171, 3) for 170 mm at 1 mm
    """

    def __init__(
        self,
        fiber: FiberModel,
        calibration: Calibration | None = None,
        method: str = "material",
        interpolation: str = "spline",
        integrator: str | None = None,
        torsion: str | None = None,
        step: float = 1e-3,
        inversion: str | None = None,
        kappa_min: float | None = None,
        twist: bool | None = None,
        wavelength_noise: float = 1e-3,
        peak_window: float | None = PEAK_WINDOW,
        fused: bool | None = None,
    ):
        if not isinstance(fiber, FiberModel):
            raise TypeError(f"fiber must be a FiberModel, got {type(fiber).__name__}")
        if method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}; got {method!r}")
        if interpolation not in curve.INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {', '.join(curve.INTERPOLATIONS)}; got {interpolation!r}")
        integrator = integrator or ("magnus4" if method == "material" else "hem-left")
        if integrator not in curve.INTEGRATORS:
            raise ValueError(f"integrator must be one of {', '.join(curve.INTEGRATORS)}; got {integrator!r}")
        if torsion is not None and method == "material":
            raise ValueError("torsion applies to method='paper' only (the material frame needs no torsion)")
        torsion = torsion or "forward"
        if torsion not in curve.TORSIONS:
            raise ValueError(f"torsion must be one of {', '.join(curve.TORSIONS)}; got {torsion!r}")
        inversion = inversion or ("lstsq" if method == "material" else "paper")
        if kappa_min is not None and method != "paper":
            raise ValueError("kappa_min applies to the paper method only (the material frame needs no bend angle)")
        kappa_min = PAPER_KAPPA_MIN if kappa_min is None else float(kappa_min)
        if not (np.isfinite(kappa_min) and kappa_min >= 0):
            raise ValueError(f"kappa_min must be a curvature >= 0 in 1/m, got {kappa_min}")
        self.kappa_min = kappa_min if method == "paper" else 0.0
        if twist is None:
            twist = bool(fiber.spin_rate) and method == "material"
        if twist and not fiber.spin_rate:
            raise ValueError("twist=True needs a spun fibre (FiberModel.spin_rate ≠ 0); straight cores cannot see it")
        if twist and method != "material":
            raise ValueError("twist is measured with method='material' only (the Frenet pipeline has no twist)")
        if not (np.isfinite(wavelength_noise) and wavelength_noise > 0):
            raise ValueError(f"wavelength_noise must be a positive number of nm, got {wavelength_noise}")
        self.twist = bool(twist)
        self.wavelength_noise = float(wavelength_noise)
        if peak_window is not None and not (np.isfinite(peak_window) and peak_window > 0):
            raise ValueError(f"peak_window must be a positive optical strain (|Δλ/λ0|) or None; got {peak_window}")
        self.peak_window = None if peak_window is None else float(peak_window)
        self.fiber = fiber
        self.calibration = calibration or Calibration()
        self.method = method
        self.interpolation = interpolation
        self.integrator = integrator
        self.torsion = torsion
        self.inversion = inversion

        self._set_calibration(self.calibration)
        self.s, self.h = curve.step_grid(0.0, fiber.sensed_length, step)
        self._samples = curve.sample_points(self.s, self.h, integrator)  # (n_steps, m)
        self._m = self._samples.shape[1]
        self._s_nodes = fiber.grating_s
        self._cache: dict[bytes, dict] = {}
        possible = method == "material" and not self.twist and interpolation != "pchip"
        if fused and not possible:
            raise ValueError("fused=True needs method='material', a linear interpolant (not pchip) and no twist "
                             f"measurement; got method={method!r}, interpolation={interpolation!r}, twist={self.twist}")
        #: whether calls run the fused compiled path (class docstring)
        self.fused = possible if fused is None else bool(fused)
        self._no_frames = np.empty((1, 1, 3, 3))  # the kernels' frames argument when frames are not wanted
        self._outputs = Recycler()  # a large batch's positions and frames on the memory of results let go
        self._full = self._prepare(np.ones(fiber.n_gratings, bool))
        self.s.setflags(write=False)  # shared by every Shape
        self._dims = (fiber.n_gratings, fiber.n_cores, self.s.size)

    def __repr__(self) -> str:
        return (
            f"Reconstructor(method={self.method!r}, interpolation={self.interpolation!r}, "
            f"integrator={self.integrator!r}, torsion={self.torsion!r}, step={self.h:.3g} m, "
            f"inversion={self.inversion!r}, "
            + (f"kappa_min={self.kappa_min:g} 1/m, " if self.method == "paper" else "")
            + f"{self.fiber.n_gratings} gratings × {self.fiber.n_cores} cores)"
        )

    @classmethod
    def paper(cls, fiber: FiberModel, calibration: Calibration | None = None, **options) -> Reconstructor:
        """The paper's pipeline: eqs. 5–7, forward torsion, not-a-knot spline, HEM (left samples), with θ_b held
        through curvature below ``kappa_min`` (default 1 1/m; ``kappa_min=0``: the literal transcription)."""
        opts = dict(method="paper", interpolation="spline", integrator="hem-left", torsion="forward")
        opts.update(options)
        return cls(fiber, calibration, **opts)

    def _set_calibration(self, calibration: Calibration) -> None:
        self.calibration = calibration
        self._lam0 = np.ascontiguousarray(calibration.reference_for(self.fiber), dtype=np.float64)
        self._const = None  # the fused kernel's constants, packed on first use (they depend on the calibration)
        self._solver = CurvatureSolver(
            calibration.design_for(self.fiber), method=self.inversion, central_core=self.fiber.central_core,
        )
        if self.twist:
            from twin.spun import TwistSolver, helix_of, twist_design

            self._solver = TwistSolver(twist_design(self.fiber, calibration), self.wavelength_noise / self._lam0,
                                       helix=helix_of(self.fiber, calibration), s=self.fiber.grating_s)

    def with_calibration(self, calibration: Calibration | None) -> Reconstructor:
        """The same reconstructor with another calibration (cheap: the interpolation operators are shared)."""
        other = copy.copy(self)
        other._set_calibration(calibration or Calibration())
        return other

    # ------------------------------------------------------------------ per node-set precomputation
    def _prepare(self, nodes: np.ndarray) -> dict:
        """Interpolation operators for the subset ``nodes`` of gratings (cached per subset)."""
        key = nodes.tobytes()
        if key in self._cache:
            return self._cache[key]
        s_nodes = self._s_nodes[nodes]
        flat = self._samples.ravel()
        prep: dict = {"s_nodes": s_nodes, "n": int(nodes.sum())}
        linear = self.interpolation != "pchip"
        if self.method == "material":
            if linear:
                b = curve.basis(s_nodes, flat, self.interpolation)
                prep["b_k"] = np.ascontiguousarray(b.T)
                # the fused kernel's operator: (all gratings, samples), zero on the gratings left out
                prep["b_fused"] = np.zeros((nodes.size, flat.size))
                prep["b_fused"][nodes] = prep["b_k"]
                if nodes.all():  # and as polynomial pieces, for the frames with every grating
                    prep["pieces"] = curve.piecewise(s_nodes, flat, self.interpolation)
        else:
            if linear:
                prep["b_kappa"] = curve.basis(s_nodes, flat, self.interpolation)
            if self.torsion == "theta-spline":
                prep["b_theta_d"] = curve.basis(s_nodes, flat, "spline", derivative=True)
                prep["b_theta0"] = curve.basis(s_nodes, self.s[:1], "spline")
            else:
                s_tau = s_nodes if self.torsion == "forward" or s_nodes.size < 2 else (
                    0.5 * (s_nodes[:-1] + s_nodes[1:]))
                prep["s_tau"] = s_tau
                if linear:
                    prep["b_tau"] = curve.basis(s_tau, flat, self.interpolation)
                prep["b_theta0"] = curve.basis(s_nodes, self.s[:1], "knn")
        self._cache[key] = prep
        return prep

    # ------------------------------------------------------------------ the call
    def _wavelengths(self, data, check_inf: bool = True) -> np.ndarray:
        if type(data) is np.ndarray and data.dtype == np.float64:
            w = data
        elif isinstance(data, Frame):
            w = data.wavelengths
        elif isinstance(data, Sequence) and len(data) and isinstance(data[0], Frame):
            w = Frame.stack(data).wavelengths
        else:
            try:
                w = np.asarray(data, dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(
                    f"wavelengths must be numbers (nm) of shape (..., {self.fiber.n_gratings}, "
                    f"{self.fiber.n_cores}) (gratings × cores); got {_describe(data)}"
                ) from None
        n_g, n_c = self.fiber.n_gratings, self.fiber.n_cores
        if w.ndim < 2 or w.shape[-2:] != (n_g, n_c):
            raise ValueError(
                f"wavelengths must have shape (..., {n_g}, {n_c}) (gratings × cores) for this fibre; got {w.shape}"
            )
        if check_inf and np.isinf(w).any():
            raise ValueError(_INF)
        return w

    def strain(self, wavelengths) -> tuple[np.ndarray, np.ndarray]:
        """Optical strain of every peak with the peaks outside the physical window as missing, computed once
        for the window check and the reconstruction (:meth:`from_strain`).

        Parameters
        ----------
        wavelengths : ndarray, shape (..., n_gratings, n_cores)
            nm (NaN where missing; ±inf counts as outside). Not checked: the caller matched the shape.

        Returns
        -------
        strain : ndarray, shape (..., n_gratings, n_cores)
            (λ − λ0)/λ0, NaN where missing or outside.
        outside : ndarray of bool, same shape
            Peaks present but outside the window (``peak_window``) around their reference, or infinite.
        """
        w = np.asarray(wavelengths, dtype=np.float64)
        e = (w - self._lam0) / self._lam0
        outside = outside_window(e, self.peak_window)
        return (np.where(outside, np.nan, e) if outside.any() else e), outside

    def curvature(self, wavelengths):
        """Calibrated curvature vectors at the gratings (a :class:`~twin.strain.StrainSolution`).

        Peaks outside the physical window (:meth:`peaks_outside`) count as missing."""
        return self._solver.solve(self.strain(self._wavelengths(wavelengths))[0])

    def peaks_outside(self, wavelengths) -> np.ndarray:
        """Boolean (..., n_gratings, n_cores): peaks present but outside the physical window (``peak_window``)
        around their reference wavelength, or infinite; the reconstruction treats them as missing."""
        return self.strain(wavelengths)[1]

    def __call__(self, wavelengths, *, frames: bool = True) -> Shape:
        if self.fused:
            return self._fused_shapes(self._wavelengths(wavelengths, check_inf=False), True, frames)
        return self._general(self.curvature(wavelengths), frames)

    def from_strain(self, strain: np.ndarray, *, frames: bool = True) -> Shape:
        """The shapes from the strain :meth:`strain` gives (the live loop's path: the strain once per batch).

        Parameters
        ----------
        strain : ndarray, shape (..., n_gratings, n_cores)
            Optical strain, NaN where missing or outside the window.
        frames : bool
            Whether the Shape carries the material frames.
        """
        if self.fused:
            return self._fused_shapes(np.asarray(strain, dtype=np.float64), False, frames)
        return self._general(self._solver.solve(strain), frames)

    def _fused_shapes(self, x: np.ndarray, is_wavelength: bool, want_frames: bool) -> Shape:
        """The fused compiled path (:mod:`twin._fused`) on wavelengths or strain (..., n_gratings, n_cores)."""
        n_g, n_c, n_p = self._dims
        batch = x.shape[:-2]
        xf = np.ascontiguousarray(x).reshape(-1, n_g, n_c)
        n_f = xf.shape[0]
        k = np.empty((n_f, n_g, 2))
        valid = np.empty((n_f, n_g), bool)
        pos = self._outputs.empty((n_f, n_p, 3))
        fr = self._outputs.empty((n_f, n_p, 3, 3)) if want_frames else self._no_frames
        const = self._const
        if const is None:
            const = self._const = _fused.pack(self._lam0, self.peak_window or 0.0, self._solver.fused_operator(),
                                              self._full["b_fused"], self._m, self.h, self.integrator == "rk4",
                                              self._full.get("pieces"))
        n_pending = _fused.reconstruct(xf, const, is_wavelength, k, valid, pos, fr, want_frames)
        if n_pending < 0:
            raise ValueError(_INF)
        if n_pending:
            # frames that lost a grating: one interpolation operator per pattern of valid gratings
            sel = np.flatnonzero(~valid.all(axis=1))
            patterns, which = np.unique(valid[sel], axis=0, return_inverse=True)
            bases = np.stack([self._prepare(p)["b_fused"] if p.any() else self._full["b_fused"] for p in patterns])
            which = np.where(patterns.any(axis=1)[which.ravel()], which.ravel(), -1)
            _fused.integrate(k, valid, which, bases, sel, self.h, self.integrator == "rk4", pos, fr, want_frames)
        return Shape._trusted(self.s, pos.reshape(*batch, n_p, 3),
                              fr.reshape(*batch, n_p, 3, 3) if want_frames else None,
                              k.reshape(*batch, n_g, 2), self.fiber.grating_s, valid.reshape(*batch, n_g))

    def _general(self, sol, want_frames: bool) -> Shape:
        """The general path: numpy steps around the compiled chain, for every mode."""
        k, valid = sol.curvature, sol.valid
        if self.twist:
            k = np.concatenate([k, sol.twist_rate[..., None]], axis=-1)  # rates (k_x, k_y, γ)
        batch = k.shape[:-2]
        kf = k.reshape((-1, *k.shape[-2:]))
        vf = valid.reshape((-1, valid.shape[-1]))
        n_f = kf.shape[0]
        n_steps = self.s.size - 1
        if vf.all():
            rates, r0, theta = self._profiles(kf, self._full)
            pos, frames = self._integrate(rates, r0, theta)
        else:
            pos = np.full((n_f, n_steps + 1, 3), np.nan)
            frames = np.full((n_f, n_steps + 1, 3, 3), np.nan)
            for sel, nodes, prep in self._groups(vf):
                rates, r0, theta = self._profiles(kf[sel][:, nodes], prep)
                pos[sel], frames[sel] = self._integrate(rates, r0, theta)
        return Shape(
            s=self.s,
            positions=pos.reshape(batch + pos.shape[1:]),
            frames=frames.reshape(batch + frames.shape[1:]) if want_frames else None,
            curvature=k[..., :2],
            grating_s=self.fiber.grating_s,
            valid=valid,
        )

    def _groups(self, valid: np.ndarray):
        """The frames of ``valid`` (n_frames, n_gratings) grouped by which gratings they have: (frame indices,
        valid gratings, the interpolation operators for them) per pattern; frames with none are left out."""
        patterns, which = np.unique(valid, axis=0, return_inverse=True)
        for p, nodes in enumerate(patterns):
            if nodes.any():
                yield np.flatnonzero(which.ravel() == p), nodes, self._prepare(nodes)

    def _accumulate(self, rate: np.ndarray) -> np.ndarray:
        """∫ rate ds from the base to every output point, (F, n_points), from a rate at the integrator's samples
        (F, n_steps · m), by the integrator's own quadrature."""
        steps = rate.reshape(rate.shape[0], -1, self._m)
        d = self.h * (steps @ np.asarray(_QUADRATURE[self._m]))
        return np.concatenate([np.zeros((steps.shape[0], 1)), np.cumsum(d, axis=1)], axis=1)

    def _profiles(self, k: np.ndarray, prep: dict):
        """Rates at the integrator's samples (F, 2, n_steps, m), initial frames and, for the Frenet pipeline,
        the bend-plane angle along the output points."""
        n_f = k.shape[0]
        shape_r = (n_f, k.shape[-1], self.s.size - 1, self._m)
        if self.method == "material":
            if "b_k" in prep:
                # (k_x, k_y[, γ]) per node as rows: one matrix product interpolates every component of every frame
                kt = np.swapaxes(k, -1, -2).reshape(n_f * k.shape[-1], -1)
                rates = kt @ prep["b_k"]
            else:
                kk = curve.interpolate(prep["s_nodes"], k, self._samples, self.interpolation)
                rates = np.swapaxes(kk, -1, -2)
            return rates.reshape(shape_r), None, None
        # Frenet (paper) pipeline
        kappa = np.hypot(k[..., 0], k[..., 1])
        theta = curve.hold_bend_angle(np.arctan2(k[..., 1], k[..., 0]), kappa, self.kappa_min)
        if self.torsion == "theta-spline":
            th = curve.unwrap_nodes(theta)
            tau = th @ prep["b_theta_d"].T
            theta0 = th @ prep["b_theta0"].T
        else:
            s_tau, tau_n = curve.torsion_nodes(theta, prep["s_nodes"], self.torsion)
            if "b_tau" in prep:
                tau = tau_n @ prep["b_tau"].T
            else:
                tau = curve.interpolate(s_tau, tau_n[..., None], self._samples, self.interpolation)[..., 0]
            theta0 = theta @ prep["b_theta0"].T
        if "b_kappa" in prep:
            kap = kappa @ prep["b_kappa"].T
        else:
            kap = curve.interpolate(prep["s_nodes"], kappa[..., None], self._samples, self.interpolation)[..., 0]
        rates = np.stack([tau, kap], axis=1).reshape(shape_r)
        # bend-plane angle along the output points: θ(0) plus the integrator's own quadrature of τ
        theta_out = theta0[:, :1] + self._accumulate(tau)
        c0, s0 = np.cos(theta_out[:, 0]), np.sin(theta_out[:, 0])
        r0 = _frenet_from_material(c0, s0)
        return rates, r0, theta_out

    def twist_angle(self, wavelengths) -> np.ndarray:
        """The measured twist ψ(s) = ∫ τ ds from the base to every output point, rad, shape (..., n_points).

        The same interpolation and quadrature of τ as the frame integration; needs ``twist`` (a spun fibre).
        """
        if not self.twist:
            raise ValueError("twist_angle needs a reconstructor that measures twist (a spun fibre, twist=True)")
        sol = self.curvature(wavelengths)
        tau, valid = sol.twist_rate, sol.valid
        batch = tau.shape[:-1]
        tf = tau.reshape(-1, tau.shape[-1])
        vf = valid.reshape(-1, valid.shape[-1])
        out = np.full((tf.shape[0], self.s.size), np.nan)
        for sel, nodes, prep in self._groups(vf):
            tau_s = curve.interpolate(prep["s_nodes"], tf[sel][:, nodes, None], self._samples, self.interpolation)
            out[sel] = self._accumulate(tau_s[..., 0].reshape(sel.size, -1))
        return out.reshape((*batch, self.s.size))

    def _integrate(self, rates, r0, theta):
        if self.method == "material":
            return curve.integrate(rates, self.h, self.integrator)
        pos, f = curve.integrate(rates, self.h, self.integrator, frenet=True, r0=r0)
        # material frame of a twist-free fibre: R = F Q(θ)ᵀ (docs/math.md §1)
        q = _frenet_from_material(np.cos(theta), np.sin(theta))
        return pos, f @ np.swapaxes(q, -1, -2)


_INF = "wavelengths contain ±inf; use NaN for a missing peak"


def _describe(data) -> str:
    """A short description of what was given as wavelengths, for an error message."""
    if isinstance(data, str | bytes):
        return f"{type(data).__name__} {data[:40]!r}"
    if isinstance(data, Sequence):
        lengths = sorted({str(len(x)) if isinstance(x, Sequence | np.ndarray) else "scalar" for x in data})
        if len(lengths) > 1:
            return f"a ragged sequence of {len(data)} rows (row lengths {', '.join(lengths)})"
        return f"a sequence of {len(data)} items that are not all numbers"
    return type(data).__name__


def _frenet_from_material(c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Q(θ) = [e3 | (cos θ, sin θ, 0) | (−sin θ, cos θ, 0)], the Frenet frame in material coordinates."""
    q = np.zeros((*c.shape, 3, 3))
    q[..., 2, 0] = 1.0
    q[..., 0, 1] = c
    q[..., 1, 1] = s
    q[..., 0, 2] = -s
    q[..., 1, 2] = c
    return q
