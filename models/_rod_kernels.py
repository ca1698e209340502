"""Compiled per-edge loops of the rod-state reader (numba): they run at the sensor rate, up to 1 kHz.

The numpy formulation in :mod:`models.rod_state` documents the method; these kernels do the same arithmetic in
one pass without temporaries (≈ 2 µs instead of ≈ 50 µs for 100 segments).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from twin.so3 import exp_entries, log_entries


@njit(cache=True, nogil=True, inline="always")
def _qdot(frames, i, j, k):
    """Entry (j, k) of R_iᵀ R_{i+1}: column j of edge i's frame dotted with column k of edge i + 1's."""
    return (frames[i, 0, j] * frames[i + 1, 0, k] + frames[i, 1, j] * frames[i + 1, 1, k]
            + frames[i, 2, j] * frames[i + 1, 2, k])


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
        ax, ay, az = plastic[6 * e], plastic[6 * e + 1], plastic[6 * e + 2]
        ux, uy, uz = plastic[6 * e + 3], plastic[6 * e + 4], plastic[6 * e + 5]
        # parallel transport from t_old to t: u + 2 (a·u) t − ((a + t)·u) (a + t) / (1 + a·t)
        wx, wy, wz = ax + tx, ay + ty, az + tz
        c_at = ax * tx + ay * ty + az * tz
        au = ax * ux + ay * uy + az * uz
        wu = (wx * ux + wy * uy + wz * uz) / (1.0 + c_at)
        ux, uy, uz = ux + 2.0 * au * tx - wu * wx, uy + 2.0 * au * ty - wu * wy, uz + 2.0 * au * tz - wu * wz
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
