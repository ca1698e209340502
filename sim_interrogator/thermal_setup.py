"""``sim://bath``: a shaped catheter in a water bath that cools from 60 °C to 30 °C (the paper's temperature test).

The catheter is held in one library shape — by connect constraints (exact, the default) or a rigid 3 mm tube —
exactly as :class:`~sim_interrogator.setups.StaticShape` holds it, while the bath temperature changes over time.
The temperature reaches the optics through :meth:`Bath.conditions`, which the
:class:`~sim_interrogator.sim.SimInterrogator` turns into a Bragg shift S_T,i·ΔT per core
(:mod:`sim_interrogator.optics`). The central core sees the same ΔT as the outer ones, so a reconstruction that
removes the common mode cancels it, except for the per-core S_T mismatch (``OpticsConfig.thermal_mismatch``).

Temperatures
------------
λ0 is referenced to room temperature, so the fibre sees ΔT(s, t) = T(s, t) − T_ref (K), with
``reference_celsius`` = T_ref (default 22 °C, a lab's room). The bath follows

* ``profile="exponential"`` (default): Newton cooling toward the room, T(t) = T_room + (T_start − T_room)
  exp(−t/τ), with τ = duration / ln((T_start − T_room)/(T_end − T_room)) so that it reaches T_end at the end of
  the run (needs T_end > T_room: Newton cooling never goes below the room); at the defaults τ = 38.5 s for
  60 s. A real bath of a few litres takes tens of minutes; the simulated time is compressed because the
  physics is static and only the interrogator's drift (∝ √t) depends on the time scale;
* ``profile="linear"``: T(t) = T_start + (T_end − T_start) t / duration.

After ``duration`` the temperature holds at T_end. An optional spatial gradient along the fibre,
``gradient`` K/m, adds g·(s − L/2) (constant in time; e.g. a bath warmer at depth). ``conditions`` returns ΔT at
each grating's centre (a linear gradient averages to its centre value over a grating).

What is modelled and what is not
--------------------------------
* The temperature affects **only the optics** here. The physics is static (the fixture holds the shape), so
  the rod state is the same at every frame up to solver round-off (< 1e-4 µm and < 3e-5 1/m over 20 s at
  the default 5 ms step, measured).
* **Thermal expansion of the catheter is neglected** (no axial strain from ΔT, no change of shape or
  stiffness with temperature: a polymer shaft's modulus falls several % per 10 K, and its length grows by
  α ≈ 1e-4/K; held by the fixture, neither changes the centreline much). A fibre free in its lumen does not
  feel the shaft's expansion; a bonded one would see a common-mode strain α_cath·ΔT (removed by the central
  core like the thermal shift itself, apart from the same small mismatch).
* Water (buoyancy, convection) is not modelled: gravity keeps the CatheterSpec's scaled value.

Physics step. The default 5 ms for connect constraints keeps the settled curvature as accurate as 2 ms
(0.154 vs 0.153 1/m from the library helix) at 2.5× the speed (≈ 3500 steps/s → 60 s simulated in ≈ 3.5 s
wall); 10 ms doubled that deviation and 20 ms made it 1.2 1/m (soft constraints: MuJoCo raises their time
constant to 2·dt). Switching to a coarse step *after* settling at 2 ms is worse (the constraints re-settle:
26 µm and 6 1/m at 10 ms). Tubes and grooves keep 2 ms (docs/simulation-notes.md pitfall 5).
"""

from __future__ import annotations

import math

import numpy as np

from sim_interrogator.setups import StaticShape

__all__ = ["Bath"]

PROFILES = ("exponential", "linear")


