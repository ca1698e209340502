"""``sim://SETUP?key=value…``: open a :class:`~sim_interrogator.sim.SimInterrogator` by URL.

Query keys are the setup's own parameters (e.g. ``shape``, ``fixture``), plus these for the interrogator:
``rate`` (Hz, default 100), ``realtime`` (0/1, default 0), ``optics`` (``realistic`` or ``ideal``), ``noise_pm``,
``seed`` and ``truth`` (0/1). Example: ``sim://static?shape=helix&fixture=tube&rate=100``.
"""

from __future__ import annotations

import importlib
import importlib.util

from sim_interrogator.optics import OpticsConfig
from sim_interrogator.setups import SETUPS, parse_params
from sim_interrogator.sim import SimInterrogator
from twin.io.source import parse_url

__all__ = ["open_sim"]

_SOURCE_KEYS = {"rate", "realtime", "optics", "noise_pm", "seed", "truth"}

#: Modules that register more setups (imported on first use; absent ones are skipped).
SETUP_MODULES = ("sim_interrogator.sheath", "sim_interrogator.tendon", "sim_interrogator.thermal")


def _load_setups() -> None:
    for name in SETUP_MODULES:
        if importlib.util.find_spec(name) is not None:
            importlib.import_module(name)


def open_sim(url: str, **options) -> SimInterrogator:
    """Build the setup named in ``url`` and return its SimInterrogator (``options`` override the query)."""
    _load_setups()
    _, name, params = parse_url(url)
    fiber = options.pop("fiber", None)
    params.update({k: str(v) for k, v in options.items()})
    name = name.strip("/")
    if name not in SETUPS:
        raise ValueError(f"{url!r}: unknown simulated setup {name!r}; known: {', '.join(sorted(SETUPS))}")
    source = {k: params.pop(k) for k in list(params) if k in _SOURCE_KEYS}
    kind = source.get("optics", "realistic")
    if kind not in ("realistic", "ideal"):
        raise ValueError(f"{url!r}: optics must be realistic or ideal, got {kind!r}")
    cfg = OpticsConfig() if kind == "realistic" else OpticsConfig.ideal()
    try:
        if "noise_pm" in source:
            cfg = cfg.replace(noise=float(source["noise_pm"]) * 1e-3)
        if "seed" in source:
            cfg = cfg.replace(seed=int(source["seed"]))
        rate = float(source.get("rate", 100.0))
    except ValueError as exc:
        raise ValueError(f"{url!r}: {exc}") from None
    setup = SETUPS[name](**parse_params(SETUPS[name], params))
    flag = {"1", "true", "yes", "on"}
    sim = SimInterrogator(setup, fiber, optics=cfg, rate=rate, realtime=source.get("realtime", "0").lower() in flag,
                          truth=source.get("truth", "1").lower() in flag)
    sim.url = url
    return sim
