"""Calibration: reference wavelengths, intrinsic twist and identified parameters (docs/math.md §4.2, §5).

A :class:`Calibration` refines a :class:`~twin.fiber.FiberModel` for one physical sensor:

* ``lambda0`` — reference (straight, unloaded) wavelengths per grating and core, nm (step 1 of the paper);
* ``twist`` — the cores' intrinsic twist at each grating relative to grating 0, rad: core i sits at
  θ_i + twist[n] (step 2; the paper's θ_b,t with the opposite sign and the global roll removed);
* ``delta_theta``, ``gain`` — identified outer-core spacing Δθ (rad) and gain g = r·S_ε (m), with 1σ
  uncertainties (see :mod:`twin.calibration.identify`);
* ``design`` — fitted per-grating design matrices (n_gratings, n_cores, 3) from a jig calibration, which
  replace the physical model entirely when present;
* ``spin_rate``, ``spin_rate_std`` — a spun fibre's measured spin rate, turns/m, and its 1σ (the two-step
  procedure fits it to the bend step's residual core angles; docs/spun-fibers.md); ``twist`` then holds what the
  fitted helix leaves;
* ``provenance`` — free-form record of how it was made.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twin._validate import check_bragg_nm, check_field_types, check_table, frozen, real_array
from twin.fiber import FiberModel, origin, read_toml
from twin.frames import Frame
from twin.strain import CurvatureSolver, design_matrix, optical_strain

__all__ = ["Calibration", "CalibrationError", "CalibrationReport", "scaled_core_angles", "two_step"]

_OWNER = "Calibration"

#: what each field of a calibration file holds (checked before anything is converted)
FIELD_KINDS = {
    "lambda0": "rows",
    "twist": "numbers",
    "delta_theta": "number",
    "gain": "number",
    "delta_theta_std": "number",
    "gain_std": "number",
    "design": "matrices",
    "provenance": "table",
    "spin_rate": "number",
    "spin_rate_std": "number",
}
#: resolution λ0 is stored at, nm (see :func:`two_step`)
LAMBDA0_RESOLUTION_DECIMALS = 9


class CalibrationError(ValueError):
    """A calibration step cannot be used (weak bend, inflection, motion, missing peaks)."""


def scaled_core_angles(fiber: FiberModel, delta_theta: float) -> np.ndarray:
    """Core angles with the off-axis cores' spacing set to ``delta_theta`` (rad), in the fibre's own sense.

    The nominal spacing is the angle between the first two off-axis cores; each off-axis core keeps its offset
    from the first one measured in units of that spacing (0, 1, 2 for the paper's adjacent cores).
    """
    bend = fiber.bending_cores
    angles = fiber.core_angles.copy()
    ref = angles[bend[0]]
    nominal = angles[bend[1]] - ref
    if nominal == 0:
        raise ValueError("the first two off-axis cores share one angle; Δθ is undefined for this layout")
    angles[bend] = ref + (angles[bend] - ref) / nominal * delta_theta
    return angles


def nominal_delta_theta(fiber: FiberModel) -> float:
    """The fibre's nominal off-axis core spacing, rad (see :func:`scaled_core_angles`)."""
    b = fiber.bending_cores
    return float(fiber.core_angles[b[1]] - fiber.core_angles[b[0]])


def nominal_gain(fiber: FiberModel) -> float:
    """The fibre's nominal g = r̄·S_ε over the off-axis cores, m."""
    return float(fiber.core_radii[fiber.bending_cores].mean() * fiber.strain_sensitivity)


@dataclass(frozen=True, eq=False)
class Calibration:
    """Sensor-specific corrections to a fibre model (see the module docstring for each field's meaning).

    All fields are optional; an empty calibration reproduces the nominal fibre.
    """

    lambda0: np.ndarray | None = None
    twist: np.ndarray | None = None
    delta_theta: float | None = None
    gain: float | None = None
    delta_theta_std: float | None = None
    gain_std: float | None = None
    design: np.ndarray | None = None
    provenance: Mapping[str, object] = field(default_factory=dict)
    spin_rate: float | None = None
    spin_rate_std: float | None = None

    def __post_init__(self) -> None:
        if self.lambda0 is not None:
            lam = real_array(self.lambda0, "lambda0", shape=(None, None), unit="nm", owner=_OWNER)
            check_bragg_nm(lam, f"{_OWNER}.lambda0")  # the fibre model's range: a calibration in µm runs unusable
            object.__setattr__(self, "lambda0", frozen(lam))
        if self.twist is not None:
            object.__setattr__(
                self, "twist", frozen(real_array(self.twist, "twist", shape=(None,), unit="rad", owner=_OWNER))
            )
        if self.design is not None:
            object.__setattr__(
                self, "design",
                frozen(real_array(self.design, "design", shape=(None, None, 3), owner=_OWNER)),
            )
        for name, lo, hi, unit in (
            ("delta_theta", 0.0, 2 * np.pi, "rad"),
            ("gain", 1e-9, 1e-3, "m (r·S_ε, e.g. 2.9e-05)"),
            ("delta_theta_std", 0.0, np.inf, "rad"),
            ("gain_std", 0.0, np.inf, "m"),
            ("spin_rate", -1000.0, 1000.0, "turns/m"),
            ("spin_rate_std", 0.0, np.inf, "turns/m"),
        ):
            v = getattr(self, name)
            if v is not None:
                v = float(v)
                if not (np.isfinite(v) and lo <= v <= hi):
                    raise ValueError(f"{_OWNER}.{name}: expected a value in [{lo}, {hi}] {unit}, got {v}")
                object.__setattr__(self, name, v)
        object.__setattr__(self, "provenance", dict(self.provenance))

    # ---------------------------------------------------------------- applying it to a fibre
    def check(self, fiber: FiberModel) -> None:
        """Raise a clear error when this calibration does not fit ``fiber``'s gratings and cores; it names the
        calibration's file and the fibre model's when they were read from files (:func:`twin.fiber.origin`)."""
        n_g, n_c = fiber.n_gratings, fiber.n_cores
        for name, shape in (("lambda0", (n_g, n_c)), ("twist", (n_g,)), ("design", (n_g, n_c, 3))):
            v = getattr(self, name)
            if v is not None and v.shape != shape:
                cal = origin(self)
                fib = origin(fiber)
                raise ValueError(
                    f"{cal + ': ' if cal else ''}calibration field {name} has shape {v.shape} but the fibre model"
                    f"{' (' + fib + ')' if fib else ''} has {n_g} gratings × {n_c} cores (expected {shape}); "
                    "was the calibration made for another sensor?"
                )

    def reference_for(self, fiber: FiberModel) -> np.ndarray:
        """Reference wavelengths to use with ``fiber``, nm, shape (n_gratings, n_cores)."""
        self.check(fiber)
        return fiber.lambda0 if self.lambda0 is None else self.lambda0

    def design_for(self, fiber: FiberModel) -> np.ndarray:
        """Design matrices (n_gratings, n_cores, 3) of the calibrated sensor (see :mod:`twin.strain`)."""
        self.check(fiber)
        if self.design is not None:
            return np.array(self.design)
        angles = None if self.delta_theta is None else scaled_core_angles(fiber, self.delta_theta)
        gains = None
        if self.gain is not None:
            gains = fiber.gains * (self.gain / nominal_gain(fiber))
        if self.spin_rate is not None:
            fiber = fiber.replace(spin_rate=self.spin_rate)
        return design_matrix(fiber, core_angles=angles, gains=gains, twist=self.twist)

    def replace(self, **changes) -> Calibration:
        return dataclasses.replace(self, **changes)

    # ---------------------------------------------------------------- files
    def to_dict(self) -> dict:
        d: dict = {}
        for name in ("delta_theta", "gain", "delta_theta_std", "gain_std", "spin_rate", "spin_rate_std"):
            v = getattr(self, name)
            if v is not None:
                d[name] = v
        for name in ("lambda0", "twist", "design"):
            v = getattr(self, name)
            if v is not None:
                d[name] = v.tolist()
        d["provenance"] = {k: v for k, v in self.provenance.items() if v is not None}
        return d

    @classmethod
    def from_dict(cls, data: Mapping, *, source: str = "") -> Calibration:
        where = f"{source}: " if source else ""
        check_table(data, cls, "calibration", where)
        check_field_types(data, FIELD_KINDS, where)
        try:
            cal = cls(**data)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}{exc}") from None
        if source:
            object.__setattr__(cal, "_origin", source)
        return cal

    def save(self, path: str | Path) -> None:
        """Write as TOML (SI units; wavelengths in nm)."""
        import tomli_w

        header = (
            "# twin calibration: lambda0 in nm; twist and delta_theta in rad (twist = core rotation relative to\n"
            "# grating 0); gain = r*S_eps in m; design = per-grating matrices e = D (c, k_x, k_y)\n"
        )
        Path(path).write_text(header + tomli_w.dumps(self.to_dict()))

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        path = Path(path)
        return cls.from_dict(read_toml(path, "calibration"), source=str(path))

    # ---------------------------------------------------------------- the paper's two-step procedure
    @classmethod
    def from_frames(cls, fiber: FiberModel, straight, bend, **options) -> Calibration:
        """Two-step calibration from a straight and an in-plane bend pose; see :func:`two_step`."""
        return two_step(fiber, straight, bend, **options)[0]


