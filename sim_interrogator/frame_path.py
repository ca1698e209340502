"""The compiled frame path: the rod's state in MuJoCo to peak wavelengths in one numba call per frame.

:class:`~sim_interrogator.sim.SimInterrogator` makes a frame at up to 1 kHz. Done step by step in numpy (read
the rod, average its curvature over each grating, roll it into the fibre's frame, strain, effects) it took
≈ 30 µs of CPU per frame here in about thirty small array operations, most of it interpreter and allocation
overhead around a few microseconds of arithmetic. :func:`frame_wavelengths` does the same arithmetic in one
compiled call into buffers allocated once:

1. material frames and Darboux vectors of every edge, read through views of ``mjData`` taken once, the small
   angles by their series (:class:`models.rod_state.RodView`, :func:`models._rod_kernels.view_read`); while
   MuJoCo reports the rod asleep and its inputs are bit for bit those of the last read, that read is kept;
2. (κ1, κ2, τ) averaged over each grating's length: a fixed matrix (n_gratings, n_interior) that folds the
   cubic interpolation to the grating's Gauss points and their weights (:func:`grating_average`), redone only
   after a fresh read;
3. the optional roll of (κ1, κ2) into a fibre frame turned by r about d3 (the fibre-in-lumen setups);
4. (k_x, k_y) = (κ2, −κ1), the design-form strain and the interrogator's effects
   (:func:`sim_interrogator.optics._design_strain`, :func:`sim_interrogator.optics._apply_effects`).

What stays in Python per frame: the setup's conditions (temperature, axial strain: a Python float is spread over
the gratings in the compiled call), the drift's step and the offset of the frame's normal draws in the optics'
:class:`~sim_interrogator.optics.NormalStream` (so the numbers are those of
:meth:`~sim_interrogator.optics.Optics.wavelengths` from the same seed) and the two output arrays the frame
keeps. The call goes to the compiled function directly, past numba's dispatcher (:mod:`twin._numba_entry`), with
its constants and buffers packed into one array and the arrays it reads as they are passed as one array of their
addresses (each array argument costs ≈ 70–80 ns to unpack). The result
equals the numpy path's to rounding (tests/test_sim.py); a kept read gives the frame a fresh read gives, bit for
bit (tests/test_rod_read.py). A spun fibre's exact path lengths
(:meth:`~sim_interrogator.optics.Optics.spun_wavelengths`) keep the general path.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from numba import carray, njit

from models._rod_kernels import view_parts_in_call, view_read
from models.rod_state import RodReader, RodView
from sim_interrogator.optics import Optics, _apply_effects, _design_strain
from twin._numba_entry import addresses, compiled_entry, float64_at, int32_at, int64_at

__all__ = ["FramePath", "frame_wavelengths", "grating_average"]


def grating_average(reader: RodReader, optics: Optics) -> np.ndarray:
    """The fixed matrix (n_gratings, n_interior) that takes the rod's Darboux vectors at its interior vertices to
    their average over each grating's length: the cubic interpolation to :attr:`Optics.sample_s` folded with
    :attr:`Optics.sample_weights`."""
    n_g = optics.nominal.n_gratings
    basis = reader.interpolation_matrix(optics.sample_s)  # (n_g · n_sub, n_interior)
    return np.ascontiguousarray(np.einsum("gsv,s->gv", basis.reshape(n_g, -1, basis.shape[-1]),
                                          optics.sample_weights))


N_SCALARS = 9  # S_ε, the fibre's offset, noise, quantisation, slot, separation, the band's ends, the lost flag


def _size(n_v: int, n_g: int, n_c: int) -> int:
    """The length of :class:`FramePath`'s buffer (:func:`_parts`)."""
    return N_SCALARS + n_v * n_g + 6 * n_g * n_c + n_c + 1 + 6 * n_g


@njit(cache=True, nogil=True, inline="always")
def _offsets(n_v, n_g, n_c):
    """Where the constants of :class:`FramePath`'s buffer end and its work begins (:func:`_parts`)."""
    m = n_g * n_c
    a = N_SCALARS
    b = a + n_v * n_g
    c = b + 3 * m
    d = c + n_c
    e = d + m
    f = e + m
    return a, b, c, d, e, f, f + 1


