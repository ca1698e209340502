"""`twin run jig`: the jig calibration of a 3-fibre needle on the twin, both fit models cross-validated.

The simulated needle (docs/needle-fibre.toml: three single-core fibres at 120°, 4 gratings at uneven positions
from 20 mm) is pressed into constant-curvature grooves at 4 orientations, several trials each, with a flat-groove
reference in every trial. The true sensor is not the nominal one: core angles a few degrees and radii a few
percent off, a slight spiral of the glued fibres, as-built reference wavelengths and per-core thermal response
scattered (sim_interrogator.optics). Every pose row is the mean of many interrogator frames with 1 pm white noise,
random-walk drift, 0.1 pm quantisation; each orientation is a session of its own (temperature offset, drift
since the previous one), the jig's indexing and groove curvatures have small errors, and pressing the sensor into
a groove adds axial strain.

It writes the CSV `twin jig-calibrate` reads (``--out``), fits the physical and the matrix model on two
orientations and validates both on the other two. Acceptance (the issue's): curvature error ≤ 0.02 1/m and bend
direction within 1° for κ ≥ 0.8 1/m at every grating in the groove. The exit status is 1 when a model fails.

``--sensor amiro`` simulates a real needle in a real jig instead: JHU AMIRo's needle_3CH_4AA_v2 (:func:`amiro_fiber`)
with what its real table shows a jig does (:data:`AMIRO`: the sensor seated a little differently at every rotation
and groove, a reference that is not the zero of the bent poses, the tip grating at the groove's end). It has no
acceptance verdict; `twin run real-jig` compares its statistics with the real table's.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict, dataclass, replace

import numpy as np

from sim_interrogator.optics import Optics, OpticsConfig
from twin import FiberModel, jsonout
from twin.calibration.jig import (
    MATCH_TOL,
    JigPoses,
    cross_validate,
    gauge_layout,
    leave_one_rotation_out,
    match_orientations,
    write_poses,
)

__all__ = ["AMIRO", "SENSORS", "JigParams", "amiro_fiber", "evaluate", "loro", "needle_fiber", "simulate"]

#: Acceptance of the issue: curvature magnitude error, 1/m; bend direction error, deg; for κ ≥ 0.8 1/m.
MAX_ERROR = 0.02
MAX_DIRECTION_ERROR_DEG = 1.0
MIN_CURVATURE = 0.8


def needle_fiber() -> FiberModel:
    """The 3-fibre needle of docs/needle-fibre.toml (kept identical to it; a test checks)."""
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
    """JHU AMIRo's needle_3CH_4AA_v2 as tests/data/amiro/needle.toml describes it (kept identical; a test checks)."""
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
        Std (per component) of the reference pose's curvature at each grating, per orientation session, 1/m: a
        reference that is not straight, or drift between the reference and the poses.
    reference_bias : (float, float)
        The part of the reference pose's curvature that is the same in every session in the jig's frame, 1/m:
        along the grooves' bend direction and across it (90° counter-clockwise from it): a "flat" groove that
        holds the sensor slightly bent.
    seat_curvature : float
        Std (per component) of a curvature offset at each grating, drawn per seating (one orientation and
        groove), 1/m: the sensor does not lie the same way in every groove.
    pose_curvature : float
        Std (per component) of a curvature offset per pose and grating, 1/m (trial-to-trial scatter).
    order : {"trial", "groove"}
        Pose order within an orientation: "trial" passes through all grooves once per trial (a reference each
        pass); "groove" takes all trials of one groove before the next (the reference groove first).
    seed : int
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


#: The AMIRo needle in its jig, as the real table of 2021-03-20 shows it (docs/jig.md, "A twin of the AMIRo needle";
#: each magnitude is justified there from tests/data/amiro/poses.csv).
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
    rng = np.random.default_rng([params.seed, 1])
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
    seating = seat[o_idx, l_idx] + pose + np.where((kappa == 0.0)[:, None, None], ref[o_idx], 0.0)
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


