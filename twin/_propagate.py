"""The compiled propagation of :class:`twin.uncertainty.Uncertainty` (numba): curvature covariance per grating →
position covariance per point, one call per frame or batch (docs/math.md §8.2).

Per frame it evaluates, at the interpolant's breakpoints (the base, the gratings, the end) and at the first
piece's middle point, the running integrals X_n = (Φ_n, Ψ_n) (6 × 2 per grating: the integrals of B_n R E and
B_n (R E) × p) by the 3-point rule on each piece, then Y = Σ_n X_n V_n X_nᵀ + Z Zᵀ (6 × 6), C = A Y Aᵀ and
C' = A' Y Aᵀ + A Y A'ᵀ, and fills C in between by cubic Hermite interpolation (t⁴(a + b t + c t²) on the first
piece). One frame (:func:`_frame`) keeps the breakpoints along the last axis of every array, so the work per
grating is a handful of element-wise loops over ~20 breakpoints that the compiler turns into vector
instructions; a batch's complete frames go LANES at a time (:func:`_lanes_block`) with the frames along the
last axis, breakpoint by breakpoint, two gratings at a time, X_n V_n X_nᵀ as W Wᵀ with W = X_n L (L the
Cholesky factor of V_n). No reduction across lanes, nothing allocated per frame.

:func:`propagate` also forms the per-grating covariance itself (the noise of the inversion for the frame's peak
pattern, looked up in a table of every pattern; the model error's white and interpolation parts; the
calibration parameters' columns ∂k/∂p σ_p), so that one call does all of :meth:`Uncertainty.propagate`; for a
frame with every grating valid the interpolation term's divided differences are one precomputed weighted sum per
grating (:func:`_stencils`).
Constants travel as one flat array made by :func:`pack`, the interpolation weights of each pattern of valid
gratings as one row of ``bases`` (:func:`pattern_weights`): numba checks every array argument on every call.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from twin import _jit_cache  # noqa: F401  (before the first cached kernel; see its docstring)

__all__ = ["covariance", "interpolation_kernel", "pack", "pattern_weights", "propagate"]

_HEADER = 16
#: fast-math without the no-NaN/no-inf assumptions: a NaN position stays NaN, and the NaN tests stay tests
_FAST = {"contract", "reassoc", "nsz", "arcp", "afn"}


def pack(quad: dict, grating_s: np.ndarray, lam0: np.ndarray, window: float | None, ck_table: np.ndarray,
         sens_table: np.ndarray, par_sd: np.ndarray, curvature: float, relative: float, interpolation: float,
         base_var: float, twist: float = 0.0, order: int = 2) -> np.ndarray:
    """The constants of :func:`propagate` and :func:`covariance` as one float64 array.

    ``quad`` the quadrature of :func:`twin.uncertainty._quadrature`; ``grating_s`` (n_g,) m; ``lam0`` (n_g, n_c)
    nm the reference; ``window`` the physical window |e| (None: none); ``ck_table`` (n_g, 2^n_c, 2, 2) the
    inversion's curvature covariance for every pattern of present peaks (bit c = core c present);
    ``sens_table`` (n_g, 2^n_c, 2, n_par, 2) the operator k ↦ ∂k/∂p per pattern; ``par_sd`` (n_par,) the
    parameters' 1σ (scaled); the model error's ``curvature`` (1/m), ``relative``, ``interpolation`` and the base
    angle's variance ``base_var`` (rad²), the unmeasured twist rate's 1σ ``twist`` (rad/m) and the interpolation
    term's difference ``order`` (2 or 4)."""
    n_g, n_c = lam0.shape
    n_p = quad["interval"].size
    n_b = quad["breaks"].size
    n_par = par_sd.size
    header = np.zeros(_HEADER)
    header[:12] = (n_g, n_c, n_p, n_b, n_par, np.inf if window is None else window, curvature, relative,
                   interpolation, base_var, ck_table.shape[1], quad["h"][0])
    header[12:14] = (twist, order)
    start, weights = _stencils(np.asarray(grating_s, dtype=np.float64), order)
    parts = [header, grating_s, lam0, ck_table, sens_table, par_sd, quad["breaks"], quad["points"],
             quad["interval"], _hermite_weights(quad), quad["first"], quad["half_points"], start, weights]
    parts = [np.asarray(a, dtype=np.float64).ravel() for a in parts]
    parts[0][14] = sum(a.size for a in parts[:-2])  # where the stencils start: _unpack_stencils reads it, not recounts
    return np.concatenate(parts)


