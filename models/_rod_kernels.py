"""Compiled per-edge loops of the rod-state reader (numba): they run at the sensor rate, up to 1 kHz.

The numpy formulation in :mod:`models.rod_state` documents the method; these kernels do the same arithmetic in
one pass without temporaries (≈ 2 µs instead of ≈ 50 µs for 100 segments).

At the sensor rate (:class:`models.rod_state.RodView`) the read takes the small angles by their Taylor series
instead of the library's sine, cosine and arctangent, which were most of its cost
(:func:`series_frames_and_darboux`). Each series is used only inside a bound where its truncation error is below
1e-17 relative (far below the rounding of a double); outside it the exact functions take over, edge by edge or
vertex by vertex. The result differs from the exact read (:func:`frames_and_darboux`, which one-off reads and
the lumen coupler's physics keep) by rounding alone: frame entries within 2e-15 and Darboux vectors within
≈ 1e-15/l̄ (≈ 1e-13 1/m at 2 mm segments; tests/test_rod_read.py holds them to 2e-15 and 1e-12 1/m).

* The twist angle of edge e enters as cos and sin of θ_e + roll. Written (θ_e − θ_ref) + (roll + θ_ref), with
  θ_ref halfway between the twist angles of the first twisted edge and the last, the second angle is one exact
  cosine and sine per read and the first is small wherever the rod's twist spans less than 1 rad: for
  |δ| ≤ 0.5 the series of sin δ to δ¹⁵ and of cos δ to δ¹⁴ leave at most δ¹⁷/17! ≤ 2.1e-20 and
  δ¹⁶/16! ≤ 7.3e-19.
* The logarithm of the rotation Q between neighbouring frames: with w = vee(Q − Qᵀ) = 2 sin φ n̂ and
  tr Q = 1 + 2 cos φ, t = tan(φ/2) = |w|/(tr Q + 1), and log Q = w · φ/|w| = w · 2h · atan(t)/t with
  h = 1/(tr Q + 1). The series atan(t)/t = Σ (−t²)ᵏ/(2k + 1) to k = 9 is used for t² ≤ 0.0225 (φ ≤ 0.298
  rad: bends up to 150 1/m at 2 mm segments): alternating, it leaves at most t²⁰/21 ≤ 1.6e-18. Neither a
  square root nor an arctangent is left, and no division but h.
"""

from __future__ import annotations

import numpy as np
from numba import carray, njit

from twin._numba_entry import float64_at
from twin.so3 import exp_entries, log_entries

# the series' bounds and the reciprocals of their divisors (numba reads module floats as constants)
_SIN_COS_MAX = 0.5  # |δ|, rad
_TAN_HALF_SQ_MAX = 0.0225  # t² = tan²(φ/2)
_S = tuple(1.0 / d for d in (6, 20, 42, 72, 110, 156, 210))  # sin: (2k)(2k + 1)
_C = tuple(1.0 / d for d in (2, 12, 30, 56, 90, 132, 182))  # cos: (2k − 1)(2k)
_S6, _S20, _S42, _S72, _S110, _S156, _S210 = _S
_C2, _C12, _C30, _C56, _C90, _C132, _C182 = _C
_A3, _A5, _A7, _A9, _A11, _A13, _A15, _A17, _A19 = (1.0 / d for d in (3, 5, 7, 9, 11, 13, 15, 17, 19))


@njit(cache=True, nogil=True, inline="always")
def _qdot(frames, i, j, k):
    """Entry (j, k) of R_iᵀ R_{i+1}: column j of edge i's frame dotted with column k of edge i + 1's."""
    return (frames[i, 0, j] * frames[i + 1, 0, k] + frames[i, 1, j] * frames[i + 1, 1, k]
            + frames[i, 2, j] * frames[i + 1, 2, k])


