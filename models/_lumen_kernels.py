"""Compiled lumen forces of :class:`models.lumen_fiber.LumenCoupler` (numba): they run before every physics step.

The arithmetic is the one :meth:`LumenCoupler.apply` documents (wall spring and cross-section damper beyond the
clearance, regularised Coulomb friction along the lumen, the lumen's end on the tip, the tension read-out), in
one pass over the fibre's vertices, with four small work arrays per call instead of numpy temporaries per operation.
"""

from __future__ import annotations

import numpy as np
from numba import njit


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