def _stencils(s: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """The interpolation term of a frame with every grating valid as one weighted sum per grating: the first
    grating of grating n's stencil (n_g,) and the weights (n_g, order + 1) such that
    Σ_q weights[n, q] k[start_n + q] is :func:`_interpolation_frame`'s |k⁽ᵖ⁾_n| √(½ Σ H^(2p+2)) / (w_n √2)
    before the norm — the p-th divided difference written out (Σ_q k_q / Π_{r≠q} (s_q − s_r)), times p! and
    the grating's constant factor. All zero with fewer than p + 1 gratings."""
    n = s.size
    start = np.zeros(n)
    weights = np.zeros((n, order + 1))
    if n < order + 1:
        return start, weights
    e = 2 * order + 2
    for j in range(n):  # once per setup: a handful of gratings
        a = min(max(j - order // 2, 0), n - order - 1)
        nodes = s[a:a + order + 1]
        diff = nodes[:, None] - nodes[None, :]
        np.fill_diagonal(diff, 1.0)
        hm = s[j] - s[j - 1] if j > 0 else 0.0
        hp = s[j + 1] - s[j] if j < n - 1 else 0.0
        factor = math.factorial(order) * np.sqrt(0.5 * (hm**e + hp**e)) / (0.5 * (hm + hp)) / np.sqrt(2.0)
        start[j] = a
        weights[j] = factor / diff.prod(axis=1)
    return start, weights


def _hermite_weights(quad: dict) -> np.ndarray:
    """Per output point (n_p, 4) the weights of C and h C' at its piece's ends (cubic Hermite: h00, h10·h, h01,
    h11·h), or on the first piece those of t⁴, t⁵, t⁶ (and 0)."""
    t, h = quad["t"], quad["h"]
    hw = np.stack([2 * t**3 - 3 * t**2 + 1, (t**3 - 2 * t**2 + t) * h, -2 * t**3 + 3 * t**2, (t**3 - t**2) * h], 1)
    first = quad["interval"] == 0
    hw[first] = np.stack([t[first] ** 4, t[first] ** 5, t[first] ** 6, 0 * t[first]], 1)
    return hw


@njit(cache=True, nogil=True)
def _unpack(const):  # pragma: no cover (compiled)
    n_g, n_c, n_p, n_b, n_par = int(const[0]), int(const[1]), int(const[2]), int(const[3]), int(const[4])
    n_codes = int(const[10])
    o = _HEADER
    grating_s = const[o:o + n_g]
    o += n_g
    lam0 = const[o:o + n_g * n_c].reshape((n_g, n_c))
    o += n_g * n_c
    ck_table = const[o:o + n_g * n_codes * 4].reshape((n_g, n_codes, 2, 2))
    o += n_g * n_codes * 4
    sens_table = const[o:o + n_g * n_codes * 4 * n_par].reshape((n_g, n_codes, 2, n_par, 2))
    o += n_g * n_codes * 4 * n_par
    par_sd = const[o:o + n_par]
    o += n_par
    breaks = const[o:o + n_b].astype(np.int64)
    o += n_b
    points = const[o:o + (n_b - 1) * 3].astype(np.int64).reshape((n_b - 1, 3))
    o += (n_b - 1) * 3
    interval = const[o:o + n_p].astype(np.int64)
    o += n_p
    hw = const[o:o + 4 * n_p].reshape((n_p, 4))
    o += 4 * n_p
    first = const[o:o + 9].reshape((3, 3))
    o += 9
    half_points = const[o:o + 3].astype(np.int64)
    return grating_s, lam0, ck_table, sens_table, par_sd, breaks, points, interval, hw, first, half_points


@njit(cache=True, nogil=True)
def _unpack_stencils(const):  # pragma: no cover (compiled)
    """The intact pattern's interpolation stencils of :func:`pack` (:func:`_stencils`): start (n_g,) int64,
    weights (n_g, order + 1)."""
    n_g, order, o = int(const[0]), int(const[13]), int(const[14])
    start = const[o:o + n_g].astype(np.int64)
    o += n_g
    return start, const[o:o + n_g * (order + 1)].reshape((n_g, order + 1))


def pattern_weights(quad: dict, basis: np.ndarray) -> np.ndarray:
    """The quadrature weights times the interpolation basis (n_points, n_g) at the rule's points, as one row
    (3 · n_int · n_g + 3 · n_g,): w_e B_n(u_e) per piece (e, piece, n), then the rule to the first piece's
    middle point (e, n)."""
    wb = (quad["weights"][:, :, None] * basis[quad["points"]]).transpose(1, 0, 2)  # (3, n_int, n_g)
    wh = quad["half_weights"][:, None] * basis[quad["half_points"]]  # (3, n_g)
    return np.concatenate([wb.ravel(), wh.ravel()])


@njit(cache=True, nogil=True, fastmath=_FAST)
def _frame(pos, fr, v, sp, use, base_var, h0, wrow, breaks, points, interval, hw, first, half_points, work,
           out):  # pragma: no cover (compiled)
    """Position covariance (n_p, 3, 3) of one frame into ``out`` from its positions (n_p, 3), frames
    (n_p, 3, 3), per-grating covariance ``v`` (n_g, 2, 2), parameter columns ``sp`` (n_g, 2, n_par) (∂k/∂p σ_p)
    and the gratings in ``use`` (n_g,); ``wrow`` the pattern's weights (:func:`pattern_weights`), ``work`` a
    scratch buffer of :func:`_work_size`."""
    n_g, n_par = v.shape[0], sp.shape[2]
    n_b = breaks.size
    n_int = n_b - 1
    kk = _lanes(n_b)  # the breakpoints, the first piece's middle point, zeros to a multiple of 8
    wb = wrow[:3 * n_g * n_int].reshape((3, n_int, n_g))
    wh = wrow[3 * n_g * n_int:].reshape((3, n_g))
    o = 0
    g = work[o:o + 3 * 12 * n_int].reshape((3, 12, n_int))
    o += 3 * 12 * n_int
    gh = work[o:o + 36].reshape((3, 12))
    o += 36
    xs = work[o:o + 12 * n_g].reshape((12, n_g))  # X_n of every grating at one breakpoint
    o += 12 * n_g
    vs = work[o:o + (3 + 2 * n_par) * n_g].reshape((3 + 2 * n_par, n_g))  # V_n (v00, v01, v11), S_n (q·2 + c)
    o += (3 + 2 * n_par) * n_g
    y = work[o:o + 36 * kk].reshape((6, 6, kk))
    o += 36 * kk
    z = work[o:o + 6 * n_par * kk].reshape((6, n_par, kk))
    o += 6 * n_par * kk
    m = work[o:o + 36 * kk].reshape((2, 3, 6, kk))  # A Y and A' Y
    o += 36 * kk
    pt = work[o:o + 6 * kk].reshape((2, 3, kk))  # p and t at the breakpoints
    o += 6 * kk
    cb = work[o:o + 18 * kk].reshape((2, 3, 3, kk))  # C and C'
    o += 18 * kk
    pc = work[o:o + n_int * 36].reshape((n_int, 4, 3, 3))

    # (R E, (R E) × p) at the rule's points: δk_x turns about d2, δk_y about −d1; row r·2 + c
    for j in range(n_int):
        for e in range(3):
            _integrand(pos, fr, points[j, e], g[e, :, j])
    for e in range(3):
        _integrand(pos, fr, half_points[e], gh[e])
    # V_n and S_n with the gratings along the last axis (a grating left out carries nothing; its X_n is zero too:
    # the pattern's basis has no column for it)
    for n in range(n_g):
        ok = use[n]
        vs[0, n] = v[n, 0, 0] if ok else 0.0
        vs[1, n] = v[n, 0, 1] if ok else 0.0
        vs[2, n] = v[n, 1, 1] if ok else 0.0
        for q in range(n_par):
            vs[3 + 2 * q, n] = sp[n, 0, q] if ok else 0.0
            vs[4 + 2 * q, n] = sp[n, 1, q] if ok else 0.0
    # breakpoint by breakpoint with the gratings along the vector axis: X_n(b) = X_n(b − 1) + piece b − 1's rule
    # for every grating at once, then Y(b) = Σ_n X_n V_n X_nᵀ and Z(b) = Σ_n X_n S_n as sums over the gratings
    # (no pass over every breakpoint per grating, no running sum waiting on itself)
    y[:] = 0.0
    z[:] = 0.0
    xs[:] = 0.0
    for b in range(1, n_b + 1):
        if b < n_b:
            j = b - 1
            for rc in range(12):
                g0, g1, g2 = g[0, rc, j], g[1, rc, j], g[2, rc, j]
                xr, w0, w1, w2 = xs[rc], wb[0, j], wb[1, j], wb[2, j]
                for n in range(n_g):
                    xr[n] += w0[n] * g0 + w1[n] * g1 + w2[n] * g2
        else:  # the first piece's middle point, from the base by its own rule (the running sums are done)
            for rc in range(12):
                g0, g1, g2 = gh[0, rc], gh[1, rc], gh[2, rc]
                xr, w0, w1, w2 = xs[rc], wh[0], wh[1], wh[2]
                for n in range(n_g):
                    xr[n] = w0[n] * g0 + w1[n] * g1 + w2[n] * g2
        _sums(xs, vs, y, z, b)
    # p and t where C is formed
    for i in range(kk):
        idx = breaks[i] if i < n_b else half_points[2]  # (the padding repeats the middle point)
        for r in range(3):
            pt[0, r, i] = pos[idx, r]
            pt[1, r, i] = fr[idx, r, 2]
    _c_and_dc(y, z, pt, m, cb)  # Y += Z Zᵀ, then C = A Y Aᵀ and C' = A' Y Aᵀ + A Y A'ᵀ
    # per piece the four 3 × 3 coefficients of its points' weights (:func:`_hermite_weights`): C and C' at its
    # ends; on the first piece t⁴ (a + b t + c t²) through C(1), h C'(1) and C at the middle point, solved
    # with the precomputed inverse ``first`` (C ~ s⁴ from the base, an angle times an arm, s⁶ along the tangent,
    # which a cubic cannot follow)
    for r in range(3):
        for c in range(3):
            rhs0, rhs1, rhs2 = cb[0, r, c, 1], h0 * cb[1, r, c, 1], cb[0, r, c, n_b]
            for e in range(3):
                pc[0, e, r, c] = first[e, 0] * rhs0 + first[e, 1] * rhs1 + first[e, 2] * rhs2
            pc[0, 3, r, c] = 0.0
            for q in range(1, n_int):
                pc[q, 0, r, c] = cb[0, r, c, q]
                pc[q, 1, r, c] = cb[1, r, c, q]
                pc[q, 2, r, c] = cb[0, r, c, q + 1]
                pc[q, 3, r, c] = cb[1, r, c, q + 1]
    # then every point from its piece's coefficients, plus the base angle exactly
    for j in range(pos.shape[0]):
        q = interval[j]
        w0, w1, w2, w3 = hw[j, 0], hw[j, 1], hw[j, 2], hw[j, 3]
        q0, q1, q2 = pos[j, 0], pos[j, 1], pos[j, 2]
        pp = q0 * q0 + q1 * q1 + q2 * q2
        for r in range(3):
            for c in range(r, 3):
                val = w0 * pc[q, 0, r, c] + w1 * pc[q, 1, r, c] + w2 * pc[q, 2, r, c] + w3 * pc[q, 3, r, c]
                val += base_var * ((pp if r == c else 0.0) - pos[j, r] * pos[j, c])
                out[j, r, c] = val
                out[j, c, r] = val


@njit(cache=True, nogil=True, fastmath=_FAST, inline="always")
def _sums(xs, vs, y, z, b):  # pragma: no cover (compiled)
    """Y[:, :, b] (upper triangle) = Σ_n X_n V_n X_nᵀ and Z[:, :, b] = Σ_n X_n S_n over the gratings, the last
    axis of ``xs`` (12, n_g) X_n (row r·2 + c) and ``vs`` (3 + 2 n_par, n_g) V_n (v00, v01, v11) and S_n (row
    3 + q·2 + c). One loop along the gratings with the 21 sums of Y side by side (in registers, one reduction
    each at its end), then one per shared column with its six. :func:`_accumulate` does the same per frame into
    rows of lanes, there as W Wᵀ with V_n's Cholesky factor (equal to rounding; a one-frame call is not bound by
    the stores that form saves): written out in both, since the compiler vectorises each loop only when its body
    is straight-line code on its own operands."""
    n_g, n_par = xs.shape[1], z.shape[1]
    y00 = 0.0
    y01 = 0.0
    y02 = 0.0
    y03 = 0.0
    y04 = 0.0
    y05 = 0.0
    y11 = 0.0
    y12 = 0.0
    y13 = 0.0
    y14 = 0.0
    y15 = 0.0
    y22 = 0.0
    y23 = 0.0
    y24 = 0.0
    y25 = 0.0
    y33 = 0.0
    y34 = 0.0
    y35 = 0.0
    y44 = 0.0
    y45 = 0.0
    y55 = 0.0
    for n in range(n_g):
        x0 = xs[0, n]
        x1 = xs[1, n]
        x2 = xs[2, n]
        x3 = xs[3, n]
        x4 = xs[4, n]
        x5 = xs[5, n]
        x6 = xs[6, n]
        x7 = xs[7, n]
        x8 = xs[8, n]
        x9 = xs[9, n]
        x10 = xs[10, n]
        x11 = xs[11, n]
        v0, v1, v2 = vs[0, n], vs[1, n], vs[2, n]
        u00 = x0 * v0 + x1 * v1
        u01 = x0 * v1 + x1 * v2
        u10 = x2 * v0 + x3 * v1
        u11 = x2 * v1 + x3 * v2
        u20 = x4 * v0 + x5 * v1
        u21 = x4 * v1 + x5 * v2
        u30 = x6 * v0 + x7 * v1
        u31 = x6 * v1 + x7 * v2
        u40 = x8 * v0 + x9 * v1
        u41 = x8 * v1 + x9 * v2
        u50 = x10 * v0 + x11 * v1
        u51 = x10 * v1 + x11 * v2
        y00 += u00 * x0 + u01 * x1
        y01 += u00 * x2 + u01 * x3
        y02 += u00 * x4 + u01 * x5
        y03 += u00 * x6 + u01 * x7
        y04 += u00 * x8 + u01 * x9
        y05 += u00 * x10 + u01 * x11
        y11 += u10 * x2 + u11 * x3
        y12 += u10 * x4 + u11 * x5
        y13 += u10 * x6 + u11 * x7
        y14 += u10 * x8 + u11 * x9
        y15 += u10 * x10 + u11 * x11
        y22 += u20 * x4 + u21 * x5
        y23 += u20 * x6 + u21 * x7
        y24 += u20 * x8 + u21 * x9
        y25 += u20 * x10 + u21 * x11
        y33 += u30 * x6 + u31 * x7
        y34 += u30 * x8 + u31 * x9
        y35 += u30 * x10 + u31 * x11
        y44 += u40 * x8 + u41 * x9
        y45 += u40 * x10 + u41 * x11
        y55 += u50 * x10 + u51 * x11
    y[0, 0, b] = y00
    y[0, 1, b] = y01
    y[0, 2, b] = y02
    y[0, 3, b] = y03
    y[0, 4, b] = y04
    y[0, 5, b] = y05
    y[1, 1, b] = y11
    y[1, 2, b] = y12
    y[1, 3, b] = y13
    y[1, 4, b] = y14
    y[1, 5, b] = y15
    y[2, 2, b] = y22
    y[2, 3, b] = y23
    y[2, 4, b] = y24
    y[2, 5, b] = y25
    y[3, 3, b] = y33
    y[3, 4, b] = y34
    y[3, 5, b] = y35
    y[4, 4, b] = y44
    y[4, 5, b] = y45
    y[5, 5, b] = y55
    for q in range(n_par):
        z0 = z1 = z2 = z3 = z4 = z5 = 0.0
        for n in range(n_g):
            s0, s1 = vs[3 + 2 * q, n], vs[4 + 2 * q, n]
            z0 += xs[0, n] * s0 + xs[1, n] * s1
            z1 += xs[2, n] * s0 + xs[3, n] * s1
            z2 += xs[4, n] * s0 + xs[5, n] * s1
            z3 += xs[6, n] * s0 + xs[7, n] * s1
            z4 += xs[8, n] * s0 + xs[9, n] * s1
            z5 += xs[10, n] * s0 + xs[11, n] * s1
        z[0, q, b] = z0
        z[1, q, b] = z1
        z[2, q, b] = z2
        z[3, q, b] = z3
        z[4, q, b] = z4
        z[5, q, b] = z5


@njit(cache=True, nogil=True, fastmath=_FAST)
def _c_and_dc(y, z, pt, m, cb):  # pragma: no cover (compiled)
    """C = A Y Aᵀ and C' = A' Y Aᵀ + A Y A'ᵀ into ``cb`` (2, 3, 3, K), element-wise along the last axis K of
    every array: first Y (its upper triangle, (6, 6, K)) += Z Zᵀ (Z (6, n_sh, K)) and its lower triangle;
    ``pt`` (2, 3, K) p and t; ``m`` (2, 3, 6, K) scratch for A Y and A' Y (A = (−[p]×, −I), A' = (−[t]×, 0))."""
    kk, n_sh = y.shape[2], z.shape[1]
    for r in range(6):
        for c in range(r, 6):
            for q in range(n_sh):
                for i in range(kk):
                    y[r, c, i] += z[r, q, i] * z[c, q, i]
            if c > r:
                for i in range(kk):
                    y[c, r, i] = y[r, c, i]
    p0, p1, p2 = pt[0, 0], pt[0, 1], pt[0, 2]
    t0, t1, t2 = pt[1, 0], pt[1, 1], pt[1, 2]
    for e in range(6):
        for i in range(kk):
            u0, u1, u2 = y[0, e, i], y[1, e, i], y[2, e, i]
            m[0, 0, e, i] = p2[i] * u1 - p1[i] * u2 - y[3, e, i]
            m[0, 1, e, i] = p0[i] * u2 - p2[i] * u0 - y[4, e, i]
            m[0, 2, e, i] = p1[i] * u0 - p0[i] * u1 - y[5, e, i]
            m[1, 0, e, i] = t2[i] * u1 - t1[i] * u2
            m[1, 1, e, i] = t0[i] * u2 - t2[i] * u0
            m[1, 2, e, i] = t1[i] * u0 - t0[i] * u1
    for r in range(3):
        for i in range(kk):
            a0, a1, a2 = m[0, r, 0, i], m[0, r, 1, i], m[0, r, 2, i]
            d0, d1, d2 = m[1, r, 0, i], m[1, r, 1, i], m[1, r, 2, i]
            cb[0, r, 0, i] = p2[i] * a1 - p1[i] * a2 - m[0, r, 3, i]
            cb[0, r, 1, i] = p0[i] * a2 - p2[i] * a0 - m[0, r, 4, i]
            cb[0, r, 2, i] = p1[i] * a0 - p0[i] * a1 - m[0, r, 5, i]
            cb[1, r, 0, i] = p2[i] * d1 - p1[i] * d2 - m[1, r, 3, i] + t2[i] * a1 - t1[i] * a2
            cb[1, r, 1, i] = p0[i] * d2 - p2[i] * d0 - m[1, r, 4, i] + t0[i] * a2 - t2[i] * a0
            cb[1, r, 2, i] = p1[i] * d0 - p0[i] * d1 - m[1, r, 5, i] + t1[i] * a0 - t0[i] * a1


@njit(cache=True, nogil=True, fastmath=_FAST, inline="always")
def _integrand(pos, fr, i, dst):  # pragma: no cover (compiled)
    """(R E, (R E) × p) at output point i into ``dst`` (12,), row r·2 + c: the axes δk_x (d2) and δk_y (−d1)
    turn the fibre about, and their moments about the origin."""
    p0, p1, p2 = pos[i, 0], pos[i, 1], pos[i, 2]
    for c in range(2):
        if c == 0:
            a0, a1, a2 = fr[i, 0, 1], fr[i, 1, 1], fr[i, 2, 1]
        else:
            a0, a1, a2 = -fr[i, 0, 0], -fr[i, 1, 0], -fr[i, 2, 0]
        dst[c] = a0
        dst[2 + c] = a1
        dst[4 + c] = a2
        dst[6 + c] = a1 * p2 - a2 * p1
        dst[8 + c] = a2 * p0 - a0 * p2
        dst[10 + c] = a0 * p1 - a1 * p0


@njit(cache=True, nogil=True)
def _lanes(n_b):  # pragma: no cover (compiled)
    """The length of the arrays along the breakpoints: n_b + 1 rounded up to a multiple of 8, so that the loops
    along them run in whole vectors (no scalar remainder)."""
    return (n_b + 1 + 7) // 8 * 8


@njit(cache=True, nogil=True)
def _work_size(n_g, n_b, n_par):  # pragma: no cover (compiled)
    kk = _lanes(n_b)
    # g, gh, xs, vs, y, z, m, pt, cb, pc
    return 36 * (n_b - 1) + 36 + 12 * n_g + (3 + 2 * n_par) * n_g + 36 * kk + 6 * n_par * kk + 36 * kk + 6 * kk \
        + 18 * kk + 36 * (n_b - 1)


@njit(cache=True, nogil=True)
def covariance(const, pos, frames, v, sp, valid, bases, which, out):  # pragma: no cover (compiled)
    """Position covariance (F, n_p, 3, 3) into ``out`` from the per-grating covariance ``v`` (F, n_g, 2, 2) and
    parameter columns ``sp`` (F, n_g, 2, n_par) (∂k/∂p σ_p) given; ``valid`` (F, n_g), ``bases`` the patterns'
    weights (:func:`pattern_weights`), ``which`` (F,) each frame's pattern. NaN for a frame without a valid
    grating."""
    (_, _, _, _, _, breaks, points, interval, hw, first, half_points) = _unpack(const)
    n_f, n_g = v.shape[0], v.shape[1]
    base_var = const[9]
    work = np.empty(_work_size(n_g, breaks.size, sp.shape[3]))
    for f in range(n_f):
        if not valid[f].any():
            out[f] = np.nan
            continue
        _frame(pos[f], frames[f], v[f], sp[f], valid[f], base_var, const[11], bases[which[f]], breaks, points,
               interval, hw, first, half_points, work, out[f])


@njit(cache=True, nogil=True)
def propagate(const, pos, frames, k, valid, w, bases, which, cov_out, ck_out):  # pragma: no cover (compiled)
    """All of :meth:`twin.uncertainty.Uncertainty.propagate` for F frames: ``pos`` (F, n_p, 3), ``frames``
    (F, n_p, 3, 3), curvature ``k`` (F, n_g, 2) (NaN where invalid), ``valid`` (F, n_g), wavelengths ``w``
    (F, n_g, n_c) nm (or (0, n_g, n_c): every peak of a valid grating present) → ``cov_out`` (F, n_p, 3, 3) m²,
    ``ck_out`` (F, n_g, 2, 2) (1/m)², NaN at invalid gratings. ``which`` (F,) each frame's row of ``bases``; or
    empty: then ``bases[0]`` is the intact pattern's, and the frames that lost a grating are left out of
    ``cov_out`` (not of ``ck_out``) for a second call with their patterns. Returns the number left out."""
    (grating_s, lam0, ck_table, sens_table, par_sd, breaks, points, interval, hw, first,
     half_points) = _unpack(const)
    n_f, n_g = k.shape[0], k.shape[1]
    n_c, n_par = lam0.shape[1], par_sd.size
    window, white, relative, interp, base_var = const[5], const[6], const[7], const[8], const[9]
    twist, order = const[12], int(const[13])
    n_sh = n_par + (1 if twist != 0.0 else 0)  # the shared columns: the parameters, the twist
    full = (1 << n_c) - 1
    work = np.empty(_work_size(n_g, breaks.size, n_sh))
    v = np.empty((n_g, 2, 2))
    sp = np.empty((n_g, 2, n_sh))
    kf = np.empty((n_g, 2))
    sig = np.empty(n_g)
    idx = np.empty(n_g, np.int64)
    tab = np.empty((order + 1, 2))
    # the complete frames of the intact pattern's call go side by side, LANES at a time (_lanes_block); the
    # last fewer than LANES, and every frame of a call with fewer, one at a time (a block's scratch and its
    # empty lanes would cost a single frame more than its own arithmetic)
    lanes = which.size == 0 and n_f >= LANES
    nb_ = breaks.size if lanes else 1
    arrs = _block_arrays(n_g, nb_, n_sh, LANES if lanes else 0)
    vrep, sprep = arrs[0], arrs[1]
    wb = bases[0][:3 * n_g * (nb_ - 1)].reshape((3, nb_ - 1, n_g))
    wh = bases[0][3 * n_g * (nb_ - 1):].reshape((3, n_g)) if lanes else bases[0][:0].reshape((3, 0))
    st_start, st_weights = _unpack_stencils(const)
    fidx = np.empty(LANES, np.int64)
    n_l = 0
    left_out = 0
    for f in range(n_f):
        n_valid = 0
        for n in range(n_g):
            kf[n, 0] = k[f, n, 0] if valid[f, n] else 0.0
            kf[n, 1] = k[f, n, 1] if valid[f, n] else 0.0
            n_valid += valid[f, n]
        # the model error: white + relative·|k|, and the interpolation part, added in variance
        if interp != 0.0:
            if n_valid == n_g:  # the intact pattern: precomputed stencils (no divisions, no powers)
                for n in range(n_g):
                    a, d0, d1 = st_start[n], 0.0, 0.0
                    for q in range(order + 1):
                        d0 += st_weights[n, q] * kf[a + q, 0]
                        d1 += st_weights[n, q] * kf[a + q, 1]
                    sig[n] = np.sqrt(d0 * d0 + d1 * d1)
            else:
                _interpolation_frame(kf, valid[f], grating_s, order, idx, tab, sig)
        for n in range(n_g):
            wsig = white + relative * np.sqrt(kf[n, 0] ** 2 + kf[n, 1] ** 2)
            isig = interp * sig[n] if interp != 0.0 else 0.0
            var_m = wsig * wsig + isig * isig
            # the peaks present (not NaN, finite, inside the window: as the reconstructor's strain())
            code = full
            if w.shape[0] > 0:
                code = 0
                for c in range(n_c):
                    e = (w[f, n, c] - lam0[n, c]) / lam0[n, c]
                    if np.isfinite(e) and np.abs(e) <= window:
                        code |= 1 << c
            v[n, 0, 0] = ck_table[n, code, 0, 0] + var_m
            v[n, 0, 1] = ck_table[n, code, 0, 1]
            v[n, 1, 0] = ck_table[n, code, 1, 0]
            v[n, 1, 1] = ck_table[n, code, 1, 1] + var_m
            for i in range(2):
                for q in range(n_par):
                    sp[n, i, q] = par_sd[q] * (sens_table[n, code, i, q, 0] * kf[n, 0]
                                               + sens_table[n, code, i, q, 1] * kf[n, 1])
            if n_sh > n_par:
                # the unmeasured twist: δk_n = τ s_n J k_n, J k = (−k_y, k_x), per 1σ of τ; it moves the
                # positions, not the measured curvature (ModelError.twist_sensitivity)
                sp[n, 0, n_par] = -twist * grating_s[n] * kf[n, 1]
                sp[n, 1, n_par] = twist * grating_s[n] * kf[n, 0]
            for i in range(2):
                for j in range(2):
                    acc = v[n, i, j]
                    for q in range(n_par):
                        acc += sp[n, i, q] * sp[n, j, q]
                    ck_out[f, n, i, j] = acc if valid[f, n] else np.nan
        if n_valid == 0:
            cov_out[f] = np.nan
            continue
        if which.size == 0 and n_valid < n_g:
            left_out += 1
            continue
        if lanes:
            for n in range(n_g):
                vrep[n, n_l] = v[n, 0, 0]
                vrep[n, LANES + n_l] = v[n, 0, 1]
                vrep[n, 2 * LANES + n_l] = v[n, 1, 1]
                for i in range(2):
                    for q in range(n_sh):
                        sprep[n, (q * 2 + i) * LANES + n_l] = sp[n, i, q]
            fidx[n_l] = f
            n_l += 1
            if n_l == LANES:
                _lanes_block(arrs, pos, frames, fidx, n_l, base_var, const[11], wb, wh, breaks, points,
                             interval, hw, first, half_points, cov_out)
                n_l = 0
            continue
        row = bases[0] if which.size == 0 else bases[which[f]]
        _frame(pos[f], frames[f], v, sp, valid[f], base_var, const[11], row, breaks, points, interval, hw, first,
               half_points, work, cov_out[f])
    for ll in range(n_l):  # the last fewer than LANES: their v and S from the lanes
        f = fidx[ll]
        for n in range(n_g):
            v[n, 0, 0] = vrep[n, ll]
            v[n, 0, 1] = v[n, 1, 0] = vrep[n, LANES + ll]
            v[n, 1, 1] = vrep[n, 2 * LANES + ll]
            for i in range(2):
                for q in range(n_sh):
                    sp[n, i, q] = sprep[n, (q * 2 + i) * LANES + ll]
        _frame(pos[f], frames[f], v, sp, valid[f], base_var, const[11], bases[0], breaks, points, interval, hw,
               first, half_points, work, cov_out[f])
    return left_out


@njit(cache=True, nogil=True)
def _interpolation_frame(k, valid, s, order, idx, tab, out):  # pragma: no cover (compiled)
    """:func:`interpolation_kernel` for one frame: k (n, 2), valid (n,) → out (n,); ``idx`` (n,) int64 and
    ``tab`` (order + 1, 2) scratch."""
    n = valid.shape[0]
    fact = 1.0
    for q in range(2, order + 1):
        fact *= q
    m = 0
    for i in range(n):
        out[i] = 0.0
        if valid[i]:
            idx[m] = i
            m += 1
    if m < order + 1:
        return
    for j in range(m):
        start = min(max(j - order // 2, 0), m - order - 1)
        for q in range(order + 1):
            tab[q, 0] = k[idx[start + q], 0]
            tab[q, 1] = k[idx[start + q], 1]
        for lev in range(1, order + 1):  # divided differences in place
            for q in range(order, lev - 1, -1):
                d = s[idx[start + q]] - s[idx[start + q - lev]]
                tab[q, 0] = (tab[q, 0] - tab[q - 1, 0]) / d
                tab[q, 1] = (tab[q, 1] - tab[q - 1, 1]) / d
        dk = fact * np.sqrt(tab[order, 0] ** 2 + tab[order, 1] ** 2)
        i = idx[j]
        hm = s[i] - s[idx[j - 1]] if j > 0 else 0.0
        hp = s[idx[j + 1]] - s[i] if j < m - 1 else 0.0
        e = 2 * order + 2
        out[i] = dk * np.sqrt(0.5 * (hm**e + hp**e)) / (0.5 * (hm + hp)) / np.sqrt(2.0)


@njit(cache=True, nogil=True)
def interpolation_kernel(k, valid, s, order, out):  # pragma: no cover (compiled)
    """|k⁽ᵖ⁾_n| √(½ Σ H^(2p+2)) / (w_n √2) per frame and grating (:meth:`ModelError.interpolation_sigma`
    without c), p = ``order`` (2 or 4): k (F, n, 2), valid (F, n), s (n,), out (F, n); k⁽ᵖ⁾_n is p! times the
    p-th divided difference over p + 1 consecutive valid gratings centred on n (shifted inwards at the ends, so
    the end gratings share their neighbours' stencil); 0 at invalid gratings, and with fewer than p + 1 valid."""
    n_f, n = valid.shape
    idx = np.empty(n, np.int64)
    tab = np.empty((order + 1, 2))
    for f in range(n_f):
        _interpolation_frame(k[f], valid[f], s, order, idx, tab, out[f])



#: the complete frames :func:`propagate` carries side by side: 16, two vectors of eight, so that the loops over them
#: are long enough for the compiler's loop vectoriser (it leaves loops of fewer than 16 iterations scalar)
LANES = 16


@njit(cache=True, nogil=True)
def _block_arrays(n_g, n_b, n_sh, L):  # pragma: no cover (compiled)
    """The scratch arrays of :func:`_lanes_block`, LANES frames side by side in the last axis (index
    row · LANES + frame; ``L`` LANES, or 0 for a call that does not use them): per-grating covariance
    (n_g, 3 · LANES: v00, v01, v11) and shared columns (n_g, 2 · n_sh · LANES, row q·2 + c), which
    :func:`propagate` fills; the integrand per piece and rule point (n_b − 1, 3, 12 · LANES) and to the first
    piece's middle point (3, 12 · LANES); the running X_n (n_g, 12 · LANES); X_n at the first piece's middle
    point (12 · LANES); per breakpoint Y's upper triangle (n_b + 1, 21 · LANES) and Z (n_b + 1, 6 · n_sh · LANES,
    row q·6 + r); then along K = (n_b + 1) · LANES (breakpoint-major, frame-minor) Y (6, 6, K), Z (6, n_sh, K),
    p and t (2, 3, K), A Y and A' Y (2, 3, 6, K), C and C' (2, 3, 3, K); one point's work (48 · LANES: its
    piece's coefficients 36, its position 3, its covariance 9); the shared columns' curvature error
    interpolated to the rule's points, times the rule's weights, per piece (n_b − 1, 3, 2 · n_sh · LANES) and to
    the first piece's middle point (3, 2 · n_sh · LANES), row q·2 + c; V_n's Cholesky factor (n_g, 3 · LANES: l00,
    l10, l11)."""
    kb = (n_b + 1) * L
    sizes = (3 * n_g * L, 2 * n_g * n_sh * L, 36 * (n_b - 1) * L, 36 * L, 12 * n_g * L, 12 * L,
             21 * kb, 6 * n_sh * kb, 36 * kb, 6 * n_sh * kb, 6 * kb, 36 * kb, 18 * kb, 48 * L,
             6 * n_sh * (n_b - 1) * L, 6 * n_sh * L, 3 * n_g * L)
    # one allocation (empty for a call without lanes)
    o = np.zeros(len(sizes) + 1, np.int64)
    for i in range(len(sizes)):
        o[i + 1] = o[i] + sizes[i]
    buf = np.empty(o[-1])
    return (buf[o[0]:o[1]].reshape((n_g, 3 * L)), buf[o[1]:o[2]].reshape((n_g, 2 * n_sh * L)),
            buf[o[2]:o[3]].reshape((n_b - 1, 3, 12 * L)), buf[o[3]:o[4]].reshape((3, 12 * L)),
            buf[o[4]:o[5]].reshape((n_g, 12 * L)), buf[o[5]:o[6]],
            buf[o[6]:o[7]].reshape((n_b + 1, 21 * L)), buf[o[7]:o[8]].reshape((n_b + 1, 6 * n_sh * L)),
            buf[o[8]:o[9]].reshape((6, 6, kb)), buf[o[9]:o[10]].reshape((6, n_sh, kb)),
            buf[o[10]:o[11]].reshape((2, 3, kb)), buf[o[11]:o[12]].reshape((2, 3, 6, kb)),
            buf[o[12]:o[13]].reshape((2, 3, 3, kb)), buf[o[13]:o[14]],
            buf[o[14]:o[15]].reshape((n_b - 1, 3, 2 * n_sh * L)), buf[o[15]:o[16]].reshape((3, 2 * n_sh * L)),
            buf[o[16]:o[17]].reshape((n_g, 3 * L)))


@njit(cache=True, nogil=True, fastmath=_FAST)
def _lanes_block(arrs, pos, fr, fidx, n_l, base_var, h0, wb, wh, breaks, points, interval, hw, first,
                 half_points, out):  # pragma: no cover (compiled)
    """:func:`_frame` for up to LANES complete frames at once (every grating valid, the intact pattern): the
    frames ``fidx[:n_l]`` of ``pos``, ``fr`` and ``out``, their per-grating covariance and shared columns in
    ``arrs``' first two (:func:`_block_arrays`). The frames are the innermost axis of every array, so that each
    step is a short loop over them at constant offsets that the compiler turns into vector instructions; the
    running integrals go breakpoint by breakpoint (each grating's X_n updated in place, then added into that
    breakpoint's Y and Z at once), so that Y and Z are touched once per breakpoint and grating in the first-level
    cache instead of in a pass over every breakpoint per grating; two gratings at a time, so that Y's rows are
    loaded and stored once per pair (:func:`_accumulate2`). ``wb`` (3, n_b − 1, n_g) the pattern's piece
    weights, ``wh`` (3, n_g) those of the first piece's middle point. Each frame's arithmetic is :func:`_frame`'s
    but for X_n V_n X_nᵀ, formed as W Wᵀ with W = X_n L (L V_n's Cholesky factor): equal to rounding.
    Lanes beyond ``n_l`` (none: :func:`propagate` hands over full blocks) would compute on stale data, never
    written out."""
    vrep, sprep, g, gh, xn, xm, yb, zb, y, z, pt, m, cb, fw, wsq, wsqh, lrep = arrs
    L = LANES
    n_g = vrep.shape[0]
    n_b = breaks.size
    n_int = n_b - 1
    n_p = pos.shape[1]
    # gather: the integrand (R E, (R E) × p) at the rule's points, p and t at the breakpoints
    # (point by point, the frames innermost: unit-stride stores, the loads gathered)
    for pi in range(3 * n_int + 3):
        if pi < 3 * n_int:
            i = points[pi // 3, pi % 3]
            dst = g[pi // 3, pi % 3]
        else:
            i = half_points[pi - 3 * n_int]
            dst = gh[pi - 3 * n_int]
        for ll in range(n_l):
            f = fidx[ll]
            p0, p1, p2 = pos[f, i, 0], pos[f, i, 1], pos[f, i, 2]
            a0, a1, a2 = fr[f, i, 0, 1], fr[f, i, 1, 1], fr[f, i, 2, 1]
            b0, b1, b2 = -fr[f, i, 0, 0], -fr[f, i, 1, 0], -fr[f, i, 2, 0]
            dst[ll] = a0
            dst[L + ll] = b0
            dst[2 * L + ll] = a1
            dst[3 * L + ll] = b1
            dst[4 * L + ll] = a2
            dst[5 * L + ll] = b2
            dst[6 * L + ll] = a1 * p2 - a2 * p1
            dst[7 * L + ll] = b1 * p2 - b2 * p1
            dst[8 * L + ll] = a2 * p0 - a0 * p2
            dst[9 * L + ll] = b2 * p0 - b0 * p2
            dst[10 * L + ll] = a0 * p1 - a1 * p0
            dst[11 * L + ll] = b0 * p1 - b1 * p0
    for i in range(n_b + 1):
        idx = breaks[i] if i < n_b else half_points[2]
        for ll in range(n_l):
            f = fidx[ll]
            for r in range(3):
                pt[0, r, i * L + ll] = pos[f, idx, r]
                pt[1, r, i * L + ll] = fr[f, idx, r, 2]
    # breakpoint by breakpoint, grating by grating: X_n(b) = X_n(b − 1) + the piece's rule (in place), then at
    # once Y(b) += X_n V_n X_nᵀ (upper triangle) and Z(b) += X_n S_n; every operand is a row of LANES frames at
    # a constant offset of a small array, so that each update is a handful of vector instructions on data in
    # the first-level cache (no pass over every breakpoint per grating)
    n_sh = zb.shape[1] // (6 * L)
    # the shared columns through their interpolated curvature error: Z = Σ_n X_n S_n = ∫ (R E, (R E) × p) δk_sh,
    # δk_sh(u) = Σ_n B_n(u) S_n, so per rule point w_e δk_sh(u_e) once (n_g multiply-adds per column) and Z runs
    # along the pieces like X_n (12 · n_sh per rule point instead of 12 · n_sh per grating and breakpoint)
    nw = 2 * n_sh * L
    wsq[:] = 0.0
    wsqh[:] = 0.0
    for n in range(n_g):
        sn = sprep[n]
        for j in range(n_int):
            for e in range(3):
                w, dst = wb[e, j, n], wsq[j, e]
                for i in range(nw):
                    dst[i] += w * sn[i]
        for e in range(3):
            w, dst = wh[e, n], wsqh[e]
            for i in range(nw):
                dst[i] += w * sn[i]
    # V_n = L Lᵀ per grating and frame, L = ((l00, 0), (l10, l11)) (V_n is a covariance: l00 = 0 only where
    # v00 = 0, and then v01 = 0; the clamp keeps a rounding below zero out of the root)
    for n in range(n_g):
        vr, lr = vrep[n], lrep[n]
        for ll in range(L):
            l00 = np.sqrt(vr[ll])
            l10 = vr[L + ll] / l00 if l00 > 0.0 else 0.0
            lr[ll] = l00
            lr[L + ll] = l10
            lr[2 * L + ll] = np.sqrt(max(vr[2 * L + ll] - l10 * l10, 0.0))
    xn[:] = 0.0
    yb[0] = 0.0
    zb[0] = 0.0
    for b in range(1, n_b + 1):
        ybb, zbb = yb[b], zb[b]
        if b < n_b:  # the running integrals at breakpoint b: piece b − 1's rule added
            zbb[:] = zb[b - 1]
            for e in range(3):
                _shared(g[b - 1, e], wsq[b - 1, e], zbb, n_sh)
        else:  # the first piece's middle point, from the base by its own rule
            zbb[:] = 0.0
            for e in range(3):
                _shared(gh[e], wsqh[e], zbb, n_sh)
        ybb[:] = 0.0
        if b < n_b:
            # two gratings at a time: X_n and X_m updated in one pass over the piece's integrand, then both
            # added into Y(b) in one pass over it (Y's rows are loaded and stored once per pair: the update is
            # bound by the first-level cache's stores, not by its arithmetic)
            g0, g1, g2 = g[b - 1, 0], g[b - 1, 1], g[b - 1, 2]
            for n in range(0, n_g - 1, 2):
                w0, w1, w2 = wb[0, b - 1, n], wb[1, b - 1, n], wb[2, b - 1, n]
                u0, u1, u2 = wb[0, b - 1, n + 1], wb[1, b - 1, n + 1], wb[2, b - 1, n + 1]
                xr, xs = xn[n], xn[n + 1]
                for i in range(12 * L):
                    a0, a1, a2 = g0[i], g1[i], g2[i]
                    xr[i] += w0 * a0 + w1 * a1 + w2 * a2
                    xs[i] += u0 * a0 + u1 * a1 + u2 * a2
                _accumulate2(xr, xs, lrep[n], lrep[n + 1], ybb)
            if n_g % 2:
                n = n_g - 1
                w0, w1, w2 = wb[0, b - 1, n], wb[1, b - 1, n], wb[2, b - 1, n]
                xr = xn[n]
                for i in range(12 * L):
                    xr[i] += w0 * g0[i] + w1 * g1[i] + w2 * g2[i]
                _accumulate(xr, lrep[n], ybb)
        else:
            for n in range(n_g):
                w0, w1, w2 = wh[0, n], wh[1, n], wh[2, n]
                for i in range(12 * L):
                    xm[i] = w0 * gh[0, i] + w1 * gh[1, i] + w2 * gh[2, i]
                _accumulate(xm, lrep[n], ybb)
    # into the layout of _c_and_dc
    t = 0
    for r in range(6):
        for c in range(r, 6):
            for b in range(n_b + 1):
                for ll in range(L):
                    y[r, c, b * L + ll] = yb[b, t * L + ll]
            t += 1
    for r in range(6):
        for q in range(n_sh):
            for b in range(n_b + 1):
                for ll in range(L):
                    z[r, q, b * L + ll] = zb[b, (q * 6 + r) * L + ll]
    _c_and_dc(y, z, pt, m, cb)  # Y += Z Zᵀ, then C and C' at the breakpoints of every frame
    # every point from its piece's coefficients (as _frame), plus the base angle exactly; ``fw`` holds the
    # piece's coefficients (rows e·9 + r·3 + c), the point's position (36–38) and covariance (39–47) at constant
    # offsets, so that the loop over the frames is vectorised as in twin._kernels.exp_lanes
    cur = -1
    for j in range(n_p):
        q = interval[j]
        if q != cur:
            cur = q
            for r in range(3):
                for c in range(3):
                    rc = r * 3 + c
                    if q == 0:
                        for e in range(3):
                            f0, f1, f2 = first[e, 0], first[e, 1], first[e, 2]
                            for ll in range(L):
                                fw[(e * 9 + rc) * L + ll] = (f0 * cb[0, r, c, L + ll] + f1 * (h0 * cb[1, r, c, L + ll])
                                                             + f2 * cb[0, r, c, n_b * L + ll])
                        for ll in range(L):
                            fw[(27 + rc) * L + ll] = 0.0
                    else:
                        for ll in range(L):
                            fw[rc * L + ll] = cb[0, r, c, q * L + ll]
                            fw[(9 + rc) * L + ll] = cb[1, r, c, q * L + ll]
                            fw[(18 + rc) * L + ll] = cb[0, r, c, (q + 1) * L + ll]
                            fw[(27 + rc) * L + ll] = cb[1, r, c, (q + 1) * L + ll]
        for ll in range(n_l):
            f = fidx[ll]
            fw[36 * L + ll] = pos[f, j, 0]
            fw[37 * L + ll] = pos[f, j, 1]
            fw[38 * L + ll] = pos[f, j, 2]
        _fill_point(fw, hw[j, 0], hw[j, 1], hw[j, 2], hw[j, 3], base_var)
        for ll in range(n_l):  # nine stores a point (the upper triangle mirrored, each diagonal element once)
            o = out[fidx[ll], j]
            o[0, 0] = fw[39 * L + ll]
            o[1, 1] = fw[43 * L + ll]
            o[2, 2] = fw[47 * L + ll]
            val = fw[40 * L + ll]
            o[0, 1] = val
            o[1, 0] = val
            val = fw[41 * L + ll]
            o[0, 2] = val
            o[2, 0] = val
            val = fw[44 * L + ll]
            o[1, 2] = val
            o[2, 1] = val


@njit(cache=True, nogil=True, fastmath=_FAST, inline="always")
def _accumulate(x, l, yb):  # pragma: no cover (compiled)
    """Y += X V Xᵀ (upper triangle, row-major) for one grating and LANES frames as W Wᵀ, W = X L with L the
    lower Cholesky factor of V_n (V_n = L Lᵀ; 18 multiply-adds for W and 42 for its 21 products where X V and
    (X V) Xᵀ take 24 and 42, and 12 values live per grating instead of 24); every array 1-D with rows of LANES
    frames: ``x`` (12 rows) X_n, row r·2 + c; ``l`` (3 rows) (l00, l10, l11); ``yb`` (21 rows). Written out at
    constant offsets: a few vector instructions per row."""
    L = LANES
    for ll in range(L):
        l0, l1, l2 = l[ll], l[L + ll], l[2 * L + ll]
        ea = x[0 * L + ll]
        eb = x[1 * L + ll]
        w00 = ea * l0 + eb * l1
        w01 = eb * l2
        ea = x[2 * L + ll]
        eb = x[3 * L + ll]
        w10 = ea * l0 + eb * l1
        w11 = eb * l2
        ea = x[4 * L + ll]
        eb = x[5 * L + ll]
        w20 = ea * l0 + eb * l1
        w21 = eb * l2
        ea = x[6 * L + ll]
        eb = x[7 * L + ll]
        w30 = ea * l0 + eb * l1
        w31 = eb * l2
        ea = x[8 * L + ll]
        eb = x[9 * L + ll]
        w40 = ea * l0 + eb * l1
        w41 = eb * l2
        ea = x[10 * L + ll]
        eb = x[11 * L + ll]
        w50 = ea * l0 + eb * l1
        w51 = eb * l2
        yb[0 * L + ll] += w00 * w00 + w01 * w01
        yb[1 * L + ll] += w00 * w10 + w01 * w11
        yb[2 * L + ll] += w00 * w20 + w01 * w21
        yb[3 * L + ll] += w00 * w30 + w01 * w31
        yb[4 * L + ll] += w00 * w40 + w01 * w41
        yb[5 * L + ll] += w00 * w50 + w01 * w51
        yb[6 * L + ll] += w10 * w10 + w11 * w11
        yb[7 * L + ll] += w10 * w20 + w11 * w21
        yb[8 * L + ll] += w10 * w30 + w11 * w31
        yb[9 * L + ll] += w10 * w40 + w11 * w41
        yb[10 * L + ll] += w10 * w50 + w11 * w51
        yb[11 * L + ll] += w20 * w20 + w21 * w21
        yb[12 * L + ll] += w20 * w30 + w21 * w31
        yb[13 * L + ll] += w20 * w40 + w21 * w41
        yb[14 * L + ll] += w20 * w50 + w21 * w51
        yb[15 * L + ll] += w30 * w30 + w31 * w31
        yb[16 * L + ll] += w30 * w40 + w31 * w41
        yb[17 * L + ll] += w30 * w50 + w31 * w51
        yb[18 * L + ll] += w40 * w40 + w41 * w41
        yb[19 * L + ll] += w40 * w50 + w41 * w51
        yb[20 * L + ll] += w50 * w50 + w51 * w51


@njit(cache=True, nogil=True, fastmath=_FAST, inline="always")
def _accumulate2(x, xb, l, lb, yb):  # pragma: no cover (compiled)
    """:func:`_accumulate` for two gratings at once: Y += W Wᵀ + W_b W_bᵀ, each row of ``yb`` loaded and stored
    once."""
    L = LANES
    for ll in range(L):
        l0, l1, l2 = l[ll], l[L + ll], l[2 * L + ll]
        ea = x[0 * L + ll]
        eb = x[1 * L + ll]
        w00 = ea * l0 + eb * l1
        w01 = eb * l2
        ea = x[2 * L + ll]
        eb = x[3 * L + ll]
        w10 = ea * l0 + eb * l1
        w11 = eb * l2
        ea = x[4 * L + ll]
        eb = x[5 * L + ll]
        w20 = ea * l0 + eb * l1
        w21 = eb * l2
        ea = x[6 * L + ll]
        eb = x[7 * L + ll]
        w30 = ea * l0 + eb * l1
        w31 = eb * l2
        ea = x[8 * L + ll]
        eb = x[9 * L + ll]
        w40 = ea * l0 + eb * l1
        w41 = eb * l2
        ea = x[10 * L + ll]
        eb = x[11 * L + ll]
        w50 = ea * l0 + eb * l1
        w51 = eb * l2
        bl0, bl1, bl2 = lb[ll], lb[L + ll], lb[2 * L + ll]
        bea = xb[0 * L + ll]
        beb = xb[1 * L + ll]
        bw00 = bea * bl0 + beb * bl1
        bw01 = beb * bl2
        bea = xb[2 * L + ll]
        beb = xb[3 * L + ll]
        bw10 = bea * bl0 + beb * bl1
        bw11 = beb * bl2
        bea = xb[4 * L + ll]
        beb = xb[5 * L + ll]
        bw20 = bea * bl0 + beb * bl1
        bw21 = beb * bl2
        bea = xb[6 * L + ll]
        beb = xb[7 * L + ll]
        bw30 = bea * bl0 + beb * bl1
        bw31 = beb * bl2
        bea = xb[8 * L + ll]
        beb = xb[9 * L + ll]
        bw40 = bea * bl0 + beb * bl1
        bw41 = beb * bl2
        bea = xb[10 * L + ll]
        beb = xb[11 * L + ll]
        bw50 = bea * bl0 + beb * bl1
        bw51 = beb * bl2
        yb[0 * L + ll] += (w00 * w00 + w01 * w01) + (bw00 * bw00 + bw01 * bw01)
        yb[1 * L + ll] += (w00 * w10 + w01 * w11) + (bw00 * bw10 + bw01 * bw11)
        yb[2 * L + ll] += (w00 * w20 + w01 * w21) + (bw00 * bw20 + bw01 * bw21)
        yb[3 * L + ll] += (w00 * w30 + w01 * w31) + (bw00 * bw30 + bw01 * bw31)
        yb[4 * L + ll] += (w00 * w40 + w01 * w41) + (bw00 * bw40 + bw01 * bw41)
        yb[5 * L + ll] += (w00 * w50 + w01 * w51) + (bw00 * bw50 + bw01 * bw51)
        yb[6 * L + ll] += (w10 * w10 + w11 * w11) + (bw10 * bw10 + bw11 * bw11)
        yb[7 * L + ll] += (w10 * w20 + w11 * w21) + (bw10 * bw20 + bw11 * bw21)
        yb[8 * L + ll] += (w10 * w30 + w11 * w31) + (bw10 * bw30 + bw11 * bw31)
        yb[9 * L + ll] += (w10 * w40 + w11 * w41) + (bw10 * bw40 + bw11 * bw41)
        yb[10 * L + ll] += (w10 * w50 + w11 * w51) + (bw10 * bw50 + bw11 * bw51)
        yb[11 * L + ll] += (w20 * w20 + w21 * w21) + (bw20 * bw20 + bw21 * bw21)
        yb[12 * L + ll] += (w20 * w30 + w21 * w31) + (bw20 * bw30 + bw21 * bw31)
        yb[13 * L + ll] += (w20 * w40 + w21 * w41) + (bw20 * bw40 + bw21 * bw41)
        yb[14 * L + ll] += (w20 * w50 + w21 * w51) + (bw20 * bw50 + bw21 * bw51)
        yb[15 * L + ll] += (w30 * w30 + w31 * w31) + (bw30 * bw30 + bw31 * bw31)
        yb[16 * L + ll] += (w30 * w40 + w31 * w41) + (bw30 * bw40 + bw31 * bw41)
        yb[17 * L + ll] += (w30 * w50 + w31 * w51) + (bw30 * bw50 + bw31 * bw51)
        yb[18 * L + ll] += (w40 * w40 + w41 * w41) + (bw40 * bw40 + bw41 * bw41)
        yb[19 * L + ll] += (w40 * w50 + w41 * w51) + (bw40 * bw50 + bw41 * bw51)
        yb[20 * L + ll] += (w50 * w50 + w51 * w51) + (bw50 * bw50 + bw51 * bw51)


@njit(cache=True, nogil=True, fastmath=_FAST, inline="always")
def _shared(gq, wq, zb, n_sh):  # pragma: no cover (compiled)
    """Z += G (w δk_sh) at one rule point for LANES frames: ``gq`` (12 rows) the integrand, row r·2 + c; ``wq``
    (2 · n_sh rows) the rule's weight times the shared columns' interpolated curvature error, row q·2 + c; ``zb``
    (6 · n_sh rows), row q·6 + r. One column at a time, so that the offsets within it are constants."""
    L = LANES
    for q in range(n_sh):
        sq = wq[2 * q * L:2 * (q + 1) * L]
        zq = zb[6 * q * L:6 * (q + 1) * L]
        for ll in range(L):
            s0, s1 = sq[ll], sq[L + ll]
            for r in range(6):
                zq[r * L + ll] += gq[2 * r * L + ll] * s0 + gq[(2 * r + 1) * L + ll] * s1


@njit(cache=True, nogil=True, fastmath=_FAST)
def _fill_point(fw, w0, w1, w2, w3, base_var):  # pragma: no cover (compiled)
    """One point's covariance for the LANES frames of ``fw`` (:func:`_lanes_block`): the Hermite (or first
    piece's) weights on the piece's coefficients, plus σ_b² (|p|² I − p pᵀ). Branch-free, constant offsets."""
    L = LANES
    for ll in range(L):
        q0, q1, q2 = fw[36 * L + ll], fw[37 * L + ll], fw[38 * L + ll]
        pp = q0 * q0 + q1 * q1 + q2 * q2
        for r in range(3):
            for c in range(3):
                rc = r * 3 + c
                val = (w0 * fw[rc * L + ll] + w1 * fw[(9 + rc) * L + ll] + w2 * fw[(18 + rc) * L + ll]
                       + w3 * fw[(27 + rc) * L + ll])
                pr = fw[(36 + r) * L + ll]
                pc = fw[(36 + c) * L + ll]
                diag = pp if r == c else 0.0
                fw[(39 + rc) * L + ll] = val + base_var * (diag - pr * pc)