@njit(cache=True, nogil=True, inline="always")
def _sin_cos_small(d):
    """(sin d, cos d) by their Taylor series, for |d| ≤ ``_SIN_COS_MAX`` (the module docstring's bound)."""
    d2 = d * d
    s = d * (1.0 - d2 * _S6 * (1.0 - d2 * _S20 * (1.0 - d2 * _S42 * (1.0 - d2 * _S72 * (
        1.0 - d2 * _S110 * (1.0 - d2 * _S156 * (1.0 - d2 * _S210)))))))
    c = 1.0 - d2 * _C2 * (1.0 - d2 * _C12 * (1.0 - d2 * _C30 * (1.0 - d2 * _C56 * (
        1.0 - d2 * _C90 * (1.0 - d2 * _C132 * (1.0 - d2 * _C182))))))
    return s, c


@njit(cache=True, nogil=True, inline="always")
def _transported(plastic, e, tx, ty, tz):
    """MuJoCo's reference director of edge e (``plastic``: (t_old, u_old) per edge) parallel-transported from
    t_old to the tangent t: u + 2 (a·u) t − ((a + t)·u) (a + t) / (1 + a·t) with a = t_old."""
    ax, ay, az = plastic[6 * e], plastic[6 * e + 1], plastic[6 * e + 2]
    ux, uy, uz = plastic[6 * e + 3], plastic[6 * e + 4], plastic[6 * e + 5]
    wx, wy, wz = ax + tx, ay + ty, az + tz
    c_at = ax * tx + ay * ty + az * tz
    au = ax * ux + ay * uy + az * uz
    wu = (wx * ux + wy * uy + wz * uz) / (1.0 + c_at)
    return ux + 2.0 * au * tx - wu * wx, uy + 2.0 * au * ty - wu * wy, uz + 2.0 * au * tz - wu * wz


@njit(cache=True, nogil=True)
def frames_and_darboux(x, plastic, theta, site_x, inv_lbar, frames, darboux):
    """Material frames per edge and discrete Darboux vectors per interior vertex.

    Parameters
    ----------
    x : (nv, 3) vertex positions.
    plastic : (6 ne,) per edge (t_old, u_old), MuJoCo's reference frames.
    theta : (ne,) twist-joint angles (0 for a clamped edge).
    site_x : (3,) x axis of the base site; its direction fixes the roll of the clamped edge's d1. A zero vector
        leaves MuJoCo's roll.
    inv_lbar : (ne − 1,) 1 / mean rest length of the two edges at each interior vertex.
    frames : (ne, 3, 3) out: columns d1, d2, d3.
    darboux : (ne − 1, 3) out: log(R_{i−1}ᵀ R_i) / l̄_i.
    """
    ne = theta.size
    roll = 0.0
    for e in range(ne):
        tx = x[e + 1, 0] - x[e, 0]
        ty = x[e + 1, 1] - x[e, 1]
        tz = x[e + 1, 2] - x[e, 2]
        n = np.sqrt(tx * tx + ty * ty + tz * tz)
        tx /= n
        ty /= n
        tz /= n
        ux, uy, uz = _transported(plastic, e, tx, ty, tz)
        vx, vy, vz = ty * uz - tz * uy, tz * ux - tx * uz, tx * uy - ty * ux
        if e == 0 and (site_x[0] != 0.0 or site_x[1] != 0.0 or site_x[2] != 0.0):
            roll = np.arctan2(site_x[0] * vx + site_x[1] * vy + site_x[2] * vz,
                              site_x[0] * ux + site_x[1] * uy + site_x[2] * uz) - theta[0]
        th = theta[e] + roll
        c, s = np.cos(th), np.sin(th)
        frames[e, 0, 0] = c * ux + s * vx
        frames[e, 1, 0] = c * uy + s * vy
        frames[e, 2, 0] = c * uz + s * vz
        frames[e, 0, 1] = c * vx - s * ux
        frames[e, 1, 1] = c * vy - s * uy
        frames[e, 2, 1] = c * vz - s * uz
        frames[e, 0, 2] = tx
        frames[e, 1, 2] = ty
        frames[e, 2, 2] = tz
    for i in range(ne - 1):
        # Q = R_{i}ᵀ R_{i+1}; only its antisymmetric part and trace are needed (scalars: no allocation per vertex)
        w0, w1, w2 = log_entries(_qdot(frames, i, 0, 0), _qdot(frames, i, 0, 1), _qdot(frames, i, 0, 2),
                                 _qdot(frames, i, 1, 0), _qdot(frames, i, 1, 1), _qdot(frames, i, 1, 2),
                                 _qdot(frames, i, 2, 0), _qdot(frames, i, 2, 1), _qdot(frames, i, 2, 2))
        darboux[i, 0] = w0 * inv_lbar[i]
        darboux[i, 1] = w1 * inv_lbar[i]
        darboux[i, 2] = w2 * inv_lbar[i]


