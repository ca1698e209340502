"""Jig calibration: known constant-curvature grooves at known rotations → a calibration you can trust (docs/jig.md).

A lab presses the sensor into grooves of known constant curvature κ on a plate, at several known rotations ψ of
the sensor about its own axis, with a zero-curvature (flat groove) reference at each rotation. One row per pose
(usually the mean of many frames) goes into a CSV (:func:`read_poses`). This module fits, per grating, how the
cores respond to bending, and checks the result on poses the fit did not see.

Conventions (docs/math.md §1, docs/jig.md)
-------------------------------------------
* ψ (``orientation_rad``) is the sensor's rotation about its own tangent +d3 (base → tip), counter-clockwise
  seen from the tip looking back to the base — the sense in which core angles are counted. A groove bends the
  sensor toward a fixed direction of the plate, so in the fibre's material frame

      k(ψ) = κ (cos(α − ψ), sin(α − ψ)),

  with α, the *roll*, the bend direction in the fibre frame at ψ = 0 (a property of how the sensor is mounted
  in the jig; fitted).
* Optical strain relative to the reference of the SAME orientation: e = (λ − λ_ref)/λ_ref, λ_ref the mean of
  that orientation's curvature-0 rows. Per grating and core (docs/math.md §2.2)

      e_i = c − p_i · k,      p_i = g_i (cos θ_i, sin θ_i),   g_i = r_i S_ε,

  with c the common mode of the pose (temperature, axial strain: unknown and different for every pose).

Models
------
Both models estimate, per grating, the same object: the cores' response in the jig frame, e = c + β j + δ_o with
j = κ (cos ψ, −sin ψ) the curvature in the jig frame, β (n_cores × 2) = −(p_i rotated by −α), and δ_o a per-core
offset of orientation o: the error of that session's zero (reference noise, drift since it was taken, a
reference pose that was not quite straight). δ_o is fitted by default, the reference rows entering as κ = 0 poses
like any other, so the calibration rests on the differences between grooves; ``trust_references=True`` sets it
to 0 and fits the bent poses only.

* ``physical``: the forward model above, fitted in strain space by weighted least squares (weights from the
  ``std_`` columns), the per-pose common mode c eliminated exactly (variable projection). It is linear in β and
  δ, so the least-squares optimum is found in closed form, with no starting point; the core angles θ_i, gains
  g_i and the roll α follow from β, with uncertainties by the delta method from the fit covariance scaled by
  the residual variance. This is the maximum-likelihood fit for independent wavelength noise.
* ``matrix``: a general linear calibration k = M e (M: 2 × n_cores, M·1 = 0 so that the common mode is
  rejected, docs/math.md §5.1), fitted in curvature space by ordinary least squares with one curvature intercept per
  orientation (the image of δ_o). It minimises the curvature error directly and needs no physical model. Its
  design for :class:`~twin.strain.CurvatureSolver` is [1, M⁺], which the solver inverts back to exactly M. With
  more than 3 cores, directions of M that only noise determines are taken at minimum norm. Its frame (roll), the
  reported layout and the fit statistics come from the forward fit, which it runs too, so both models share one
  fibre frame.

With free per-core angles and gains and an unknown common mode per pose the two span the same curvature maps
(both have 2(n_cores − 1) identifiable numbers per grating); they differ as estimators and in what they report.

What a jig cannot tell (and how it is fixed)
---------------------------------------------
* Rotation: rotating every core by δ and the roll by δ changes nothing. The *fibre frame* is fixed by the bearing
  of the first off-axis core from the anchor (below): at each grating the roll α_n puts it at its nominal bearing;
  the roll α is the circular mean of the α_n, and what is left, α − α_n, is the rotation of the cores at that
  grating (intrinsic twist, reported).
* Translation: with an unknown common mode per pose, shifting every p_i by the same vector t is the same as
  adding t·k to c, so the jig fixes the cores' positions relative to each other, not relative to the neutral
  axis. The curvature does not depend on it; only the common-mode estimate and the reported θ_i, g_i do. The
  anchor is the central core (on the neutral axis by definition) or, without one, the cores' centroid placed at
  its nominal position (the centroid of the nominal layout).

Everything is SI (rad, 1/m, m); wavelengths in nm.

Layout: :mod:`~twin.calibration.jig.poses` (pose table and CSV), :mod:`~twin.calibration.jig.fits`
(the two models), :mod:`~twin.calibration.jig.validation` (validation, cross-validation); everything public is
re-exported here.
"""

from __future__ import annotations

from twin.calibration.jig.fits import JigFit, fit, gauge_layout, reference_bend
from twin.calibration.jig.poses import (
    MATCH_TOL,
    MODELS,
    ORIENTATION_TOL,
    JigPoses,
    jig_curvature,
    match_orientations,
    read_poses,
    write_poses,
)
from twin.calibration.jig.validation import (
    JigValidation,
    LoroStatistics,
    cross_validate,
    leave_one_rotation_out,
    validate,
)

__all__ = [
    "MATCH_TOL",
    "MODELS",
    "ORIENTATION_TOL",
    "JigFit",
    "JigPoses",
    "JigValidation",
    "LoroStatistics",
    "cross_validate",
    "fit",
    "gauge_layout",
    "jig_curvature",
    "leave_one_rotation_out",
    "match_orientations",
    "read_poses",
    "reference_bend",
    "validate",
    "write_poses",
]
