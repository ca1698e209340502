"""The fused reconstruction kernel (numba): wavelengths or strain → curvature at the gratings → samples → chain.

One compiled call does, per frame, what :class:`twin.reconstruct.Reconstructor`'s general path does in a dozen
numpy calls: the optical strain and the physical window, the curvature inversion at every grating (the
precomputed pseudo-inverse when every core is present; the weighted normal equations of the remaining cores, with
the same conditioning test, when some are missing), the linear interpolation of (k_x, k_y) to the integrator's
samples, and the chain (:mod:`twin._kernels`). Outputs are preallocated by the caller; nothing is allocated per
frame. A frame that lost a grating needs another interpolation operator (one per pattern of valid gratings); the
kernel counts it and leaves its positions to :func:`integrate`, called with the operators of those patterns.

Everything constant for a reconstructor — the reference wavelengths, the window, the solver
(:meth:`twin.strain.CurvatureSolver.fused_operator`), the interpolation operator, the step — travels as one flat
array made by :func:`pack`: numba checks the type of every argument on every call (~0.15 µs an array), which
for a single frame is a measurable share of the whole reconstruction.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from twin import _jit_cache  # noqa: F401  (before the first cached kernel; see its docstring)
from twin._kernels import LANES, exp_curve, exp_lanes, exp_material, rk4_curve

__all__ = ["integrate", "pack", "reconstruct"]

_HEADER = 8  # window, h, rcond, m, rk4, paper, n_q, n_seg
#: frames interpolated by one matrix product in :func:`reconstruct`
BLOCK = 32


def pack(lam0, window, solver, basis, m, h, rk4, pieces=None) -> np.ndarray:
    """The constants of :func:`reconstruct` as one float64 array: ``lam0`` (n_g, n_c) nm, ``window`` (|e| bound,
    0: none), ``solver`` = (p, ds, weights, scale, needed, rcond, paper) from ``fused_operator``, ``basis``
    (n_g, n_steps · m), ``m`` samples per step, ``h`` step (m), ``rk4``, and ``pieces`` the same operator as
    polynomials per grating interval (:func:`twin.curve.piecewise`: segment, t, coef) or None."""
    p, ds, weights, scale, needed, rcond, paper = solver
    n_seg = 0 if pieces is None else pieces[2].shape[0]
    header = np.array([window, h, rcond, m, float(rk4), float(paper), basis.shape[1], n_seg])
    parts = [lam0, p, ds, weights, scale, needed, basis]
    if pieces is not None:
        segment, t, coef = pieces
        parts += [segment, t, np.transpose(coef, (2, 0, 1))]  # (n_g, n_seg, 4): grating-major
    return np.concatenate([header, *(np.asarray(a, dtype=np.float64).ravel() for a in parts)])


@njit(cache=True, nogil=True)
def _unpack(const, n_g, n_c):
    """The views of :func:`pack`'s array (the pieces empty when there are none)."""
    n_q = int(const[6])
    n_seg = int(const[7])
    o = _HEADER
    lam0 = const[o:o + n_g * n_c].reshape((n_g, n_c))
    o += n_g * n_c
    p = const[o:o + n_g * 2 * n_c].reshape((n_g, 2, n_c))
    o += n_g * 2 * n_c
    ds = const[o:o + n_g * n_c * 3].reshape((n_g, n_c, 3))
    o += n_g * n_c * 3
    weights = const[o:o + n_g * n_c].reshape((n_g, n_c))
    o += n_g * n_c
    scale = const[o:o + 3]
    o += 3
    needed = const[o:o + n_c]
    o += n_c
    basis = const[o:o + n_g * n_q].reshape((n_g, n_q))
    o += n_g * n_q
    segment = const[o:o + n_q * (n_seg > 0)]
    o += segment.size
    t = const[o:o + n_q * (n_seg > 0)]
    o += t.size
    coef = const[o:o + n_seg * 4 * n_g].reshape((n_g, n_seg * 4))
    return lam0, p, ds, weights, scale, needed, basis, segment, t, coef


