"""The simulated fibre's calibration, made the way a lab makes one: the two-step calibration in the twin
(``sim://calibration``) and, optionally, identification of [Δθ, g] on library shapes held by connect constraints
(the rod's centreline as the truth, as a CT would give it).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sim_interrogator.optics import OpticsConfig
from sim_interrogator.setups import CalibrationPoses, StaticShape
from sim_interrogator.sim import SimInterrogator
from twin import Calibration, FiberModel
from twin.calibration import CalibrationReport, two_step
from twin.calibration.identify import Identification, Observation, identify

__all__ = ["IDENTIFY_SHAPES", "identify_in_twin", "two_step_in_twin"]

IDENTIFY_SHAPES = ("arc", "s-curve", "hook", "helix", "rotating-bend", "two-plane")


def two_step_in_twin(fiber: FiberModel, optics: OpticsConfig | None = None, frames: int = 100,
                     ) -> tuple[Calibration, CalibrationReport, dict]:
    """Run the two-step calibration on the simulated fibre; returns (calibration, report, the true parameters)."""
    sim = SimInterrogator(CalibrationPoses(), fiber, optics or OpticsConfig(), truth=False)
    straight = np.stack([sim.read().wavelengths for _ in range(frames)])
    sim.set_pose("bend")
    bend = np.stack([sim.read().wavelengths for _ in range(frames)])
    cal, report = two_step(fiber, straight, bend)
    return cal.replace(provenance={**cal.provenance, "source": "sim://calibration"}), report, sim.describe()


def identify_in_twin(fiber: FiberModel, calibration: Calibration, names=IDENTIFY_SHAPES, repeats: int = 5,
                     fixture: str = "connect", seed: int = 1,
                     progress: Callable[[str], None] | None = None) -> Identification:
    """Identify [Δθ, g] from library shapes in the twin (the rod's centreline as the truth)."""
    obs = []
    for i, name in enumerate(names):
        if progress:
            progress(f"  shape {i + 1}/{len(names)}: {name}")
        sim = SimInterrogator(StaticShape(name, fixture), fiber, OpticsConfig(seed=seed + i))
        frames = [sim.read() for _ in range(repeats)]
        truth = frames[0].truth
        obs.append(Observation(np.stack([f.wavelengths for f in frames]), truth.positions, truth.s, name))
    return identify(fiber, obs, calibration)
