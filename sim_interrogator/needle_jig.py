"""A simulated needle in a calibration jig: the interrogator's pose table as a real jig session produces it.

The needle (docs/needle-fiber.toml, or JHU AMIRo's needle_3CH_4AA_v2) is pressed into constant-curvature
grooves at several orientations, trials each, with a flat-groove reference; every pose row is the mean of many
interrogator frames through :mod:`sim_interrogator.optics`. :data:`AMIRO` adds what the real AMIRo table shows a
jig does (docs/jig.md has the error budget). Used by ``twin run jig`` and ``twin run real-jig``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from sim_interrogator.optics import Optics, OpticsConfig
from twin import FiberModel
from twin.calibration.jig import JigPoses, leave_one_rotation_out

__all__ = ["AMIRO", "MIN_CURVATURE", "SENSORS", "JigParams", "amiro_fiber", "loro", "needle_fiber", "simulate"]

#: Bent levels the jig's statistics use: κ ≥ this, 1/m.
MIN_CURVATURE = 0.8


def needle_fiber() -> FiberModel:
    """The 3-fibre needle of docs/needle-fiber.toml (kept identical to it; a test checks)."""
    return FiberModel(
        name="3 single-core fibres glued at 120° on a 0.6 mm needle",
        handedness=1,
        strain_sensitivity=0.777,
        temperature_sensitivity=6.6e-6,
        core_angles=[0.0, 2.0943951023931953, 4.1887902047863905],
        core_radii=[3.5e-4, 3.5e-4, 3.5e-4],
        grating_s=[0.02, 0.035, 0.055, 0.08],
        lambda0=[[1530.0] * 3, [1545.0] * 3, [1560.0] * 3, [1575.0] * 3],
    )


def amiro_fiber() -> FiberModel:
    """JHU AMIRo's needle_3CH_4AA_v2 as twin/data/jig/amiro/needle.toml describes it (kept identical; a test checks)."""
    return FiberModel(
        name="AMIRo needle_3CH_4AA_v2: 3 single-core fibres, 4 gratings",
        handedness=1,
        strain_sensitivity=0.777,
        temperature_sensitivity=6.6e-6,
        core_angles=[0.0, 4.1887902047863905, 2.0943951023931953],
        core_radii=[3.0e-4, 3.0e-4, 3.0e-4],
        grating_s=[0.099, 0.134, 0.169, 0.189],
        lambda0=[[1538.250, 1538.177, 1538.094], [1546.358, 1546.135, 1546.111],
                 [1554.197, 1554.076, 1553.976], [1562.064, 1562.070, 1561.948]],
    )


