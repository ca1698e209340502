"""The rotation group's exponential and logarithm, compiled (numba), for every kernel that needs them.

One implementation serves the reconstruction's SE(3) chain (:mod:`twin._kernels`) and the twin's rod-state
reader (``models._rod_kernels``): ``exp(φ̂) = I + A φ̂ + B φ̂²`` with A = sin t/t, B = (1 − cos t)/t², t = |φ|
(Rodrigues), and its inverse. Scalar functions, so that compiled loops call them without allocating; the batch
forms :func:`exp` and :func:`log` (leading axes ``...``) are for tests and numpy code.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from twin import _jit_cache  # noqa: F401  (before the first cached kernel; see its docstring)

__all__ = ["exp", "exp_coefficients", "exp_entries", "from_quaternion", "log", "log_entries", "to_quaternion"]

# the Taylor series' divisors as reciprocals (numba reads module floats as constants)
_R6, _R12, _R20, _R30, _R42, _R56, _R72, _R90, _R110 = (1.0 / d for d in (6, 12, 20, 30, 42, 56, 72, 90, 110))


@njit(cache=True, nogil=True)
def exp_coefficients(t2):
    """A = sin t/t, B = (1 − cos t)/t², C = (t − sin t)/t³ for t² = |φ|², finite at t = 0 (docs/math.md §3.3)."""
    if t2 < 0.04:
        # Taylor series to t^8: truncation error < 2e-17 for t < 0.2.
        # multiplications by the reciprocals, not divisions: a division costs several multiplications' time
        # (the chain runs this every step) and the reciprocals' rounding (≤ 1 ulp) is far below the truncation
        a = 1.0 - t2 * _R6 * (1.0 - t2 * _R20 * (1.0 - t2 * _R42 * (1.0 - t2 * _R72)))
        b = 0.5 * (1.0 - t2 * _R12 * (1.0 - t2 * _R30 * (1.0 - t2 * _R56 * (1.0 - t2 * _R90))))
        c = (1.0 - t2 * _R20 * (1.0 - t2 * _R42 * (1.0 - t2 * _R72 * (1.0 - t2 * _R110)))) * _R6
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


def to_quaternion(matrices) -> np.ndarray:
    """Unit quaternions (..., 4), scalar last (x, y, z, w) as ROS writes them, of rotation matrices (..., 3, 3).

    Shepperd's method: each quaternion comes from the largest of 1 + trace and the 1 + 2 R_ii − trace, so no
    division by a small number; w ≥ 0 (q and −q are the same rotation). Each of the four cases is computed on
    the matrices that take it only (a few array operations per case, whatever the batch).
    """
    r = np.asarray(matrices, dtype=np.float64)
    flat = r.reshape(-1, 3, 3)
    d = np.einsum("nii->ni", flat)
    t = np.stack([1 + d.sum(axis=1), 1 + d[:, 0] - d[:, 1] - d[:, 2], 1 - d[:, 0] + d[:, 1] - d[:, 2],
                  1 - d[:, 0] - d[:, 1] + d[:, 2]], axis=1)
    case = np.argmax(t, axis=1)
    q = np.empty((len(flat), 4))
    # (component filled by the largest term, then the three from sums/differences of off-diagonal pairs)
    pairs = {0: ((3, (2, 1), (1, 2), -1), (0, (2, 1), (1, 2), -1), (1, (0, 2), (2, 0), -1), (2, (1, 0), (0, 1), -1)),
             1: ((0, (0, 0), (0, 0), 0), (1, (0, 1), (1, 0), 1), (2, (0, 2), (2, 0), 1), (3, (2, 1), (1, 2), -1)),
             2: ((1, (0, 0), (0, 0), 0), (0, (0, 1), (1, 0), 1), (2, (1, 2), (2, 1), 1), (3, (0, 2), (2, 0), -1)),
             3: ((2, (0, 0), (0, 0), 0), (0, (0, 2), (2, 0), 1), (1, (1, 2), (2, 1), 1), (3, (1, 0), (0, 1), -1))}
    for k, terms in pairs.items():
        sel = np.flatnonzero(case == k)
        if not sel.size:
            continue
        m, tk = flat[sel], t[sel, k]
        half = 0.5 / np.sqrt(tk)
        main, *rest = terms
        q[sel, main[0]] = tk * half
        for comp, (i, j), (u, v), sign in rest:
            q[sel, comp] = (m[:, i, j] + sign * m[:, u, v]) * half
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q.reshape(*r.shape[:-2], 4)


def from_quaternion(quaternions) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4), scalar last (x, y, z, w); normalised first."""
    q = np.asarray(quaternions, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)
