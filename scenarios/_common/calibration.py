"""The calibration a scenario reports its results with: one helper for every scenario.

``--calibration`` takes

* ``lab`` (the default wherever a result is reported): the calibration a lab could make of the twin's fibre —
  the two-step calibration in ``sim://calibration`` (straight, then an in-plane bend), then identification of
  [Δθ, g] against the *fixture's* geometry (the grooves' and tubes' centrelines, as a mould's CAD model gives
  them; not the rod's exact centreline, which no lab has) on the paper's identification shapes
  (:data:`LAB_SHAPES`: 3 planar in the grooved plate, 3 spatial in 3 mm tubes). Dynamic experiments report on
  other shapes; ``static-shapes`` identifies on the half of the library it does not report (two folds) through
  :func:`identify_on_fixtures`;
* ``true``: the twin's true fibre parameters (as-built λ0, intrinsic twist, Δθ, g), which no lab has — for
  studies of everything but the calibration;
* ``lambda0``: the as-built λ0 only; ``nominal``: the datasheet;
* the path of a calibration TOML.

The lab calibration depends only on the simulated physical fibre (the true parameters and ``fiber_seed`` of the
optics), so it is computed once and cached as a calibration TOML under ``$TWIN_CACHE_DIR`` (default
``~/.cache/catheter-twin``), keyed by a hash of everything it depends on; a second run loads it in
milliseconds. Its noise seeds are fixed, independent of the scenario's ``--seed``.

Every result says which calibration it used: :meth:`UsedCalibration.to_dict` goes into ``--json``,
:attr:`UsedCalibration.label` onto every report and figure.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenarios._common.entry import option
from sim_interrogator.optics import Optics, OpticsConfig
from sim_interrogator.setups import CalibrationPoses, StaticShape
from sim_interrogator.sim import SimInterrogator
from twin import Calibration, FiberModel, shapes
from twin.calibration import CalibrationReport
from twin.calibration import two_step as calibration_two_step
from twin.calibration.identify import Observation, identify

__all__ = ["CALIBRATIONS", "LAB_SHAPES", "UsedCalibration", "cache_dir", "calibration_field", "calibration_for",
           "check_calibration", "fixture_observation", "identify_on_fixtures", "lab_calibration", "label",
           "paper_fixture"]

#: What ``--calibration`` accepts besides a calibration TOML.
CALIBRATIONS = ("lab", "true", "lambda0", "nominal")
#: The paper's identification shapes (3 planar, 3 spatial), as in ``paper-ablation``.
LAB_SHAPES = ("arc", "s-curve", "hook", "helix", "rotating-bend", "two-plane")
_CACHE_VERSION = 1
_LAB_SEED = 1000  # noise seeds of the lab session, independent of any scenario's --seed

Say = Callable[[str], None]


@dataclass(frozen=True, eq=False)
class UsedCalibration:
    """A calibration and what it is.

    Attributes
    ----------
    name : str
        ``lab``, ``true``, ``lambda0``, ``nominal`` or the TOML's path.
    calibration : Calibration or None
        None: the datasheet.
    description : str
        One sentence for reports.
    """

    name: str
    calibration: Calibration | None
    description: str

    @property
    def label(self) -> str:
        """Short text stamped on figures."""
        return label(self.name)

    def to_dict(self) -> dict:
        c = self.calibration
        out: dict = {"name": self.name, "description": self.description}
        if c is not None and c.delta_theta is not None:
            out["delta_theta"] = c.delta_theta
        if c is not None and c.gain is not None:
            out["g_um"] = c.gain * 1e6
        return out


_SHORT = {"lab": "two-step + identification on fixture geometry", "true": "the twin's true parameters",
          "lambda0": "as-built λ0 only", "nominal": "datasheet"}


def label(name: str) -> str:
    """Short text stamped on figures for the calibration called ``name`` (or a result's ``calibration`` dict)."""
    if isinstance(name, dict):
        name = str(name.get("name", "?"))
    return f"calibration: {name}" + (f" ({_SHORT[name]})" if name in _SHORT else "")


def calibration_field(default: str = "lab"):
    """The ``calibration`` field of a scenario's ``Params``: ``--calibration``, resolved by
    :func:`calibration_for`."""
    return field(default=default, metadata=option(
        f"{', '.join(CALIBRATIONS)} or a calibration TOML (scenarios/_common/calibration.py)", metavar="CAL"))


def check_calibration(kind: str) -> str:
    """``kind`` if ``--calibration`` accepts it; a clear ValueError otherwise."""
    if kind not in CALIBRATIONS and not Path(kind).is_file():
        raise ValueError(f"--calibration {kind}: no such file (or one of {', '.join(CALIBRATIONS)})")
    return kind


def calibration_for(kind: str, optics: OpticsConfig | Optics, fiber: FiberModel | None = None, *,
                    progress: Say | None = None) -> UsedCalibration:
    """The calibration called ``kind`` (see the module docstring) for the twin's fibre read through ``optics``
    (an :class:`OpticsConfig` or a running simulator's :class:`Optics`)."""
    check_calibration(kind)
    fiber = fiber or FiberModel.paper()
    opt = optics if isinstance(optics, Optics) else Optics(fiber, optics)
    if kind == "true":
        return UsedCalibration(kind, opt.true_calibration(), "the twin's true fibre parameters (as-built λ0, "
                               "intrinsic twist, Δθ, g), which no lab has")
    if kind == "lambda0":
        cal = Calibration(lambda0=opt.true_fiber.lambda0,
                          provenance={"method": "the simulated fibre's as-built λ0 only"})
        return UsedCalibration(kind, cal, "the twin's as-built reference wavelengths only, datasheet otherwise")
    if kind == "nominal":
        return UsedCalibration(kind, None, "the datasheet: nominal λ0, no twist, nominal Δθ and g")
    if kind == "lab":
        cal = lab_calibration(fiber, opt.config, progress=progress)
        return UsedCalibration(kind, cal, "as a lab makes it: two-step calibration in the twin, then [Δθ, g] "
                               f"identified against the fixtures' geometry on {', '.join(LAB_SHAPES)} "
                               f"(Δθ = {cal.delta_theta:.4f} rad, g = {cal.gain * 1e6:.3f} µm)")
    return UsedCalibration(kind, Calibration.load(kind), f"loaded from {kind}")


def paper_fixture(name: str) -> str:
    """The paper's fixture for a library shape: the grooved plate for planar shapes, a 3 mm tube otherwise."""
    return "groove" if shapes.get(name).planar else "tube"


def fixture_observation(frames, fiber: FiberModel, name: str) -> Observation:
    """An identification input from frames of one settled shape, its truth the fixture's centreline (arc
    length spread over the sensed length, as a CAD model of the mould gives it)."""
    fixture = frames[0].truth.fixture
    return Observation(np.stack([f.wavelengths for f in frames]), fixture,
                       np.linspace(0.0, fiber.sensed_length, len(fixture)), name)


def identify_on_fixtures(fiber: FiberModel, base: Calibration, observations: Sequence[Observation]) -> Calibration:
    """``base`` (λ0, twist from the two-step calibration) with [Δθ, g] identified on ``observations``."""
    cal = identify(fiber, observations, base).calibration(base)
    names = ", ".join(o.name for o in observations)
    return cal.replace(provenance={**cal.provenance, "identified_on": f"fixture geometry of {names}"})


def cache_dir() -> Path:
    return Path(os.environ.get("TWIN_CACHE_DIR") or Path.home() / ".cache" / "catheter-twin")


def two_step_in_twin(fiber: FiberModel, optics: OpticsConfig | None = None, frames: int = 100,
                     ) -> tuple[Calibration, CalibrationReport, dict]:
    """The two-step calibration in ``sim://calibration`` (straight, then the in-plane bend), the twin taking each
    pose; returns (calibration, report, the true parameters)."""
    sim = SimInterrogator(CalibrationPoses(), fiber, optics or OpticsConfig(), truth=False)
    straight = np.stack([sim.read().wavelengths for _ in range(frames)])
    sim.set_pose("bend")
    bend = np.stack([sim.read().wavelengths for _ in range(frames)])
    cal, report = calibration_two_step(fiber, straight, bend)
    return cal.replace(provenance={**cal.provenance, "source": "sim://calibration"}), report, sim.describe()


def two_step(fiber: FiberModel, optics: OpticsConfig, frames: int = 100) -> Calibration:
    """The two-step calibration in ``sim://calibration`` with the lab session's noise seed."""
    return two_step_in_twin(fiber, optics.replace(seed=_LAB_SEED), frames)[0]


def lab_calibration(fiber: FiberModel, optics: OpticsConfig, *, names: Sequence[str] = LAB_SHAPES,
                    repeats: int = 5, cache: bool = True, progress: Say | None = None) -> Calibration:
    """The lab calibration of the twin's fibre (module docstring), from the cache when it is there."""
    say = progress or (lambda msg: None)
    key = {"version": _CACHE_VERSION, "fiber": fiber.to_dict(),
           # the noise seed is the lab session's own; S_T mismatch does not act at the calibration's temperature
           "optics": {k: v for k, v in dataclasses.asdict(optics).items() if k not in ("seed", "thermal_mismatch")},
           "shapes": list(names), "repeats": repeats}
    digest = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:16]
    path = cache_dir() / f"lab-calibration-{digest}.toml"
    if cache and path.is_file():
        say(f"calibration: lab, from the cache ({path})")
        return Calibration.load(path)
    say("calibration: lab — two-step calibration in the twin (straight, then an in-plane bend) …")
    base = two_step(fiber, optics)
    obs = []
    for i, name in enumerate(names):
        say(f"calibration: lab — identification shape {i + 1}/{len(names)}: {name} in the {paper_fixture(name)} …")
        sim = SimInterrogator(StaticShape(name, paper_fixture(name)), fiber,
                              optics.replace(seed=_LAB_SEED + 1 + i))
        obs.append(fixture_observation([sim.read() for _ in range(repeats)], fiber, name))
    cal = identify_on_fixtures(fiber, base, obs)
    if cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        cal.save(tmp)
        tmp.replace(path)  # atomic: concurrent runs never read half a file
        say(f"calibration: lab, cached in {path}")
    return cal