@njit(cache=True, nogil=True)
def _parts(buffer, n_v, n_g, n_c):
    """The parts of :class:`FramePath`'s buffer. Constants: the scalars, the grating average transposed (n_v,
    n_g), the design matrix (n_g, n_c, 3), S_T (n_c,), λ0 and the nominal λ0 (n_g, n_c). Work: the rod read the
    average is of (1,), axial strain and temperature change (1, n_g), the average's κ1 and κ2 (n_g,), (k_x, k_y)
    (1, n_g, 2), the strain (1, n_g, n_c)."""
    a, b, c, d, e, f, g = _offsets(n_v, n_g, n_c)
    return (buffer[:a], buffer[a:b].reshape((n_v, n_g)), buffer[b:c].reshape((n_g, n_c, 3)), buffer[c:d],
            buffer[d:e].reshape((n_g, n_c)), buffer[e:f].reshape((n_g, n_c)), buffer[f:g],
            buffer[g : g + n_g].reshape((1, n_g)), buffer[g + n_g : g + 2 * n_g].reshape((1, n_g)),
            buffer[g + 2 * n_g : g + 3 * n_g], buffer[g + 3 * n_g : g + 4 * n_g],
            buffer[g + 4 * n_g : g + 6 * n_g].reshape((1, n_g, 2)),
            buffer[g + 6 * n_g : g + 6 * n_g + n_g * n_c].reshape((1, n_g, n_c)))


@njit(cache=True, nogil=True, inline="always")
def _parts_at(p, n_v, n_g, n_c):
    """:func:`_parts` as views made from the buffer's address ``p``, inside one compiled call (numba's slicing and
    reshaping check each part, ≈ 30–50 ns a part a call)."""
    a, b, c, d, e, f, g = _offsets(n_v, n_g, n_c)
    return (carray(float64_at(p), a), carray(float64_at(p + 8 * a), (n_v, n_g)),
            carray(float64_at(p + 8 * b), (n_g, n_c, 3)), carray(float64_at(p + 8 * c), n_c),
            carray(float64_at(p + 8 * d), (n_g, n_c)), carray(float64_at(p + 8 * e), (n_g, n_c)),
            carray(float64_at(p + 8 * f), 1), carray(float64_at(p + 8 * g), (1, n_g)),
            carray(float64_at(p + 8 * (g + n_g)), (1, n_g)), carray(float64_at(p + 8 * (g + 2 * n_g)), n_g),
            carray(float64_at(p + 8 * (g + 3 * n_g)), n_g), carray(float64_at(p + 8 * (g + 4 * n_g)), (1, n_g, 2)),
            carray(float64_at(p + 8 * (g + 6 * n_g)), (1, n_g, n_c)))