SCRATCH_ROWS = 14  # the rows (n_edges,) of series_frames_and_darboux's scratch


# numpy's error model: a division by zero gives inf or NaN instead of raising, which lets LLVM run the loops on
# vector registers (a NaN vertex is then redone by the exact function and stays NaN)
@njit(cache=True, nogil=True, error_model="numpy")
def series_frames_and_darboux(x, plastic, theta, site_x, inv_lbar, frames, darboux, scratch):
    """:func:`frames_and_darboux` with the small angles by their series (the module docstring), equal to it to
    rounding, for reads at the sensor rate.

    The work is laid out in rows of ``scratch`` (``SCRATCH_ROWS``, n_edges), one per coordinate, so that the
    series, the frames' columns and the rotations between neighbouring frames run on vector registers, several
    edges at a time; an edge or vertex outside the series' bounds is then redone by the exact functions. Only
    the tangents and MuJoCo's reference frames are read edge by edge (their entries are interleaved in
    ``mjData``).
    """
    ne = theta.size
    t_x, t_y, t_z, u_x, u_y, u_z = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4], scratch[5]
    a_x, a_y, a_z, b_x, b_y, b_z = scratch[6], scratch[7], scratch[8], scratch[9], scratch[10], scratch[11]
    cos_t, sin_t = scratch[12], scratch[13]
    for e in range(ne):
        tx = x[e + 1, 0] - x[e, 0]
        ty = x[e + 1, 1] - x[e, 1]
        tz = x[e + 1, 2] - x[e, 2]
        n = 1.0 / np.sqrt(tx * tx + ty * ty + tz * tz)  # one division, not three
        tx, ty, tz = tx * n, ty * n, tz * n
        t_x[e], t_y[e], t_z[e] = tx, ty, tz
        u_x[e], u_y[e], u_z[e] = _transported(plastic, e, tx, ty, tz)
    roll = 0.0
    if site_x[0] != 0.0 or site_x[1] != 0.0 or site_x[2] != 0.0:
        vx = t_y[0] * u_z[0] - t_z[0] * u_y[0]
        vy = t_z[0] * u_x[0] - t_x[0] * u_z[0]
        vz = t_x[0] * u_y[0] - t_y[0] * u_x[0]
        roll = np.arctan2(site_x[0] * vx + site_x[1] * vy + site_x[2] * vz,
                          site_x[0] * u_x[0] + site_x[1] * u_y[0] + site_x[2] * u_z[0]) - theta[0]
    # θ_e + roll = (θ_e − θ_ref) + (roll + θ_ref): θ_ref between the twisted edges' ends, the first angle small
    # for a rod whose twist spans less than 1 rad (any other edge is redone below)
    ref = 0.5 * (theta[min(1, ne - 1)] + theta[ne - 1])
    c_ref, s_ref = np.cos(roll + ref), np.sin(roll + ref)
    for e in range(ne):  # on vector registers: no branch, no call
        sd, cd = _sin_cos_small(theta[e] - ref)
        cos_t[e] = c_ref * cd - s_ref * sd
        sin_t[e] = s_ref * cd + c_ref * sd
    for e in range(ne):
        if not abs(theta[e] - ref) <= _SIN_COS_MAX:
            th = theta[e] + roll
            cos_t[e], sin_t[e] = np.cos(th), np.sin(th)
    for e in range(ne):  # d1 = c u + s v, d2 = c v − s u with v = t × u
        tx, ty, tz, ux, uy, uz, c, s = t_x[e], t_y[e], t_z[e], u_x[e], u_y[e], u_z[e], cos_t[e], sin_t[e]
        vx, vy, vz = ty * uz - tz * uy, tz * ux - tx * uz, tx * uy - ty * ux
        a_x[e], a_y[e], a_z[e] = c * ux + s * vx, c * uy + s * vy, c * uz + s * vz
        b_x[e], b_y[e], b_z[e] = c * vx - s * ux, c * vy - s * uy, c * vz - s * uz
    for e in range(ne):
        frames[e, 0, 0], frames[e, 1, 0], frames[e, 2, 0] = a_x[e], a_y[e], a_z[e]
        frames[e, 0, 1], frames[e, 1, 1], frames[e, 2, 1] = b_x[e], b_y[e], b_z[e]
        frames[e, 0, 2], frames[e, 1, 2], frames[e, 2, 2] = t_x[e], t_y[e], t_z[e]
    # Q = R_iᵀ R_{i+1} from the rows at i and i + 1: its antisymmetric part w and trace, then the series; the rows
    # of u and of cos θ are free again and take w and the vertices the series must not serve
    w_0, w_1, w_2, exact = u_x, u_y, u_z, cos_t
    for i in range(ne - 1):  # on vector registers
        j = i + 1
        q00 = a_x[i] * a_x[j] + a_y[i] * a_y[j] + a_z[i] * a_z[j]
        q11 = b_x[i] * b_x[j] + b_y[i] * b_y[j] + b_z[i] * b_z[j]
        q22 = t_x[i] * t_x[j] + t_y[i] * t_y[j] + t_z[i] * t_z[j]
        w0 = (t_x[i] * b_x[j] + t_y[i] * b_y[j] + t_z[i] * b_z[j]) - (b_x[i] * t_x[j] + b_y[i] * t_y[j]
                                                                       + b_z[i] * t_z[j])
        w1 = (a_x[i] * t_x[j] + a_y[i] * t_y[j] + a_z[i] * t_z[j]) - (t_x[i] * a_x[j] + t_y[i] * a_y[j]
                                                                       + t_z[i] * a_z[j])
        w2 = (b_x[i] * a_x[j] + b_y[i] * a_y[j] + b_z[i] * a_z[j]) - (a_x[i] * b_x[j] + a_y[i] * b_y[j]
                                                                       + a_z[i] * b_z[j])
        tr = q00 + q11 + q22
        h = 1.0 / (tr + 1.0)
        y = (w0 * w0 + w1 * w1 + w2 * w2) * (h * h)
        f = 2.0 * h * (1.0 - y * (_A3 - y * (_A5 - y * (_A7 - y * (_A9 - y * (_A11 - y * (_A13 - y * (
            _A15 - y * (_A17 - y * _A19)))))))))
        exact[i] = 0.0 if (tr > 1.0 and y <= _TAN_HALF_SQ_MAX) else 1.0  # false for NaN too
        w_0[i], w_1[i], w_2[i] = w0 * f * inv_lbar[i], w1 * f * inv_lbar[i], w2 * f * inv_lbar[i]
    for i in range(ne - 1):
        if exact[i] != 0.0:
            w0, w1, w2 = log_entries(_qdot(frames, i, 0, 0), _qdot(frames, i, 0, 1), _qdot(frames, i, 0, 2),
                                     _qdot(frames, i, 1, 0), _qdot(frames, i, 1, 1), _qdot(frames, i, 1, 2),
                                     _qdot(frames, i, 2, 0), _qdot(frames, i, 2, 1), _qdot(frames, i, 2, 2))
            w_0[i], w_1[i], w_2[i] = w0 * inv_lbar[i], w1 * inv_lbar[i], w2 * inv_lbar[i]
        darboux[i, 0], darboux[i, 1], darboux[i, 2] = w_0[i], w_1[i], w_2[i]


