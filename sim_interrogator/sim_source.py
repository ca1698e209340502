"""``sim://SETUP?key=value…``: open a :class:`~sim_interrogator.sim.SimInterrogator` by URL.

Query keys are the setup's own parameters (e.g. ``shape``, ``fixture``), plus these for the interrogator:
``rate`` (Hz, default 100), ``realtime`` (0/1, default 0), ``optics`` (``realistic`` or ``ideal``), ``noise_pm``,
``seed`` and ``truth`` (0/1). Example: ``sim://static?shape=helix&fixture=tube&rate=100``.
"""

from __future__ import annotations

from sim_interrogator.optics import OpticsConfig
from sim_interrogator.setups import parse_params
from sim_interrogator.sim import SimInterrogator
from twin import registry
from twin.io.source import parse_url

__all__ = ["open_sim"]

_SOURCE_KEYS = {"rate", "realtime", "optics", "noise_pm", "seed", "truth"}

def open_sim(url: str, **options) -> SimInterrogator:
    """Build the setup named in ``url`` and return its SimInterrogator (``options`` override the query)."""
    _, name, params = parse_url(url)
    fiber = options.pop("fiber", None)
    params.update({k: str(v) for k, v in options.items()})
    name = name.strip("/")
    known = registry.entries("twin.sim_setups")
    if name not in known:
        raise ValueError(f"{url!r}: unknown simulated setup {name!r}; known: {', '.join(known)}")
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
    cls = registry.load("twin.sim_setups", name)
    setup = cls(**parse_params(cls, params))
    flag = {"1", "true", "yes", "on"}
    sim = SimInterrogator(setup, fiber, optics=cfg, rate=rate, realtime=source.get("realtime", "0").lower() in flag,
                          truth=source.get("truth", "1").lower() in flag)
    sim.url = url
    return sim
