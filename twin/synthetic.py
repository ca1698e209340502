"""``synthetic://`` — frames from the reconstruction's own forward model, no physics engine needed (a source
above :mod:`twin.io`: it runs the forward model, :func:`twin.strain.forward`).

The fibre bends as a circular arc whose curvature and bending plane move in time: at sample ``i`` (time
t = i / rate) the curvature vector at every grating is κ(t)·(cos φ(t), sin φ(t)) with

    κ(t) = kappa + kappa_amp · sin(2π t / period),        φ(t) = phi + 2π · spin · t,

the wavelengths are :func:`twin.strain.forward` of it (optionally with white noise, quantisation and randomly
dropped peaks), and the truth is exact: a constant curvature vector without twist is an arc in the plane of the
tangent and (cos φ, sin φ, 0), so positions and material frames are closed-form (a rotation about the fixed
binormal). Frames are a pure function of the sample index and ``seed``, never of the wall clock, so a paced
and an unpaced source deliver identical frames.

URL: ``synthetic://?key=value&…`` with keys (defaults in brackets)

=============  ==========================================================================================
rate           samples per second, Hz [1000]
pace           ``realtime`` (deliver each frame at its time) or ``max`` (as fast as asked) [realtime]
cores          3–7: central core + the first ``cores − 1`` outer cores of a hexagonal 7-core MCF (4 = the
               paper's fibre, 7 = all cores) [4]
gratings       gratings per core, every 10 mm from the base [18]
kappa          mean curvature, 1/m [20]
kappa_amp      curvature swing, 1/m [10]
period         period of the curvature swing, s [2]
phi            bending-plane angle at t = 0, rad [0]
spin           turns of the bending plane per second, Hz [0.25]
noise          white wavelength noise (1σ), nm [0]
quantise       wavelength resolution, nm (0: none) [1e-4, the 0.1 pm of ILLumiSense and FiSpec]
drop           probability that a peak is missing (NaN + MISSING) [0]
seed           random seed of noise and drops [0]
frames         stop after this many frames (SourceClosed) [unbounded]
duration       stop after this many seconds of samples [unbounded]
truth          attach :class:`~twin.frames.Truth` to every frame (1/0) [1]
=============  ==========================================================================================
"""

from __future__ import annotations

import time
from urllib.parse import urlencode

import numpy as np

from twin import strain
from twin.curve import step_grid
from twin.fiber import FiberModel
from twin.frames import Frame, PeakStatus, Truth
from twin.io.options import Option, parse_options
from twin.io.source import MAX_BATCH, Source, SourceClosed, parse_url

__all__ = ["SyntheticSource", "arc_truth", "multicore_fiber", "open_synthetic"]

_MISSING = np.uint8(PeakStatus.MISSING)
_BLOCK = 64  # frames generated per vectorised call


def multicore_fiber(cores: int = 7, gratings: int = 18, spacing: float = 0.01, radius: float = 37.5e-6) -> FiberModel:
    """A hexagonal 7-core MCF read on its central core and ``cores − 1`` adjacent outer cores.

    Parameters
    ----------
    cores : int
        3 to 7. Core 0 is the central core; outer core j sits at θ = (j − 1)·π/3. ``cores=4`` is the layout of
        :meth:`FiberModel.paper` (same angles, radius, S_ε and wavelengths when ``gratings`` is 18).
    gratings : int
        Gratings per core, at ``spacing``·n from the base, with λ0 = 1510 + 5n nm (spread evenly over
        1510–1595 nm when there are more than 18).
    spacing : float
        Grating pitch, m.
    radius : float
        Outer-core distance from the axis, m.
    """
    if not 3 <= int(cores) <= 7:
        raise ValueError(f"cores: expected 3 to 7 (central core + outer cores of a 7-core MCF), got {cores}")
    if not 3 <= int(gratings) <= 10_000:  # bounded before anything is sized by it (10^19 overflowed numpy)
        raise ValueError(f"gratings: expected 3 to 10000, got {gratings}")
    cores, gratings = int(cores), int(gratings)
    pitch_nm = min(5.0, 85.0 / (gratings - 1))
    lam = np.repeat((1510.0 + pitch_nm * np.arange(gratings))[:, None], cores, axis=1)
    return FiberModel(
        core_angles=[0.0] + [j * np.pi / 3 for j in range(cores - 1)],
        core_radii=[0.0] + [radius] * (cores - 1),
        grating_s=spacing * np.arange(gratings),
        lambda0=lam,
        central_core=0,
        strain_sensitivity=0.777,
        temperature_sensitivity=6.6e-6,
        name=f"hexagonal 7-core MCF read on {cores} cores × {gratings} gratings",
    )


