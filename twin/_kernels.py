"""Compiled SE(3) chaining kernels (numba). The only loops over integration steps live here.

Both kernels integrate Y' = Y·Â(s) on SE(3) with Y = [[R, p], [0, 1]] and Â = [[û, e_T], [0, 0]]: R' = R û and
p' = R e_T, with u the angular rate in the body frame and e_T the body axis that is the tangent. Rates come as
an array ``rates`` of shape (F, C, n_steps, m): m samples per step, C components, read as

* material frame (``frenet`` False): rates = (k_x, k_y[, γ]) and u = (−k_y, k_x, γ), e_T = e3;
* Frenet frame (``frenet`` True): rates = (τ, κ) and u = (τ, 0, κ), e_T = e1.

Frames start at ``r0`` (one per curve) and positions at the origin.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from twin import _jit_cache  # noqa: F401  (before the first cached kernel; see its docstring)
from twin.so3 import exp_coefficients

_SQRT3_12 = np.sqrt(3.0) / 12.0


@njit(cache=True, nogil=True)
def _rate(rates, j, i, frenet):
    """Body angular rate u at sample i of step j of one curve's rates (C, n, m)."""
    a = rates[0, j, i]
    b = rates[1, j, i]
    if frenet:
        return a, 0.0, b
    g = rates[2, j, i] if rates.shape[0] > 2 else 0.0
    return -b, a, g


@njit(cache=True, nogil=True, inline="always")
def _compose(r00, r01, r02, r10, r11, r12, r20, r21, r22, e00, e01, e02, e10, e11, e12, e20, e21, e22):
    """The entries of R E (row-major) from those of R and E."""
    return (r00 * e00 + r01 * e10 + r02 * e20, r00 * e01 + r01 * e11 + r02 * e21, r00 * e02 + r01 * e12 + r02 * e22,
            r10 * e00 + r11 * e10 + r12 * e20, r10 * e01 + r11 * e11 + r12 * e21, r10 * e02 + r11 * e12 + r12 * e22,
            r20 * e00 + r21 * e10 + r22 * e20, r20 * e01 + r21 * e11 + r22 * e21, r20 * e02 + r21 * e12 + r22 * e22)