@njit(cache=True, nogil=True)
def frames_at(edge_s, edge_frames, darboux, s, out):
    """Geodesic interpolation of edge frames at arc lengths ``s`` (clamped to the edge midpoints)."""
    ne = edge_s.size
    for q in range(s.size):
        sq = min(max(s[q], edge_s[0]), edge_s[ne - 1])
        e = np.searchsorted(edge_s, sq, side="right") - 1
        e = min(max(e, 0), ne - 2)
        h = sq - edge_s[e]
        wx, wy, wz = h * darboux[e, 0], h * darboux[e, 1], h * darboux[e, 2]
        e00, e01, e02, e10, e11, e12, e20, e21, e22 = exp_entries(wx, wy, wz)
        for r in range(3):
            f0, f1, f2 = edge_frames[e, r, 0], edge_frames[e, r, 1], edge_frames[e, r, 2]
            out[q, r, 0] = f0 * e00 + f1 * e10 + f2 * e20
            out[q, r, 1] = f0 * e01 + f1 * e11 + f2 * e21
            out[q, r, 2] = f0 * e02 + f1 * e12 + f2 * e22


@njit(cache=True, nogil=True)
def positions_at(s_grid, positions, s, out):
    """Linear interpolation of the vertex positions (n_vertices, 3) along the polyline at arc lengths ``s``,
    clamped to the rod (``np.interp``'s arithmetic per coordinate), into ``out`` (len(s), 3)."""
    n = s_grid.size
    for q in range(s.size):
        sq = s[q]
        if sq != sq:  # NaN in, NaN out (as np.interp)
            for k in range(3):
                out[q, k] = np.nan
            continue
        if sq <= s_grid[0]:
            for k in range(3):
                out[q, k] = positions[0, k]
            continue
        if sq >= s_grid[n - 1]:
            for k in range(3):
                out[q, k] = positions[n - 1, k]
            continue
        i = np.searchsorted(s_grid, sq, side="right") - 1
        a = (sq - s_grid[i]) / (s_grid[i + 1] - s_grid[i])
        for k in range(3):
            out[q, k] = positions[i, k] + a * (positions[i + 1, k] - positions[i, k])