class Bath(StaticShape):
    """A catheter held in a library shape while the bath around it cools.

    Parameters
    ----------
    shape : str
        A :mod:`twin.shapes` name.
    fixture : {"connect", "tube", "groove"}
        How the shape is held (see :class:`~sim_interrogator.setups.StaticShape`).
    start_celsius, end_celsius : float
        Bath temperature at the start and at ``duration``, °C.
    room_celsius : float
        Ambient temperature the bath cools toward (exponential profile), °C.
    reference_celsius : float
        Temperature at which λ0 was recorded (room temperature), °C: ΔT = T − T_ref.
    profile : {"exponential", "linear"}
    duration : float
        Simulated seconds of the run (the frames' time span), s.
    gradient : float
        Temperature gradient along the fibre, K/m, added as g·(s − L/2).
    segments : int
        Rod segments.
    timestep : float
        Physics step, s; 0 picks 5 ms for connect constraints and 2 ms for a tube or groove.
    settle_time : float
        Longest time to let the shape settle before the run, s.
    """

    name = "bath"

    def __init__(self, shape: str = "helix", fixture: str = "connect", start_celsius: float = 60.0,
                 end_celsius: float = 30.0, room_celsius: float = 22.0, reference_celsius: float = 22.0,
                 profile: str = "exponential", duration: float = 60.0, gradient: float = 0.0,
                 segments: int = 100, timestep: float = 0.0, settle_time: float = 10.0):
        if profile not in PROFILES:
            raise ValueError(f"sim://bath: profile must be one of {', '.join(PROFILES)}; got {profile!r}")
        values = dict(start_celsius=start_celsius, end_celsius=end_celsius, room_celsius=room_celsius,
                      reference_celsius=reference_celsius, duration=duration, gradient=gradient,
                      timestep=timestep)
        for key, v in values.items():
            if not (isinstance(v, int | float) and math.isfinite(v)):
                raise ValueError(f"sim://bath: {key} must be a finite number, got {v!r}")
        if duration <= 0:
            raise ValueError(f"sim://bath: duration must be > 0 s, got {duration}")
        if timestep < 0:
            raise ValueError(f"sim://bath: timestep must be >= 0 s (0: automatic), got {timestep}")
        if profile == "exponential":
            if not start_celsius > end_celsius > room_celsius:
                raise ValueError(
                    "sim://bath: an exponential (Newton) cooling curve needs start > end > room temperature, got "
                    f"start {start_celsius} °C, end {end_celsius} °C, room {room_celsius} °C; use profile=linear "
                    "for other ramps"
                )
        if timestep == 0:
            timestep = 5e-3 if fixture == "connect" else 2e-3
        super().__init__(shape, fixture, segments=segments, timestep=timestep, settle_time=settle_time)
        self.start_celsius = float(start_celsius)
        self.end_celsius = float(end_celsius)
        self.room_celsius = float(room_celsius)
        self.reference_celsius = float(reference_celsius)
        self.profile = profile
        self.duration = float(duration)
        self.gradient = float(gradient)
        if profile == "exponential":
            self.tau = self.duration / math.log((start_celsius - room_celsius) / (end_celsius - room_celsius))
        else:
            self.tau = math.inf

    def bath_celsius(self, t) -> np.ndarray:
        """Bath temperature at times ``t`` (s since the start, any shape), °C; held at the end value after
        ``duration`` and at the start value before 0."""
        tc = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration)
        if self.profile == "exponential":
            return self.room_celsius + (self.start_celsius - self.room_celsius) * np.exp(-tc / self.tau)
        return self.start_celsius + (self.end_celsius - self.start_celsius) * tc / self.duration

    def delta_t(self, t, s) -> np.ndarray:
        """ΔT = T(s, t) − T_ref in K at times ``t`` (shape (...)) and fibre arc lengths ``s`` (shape (n,), m):
        shape (..., n)."""
        s = np.asarray(s, dtype=np.float64)
        bath = self.bath_celsius(t)[..., None]
        return bath - self.reference_celsius + self.gradient * (s - 0.5 * self.spec.sensed_length)

    def conditions(self, t: float, grating_s: np.ndarray) -> tuple[np.ndarray, float]:
        """(ΔT at each grating in K, axial strain 0): the temperature affects only the optics."""
        return self.delta_t(t, grating_s), 0.0

    def describe(self) -> dict:
        return {**super().describe(), "setup": self.name, "start_celsius": self.start_celsius,
                "end_celsius": self.end_celsius, "room_celsius": self.room_celsius,
                "reference_celsius": self.reference_celsius, "profile": self.profile, "duration_s": self.duration,
                "cooling_time_constant_s": None if math.isinf(self.tau) else self.tau,
                "gradient_k_per_m": self.gradient}
