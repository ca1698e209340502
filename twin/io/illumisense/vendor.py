"""ILLumiSense's own reconstruction, its sensor blocks: building them from our shapes, as the simulated
interrogator sends them (the comparison of the two shapes is :mod:`twin.reference_errors`'s).

Frame convention (docs/protocols-illumisense.md, vendor frame): our reconstructions have the base at the
origin, tangent +z and d1 (the first core's bending direction) = +x; the vendor's shape has x along the fibre
axis. The simulator maps ours to the vendor's by the cyclic permutation (x, y, z)_vendor = (z, x, y)_ours — a
proper rotation, so handedness is kept, with d1 becoming the vendor's y. The reported distance is taken after
a rigid registration, so it does not depend on this choice.
"""

from __future__ import annotations

import numpy as np

from twin.frames import Shape, VendorArrays, VendorSensor
from twin.io.illumisense.codec import SHAPE_SPACING

__all__ = ["VENDOR_FROM_BASE", "VendorArrays", "vendor_sensors"]

#: rows map our base-frame coordinates to the vendor's: vendor = VENDOR_FROM_BASE @ ours
VENDOR_FROM_BASE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def vendor_sensors(shapes: Shape, spacing: float = SHAPE_SPACING) -> list[VendorSensor]:
    """One :class:`VendorSensor` per reconstructed shape, as ILLumiSense would send it.

    Parameters
    ----------
    shapes : Shape
        A batch (n, …) of reconstructions.
    spacing : float
        Arc length between shape points, m (1 mm like the vendor's).

    Returns
    -------
    list of VendorSensor
        Curvature |κ| (1/m) and bending angle atan2(κ_y, κ_x) (rad, material frame) at the gratings; shape
        points every ``spacing`` from the base to the last whole step, in the vendor frame (module docstring).
    """
    k = np.asarray(shapes.curvature)
    if k.ndim == 2:
        k = k[None]
    s_end = float(shapes.s[-1])
    s_v = spacing * np.arange(int(np.floor(s_end / spacing + 1e-9)) + 1)
    if s_v.size == shapes.s.size and np.allclose(s_v, shapes.s, atol=1e-12):
        p = shapes.positions
    else:
        p = shapes.positions_at(s_v)
    p = np.asarray(p).reshape(-1, s_v.size, 3) @ VENDOR_FROM_BASE.T
    mag = np.hypot(k[..., 0], k[..., 1])
    ang = np.arctan2(k[..., 1], k[..., 0])
    return [VendorSensor(mag[i], ang[i], p[i], spacing) for i in range(p.shape[0])]
