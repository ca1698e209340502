"""Simulated setups: a MuJoCo scene with the catheter and what drives it over time.

A :class:`Setup` is what :class:`~sim_interrogator.sim.SimInterrogator` runs: it builds the scene, brings it
to its starting state, and is asked to act on the model as simulated time passes (move a hub, change
constraint targets, apply tendon forces, change the temperature). Setups are registered by name as entry points
of the ``twin.sim_setups`` group in pyproject.toml (:mod:`twin.registry`), which is what ``sim://NAME?key=value…``
opens; a setup's :attr:`Setup.name` is its entry's name. The experiments in ``scenarios/`` run setups and
evaluate what comes out.
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from models.catheter import CatheterSpec, Pose
from models.fixtures import (
    ExtendedCurve,
    build_connect,
    build_groove,
    build_tube,
    rod_base_pose,
    settle,
    sleep_at_rest,
    wake,
)
from twin import shapes
from twin.io.options import Option, parse_options

__all__ = ["CalibrationPoses", "Setup", "StaticShape", "parse_params"]


class Setup:
    """Base class of simulated setups.

    Subclasses set :attr:`name`, declare their parameters as keyword arguments of ``__init__`` (with
    defaults, in SI units) and override :meth:`build`; :meth:`actuate` and :meth:`conditions` default to a
    static, isothermal setup.

    Attributes
    ----------
    name : str
        Registry name (``sim://NAME``).
    duration : float or None
        Simulated seconds the setup runs after :meth:`prepare`; None for a static setup that runs until
        closed.
    rod_name : str
        The catheter flexcomp's name.
    actuated : bool
        Whether :meth:`actuate` must be called before every physics step (False: steps run in blocks).
    """

    name = "setup"
    duration: float | None = None
    rod_name = "cath"
    actuated = False

    def build(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        raise NotImplementedError

    def prepare(self, model: mujoco.MjModel, data: mujoco.MjData,
                progress: Callable[[float, float], None] | None = None) -> None:
        """Bring the scene to its starting state (typically: let it settle)."""

    def actuate(self, model: mujoco.MjModel, data: mujoco.MjData, t: float) -> None:
        """Act on the scene at time ``t`` s since the start (called before each physics step if actuated)."""

    def conditions(self, t: float, grating_s: np.ndarray) -> tuple[float | np.ndarray, float | np.ndarray]:
        """(temperature change K, axial strain) at the gratings at time ``t``."""
        return 0.0, 0.0

    def fixture_centreline(self) -> np.ndarray | None:
        """The fixture's centreline in world coordinates, (k, 3) m, when there is one (for Truth.fixture)."""
        return None

    def describe(self) -> dict:
        """Parameters, JSON-ready."""
        return {"setup": self.name}

    #: named poses the setup can put the catheter in on request (:meth:`set_pose`)
    poses: tuple[str, ...] = ()

    def set_pose(self, model: mujoco.MjModel, data: mujoco.MjData, pose: str,
                 progress: Callable[[float, float], None] | None = None) -> None:
        """Put the catheter in a named pose and let it settle (what a person does by hand on hardware)."""
        raise ValueError(f"sim://{self.name} has no poses to set; known: {', '.join(self.poses) or 'none'}")


def parse_params(cls: type[Setup], params: dict[str, str]) -> dict:
    """Convert URL query strings to the types of ``cls``'s keyword defaults (:mod:`twin.io.options`: unknown
    keys, bad booleans and bad or non-finite numbers are one-line errors naming the setup and the key)."""
    import inspect

    sig = inspect.signature(cls.__init__)
    spec = {}
    for key, p in sig.parameters.items():
        if key == "self":
            continue
        d = p.default
        kind = "bool" if isinstance(d, bool) else "int" if isinstance(d, int) else \
            "float" if isinstance(d, float) else "str"
        spec[key] = Option(kind)
    return parse_options(f"sim://{cls.name}", params, spec)


class StaticShape(Setup):
    """The catheter held in one library shape (the paper's static experiment).

    Parameters
    ----------
    shape : str
        A :mod:`twin.shapes` name.
    fixture : {"connect", "tube", "groove"}
        Exact shaping by connect constraints, a 3 mm rigid tube, or a grooved plate (planar shapes).
    segments : int
        Rod segments over the whole catheter (base + sensed + tip).
    timestep : float
        Physics step, s.
    settle_time : float
        Longest time to let the shape settle, s (a clear error if it does not).
    """

    name = "static"

    def __init__(self, shape: str = "helix", fixture: str = "connect", segments: int = 100,
                 timestep: float = 2e-3, settle_time: float = 10.0):
        if fixture not in ("connect", "tube", "groove"):
            raise ValueError(f"fixture must be connect, tube or groove; got {fixture!r}")
        self.curve = shapes.get(shape)
        if fixture == "groove" and not self.curve.planar:
            raise ValueError(f"shape {shape!r} is not planar: a groove cannot hold it; use fixture=tube")
        self.fixture_kind = fixture
        self.spec = CatheterSpec(n_segments=int(segments), timestep=float(timestep))
        self.settle_time = float(settle_time)
        self.fixture = None

    def build(self):
        builder = {"connect": build_connect, "tube": build_tube, "groove": build_groove}[self.fixture_kind]
        model, data, self.fixture = builder(self.curve, self.spec)
        return model, data

    def prepare(self, model, data, progress=None):
        settle(model, data, max_time=self.settle_time, progress=progress)
        if self.fixture_kind == "connect":
            # held by constraints alone, the settled rod is at rest: MuJoCo stops integrating it (≈ 3× fewer CPU
            # per step); a rod on a tube's or groove's contacts still creeps and stays awake (docs/simulation.md §4)
            sleep_at_rest(model)

    def fixture_centreline(self):
        s = np.linspace(0.0, self.curve.length, 341)
        return self.fixture.pose.apply(self.fixture.curve.positions(s))

    def describe(self):
        return {"setup": self.name, "shape": self.curve.name, "fixture": self.fixture_kind,
                "segments": self.spec.n_segments, "timestep": self.spec.timestep}


class CalibrationPoses(Setup):
    """The two poses of the two-step calibration, on request: ``straight``, then an in-plane ``bend``.

    The catheter is held by connect constraints, first straight; :meth:`set_pose` retargets them. The bend is
    a planar arc of ``bend_curvature`` (default 16 1/m, the paper's 0.16 1/cm) in the plane at ``bend_angle``
    (rad, about the fibre axis from d1) — unknown to the calibration, which must not depend on it.

    Parameters
    ----------
    bend_curvature : float
        1/m.
    bend_angle : float
        rad.
    segments : int
    settle_time : float
        s.
    """

    name = "calibration"
    poses = ("straight", "bend")

    def __init__(self, bend_curvature: float = 16.0, bend_angle: float = 0.6, segments: int = 100,
                 settle_time: float = 10.0):
        k = float(bend_curvature) * np.array([np.cos(bend_angle), np.sin(bend_angle)])
        self.shapes = {
            "straight": shapes.ShapeCurve("straight", True, lambda s: np.zeros((*np.shape(s), 2))),
            "bend": shapes.ShapeCurve("calibration-bend", True, lambda s: np.broadcast_to(k, (*np.shape(s), 2))),
        }
        self.spec = CatheterSpec(n_segments=int(segments))
        self.settle_time = float(settle_time)
        self.pose = "straight"
        self.fixture = None

    def build(self):
        model, data, self.fixture = build_connect(self.shapes["straight"], self.spec)
        return model, data

    def prepare(self, model, data, progress=None):
        settle(model, data, max_time=self.settle_time, progress=progress)
        sleep_at_rest(model)  # connect constraints alone: at rest once settled (StaticShape.prepare)

    def set_pose(self, model, data, pose, progress=None):
        if pose not in self.shapes:
            raise ValueError(f"sim://{self.name}: unknown pose {pose!r}; known: {', '.join(self.poses)}")
        # Keep the clamp where it is: place the new curve so that its clamp pose is the current one.
        def clamp(name):
            return rod_base_pose(ExtendedCurve(self.shapes[name], self.spec.base_length, self.spec.tip_length),
                                 self.spec)

        old, new = clamp(self.pose), clamp(pose)
        inverse_new = Pose(-new.rot.T @ new.pos, new.rot.T)
        self._placement = getattr(self, "_placement", self.fixture.pose) @ old @ inverse_new
        wake(model)  # new connect targets do not wake a sleeping rod by themselves
        self.fixture.set_shape(model, self.shapes[pose], self._placement)
        self.pose = pose
        settle(model, data, max_time=self.settle_time, progress=progress, label=f"calibration pose {pose!r}")
        sleep_at_rest(model)

    def fixture_centreline(self):
        s = np.linspace(0.0, self.spec.sensed_length, 341)
        placement = getattr(self, "_placement", self.fixture.pose)
        curve = ExtendedCurve(self.shapes[self.pose], self.spec.base_length, self.spec.tip_length)
        return placement.apply(curve.positions(s))

    def describe(self):
        return {"setup": self.name, "pose": self.pose, "segments": self.spec.n_segments}