@dataclass(frozen=True, eq=False)
class CalibrationReport:
    """What the two-step calibration measured.

    Attributes
    ----------
    n_straight, n_bend : int
        Frames averaged in each step.
    lambda0_std : ndarray (n_gratings, n_cores)
        Frame-to-frame std of the straight wavelengths, nm (the interrogator noise).
    bend_curvature : ndarray (n_gratings, 2)
        Mean measured curvature vector of the bend step (nominal model, no twist compensation), 1/m.
    twist : ndarray (n_gratings,)
        Intrinsic twist found, rad.
    twist_std : ndarray (n_gratings,)
        Its 1σ noise from the frame-to-frame scatter of the bend step, rad.
    motion : tuple of float
        Frame-to-frame std of the curvature in each step, 1/m (high means the catheter moved).
    sign_changes : int
        Gratings where the bend direction flipped (an inflection), accepted only with ``allow_sign_change``.
    spin_rate, spin_rate_std : float or None
        A spun fibre's fitted spin rate and its 1σ, turns/m (None for straight cores).
    """

    n_straight: int
    n_bend: int
    lambda0_std: np.ndarray
    bend_curvature: np.ndarray
    twist: np.ndarray
    twist_std: np.ndarray
    motion: tuple[float, float]
    sign_changes: int
    spin_rate: float | None = None
    spin_rate_std: float | None = None


