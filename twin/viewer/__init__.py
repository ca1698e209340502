"""Live 3D view of reconstructed catheter shapes in a browser, through meshcat.

:class:`Viewer` starts a meshcat server on 127.0.0.1 (no browser is opened; open the printed URL) and draws
one frame per :meth:`Viewer.show`:

- the **reconstruction** as a swept tube of the catheter's radius (orange), one mesh message per update;
- the **truth** (when given, e.g. from the simulator) as a thinner tube in a second colour (green);
- the **gratings** as markers coloured by |curvature| (viridis over ``curvature_range``, grey where the
  grating could not be solved), one points message with per-vertex colours;
- the **fixture** or sheath centreline (tube, groove, sheath) as a faint translucent tube, sent again only
  when it changes;
- a **label** (name, live/stale state); a stale stream turns the catheter grey.

Placement: a Shape lives in the fibre's base frame. ``base_pose`` (R, p) puts it in the world; else, with a
truth that carries its material frames at s = 0, the truth's base pose is used (what a tracked catheter
base would give); else the reconstruction is registered onto the truth (Kabsch on arc-length
correspondences); without any truth the scene is the base frame itself.

Units: geometry is sent in metres (SI like the rest of the package). meshcat's scene (grid 0.5 units, axes
0.5 units, camera near plane 0.01 units) is made for ~1 m objects, so everything hangs under a root node
scaled by ``ViewerConfig.scale`` (10 by default: one scene unit is 10 cm, a grid cell 5 cm, the axes at the
world origin 5 cm) and shifted so the catheter sits at the scene origin, where the orbit controls turn.
The camera is framed on the catheter at the first frame (and on ``show(..., reframe=True)``).

A display-rate limiter (``max_fps``, 30 by default) drops frames that come sooner than the browser needs,
so a 1 kHz source does not flood it. :class:`ViewerSink` plugs a viewer into :class:`twin.live.LiveLoop`.

meshcat is imported lazily: ``import twin`` stays light and works without it. The viewer is not thread-safe
(call it from one thread).
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import io
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from twin.frames import Frame, Shape, Truth

if TYPE_CHECKING:  # pragma: no cover
    from twin.live import LiveStatus

__all__ = ["Viewer", "ViewerConfig", "ViewerError", "ViewerSink", "curvature_colors", "tube_mesh"]

#: meshcat's default perspective camera (three.js): vertical field of view, degrees
CAMERA_FOV_DEG = 75.0

# The meshcat server runs in its own process. This launcher makes its web server listen on 127.0.0.1 only
# (meshcat binds every interface by default; our servers bind loopback unless told otherwise), silences
# pyzmq's deprecation warning, and exits when its parent dies (so a killed test or Ctrl-C'd run never leaves
# a server holding ports 6000/7000).
_SERVER_CODE = r"""
import os, sys, threading, time, warnings
warnings.simplefilter("ignore", DeprecationWarning)
import tornado.web
_listen = tornado.web.Application.listen
def _listen_loopback(self, port, address="127.0.0.1", **kw):
    return _listen(self, port, address=address, **kw)
