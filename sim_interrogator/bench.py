"""The `sim` section of `twin bench`: physics speed and the cost of producing interrogator frames.

Setup: the default 8 Fr catheter (100 segments) held in the library helix by connect constraints, physics step
1 ms, realistic optics, frames with truth at 1 kHz.

* ``steps_per_s``: physics steps per wall second (``mj_step`` only) of the rod kept awake.
* ``realtime_factor``: simulated seconds per wall second while producing 1 kHz frames (physics, rod read,
  optics, truth) as the twin runs them: the settled rod asleep (MuJoCo's ``sleep``, docs/simulation.md §4).
* ``realtime_factor_awake``: the same with the rod kept awake (every step integrated, as before sleeping).
* ``optics_overhead``: fraction of that wall time spent in the optics (reading the rod state, curvature at
  the gratings, wavelengths with every effect); the truth attached to each frame is reported apart
  (``truth_us_per_frame``).
* ``optics_overhead_awake``: the same fraction of the ``realtime_factor_awake`` run (every frame reads a rod
  that moved: no read is kept as MuJoCo's sleep allows), with ``optics_us_per_frame_awake``.
* ``sheath_steps_per_s``: physics steps per wall second of the catheter in the default sheath
  (``sim://sheath-cycle``: 100 segments, 2 ms, ≈ 70 contacts), the frames at 100 Hz — where the contact solve
  bounds every sheath scenario and design study (docs/simulation.md §4).
* ``realtime_factor_50_segments``: ``realtime_factor`` with a 50-segment rod (what the integration study's sheath
  cycles use); docs/simulation.md §4 gives the accuracy this costs.
"""

from __future__ import annotations

import time

import mujoco

from models.fixtures import wake
from sim_interrogator.setups import StaticShape
from sim_interrogator.sim import SimInterrogator


def _frames(segments: int, duration: float, awake: bool = False) -> tuple[SimInterrogator, float, float]:
    """Frames with truth at 1 kHz for ``duration`` simulated seconds: (source, simulated s, wall s)."""
    sim = SimInterrogator(StaticShape("helix", "connect", segments=segments, timestep=1e-3), rate=1000.0)
    if awake:
        wake(sim.model)
    for _ in range(20):  # load the compiled kernels before timing
        sim.read()
    sim.physics_time = sim.optics_time = sim.truth_time = 0.0
    t_start = sim.time
    t0 = time.perf_counter()
    for _ in range(int(duration * sim.rate)):
        sim.read()
    return sim, sim.time - t_start, time.perf_counter() - t0


def bench_sim(quick: bool = False) -> dict:
    from twin import registry

    duration = 1.0 if quick else 4.0
    sim = SimInterrogator(StaticShape("helix", "connect", segments=100, timestep=1e-3), rate=1000.0)
    wake(sim.model)
    n = int(duration / sim.model.opt.timestep)
    t0 = time.perf_counter()
    mujoco.mj_step(sim.model, sim.data, nstep=n)
    steps_per_s = n / (time.perf_counter() - t0)

    sim, simulated, wall = _frames(100, duration)
    frames = int(duration * sim.rate)
    awake, awake_simulated, awake_wall = _frames(100, duration, awake=True)
    _, coarse_simulated, coarse_wall = _frames(50, duration)

    sheath = SimInterrogator(registry.load("twin.sim_setups", "sheath-cycle")(), rate=100.0, truth=False)
    n_frames = round((0.5 if quick else 2.0) * sheath.rate)
    t0 = time.perf_counter()
    for _ in range(n_frames):
        sheath.read()
    sheath_steps = sheath.time / sheath.model.opt.timestep / (time.perf_counter() - t0)
    return {
        "steps_per_s": round(steps_per_s),
        "realtime_factor": round(simulated / wall, 2),
        "optics_overhead": round(sim.optics_time / wall, 3),
        "frames_per_s": round(frames / wall),
        "optics_us_per_frame": round(sim.optics_time / frames * 1e6, 1),
        "truth_us_per_frame": round(sim.truth_time / frames * 1e6, 1),
        "segments": 100,
        "timestep_s": sim.model.opt.timestep,
        "frame_rate_hz": sim.rate,
        "realtime_factor_50_segments": round(coarse_simulated / coarse_wall, 2),
        "realtime_factor_awake": round(awake_simulated / awake_wall, 2),
        "optics_overhead_awake": round(awake.optics_time / awake_wall, 3),
        "optics_us_per_frame_awake": round(awake.optics_time / frames * 1e6, 1),
        "sheath_steps_per_s": round(sheath_steps),
    }