def _as_stack(frames, fiber: FiberModel, step: str) -> np.ndarray:
    if isinstance(frames, Frame):  # one frame or a batch
        w = frames.wavelengths.reshape(-1, *frames.wavelengths.shape[-2:])
    elif isinstance(frames, list | tuple) and frames and isinstance(frames[0], Frame):
        w = Frame.stack(frames).wavelengths
    else:
        w = np.asarray(frames, dtype=np.float64)
        if w.ndim == 2:
            w = w[None]
    if w.ndim != 3 or w.shape[1:] != (fiber.n_gratings, fiber.n_cores):
        raise CalibrationError(
            f"{step} step: expected frames of shape (n_frames, {fiber.n_gratings}, {fiber.n_cores}), got {w.shape}"
        )
    return w


def _mean_peaks(w: np.ndarray, step: str, fiber: FiberModel, max_missing: float) -> np.ndarray:
    missing = np.isnan(w).mean(axis=0)
    if np.any(missing > max_missing):
        n, c = np.argwhere(missing > max_missing)[0]
        raise CalibrationError(
            f"{step} step: grating {n} (s = {fiber.grating_s[n] * 1e3:.1f} mm) core {c} lost its peak in "
            f"{missing[n, c]:.0%} of {w.shape[0]} frames; check the connection and that no peak leaves its slot"
        )
    return np.nanmean(w, axis=0)


