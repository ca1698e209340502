"""What the three sheath experiments (rotation, repeatability, sheath-motion) share: running a sheath setup into a
:class:`~scenarios.series.Series` with a few extra per-frame records, the reconstructors, an EM-sensor-like tip
reading, the viewer hook, command-line options and report pieces.

The EM sensor. The paper measured the tip with an electromagnetic tracker (an NDI Aurora 6-DOF sensor at the tip).
It is modelled as the true position of the end of the sensed region plus white Gaussian noise of ``em_noise`` per
axis (default 0.2 mm, the order of an Aurora's static jitter in a good field; its absolute accuracy, ≈ 0.5 mm RMS,
is a fixed distortion of the field that the registration absorbs). A static reading is the mean over the frames of
a measurement window, as an experimenter averages a held position.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from scenarios.series import Series, collect
from sim_interrogator.optics import OpticsConfig
from sim_interrogator.sheath import SheathSetup
from sim_interrogator.sim import SimInterrogator
from twin import Calibration, FiberModel, Reconstructor, Shape, jsonout
from twin.frames import Truth

MODES = ("default", "paper")


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
    """A SimInterrogator stand-in for :func:`scenarios.series.collect` that records the hub and the twist."""

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


def optics_config(kind: str, seed: int) -> OpticsConfig:
    if kind not in ("realistic", "ideal"):
        raise ValueError(f"optics must be realistic or ideal; got {kind!r}")
    return OpticsConfig(seed=seed) if kind == "realistic" else OpticsConfig.ideal()


def reconstructors(fiber: FiberModel, cal: Calibration | None) -> dict[str, Reconstructor]:
    """The default pipeline and the paper's, with the same calibration."""
    return {"default": Reconstructor(fiber, cal), "paper": Reconstructor.paper(fiber, cal)}


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


def em_readings(tip: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    """EM-sensor-like tip readings: ``tip`` (n, 3) m plus white Gaussian noise of ``sigma`` m per axis."""
    rng = np.random.default_rng(seed + 7919)
    return tip + sigma * rng.standard_normal(tip.shape)


def windows(t: np.ndarray, ends: np.ndarray, length: float) -> list[np.ndarray]:
    """Indices of the frames in (end − length, end] for each end time (at least the frame nearest the end)."""
    out = []
    for e in ends:
        idx = np.flatnonzero((t > e - length - 1e-9) & (t <= e + 1e-9))
        out.append(idx if idx.size else np.array([int(np.argmin(np.abs(t - e)))]))
    return out


def place(shape: Shape, positions: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Reconstructed points (n, p, 3) placed in the world with base poses (n, 3) and frames (n, 3, 3)."""
    return np.einsum("nij,npj->npi", frames, shape.positions) + positions[:, None, :]


def show_frames(viewer, shapes: Shape, series: Series, count: int = 40, pause: float = 0.1) -> None:
    """Replay about ``count`` evenly spaced frames in a viewer (:class:`twin.viewer.Viewer` or anything with its
    ``show(shape, truth, *, base_pose, label, force)``), ``pause`` s apart, each placed with the fibre base's
    tracked pose; nothing without a viewer. Frames with no usable grating (NaN shape) are skipped."""
    if viewer is None:
        return
    for i in np.unique(np.linspace(0, len(series) - 1, count).round().astype(int)):
        i = int(i)
        if not np.all(np.isfinite(shapes.positions[i])):
            continue
        truth = Truth(s=series.truth_s, positions=series.truth_positions[i], frames=None,
                      curvature=series.truth_curvature[i], fixture=series.fixture)
        viewer.show(shapes[i], truth, base_pose=(series.base_frames[i], series.base_positions[i]),
                    label=f"t = {series.t[i]:.1f} s", force=True)
        time.sleep(pause)


# ------------------------------------------------------------------------------------------------ command line
def add_common_arguments(parser: argparse.ArgumentParser, *, rate: float, friction: float) -> None:
    parser.add_argument("--optics", choices=("realistic", "ideal"), default="realistic",
                        help="synthetic interrogator effects (default realistic)")
    parser.add_argument("--calibration", default="true",
                        help="true (the twin's true parameters), nominal, or a calibration TOML (default true)")
    parser.add_argument("--friction", type=float, default=friction,
                        help=f"Coulomb friction catheter–sheath (default {friction:g})")
    parser.add_argument("--segments", type=int, default=100, help="rod segments (default 100)")
    parser.add_argument("--rate", type=float, default=rate, help=f"interrogator frame rate, Hz (default {rate:g})")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (interrogator and EM sensor)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--report", metavar="DIR", help="write DIR/report.md with PNG plots")


def stderr_progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run_cli(name: str, args, module) -> int:
    """``twin run NAME`` for a sheath experiment ``module`` (its params_from_args, run_experiment, write_report
    and text_report): run it with progress on stderr, write ``--report``, print ``--json`` or the text report.
    A catheter that does not settle, or a simulation that goes unstable, is one line on stderr (which setup,
    how far it still moved) and exit status 1."""
    from models.fixtures import SettleError

    params = module.params_from_args(args)
    try:
        result = module.run_experiment(params, progress=stderr_progress, viewer=getattr(args, "viewer", None))
    except SettleError as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 1
    if args.report:
        stderr_progress(f"report: {module.write_report(result, args.report)}")
    print(jsonout.dumps(result.to_dict(), indent=2) if args.json else module.text_report(result))
    return 0


def paper_table(rows: list[tuple[str, str, str, str]]) -> tuple[list[str], list[tuple[str, str, str, str]]]:
    """Headers and rows of the 'paper vs twin' table."""
    return ["quantity", "paper", "twin: default pipeline", "twin: paper's pipeline"], rows


def mm(x) -> str:
    return f"{float(x) * 1e3:.2f} mm"
