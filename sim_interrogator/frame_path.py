"""The compiled frame path: the rod's state in MuJoCo to peak wavelengths in one numba call per frame.

:class:`~sim_interrogator.sim.SimInterrogator` makes a frame at up to 1 kHz. Done step by step in numpy (read
the rod, average its curvature over each grating, roll it into the fibre's frame, strain, effects) it took
≈ 30 µs of CPU per frame here in about thirty small array operations, most of it interpreter and allocation
overhead around a few microseconds of arithmetic. :func:`frame_wavelengths` does the same arithmetic in one
compiled call into buffers allocated once:

1. material frames and Darboux vectors of every edge (:func:`models._rod_kernels.frames_and_darboux`);
2. (κ1, κ2, τ) averaged over each grating's length: a fixed matrix (n_gratings, n_interior) that folds the
   cubic interpolation to the grating's Gauss points and their weights (:meth:`models.rod_state.RodReader.
   interpolation_matrix`, :attr:`sim_interrogator.optics.Optics.sample_weights`);
3. the optional roll of (κ1, κ2) into a fibre frame turned by r about d3 (the fibre-in-lumen setups);
4. (k_x, k_y) = (κ2, −κ1), the design-form strain and the interrogator's effects
   (:func:`sim_interrogator.optics._design_strain`, :func:`sim_interrogator.optics._apply_effects`).

What stays in Python per frame: the setup's conditions (temperature, axial strain), one normal draw of the
noise (:meth:`~sim_interrogator.optics.Optics.random_draw`, so the numbers are those of
:meth:`~sim_interrogator.optics.Optics.wavelengths` from the same seed) and the two output arrays the frame
keeps. The result equals the numpy path's to rounding (tests/test_sim.py). A spun fibre's exact path lengths
(:meth:`~sim_interrogator.optics.Optics.spun_wavelengths`) keep the general path.
"""

from __future__ import annotations

import mujoco
import numpy as np
from numba import njit

from models._rod_kernels import frames_and_darboux
from models.rod_state import RodReader
from sim_interrogator.optics import Optics, _apply_effects, _design_strain

__all__ = ["FramePath", "frame_wavelengths"]


@njit(cache=True, nogil=True)
def frame_wavelengths(x, plastic, theta, site_x, inv_lbar, frames, darboux, average, roll_c, roll_s, axial, temp,
                      curvature, strain, design, s_eps, s_t, offset, lam0, lam0_nominal, drift, drift_step, z,
                      noise, quant, slot, separation, band_lo, band_hi, order, lost_flag, w, status):
    """Rod state → curvature at the gratings → wavelengths, in one call (see the module docstring).

    ``frames`` (n_edges, 3, 3) and ``darboux`` (n_interior, 3) are filled as by
    :func:`~models._rod_kernels.frames_and_darboux`; ``average`` is (n_gratings, n_interior); ``axial``,
    ``temp`` (1, n_gratings); ``curvature`` (1, n_gratings, 2) receives (k_x, k_y) at the gratings, 1/m;
    ``strain`` (1, n_gratings, n_cores) the optical strain; ``w`` and ``status`` (1, n_gratings, n_cores) the
    wavelengths (nm, NaN where lost) and their status. The remaining arguments are those of
    :func:`~sim_interrogator.optics._design_strain` and :func:`~sim_interrogator.optics._apply_effects`.
    """
    frames_and_darboux(x, plastic, theta, site_x, inv_lbar, frames, darboux)
    n_g, n_v = average.shape
    for g in range(n_g):
        k1 = 0.0
        k2 = 0.0
        for v in range(n_v):
            a = average[g, v]
            k1 += a * darboux[v, 0]
            k2 += a * darboux[v, 1]
        r1 = roll_c * k1 + roll_s * k2  # (κ1, κ2) in the frame rolled by r about d3 (r = 0: unchanged)
        r2 = roll_c * k2 - roll_s * k1
        curvature[0, g, 0] = r2  # (k_x, k_y) = (κ2, −κ1)
        curvature[0, g, 1] = -r1
    _design_strain(curvature, axial, temp, design, s_eps, s_t, offset, strain)
    _apply_effects(strain, lam0, lam0_nominal, drift, drift_step, z, noise, quant, slot, separation, band_lo,
                   band_hi, order, lost_flag, w, status)


class FramePath:
    """Buffers and constants of :func:`frame_wavelengths` for one rod and one :class:`Optics`.

    Parameters
    ----------
    reader : RodReader
        The rod the optics read (the catheter's, or a fibre-in-lumen setup's own fibre rod).
    optics : Optics
        A fibre with straight cores (``spin_rate == 0``).

    Attributes
    ----------
    frames, darboux : ndarray
        The rod's edge frames (n_edges, 3, 3) and interior Darboux vectors (n_interior, 3) of the last call.
    """

    def __init__(self, reader: RodReader, optics: Optics) -> None:
        if optics.true_fiber.spin_rate:
            raise ValueError("FramePath: a spun fibre needs the exact path lengths (Optics.spun_wavelengths)")
        self.reader, self.optics = reader, optics
        n_g, n_c = optics.nominal.n_gratings, optics.nominal.n_cores
        basis = reader.interpolation_matrix(optics.sample_s)  # (n_g · n_sub, n_interior)
        self.average = np.ascontiguousarray(
            np.einsum("gsv,s->gv", basis.reshape(n_g, -1, basis.shape[-1]), optics.sample_weights))
        n_e = reader.n_vertices - 1
        self.frames = np.empty((n_e, 3, 3))
        self.darboux = np.empty((n_e - 1, 3))
        self._axial = np.zeros((1, n_g))
        self._temp = np.zeros((1, n_g))
        self._curvature = np.empty((1, n_g, 2))
        self._strain = np.empty((1, n_g, n_c))
        self._shape = (1, n_g, n_c)
        self._constants = optics.effect_arguments()

    def __call__(self, data: mujoco.MjData, axial, delta_t, t: float, roll: float = 0.0
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Wavelengths (n_gratings, n_cores) nm and status (uint8) of the rod in ``data`` at time ``t`` s.

        ``axial`` (strain) and ``delta_t`` (K) are scalars or (n_gratings,) arrays; ``roll`` (rad) turns
        (κ1, κ2) about d3 before the strain (the fibre's glued roll relative to its rod's material frame)."""
        x, p, theta, site_x = self.reader.kernel_inputs(data)
        self._axial[0] = axial
        self._temp[0] = delta_t
        step, z = self.optics.random_draw(t, 1)
        w = np.empty(self._shape)
        status = np.zeros(self._shape, np.uint8)
        design, s_eps, s_t, offset, *effects = self._constants
        frame_wavelengths(x, p, theta, site_x, self.reader.inverse_lbar, self.frames, self.darboux, self.average,
                          np.cos(roll), np.sin(roll), self._axial, self._temp, self._curvature, self._strain, design,
                          s_eps, s_t, offset, effects[0], effects[1], effects[2], step, z, *effects[3:], w, status)
        return w[0], status[0]