tornado.web.Application.listen = _listen_loopback
parent = os.getppid()
def _watch():
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(0)
threading.Thread(target=_watch, daemon=True).start()
from meshcat.servers import zmqserver
sys.argv = ["meshcat-server"]
zmqserver.main()
"""


class ViewerError(OSError):
    """The viewer cannot draw: meshcat is missing, its server is gone or does not answer, or it was closed."""


@dataclass(frozen=True)
class ViewerConfig:
    """How the viewer draws (lengths in m, colours 0xRRGGBB).

    Attributes
    ----------
    radius : float
        Radius of the reconstructed catheter tube, m (8 Fr ≈ 2.67 mm diameter).
    truth_radius : float
        Radius of the truth tube, m; thinner, so it shows where the reconstruction strays from it.
    fixture_radius : float
        Radius of the fixture's translucent tube, m (the 3 mm printed tubes of the static experiment).
    exaggerate : float
        Display gain on the reconstruction's deviation from the truth (1 = true geometry). With a truth, the
        reconstruction is drawn at ``truth + exaggerate · (reconstruction − truth)`` at equal arc length, so
        sub-millimetre errors become visible. Display only.
    sides : int
        Polygon sides of the tube's cross-section.
    max_rings : int
        Most cross-sections per tube (the centreline is subsampled evenly beyond this).
    marker_size : float
        Grating marker size, m (meshcat points: square sprites, shown on top of the tube).
    curvature_range : (float, float)
        |curvature| mapped to the ends of the colormap, 1/m.
    colormap : str
        matplotlib colormap name for the grating markers.
    max_fps : float
        Most frames drawn per second, Hz (``inf``: no limit); :meth:`Viewer.show` skips the others.
    scale : float
        Scene units per metre (see the module notes).
    shape_color, truth_color, fixture_color, stale_color : int
        Reconstruction, truth, fixture and stale-reconstruction colours.
    fixture_opacity : float
        Opacity of the fixture tube (0–1).
    label : bool
        Show the text label (name and state).
    timeout : float
        Longest wait for the server's answer to one message, s; after that the viewer gives up (never hangs).
    """

    radius: float = 1.3e-3
    truth_radius: float = 0.5e-3
    fixture_radius: float = 1.5e-3
    exaggerate: float = 1.0
    sides: int = 12
    max_rings: int = 200
    marker_size: float = 3.5e-3
    curvature_range: tuple[float, float] = (0.0, 70.0)
    colormap: str = "viridis"
    max_fps: float = 30.0
    scale: float = 10.0
    shape_color: int = 0xFF7F0E
    truth_color: int = 0x2CA02C
    fixture_color: int = 0xFFFFFF
    fixture_opacity: float = 0.2
    stale_color: int = 0x8C8C8C
    label: bool = True
    timeout: float = 2.0

    def __post_init__(self) -> None:
        for name in ("radius", "truth_radius", "fixture_radius", "marker_size", "scale", "timeout"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ViewerConfig.{name} must be positive and finite, got {v}")
        if not self.max_fps > 0:
            raise ValueError(f"ViewerConfig.max_fps must be positive (inf for no limit), got {self.max_fps}")
        if not np.isfinite(self.exaggerate) or self.exaggerate <= 0:
            raise ValueError(f"ViewerConfig.exaggerate must be positive, got {self.exaggerate}")
        if self.sides < 3 or self.max_rings < 2:
            raise ValueError(f"ViewerConfig: sides >= 3 and max_rings >= 2 needed, got {self.sides}, "
                             f"{self.max_rings}")
        lo, hi = self.curvature_range
        if not hi > lo:
            raise ValueError(f"ViewerConfig.curvature_range must be increasing, got {self.curvature_range}")
        if not 0 <= self.fixture_opacity <= 1:
            raise ValueError(f"ViewerConfig.fixture_opacity must lie in [0, 1], got {self.fixture_opacity}")


# ------------------------------------------------------------------------------------------------ geometry
def _tangents(points: np.ndarray) -> np.ndarray:
    t = np.gradient(points, axis=0)
    n = np.linalg.norm(t, axis=-1, keepdims=True)
    return t / np.where(n > 0, n, 1.0)


def _perpendicular(t: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to the unit vector ``t``."""
    a = np.eye(3)[int(np.argmin(np.abs(t)))]
    v = np.cross(t, a)
    return v / np.linalg.norm(v)


def _transported_normals(points: np.ndarray, tangents: np.ndarray) -> np.ndarray:
    """Rotation-minimising normals along a polyline (double reflection, Wang et al. 2008).

    A sequential recurrence, used only for curves that come without material frames (a fixture, a truth
    without frames): they are drawn rarely, so the short Python loop is off the hot path.
    """
    n = np.empty_like(points)
    r = _perpendicular(tangents[0])
    n[0] = r
    for i in range(len(points) - 1):
        v1 = points[i + 1] - points[i]
        c1 = v1 @ v1
        if c1 <= 0:
            n[i + 1] = r
            continue
        r_l = r - (2.0 / c1) * (v1 @ r) * v1
        t_l = tangents[i] - (2.0 / c1) * (v1 @ tangents[i]) * v1
        v2 = tangents[i + 1] - t_l
        c2 = v2 @ v2
        r = r_l - (2.0 / c2) * (v2 @ r_l) * v2 if c2 > 1e-30 else r_l
        n[i + 1] = r
    return n


