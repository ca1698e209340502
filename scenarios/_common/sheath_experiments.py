"""What the three sheath experiments (rotation, repeatability, sheath-motion) share: running a sheath setup into a
:class:`~scenarios._common.series.Series` with a few extra per-frame records, the EM sensor's noise stream,
measurement windows, the parameters every sheath experiment has and report pieces. The command-line glue, the
calibration, the optics, the three pipelines, EM-sensor-like readings and the viewer replay are every scenario's
(:mod:`scenarios._common`), handed on from here as ``common.NAME``.

The EM sensor. The paper measured the tip with an electromagnetic tracker (an NDI Aurora 6-DOF sensor at the tip).
It is modelled as the true position of the end of the sensed region plus white Gaussian noise of ``em_noise`` per
axis (default 0.2 mm, the order of an Aurora's static jitter in a good field; its absolute accuracy, ≈ 0.5 mm RMS,
is a fixed distortion of the field that the registration absorbs). A static reading is the mean over the frames of
a measurement window, as an experimenter averages a held position.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

# MODES, reconstructors, the optics and calibration fields, em_readings and show_frames are every experiment's,
# reached from here as ``common.NAME`` by the sheath experiments
from scenarios._common.calibration import calibration_field
from scenarios._common.entry import option
from scenarios._common.optics_presets import optics_config, optics_field
from scenarios._common.pipelines import MODES, reconstructors
from scenarios._common.series import Series, collect, em_readings, show_frames
from sim_interrogator.sheath_setups import SheathSetup
from sim_interrogator.sim import SimInterrogator
from twin import FiberModel

__all__ = ["EM_STREAM", "MODES", "Run", "calibration_field", "em_readings", "optics_field", "paper_table",
           "reconstructors", "run_setup", "seed_field", "show_frames", "windows"]

#: Added to ``--seed`` for the EM sensor's noise stream (:func:`em_readings`), apart from the interrogator's.
EM_STREAM = 7919


def seed_field():
    return field(default=0, metadata=option("noise seed (interrogator and EM sensor)"))


@dataclass(frozen=True, eq=False)
class Run:
    """A sheath setup run into a series, with what :class:`Series` does not hold (leading axis: kept frames).

    Attributes
    ----------
    series : Series
    setup : SheathSetup
    sim : SimInterrogator
    hub : ndarray (n, 2)
        The hub's actual (insertion m, roll rad).
    twist : ndarray (n,)
        The catheter's mechanical twist integrated over the sensed region (∫ τ ds over the gratings), rad: what a
        3-core fibre glued in the catheter cannot see.
    bore : ndarray (n,)
        Largest distance of the sensed region (the part inside the sheath) from the sheath's centreline, m.
    wall_s : float
        Wall time of building, settling and running, s.
    """

    series: Series
    setup: SheathSetup
    sim: SimInterrogator
    hub: np.ndarray
    twist: np.ndarray
    bore: np.ndarray
    wall_s: float

    @property
    def clearance(self) -> float:
        """Radial play of the catheter in the sheath's bore, m."""
        return 0.5 * (self.setup.geometry.inner_diameter - self.setup.spec.outer_diameter)

    def check_bore(self, say: Callable[[str], None], label: str, allowance: float = 1e-3) -> None:
        """Warn through ``say`` when the sensed region left the bore by more than ``allowance`` beyond the
        clearance (the contacts gave way: the result then shows a catheter through the wall)."""
        worst = float(np.nanmax(self.bore)) if np.isfinite(self.bore).any() else 0.0
        if worst > self.clearance + allowance:
            i = int(np.nanargmax(self.bore))
            say(f"{label}: WARNING: the catheter left the sheath's bore ({worst * 1e3:.2f} mm off its centreline at "
                f"t = {self.series.t[i]:.2f} s against {self.clearance * 1e3:.3f} mm of clearance); the contacts gave "
                "way: try a smaller timestep (setup parameter timestep) or a lower friction")


class _Recording:
    """A SimInterrogator stand-in for :func:`scenarios._common.series.collect` that records the hub and the twist."""

    def __init__(self, sim: SimInterrogator, setup: SheathSetup):
        self.sim, self.setup = sim, setup
        self.rate = sim.rate
        self.hub: list[tuple[float, float]] = []
        self.twist: list[float] = []
        self.bore: list[float] = []
        d = np.diff(sim.fiber.grating_s)
        self._w = np.zeros(d.size + 1)  # trapezoid weights of ∫ τ ds over the gratings
        self._w[:-1] += 0.5 * d
        self._w[1:] += 0.5 * d

    def read(self):
        f = self.sim.read()
        self.hub.append(self.setup.hub_state(self.sim.data))
        self.twist.append(float(self._w @ f.truth.twist) if f.truth is not None else np.nan)
        off = self.setup.bore_offsets(f.truth.positions) if f.truth is not None else np.full(1, np.nan)
        self.bore.append(float(np.nanmax(off)) if np.isfinite(off).any() else np.nan)
        return f


def run_setup(setup: SheathSetup, *, optics: str, seed: int, rate: float, label: str,
              progress: Callable[[str], None] | None = None) -> Run:
    """Build and settle ``setup``, then read frames at ``rate`` over its whole duration (progress on the way)."""
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    say(f"{label}: building sim://{setup.name} and settling the catheter in the sheath …")

    def tick(t, moved):
        say(f"    settling: t = {t:.2f} s, still moving {moved * 1e6:.1f} µm")

    sim = SimInterrogator(setup, FiberModel.paper(), optics_config(optics, seed), rate=rate,
                          progress=tick if progress else None)
    n = int(setup.duration * rate + 1e-9) + 1
    say(f"{label}: settled in {setup.settle_result.time:.2f} s simulated; running {setup.duration:.1f} s at "
        f"{rate:g} Hz ({n} frames) …")
    rec = _Recording(sim, setup)
    last = [time.perf_counter()]

    def step(done, total):  # called every ~5 % of the frames; say something every 10 s of wall time at most
        now = time.perf_counter()
        if now - last[0] >= 10.0 or done == total:
            last[0] = now
            say(f"    {label}: frame {done}/{total} (t = {done / rate:.1f} s), {now - t0:.0f} s wall")

    series = collect(rec, n, progress=step if progress else None)
    run = Run(series, setup, sim, np.array(rec.hub), np.array(rec.twist), np.array(rec.bore),
              time.perf_counter() - t0)
    run.check_bore(say, label)
    return run


def windows(t: np.ndarray, ends: np.ndarray, length: float) -> list[np.ndarray]:
    """Indices of the frames in (end − length, end] for each end time (at least the frame nearest the end)."""
    out = []
    for e in ends:
        idx = np.flatnonzero((t > e - length - 1e-9) & (t <= e + 1e-9))
        out.append(idx if idx.size else np.array([int(np.argmin(np.abs(t - e)))]))
    return out


# ------------------------------------------------------------------------------------------------ reports
def paper_table(rows: list[tuple[str, ...]]) -> tuple[list[str], list[tuple[str, ...]]]:
    """Headers and rows of the 'paper vs twin' table."""
    return ["quantity", "paper (hardware)", "twin: default pipeline", "twin: paper's pipeline (guarded)",
            "twin: paper's pipeline, literal"], rows

