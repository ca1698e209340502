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
* peak loss when a peak leaves its grating's wavelength slot (the paper's failure at sharp bends): NaN with
  :attr:`twin.PeakStatus.OUT_OF_SLOT`. A real interrogator may also swap two peaks that cross; this model
  reports them lost instead.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from twin import FiberModel, PeakStatus, strain
from twin.calibration import nominal_delta_theta, scaled_core_angles

__all__ = ["Optics", "OpticsConfig"]


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
        Relative std of the per-core S_T (0.3 % reproduces the paper's 0.29 mm over 30 K, simulation.md §6).
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
    slot_half_width : float or None
        A peak further than this from its grating's nominal wavelength is lost, nm (None = never).
    grating_length : float
        Length over which each grating averages the strain, m.
    jitter : float
        Timestamp jitter (1σ), s.
    seed : int or None
        Seed of every random effect (as-built scatter, noise, drift, jitter).
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
    slot_half_width: float | None = 2.5
    grating_length: float = 1e-3
    jitter: float = 2e-5
    seed: int | None = 0

    @classmethod
    def ideal(cls, **changes) -> OpticsConfig:
        """Every effect off: the nominal fibre, exact wavelengths from :func:`twin.strain.forward`."""
        off = dict(delta_theta=None, gain_scale=1.0, lambda0_spread=0.0, twist_total=0.0, twist_wobble=0.0,
                   thermal_mismatch=0.0, temperature=0.0, fiber_offset=0.0, noise=0.0, drift=0.0,
                   quantisation=0.0, slot_half_width=None, grating_length=0.0, jitter=0.0)
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
        rng = np.random.default_rng(cfg.seed)
        angles = fiber.core_angles if cfg.delta_theta is None else scaled_core_angles(fiber, cfg.delta_theta)
        s_t = np.broadcast_to(np.asarray(fiber.temperature_sensitivity, float), (fiber.n_cores,))
        s_t = s_t * (1.0 + cfg.thermal_mismatch * rng.standard_normal(fiber.n_cores))
        self.true_fiber = fiber.replace(
            core_angles=angles,
            strain_sensitivity=fiber.strain_sensitivity * cfg.gain_scale,
            lambda0=fiber.lambda0 + cfg.lambda0_spread * rng.standard_normal(fiber.lambda0.shape),
            temperature_sensitivity=s_t,
        )
        x = fiber.grating_s / fiber.sensed_length
        self.twist = cfg.twist_total * x + cfg.twist_wobble * np.sin(2 * np.pi * x)
        if cfg.grating_length > 0:
            nodes, weights = np.polynomial.legendre.leggauss(self.N_SUB)
            self.sample_offsets, self._weights = 0.5 * cfg.grating_length * nodes, 0.5 * weights
        else:
            self.sample_offsets, self._weights = np.zeros(1), np.ones(1)
        self._rng = rng
        self._drift = np.zeros(fiber.lambda0.shape)
        self._t_last: float | None = None

    @property
    def sample_s(self) -> np.ndarray:
        """Arc lengths to sample the curvature at, shape (n_gratings, n_sub), m."""
        return self.nominal.grating_s[:, None] + self.sample_offsets[None, :]

    def wavelengths(self, curvature, axial_strain=0.0, delta_T=None, t: float | None = None):
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

        Returns
        -------
        wavelengths : ndarray (..., n_gratings, n_cores)
            nm; NaN where a peak was lost.
        status : ndarray of uint8, same shape
            :class:`twin.PeakStatus` bits.
        """
        cfg = self.config
        k = np.asarray(curvature, dtype=np.float64)
        if k.ndim >= 3 and k.shape[-3:-1] == (self.nominal.n_gratings, self.sample_offsets.size) \
                and k.shape[-1] == 2:
            k = np.einsum("...gsc,s->...gc", k, self._weights)
        axial = np.asarray(axial_strain, dtype=np.float64) - cfg.fiber_offset * k[..., 0]
        d_t = cfg.temperature if delta_T is None else delta_T
        w = strain.forward(self.true_fiber, k, axial_strain=axial, delta_T=d_t, twist=self.twist)
        if cfg.drift and t is not None:
            if self._t_last is not None and t > self._t_last:
                self._drift += cfg.drift * np.sqrt(t - self._t_last) * self._rng.standard_normal(self._drift.shape)
            self._t_last = t
        w = w + self._drift
        if cfg.noise:
            w = w + cfg.noise * self._rng.standard_normal(w.shape)
        if cfg.quantisation:
            w = np.round(w / cfg.quantisation) * cfg.quantisation
        status = np.zeros(w.shape, np.uint8)
        if cfg.slot_half_width is not None:
            lost = np.abs(w - self.nominal.lambda0) > cfg.slot_half_width
            w = np.where(lost, np.nan, w)
            status[lost] = PeakStatus.OUT_OF_SLOT | PeakStatus.MISSING
        return w, status

    def timestamp(self, t: float) -> float:
        """The interrogator's timestamp for simulation time ``t`` (with jitter), s."""
        return t + (self.config.jitter * self._rng.standard_normal() if self.config.jitter else 0.0)

    def describe(self) -> dict:
        """The true parameters a calibration and identification should recover (SI, JSON-ready)."""
        f = self.true_fiber
        return {
            "delta_theta": nominal_delta_theta(f),
            "gain_m": float(f.core_radii[f.bending_cores].mean() * f.strain_sensitivity),
            "twist_rad": (self.twist - self.twist[0]).tolist(),
        }
