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
from twin.io.options import Option, parse_options
from twin.io.source import parse_url

__all__ = ["open_sim"]

#: the interrogator's options of ``sim://`` (:mod:`twin.io.options`); every other key is the setup's
SIM_OPTIONS = {
    "rate": Option("float", default=100.0, low=0.0, low_open=True, high=10_000.0),
    "realtime": Option("bool", default=False),
    "optics": Option("str", default="realistic", choices=("realistic", "ideal")),
    "noise_pm": Option("float", low=0.0),
    "seed": Option("int", low=0),
    "truth": Option("bool", default=True),
}


def open_sim(url: str, **options) -> SimInterrogator:
    """Build the setup named in ``url`` and return its SimInterrogator (``options`` override the query)."""
    _, name, params = parse_url(url)
    fiber = options.pop("fiber", None)
    params.update({k: str(v) for k, v in options.items()})
    name = name.strip("/")
    known = registry.entries("twin.sim_setups")
    if name not in known:
        raise ValueError(f"{url!r}: unknown simulated setup {name!r}; known: {', '.join(known)}")
    opts = parse_options(url, params, SIM_OPTIONS, extra=True)
    cfg = OpticsConfig() if opts["optics"] == "realistic" else OpticsConfig.ideal()
    if "noise_pm" in opts:
        cfg = cfg.replace(noise=opts["noise_pm"] * 1e-3)
    if "seed" in opts:
        cfg = cfg.replace(seed=opts["seed"])
    cls = registry.load("twin.sim_setups", name)
    setup = cls(**parse_params(cls, opts["_extra"]))
    sim = SimInterrogator(setup, fiber, optics=cfg, rate=opts["rate"], realtime=opts["realtime"], truth=opts["truth"])
    sim.url = url
    return sim
