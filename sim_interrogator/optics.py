"""Synthetic optics: what the fibre's gratings report for a given bending state (docs/simulation.md §6).

The simulated fibre is not the nominal one: its outer-core spacing, gain g = r·S_ε, reference wavelengths and
per-core thermal response differ from the datasheet as a real fibre's do, and its cores spiral by an intrinsic
twist. Calibration and identification have these to find. The wavelengths come from
:func:`twin.strain.forward` with the true parameters, so with every effect off the optics are exactly the
reconstruction's forward model.

Effects, each a field of :class:`OpticsConfig` (``OpticsConfig.ideal()`` turns all off):

* true fibre: Δθ (default the paper's identified 1.039 rad), gain 3.9 % below nominal (the paper's finding);
* λ0 spread: as-built reference wavelengths scattered about the nominal ones;
* intrinsic twist φ(s) = φ_L s/L + φ_w sin(2π s/L) (cores at θ_i + φ);
* temperature (uniform ΔT, or a field passed per call) with a per-core S_T mismatch;
* axial strain (common mode) and a glued fibre's offset from the catheter's neutral axis;
* finite grating length (strain averaged over it — the caller samples the curvature along each grating);
* white wavelength noise and a slow random-walk drift per peak;
* quantisation to the interrogator's resolution;
* peak loss (the paper's failure at sharp bends and compression): the interrogator assigns the peaks of a core
  to its gratings in wavelength order, so two peaks of neighbouring gratings that come closer than
  ``min_peak_separation`` merge and both are lost, and a peak outside the interrogator's ``band`` is lost; with
  ``slot_half_width`` set, a window-based interrogator also loses a peak that leaves its grating's window.
  Lost peaks are NaN with :attr:`twin.PeakStatus.OUT_OF_SLOT`. (Peaks that cross would be swapped by a real
  interrogator; the model reports them lost.)

A spun fibre (``FiberModel.spin_rate`` ≠ 0, docs/spun-fibers.md) takes the mechanical twist rate too: its strains
are the exact path lengths of the helical cores (:func:`twin.spun.exact_strain`), evaluated at the grating's
sample points where the cores' angle advances by Ω along the grating, with the same noise, drift, quantisation,
temperature and peak loss; ``spin_error`` makes the as-drawn spin rate differ from the datasheet's.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

import twin._jit_cache  # noqa: F401  (before the first cached kernel; see its docstring)
from twin import Calibration, FiberModel, PeakStatus, spun, strain
from twin.calibration import nominal_delta_theta, scaled_core_angles

__all__ = ["NormalStream", "Optics", "OpticsConfig"]


@dataclass(frozen=True)
class OpticsConfig:
    """Parameters of the synthetic interrogator and the simulated fibre's true properties.

    Attributes
    ----------
    delta_theta : float or None
        True outer-core spacing, rad; None keeps the nominal (π/3 for the paper's fibre).
    gain_scale : float
        True g = r·S_ε relative to nominal (the paper identified −3.9 %).
    lambda0_spread : float
        Std of the as-built reference wavelengths about the nominal ones, nm.
    twist_total, twist_wobble : float
        Intrinsic twist: linear part reaching ``twist_total`` at the sensed length, and the amplitude of a
        sinusoid with one period over it, rad.
    thermal_mismatch : float
        Relative std of the per-core S_T (0.3 % reproduces the paper's 0.29 mm over 30 K, docs/simulation.md §6).
    temperature : float
        Uniform temperature change, K, used when a call passes none.
    fiber_offset : float
        Distance of a glued fibre from the catheter's neutral axis along d1, m; adds ε = −k_x·offset to all
        cores (common mode). A fibre free to slide in a lumen has none (default).
    noise : float
        White wavelength noise per peak (1σ), nm (1 pm for a WDM interrogator).
    drift : float
        Random-walk drift per peak, nm/√s.
    quantisation : float
        Wavelength resolution, nm (0 = none).
    min_peak_separation : float
        Peaks of neighbouring gratings (in wavelength order) closer than this merge and are lost, nm.
    band : tuple of float
        The interrogator's wavelength range, nm; peaks outside it are lost.
    slot_half_width : float or None
        For a window-based interrogator: a peak further than this from its grating's nominal wavelength is
        lost, nm (None: peaks are tracked by order, the default).
    grating_length : float
        Length over which each grating averages the strain, m.
    jitter : float
        Timestamp jitter (1σ), s.
    spin_error : float
        A spun fibre's as-drawn spin rate minus the nominal one, turns/m (ignored for straight cores).
    fiber_seed : int
        Seed of the as-built scatter (λ0 spread, S_T mismatch): one value is one physical fibre, so a
        calibration made in one run holds in the next.
    seed : int or None
        Seed of the noise, drift and jitter (None: fresh each time).
    """

    delta_theta: float | None = 1.039
    gain_scale: float = 1.0 - 0.039
    lambda0_spread: float = 0.3
    twist_total: float = float(np.deg2rad(25.0))
    twist_wobble: float = float(np.deg2rad(8.0))
    thermal_mismatch: float = 0.003
    temperature: float = 0.0
    fiber_offset: float = 0.0
    noise: float = 1e-3
    drift: float = 2e-4
    quantisation: float = 1e-4
    min_peak_separation: float = 1.0
    band: tuple[float, float] = (1500.0, 1600.0)
    slot_half_width: float | None = None
    grating_length: float = 1e-3
    jitter: float = 2e-5
    fiber_seed: int = 0
    seed: int | None = 0
    spin_error: float = 0.0

    @classmethod
    def ideal(cls, **changes) -> OpticsConfig:
        """Every effect off: the nominal fibre, exact wavelengths from :func:`twin.strain.forward`."""
        off = dict(delta_theta=None, gain_scale=1.0, lambda0_spread=0.0, twist_total=0.0, twist_wobble=0.0,
                   thermal_mismatch=0.0, temperature=0.0, fiber_offset=0.0, noise=0.0, drift=0.0,
                   quantisation=0.0, min_peak_separation=0.0, band=(0.0, np.inf), slot_half_width=None,
                   grating_length=0.0, jitter=0.0)
        off.update(changes)
        return cls(**off)

    def replace(self, **changes) -> OpticsConfig:
        return dataclasses.replace(self, **changes)


class Optics:
    """The simulated fibre and interrogator for one nominal fibre model.

    Parameters
    ----------
    fiber : FiberModel
        The nominal (datasheet) fibre, as the reconstruction knows it.
    config : OpticsConfig, optional

    Attributes
    ----------
    nominal : FiberModel
    true_fiber : FiberModel
        The simulated fibre's actual parameters.
    twist : ndarray (n_gratings,)
        Intrinsic twist at each grating, rad.
    sample_offsets : ndarray (n_sub,)
        Where within each grating the caller should sample curvature, m relative to the grating centre.
    """

    N_SUB = 5  #: curvature samples per grating for the length average (Gauss–Legendre: exact for quintics)

    def __init__(self, fiber: FiberModel, config: OpticsConfig | None = None):
        self.nominal = fiber
        self.config = cfg = config or OpticsConfig()
        rng = np.random.default_rng(cfg.fiber_seed)
        angles = fiber.core_angles if cfg.delta_theta is None else scaled_core_angles(fiber, cfg.delta_theta)
        s_t = np.broadcast_to(np.asarray(fiber.temperature_sensitivity, float), (fiber.n_cores,))
        s_t = s_t * (1.0 + cfg.thermal_mismatch * rng.standard_normal(fiber.n_cores))
        self.true_fiber = fiber.replace(
            core_angles=angles,
            strain_sensitivity=fiber.strain_sensitivity * cfg.gain_scale,
            lambda0=fiber.lambda0 + cfg.lambda0_spread * rng.standard_normal(fiber.lambda0.shape),
            temperature_sensitivity=s_t,
        )
        if fiber.spin_rate:
            self.true_fiber = self.true_fiber.replace(spin_rate=fiber.spin_rate + cfg.spin_error)
        x = fiber.grating_s / fiber.sensed_length
        self.twist = cfg.twist_total * x + cfg.twist_wobble * np.sin(2 * np.pi * x)
        self._design = strain.design_matrix(self.true_fiber, twist=self.twist)
        self._s_t = np.ascontiguousarray(np.broadcast_to(self.true_fiber.temperature_sensitivity, (fiber.n_cores,)))
        self._no_noise = np.zeros((1, 1, 1))
        # neighbours in wavelength order, per core: the interrogator assigns peaks by order
        self._order = np.ascontiguousarray(np.argsort(fiber.lambda0, axis=0))
        self._lost_flag = int(PeakStatus.OUT_OF_SLOT | PeakStatus.MISSING)
        if cfg.grating_length > 0:
            nodes, weights = np.polynomial.legendre.leggauss(self.N_SUB)
            self.sample_offsets, self._weights = 0.5 * cfg.grating_length * nodes, 0.5 * weights
        else:
            self.sample_offsets, self._weights = np.zeros(1), np.ones(1)
        # noise, drift and jitter: the seed's normals, served in the order they are asked for
        self.normals = NormalStream(np.random.default_rng(cfg.seed))
        self._drift = np.zeros(fiber.lambda0.shape)
        self._t_last: float | None = None

    @property
    def sample_s(self) -> np.ndarray:
        """Arc lengths to sample the curvature at, shape (n_gratings, n_sub), m."""
        return self.nominal.grating_s[:, None] + self.sample_offsets[None, :]

    @property
    def sample_weights(self) -> np.ndarray:
        """Quadrature weights (n_sub,) that average samples at :attr:`sample_s` over each grating."""
        return self._weights

    def wavelengths(self, curvature, axial_strain=0.0, delta_T=None, t: float | None = None, twist_rate=None):
        """Peak wavelengths and status for one state (or a batch of states).

        Parameters
        ----------
        curvature : array_like, shape (..., n_gratings, 2) or (..., n_gratings, n_sub, 2)
            Curvature vector (k_x, k_y) of the catheter in its material frame, 1/m: at the gratings, or at
            :attr:`sample_s` to be averaged over each grating's length.
        axial_strain : float or array_like (..., n_gratings)
            Mechanical strain of the neutral axis.
        delta_T : float or array_like (..., n_gratings), optional
            Temperature change, K; default ``config.temperature``.
        t : float, optional
            Simulation time, s; advances the drift by the time since the last call.
        twist_rate : array_like (..., n_gratings) or (..., n_gratings, n_sub), optional
            The catheter's mechanical twist rate τ, rad/m: read by a spun fibre (default 0), ignored otherwise.

        Returns
        -------
        wavelengths : ndarray (..., n_gratings, n_cores)
            nm; NaN where a peak was lost.
        status : ndarray of uint8, same shape
            :class:`twin.PeakStatus` bits.
        """
        if self.true_fiber.spin_rate:
            return self.spun_wavelengths(curvature, 0.0 if twist_rate is None else twist_rate, axial_strain,
                                         delta_T, t)
        cfg, fiber = self.config, self.true_fiber
        k = np.asarray(curvature, dtype=np.float64)
        n_g, n_c = fiber.n_gratings, fiber.n_cores
        if k.ndim >= 3 and k.shape[-3:] == (n_g, self.sample_offsets.size, 2):
            k = np.einsum("...gsc,s->...gc", k, self._weights)
        if k.ndim < 2 or k.shape[-2:] != (n_g, 2):
            raise ValueError(f"curvature must have shape (..., {n_g}, 2) or (..., {n_g}, "
                             f"{self.sample_offsets.size}, 2), got {k.shape}")
        batch = k.shape[:-2]
        n_f = int(np.prod(batch)) if batch else 1
        d_t = cfg.temperature if delta_T is None else delta_T
        axial = self._per_grating(axial_strain, batch, n_f)
        temp = self._per_grating(d_t, batch, n_f)
        e = np.empty((n_f, n_g, n_c))
        _design_strain(k.reshape(n_f, n_g, 2), axial, temp, self._design, fiber.strain_sensitivity, self._s_t,
                       cfg.fiber_offset, e)
        w, status = self._effects(e, t)
        if not batch:
            return w[0], status[0]
        return w.reshape(*batch, n_g, n_c), status.reshape(*batch, n_g, n_c)

    def spun_wavelengths(self, curvature, twist_rate, axial_strain=0.0, delta_T=None, t: float | None = None):
        """A spun fibre's peak wavelengths and status from the exact helical path lengths (docs/spun-fibers.md §2).

        Parameters as :meth:`wavelengths`; ``twist_rate`` (rad/m) has the curvature's leading shape without its
        last axis. Curvature and twist given per grating are held over the grating's length; the strain is
        evaluated at :attr:`sample_s` (the cores turn by Ω × the grating length within it) and averaged.
        """
        cfg, fiber = self.config, self.true_fiber
        n_g, n_c, n_sub = fiber.n_gratings, fiber.n_cores, self.sample_offsets.size
        k = np.asarray(curvature, dtype=np.float64)
        per_sample = k.ndim >= 3 and k.shape[-3:] == (n_g, n_sub, 2)
        if not per_sample and (k.ndim < 2 or k.shape[-2:] != (n_g, 2)):
            raise ValueError(f"curvature must have shape (..., {n_g}, 2) or (..., {n_g}, {n_sub}, 2), got {k.shape}")
        batch = k.shape[:-3] if per_sample else k.shape[:-2]
        n_f = int(np.prod(batch)) if batch else 1
        k = np.broadcast_to(k if per_sample else k[..., None, :], (*batch, n_g, n_sub, 2)).reshape(n_f, -1, 2)
        tau = np.asarray(twist_rate, dtype=np.float64)
        if tau.ndim and tau.shape[len(batch):] == (n_g,):
            tau = tau[..., None]
        tau = np.broadcast_to(tau, (*batch, n_g, n_sub)).reshape(n_f, -1)
        d_t = cfg.temperature if delta_T is None else delta_T
        axial = self._per_grating(axial_strain, batch, n_f)
        temp = self._per_grating(d_t, batch, n_f)
        s = self.sample_s.ravel()
        x = s / self.nominal.sensed_length
        phase = cfg.twist_total * x + cfg.twist_wobble * np.sin(2 * np.pi * x)  # the intrinsic twist, as above
        eps0 = np.repeat(axial, n_sub, axis=1) - cfg.fiber_offset * k[..., 0]
        mech = spun.exact_strain(fiber, k, tau, eps0, s=s, twist=phase).reshape(n_f, n_g, n_sub, n_c)
        e = fiber.strain_sensitivity * np.einsum("fgsc,s->fgc", mech, self._weights)
        e += temp[..., None] * self._s_t
        w, status = self._effects(np.ascontiguousarray(e), t)
        if not batch:
            return w[0], status[0]
        return w.reshape(*batch, n_g, n_c), status.reshape(*batch, n_g, n_c)

    def _effects(self, e: np.ndarray, t: float | None) -> tuple[np.ndarray, np.ndarray]:
        """Wavelengths (nm, NaN where lost) and status from optical strains ``e`` (n_f, n_g, n_c) with drift,
        noise, quantisation and peak loss (:func:`_apply_effects`): one implementation for the design form and
        the spun fibre's exact path lengths, so a straight fibre gets the same noise from the same seed."""
        cfg = self.config
        step, z = self.random_draw(t, e.shape[0])
        w = np.empty(e.shape)
        status = np.zeros(e.shape, np.uint8)
        _apply_effects(e, self.true_fiber.lambda0, self.nominal.lambda0, self._drift, step, z, cfg.noise,
                       cfg.quantisation, cfg.slot_half_width or 0.0, cfg.min_peak_separation, float(cfg.band[0]),
                       float(cfg.band[1]), self._order, self._lost_flag, w, status)
        return w, status

    def drift_step(self, t: float | None) -> float:
        """The drift's random-walk step, nm: ``drift`` × √(time since the last call) (0 on the first call, without
        a time or without drift)."""
        cfg = self.config
        step = 0.0
        if cfg.drift and t is not None:
            if self._t_last is not None and t > self._t_last:
                step = cfg.drift * math.sqrt(t - self._t_last)
            self._t_last = t
        return step

    def random_draw(self, t: float | None, n_states: int) -> tuple[float, np.ndarray]:
        """The drift's step (nm, from the time since the last call) and the normal draws of one call for
        ``n_states`` states: ``z[0]`` drives the drift, ``z[1 + f]`` the noise of state f (a (1, 1, 1) zero
        array when neither is on). The compiled frame path (:mod:`sim_interrogator.frame_path`) draws the same
        numbers from the same seed (:meth:`drift_step`, then ``normals.take`` when noise or step)."""
        step = self.drift_step(t)
        # one draw per call: drift increments (first slice) and white noise
        if self.config.noise or step:
            return step, self.normals.array((n_states + 1, *self._drift.shape))
        return step, self._no_noise

    def effect_arguments(self) -> tuple:
        """The constant arguments of :func:`_apply_effects` after ``e`` … ``z`` (λ0s, drift state, noise,
        quantisation, slot, separation, band, order, lost flag) and of :func:`_design_strain` (design,
        S_ε, S_T, offset), for a compiled caller that runs both in one call (:mod:`sim_interrogator.frame_path`)."""
        cfg, f = self.config, self.true_fiber
        return (self._design, float(f.strain_sensitivity), self._s_t, float(cfg.fiber_offset),
                f.lambda0, self.nominal.lambda0, self._drift, float(cfg.noise), float(cfg.quantisation),
                float(cfg.slot_half_width or 0.0), float(cfg.min_peak_separation), float(cfg.band[0]),
                float(cfg.band[1]), self._order, self._lost_flag)

    def _per_grating(self, value, batch: tuple, n_f: int) -> np.ndarray:
        """A scalar or (..., n_gratings) value as a (n_f, n_gratings) array (a zero-stride view if scalar)."""
        if np.ndim(value) == 0:
            return np.broadcast_to(float(value), (n_f, self.nominal.n_gratings))
        a = np.asarray(value, dtype=np.float64)
        return np.broadcast_to(a, (*batch, self.nominal.n_gratings)).reshape(n_f, -1)

    def timestamp(self, t: float) -> float:
        """The interrogator's timestamp for simulation time ``t`` (with jitter), s."""
        return t + (self.config.jitter * self.normals.next() if self.config.jitter else 0.0)

    def true_calibration(self) -> Calibration:
        """The calibration a perfect procedure would find: as-built λ0, the intrinsic twist (relative to
        grating 0) and the true Δθ and g. Reconstructing with it leaves only noise, drift, quantisation and the
        grating-length average."""
        d = self.describe()
        spin = d.get("spin_rate")
        gain = d["gain_m"]
        if spin:
            # the cores turn by Ω l within a grating of length l, which averages the bending strain by
            # sinc(Ω l/2) (docs/spun-fibers.md §6); a gain calibration absorbs it
            half = 0.5 * 2 * np.pi * spin * self.config.grating_length
            gain *= np.sin(half) / half if half else 1.0
        return Calibration(lambda0=self.true_fiber.lambda0, twist=np.asarray(d["twist_rad"]),
                           delta_theta=d["delta_theta"], gain=gain, spin_rate=spin,
                           provenance={"method": "the simulated fibre's true parameters"})

    def describe(self) -> dict:
        """The true parameters a calibration and identification should recover (SI, JSON-ready)."""
        f = self.true_fiber
        return {
            "delta_theta": nominal_delta_theta(f),
            "gain_m": float(f.core_radii[f.bending_cores].mean() * f.strain_sensitivity),
            "twist_rad": (self.twist - self.twist[0]).tolist(),
            **({"spin_rate": f.spin_rate} if f.spin_rate else {}),
        }


class NormalStream:
    """Standard normal numbers of one :class:`numpy.random.Generator`, drawn ahead in blocks.

    The generator draws each normal on its own from its bit stream and keeps no spare, so its normals form one
    sequence whatever the sizes of the calls that draw them: served from a block drawn ahead, every caller gets
    the numbers it would have drawn itself, in the same order (the noise, drift and jitter of a seed are
    unchanged; tests/test_sim.py). Drawing a block at a time pays the generator's cold start once per block:
    at 1 kHz each frame's draw came after a physics step that had evicted the generator's code and tables from
    the cache, and took ≈ 6 µs for 144 numbers where a warm draw takes ≈ 1.5 µs (docs/simulation.md §4).

    Parameters
    ----------
    rng : numpy.random.Generator
        Drawn from by this stream only (any other draw would reorder the numbers).
    block : int
        Numbers drawn at a time.
    """

    def __init__(self, rng: np.random.Generator, block: int = 4096) -> None:
        self.rng = rng
        self.buffer = np.empty(block)  #: the block; :meth:`take` gives offsets into it
        self._pos = block  # nothing drawn yet

    def take(self, n: int) -> int:
        """Offset in :attr:`buffer` of the next ``n`` numbers (valid until the next call: a refill moves them)."""
        pos = self._pos
        if pos + n > self.buffer.size:
            # keep the numbers not yet served, in front of the fresh ones
            rest = self.buffer.size - pos
            if n > self.buffer.size:
                buf = np.empty(n + self.buffer.size)
                buf[:rest] = self.buffer[pos:]
                self.buffer = buf
            else:
                self.buffer[:rest] = self.buffer[pos:].copy()
            self.rng.standard_normal(out=self.buffer[rest:])
            pos = 0
        self._pos = pos + n
        return pos

    def array(self, shape: tuple[int, ...]) -> np.ndarray:
        """The next numbers as a new array of ``shape``."""
        n = math.prod(shape)
        o = self.take(n)
        return self.buffer[o : o + n].reshape(shape).copy()

    def next(self) -> float:
        """The next number."""
        return float(self.buffer[self.take(1)])


@njit(cache=True, nogil=True)
def _design_strain(k, axial, temp, design, s_eps, s_t, offset, e):
    """Optical strain ``e`` (F, n_g, n_c) of F states in design form: c_i + D_i1 k_x + D_i2 k_y with
    c_i = S_ε ε_axial + S_T,i ΔT, the linear model of :func:`twin.strain.forward` (tests/test_sim.py checks the
    two agree); compiled because it runs at up to 1 kHz."""
    n_f, n_g, n_c = e.shape
    for f in range(n_f):
        for g in range(n_g):
            kx, ky = k[f, g, 0], k[f, g, 1]
            eps = axial[f, g] - offset * kx
            for c in range(n_c):
                e[f, g, c] = design[g, c, 1] * kx + design[g, c, 2] * ky + s_eps * eps + s_t[c] * temp[f, g]


@njit(cache=True, nogil=True)
def _apply_effects(e, lam0, lam0_nominal, drift, drift_step, z, noise, quant, slot, separation, band_lo, band_hi,
                   order, lost_flag, w, status):
    """Wavelengths λ = λ0 (1 + e) with drift, noise, quantisation and peak loss for F states of optical strain
    ``e`` (F, n_g, n_c), into ``w`` and ``status``; compiled because it runs at up to 1 kHz.

    ``z[0]`` drives the drift's random walk (step ``drift_step`` nm), ``z[1 + f]`` the noise of state f;
    ``order[:, c]`` lists core c's gratings by nominal wavelength.
    """
    n_f, n_g, n_c = w.shape
    if drift_step > 0.0:
        for g in range(n_g):
            for c in range(n_c):
                drift[g, c] += drift_step * z[0, g, c]
    for f in range(n_f):
        for g in range(n_g):
            for c in range(n_c):
                lam = lam0[g, c] * (1.0 + e[f, g, c]) + drift[g, c]
                if noise > 0.0:
                    lam += noise * z[1 + f, g, c]
                if quant > 0.0:
                    lam = np.round(lam / quant) * quant
                if (slot > 0.0 and abs(lam - lam0_nominal[g, c]) > slot) or lam < band_lo or lam > band_hi:
                    status[f, g, c] = lost_flag
                w[f, g, c] = lam
        if separation > 0.0:
            for c in range(n_c):
                for j in range(n_g - 1):
                    a, b = order[j, c], order[j + 1, c]
                    if abs(w[f, a, c] - w[f, b, c]) < separation:
                        status[f, a, c] = lost_flag
                        status[f, b, c] = lost_flag
        for g in range(n_g):
            for c in range(n_c):
                if status[f, g, c]:
                    w[f, g, c] = np.nan