def two_step(
    fiber: FiberModel,
    straight,
    bend,
    *,
    base: Calibration | None = None,
    min_curvature: float = 5.0,
    max_motion: float = 0.5,
    max_missing: float = 0.2,
    allow_sign_change: bool = False,
) -> tuple[Calibration, CalibrationReport]:
    """The paper's two-step calibration with the fixes of docs/math.md §4.2.

    Step 1 (``straight``): the mean wavelengths of the straight, unloaded fibre become λ0 (rounded to 1e-9 nm,
    far below any interrogator's resolution, so that files carry the mean and not its binary summation error).
    Step 2 (``bend``): a single-sign in-plane bend; the bend angle measured at each grating departs from a
    constant by the cores' intrinsic twist, which is unwrapped modulo π and stored relative to grating 0.

    Parameters
    ----------
    fiber : FiberModel
    straight, bend : Frame (one or a batch), list of Frame, or array (n_frames, n_gratings, n_cores)
        Wavelengths (nm) recorded in each pose; many frames are averaged.
    base : Calibration, optional
        Identified Δθ and g to keep (and use while measuring the twist).
    min_curvature : float
        Smallest usable bend curvature at any grating, 1/m (the angle noise is ≈ σ_k/κ; the paper's 0.16 1/cm
        is 16 1/m).
    max_motion : float
        Largest frame-to-frame std of the curvature within a step, 1/m, before the step counts as moving.
    max_missing : float
        Largest fraction of frames in which a peak may be missing.
    allow_sign_change : bool
        Accept a bend whose direction flips (an inflection) by trusting the mod-π unwrapping; refused by default
        because the twist there is only as good as the assumption |Δφ| < π/2 between gratings.

    Raises
    ------
    CalibrationError
        When a step is unusable; the message names the grating and the reason.
    """
    ws = _as_stack(straight, fiber, "straight")
    wb = _as_stack(bend, fiber, "bend")
    base = base or Calibration()
    # The mean of wavelengths quantised at 1e-4 nm is a decimal of a few more places; summing in binary leaves
    # an error of an ulp or so (2.3e-13 nm at 1510 nm), which the file would then carry as 1510.1080899999997
    # for 1510.10809. Rounding to 1e-9 nm removes that artefact and nothing measured: it is 5 orders of
    # magnitude below the interrogators' 1e-4 nm resolution (an optical strain of 3e-13).
    lam0 = np.round(_mean_peaks(ws, "straight", fiber, max_missing), LAMBDA0_RESOLUTION_DECIMALS)
    lam_b = _mean_peaks(wb, "bend", fiber, max_missing)
    nominal = base.replace(lambda0=None, twist=None, design=None)
    solver = CurvatureSolver(nominal.design_for(fiber), central_core=fiber.central_core)

    k_straight = solver.solve(optical_strain(ws, lam0)).curvature  # missing peaks drop out per frame
    k_bend_frames = solver.solve(optical_strain(wb, lam0)).curvature
    with np.errstate(invalid="ignore"):
        motion = tuple(float(np.nanmax(np.nanstd(k, axis=0), initial=0.0)) for k in (k_straight, k_bend_frames))
    for step, m in zip(("straight", "bend"), motion, strict=True):
        if m > max_motion:
            raise CalibrationError(
                f"{step} step: the curvature varies by {m:.2f} 1/m (std) between frames, above {max_motion} 1/m; "
                "hold the catheter still while recording"
            )
    k = solver.solve(optical_strain(lam_b, lam0)).curvature
    kappa = np.hypot(k[:, 0], k[:, 1])
    weak = kappa < min_curvature
    if weak.any():
        n = int(np.argmax(weak))
        raise CalibrationError(
            f"bend step: grating {n} (s = {fiber.grating_s[n] * 1e3:.1f} mm) is bent only {kappa[n]:.2f} 1/m, below "
            f"{min_curvature} 1/m; bend the whole sensed length more (≈ 16 1/m, the paper's 0.16 1/cm)"
        )
    theta = np.arctan2(k[:, 1], k[:, 0])
    theta_pi = 0.5 * np.unwrap(2 * theta)  # mod-π unwrapping (docs/math.md §4.2)
    # theta_pi − theta is a multiple of π; an odd multiple marks a grating whose bend direction is reversed
    flips = np.abs(np.round((theta_pi - theta) / np.pi)) % 2 == 1
    sign_changes = int(np.count_nonzero(np.diff(flips.astype(int))))
    if sign_changes and not allow_sign_change:
        n = int(np.argmax(np.diff(flips.astype(int)) != 0)) + 1
        raise CalibrationError(
            f"bend step: the bend direction flips at grating {n} (s = {fiber.grating_s[n] * 1e3:.1f} mm), an "
            "inflection; use a single-sign bend (an arc), or pass allow_sign_change=True to trust mod-π unwrapping"
        )
    twist = -(theta_pi - theta_pi[0])
    # angle noise per grating: scatter of the per-frame curvature across the bend direction
    kf = k_bend_frames
    across = (-kf[..., 0] * np.sin(theta) + kf[..., 1] * np.cos(theta))
    twist_std = np.nanstd(across, axis=0) / kappa / np.sqrt(wb.shape[0])
    spin = spin_std = None
    if fiber.spin_rate:
        twist, spin, spin_std = _fit_spin(fiber, base, twist, twist_std)
    report = CalibrationReport(
        n_straight=ws.shape[0],
        n_bend=wb.shape[0],
        lambda0_std=np.nanstd(ws, axis=0),
        bend_curvature=k,
        twist=twist,
        twist_std=twist_std,
        motion=motion,
        sign_changes=sign_changes,
        spin_rate=spin,
        spin_rate_std=spin_std,
    )
    provenance = dict(base.provenance)
    provenance.update(
        {
            "method": "two-step (straight, in-plane bend)",
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "straight_frames": ws.shape[0],
            "bend_frames": wb.shape[0],
            "bend_curvature_min_1_per_m": float(kappa.min()),
            "twist_range_rad": float(np.ptp(twist)),
        }
    )
    if spin is not None:
        provenance["spin_rate_turns_per_m"] = spin
    cal = base.replace(lambda0=lam0, twist=twist, design=None, provenance=provenance, spin_rate=spin,
                       spin_rate_std=spin_std)
    return cal, report


