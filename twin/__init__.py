"""twin: fibre-optic (multi-core FBG) shape sensing of catheters.

Peak wavelengths → strain → curvature → 3D centreline, with calibration and parameter identification.
Needs only numpy, scipy and numba; the MuJoCo twin lives in the ``models`` and ``sim_interrogator`` packages.
"""

from twin import strain
from twin.calibration import Calibration, CalibrationError
from twin.fiber import FiberModel
from twin.frames import Frame, PeakStatus, Shape, Truth
from twin.reconstruct import Reconstructor

__all__ = [
    "Calibration",
    "CalibrationError",
    "FiberModel",
    "Frame",
    "PeakStatus",
    "Reconstructor",
    "Shape",
    "Truth",
    "strain",
]
__version__ = "0.1.0"