def evaluate(params: JigParams = JigParams(), fiber: FiberModel | None = None, out: str | None = None,
             accept: bool = True) -> dict:
    """Simulate, fit both models on ``params.fit_orientations_deg`` and validate on the other orientations.

    Returns a JSON-ready (and picklable) dict: parameters, truth, and per model the fit and the validation with
    its acceptance verdict (``accept=False``: no verdict, for a sensor simulated as the real jig shows it, whose
    errors are the point), and the leave-one-rotation-out statistics of the session (``loro``).
    """
    nominal = fiber or needle_fiber()
    poses, truth = simulate(params, nominal)
    if out:
        write_poses(out, poses, comment="twin jig scenario: one row per pose, mean of "
                    f"{params.frames} frames; orientation_rad = rotation about +d3; wavelengths in nm")
    fit_o = np.deg2rad(np.asarray(params.fit_orientations_deg, dtype=np.float64))
    match_orientations(poses, fit_o)  # every fit orientation exists (or a clear error)
    fitted = np.any(np.abs(poses.orientations[:, None] - fit_o[None, :]) < MATCH_TOL, axis=1)
    holdout = poses.orientations[~fitted]
    gratings = truth["gratings_in_groove"]
    result = {"params": asdict(params), "truth": truth,
              "poses": poses.n_poses, "fit_orientations_rad": fit_o.tolist(),
              "validation_orientations_rad": holdout.tolist(), "models": {}}
    for model in ("physical", "matrix"):
        jig_fit, check = cross_validate(nominal, poses, holdout, model=model, gratings=gratings,
                                        min_curvature=MIN_CURVATURE)
        result["models"][model] = {
            "fit": jig_fit.to_dict(),
            "validation": check.to_dict(),
            "recovery": _recovery(nominal, truth, jig_fit),
            "passes": check.passes(MAX_ERROR, MAX_DIRECTION_ERROR_DEG),
        }
        if not accept:
            result["models"][model]["passes"] = None
    result["loro"] = (leave_one_rotation_out(nominal, poses, gratings=gratings, min_curvature=MIN_CURVATURE).to_dict()
                      if poses.orientations.size > 2 else None)
    result["acceptance"] = {"max_error_1_per_m": MAX_ERROR, "max_direction_error_deg": MAX_DIRECTION_ERROR_DEG,
                            "min_curvature_1_per_m": MIN_CURVATURE, "applies": accept,
                            "passes": all(m["passes"] for m in result["models"].values()) if accept else None}
    return result