@njit(cache=True, nogil=True)
def _solve_frame(e, p, ds, weights, scale, needed, rcond, paper, k, valid):
    """Curvature (k_x, k_y) at every grating of one frame from its strain ``e`` (n_g, n_c), NaN or ±inf = missing,
    into ``k`` (n_g, 2) and ``valid`` (n_g,). Returns the number of valid gratings."""
    n_g, n_c = e.shape
    n_valid = 0
    for n in range(n_g):
        complete = True
        for c in range(n_c):
            if not np.isfinite(e[n, c]):
                complete = False
                break
        if complete:
            kx = 0.0
            ky = 0.0
            for c in range(n_c):
                kx += p[n, 0, c] * e[n, c]
                ky += p[n, 1, c] * e[n, c]
            ok = True
        elif paper:
            # eqs. 5–7 need every core they use; the others do not enter
            ok = True
            kx = 0.0
            ky = 0.0
            for c in range(n_c):
                if not np.isfinite(e[n, c]):
                    if needed[c] != 0.0:
                        ok = False
                else:
                    kx += p[n, 0, c] * e[n, c]
                    ky += p[n, 1, c] * e[n, c]
        else:
            # weighted least squares on the cores left, columns scaled to O(1) (CurvatureSolver)
            normal = np.zeros((3, 3))
            rhs = np.zeros((3, 1))
            for c in range(n_c):
                if np.isfinite(e[n, c]):
                    for a in range(3):
                        wa = ds[n, c, a] * weights[n, c]
                        rhs[a, 0] += wa * e[n, c]
                        for b in range(3):
                            normal[a, b] += wa * ds[n, c, b]
            ev = np.linalg.eigvalsh(normal)
            ok = ev[0] / max(ev[2], 1e-300) >= rcond
            kx = np.nan
            ky = np.nan
            if ok:
                x = np.linalg.solve(normal, rhs)
                kx = x[1, 0] * scale[1]
                ky = x[2, 0] * scale[2]
        if ok:
            k[n, 0] = kx
            k[n, 1] = ky
            valid[n] = True
            n_valid += 1
        else:
            k[n, 0] = np.nan
            k[n, 1] = np.nan
            valid[n] = False
    return n_valid


@njit(cache=True, nogil=True)
def _chain(k, valid, basis, rates, r0, h, rk4, pos, frames, store_frames):
    """Interpolate one frame's valid (k_x, k_y) to the samples (``basis`` (n_g, n_steps · m), zero on the
    gratings left out) into ``rates`` (2, n_steps, m), then chain it from ``r0`` (the identity)."""
    n_g, n_q = basis.shape
    rx = rates[0].reshape(n_q)
    ry = rates[1].reshape(n_q)
    rx[:] = 0.0
    ry[:] = 0.0
    # grating by grating, so that the inner loop runs along the samples (vectorised); each sample still sums
    # its gratings in order
    for n in range(n_g):
        if valid[n]:
            kx = k[n, 0]
            ky = k[n, 1]
            b = basis[n]
            for q in range(n_q):
                rx[q] += b[q] * kx
                ry[q] += b[q] * ky
    if rk4:
        rk4_curve(rates, False, h, r0, pos, frames, store_frames)
    else:
        exp_material(rates, h, pos, frames, store_frames)