@dataclass(frozen=True)
class JigParams:
    """The simulated jig session (SI units; angles in degrees where named so).

    Attributes
    ----------
    curvatures : tuple of float
        Groove curvatures, 1/m; 0 is the flat reference groove.
    orientations_deg : tuple of float
        Rotations ψ of the sensor in the jig, deg (written to the CSV in rad).
    fit_orientations_deg : tuple of float
        Orientations the fits use; the others validate.
    trials : int
        Passes through all grooves per orientation (each pass starts with a reference).
    frames : int
        Interrogator frames averaged into one CSV row.
    roll_deg : float
        True bend direction in the fibre frame at ψ = 0.
    angle_error_deg, radius_error : float
        RMS deviation of the true core angles from nominal (deg) and of the true radii (relative); the
        deviations are random, scaled to exactly this RMS.
    twist_deg : float
        Spiral of the glued fibres over the sensed length (all cores rotate together), deg.
    orientation_error_deg : float
        Std of the jig's indexing error per orientation, deg.
    groove_tolerance : float
        Relative std of each groove's true curvature.
    session_temperature_k, pose_temperature_k : float
        Std of each orientation session's temperature offset and of the wander from pose to pose, K.
    axial_strain : float
        Std of the axial strain from pressing the sensor into a groove.
    noise, drift, quantisation : float
        Interrogator white noise per frame (nm), random-walk drift (nm/√s), resolution (nm).
    pose_interval_s, session_gap_s : float
        Time between poses and between the start of two orientation sessions, s.
    groove_length : float or None
        Arc length from the base that lies in the groove, m; gratings beyond it stay straight. None: all.
    grating_conformity : tuple of float or None
        Fraction of the groove's curvature each grating follows (a grating near the groove's end, or where the
        sensor lifts out, reads less); None: 1 everywhere. A grating that follows less than 3/4 of the groove
        counts as outside it: it is not fitted (``truth["gratings_in_groove"]``).
    conformity_std : float
        Relative std of how well the sensor follows the groove, drawn per orientation session and grating (the
        sensor's stiffness against the groove: seated a little differently each time).
    seat_twist_deg : float
        Std of the sensor's rotation at each grating, per orientation session, deg (twisting when pressed in; on
        top of the session's ``orientation_error_deg``).
    reference_curvature : float
        Std (per component) of each orientation session's zero at each grating, 1/m: how much less (or more) the
        bent grooves of that seating bend the sensor than their labels, the same in all of them.
    reference_bias : (float, float)
        The part of that zero which is the same in every session in the jig's frame, 1/m: along the grooves' bend
        direction and across it (90° counter-clockwise from it): the bent grooves hold the sensor this much less
        bent than labelled. Against each orientation's own reference this is the same as a flat groove that holds
        the sensor bent by as much; the real AMIRo references' absolute wavelengths say it is the bent grooves
        (docs/jig.md, "The jig's zero"), so the reference pose is straight here.
    seat_curvature : float
        Std (per component) of a curvature offset at each grating, drawn per seating (one orientation and
        groove), 1/m: the sensor does not lie the same way in every groove.
    pose_curvature : float
        Std (per component) of a curvature offset per pose and grating, 1/m (trial-to-trial scatter).
    order : {"trial", "groove"}
        Pose order within an orientation: "trial" passes through all grooves once per trial (a reference each
        pass); "groove" takes all trials of one groove before the next (the reference groove first).
    seed : int
        Draws the as-built sensor and, unless ``session_seed`` is given, the session.
    session_seed : int or None
        Draws the session (jig errors, seating, interrogator noise, temperatures) apart from the sensor: two
        values give two sessions of the same sensor (core angles, radii, twist) in the same jig. The optics' as-built
        λ0 scatter and thermal mismatch are drawn with the session: each orientation's reference removes the
        first, and the second acts only through the 1 K session temperatures.
    """

    curvatures: tuple[float, ...] = (0.0, 0.25, 0.8, 1.0, 1.25, 3.125)
    orientations_deg: tuple[float, ...] = (0.0, 90.0, 180.0, 270.0)
    fit_orientations_deg: tuple[float, ...] = (0.0, 90.0)
    trials: int = 3
    frames: int = 50
    roll_deg: float = 17.0
    angle_error_deg: float = 3.0
    radius_error: float = 0.03
    twist_deg: float = 2.0
    orientation_error_deg: float = 0.1
    groove_tolerance: float = 0.002
    session_temperature_k: float = 2.0
    pose_temperature_k: float = 0.2
    axial_strain: float = 20e-6
    noise: float = 1e-3
    drift: float = 2e-4
    quantisation: float = 1e-4
    pose_interval_s: float = 15.0
    session_gap_s: float = 1800.0
    groove_length: float | None = None
    grating_conformity: tuple[float, ...] | None = None
    conformity_std: float = 0.0
    seat_twist_deg: float = 0.0
    reference_curvature: float = 0.0
    reference_bias: tuple[float, float] = (0.0, 0.0)
    seat_curvature: float = 0.0
    pose_curvature: float = 0.0
    order: str = "trial"
    seed: int = 0
    session_seed: int | None = None


#: The AMIRo needle in its jig, as the real table of 2021-03-20 shows it (docs/jig.md, "A twin of the AMIRo needle";
#: each magnitude is justified there from twin/data/jig/amiro/poses.csv).
AMIRO = JigParams(
    curvatures=(0.0, 0.5, 1.6, 2.0, 2.5, 3.2, 4.0),
    orientations_deg=(0.0, 90.0, 180.0, 270.0),
    fit_orientations_deg=(0.0, 90.0, 180.0),
    trials=3,
    frames=10,
    roll_deg=102.0,
    angle_error_deg=3.0,
    radius_error=0.05,
    twist_deg=2.0,
    orientation_error_deg=3.0,
    groove_tolerance=0.01,
    session_temperature_k=1.0,
    pose_temperature_k=0.2,
    axial_strain=20e-6,
    noise=1.2e-3,
    drift=2e-4,
    quantisation=2e-4,
    pose_interval_s=12.0,
    session_gap_s=1000.0,
    grating_conformity=(1.0, 1.0, 1.0, 0.5),
    conformity_std=0.045,
    seat_twist_deg=1.2,
    reference_curvature=0.10,
    reference_bias=(0.14, 0.10),
    seat_curvature=0.07,
    pose_curvature=0.015,
    order="groove",
)