@njit(cache=True, nogil=True)
def frame_wavelengths(fixed, have_frames, roll, axial_value, temp_value, drift_step, normals, z_offset, w,
                      status):
    """Rod state → curvature at the gratings → wavelengths, in one call (see the module docstring).

    ``fixed`` holds the addresses and sizes (:func:`twin._numba_entry.addresses`) of the arrays every call reads
    as they are, viewed again here (one array to unpack instead of nine): those of
    :func:`models._rod_kernels.view_read` (views of ``mjData`` and the rod view's buffer), ``buffer``, ``order``
    and ``drift``. With ``have_frames`` the view's buffers are taken as they are. Returns False, computing
    nothing, when the rod has no frames yet (``plastic`` still zero: the caller fills the buffers and calls again
    with ``have_frames``). The grating average is redone only when the view's buffers were filled afresh (a rod
    read kept asleep keeps its average, bit for bit).

    ``buffer`` packs the constants and the work buffers (:func:`_parts`): the scalars S_ε, the fibre's offset,
    noise, quantisation, slot, separation, the band's ends and the lost flag; :func:`grating_average` transposed,
    (n_interior, n_gratings); the design matrix, S_T, λ0 and the nominal λ0 of
    :func:`~sim_interrogator.optics._design_strain` and :func:`~sim_interrogator.optics._apply_effects`. The
    axial strain and temperature change at the gratings are set there to ``axial_value``, ``temp_value`` unless
    these are NaN (the caller filled them); (k_x, k_y) at the gratings (1/m) and the optical strain are left
    there. ``order`` and ``drift`` are the optics' (:meth:`~sim_interrogator.optics.Optics.effect_arguments`);
    ``roll`` rad; ``w`` and ``status`` (n_gratings, n_cores) receive the wavelengths (nm, NaN where lost) and
    their status. ``normals[z_offset:]`` holds the frame's 2 · n_gratings · n_cores normal draws
    (:meth:`~sim_interrogator.optics.Optics.random_draw`'s ``z``, read only with drift or noise).
    """
    n_g, n_c = w.shape
    sizes = fixed[9:]
    x = carray(float64_at(fixed[0]), (sizes[0] // 3, 3))
    plastic = carray(float64_at(fixed[1]), sizes[1])
    qpos = carray(float64_at(fixed[2]), sizes[2])
    site_row = carray(float64_at(fixed[3]), sizes[3])
    tree_asleep = carray(int32_at(fixed[4]), sizes[4])
    rod_buffer = carray(float64_at(fixed[5]), sizes[5])
    order = carray(int64_at(fixed[7]), (n_g, n_c))
    drift = carray(float64_at(fixed[8]), (n_g, n_c))
    ne = plastic.size // 6
    n_v = ne - 1
    (scalars, average_t, design, s_t, lam0, lam0_nominal, averaged, axial, temp, k1, k2, curvature,
     strain) = _parts_at(fixed[6], n_v, n_g, n_c)
    if axial_value == axial_value:  # a number for every grating (NaN: ``axial`` holds them already)
        axial[0, :] = axial_value
    if temp_value == temp_value:
        temp[0, :] = temp_value
    if not have_frames and view_read(x, plastic, qpos, site_row, tree_asleep, rod_buffer) < 0:
        return False
    darboux = view_parts_in_call(rod_buffer, ne)[5]
    read = rod_buffer[1]  # the view's count of fresh reads: the average is of the read it names
    if averaged[0] != read:
        # (κ1, κ2) averaged over each grating: average_t is the matrix transposed, (n_interior, n_gratings), so
        # that the gratings' sums advance side by side in two contiguous rows (each still adds its terms in
        # vertex order) instead of one dependent chain after another
        k1[:] = 0.0
        k2[:] = 0.0
        for v in range(n_v):
            d1, d2 = darboux[v, 0], darboux[v, 1]
            for g in range(n_g):
                a = average_t[v, g]
                k1[g] += a * d1
                k2[g] += a * d2
        averaged[0] = read
    roll_c, roll_s = (np.cos(roll), np.sin(roll)) if roll != 0.0 else (1.0, 0.0)
    k = curvature[0]
    for g in range(n_g):
        r1 = roll_c * k1[g] + roll_s * k2[g]  # (κ1, κ2) in the frame rolled by r about d3 (r = 0: unchanged)
        r2 = roll_c * k2[g] - roll_s * k1[g]
        k[g, 0] = r2  # (k_x, k_y) = (κ2, −κ1)
        k[g, 1] = -r1
    _design_strain(curvature, axial, temp, design, scalars[0], s_t, scalars[1], strain)
    z = normals[z_offset : z_offset + 2 * n_g * n_c].reshape((2, n_g, n_c))
    _apply_effects(strain, lam0, lam0_nominal, drift, drift_step, z, scalars[2], scalars[3], scalars[4], scalars[5],
                   scalars[6], scalars[7], order, int(scalars[8]), w.reshape((1, n_g, n_c)),
                   status.reshape((1, n_g, n_c)))
    return True


class FramePath:
    """Buffers and constants of :func:`frame_wavelengths` for one rod and one :class:`Optics`.

    Parameters
    ----------
    rod : RodView
        The rod the optics read (the catheter's, or a fibre-in-lumen setup's own fibre rod), bound to its
        ``mjData``.
    optics : Optics
        A fibre with straight cores (``spin_rate == 0``).

    Attributes
    ----------
    frames, darboux : ndarray
        The rod's edge frames (n_edges, 3, 3) and interior Darboux vectors (n_interior, 3) of the last call
        (the view's buffers: :class:`models.rod_state.RodTruth` reads them).
    temperature : ndarray, shape (n_gratings,)
        The temperature change of the last call at each grating, K (a buffer).
    """

    def __init__(self, rod: RodView, optics: Optics) -> None:
        if optics.true_fiber.spin_rate:
            raise ValueError("FramePath: a spun fibre needs the exact path lengths (Optics.spun_wavelengths)")
        self.rod, self.optics = rod, optics
        reader = rod.reader
        n_g, n_c = optics.nominal.n_gratings, optics.nominal.n_cores
        self.average = grating_average(reader, optics)
        self.frames, self.darboux = rod.frames, rod.darboux
        (design, s_eps, s_t, offset, lam0, lam0_nominal, drift, noise, quant, slot, separation, band_lo, band_hi,
         order, lost_flag) = optics.effect_arguments()
        n_v = self.average.shape[1]
        self._buffer = np.zeros(_size(n_v, n_g, n_c))
        (scalars, average_t, design_part, s_t_part, lam0_part, nominal_part, averaged, self._axial, self._temp,
         *_) = _parts(self._buffer, n_v, n_g, n_c)
        scalars[:] = s_eps, offset, noise, quant, slot, separation, band_lo, band_hi, lost_flag
        average_t[:], design_part[:], s_t_part[:] = self.average.T, design, s_t
        lam0_part[:], nominal_part[:] = lam0, lam0_nominal
        averaged[0] = -1.0  # no average yet
        self.temperature = self._temp[0]
        self._shape = (n_g, n_c)
        self._n_z = 2 * n_g * n_c  # the normals of a frame: the drift's steps and the noise
        self._no_draw = np.zeros(self._n_z)
        self._draws = bool(optics.config.noise)
        # the arrays every call reads as they are (the views, constants and buffers), passed by address: they stay
        # where they are while this path lives (mjData's arrays, buffers allocated once; held here)
        self._held = (*rod.read_arguments(), self._buffer, np.ascontiguousarray(order, np.int64), drift)
        if self._held[8] is not drift or self._held[4].dtype != np.int32 or self._held[7].shape != self._shape:
            raise ValueError("FramePath: the optics' drift state, MuJoCo's tree_asleep or the order is not as expected")
        self._fixed = addresses(*self._held)
        # the compiled function itself, past numba's dispatcher (twin/_numba_entry.py): the arguments' types
        # below are those of every call
        self._kernel = compiled_entry(frame_wavelengths, self._fixed, False, 0.0, 0.0, 0.0, 0.0, self._no_draw, 0,
                                      np.empty(self._shape), np.zeros(self._shape, np.uint8))

    def __call__(self, data: mujoco.MjData, axial, delta_t, t: float, roll: float = 0.0
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Wavelengths (n_gratings, n_cores) nm and status (uint8) of the rod in ``data`` at time ``t`` s.

        ``data`` is the view's (:attr:`RodView.data`); ``axial`` (strain) and ``delta_t`` (K) are scalars or
        (n_gratings,) arrays; ``roll`` (rad) turns (κ1, κ2) about d3 before the strain (the fibre's glued roll
        relative to its rod's material frame)."""
        if data is not self.rod.data:
            raise ValueError("FramePath: data is not the mjData its rod view is bound to")
        # a Python float (what most setups give) is spread over the gratings in the compiled call
        if type(axial) is float and axial == axial:
            axial_value = axial
        else:
            self._axial[0], axial_value = axial, math.nan
        if type(delta_t) is float and delta_t == delta_t:
            temp_value = delta_t
        else:
            self._temp[0], temp_value = delta_t, math.nan
        # the draws of Optics.random_draw (the same numbers from the same seed), read in place from the stream
        optics = self.optics
        step = optics.drift_step(t)
        if self._draws or step:
            normals = optics.normals
            offset = normals.take(self._n_z)
            normals = normals.buffer
        else:
            normals, offset = self._no_draw, 0
        w = np.empty(self._shape)
        status = np.zeros(self._shape, np.uint8)
        roll = float(roll)
        if not self._kernel(self._fixed, False, roll, axial_value, temp_value, step, normals, offset, w, status):
            self.rod.restart()
            self._kernel(self._fixed, True, roll, axial_value, temp_value, step, normals, offset, w, status)
        return w, status
