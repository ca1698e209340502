"""SimInterrogator: the physics twin as a source of interrogator frames with their ground truth.

It runs a :class:`~sim_interrogator.setups.Setup` in MuJoCo and, at the interrogator's rate, reads the rod's
state (:class:`models.rod_state.RodReader`), samples its curvature along each grating and turns it into peak
wavelengths through :class:`~sim_interrogator.optics.Optics`. Each :class:`twin.Frame` carries a
:class:`twin.Truth`: the rod's centreline and material frames, its curvature and twist at the gratings, the
temperature and the fixture's centreline.

Frames come at simulated times k / rate after the setup's start (their timestamps), each showing the physics
state at the step nearest that time (within half a physics step). With ``realtime`` the source waits for the
wall clock (as hardware does); otherwise it runs as fast as it can.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import mujoco
import numpy as np

from models.catheter import WARNINGS_NOTE, collect_warnings
from models.rod_state import RodReader, RodTruth
from sim_interrogator.frame_path import FramePath, grating_average
from sim_interrogator.optics import Optics, OpticsConfig
from sim_interrogator.setups import Setup
from twin import FiberModel, Frame
from twin.io.source import FrameByFrame, SourceClosed

__all__ = ["SimInterrogator"]


class SimInterrogator(FrameByFrame):
    """A simulated interrogator on a simulated catheter.

    Parameters
    ----------
    setup : Setup
        The scene and its actuation.
    fiber : FiberModel, optional
        The nominal fibre (what the reconstruction is told); default the paper's.
    optics : OpticsConfig or Optics, optional
        Effects and the simulated fibre's true parameters; default :class:`OpticsConfig` (realistic).
    rate : float
        Frames per simulated second, Hz (the paper: 100; up to 1 kHz).
    realtime : bool
        Pace frames to the wall clock.
    truth : bool
        Attach :class:`twin.Truth` to every frame (turn off to save time when no one reads it).
    progress : callable (time s, moved m), optional
        Called while the setup settles.
    """

    def __init__(self, setup: Setup, fiber: FiberModel | None = None, optics: OpticsConfig | Optics | None = None,
                 rate: float = 100.0, realtime: bool = False, truth: bool = True,
                 progress: Callable[[float, float], None] | None = None):
        if not (np.isfinite(rate) and 0 < rate <= 10_000):
            raise ValueError(f"rate must be in (0, 10000] Hz, got {rate}")
        self.setup = setup
        self.fiber = fiber or FiberModel.paper()
        self.optics = optics if isinstance(optics, Optics) else Optics(self.fiber, optics)
        self.rate = float(rate)
        self.realtime = realtime
        self.with_truth = truth
        self.url = f"sim://{setup.name}"
        # MuJoCo's start-up notes on the flex rod are collected and reported by stats(), not printed raw (nor
        # written to MUJOCO_LOG.TXT in the user's folder)
        self.warnings = collect_warnings()
        self.model, self.data = setup.build()
        setup.prepare(self.model, self.data, progress)
        self.reader = RodReader(self.model, setup.rod_name)
        self._t0 = self.data.time
        self._k = 0
        self._wall0: float | None = None
        self._closed = False
        self._fixture = setup.fixture_centreline() if truth else None
        # A setup with the fibre as its own body (models/lumen_fiber.py) names the fibre's rod: the optics read its
        # curvature (in the catheter's roll convention, setup.optics_roll()); the truth stays the catheter's.
        optics_rod = getattr(setup, "optics_rod_name", None) or setup.rod_name
        self.optics_reader = self.reader if optics_rod == setup.rod_name else RodReader(self.model, optics_rod)
        self._optics_roll = getattr(setup, "optics_roll", None)
        self._disturb = getattr(setup, "disturb_peaks", None)
        # Darboux vectors (κ1, κ2, τ) at the interior vertices → (k_x, k_y) = (κ2, −κ1) averaged over each
        # grating's length (models/rod_state.py), as one fixed matrix (n_g, n_interior); a fibre with straight
        # cores takes the compiled frame path (one numba call per frame, sim_interrogator/frame_path.py), a spun
        # one the general optics (its exact path lengths need the twist rate too). Both read the rod through a
        # view bound to self.data (models.rod_state.RodView: mjData's arrays taken once).
        self._optics_rod = self.optics_reader.bind(self.data)
        self._path = None if self.optics.true_fiber.spin_rate else FramePath(self._optics_rod, self.optics)
        self._grating_average = (grating_average(self.optics_reader, self.optics) if self._path is None
                                 else self._path.average)
        self._sign = np.array([1.0, -1.0])
        # the truth (one compiled call, models.rod_state.RodTruth) reuses the optics' rod read when both read the
        # same rod, else reads the catheter's itself
        self._truth_from_optics = self.optics_reader is self.reader
        self._truth_rod = self._optics_rod if self._truth_from_optics else self.reader.bind(self.data)
        self._truth = RodTruth(self._truth_rod, self.fiber.grating_s)
        self.physics_time = 0.0  # wall seconds in mj_step
        self.optics_time = 0.0  # wall seconds reading the rod and making wavelengths
        self.truth_time = 0.0  # wall seconds making the truth and the frame

    @property
    def time(self) -> float:
        """Simulated time since the setup's start, s."""
        return self.data.time - self._t0

    def _advance(self, t_target: float) -> None:
        model, data, setup = self.model, self.data, self.setup
        dt = model.opt.timestep
        n = round((t_target - self.time) / dt)
        if n <= 0:
            return
        t0 = time.perf_counter()
        if setup.actuated:
            for _ in range(n):
                setup.actuate(model, data, self.time)
                mujoco.mj_step(model, data)
        else:
            mujoco.mj_step(model, data, nstep=n)
        self.physics_time += time.perf_counter() - t0

    def next_frame(self, timeout: float | None = None) -> Frame | None:
        """The next frame (the live loop gathers them into batches: :class:`~twin.io.source.FrameByFrame`)."""
        if self._closed:
            raise SourceClosed(f"{self.url}: closed")
        t = self._k / self.rate
        if self.setup.duration is not None and t > self.setup.duration + 1e-12:
            raise SourceClosed(f"{self.url}: the setup ended after {self.setup.duration} s")
        if self.realtime:
            now = time.monotonic()
            if self._wall0 is None:
                self._wall0 = now - t
            wait = self._wall0 + t - now
            if timeout is not None and wait > timeout:
                time.sleep(max(timeout, 0.0))
                return None
            if wait > 0:
                time.sleep(wait)
        self._advance(t)
        return self._frame(t)

    def _frame(self, t: float) -> Frame:
        t0 = time.perf_counter()
        delta_t, axial = self.setup.conditions(t, self.fiber.grating_s)
        roll = 0.0 if self._optics_roll is None else self._optics_roll()  # rad
        path = self._path
        if path is not None:
            w, status = path(self.data, axial, delta_t, t, roll)
        else:
            w, status = self._general_optics(t, delta_t, axial, roll)
        if self._disturb is not None:
            self._disturb(t, w, status)
        t1 = time.perf_counter()
        self.optics_time += t1 - t0
        truth = None
        if self.with_truth:
            if path is not None:
                temp = path.temperature  # delta_t at the gratings (the truth copies it)
            else:
                temp = np.broadcast_to(np.asarray(delta_t, float), self.fiber.grating_s.shape)
            if not self._truth_from_optics:
                self._truth_rod.compute()
            truth = self._truth(temp, self._fixture)
        # the optics' arrays are new, float64 and uint8 of shape (n_gratings, n_cores); the timestamp a float
        frame = Frame._trusted(w, self.optics.timestamp(t), self._k, status=status, truth=truth)
        self._k += 1
        self.truth_time += time.perf_counter() - t1
        return frame

    def _general_optics(self, t: float, delta_t, axial, roll: float) -> tuple[np.ndarray, np.ndarray]:
        """The optics through :meth:`Optics.wavelengths` (a spun fibre: it needs the twist rate too)."""
        self._optics_rod.compute()
        d = self._grating_average @ self._optics_rod.darboux  # (κ1, κ2, τ) averaged over each grating
        c, s = np.cos(roll), np.sin(roll)
        k1, k2 = d[:, 0].copy(), d[:, 1].copy()
        d[:, 0], d[:, 1] = c * k1 + s * k2, c * k2 - s * k1  # (κ1, κ2) in the frame rolled by r about d3
        k = d[:, 1::-1] * self._sign  # (k_x, k_y) = (κ2, −κ1)
        return self.optics.wavelengths(k, axial, delta_t, t=t, twist_rate=d[:, 2])

    @property
    def poses(self) -> tuple[str, ...]:
        """Poses the simulated catheter can be put in on request (see :meth:`set_pose`)."""
        return self.setup.poses

    def set_pose(self, pose: str, progress: Callable[[float, float], None] | None = None) -> None:
        """Put the simulated catheter in a named pose (e.g. the calibration's ``straight`` and ``bend``) and
        let it settle; frames continue from the settled state."""
        self.setup.set_pose(self.model, self.data, pose, progress)
        self._t0 = self.data.time - self._k / self.rate
        self._fixture = self.setup.fixture_centreline() if self.with_truth else None

    def describe(self) -> dict:
        """The setup and the simulated fibre's true parameters (what calibration should find)."""
        return {"url": self.url, "rate_hz": self.rate, **self.setup.describe(), **self.optics.describe()}

    def stats(self) -> dict:
        out = {"frames": self._k, "sim_time_s": self.time, "physics_wall_s": self.physics_time,
               "optics_wall_s": self.optics_time, "truth_wall_s": self.truth_time, "warnings": len(self.warnings)}
        if self.warnings:  # what a command prints beside the count (twin live's summary)
            out["warnings_note"] = f"MuJoCo solver warnings, {WARNINGS_NOTE}; the first: {self.warnings[0]}"
        return out

    def close(self) -> None:
        self._closed = True