@njit(cache=True, nogil=True)
def reconstruct(x, const, is_wavelength, k, valid, pos, frames, store_frames):
    """The fused path over a batch.

    Parameters
    ----------
    x : (F, n_g, n_c) wavelengths, nm (``is_wavelength``), or optical strain with NaN for missing peaks.
    const : :func:`pack`'s array: the reference wavelengths (used for wavelengths only), the physical window
        |e| ≤ window (a peak beyond it is missing; 0: none), the solver, the interpolation operator of the full
        set of gratings (n_g, n_steps · m; columns = samples in step order), m samples per step, the step h (m),
        and RK4 (m = 3) instead of the exponential chain.
    k : (F, n_g, 2), valid : (F, n_g), pos : (F, n_steps + 1, 3), frames : (F, n_steps + 1, 3, 3) or (1, 1, 3, 3)
        when not ``store_frames``: outputs.

    Returns
    -------
    int
        The number of frames pending — frames that lost a grating: ``k`` and ``valid`` filled, the positions
        left to :func:`integrate` — or −1 when a wavelength is ±inf (outputs then incomplete).
    """
    n_f, n_g, n_c = x.shape
    window, h, rcond = const[0], const[1], const[2]
    m, rk4, paper = int(const[3]), const[4] != 0.0, const[5] != 0.0
    lam0, p, ds, weights, scale, needed, basis, segment, tq, coef = _unpack(const, n_g, n_c)
    n_steps = pos.shape[1] - 1
    n_q = n_steps * m
    e = np.empty((n_g, n_c))
    r0 = np.eye(3)
    # complete frames are interpolated BLOCK at a time, as one matrix product of their (k_x, k_y) rows with the
    # operator, then chained one by one
    block = min(BLOCK, n_f)
    kt = np.empty((2 * block, n_g))
    rates = np.empty((2 * block, n_q))
    which = np.empty(block, np.int64)
    filled = 0
    n_pending = 0
    for f in range(n_f):
        if is_wavelength:
            for n in range(n_g):
                for c in range(n_c):
                    w = x[f, n, c]
                    if np.isinf(w):
                        return -1
                    v = (w - lam0[n, c]) / lam0[n, c]
                    if window > 0 and abs(v) > window:
                        v = np.nan  # outside the physical window: missing
                    e[n, c] = v
            n_valid = _solve_frame(e, p, ds, weights, scale, needed, rcond, paper, k[f], valid[f])
        else:
            n_valid = _solve_frame(x[f], p, ds, weights, scale, needed, rcond, paper, k[f], valid[f])
        if n_valid < n_g:
            n_pending += 1
            continue
        which[filled] = f
        kt[2 * filled] = k[f, :, 0]
        kt[2 * filled + 1] = k[f, :, 1]
        filled += 1
        if filled == block:
            _chain_block(kt, basis, segment, tq, coef, rates, which, filled, r0, h, m, rk4, pos, frames,
                         store_frames)
            filled = 0
    if filled:
        _chain_block(kt[:2 * filled], basis, segment, tq, coef, rates[:2 * filled], which, filled, r0, h, m, rk4,
                     pos, frames, store_frames)
    return n_pending


@njit(cache=True, nogil=True)
def _chain_block(kt, basis, segment, tq, coef, rates, which, n, r0, h, m, rk4, pos, frames, store_frames):
    """Rates of ``n`` frames at once, ``rates`` (2n, n_q) = ``kt`` (2n, n_g) @ ``basis`` (n_g, n_q) (a lone
    frame's by the polynomial pieces where there are some), then the chain of each from ``r0`` into
    ``pos[which[i]]`` and ``frames[which[i]]``: :data:`LANES` frames at a time on SIMD lanes
    (:func:`_lanes_block`) for the exponential integrators, one by one for RK4 and a lone frame."""
    if not rk4 and n >= 2:
        _lanes_block(kt, basis, segment, tq, coef, which, n, r0, h, m, pos, frames, store_frames)
        return
    if coef.size and not rk4:  # a lone frame: its two rates by the polynomial pieces
        _piecewise_pair(kt[0], kt[1], segment, tq, coef, rates[0], rates[1])
    elif n >= 4:
        np.dot(kt, basis, rates)
    else:  # BLAS would copy the whole operator for a product this small: sum it here, grating by grating
        n_g, n_q = basis.shape
        rates[:] = 0.0
        for g in range(n_g):
            for i in range(2 * n):
                a = kt[i, g]
                row = rates[i]
                b = basis[g]
                for q in range(n_q):
                    row[q] += b[q] * a
    n_steps = rates.shape[1] // m
    for i in range(n):
        f = which[i]
        r = rates[2 * i:2 * i + 2].reshape((2, n_steps, m))
        if rk4:
            rk4_curve(r, False, h, r0, pos[f], frames[f if store_frames else 0], store_frames)
        else:
            exp_material(r, h, pos[f], frames[f if store_frames else 0], store_frames)