def arc_truth(kappa: np.ndarray, phi: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions and material frames of twist-free arcs with constant curvature vector κ(cos φ, sin φ).

    Parameters
    ----------
    kappa, phi : ndarray, shape (n,)
        Curvature, 1/m, and bending-plane angle, rad, of each arc.
    s : ndarray, shape (m,)
        Arc lengths, m.

    Returns
    -------
    positions : ndarray, shape (n, m, 3)
        m; base at the origin, tangent +z, d1 = +x (the reconstruction's base frame).
    frames : ndarray, shape (n, m, 3, 3)
        Material frames [d1 d2 d3] as columns: the rotation by κs about the binormal (−sin φ, cos φ, 0).
    """
    kappa = np.asarray(kappa, dtype=np.float64)[:, None]
    c, sn = np.cos(phi)[:, None], np.sin(phi)[:, None]
    a = kappa * s[None, :]  # bending angle along the arc
    ca, sa = np.cos(a), np.sin(a)
    # (1 − cos κs)/κ and sin(κs)/κ without dividing by a vanishing κ
    small = np.abs(kappa) < 1e-9
    k_safe = np.where(small, 1.0, kappa)
    lateral = np.where(small, 0.5 * kappa * s**2, (1.0 - ca) / k_safe)
    axial = np.where(small, s, sa / k_safe)
    pos = np.stack([lateral * c, lateral * sn, axial], axis=-1)
    # Rodrigues about b = (−sin φ, cos φ, 0): R = I + sin a [b]× + (1 − cos a) [b]×²
    bx, by = -sn[..., None, None], c[..., None, None]
    zero = np.zeros_like(bx)
    k_mat = np.concatenate(
        [
            np.concatenate([zero, zero, by], axis=-1),
            np.concatenate([zero, zero, -bx], axis=-1),
            np.concatenate([-by, bx, zero], axis=-1),
        ],
        axis=-2,
    )  # (n, 1, 3, 3)
    k2 = k_mat @ k_mat
    frames = np.eye(3) + sa[..., None, None] * k_mat + (1.0 - ca)[..., None, None] * k2
    return pos, frames


class SyntheticSource(Source):
    """Frames from :func:`twin.strain.forward` on an analytic moving arc (module docstring for the motion).

    Parameters
    ----------
    rate : float
        Hz.
    pace : bool
        Deliver each frame no earlier than its sample time (True) or as fast as asked.
    fiber : FiberModel, optional
        Sensor to simulate; default :func:`multicore_fiber` (``cores``, ``gratings``).
    cores, gratings : int
        Used when ``fiber`` is None.
    kappa, kappa_amp, period, phi, spin, noise, quantise, drop, seed, frames, duration, truth
        See the module docstring (SI units: 1/m, s, rad, Hz, nm).
    url : str
        What was opened (for messages).
    """

    def __init__(
        self,
        *,
        rate: float = 1000.0,
        pace: bool = True,
        fiber: FiberModel | None = None,
        cores: int = 4,
        gratings: int = 18,
        kappa: float = 20.0,
        kappa_amp: float = 10.0,
        period: float = 2.0,
        phi: float = 0.0,
        spin: float = 0.25,
        noise: float = 0.0,
        quantise: float = 1e-4,
        drop: float = 0.0,
        seed: int = 0,
        frames: int | None = None,
        duration: float | None = None,
        truth: bool = True,
        url: str = "",
    ):
        if not (np.isfinite(rate) and rate > 0):
            raise ValueError(f"synthetic: rate must be a positive frequency in Hz, got {rate}")
        if not 0 <= drop < 1:
            raise ValueError(f"synthetic: drop must be a probability in [0, 1), got {drop}")
        if noise < 0 or quantise < 0 or period <= 0:
            raise ValueError("synthetic: noise and quantise must be >= 0 nm and period > 0 s")
        self.fiber = fiber if fiber is not None else multicore_fiber(cores, gratings)
        self.rate = float(rate)
        self.url = url or "synthetic://?" + urlencode({"rate": rate, "cores": self.fiber.n_cores})
        self.pace = bool(pace)
        self.kappa, self.kappa_amp, self.period = float(kappa), float(kappa_amp), float(period)
        self.phi, self.spin = float(phi), float(spin)
        self.noise, self.quantise, self.drop = float(noise), float(quantise), float(drop)
        self.seed = int(seed)
        limit = None if frames is None else int(frames)
        if duration is not None:
            if not (np.isfinite(float(duration)) and float(duration) >= 0):
                raise ValueError(f"synthetic: duration must be a number of seconds >= 0, got {duration}")
            by_time = float(duration) * self.rate
            if by_time < 2.0**62:  # beyond: longer than any run (and round() of inf would raise)
                limit = round(by_time) if limit is None else min(limit, round(by_time))
        self.limit = limit
        self.with_truth = bool(truth)
        self.truth_s = step_grid(0.0, self.fiber.sensed_length, 1e-3)[0]
        self._index = 0  # next frame to deliver
        self._block: Frame | None = None
        self._block_start = 0
        self._t0_wall = time.time()
        self._t0 = time.monotonic()
        self._closed = False

    # ------------------------------------------------------------------ the motion
    def state(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Curvature κ (1/m) and bending-plane angle φ (rad) at sample times ``t`` (s)."""
        t = np.asarray(t, dtype=np.float64)
        kappa = self.kappa + self.kappa_amp * np.sin(2 * np.pi * t / self.period)
        return kappa, self.phi + 2 * np.pi * self.spin * t

    def _generate(self, i0: int, n: int) -> Frame:
        """Frames i0 … i0 + n − 1 as one batch (with their batched truth)."""
        idx = np.arange(i0, i0 + n)
        t = idx / self.rate
        kappa, phi = self.state(t)
        g = self.fiber.n_gratings
        k = np.stack([kappa * np.cos(phi), kappa * np.sin(phi)], axis=-1)  # (n, 2)
        k = np.broadcast_to(k[:, None, :], (n, g, 2))
        w = strain.forward(self.fiber, k)
        # one generator per block, seeded by (seed, block start): frames do not depend on how they are read
        rng = np.random.default_rng([self.seed, i0])
        if self.noise:
            w = w + self.noise * rng.standard_normal(w.shape)
        if self.quantise:
            w = np.round(w / self.quantise) * self.quantise
        status = np.zeros(w.shape, np.uint8)
        if self.drop:
            lost = rng.random(w.shape) < self.drop
            w[lost] = np.nan
            status[lost] = _MISSING
        powers = np.where(np.isnan(w), np.nan, -20.0)
        truth = None
        if self.with_truth:
            pos, frames = arc_truth(kappa, phi, self.truth_s)
            zeros = np.zeros((n, g))
            truth = Truth(s=self.truth_s, positions=pos, frames=frames, curvature=np.array(k), twist=zeros,
                          temperature=zeros)
        return Frame(wavelengths=w, timestamp=self._t0_wall + t, sequence=idx, powers=powers, status=status,
                     truth=truth)

    # ------------------------------------------------------------------ Source
    def _frames(self, i: int, n: int) -> Frame:
        """Frames i … i + n − 1, generated in the aligned blocks of ``_BLOCK`` frames that hold them (so that the
        random numbers, seeded per block, do not depend on how the frames are read)."""
        parts = []
        while n > 0:
            if not self._block_start <= i < self._block_start + _BLOCK or self._block is None:
                start = i - i % _BLOCK
                self._block = self._generate(start, _BLOCK)  # always whole blocks: same draws whatever the limit
                self._block_start = start
            j = i - self._block_start
            take = min(n, _BLOCK - j)
            parts.append(self._block[j : j + take])
            i, n = i + take, n - take
        return parts[0] if len(parts) == 1 else Frame.stack(parts)

    def read_batch(self, max_frames: int = MAX_BATCH, timeout: float | None = None) -> Frame | None:
        """Every frame that is due now (up to ``max_frames``), waiting up to ``timeout`` s for the first."""
        if self._closed:
            raise SourceClosed(f"{self.url}: closed")
        i = self._index
        if self.limit is not None and i >= self.limit:
            raise SourceClosed(f"{self.url}: all {self.limit} frames delivered")
        if self.pace:
            wait = self._t0 + i / self.rate - time.monotonic()
            if wait > 0:
                if timeout is not None and timeout < wait:
                    time.sleep(max(0.0, timeout))
                    return None
                time.sleep(wait)
        due = (1 << 62) if not self.pace else max(i + 1, int((time.monotonic() - self._t0) * self.rate) + 1)
        if self.limit is not None:
            due = min(due, self.limit)
        n = max(1, min(max_frames, due - i))
        self._index = i + n
        return self._frames(i, n)

    def close(self) -> None:
        self._closed = True
        self._block = None

    def stats(self) -> dict:
        return {"frames": self._index, "rate_hz": self.rate}


#: the options of ``synthetic://`` (module docstring; :mod:`twin.io.options`)
SYNTHETIC_OPTIONS = {
    "rate": Option("float", low=0.0, low_open=True),
    "pace": Option("str", choices=("realtime", "max")),
    "cores": Option("int", low=3, high=7),
    "gratings": Option("int", low=3, high=10_000),
    "kappa": Option("float"),
    "kappa_amp": Option("float"),
    "period": Option("float", low=0.0, low_open=True),
    "phi": Option("float"),
    "spin": Option("float"),
    "noise": Option("float", low=0.0),
    "quantise": Option("float", low=0.0),
    "drop": Option("float", low=0.0, high=0.999999),
    "seed": Option("int", low=0),
    "frames": Option("int", low=1),
    "duration": Option("float", low=0.0, low_open=True),
    "truth": Option("bool"),
}


def open_synthetic(url: str, **options) -> SyntheticSource:
    """Open ``synthetic://?key=value…`` (keys in the module docstring); ``options`` override the query.

    A ``fiber`` option (FiberModel) replaces ``cores``/``gratings``.
    """
    _, rest, query = parse_url(url)
    if rest.strip("/"):
        raise ValueError(f"{url!r}: synthetic URLs take only options: synthetic://?rate=1000&cores=7")
    kw = parse_options(url, query, SYNTHETIC_OPTIONS)
    if "pace" in kw:
        kw["pace"] = kw["pace"] == "realtime"
    kw.update(options)
    return SyntheticSource(url=url, **kw)