#: Sensors ``twin run jig --sensor`` simulates: (nominal fibre, session parameters).
SENSORS = {"needle": (needle_fiber, JigParams()), "amiro": (amiro_fiber, AMIRO)}


def simulate(params: JigParams = JigParams(), fiber: FiberModel | None = None) -> tuple[JigPoses, dict]:
    """Simulate the jig session.

    Returns
    -------
    poses : JigPoses
        One row per pose (mean of ``params.frames`` frames) with std columns (frame std / √frames).
    truth : dict
        The true sensor and jig (JSON-ready, SI): core angles and radii, roll, twist, orientation errors,
        groove curvatures, gratings in the groove.
    """
    nominal = fiber or needle_fiber()
    rng = np.random.default_rng(params.seed)
    bend = nominal.bending_cores
    angles = nominal.core_angles.copy()
    radii = nominal.core_radii.copy()
    # random deviations scaled to the requested RMS, so every seed is "a few degrees and percent" off
    z = rng.standard_normal((2, bend.size))
    z /= np.sqrt(np.mean(z**2, axis=1, keepdims=True))
    if params.session_seed is not None:  # the same sensor, another session
        rng = np.random.default_rng([params.session_seed, 2])
    angles[bend] += np.deg2rad(params.angle_error_deg) * z[0]
    radii[bend] *= 1.0 + params.radius_error * z[1]
    true = nominal.replace(core_angles=angles, core_radii=radii, name=f"{nominal.name} (as built)")
    # Optics perturbs the fibre it is given by Δθ and gain scale; with those off, it simulates this true fibre
    # (plus its as-built λ0 scatter and thermal mismatch), and judges peak loss against the same nominal λ0.
    config = OpticsConfig(delta_theta=None, gain_scale=1.0, twist_total=np.deg2rad(params.twist_deg),
                          twist_wobble=0.0, noise=params.noise, drift=params.drift,
                          quantisation=params.quantisation, grating_length=0.0, jitter=0.0,
                          seed=int(rng.integers(2**31)))
    optics = Optics(true, config)
    psi = np.deg2rad(np.asarray(params.orientations_deg, dtype=np.float64))
    psi_true = psi + np.deg2rad(params.orientation_error_deg) * rng.standard_normal(psi.size)
    levels = np.asarray(params.curvatures, dtype=np.float64)
    levels_true = levels * (1.0 + params.groove_tolerance * rng.standard_normal(levels.size))
    in_groove = (np.ones(nominal.n_gratings, bool) if params.groove_length is None
                 else nominal.grating_s <= params.groove_length)
    alpha = np.deg2rad(params.roll_deg)
    n_o, n_t, n_l = psi.size, params.trials, levels.size
    if params.order == "trial":  # pose order: orientation (session), trial, groove
        o_idx, _, l_idx = (a.ravel() for a in np.meshgrid(np.arange(n_o), np.arange(n_t), np.arange(n_l),
                                                           indexing="ij"))
    elif params.order == "groove":  # orientation, groove, trial
        o_idx, l_idx, _ = (a.ravel() for a in np.meshgrid(np.arange(n_o), np.arange(n_l), np.arange(n_t),
                                                           indexing="ij"))
    else:
        raise ValueError(f"order must be 'trial' or 'groove', got {params.order!r}")
    n_p = o_idx.size
    t = o_idx * params.session_gap_s + (np.arange(n_p) % (n_t * n_l)) * params.pose_interval_s
    kappa = levels_true[l_idx]
    k, seating = _seated_curvature(params, nominal.n_gratings, alpha - psi_true, o_idx, l_idx, kappa)
    k = np.where(in_groove[None, :, None], k, 0.0)  # (P, G, 2)
    k = k + seating
    d_t = (params.session_temperature_k * rng.standard_normal(n_o))[o_idx] + \
        params.pose_temperature_k * rng.standard_normal(n_p)
    axial = params.axial_strain * rng.standard_normal(n_p)
    mean = np.empty((n_p, nominal.n_gratings, nominal.n_cores))
    std = np.empty_like(mean)
    for p in range(n_p):  # the interrogator's drift advances pose by pose; the frames of a pose are one batch
        frames = np.broadcast_to(k[p], (params.frames, *k.shape[1:]))
        w, _ = optics.wavelengths(frames, axial_strain=axial[p], delta_T=d_t[p], t=float(t[p]))
        mean[p] = np.nanmean(w, axis=0)
        std[p] = np.nanstd(w, axis=0, ddof=1) / np.sqrt(params.frames) if params.frames > 1 else params.noise
    poses = JigPoses(orientation=psi[o_idx], curvature=levels[l_idx], wavelengths=mean, std=std,
                     source="twin jig scenario")
    truth = {
        "core_angles_rad": angles.tolist(),
        "core_radii_m": radii.tolist(),
        "gains_m": true.gains.tolist(),
        "roll_rad": float(alpha),
        "twist_rad": optics.twist.tolist(),
        "orientation_errors_rad": (psi_true - psi).tolist(),
        "groove_curvatures_1_per_m": levels_true.tolist(),
        "gratings_in_groove": np.flatnonzero(in_groove & (_conformity(params, nominal.n_gratings) > 0.75)).tolist(),
    }
    return poses, truth