@njit(cache=True, nogil=True)
def bound_frames_and_darboux(x, plastic, qpos, twist_edges, twist_qadr, theta, site_row, inv_lbar, frames, darboux):
    """:func:`frames_and_darboux` straight from views of ``mjData`` (:class:`models.rod_state.RodView`).

    ``qpos`` is all of ``mjData.qpos``: the twist angles are gathered into ``theta`` (n_edges,) at ``twist_edges``
    from ``twist_qadr`` (the clamped edge's entry stays 0); ``site_row`` is the base site's ``site_xmat`` row (9,),
    whose x axis is its entries 0, 3, 6 (zeros: no site). Returns False, computing nothing, while ``plastic`` is
    still zero (before the first step: the caller rebuilds the frames as MuJoCo restarts them).
    """
    if plastic[3] == 0.0 and plastic[4] == 0.0 and plastic[5] == 0.0:
        return False
    for k in range(twist_edges.size):
        theta[twist_edges[k]] = qpos[twist_qadr[k]]
    frames_and_darboux(x, plastic, theta, site_row[::3], inv_lbar, frames, darboux)
    return True


READ_HEADER = 2  # a view buffer's leading entries: [the saved inputs are valid (1.0), reads so far]


@njit(cache=True, nogil=True, inline="always")
def _view_offsets(ne):
    """Where the parts of a view buffer (:func:`view_parts`) end, for a rod of ``ne`` edges."""
    a = READ_HEADER
    b = a + ne - 1
    c = b + ne
    d = c + 3 * (ne + 1) + 7 * ne + 9
    f = d + 9 * ne
    g = f + 3 * (ne - 1)
    return a, b, c, d, f, g, g + SCRATCH_ROWS * ne


