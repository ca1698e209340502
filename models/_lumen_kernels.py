"""Compiled lumen forces of :class:`models.lumen_fiber.LumenCoupler` (numba): they run before every physics step.

The arithmetic is the one :meth:`LumenCoupler.apply` documents (wall spring and cross-section damper beyond the
clearance, regularised Coulomb friction along the lumen, the lumen's end on the tip, the tension read-out), in
one pass over the fibre's vertices, with four small work arrays per call instead of numpy temporaries per operation.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from models import _rod_kernels
from twin import _jit_cache  # noqa: F401  (before the first cached kernel; see its docstring)


@njit(cache=True, nogil=True)
def _lumen_point(x_c, frames, cs0, l, offset, sigma, out_p, out_t):
    """Lumen axis point and tangent at catheter arc length ``sigma`` (into out_p, out_t, (3,) each)."""
    u = (sigma - cs0) / l
    j = int(np.floor(u))
    j = min(max(j, 0), x_c.shape[0] - 2)
    w = u - j
    for i in range(3):
        out_p[i] = (1.0 - w) * x_c[j, i] + w * x_c[j + 1, i] + offset * frames[j, i, 0]
        out_t[i] = frames[j, i, 2]


@njit(cache=True, nogil=True)
def lumen_forces(x_c, frames, cs0, l, offset, x_f, v_f, sigma, free, prev_p, dt, v_l, drag, clearance,
                 wall_stiffness, wall_damping, friction, slip_speed, visc_cap, lumen_end, p, force, normal,
                 tension):
    """Update the lumen coordinates and compute the lumen's forces on the fibre; returns the tip force, N.

    Parameters
    ----------
    x_c : (nc, 3) catheter vertices, m. frames : (nc − 1, 3, 3) its material frames (columns d1, d2, d3).
    cs0, l : catheter arc length of its first vertex and its edge length, m. offset : lumen offset along d1, m.
    x_f, v_f : (nf, 3) fibre vertex positions (m) and velocities (m/s), world.
    sigma : (nf,) in/out: lumen coordinate of each fibre vertex, m (updated by one projection step where free).
    free : (nf,) bool, vertices not held by glue.
    prev_p : (nf, 3) lumen points of the previous step; dt : s since then (0: keep ``v_l``).
    v_l : (nf, 3) in/out: lumen velocity at the fibre's vertices, m/s.
    drag, clearance, wall_stiffness, wall_damping, friction, slip_speed, visc_cap : the FiberSpec's values
        (visc_cap = 0.5 · vertex_mass / timestep, N·s/m).
    lumen_end : catheter arc length of the lumen's end, m.
    p : (nf, 3) out: lumen points at the updated coordinates. force : (nf, 3) out, N. normal : (nf,) out, N.
    tension : (nf − 1,) out: axial force per fibre edge from the wall, the friction and the end, N.
    """
    nf = x_f.shape[0]
    hi = cs0 + l * (x_c.shape[0] - 1)
    t = np.empty((nf, 3))
    tp = np.empty(3)
    for n in range(nf):
        if free[n]:  # one projection step: the fibre slides far less than an edge per step
            _lumen_point(x_c, frames, cs0, l, offset, sigma[n], p[n], tp)
            a = 0.0
            for i in range(3):
                a += (x_f[n, i] - p[n, i]) * tp[i]
            sigma[n] = min(max(sigma[n] + a, cs0), hi)
        _lumen_point(x_c, frames, cs0, l, offset, sigma[n], p[n], t[n])
        if dt > 0.0:
            for i in range(3):
                v_l[n, i] = (p[n, i] - prev_p[n, i]) / dt
    along = np.empty(nf)
    vr = np.empty(3)
    r = np.empty(3)
    for n in range(nf):
        rt = 0.0
        v_ax = 0.0
        for i in range(3):
            vr[i] = v_f[n, i] - v_l[n, i]
            r[i] = x_f[n, i] - p[n, i]
            rt += r[i] * t[n, i]
            v_ax += vr[i] * t[n, i]
        d2 = 0.0
        for i in range(3):
            r[i] -= rt * t[n, i]
            d2 += r[i] * r[i]
        d = np.sqrt(d2)
        pen = d - clearance
        contact = free[n] and pen > 0.0
        nn = wall_stiffness * pen if contact else 0.0
        normal[n] = nn
        inv_d = 1.0 / max(d, 1e-12)
        visc = min(friction * nn / np.sqrt(v_ax * v_ax + slip_speed * slip_speed), visc_cap)
        s = 0.0
        for i in range(3):
            f = -drag * vr[i] - nn * r[i] * inv_d - visc * v_ax * t[n, i]
            if contact:  # the damper acts over the whole cross-section (not along the radius only)
                f -= wall_damping * (vr[i] - v_ax * t[n, i])
            force[n, i] = f
            s += f * t[n, i]
        along[n] = s
    tip = wall_stiffness * max(sigma[nf - 1] - lumen_end, 0.0)
    for i in range(3):
        force[nf - 1, i] -= tip * t[nf - 1, i]
    along[nf - 1] -= tip
    acc = 0.0
    for n in range(nf - 1, 0, -1):
        acc += along[n]
        tension[n - 1] = acc
    return tip


@njit(cache=True, nogil=True)
def coupler_step(xc, cplastic, qpos, tw_edges, tw_qadr, theta, site_row, inv_lbar, cframes, cdarb, read_frames,
                 cs0, l, offset, x_f, qvel, dof, axes, rp, axes_w, v_f, sigma, free, prev_p, dt, advance, v_l, drag,
                 clearance, wall_stiffness, wall_damping, friction, slip_speed, visc_cap, lumen_end, p, force, normal,
                 tension, weight, carrier_force, couple_k, moment, first, qfrc, glue_eq, glue_idx, eq_data, cath_rp):
    """One step of :meth:`models.lumen_fiber.LumenCoupler.apply` over views of ``mjData`` bound once; returns the
    tip force, N, or NaN having changed nothing while the catheter's ``plastic`` is still zero (``read_frames``:
    the caller rebuilds its frames as MuJoCo restarts them and calls again with ``read_frames`` False).

    Parameters
    ----------
    xc … cdarb : the catheter's :func:`models._rod_kernels.bound_frames_and_darboux` arguments (frames into
        ``cframes``, (nc − 1, 3, 3)). read_frames : bool, read them (False: ``cframes`` already hold them).
    cs0, l, offset, x_f, sigma, free, prev_p, dt, v_l, drag … tension : as :func:`lumen_forces`.
    qvel : all of ``mjData.qvel``; dof : (nf, 3) the fibre's slide dofs; axes : (nf, 3, 3) their axes in the
        parent frame; rp : (9,) the parent's ``xmat`` row; axes_w, v_f : (nf, 3, 3), (nf, 3) work arrays.
    advance : bool, keep this step's lumen points as the previous ones (time has moved on).
    weight : (3,) the vertex's weight, N (cancelled); carrier_force : (3,) vertex mass × the carrier's
        acceleration, N (added).
    couple_k : the glue couple's fibre edge (−1: none); moment : its couple T·e, N·m. first : catheter edge of
        the fibre's first vertex.
    qfrc : all of ``mjData.qfrc_applied`` (the fibre's dofs written). glue_eq, glue_idx : the glue's connect
        equalities and their fibre vertices (empty, or ``offset`` 0: anchors left alone); eq_data : all of
        ``mjModel.eq_data`` (neq, 11); cath_rp : (9,) ``xmat`` row of the catheter's parent.
    """
    if read_frames and not _rod_kernels.bound_frames_and_darboux(xc, cplastic, qpos, tw_edges, tw_qadr, theta,
                                                                  site_row, inv_lbar, cframes, cdarb):
        return np.nan
    nf = x_f.shape[0]
    for n in range(nf):  # joint axes in the world (axes @ R.T) and the vertices' velocities
        for j in range(3):
            for i in range(3):
                axes_w[n, j, i] = axes[n, j, 0] * rp[3 * i] + axes[n, j, 1] * rp[3 * i + 1] \
                    + axes[n, j, 2] * rp[3 * i + 2]
        for i in range(3):
            v_f[n, i] = qvel[dof[n, 0]] * axes_w[n, 0, i] + qvel[dof[n, 1]] * axes_w[n, 1, i] \
                + qvel[dof[n, 2]] * axes_w[n, 2, i]
    tip = lumen_forces(xc, cframes, cs0, l, offset, x_f, v_f, sigma, free, prev_p, dt, v_l, drag, clearance,
                       wall_stiffness, wall_damping, friction, slip_speed, visc_cap, lumen_end, p, force, normal,
                       tension)
    if advance:
        prev_p[:] = p
    for n in range(nf):
        for i in range(3):
            force[n, i] = force[n, i] - weight[i] + carrier_force[i]
    if couple_k >= 0:  # the lead's traction through the eccentric glue (LumenCoupler._glue_couple)
        k = couple_k
        e0, e1, e2 = x_f[k + 1, 0] - x_f[k, 0], x_f[k + 1, 1] - x_f[k, 1], x_f[k + 1, 2] - x_f[k, 2]
        le = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        t0, t1, t2 = e0 / le, e1 / le, e2 / le
        c = min(first + k, cframes.shape[0] - 1)
        g0, g1, g2 = cframes[c, 0, 0], cframes[c, 1, 0], cframes[c, 2, 0]
        gt = g0 * t0 + g1 * t1 + g2 * t2
        n0, n1, n2 = g0 - gt * t0, g1 - gt * t1, g2 - gt * t2
        nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        a = moment / le
        f0, f1, f2 = a * (n0 / nn), a * (n1 / nn), a * (n2 / nn)
        force[k, 0] += f0
        force[k, 1] += f1
        force[k, 2] += f2
        force[k + 1, 0] -= f0
        force[k + 1, 1] -= f1
        force[k + 1, 2] -= f2
    for n in range(nf):
        for j in range(3):
            qfrc[dof[n, j]] = force[n, 0] * axes_w[n, j, 0] + force[n, 1] * axes_w[n, j, 1] \
                + force[n, 2] * axes_w[n, j, 2]
    if offset != 0.0:  # the glue's connect anchors follow the lumen's offset, in the catheter's parent frame
        for q in range(glue_eq.size):
            c = min(first + glue_idx[q], cframes.shape[0] - 1)
            for i in range(3):
                eq_data[glue_eq[q], 3 + i] = offset * cframes[c, 0, 0] * cath_rp[i] \
                    + offset * cframes[c, 1, 0] * cath_rp[3 + i] + offset * cframes[c, 2, 0] * cath_rp[6 + i]
    return tip
