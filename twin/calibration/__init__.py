"""Calibration of a fibre: the reference wavelengths and intrinsic twist a reconstruction needs, and how to get them.

``twostep``
    :class:`Calibration` and the paper's two-step procedure (straight pose, then an in-plane bend).
``identify``
    identification of the core spacing Δθ and the gain g = r·S_ε from shapes of known geometry.
``jig``
    calibration and validation in a jig of constant-curvature grooves (needles, fibre bundles).
"""

from twin.calibration.twostep import (
    Calibration,
    CalibrationError,
    CalibrationReport,
    nominal_delta_theta,
    nominal_gain,
    scaled_core_angles,
    two_step,
)

__all__ = [
    "Calibration",
    "CalibrationError",
    "CalibrationReport",
    "nominal_delta_theta",
    "nominal_gain",
    "scaled_core_angles",
    "two_step",
]