@njit(cache=True, nogil=True)
def view_parts(buffer, ne):
    """The parts of a :class:`models.rod_state.RodView` buffer for a rod of ``ne`` edges: the header, 1/l̄
    (ne − 1,), θ (ne,), the inputs of the last read (3 (ne + 1) + 6 ne + ne + 9,), frames (ne, 3, 3), Darboux
    vectors (ne − 1, 3), the read's scratch (``SCRATCH_ROWS``, ne) and the index (the rest: the number of twist
    joints n_tw, the edges they turn (n_tw,), their ``qpos`` addresses (n_tw,) and the kinematic trees of the
    rod's bodies, as floats)."""
    a, b, c, d, f, g, h = _view_offsets(ne)
    return (buffer[:a], buffer[a:b], buffer[b:c], buffer[c:d], buffer[d:f].reshape((ne, 3, 3)),
            buffer[f:g].reshape((ne - 1, 3)), buffer[g:h].reshape((SCRATCH_ROWS, ne)), buffer[h:])


@njit(cache=True, nogil=True, inline="always")
def view_parts_in_call(buffer, ne):
    """:func:`view_parts` as views made from the buffer's address, for use inside one compiled call only (they
    keep no reference to the buffer): numba's slicing and reshaping check each part, ≈ 30–50 ns a part a call."""
    p = buffer.ctypes.data
    a, b, c, d, f, g, h = _view_offsets(ne)
    return (carray(float64_at(p), a), carray(float64_at(p + 8 * a), b - a), carray(float64_at(p + 8 * b), c - b),
            carray(float64_at(p + 8 * c), d - c), carray(float64_at(p + 8 * d), (ne, 3, 3)),
            carray(float64_at(p + 8 * f), (ne - 1, 3)), carray(float64_at(p + 8 * g), (SCRATCH_ROWS, ne)),
            carray(float64_at(p + 8 * h), buffer.size - h))


@njit(cache=True, nogil=True, inline="always")
def _kept(values, saved, o, store):
    """Copy ``values`` (flat, C-contiguous) to ``saved[o:]`` (``store``) or tell whether they are there bit for bit
    (compared as 64-bit integers over the whole length, without an early exit, so that the loop runs on vector
    registers); the offset after them and the answer."""
    n = values.size
    if store:
        saved[o : o + n] = values
        return o + n, True
    a, b = values.view(np.int64), saved[o : o + n].view(np.int64)
    diff = 0
    for k in range(n):
        diff |= a[k] ^ b[k]
    return o + n, diff == 0


