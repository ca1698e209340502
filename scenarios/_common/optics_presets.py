"""The simulated interrogator's optics, by name: one switch for every scenario.

* ``realistic``: the twin's as-built fibre (Δθ, gain, λ0 scatter, intrinsic twist off their datasheet values)
  read with noise, drift, quantisation, peak loss and the grating-length average (``OpticsConfig(seed=…)``);
* ``ideal``: every effect off, the nominal fibre read exactly (``OpticsConfig.ideal()``).
"""

from __future__ import annotations

from dataclasses import field

from scenarios._common.entry import option
from sim_interrogator.optics import OpticsConfig

__all__ = ["OPTICS", "optics_config", "optics_field"]

OPTICS = ("realistic", "ideal")


def optics_config(name: str, seed: int = 0) -> OpticsConfig:
    """The :class:`OpticsConfig` called ``name`` (one of :data:`OPTICS`), its noise seeded with ``seed``."""
    if name == "realistic":
        return OpticsConfig(seed=seed)
    if name == "ideal":
        return OpticsConfig.ideal()
    raise ValueError(f"optics must be one of {', '.join(OPTICS)}; got {name!r}")


def optics_field(default: str = "realistic"):
    """The ``optics`` field of a scenario's ``Params``: ``--optics``, one of :data:`OPTICS`."""
    return field(default=default, metadata=option("synthetic interrogator effects", choices=OPTICS))