@njit(cache=True, nogil=True)
def _lanes_block(kt, basis, segment, tq, coef, which, n, r0, h, m, pos, frames, store_frames):
    """:func:`_chain_block` for the exponential integrators: the rates in lane order, ``rt`` (n_q, 2n) = the
    interpolant (the polynomial pieces where there are some, else ``basis``ᵀ @) of the (k_x, k_y) of the frames
    as columns, group by group of :data:`LANES` frames (k_x of the group, then k_y), chained by
    :func:`twin._kernels.exp_lanes` (a frame with a step beyond the series' range again by :func:`exp_curve`),
    a group of half the lanes or fewer by :func:`exp_material` frame by frame."""
    n_g, n_q = basis.shape
    n_steps = n_q // m
    ktt = np.empty((n_g, 2 * n))
    for g0 in range(0, n, LANES):
        nl = min(LANES, n - g0)
        for i in range(nl):
            for g in range(n_g):
                ktt[g, 2 * g0 + i] = kt[2 * (g0 + i), g]
                ktt[g, 2 * g0 + nl + i] = kt[2 * (g0 + i) + 1, g]
    if coef.size:
        rt = np.empty((n_q, 2 * n))
        _piecewise_rates(ktt, segment, tq, coef, rt)
    else:
        rt = np.dot(basis.T, ktt)
    ok = np.zeros(LANES, np.bool_)
    r = np.empty((2, n_steps, m))
    for g0 in range(0, n, LANES):
        nl = min(LANES, n - g0)
        # a group costs the same however few of its lanes are used: up to half of them, one frame at a time
        lanes = nl > LANES // 2
        if lanes:
            exp_lanes(rt[:, 2 * g0:2 * (g0 + nl)], h, m, which[g0:g0 + nl], pos, frames, store_frames, ok)
        for i in range(nl):
            if lanes and ok[i]:
                continue
            f = which[g0 + i]
            for j in range(n_steps):
                for k in range(m):
                    r[0, j, k] = rt[j * m + k, 2 * g0 + i]
                    r[1, j, k] = rt[j * m + k, 2 * g0 + nl + i]
            fr = frames[f if store_frames else 0]
            if lanes:  # a step beyond the series' range: the exact coefficients
                exp_curve(r, False, h, r0, pos[f], fr, store_frames)
            else:
                exp_material(r, h, pos[f], fr, store_frames)


@njit(cache=True, nogil=True)
def _piecewise_rates(kcols, segment, tq, coef, out):
    """``out`` (n_q, C) = the interpolant of the node values ``kcols`` (n_g, C) at the samples, by its
    polynomial pieces (``coef`` (n_g, n_seg · 4): t⁰ … t³ of each interval; ``segment``, ``tq`` per sample):
    4 · n_seg · n_g + 3 · n_q multiply-adds per column instead of n_q · n_g."""
    n_c = kcols.shape[1]
    ck = np.dot(coef.T, kcols)  # (n_seg · 4, C)
    for q in range(tq.size):
        o = 4 * int(segment[q])
        t = tq[q]
        c0 = ck[o]
        c1 = ck[o + 1]
        c2 = ck[o + 2]
        c3 = ck[o + 3]
        row = out[q]
        for i in range(n_c):
            row[i] = ((c3[i] * t + c2[i]) * t + c1[i]) * t + c0[i]


@njit(cache=True, nogil=True)
def _piecewise_pair(kx, ky, segment, tq, coef, rx, ry):
    """:func:`_piecewise_rates` for one frame's (k_x, k_y) (n_g,) each, into ``rx``, ``ry`` (n_q,), without BLAS
    (its call and copies cost more than this product)."""
    n_g, n_r = coef.shape
    cx = np.zeros(n_r)
    cy = np.zeros(n_r)
    for g in range(n_g):  # grating by grating, so that the inner loop runs along the coefficients (SIMD)
        a = kx[g]
        b = ky[g]
        row = coef[g]
        for r in range(n_r):
            cx[r] += row[r] * a
            cy[r] += row[r] * b
    for q in range(tq.size):
        o = 4 * int(segment[q])
        t = tq[q]
        rx[q] = ((cx[o + 3] * t + cx[o + 2]) * t + cx[o + 1]) * t + cx[o]
        ry[q] = ((cy[o + 3] * t + cy[o + 2]) * t + cy[o + 1]) * t + cy[o]


@njit(cache=True, nogil=True)
def integrate(k, valid, which, bases, select, h, rk4, pos, frames, store_frames):
    """The interpolation and chain of the frames ``select`` with the operator ``bases[which[i]]`` for
    ``select[i]`` (arrays as :func:`reconstruct`); a frame whose pattern has no valid grating gets NaN."""
    n_steps = pos.shape[1] - 1
    m = bases.shape[2] // n_steps
    rates = np.empty((2, n_steps, m))
    r0 = np.eye(3)
    for i in range(select.size):
        f = select[i]
        fr = frames[f if store_frames else 0]
        if which[i] < 0:
            pos[f] = np.nan
            if store_frames:
                fr[:] = np.nan
            continue
        _chain(k[f], valid[f], bases[which[i]], rates, r0, h, rk4, pos[f], fr, store_frames)