@njit(cache=True, nogil=True)
def view_read(x, plastic, qpos, site_row, tree_asleep, buffer):
    """The rod read of a :class:`models.rod_state.RodView`: :func:`series_frames_and_darboux`, straight
    from views of ``mjData``, into the view's ``buffer`` (:func:`view_parts`).

    ``qpos`` is all of ``mjData.qpos`` and ``tree_asleep`` all of ``mjData.tree_asleep``; ``site_row`` is the base
    site's ``site_xmat`` row (9,), whose x axis is its entries 0, 3, 6 (zeros: no site). The buffer's index (the
    twist joints' edges and ``qpos`` addresses, the kinematic trees of the rod's bodies) is stored as floats, in
    the buffer, so that a call unpacks one array fewer (≈ 70 ns each).

    While MuJoCo reports every tree of the rod asleep, the read's inputs (vertex positions, MuJoCo's reference
    frames, twist angles, base site) are kept; a later read that finds MuJoCo still reporting them asleep and the
    inputs the same bit for bit keeps the buffers as they are (the same inputs give the same frames and Darboux
    vectors). Returns 1 then, 0 after computing (the header's count of reads then goes up by one), and −1,
    computing nothing, while ``plastic`` is still zero (before the first step: the caller rebuilds the frames as
    MuJoCo restarts them).
    """
    ne = plastic.size // 6
    header, inv_lbar, theta, saved, frames, darboux, scratch, index = view_parts_in_call(buffer, ne)
    if plastic[3] == 0.0 and plastic[4] == 0.0 and plastic[5] == 0.0:
        header[0] = 0.0
        return -1
    n_tw = int(index[0])
    for k in range(n_tw):
        theta[int(index[1 + k])] = qpos[int(index[1 + n_tw + k])]
    asleep = True
    for k in range(1 + 2 * n_tw, index.size):
        if tree_asleep[int(index[k])] < 0:  # MuJoCo: < 0 awake, ≥ 0 asleep (the next tree of its sleeping island)
            asleep = False
            break
    flat = x.ravel()  # a view: the vertex rows are contiguous in mjData
    if asleep and header[0] == 1.0:
        o, same = _kept(flat, saved, 0, False)
        o, same_p = _kept(plastic, saved, o, False)
        o, same_t = _kept(theta, saved, o, False)
        _, same_s = _kept(site_row, saved, o, False)
        if same and same_p and same_t and same_s:
            return 1
    series_frames_and_darboux(x, plastic, theta, site_row[::3], inv_lbar, frames, darboux, scratch)
    header[1] += 1.0
    header[0] = 0.0
    if asleep:  # keep the inputs for the next read (only asleep: the copy would cost an awake rod every read)
        o, _ = _kept(flat, saved, 0, True)
        o, _ = _kept(plastic, saved, o, True)
        o, _ = _kept(theta, saved, o, True)
        _kept(site_row, saved, o, True)
        header[0] = 1.0
    return 0


@njit(cache=True, nogil=True)
def truth_samples(x, frames, darboux, lerp_index, lerp_weight, frame_edge, frame_h, basis_t, positions, frames_out,
                  curvature, twist):
    """What :meth:`models.rod_state.RodState.to_truth` computes, in one pass, at sample points fixed for a rod
    (:class:`models.rod_state.RodTruth` places them once).

    Centreline ``positions`` (m, 3): x[i0] + a (x[i1] − x[i0]) with (i0, i1) = ``lerp_index`` (m, 2), a =
    ``lerp_weight`` (m,) (:func:`positions_at`'s arithmetic); material frames ``frames_out`` (m, 3, 3): edge
    ``frame_edge`` (m,)'s frame turned by exp(h · Darboux) with h = ``frame_h`` (m,) (:func:`frames_at`'s);
    (k_x, k_y) = (κ2, −κ1) into ``curvature`` (n_g, 2) and τ into ``twist`` (n_g,) through ``basis_t``
    (n_interior, n_g), the interpolation matrix to the gratings transposed.
    """
    for q in range(lerp_weight.size):
        i0, i1, a = lerp_index[q, 0], lerp_index[q, 1], lerp_weight[q]
        for k in range(3):
            positions[q, k] = x[i0, k] + a * (x[i1, k] - x[i0, k])
    for q in range(frame_h.size):
        e, h = frame_edge[q], frame_h[q]
        e00, e01, e02, e10, e11, e12, e20, e21, e22 = exp_entries(h * darboux[e, 0], h * darboux[e, 1],
                                                                  h * darboux[e, 2])
        for r in range(3):
            f0, f1, f2 = frames[e, r, 0], frames[e, r, 1], frames[e, r, 2]
            frames_out[q, r, 0] = f0 * e00 + f1 * e10 + f2 * e20
            frames_out[q, r, 1] = f0 * e01 + f1 * e11 + f2 * e21
            frames_out[q, r, 2] = f0 * e02 + f1 * e12 + f2 * e22
    # basis_t is (n_interior, n_g): the gratings' sums advance side by side, each in vertex order
    n_v, n_g = basis_t.shape
    curvature[:] = 0.0
    twist[:] = 0.0
    for v in range(n_v):
        d0, d1, d2 = darboux[v, 0], darboux[v, 1], darboux[v, 2]
        for g in range(n_g):
            b = basis_t[v, g]
            curvature[g, 0] += b * d1
            curvature[g, 1] -= b * d0
            twist[g] += b * d2