@njit(cache=True, nogil=True, inline="always")
def _store(frame, r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """``frame`` (3, 3) = the entries given (row-major)."""
    frame[0, 0] = r00
    frame[0, 1] = r01
    frame[0, 2] = r02
    frame[1, 0] = r10
    frame[1, 1] = r11
    frame[1, 2] = r12
    frame[2, 0] = r20
    frame[2, 1] = r21
    frame[2, 2] = r22


@njit(cache=True, nogil=True)
def exp_chain(rates, frenet, h, r0, pos, frames):
    """Chain exponential steps: Magnus-4 with 2 samples per step (Gauss points), the exponential Euler (HEM) with 1.

    Parameters
    ----------
    rates : (F, C, n, m) rates at the samples of each step: m = 2 Gauss points (Magnus-4) or m = 1 (HEM).
    frenet : bool, see the module docstring.
    h : step length.
    r0 : (F, 3, 3) initial frames.
    pos : (F, n + 1, 3) output positions.
    frames : (F, n + 1, 3, 3) output frames.

    Per step (docs/math.md §3.5): φ = h/2 (u1 + u2) + √3h²/12 (u1 × u2), ρ = h e_T + √3h²/12 (u1 − u2) × e_T,
    R⁺ = R exp(φ̂), p⁺ = p + R V(φ) ρ with V = I + B φ̂ + C φ̂².
    """
    for f in range(rates.shape[0]):
        exp_curve(rates[f], frenet, h, r0[f], pos[f], frames[f], True)


@njit(cache=True, nogil=True)
def exp_curve(rates, frenet, h, r0, pos, frames, store_frames):
    """:func:`exp_chain` for one curve: rates (C, n, m), r0 (3, 3), pos (n + 1, 3), frames (n + 1, 3, 3) written
    only when ``store_frames`` (else any array, untouched)."""
    _, n, m = rates.shape
    c = _SQRT3_12 * h * h
    t0 = 1.0 if frenet else 0.0
    t2_ = 0.0 if frenet else 1.0
    r00, r01, r02 = r0[0, 0], r0[0, 1], r0[0, 2]
    r10, r11, r12 = r0[1, 0], r0[1, 1], r0[1, 2]
    r20, r21, r22 = r0[2, 0], r0[2, 1], r0[2, 2]
    px = 0.0
    py = 0.0
    pz = 0.0
    pos[0, 0] = 0.0
    pos[0, 1] = 0.0
    pos[0, 2] = 0.0
    if store_frames:
        for i in range(3):
            for j in range(3):
                frames[0, i, j] = r0[i, j]
    for j in range(n):
        a0, a1, a2 = _rate(rates, j, 0, frenet)
        b0, b1, b2 = _rate(rates, j, m - 1, frenet)
        x0 = 0.5 * h * (a0 + b0) + c * (a1 * b2 - a2 * b1)
        x1 = 0.5 * h * (a1 + b1) + c * (a2 * b0 - a0 * b2)
        x2 = 0.5 * h * (a2 + b2) + c * (a0 * b1 - a1 * b0)
        d0, d1, d2 = c * (a0 - b0), c * (a1 - b1), c * (a2 - b2)
        # ρ = h e_T + d × e_T, with e_T = (t0, 0, t2_)
        q0 = h * t0 + d1 * t2_
        q1 = d2 * t0 - d0 * t2_
        q2 = h * t2_ - d1 * t0
        aa, bb, cc = exp_coefficients(x0 * x0 + x1 * x1 + x2 * x2)
        # E = exp(φ̂) = I + A φ̂ + B φ̂²
        e00 = 1.0 - bb * (x1 * x1 + x2 * x2)
        e11 = 1.0 - bb * (x0 * x0 + x2 * x2)
        e22 = 1.0 - bb * (x0 * x0 + x1 * x1)
        e01 = -aa * x2 + bb * x0 * x1
        e10 = aa * x2 + bb * x0 * x1
        e02 = aa * x1 + bb * x0 * x2
        e20 = -aa * x1 + bb * x0 * x2
        e12 = -aa * x0 + bb * x1 * x2
        e21 = aa * x0 + bb * x1 * x2
        # v = V(φ) ρ = ρ + B φ×ρ + C φ×(φ×ρ)
        w0 = x1 * q2 - x2 * q1
        w1 = x2 * q0 - x0 * q2
        w2 = x0 * q1 - x1 * q0
        v0 = q0 + bb * w0 + cc * (x1 * w2 - x2 * w1)
        v1 = q1 + bb * w1 + cc * (x2 * w0 - x0 * w2)
        v2 = q2 + bb * w2 + cc * (x0 * w1 - x1 * w0)
        px += r00 * v0 + r01 * v1 + r02 * v2
        py += r10 * v0 + r11 * v1 + r12 * v2
        pz += r20 * v0 + r21 * v1 + r22 * v2
        n00, n01, n02, n10, n11, n12, n20, n21, n22 = _compose(r00, r01, r02, r10, r11, r12, r20, r21, r22,
                                                               e00, e01, e02, e10, e11, e12, e20, e21, e22)
        r00, r01, r02 = n00, n01, n02
        r10, r11, r12 = n10, n11, n12
        r20, r21, r22 = n20, n21, n22
        pos[j + 1, 0] = px
        pos[j + 1, 1] = py
        pos[j + 1, 2] = pz
        if store_frames:
            _store(frames[j + 1], r00, r01, r02, r10, r11, r12, r20, r21, r22)


@njit(cache=True, nogil=True)
def _hat_mul(r, u, out):
    """out = R û."""
    for i in range(3):
        out[i, 0] = r[i, 1] * u[2] - r[i, 2] * u[1]
        out[i, 1] = r[i, 2] * u[0] - r[i, 0] * u[2]
        out[i, 2] = r[i, 0] * u[1] - r[i, 1] * u[0]


@njit(cache=True, nogil=True)
def _rate_vec(rates, j, i, frenet, out):
    a, b, c = _rate(rates, j, i, frenet)
    out[0] = a
    out[1] = b
    out[2] = c
    return out


@njit(cache=True, nogil=True)
def rk4_chain(rates, frenet, h, r0, pos, frames):
    """Classical RK4 on R' = R û, p' = R e_T with u sampled at the start, middle and end of each step (m = 3).

    The frame is not re-orthonormalised (the drift is part of what the method comparison shows).
    Arrays as :func:`exp_chain`.
    """
    for f in range(rates.shape[0]):
        rk4_curve(rates[f], frenet, h, r0[f], pos[f], frames[f], True)


@njit(cache=True, nogil=True)
def rk4_curve(rates, frenet, h, r0, pos, frames, store_frames):
    """:func:`rk4_chain` for one curve; arrays as :func:`exp_curve`."""
    _, n, _ = rates.shape
    tangent_axis = 0 if frenet else 2
    ul = np.empty(3)
    um = np.empty(3)
    ur = np.empty(3)
    r = np.empty((3, 3))
    k1 = np.empty((3, 3))
    k2 = np.empty((3, 3))
    k3 = np.empty((3, 3))
    k4 = np.empty((3, 3))
    tmp = np.empty((3, 3))
    p = np.zeros(3)
    for i in range(3):
        for j in range(3):
            r[i, j] = r0[i, j]
            if store_frames:
                frames[0, i, j] = r[i, j]
        pos[0, i] = 0.0
    for j in range(n):
        _rate_vec(rates, j, 0, frenet, ul)
        _rate_vec(rates, j, 1, frenet, um)
        _rate_vec(rates, j, 2, frenet, ur)
        _hat_mul(r, ul, k1)
        for a in range(3):
            for b in range(3):
                tmp[a, b] = r[a, b] + 0.5 * h * k1[a, b]
        p2 = tmp[:, tangent_axis].copy()
        _hat_mul(tmp, um, k2)
        for a in range(3):
            for b in range(3):
                tmp[a, b] = r[a, b] + 0.5 * h * k2[a, b]
        p3 = tmp[:, tangent_axis].copy()
        _hat_mul(tmp, um, k3)
        for a in range(3):
            for b in range(3):
                tmp[a, b] = r[a, b] + h * k3[a, b]
        p4 = tmp[:, tangent_axis].copy()
        _hat_mul(tmp, ur, k4)
        for a in range(3):
            p[a] += h / 6.0 * (r[a, tangent_axis] + 2.0 * p2[a] + 2.0 * p3[a] + p4[a])
            for b in range(3):
                r[a, b] += h / 6.0 * (k1[a, b] + 2.0 * k2[a, b] + 2.0 * k3[a, b] + k4[a, b])
        for a in range(3):
            pos[j + 1, a] = p[a]
            if store_frames:
                for b in range(3):
                    frames[j + 1, a, b] = r[a, b]


#: the curves :func:`exp_lanes` chains at once and the steps :func:`exp_material` prepares at once (the SIMD
#: loops' trip count, a constant the compiler sees)
LANES = 8
#: the largest |φ|² of a step that the series of the SIMD loops takes (the Taylor branch of
#: :func:`twin.so3.exp_coefficients`, truncation < 2e-17)
LANES_T2_MAX = 0.04
_R6, _R12, _R20, _R30, _R42, _R56, _R72, _R90, _R110 = (1.0 / d for d in (6, 12, 20, 30, 42, 56, 72, 90, 110))
# rows of a work chunk (each LANES long; offsets are constants, so the compiler sees the rows apart): the rates
# (k_x, k_y) at the step's first and last sample 0–3, E = exp(φ̂) row-major 4–12, v = V(φ)ρ 13–15, a flag 16 (1:
# a step beyond the series' range), then for exp_lanes the state R row-major 17–25 and p 26–28
_W_E = 4 * LANES
_W_V = 13 * LANES
_W_FLAG = 16 * LANES
_W_R = 17 * LANES
_W_P = 26 * LANES
_W_STEP = 17 * LANES
_W_LANES = 29 * LANES


@njit(cache=True, nogil=True, fastmath={"contract"})
def _increments(w, h):
    """E = exp(φ̂) and v = V(φ)ρ of the LANES steps in the work chunk ``w`` (material frame, e_T =
    e3, u = (−k_y, k_x, 0)); the flag row is set where |φ|² ≥ LANES_T2_MAX (or NaN). Branch- and call-free."""
    c = _SQRT3_12 * h * h
    hh = 0.5 * h
    for i in range(LANES):
        a0 = -w[LANES + i]
        a1 = w[i]
        b0 = -w[3 * LANES + i]
        b1 = w[2 * LANES + i]
        x0 = hh * (a0 + b0)
        x1 = hh * (a1 + b1)
        x2 = c * (a0 * b1 - a1 * b0)
        q0 = c * (a1 - b1)  # ρ = h e_T + d × e_T, d = c (u_a − u_b)
        q1 = -(c * (a0 - b0))
        q2 = h
        t2 = x0 * x0 + x1 * x1 + x2 * x2
        w[_W_FLAG + i] = 0.0 if t2 < LANES_T2_MAX else 1.0
        # exp_coefficients' series, the same expressions
        aa = 1.0 - t2 * _R6 * (1.0 - t2 * _R20 * (1.0 - t2 * _R42 * (1.0 - t2 * _R72)))
        bb = 0.5 * (1.0 - t2 * _R12 * (1.0 - t2 * _R30 * (1.0 - t2 * _R56 * (1.0 - t2 * _R90))))
        cc = (1.0 - t2 * _R20 * (1.0 - t2 * _R42 * (1.0 - t2 * _R72 * (1.0 - t2 * _R110)))) * _R6
        w[_W_E + i] = 1.0 - bb * (x1 * x1 + x2 * x2)
        w[_W_E + LANES + i] = -aa * x2 + bb * x0 * x1
        w[_W_E + 2 * LANES + i] = aa * x1 + bb * x0 * x2
        w[_W_E + 3 * LANES + i] = aa * x2 + bb * x0 * x1
        w[_W_E + 4 * LANES + i] = 1.0 - bb * (x0 * x0 + x2 * x2)
        w[_W_E + 5 * LANES + i] = -aa * x0 + bb * x1 * x2
        w[_W_E + 6 * LANES + i] = -aa * x1 + bb * x0 * x2
        w[_W_E + 7 * LANES + i] = aa * x0 + bb * x1 * x2
        w[_W_E + 8 * LANES + i] = 1.0 - bb * (x0 * x0 + x1 * x1)
        w0 = x1 * q2 - x2 * q1
        w1 = x2 * q0 - x0 * q2
        w2 = x0 * q1 - x1 * q0
        w[_W_V + i] = q0 + bb * w0 + cc * (x1 * w2 - x2 * w1)
        w[_W_V + LANES + i] = q1 + bb * w1 + cc * (x2 * w0 - x0 * w2)
        w[_W_V + 2 * LANES + i] = q2 + bb * w2 + cc * (x0 * w1 - x1 * w0)


@njit(cache=True, nogil=True, inline="always")
def _increment(w, i):
    """E (row-major) and v of column ``i`` of the work chunk ``w`` (:func:`_increments`' output)."""
    return (w[_W_E + i], w[_W_E + LANES + i], w[_W_E + 2 * LANES + i], w[_W_E + 3 * LANES + i],
            w[_W_E + 4 * LANES + i], w[_W_E + 5 * LANES + i], w[_W_E + 6 * LANES + i], w[_W_E + 7 * LANES + i],
            w[_W_E + 8 * LANES + i], w[_W_V + i], w[_W_V + LANES + i], w[_W_V + 2 * LANES + i])


@njit(cache=True, nogil=True, fastmath={"contract"})
def _lanes_update(w):
    """R⁺ = R E, p⁺ = p + R v for the LANES lanes of :func:`exp_lanes`' work array ``w``, in place."""
    for i in range(LANES):
        e00, e01, e02, e10, e11, e12, e20, e21, e22, v0, v1, v2 = _increment(w, i)
        for r in range(3):
            r0 = w[_W_R + 3 * r * LANES + i]
            r1 = w[_W_R + (3 * r + 1) * LANES + i]
            r2 = w[_W_R + (3 * r + 2) * LANES + i]
            w[_W_P + r * LANES + i] += r0 * v0 + r1 * v1 + r2 * v2
            w[_W_R + 3 * r * LANES + i] = r0 * e00 + r1 * e10 + r2 * e20
            w[_W_R + (3 * r + 1) * LANES + i] = r0 * e01 + r1 * e11 + r2 * e21
            w[_W_R + (3 * r + 2) * LANES + i] = r0 * e02 + r1 * e12 + r2 * e22


@njit(cache=True, nogil=True)
def exp_lanes(rt, h, m, which, pos, frames, store_frames, ok):
    """:func:`exp_curve` (material frame, rates (k_x, k_y), r0 = I) of up to :data:`LANES` curves at once.

    The curves are the lanes of the innermost loops (:func:`_increments`, :func:`_lanes_update`), free of
    branches and calls, over one work array with constant offsets, so that the compiler runs them on SIMD
    registers. The exponential's coefficients come from ``exp_coefficients``' series, valid for |φ|² <
    :data:`LANES_T2_MAX`: a lane with a longer step (or a NaN) is flagged ``ok`` False and its outputs are to
    be redone by :func:`exp_curve`. Otherwise the results are :func:`exp_curve`'s up to rounding (fused
    multiply-adds; the terms of the absent twist rate are left out).

    Parameters
    ----------
    rt : (n · m, 2L) rates, row = sample (step-major), columns = k_x of the L ≤ LANES lanes, then their k_y, 1/m.
    h : step, m.  m : samples per step (2: Magnus-4, 1: HEM).
    which : (L,) the index of each lane's curve in ``pos`` and ``frames``.
    pos : (F, n + 1, 3), frames : (F, n + 1, 3, 3) (written only when ``store_frames``): outputs.
    ok : (L,) bool, out: whether the lane's outputs are final.
    """
    n_lanes = which.size
    n = rt.shape[0] // m
    w = np.zeros(_W_LANES)  # lanes beyond n_lanes chain zero rates, never read
    for i in range(LANES):
        w[_W_R + i] = 1.0
        w[_W_R + 4 * LANES + i] = 1.0
        w[_W_R + 8 * LANES + i] = 1.0
        ok[i] = True
    for i in range(n_lanes):
        f = which[i]
        pos[f, 0, :] = 0.0
        if store_frames:
            frames[f, 0] = 0.0
            frames[f, 0, 0, 0] = 1.0
            frames[f, 0, 1, 1] = 1.0
            frames[f, 0, 2, 2] = 1.0
    for j in range(n):
        ra = rt[j * m]
        rb = rt[j * m + m - 1]
        for i in range(n_lanes):
            w[i] = ra[i]
            w[LANES + i] = ra[n_lanes + i]
            w[2 * LANES + i] = rb[i]
            w[3 * LANES + i] = rb[n_lanes + i]
        _increments(w, h)
        _lanes_update(w)
        for i in range(n_lanes):
            if w[_W_FLAG + i] != 0.0:
                ok[i] = False
            f = which[i]
            pos[f, j + 1, 0] = w[_W_P + i]
            pos[f, j + 1, 1] = w[_W_P + LANES + i]
            pos[f, j + 1, 2] = w[_W_P + 2 * LANES + i]
        if store_frames:
            for i in range(n_lanes):
                f = which[i]
                frames[f, j + 1, 0, 0] = w[_W_R + i]
                frames[f, j + 1, 0, 1] = w[_W_R + LANES + i]
                frames[f, j + 1, 0, 2] = w[_W_R + 2 * LANES + i]
                frames[f, j + 1, 1, 0] = w[_W_R + 3 * LANES + i]
                frames[f, j + 1, 1, 1] = w[_W_R + 4 * LANES + i]
                frames[f, j + 1, 1, 2] = w[_W_R + 5 * LANES + i]
                frames[f, j + 1, 2, 0] = w[_W_R + 6 * LANES + i]
                frames[f, j + 1, 2, 1] = w[_W_R + 7 * LANES + i]
                frames[f, j + 1, 2, 2] = w[_W_R + 8 * LANES + i]


@njit(cache=True, nogil=True, fastmath={"contract"})
def exp_material(rates, h, pos, frames, store_frames):
    """:func:`exp_curve` for one curve in the material frame without twist (rates (2, n, m) = (k_x, k_y), r0 = I),
    in two passes: every step's E = exp(φ̂) and v = V(φ)ρ, LANES steps at a time (:func:`_increments`,
    independent of the state: SIMD over the steps), then the chain R⁺ = R E, p⁺ = p + R v. The results are
    :func:`exp_curve`'s up to rounding; a curve with a step beyond the series' range is :func:`exp_curve`'s."""
    _, n, m = rates.shape
    n_chunks = (n + LANES - 1) // LANES
    w = np.zeros(n_chunks * _W_STEP)
    for j in range(n):
        o = (j // LANES) * _W_STEP + j % LANES
        w[o] = rates[0, j, 0]
        w[o + LANES] = rates[1, j, 0]
        w[o + 2 * LANES] = rates[0, j, m - 1]
        w[o + 3 * LANES] = rates[1, j, m - 1]
    beyond = 0.0
    for b in range(n_chunks):
        _increments(w[b * _W_STEP:(b + 1) * _W_STEP], h)
        for i in range(LANES):
            beyond += w[b * _W_STEP + _W_FLAG + i]
    if beyond != 0.0:
        exp_curve(rates, False, h, np.eye(3), pos, frames, store_frames)
        return
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
    px, py, pz = 0.0, 0.0, 0.0
    pos[0] = 0.0
    if store_frames:
        frames[0] = 0.0
        frames[0, 0, 0] = 1.0
        frames[0, 1, 1] = 1.0
        frames[0, 2, 2] = 1.0
    for j in range(n):
        wb = w[(j // LANES) * _W_STEP:]
        e00, e01, e02, e10, e11, e12, e20, e21, e22, v0, v1, v2 = _increment(wb, j % LANES)
        px += r00 * v0 + r01 * v1 + r02 * v2
        py += r10 * v0 + r11 * v1 + r12 * v2
        pz += r20 * v0 + r21 * v1 + r22 * v2
        n00, n01, n02, n10, n11, n12, n20, n21, n22 = _compose(r00, r01, r02, r10, r11, r12, r20, r21, r22,
                                                               e00, e01, e02, e10, e11, e12, e20, e21, e22)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = n00, n01, n02, n10, n11, n12, n20, n21, n22
        pos[j + 1, 0] = px
        pos[j + 1, 1] = py
        pos[j + 1, 2] = pz
        if store_frames:
            _store(frames[j + 1], r00, r01, r02, r10, r11, r12, r20, r21, r22)
