"""The studies ``twin study NAME`` knows, and their task functions (each takes a parameter dict, returns a row).

* ``integration`` — the fibre-integration guidelines (:mod:`scenarios.integration`): its design points × seeds,
  MuJoCo physics per task (about a minute each on one core);
* ``sensor-design`` — the sensor's design against its errors, without MuJoCo: the 12 library shapes' exact
  curvature through the simulated optics (:class:`sim_interrogator.optics.Optics`) and back through the default
  reconstruction, over wavelength noise, grating count and spacing, core-angle error and temperature; a fraction
  of a second per task;
* ``selftest`` — tiny tasks (one raises on purpose) to check a cluster and the runner.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from scenarios.studies.runner import Study

__all__ = ["STUDIES", "get", "integration_task", "selftest_task", "sensor_design_task"]


# ---------------------------------------------------------------------------------------------- sensor design
def sensor_design_task(p: dict) -> dict:
    """Errors of the default pipeline on the library shapes for one sensor design (lengths in mm).

    Parameters (``p``): ``noise_pm`` white wavelength noise (1σ); ``n_gratings`` and ``spacing_mm`` (the gratings
    from s = 0); ``core_angle_error_deg`` the true outer-core spacing's departure from nominal, left uncalibrated;
    ``temperature_k`` a uniform temperature change with 0.3 % per-core sensitivity mismatch; ``seed``.
    """
    from sim_interrogator.optics import Optics, OpticsConfig
    from twin import Calibration, FiberModel, Reconstructor, metrics, shapes

    paper = FiberModel.paper()
    n_g, spacing = int(p["n_gratings"]), float(p["spacing_mm"]) * 1e-3
    s = spacing * np.arange(n_g)
    lam = paper.lambda0[np.arange(n_g) % paper.n_gratings]
    fiber = paper.replace(grating_s=s, lambda0=lam, length=float(s[-1]))
    delta_theta = math.pi / 3 + math.radians(float(p["core_angle_error_deg"]))
    cfg = OpticsConfig.ideal(delta_theta=delta_theta, noise=float(p["noise_pm"]) * 1e-3,
                             temperature=float(p["temperature_k"]), thermal_mismatch=0.003,
                             fiber_seed=int(p["seed"]), seed=int(p["seed"]))
    optics = Optics(fiber, cfg)
    rec = Reconstructor(fiber, Calibration(lambda0=fiber.lambda0))  # λ0 known, Δθ error left in
    maxima, means, tips = [], [], []
    for curve in shapes.library():
        if curve.length < s[-1] - 1e-9:
            continue
        w, _ = optics.wavelengths(np.repeat(curve.curvature(s)[None], 3, axis=0), 0.0)
        shape = rec(w)
        truth_s, truth = curve.sample(2e-4)
        err = metrics.shape_error(shape.positions, truth, s=shape.s, truth_s=truth_s)
        maxima.append(float(np.max(err.max)))
        means.append(float(np.mean(err.mean)))
        tips.append(float(np.mean(err.tip)))
    return {"max_error_mm": max(maxima) * 1e3, "mean_error_mm": float(np.mean(means)) * 1e3,
            "tip_error_mm": float(np.mean(tips)) * 1e3, "shapes": len(maxima)}


def sensor_design_study(seeds: int = 3, quick: bool = False) -> Study:
    grid = {"noise_pm": (0.5, 1.0, 5.0), "n_gratings": (9, 18, 35), "core_angle_error_deg": (0.0, 1.0, 3.0),
            "temperature_k": (0.0, 20.0)}
    if quick:
        grid = {"noise_pm": (1.0, 5.0), "n_gratings": (18,), "core_angle_error_deg": (0.0, 2.0),
                "temperature_k": (0.0,)}
    tasks = []
    for noise, n_g, ang, temp in itertools.product(*grid.values()):
        spacing = 170.0 / (n_g - 1)  # the same 170 mm sensed length: more gratings, closer together
        for seed in range(seeds):
            tasks.append({"noise_pm": noise, "n_gratings": n_g, "spacing_mm": round(spacing, 4),
                          "core_angle_error_deg": ang, "temperature_k": temp, "seed": seed})
    return Study("sensor-design", "scenarios.studies.definitions:sensor_design_task", tuple(tasks),
                 group_by=("noise_pm", "n_gratings", "spacing_mm", "core_angle_error_deg", "temperature_k"),
                 metrics=("max_error_mm", "mean_error_mm", "tip_error_mm"),
                 description="The library shapes' exact curvature through the simulated optics and back through the "
                             "default reconstruction (λ0 calibrated, core-angle error left in): error per sensor "
                             "design over seeds of noise and of the as-built thermal mismatch.")


# ------------------------------------------------------------------------------------------------ integration
def integration_task(p: dict) -> dict:
    """One design point of :mod:`scenarios.integration` (``p``: its point plus ``seed``, ``shapes``, ``cycles``)."""
    from scenarios.integration import BASELINE, Params, run_point

    params = Params(shapes=tuple(p.get("shapes", Params.shapes)), cycles=int(p.get("cycles", Params.cycles)),
                    repeats=int(p.get("repeats", Params.repeats)), seed=int(p.get("seed", 0)))
    point = {k: p[k] for k in ("label", "clearance", "friction", "fixations", "dx_prox", "dx_dist", "offset",
                               "glued")} | {"lead_tension": float(p.get("lead_tension", BASELINE["lead_tension"]))}
    return run_point(point, params)


#: design points whose question is repeatability (the light study runs sheath cycles only for these)
REPEATABILITY_POINTS = ("glued", "clearance 0.1 mm", "0 fixation(s)", "1 fixation(s)",
                        "clearance 0.1 mm, lining μ 0.05", "dx_prox 0 mm", "dx_prox 5 mm", "dx_prox 25 mm")


def integration_study(seeds: int = 1, quick: bool = False, light: bool = False) -> Study:
    """The integration study; ``light``: two static shapes, and three sheath cycles only at
    :data:`REPEATABILITY_POINTS` (what a loaded 2-core machine finishes in half an hour)."""
    from scenarios.integration import DEFAULT_SHAPES, design_points

    points = design_points("quick" if quick else "guidelines")
    if quick:
        extra = {"shapes": ["arc"], "cycles": 0, "repeats": 1}
    elif light:
        extra = {"shapes": ["arc", "helix"], "repeats": 2}
    else:
        extra = {"shapes": list(DEFAULT_SHAPES)}
    tasks = []
    for pt in points:
        cyc = {}
        if light and pt["label"] not in REPEATABILITY_POINTS:
            cyc = {"cycles": 0}  # light: the sheath cycles only where repeatability is the question
        elif light:
            cyc = {"cycles": 3}
        tasks += [{**pt, **extra, **cyc, "seed": s} for s in range(seeds)]
    tasks = tuple(tasks)
    return Study("integration", "scenarios.studies.definitions:integration_task", tasks,
                 group_by=("label",), metrics=("max_error_mm", "mean_error_mm", "static_tip_error_mm", "repeat_std_mm",
                                             "repeat_max_mm", "true_repeat_std_mm", "cycle_tip_error_max_mm"),
                 description="The fibre-integration guidelines (docs/integration.md): one factor at a time about the "
                             "baseline, static shapes and sheath cycles per design point.")


# --------------------------------------------------------------------------------------------------- selftest
def selftest_task(p: dict) -> dict:
    """Square ``x`` after ``sleep`` seconds; raise if ``fail`` (checks that failures are reported)."""
    import time

    time.sleep(float(p.get("sleep", 0.0)))
    if p.get("fail"):
        raise RuntimeError(f"selftest task {p['x']} fails on purpose")
    return {"y": float(p["x"]) ** 2}


def selftest_study(seeds: int = 1, quick: bool = False, n: int = 8, sleep: float = 0.0, fail: tuple = (3,)) -> Study:
    tasks = tuple({"x": i, "sleep": sleep, "fail": i in fail, "seed": s} for i in range(n) for s in range(seeds))
    return Study("selftest", "scenarios.studies.definitions:selftest_task", tasks, group_by=("x",),
                 metrics=("y",), description="Tiny tasks; one raises on purpose.")


#: name → function(seeds, quick) → Study
STUDIES = {"integration": integration_study,
           "integration-light": lambda seeds=1, quick=False: integration_study(seeds, quick, light=True),
           "sensor-design": sensor_design_study, "selftest": selftest_study}


def get(name: str, seeds: int = 1, quick: bool = False) -> Study:
    if name not in STUDIES:
        raise KeyError(f"no study {name!r}; known: {', '.join(STUDIES)}")
    return STUDIES[name](seeds=seeds, quick=quick)