def _fit_spin(fiber: FiberModel, base: Calibration, residual: np.ndarray, std: np.ndarray):
    """A spun fibre's spin rate from the bend step: the core angles left over by the nominal helix are fitted
    with a phase and a rate, a + b s (weighted by their noise); the rate joins the calibration's spin rate and
    ``twist`` keeps only what the line leaves, so the calibrated core angles reproduce the measured ones.

    Returns (twist rad (n_gratings,), spin rate turns/m, its 1σ turns/m).
    """
    s = fiber.grating_s
    if s.size < 2:  # a phase and a rate from one grating: numpy's bare "Singular matrix" named nothing
        fib = origin(fiber)
        raise CalibrationError(f"{fib + ': ' if fib else ''}FiberModel.grating_s: a spun fibre's spin rate is fitted "
                               f"along its gratings and needs 2 or more; this one has {s.size}")
    nominal = fiber.spin_rate if base.spin_rate is None else base.spin_rate
    w = 1.0 / np.maximum(std, 1e-6) ** 2  # a noise-free (simulated) step still weighs every grating
    a = np.stack([np.ones_like(s), s], axis=1)
    normal = (a.T * w) @ a
    coef = np.linalg.solve(normal, (a.T * w) @ residual)
    # the scatter about the line sets the rate's 1σ when it exceeds the per-grating noise (a non-helical twist)
    dof = max(s.size - 2, 1)
    chi2 = float(np.sum(w * (residual - a @ coef) ** 2) / dof)
    rate_std = float(np.sqrt(np.linalg.inv(normal)[1, 1] * max(chi2, 1.0)))
    b = float(coef[1])
    spin = nominal + fiber.handedness * b / (2 * np.pi)
    return residual - b * s, float(spin), rate_std / (2 * np.pi)