def tube_mesh(points, radius: float, sides: int = 12, normals=None) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh of a tube swept along a centreline, closed by flat caps.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Centreline, n >= 2 (any length unit; the mesh comes out in the same unit).
    radius : float
        Tube radius, same unit.
    sides : int
        Vertices per cross-section.
    normals : array_like, shape (n, 3), optional
        A direction normal to the centreline at each point (e.g. the material frame's d1), which sets the
        orientation of the cross-sections; projected onto the normal plane here. Without it, rotation-
        minimising frames are transported along the curve.

    Returns
    -------
    vertices : ndarray, shape (n·sides + 2·(sides + 1), 3)
        Ring vertices (ring i is rows i·sides … i·sides + sides − 1), then the two caps (centre, then a
        copy of the end ring so the caps shade flat).
    faces : ndarray of uint32, shape (2·(n − 1)·sides + 2·sides, 3)
        Triangles, wound so their normals point out of the tube.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 2:
        raise ValueError(f"tube_mesh: points must have shape (n >= 2, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("tube_mesh: points contain NaN or inf")
    t = _tangents(p)
    if normals is None:
        u = _transported_normals(p, t)
    else:
        u = np.asarray(normals, dtype=np.float64)
        if u.shape != p.shape:
            raise ValueError(f"tube_mesh: normals must have the shape of points {p.shape}, got {u.shape}")
        u = u - np.sum(u * t, axis=-1, keepdims=True) * t  # back into the normal plane
        bad = np.linalg.norm(u, axis=-1) < 1e-9
        if bad.any():  # a normal along the tangent (should not happen with material frames)
            u[bad] = _transported_normals(p, t)[bad]
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    w = np.cross(t, u)
    phi = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
    ring = np.cos(phi)[None, :, None] * u[:, None, :] + np.sin(phi)[None, :, None] * w[:, None, :]
    rings = p[:, None, :] + radius * ring  # (n, sides, 3)
    n = p.shape[0]
    vertices = np.concatenate([rings.reshape(-1, 3), p[:1], rings[0], p[-1:], rings[-1]])
    i = np.arange(n - 1)[:, None]
    j = np.arange(sides)[None, :]
    a = i * sides + j
    b = i * sides + (j + 1) % sides
    c = b + sides
    d = a + sides
    side_faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    jj = np.arange(sides)
    c0 = n * sides  # start-cap centre, then its ring copy
    c1 = c0 + sides + 1  # end-cap centre, then its ring copy
    start = np.stack([np.full(sides, c0), c0 + 1 + (jj + 1) % sides, c0 + 1 + jj], -1)  # normal −t
    end = np.stack([np.full(sides, c1), c1 + 1 + jj, c1 + 1 + (jj + 1) % sides], -1)  # normal +t
    faces = np.concatenate([side_faces, start, end]).astype(np.uint32)
    return vertices, faces


def _colormap_lut(name: str, n: int = 256) -> np.ndarray:
    """RGB table (n, 3) of a matplotlib colormap (matplotlib is imported here only)."""
    import matplotlib

    return np.asarray(matplotlib.colormaps[name].resampled(n)(np.linspace(0.0, 1.0, n)))[:, :3]


def curvature_colors(curvature, valid=None, curvature_range: tuple[float, float] = (0.0, 70.0),
                     colormap: str | np.ndarray = "viridis", invalid_color=(0.5, 0.5, 0.5)) -> np.ndarray:
    """Colour of each grating marker from its curvature vector.

    Parameters
    ----------
    curvature : array_like, shape (n_gratings, 2)
        Curvature vectors, 1/m (NaN where unsolved).
    valid : array_like of bool, shape (n_gratings,), optional
        Gratings whose curvature could be computed; the others get ``invalid_color``.
    curvature_range : (float, float)
        |curvature| at the low and high ends of the colormap, 1/m; values outside are clipped.
    colormap : str or ndarray (m, 3)
        matplotlib colormap name, or a lookup table of RGB rows in [0, 1].

    Returns
    -------
    ndarray, shape (n_gratings, 3)
        RGB in [0, 1].
    """
    k = np.linalg.norm(np.asarray(curvature, dtype=np.float64), axis=-1)
    lut = _colormap_lut(colormap) if isinstance(colormap, str) else np.asarray(colormap, dtype=np.float64)
    lo, hi = curvature_range
    x = np.clip((np.nan_to_num(k, nan=lo) - lo) / (hi - lo), 0.0, 1.0)
    rgb = lut[np.rint(x * (len(lut) - 1)).astype(int)]
    bad = ~np.isfinite(k)
    if valid is not None:
        bad |= ~np.asarray(valid, dtype=bool)
    rgb[bad] = invalid_color
    return rgb


def _rgb(color: int) -> np.ndarray:
    return np.array([(color >> 16) & 255, (color >> 8) & 255, color & 255], dtype=np.float64) / 255.0


def _subsample(n: int, most: int) -> np.ndarray:
    """Indices of at most ``most`` evenly spread points of n, always keeping both ends."""
    if n <= most:
        return np.arange(n)
    return np.unique(np.rint(np.linspace(0, n - 1, most)).astype(int))


def _interp_curve(s_new: np.ndarray, s: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Linear interpolation of a sampled curve (m, 3) at arc lengths ``s_new`` (clamped to its range)."""
    return np.stack([np.interp(s_new, s, points[:, k]) for k in range(3)], axis=-1)


def _check_pose(base_pose) -> tuple[np.ndarray, np.ndarray]:
    try:
        R, p = base_pose
    except (TypeError, ValueError):
        raise ValueError("base_pose must be a pair (R (3, 3), p (3,))") from None
    R = np.asarray(R, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    if R.shape != (3, 3) or p.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(p))):
        raise ValueError(f"base_pose must be (R (3, 3), p (3,)) finite; got shapes {R.shape}, {p.shape}")
    return R, p


def placement(shape: Shape, truth: Truth | None = None, base_pose=None) -> tuple[np.ndarray, np.ndarray, str]:
    """Where the base frame of ``shape`` sits in the world: (R (3, 3), p (3,), how).

    ``how`` is ``"base_pose"`` (given), ``"truth_base"`` (the truth's material frame at s = 0),
    ``"kabsch"`` (rigid registration of the reconstruction onto the truth at equal arc lengths) or
    ``"base_frame"`` (no truth: identity, the scene is the fibre's base frame).
    """
    if base_pose is not None:
        R, p = _check_pose(base_pose)
        return R, p, "base_pose"
    if truth is None:
        return np.eye(3), np.zeros(3), "base_frame"
    ts = np.asarray(truth.s, dtype=np.float64)
    tp = np.asarray(truth.positions, dtype=np.float64)
    if truth.frames is not None and ts.size:
        i0 = int(np.argmin(np.abs(ts)))
        if abs(ts[i0]) < 1e-9:
            return np.asarray(truth.frames[i0], dtype=np.float64), tp[i0], "truth_base"
    from twin.metrics import kabsch

    inside = (shape.s >= ts.min() - 1e-12) & (shape.s <= ts.max() + 1e-12)
    if inside.sum() < 3:
        raise ValueError("show: the truth does not overlap the reconstruction's arc lengths; give base_pose")
    target = _interp_curve(shape.s[inside], ts, tp)
    R, p = kabsch(shape.positions[inside], target)
    return R, p, "kabsch"


# ------------------------------------------------------------------------------------------------ the viewer
def _import_meshcat():
    with warnings.catch_warnings():
        # pyzmq's "zmq.eventloop.ioloop is deprecated", raised by meshcat's imports
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            import meshcat
            import meshcat.geometry
            import meshcat.visualizer
        except ImportError as exc:
            raise ViewerError(f"the viewer needs meshcat (pip install meshcat): {exc}") from None
    return meshcat


class Viewer:
    """A meshcat scene in the browser showing one catheter shape at a time (see the module notes).

    Parameters
    ----------
    config : ViewerConfig, optional
        Drawing options (defaults: 1.3 mm tube, 30 fps, scene scale ×10).
    announce : text file, "stderr" or None
        Where to print the URL to open (the current ``sys.stderr`` by default; None: silent).

    Attributes
    ----------
    url : str
        The page to open in a browser (http://127.0.0.1:7000/static/ or the next free port).
    frames_shown, frames_skipped : int
        :meth:`show` calls drawn, and dropped by the rate limiter.
    last_draw_s : float
        Wall time of the last drawing, s (meshing plus the messages to the server).
    placement : str or None
        How the last reconstruction was placed (see :func:`placement`).
    """

    def __init__(self, config: ViewerConfig | None = None, *, announce: TextIO | str | None = "stderr"):
        self.config = config or ViewerConfig()
        self._meshcat = _import_meshcat()
        self._g = self._meshcat.geometry
        self._lut = _colormap_lut(self.config.colormap)
        self._closed = False
        self._broken: str | None = None
        self.frames_shown = 0
        self.frames_skipped = 0
        self.last_draw_s = 0.0
        self.placement: str | None = None
        self._due = -float("inf")  # when the rate limiter lets the next frame through (monotonic s)
        self._framed = False
        self._centre = np.zeros(3)
        self._extent = 0.1
        self._fixture: np.ndarray | None = None
        self._stale = False
        self._state = ""
        self._label = ""
        self._label_text: str | None = None
        self._label_at = -float("inf")
        self._last: dict[str, Any] | None = None  # last reconstruction drawn, to recolour when stale
        self._camera = np.array([1.0, 0.0, 0.0])
        self._label_pose = np.eye(4)
        self._state_detail = ""
        self._proc, zmq_url, self.url = self._start_server()
        try:
            self.vis = self._connect(zmq_url)
        except BaseException:
            self._kill()
            raise
        atexit.register(self.close)
        if announce is not None:
            stream = sys.stderr if announce == "stderr" else announce  # looked up now: redirections count
            print(f"twin viewer: open {self.url}", file=stream, flush=True)

    # ---------------------------------------------------------------- server
    def _start_server(self) -> tuple[subprocess.Popen, str, str]:
        proc = subprocess.Popen(
            [sys.executable, "-u", "-c", _SERVER_CODE],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, start_new_session=True,
        )
        urls: dict[str, str] = {}
        deadline = time.monotonic() + 30.0
        try:
            # the server prints "zmq_url=…" then "web_url=…" once it listens
            while len(urls) < 2:
                line = proc.stdout.readline().decode("utf-8", "replace").strip()
                if not line and proc.poll() is not None:
                    raise ViewerError(f"the meshcat server exited at start (status {proc.returncode})")
                key, sep, value = line.partition("=")
                if sep and key in ("zmq_url", "web_url"):
                    urls[key] = value
                if time.monotonic() > deadline:
                    raise ViewerError("the meshcat server did not start within 30 s")
        except BaseException:
            proc.kill()
            proc.wait()
            raise
        # keep reading its stdout so the pipe never fills and blocks the server
        threading.Thread(target=_drain, args=(proc.stdout,), daemon=True).start()
        return proc, urls["zmq_url"], urls["web_url"]

    def _connect(self, zmq_url: str):
        import zmq

        meshcat = self._meshcat
        # A window attached to our own server process (meshcat's would print to stdout and bind every
        # interface); a REQ socket with timeouts so a dead server raises instead of hanging the caller.
        window = meshcat.visualizer.ViewerWindow.__new__(meshcat.visualizer.ViewerWindow)
        window.server_proc, window.zmq_url, window.web_url = self._proc, zmq_url, self.url
        window.zmq_socket = window.context.socket(zmq.REQ)
        ms = int(self.config.timeout * 1000)
        window.zmq_socket.setsockopt(zmq.RCVTIMEO, ms)
        window.zmq_socket.setsockopt(zmq.SNDTIMEO, ms)
        window.zmq_socket.setsockopt(zmq.LINGER, 0)
        window.zmq_socket.connect(zmq_url)
        return meshcat.Visualizer(window=window)

    @property
    def server_pid(self) -> int:
        return self._proc.pid

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def broken(self) -> str | None:
        """Why the viewer stopped drawing (server gone or unresponsive), or None."""
        return self._broken

    def _call(self, fn, *args):
        """Send one message; a dead or silent server makes the viewer unusable (ViewerError), never a hang."""
        if self._closed:
            raise ViewerError("the viewer is closed")
        if self._broken:
            raise ViewerError(self._broken)
        if self._proc.poll() is not None:
            self._broken = f"the meshcat server exited (status {self._proc.returncode})"
            raise ViewerError(self._broken)
        import zmq

        try:
            return fn(*args)
        except zmq.ZMQError as exc:
            # a REQ socket that timed out is stuck in its send/receive cycle: give up on this server
            self._broken = f"the meshcat server did not answer ({exc})"
            raise ViewerError(self._broken) from None

    def _set(self, path: str, geometry, material=None) -> None:
        self._call(self.vis[path].set_object, geometry, material)

    def _set_transform(self, path: str, matrix: np.ndarray) -> None:
        self._call(self.vis[path].set_transform, matrix)

    # ---------------------------------------------------------------- drawing
    def ready(self, now: float | None = None) -> bool:
        """Whether :meth:`show` would draw now (the rate limiter's verdict)."""
        now = time.monotonic() if now is None else now
        return now >= self._due

    def show(self, shape: Shape, truth: Truth | None = None, *, base_pose=None, fixture=None,
             label: str | None = None, force: bool = False, reframe: bool = False) -> bool:
        """Draw one reconstruction, with its truth and fixture when given.

        Parameters
        ----------
        shape : Shape
            One reconstruction (no batch axes; index a batch first), positions in the base frame, m.
        truth : Truth, optional
            The true centreline (world, m); its ``fixture`` is drawn too.
        base_pose : (R (3, 3), p (3,)), optional
            The fibre base frame in the world (columns of R: d1 d2 d3; p in m). Default: from the truth
            (see :func:`placement`), else the base frame.
        fixture : array_like (k, 3), optional
            Fixture centreline in the world, m; overrides ``truth.fixture``.
        label : str, optional
            Text shown above the catheter (e.g. the shape's name); kept until changed.
        force : bool
            Draw even if the rate limiter would skip this frame.
        reframe : bool
            Frame the camera on this shape (it is framed on the first one anyway).

        Returns
        -------
        bool
            True when drawn, False when skipped by the rate limiter.

        Raises
        ------
        ValueError
            A batch of shapes, or a shape with NaN points (an unusable frame).
        ViewerError
            The viewer is closed or its server is gone.
        """
        now = time.monotonic()
        if not force and not self.ready(now):
            self.frames_skipped += 1
            return False
        if shape.positions.ndim != 2:
            raise ValueError(f"Viewer.show takes one shape, got a batch of shape {shape.batch_shape}; index it")
        if not np.all(np.isfinite(shape.positions)):
            raise ValueError("Viewer.show: the shape has NaN points (an unusable frame)")
        t0 = time.perf_counter()
        cfg = self.config
        R, p, how = placement(shape, truth, base_pose)
        self.placement = how
        world = shape.positions @ R.T + p
        frames_d1 = shape.frames[:, :, 0] @ R.T
        truth_pts = None
        if truth is not None:
            ts, tp = np.asarray(truth.s, dtype=np.float64), np.asarray(truth.positions, dtype=np.float64)
            if cfg.exaggerate != 1.0:
                inside = (shape.s >= ts.min()) & (shape.s <= ts.max())
                ref = _interp_curve(shape.s[inside], ts, tp)
                world[inside] = ref + cfg.exaggerate * (world[inside] - ref)
            truth_pts = tp
            sensed = (ts >= shape.s[0] - 1e-9) & (ts <= shape.s[-1] + 1e-9)
            truth_frame_pts = tp[sensed] if sensed.sum() >= 2 else tp
        if fixture is None and truth is not None:
            fixture = truth.fixture
        if not self._framed or reframe:
            pts = world if truth_pts is None else np.concatenate([world, truth_frame_pts])
            self._frame(pts)
        if label is not None:
            self._label = label
        if fixture is not None:
            self._draw_fixture(np.asarray(fixture, dtype=np.float64))

        keep = _subsample(len(world), cfg.max_rings)
        verts, faces = tube_mesh(world[keep], cfg.radius, cfg.sides, normals=frames_d1[keep])
        grating_pts = _interp_curve(shape.grating_s, shape.s, world)
        colors = curvature_colors(shape.curvature, shape.valid, cfg.curvature_range, self._lut)
        self._last = {"verts": verts, "faces": faces, "markers": grating_pts, "colors": colors}
        self._draw_reconstruction()
        if truth_pts is not None and len(truth_pts) >= 2:
            tk = _subsample(len(truth_pts), cfg.max_rings)
            normals = None if truth.frames is None else np.asarray(truth.frames)[tk, :, 0]
            tv, tf = tube_mesh(truth_pts[tk], cfg.truth_radius, max(6, cfg.sides // 2), normals=normals)
            self._set("/twin/truth", self._g.TriangularMeshGeometry(tv, tf),
                      self._g.MeshPhongMaterial(color=cfg.truth_color))
        self._update_label(now, force=label is not None)
        self._due = _next_due(self._due, now, 1.0 / self.config.max_fps)
        self.frames_shown += 1
        self.last_draw_s = time.perf_counter() - t0
        return True

    def _draw_reconstruction(self) -> None:
        if self._last is None:
            return
        cfg = self.config
        g = self._g
        color = cfg.stale_color if self._stale else cfg.shape_color
        self._set("/twin/shape", g.TriangularMeshGeometry(self._last["verts"], self._last["faces"]),
                  g.MeshPhongMaterial(color=color))
        colors = np.broadcast_to(_rgb(cfg.stale_color), self._last["colors"].shape) if self._stale \
            else self._last["colors"]
        self._set("/twin/gratings", g.PointsGeometry(self._last["markers"].T.astype(np.float32),
                                                     np.ascontiguousarray(colors.T, dtype=np.float32)),
                  _marker_material(g, cfg.marker_size * cfg.scale))

    def _draw_fixture(self, fixture: np.ndarray) -> None:
        if fixture.ndim != 2 or fixture.shape[1] != 3 or len(fixture) < 2:
            raise ValueError(f"fixture must have shape (k >= 2, 3), got {fixture.shape}")
        if self._fixture is not None and self._fixture.shape == fixture.shape and np.array_equal(
                self._fixture, fixture):
            return  # unchanged: not sent again
        cfg = self.config
        ok = np.all(np.isfinite(fixture), axis=1)
        pts = fixture[ok][_subsample(int(ok.sum()), cfg.max_rings)]
        verts, faces = tube_mesh(pts, cfg.fixture_radius, cfg.sides)
        self._set("/twin/fixture", self._g.TriangularMeshGeometry(verts, faces),
                  self._g.MeshPhongMaterial(color=cfg.fixture_color, opacity=cfg.fixture_opacity,
                                            transparent=True, depthWrite=False))
        self._fixture = fixture.copy()

    # ---------------------------------------------------------------- camera
    def _frame(self, points: np.ndarray) -> None:
        """Centre the scene on ``points`` (world, m) and put the camera where it sees them whole."""
        cfg = self.config
        c = 0.5 * (points.min(axis=0) + points.max(axis=0))
        x = points - c
        extent = float(np.max(np.linalg.norm(x, axis=1))) + cfg.radius
        self._centre, self._extent = c, max(extent, 10 * cfg.radius)
        s = cfg.scale
        root = np.eye(4)
        root[:3, :3] *= s
        root[:3, 3] = -s * c
        self._set_transform("/twin", root)
        # the axes show the world origin (5 cm long at scale 10); the grid lies under the catheter
        self._set_transform("/Axes", _translation(-s * c))
        self._set_transform("/Grid", _translation([0.0, 0.0, s * (points[:, 2].min() - c[2]) - 0.2 * s
                                                   * self._extent]))
        direction = view_direction(points)
        distance = camera_distance(self._extent * s)
        eye = distance * direction
        # the label faces the camera, just above the catheter as seen from there (screen-up: +z, made
        # perpendicular to the view)
        up = np.array([0.0, 0.0, 1.0]) - direction[2] * direction
        up /= np.linalg.norm(up)
        self._label_pose = np.eye(4)
        self._label_pose[:3, 0], self._label_pose[:3, 1], self._label_pose[:3, 2] = np.cross(up, direction), up, \
            direction
        top = float(np.max(x @ up)) + cfg.radius
        self._label_pose[:3, 3] = (top + 0.2 * self._extent) * s * up
        # The camera node hangs under /Cameras/default/rotated, turned +90° about x (three.js is y-up):
        # a world offset (x, y, z) is (x, z, −y) in the camera's parent frame.
        self._call(self.vis["/Cameras/default/rotated/<object>"].set_property, "position",
                   [float(eye[0]), float(eye[2]), float(-eye[1])])
        self._camera = eye
        self._framed = True
        self._label_text = None  # re-place the label

    def camera(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Camera (eye in scene units relative to the catheter's centre, world centre in m, scale)."""
        return self._camera.copy(), self._centre.copy(), self.config.scale

    # ---------------------------------------------------------------- state and label
    def set_state(self, state: str, detail: str = "") -> None:
        """Show the stream's state: ``stale`` turns the reconstruction grey, anything else restores it.

        ``detail`` is appended to the label (e.g. "no data for 2 s"); the label is redrawn at most twice a
        second unless the state changed.
        """
        stale = state == "stale"
        changed = state != self._state
        self._state = state
        if stale != self._stale:
            self._stale = stale
            self._draw_reconstruction()
        self._state_detail = detail
        self._update_label(time.monotonic(), force=changed)

    def _update_label(self, now: float, force: bool = False) -> None:
        if not self.config.label or not self._framed:
            return
        parts = [self._label] if self._label else []
        if self._state:
            detail = self._state_detail
            parts.append(self._state.upper() + (f" ({detail})" if detail else "") if self._stale
                         else self._state)
        text = "  ·  ".join(parts)
        if text == self._label_text or (not force and now - self._label_at < 0.5):
            return
        if not text:
            self._call(self.vis["/label"].delete)
            self._label_text = text
            return
        png, aspect = _label_png(text, self._stale)
        g = self._g
        s = self.config.scale
        height = 0.12 * self._extent * s
        # a flat plane, front face only (a box's edges and back face would show slivers and mirrored text)
        material = g.MeshBasicMaterial(map=g.ImageTexture(g.PngImage(png)), transparent=True, side=0)
        self._call(self.vis["/label"].set_object, _plane(g, height * aspect, height), material)
        self._set_transform("/label", self._label_pose)
        self._label_text, self._label_at = text, now

    # ---------------------------------------------------------------- output and end
    def save_html(self, path) -> Path:
        """Write the current scene as one self-contained HTML page (meshcat's static_html); returns the path."""
        html = self._call(self.vis.static_html)
        path = Path(path)
        path.write_text(html, encoding="utf-8")
        return path

    def close(self) -> None:
        """Stop the meshcat server (the browser keeps the last picture) and release the socket. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            atexit.unregister(self.close)
        with contextlib.suppress(Exception):
            self.vis.window.zmq_socket.close(linger=0)
        self._kill()

    def _kill(self) -> None:
        proc = self._proc
        if proc.poll() is None:
            proc.kill()
        with contextlib.suppress(Exception):
            proc.wait(timeout=10)
        with contextlib.suppress(Exception):
            proc.stdout.close()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _next_due(due: float, now: float, period: float) -> float:
    """The rate limiter's next slot: one period after the last slot, not after the draw.

    Frames arrive in batches at the source's own rhythm; stepping from the slot (not from when the frame
    happened to arrive) keeps the average rate at 1/period instead of rounding each gap up to the next batch.
    A limiter that fell behind restarts from now rather than drawing a burst.
    """
    return max(due + period, now) if np.isfinite(due) else now + period


def _drain(stream) -> None:
    with contextlib.suppress(Exception):
        while stream.read(4096):
            pass


def _translation(v) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = v
    return m


@functools.cache
def _extra_classes(g) -> tuple[type, type]:
    """meshcat 0.3.2 lacks a plane geometry and points drawn on top; made once, when meshcat is imported."""

    class Plane(g.Geometry):
        """three.js PlaneGeometry: in the local x-y plane, facing +z."""

        def __init__(self, width: float, height: float):
            super().__init__()
            self.width, self.height = width, height

        def lower(self, object_data):
            return {"uuid": self.uuid, "type": "PlaneGeometry", "width": self.width, "height": self.height}

    class OnTopPoints(g.PointsMaterial):
        """Points drawn over the tube (the markers sit on the centreline, inside it); boolean vertexColors
        as three.js ≥ r113 wants."""

        def lower(self, object_data):
            data = super().lower(object_data)
            data.update(depthTest=False, transparent=True, vertexColors=True)
            return data

    return Plane, OnTopPoints


def _plane(g, width: float, height: float):
    return _extra_classes(g)[0](width, height)


def _marker_material(g, size: float):
    return _extra_classes(g)[1](size=size)


def view_direction(points: np.ndarray, min_elevation_deg: float = 15.0,
                   max_elevation_deg: float = 60.0) -> np.ndarray:
    """Unit vector from the catheter towards the camera: face-on to its best-fit plane, z up.

    The normal of the plane of the two largest principal axes shows a planar shape undistorted (and a
    spatial one at its widest); its elevation is kept within [min, max] so the grid is seen from above and
    the orbit controls' up axis (+z) never lines up with the view.
    """
    x = points - points.mean(axis=0)
    _, sv, vt = np.linalg.svd(x, full_matrices=False)
    n = vt[-1] if sv.size == 3 else np.array([1.0, 0.0, 0.0])
    if sv.size >= 2 and sv[1] < 1e-6 * max(sv[0], 1e-30):  # a straight line: any normal; prefer horizontal
        n = np.cross(vt[0], [0.0, 0.0, 1.0])
        if np.linalg.norm(n) < 1e-9:
            n = np.array([1.0, 0.0, 0.0])
    n = n / np.linalg.norm(n)
    if n[2] < 0:
        n = -n
    h = np.hypot(n[0], n[1])
    azimuth = np.arctan2(n[1], n[0]) if h > 1e-6 else np.arctan2(vt[0][1], vt[0][0]) + np.pi / 2
    elevation = np.clip(np.arctan2(n[2], h), np.radians(min_elevation_deg), np.radians(max_elevation_deg))
    return np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])


def camera_distance(radius: float, fov_deg: float = CAMERA_FOV_DEG, fill: float = 0.75) -> float:
    """Camera distance at which a sphere of ``radius`` spans ``fill`` of the view's height (same unit)."""
    return radius / (fill * np.tan(np.radians(fov_deg) / 2))


def _label_png(text: str, stale: bool) -> tuple[bytes, float]:
    """The label as a PNG (dark text on a translucent white box) and its width/height ratio."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    width_in = max(2.0, 0.13 * len(text) + 0.4)
    height_in = 0.45
    fig = Figure(figsize=(width_in, height_in), dpi=100)
    FigureCanvasAgg(fig)
    fig.patch.set_alpha(0.0)
    fig.text(0.5, 0.5, text, ha="center", va="center", fontsize=16,
             color="#b00000" if stale else "#202020",
             bbox={"boxstyle": "round,pad=0.3", "facecolor": "white", "alpha": 0.75, "edgecolor": "none"})
    buf = io.BytesIO()
    fig.savefig(buf, format="png", transparent=True)
    return buf.getvalue(), width_in / height_in


# ------------------------------------------------------------------------------------------------ live sink
class ViewerSink:
    """A :class:`twin.live.LiveLoop` sink drawing the latest usable shape of each batch, at most ``rate`` Hz.

    The frame's truth is drawn when the source carries it (the simulator). A frame dropped by the rate limit
    is kept and drawn at the next heartbeat, so the display never lags the stream's last shape. A stale
    stream turns the catheter grey. Nothing the viewer does raises out of the sink (the loop would drop it):
    errors are counted in ``errors`` (first one reported on stderr), and a viewer whose server is gone is
    left alone.

    Parameters
    ----------
    viewer : Viewer
    rate : float
        Most frames drawn per second, Hz.
    close_viewer : bool
        Close the viewer when the loop closes the sink.
    stream : text file
        Where the first error is reported (stderr).
    """

    def __init__(self, viewer: Viewer, rate: float = 30.0, *, close_viewer: bool = True,
                 stream: TextIO | None = None):
        if not rate > 0:
            raise ValueError(f"ViewerSink: rate must be positive, got {rate}")
        self.viewer = viewer
        self.period = 1.0 / rate
        self.close_viewer = close_viewer
        self.stream = stream
        self.errors = 0
        self.last_error: str | None = None
        self.frames_received = 0
        self.frames_shown = 0
        self._pending: tuple[Shape, Truth | None] | None = None
        self._due = -float("inf")

    def __call__(self, frames: Sequence[Frame], shapes: Shape | None, status: LiveStatus) -> None:
        try:
            self._handle(frames, shapes, status)
        except Exception as exc:  # the viewer must never end the live loop
            self.errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            if self.errors == 1:
                print(f"twin live: viewer: {self.last_error} (further errors counted, not shown)",
                      file=self.stream or sys.stderr)

    def _handle(self, frames, shapes, status) -> None:
        self.frames_received += len(frames)
        if frames and shapes is not None:
            pick = _latest_usable(shapes, status.flags, len(frames))
            if pick is not None:
                self._pending = (shapes[pick], frames[pick].truth)
        v = self.viewer
        if v.closed or v.broken or status.state == "ended":
            return
        if self._pending is not None:
            now = time.monotonic()
            if now >= self._due:
                shape, truth = self._pending
                self._pending = None
                self._due = _next_due(self._due, now, self.period)
                v.show(shape, truth, force=True)
                self.frames_shown += 1
        detail = ""
        if status.state == "stale" and np.isfinite(status.last_valid_age):
            detail = f"no data for {status.last_valid_age:.0f} s"
        v.set_state(status.state, detail)

    def close(self) -> None:
        if self.close_viewer:
            self.viewer.close()


def _latest_usable(shapes: Shape, flags: np.ndarray, n: int) -> int | None:
    """Index of the last frame of the batch whose shape can be drawn (not flagged unusable, finite points)."""
    from twin.live import FrameFlag

    for i in range(n - 1, -1, -1):  # from the end: usually the first one tried is drawn
        if i < len(flags) and flags[i] & FrameFlag.UNUSABLE:
            continue
        if np.all(np.isfinite(shapes.positions[i])):
            return i
    return None
