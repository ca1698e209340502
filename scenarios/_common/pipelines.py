"""The three reconstruction pipelines every experiment compares: ours, the paper's with θ_b held through low
curvature (``Reconstructor.paper``, κ_min = 1 1/m) and the paper's literal transcription (κ_min = 0). Needs
only ``twin``: the simulator-free scenarios use it too."""

from __future__ import annotations

from twin import Calibration, FiberModel, Reconstructor

__all__ = ["MODES", "reconstructors"]

#: The pipelines' names, in the order reports list them.
MODES = ("default", "paper", "paper-literal")


def reconstructors(fiber: FiberModel, cal: Calibration | None = None) -> dict[str, Reconstructor]:
    """The pipelines of :data:`MODES`, with the same calibration (None: the datasheet)."""
    return {"default": Reconstructor(fiber, cal), "paper": Reconstructor.paper(fiber, cal),
            "paper-literal": Reconstructor.paper(fiber, cal, kappa_min=0.0)}