def _recovery(nominal: FiberModel, truth: dict, jig_fit) -> dict:
    """How well the fit found the true sensor, both in the calibration's gauge
    (twin.calibration.jig.gauge_layout): largest core angle error (deg), relative gain error, and error of the core
    rotation between gratings (twist, deg)."""
    g = np.asarray(truth["gratings_in_groove"])
    twist = np.asarray(truth["twist_rad"])[g]
    true_angles = np.asarray(truth["core_angles_rad"])[None, :] + nominal.handedness * twist[:, None]
    true_gains = np.broadcast_to(np.asarray(truth["gains_m"]), true_angles.shape)
    a_true, g_true = gauge_layout(nominal, true_angles, true_gains)
    a_fit, g_fit = gauge_layout(nominal, jig_fit.core_angles, jig_fit.gains)
    bend = nominal.bending_cores
    rot = jig_fit.core_rotation - np.mean(jig_fit.core_rotation)
    return {
        "max_core_angle_error_deg": float(np.rad2deg(np.abs(a_fit - a_true)[:, bend].max())),
        "max_gain_error_rel": float((np.abs(g_fit / g_true - 1.0))[:, bend].max()),
        "max_twist_error_deg": float(np.rad2deg(np.abs(rot - (twist - twist.mean())).max())),
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sensor", choices=sorted(SENSORS), default="needle",
                        help="needle: the 3-fibre needle of docs/needle-fibre.toml in an ideal jig (with an acceptance "
                        "verdict); amiro: JHU AMIRo's needle_3CH_4AA_v2 in its jig as the real data shows it "
                        "(docs/jig.md; compare with twin run real-jig)")
    parser.add_argument("--out", metavar="POSES.csv", help="also write the simulated poses as a jig CSV")
    parser.add_argument("--fiber", metavar="FIBER.toml", help="nominal fibre model (default: the sensor's)")
    parser.add_argument("--trials", type=int, help="passes per orientation (default: the sensor's)")
    parser.add_argument("--frames", type=int, help="frames per pose row (default: the sensor's)")
    parser.add_argument("--noise-pm", type=float, help="white wavelength noise per frame, pm (default: the sensor's)")
    parser.add_argument("--fit-orientations-deg",
                        help="orientations to fit on, deg, comma-separated (default: 0,90 for the needle, 0,90,180 "
                        "for amiro); the rest validate")
    parser.add_argument("--groove-length-mm", type=float, default=None,
                        help="arc length in the groove, mm (default: every grating)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def sensor_params(args: argparse.Namespace) -> tuple[JigParams, FiberModel]:
    """The session parameters and nominal fibre of ``--sensor``, with the command-line overrides applied."""
    make_fiber, params = SENSORS[args.sensor]
    changes: dict = {"seed": args.seed}
    if args.fit_orientations_deg is not None:
        try:
            changes["fit_orientations_deg"] = tuple(float(x) for x in args.fit_orientations_deg.split(","))
        except ValueError:
            raise ValueError(
                f"--fit-orientations-deg: expected numbers in deg, got {args.fit_orientations_deg!r}") from None
    for name, value in (("trials", args.trials), ("frames", args.frames)):
        if value is not None:
            changes[name] = value
    if args.noise_pm is not None:
        changes["noise"] = args.noise_pm * 1e-3
    if args.groove_length_mm is not None:
        changes["groove_length"] = args.groove_length_mm * 1e-3
    fiber = FiberModel.load(args.fiber) if args.fiber else make_fiber()
    return replace(params, **changes), fiber


def run(args: argparse.Namespace) -> int:
    params, fiber = sensor_params(args)
    accept = args.sensor == "needle"
    result = evaluate(params, fiber, out=args.out, accept=accept)
    status = 0 if not accept or result["acceptance"]["passes"] else 1
    if args.json:
        print(jsonout.dumps(result, indent=2))
        return status
    out = sys.stdout
    fit_deg = ", ".join(f"{np.rad2deg(x):g}°" for x in result["fit_orientations_rad"])
    val_deg = ", ".join(f"{np.rad2deg(x):g}°" for x in result["validation_orientations_rad"])
    print(f"Jig calibration on the twin: {result['poses']} poses ({params.trials} trials × "
          f"{len(params.curvatures)} grooves × {len(params.orientations_deg)} orientations, {params.frames} frames "
          f"each); fit on {fit_deg}, validated on {val_deg}.", file=out)
    if args.out:
        print(f"Poses written to {args.out}", file=out)
    truth = result["truth"]
    print(f"True roll {np.rad2deg(truth['roll_rad']):.2f}°; true core angles "
          f"{', '.join(f'{np.rad2deg(x):.2f}' for x in truth['core_angles_rad'])}° and gains "
          f"{', '.join(f'{x * 1e6:.1f}' for x in truth['gains_m'])} µm.\n", file=out)
    print(f"{'grating':>7s}{'κ (1/m)':>9s}{'n':>4s}   {'physical: |Δκ| max':>19s}{'|Δdir| max':>11s}"
          f"   {'matrix: |Δκ| max':>17s}{'|Δdir| max':>11s}", file=out)
    rows = {m: result["models"][m]["validation"]["levels"] for m in ("physical", "matrix")}
    for a, b in zip(rows["physical"], rows["matrix"], strict=True):
        print(f"{a['grating']:7d}{a['curvature_1_per_m']:9.3f}{a['n']:4d}   "
              f"{a['magnitude_error_max_abs_1_per_m']:19.4f}{a['direction_error_max_abs_deg']:10.3f}°"
              f"   {b['magnitude_error_max_abs_1_per_m']:17.4f}{b['direction_error_max_abs_deg']:10.3f}°", file=out)
    print(file=out)
    for model, m in result["models"].items():
        s = m["validation"]["summary"]
        fit_d = m["fit"]
        print(f"{model:9s} roll {np.rad2deg(fit_d['roll_rad']):7.2f}°   κ ≥ {MIN_CURVATURE:g} 1/m: "
              f"max |Δκ| = {s['max_abs_magnitude_error_1_per_m']:.4f} 1/m, max |Δdir| = "
              f"{s['max_abs_direction_error_deg']:.3f}°" + (f"   {'PASS' if m['passes'] else 'FAIL'} "
              f"(≤ {MAX_ERROR:g} 1/m, ≤ {MAX_DIRECTION_ERROR_DEG:g}°)" if accept else ""), file=out)
        rec = m["recovery"]
        print(f"{'':9s} sensor found to {rec['max_core_angle_error_deg']:.3f}° (core angles), "
              f"{rec['max_gain_error_rel']:.2%} (gains), {rec['max_twist_error_deg']:.3f}° (twist between gratings)",
              file=out)
        for w in fit_d["warnings"]:
            print(f"          warning: {w}", file=out)
    if result["loro"] is not None:
        lo = result["loro"]
        print(f"\nLeave one rotation out (physical model, gratings {lo['gratings']}): in-sample RMS strain residual "
              f"{lo['rms_strain_residual'] * 1e6:.1f} µε; median per-level RMS |Δκ| "
              f"{lo['loro_kappa_error_1_per_m']:.4f} 1/m; median |mean Δdir| (κ ≥ {MIN_CURVATURE:g} 1/m) "
              f"{lo['loro_direction_error_deg']:.2f}°", file=out)
    if not accept:
        print("No acceptance verdict for this sensor: it is simulated as the real jig table shows it; "
              "twin run real-jig compares the statistics with the real table.", file=out)
    print("\nThe fitted roll and core angles are in the calibration's gauge (the cores' centroid on the axis, core 0 "
          "at its nominal bearing from it; docs/jig.md); the true sensor is compared in the same gauge.", file=out)
    return status
