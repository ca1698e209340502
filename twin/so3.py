"""The rotation group's exponential and logarithm, compiled (numba), for every kernel that needs them.

One implementation serves the reconstruction's SE(3) chain (:mod:`twin._kernels`) and the twin's rod-state
reader (``models._rod_kernels``): ``exp(φ̂) = I + A φ̂ + B φ̂²`` with A = sin t/t, B = (1 − cos t)/t², t = |φ|
(Rodrigues), and its inverse. Scalar functions, so that compiled loops call them without allocating; the batch
forms :func:`exp` and :func:`log` (leading axes ``...``) are for tests and numpy code.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["exp", "exp_coefficients", "exp_entries", "log", "log_entries"]


@njit(cache=True, nogil=True)
def exp_coefficients(t2):
    """A = sin t/t, B = (1 − cos t)/t², C = (t − sin t)/t³ for t² = |φ|², finite at t = 0 (docs/math.md §3.3)."""
    if t2 < 0.04:
        # Taylor series to t^8: truncation error < 2e-17 for t < 0.2.
        a = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0 * (1.0 - t2 / 72.0)))
        b = 0.5 * (1.0 - t2 / 12.0 * (1.0 - t2 / 30.0 * (1.0 - t2 / 56.0 * (1.0 - t2 / 90.0))))
        c = (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0 * (1.0 - t2 / 72.0 * (1.0 - t2 / 110.0)))) / 6.0
    else:
        t = np.sqrt(t2)
        s = np.sin(t)
        a = s / t
        b = (1.0 - np.cos(t)) / t2
        c = (t - s) / (t2 * t)
    return a, b, c


@njit(cache=True, nogil=True)
def exp_entries(wx, wy, wz):
    """exp of the rotation vector (wx, wy, wz) (rad) as its nine entries, row-major (e00, e01, …, e22)."""
    a, b, _ = exp_coefficients(wx * wx + wy * wy + wz * wz)
    return (1.0 - b * (wy * wy + wz * wz), -a * wz + b * wx * wy, a * wy + b * wx * wz,
            a * wz + b * wx * wy, 1.0 - b * (wx * wx + wz * wz), -a * wx + b * wy * wz,
            -a * wy + b * wx * wz, a * wx + b * wy * wz, 1.0 - b * (wx * wx + wy * wy))


@njit(cache=True, nogil=True)
def log_entries(q00, q01, q02, q10, q11, q12, q20, q21, q22):
    """The rotation vector (rad) of the rotation matrix with these entries; exact for angles below π − 1e-6.

    Uses the antisymmetric part and the trace (φ = atan2(sin φ, cos φ), well conditioned at small angles).
    """
    w0 = q21 - q12
    w1 = q02 - q20
    w2 = q10 - q01
    sin2 = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)  # 2 sin φ
    phi = np.arctan2(0.5 * sin2, 0.5 * (q00 + q11 + q22 - 1.0))
    f = phi / sin2 if sin2 > 1e-6 else 0.5 + phi * phi / 12.0
    return w0 * f, w1 * f, w2 * f


@njit(cache=True)
def _exp_batch(phi, out):
    for i in range(phi.shape[0]):
        e = exp_entries(phi[i, 0], phi[i, 1], phi[i, 2])
        for k in range(9):
            out[i, k // 3, k % 3] = e[k]


@njit(cache=True)
def _log_batch(r, out):
    for i in range(r.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = log_entries(r[i, 0, 0], r[i, 0, 1], r[i, 0, 2], r[i, 1, 0], r[i, 1, 1],
                                                      r[i, 1, 2], r[i, 2, 0], r[i, 2, 1], r[i, 2, 2])


def exp(rotvec) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3), rad."""
    phi = np.asarray(rotvec, dtype=np.float64)
    flat = np.ascontiguousarray(phi.reshape(-1, 3))
    out = np.empty((flat.shape[0], 3, 3))
    _exp_batch(flat, out)
    return out.reshape(*phi.shape[:-1], 3, 3)


def log(matrices) -> np.ndarray:
    """Rotation vectors (..., 3), rad, of rotation matrices (..., 3, 3) with angles below π."""
    r = np.asarray(matrices, dtype=np.float64)
    flat = np.ascontiguousarray(r.reshape(-1, 3, 3))
    out = np.empty((flat.shape[0], 3))
    _log_batch(flat, out)
    return out.reshape(*r.shape[:-2], 3)