def _conformity(params: JigParams, n_gratings: int) -> np.ndarray:
    if params.grating_conformity is None:
        return np.ones(n_gratings)
    c = np.asarray(params.grating_conformity, dtype=np.float64)
    if c.shape != (n_gratings,):
        raise ValueError(f"grating_conformity needs {n_gratings} values, got {c.size}")
    return c


def _seated_curvature(params: JigParams, n_gratings: int, bearing: np.ndarray, o_idx: np.ndarray,
                      l_idx: np.ndarray, kappa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The curvature each grating really has in each pose, split into the groove's part (P, G, 2) and the
    seating's part (P, G, 2), both in the fibre frame, 1/m.

    ``bearing`` (per orientation, rad) is α − ψ, the groove's bend direction in the fibre frame. The seating
    effects (docs/jig.md, "A twin of the AMIRo needle") are drawn from a generator of their own, so that with all
    of them at 0 the session is the same as without them.
    """
    rng = np.random.default_rng([params.seed if params.session_seed is None else params.session_seed, 1])
    n_o, n_l, n_p = bearing.size, int(l_idx.max()) + 1, o_idx.size
    twist = np.deg2rad(params.seat_twist_deg) * rng.standard_normal((n_o, n_gratings))
    scale = _conformity(params, n_gratings) * (1.0 + params.conformity_std * rng.standard_normal((n_o, n_gratings)))
    ref = params.reference_curvature * rng.standard_normal((n_o, n_gratings, 2))
    seat = params.seat_curvature * rng.standard_normal((n_o, n_l, n_gratings, 2))
    pose = params.pose_curvature * rng.standard_normal((n_p, n_gratings, 2))
    a = bearing[o_idx][:, None] - twist[o_idx]  # (P, G)
    along, across = params.reference_bias
    ref = ref + (along * np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)
                 + across * np.stack([-np.sin(bearing), np.cos(bearing)], axis=-1))[:, None, :]
    groove = (kappa[:, None] * scale[o_idx])[..., None] * np.stack([np.cos(a), np.sin(a)], axis=-1)
    # the session's zero acts on the bent grooves (they fall short of their label); the reference pose is straight
    seating = seat[o_idx, l_idx] + pose - np.where((kappa > 0.0)[:, None, None], ref[o_idx], 0.0)
    return groove, seating


def loro(params: JigParams, fiber: FiberModel, seeds: int = 1) -> dict:
    """The table statistics of ``twin run real-jig`` on ``seeds`` simulated sessions (seeds params.seed, +1, ...):
    in-sample RMS strain residual, leave-one-rotation-out curvature and direction errors
    (twin.calibration.jig.leave_one_rotation_out), each the median over the sessions, with the per-session values.
    """
    if seeds < 1:
        raise ValueError(f"seeds must be at least 1, got {seeds}")
    runs = []
    for i in range(seeds):
        poses, truth = simulate(replace(params, seed=params.seed + i), fiber)
        stats = leave_one_rotation_out(fiber, poses, gratings=truth["gratings_in_groove"], min_curvature=MIN_CURVATURE)
        runs.append(stats.to_dict())
    keys = ("rms_strain_residual", "loro_kappa_error_1_per_m", "loro_direction_error_deg")
    out = {k: float(np.median([r[k] for r in runs])) for k in keys}
    out["sessions"] = [{k: r[k] for k in keys} for r in runs]
    out["gratings"] = runs[0]["gratings"]
    return out
