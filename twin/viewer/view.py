"""The browser viewer's drawing side: :class:`Viewer` (one catheter shape per frame, with its error) and
:class:`ViewerConfig`; :func:`keep_open` for a page kept after the run. The package's notes
(:mod:`twin.viewer`) say what is drawn and how it is placed.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from twin.frames import Shape, Truth
from twin.live import next_due
from twin.viewer import commands as cmd
from twin.viewer import geometry as geo
from twin.viewer.client import SceneClient, ViewerError
from twin.viewer.geometry import tube_mesh

__all__ = ["CAMERA_FOV_DEG", "Viewer", "ViewerConfig", "keep_open"]

#: meshcat's default perspective camera (three.js): vertical field of view, degrees
CAMERA_FOV_DEG = 75.0


def _css(color: int) -> str:
    return f"#{color:06x}"


def _rgb(color: int) -> np.ndarray:
    return np.array([(color >> 16) & 255, (color >> 8) & 255, color & 255], dtype=np.float64) / 255.0


@dataclass(frozen=True)
class ViewerConfig:
    """How the viewer draws (lengths in m, colours 0xRRGGBB).

    Attributes
    ----------
    radius, truth_radius, fixture_radius : float
        Radii of the reconstruction's tube (8 Fr ≈ 2.67 mm diameter), the truth's centreline and the fixture.
    sides, max_rings : int
        Polygon sides of a tube's cross-section; most cross-sections per tube.
    marker_size : float
        Grating dot size, m.
    error_range, curvature_range : (float, float)
        Local error (m) and |curvature| (1/m) at the ends of the colour map; values beyond are clipped.
    shape_opacity : float
        Opacity of the reconstruction's tube (0–1): translucent, so the truth inside it shows.
    max_fps : float
        Most frames drawn per second, Hz (``inf``: no limit); :meth:`Viewer.show` skips the others.
    scale : float
        Scene units per metre.
    truth_color, fixture_color, stale_color, marker_color, scale_color, vendor_color : int
    fixture_opacity : float
    confidence_level, confidence_color, confidence_opacity : float, int, float
        The confidence envelope drawn around the tube when a shape carries its uncertainty
        (:class:`twin.uncertainty.Uncertainty`): the catheter's wall lies inside it with this probability
        (:func:`twin.viewer.geometry.envelope`); translucent.
    show_vendor : bool
        Whether the interrogator's own shape starts visible when a frame carries one (the page's scene controls
        toggle it).
    vendor_sensor : int
        Which of the frame's sensor blocks is the fibre shown (0: the first).
    timeout : float
        Longest wait for the server's answer to one message, s (never hangs).
    web_port : int
        The page's port, or the next free one after it (0: any free one).
    magnify : float or None
        The magnified-error view's factor (None: chosen per frame so that the largest deviation shows as about
        ``magnified_deviation``, a round 1-2-5 number, stated in the overlay).
    magnified_deviation : float
        The largest magnified deviation aimed at, m.
    magnify_color : int
    show_magnified : bool
        Whether the magnified-error view is drawn (with a truth, when the factor exceeds 1).
    profile_points : int
        Most points of the error-along-the-catheter plot.
    """

    radius: float = 1.3e-3
    truth_radius: float = 0.35e-3
    fixture_radius: float = 1.5e-3
    sides: int = 12
    max_rings: int = 200
    marker_size: float = 2.5e-3
    error_range: tuple[float, float] = (0.0, 1e-3)
    curvature_range: tuple[float, float] = (0.0, 70.0)
    shape_opacity: float = 0.55
    max_fps: float = 30.0
    scale: float = 10.0
    truth_color: int = 0xFF00FF
    fixture_color: int = 0xFFFFFF
    fixture_opacity: float = 0.2
    confidence_level: float = 0.95
    confidence_color: int = 0x4DA6FF
    confidence_opacity: float = 0.2
    stale_color: int = 0x8C8C8C
    marker_color: int = 0x000000
    scale_color: int = 0x202020
    vendor_color: int = 0xFF8000
    show_vendor: bool = True
    vendor_sensor: int = 0
    timeout: float = 2.0
    web_port: int = 7000
    magnify: float | None = None
    magnified_deviation: float = 10e-3
    magnify_color: int = 0x0090FF
    show_magnified: bool = True
    profile_points: int = 120

    def __post_init__(self) -> None:
        if self.magnify is not None and not (np.isfinite(self.magnify) and self.magnify >= 1):
            raise ValueError(f"ViewerConfig.magnify must be a finite factor >= 1 (None: chosen), got {self.magnify}")
        if not (np.isfinite(self.magnified_deviation) and self.magnified_deviation > 0):
            raise ValueError(f"ViewerConfig.magnified_deviation must be positive, got {self.magnified_deviation}")
        if self.profile_points < 2:
            raise ValueError(f"ViewerConfig.profile_points must be at least 2, got {self.profile_points}")
        for name in ("radius", "truth_radius", "fixture_radius", "marker_size", "scale", "timeout"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ViewerConfig.{name} must be positive and finite, got {v}")
        if not self.max_fps > 0:
            raise ValueError(f"ViewerConfig.max_fps must be positive (inf for no limit), got {self.max_fps}")
        if self.vendor_sensor < 0:
            raise ValueError(f"ViewerConfig.vendor_sensor must be a sensor index >= 0, got {self.vendor_sensor}")
        if self.sides < 3 or self.max_rings < 2:
            raise ValueError(f"ViewerConfig: sides >= 3 and max_rings >= 2 needed, got {self.sides}, "
                             f"{self.max_rings}")
        for name in ("error_range", "curvature_range"):
            lo, hi = getattr(self, name)
            if not hi > lo:
                raise ValueError(f"ViewerConfig.{name} must be increasing, got {(lo, hi)}")
        if not 0 < self.confidence_level < 1:
            raise ValueError(f"ViewerConfig.confidence_level must lie in (0, 1), got {self.confidence_level}")
        for name in ("shape_opacity", "fixture_opacity", "confidence_opacity"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"ViewerConfig.{name} must lie in [0, 1], got {getattr(self, name)}")


class Viewer:
    """A browser scene showing one catheter shape at a time, with its error (see the module notes).

    Parameters
    ----------
    config : ViewerConfig, optional
    announce : text file, "stderr" or None
        Where to print the URL to open (the current ``sys.stderr`` by default; None: silent).
    calibration : str, optional
        The calibration in use, as the overlay should name it (e.g. the file name).

    Attributes
    ----------
    url : str
        The page to open (http://127.0.0.1:7000/static/ or the next free port).
    frames_shown, frames_skipped : int
    errors : dict or None
        The last frame's max / mean / tip error, m (None without a truth).
    vendor_errors : dict or None
        The last frame's max / mean / tip distance to the interrogator's own shape after the registration, m
        (None when the frame had none).
    placement : str or None
        How the last reconstruction was placed.
    """

    def __init__(self, config: ViewerConfig | None = None, *, announce: TextIO | str | None = "stderr",
                 calibration: str | None = None):
        self.config = config or ViewerConfig()
        self._closed = False
        self.frames_shown = 0
        self.frames_skipped = 0
        self.placement: str | None = None
        self.errors: dict[str, float] | None = None
        self.vendor_errors: dict[str, float] | None = None
        self._vendor_shown = False
        self._confidence_shown = False
        self._magnified_shown = False
        self.magnification: float | None = None
        self._profile: dict | None = None
        self.info: dict[str, object] = {"calibration": calibration or "none"}
        self._due = -float("inf")
        self._framed = False
        self._centre, self._extent = np.zeros(3), 0.1
        self._camera = np.array([1.0, 0.0, 0.0])
        self._fixture: np.ndarray | None = None
        self._stale, self._state, self._detail, self._label = False, "", "", ""
        self._mode = "curvature"
        self._last: dict | None = None
        self._bar_length = 0.0
        self._hud_text: str | None = None
        self._hud_at = -float("inf")
        self._queue: list[cmd.Command] | None = None
        self._proc, zmq_url, self.url = self._start_server()
        try:
            self._client = SceneClient(zmq_url, self.config.timeout)
        except BaseException:
            self._kill()
            raise
        atexit.register(self.close)
        if announce is not None:
            stream = sys.stderr if announce == "stderr" else announce
            print(f"twin viewer: open {self.url}", file=stream, flush=True)

    # ---------------------------------------------------------------- server
    def _start_server(self) -> tuple[subprocess.Popen, str, str]:
        import importlib.util

        from twin.extras import EXTRAS, MissingExtra

        try:  # meshcat brings its viewer page and the server's packages (zmq, tornado, umsgpack)
            found = all(importlib.util.find_spec(m) is not None for m in ("meshcat", "zmq", "tornado", "umsgpack"))
        except (ValueError, AttributeError):  # a module set to None in sys.modules: blocked
            found = False
        if not found:
            raise MissingExtra("meshcat", EXTRAS["meshcat"], "the browser viewer")
        args = [sys.executable, "-m", "twin.viewer.server", "--web-port", str(self.config.web_port),
                "--parent", str(os.getpid())]
        proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                start_new_session=True)
        found: dict[str, str] = {}

        def read_first_line() -> None:
            with contextlib.suppress(Exception):
                found.update(json.loads(proc.stdout.readline().decode("utf-8", "replace")))

        reader = threading.Thread(target=read_first_line, daemon=True)
        reader.start()
        reader.join(timeout=30.0)
        if "zmq_url" not in found:
            proc.kill()
            proc.wait()
            err = proc.stderr.read().decode("utf-8", "replace").strip().splitlines()
            raise ViewerError("the viewer's server did not start" + (f": {err[-1]}" if err else " within 30 s"))
        for stream in (proc.stdout, proc.stderr):  # keep the pipes drained so the server never blocks on them
            threading.Thread(target=_drain, args=(stream,), daemon=True).start()
        return proc, found["zmq_url"], found["web_url"]

    @property
    def server_pid(self) -> int:
        return self._proc.pid

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def broken(self) -> str | None:
        """Why the viewer stopped drawing (server gone or unresponsive), or None."""
        if self._client.broken is None and self._proc.poll() is not None:
            self._client.broken = f"the viewer's server exited (status {self._proc.returncode})"
        return self._client.broken

    @property
    def alive(self) -> bool:
        return not self._closed and self.broken is None

    def _send(self, command: cmd.Command) -> None:
        if not self._closed and self.broken:
            raise ViewerError(self.broken)
        if self._queue is not None:  # inside show(): one request for the whole frame
            self._queue.append(command)
        else:
            self._client.send(command)

    # ---------------------------------------------------------------- drawing
    def ready(self, now: float | None = None) -> bool:
        """Whether :meth:`show` would draw now (the rate limiter's verdict)."""
        return (time.monotonic() if now is None else now) >= self._due

    def show(self, shape: Shape, truth: Truth | None = None, *, base_pose=None, fixture=None,
             label: str | None = None, force: bool = False, reframe: bool = False, vendor=None) -> bool:
        """Draw one reconstruction, with its truth (centreline, errors) and fixture when given.

        Parameters
        ----------
        shape : Shape
            One reconstruction (index a batch first), in the fibre's base frame, m.
        truth : Truth, optional
            The true centreline (world, m); its ``fixture`` is drawn too.
        base_pose : (R (3, 3), p (3,)), optional
            The fibre's base frame in the world; default from the truth (:func:`placement`).
        fixture : array_like (k, 3), optional
            Fixture centreline in the world, m; overrides ``truth.fixture``.
        label : str, optional
            Title of the overlay (e.g. the shape's name); kept until changed.
        force : bool
            Draw even if the rate limiter would skip this frame.
        reframe : bool
            Frame the camera on this shape (the first one is framed anyway).
        vendor : tuple of VendorSensor, or VendorSensor, optional
            The interrogator's own reconstruction of the same frame (:attr:`twin.frames.Frame.vendor`; sensor
            ``config.vendor_sensor`` of a tuple), drawn registered onto ``shape``. Without one, a vendor shape
            drawn before is removed.

        Returns
        -------
        bool
            True when drawn, False when skipped by the rate limiter.

        Raises
        ------
        ValueError
            A batch of shapes, or a shape with NaN points.
        ViewerError
            The viewer is closed or its server is gone.
        """
        now = time.monotonic()
        if not force and not self.ready(now):
            self.frames_skipped += 1
            return False
        self._queue = []
        try:
            self._show(shape, truth, base_pose, fixture, label, reframe, vendor)
            if not self._closed and self.broken:
                raise ViewerError(self.broken)
            self._client.send_many(self._queue)
        finally:
            self._queue = None
        self._due = next_due(self._due, now, 1.0 / self.config.max_fps)
        self.frames_shown += 1
        self._update_hud(now, force=label is not None or self.frames_shown == 1)
        return True

    def _show(self, shape: Shape, truth: Truth | None, base_pose, fixture, label, reframe, vendor) -> None:
        if shape.positions.ndim != 2:
            raise ValueError(f"Viewer.show takes one shape, got a batch of shape {shape.batch_shape}; index it")
        if not np.all(np.isfinite(shape.positions)):
            raise ValueError("Viewer.show: the shape has NaN points (an unusable frame)")
        cfg = self.config
        sc = geo.frame_scene(shape, truth, vendor, base_pose, cfg.vendor_sensor)
        R, world, truth_pts, ok = sc.R, sc.world, sc.truth, sc.truth_ok
        self.placement, self.errors, self._mode = sc.how, sc.errors, sc.mode
        keep = geo.subsample(len(world), cfg.max_rings)
        ring_colors = geo.colormap(sc.values[keep], *(cfg.error_range if sc.mode == "error" else cfg.curvature_range))
        if sc.mode == "error":
            self._profile = _profile(shape.s, sc.values, cfg.profile_points)
            magnified = self._magnified(world[keep], sc.nearest[keep], float(sc.values.max()))
        else:
            self._profile = None
            magnified = None
            self.magnification = None
        if fixture is None and truth is not None:
            fixture = truth.fixture
        vendor_pts, self.vendor_errors = sc.vendor, sc.vendor_errors
        if not self._framed or reframe:
            sensed = np.concatenate([c for c in (world, truth_pts, vendor_pts) if c is not None])
            self._frame(sensed)
        if label is not None:
            self._label = label
        if fixture is not None:
            self._draw_fixture(np.asarray(fixture, dtype=np.float64))
        verts, faces = tube_mesh(world[keep], cfg.radius, cfg.sides, normals=(shape.frames[:, :, 0] @ R.T)[keep])
        self._last = {"verts": verts, "faces": faces, "colors": geo.tube_colors(ring_colors, cfg.sides),
                      "markers": sc.markers}
        self._draw_reconstruction()
        self._draw_confidence(shape, world[keep], (shape.frames[:, :, 0] @ R.T)[keep], keep)
        if truth_pts is not None and len(truth_pts) >= 2:
            tk = geo.subsample(len(truth_pts), cfg.max_rings)
            normals = None if truth.frames is None else np.asarray(truth.frames)[ok][tk, :, 0]
            tv, tf = tube_mesh(truth_pts[tk], cfg.truth_radius, 8, normals=normals)
            # unlit and drawn last without depth test: the truth's own colour, even inside the tube
            mat = cmd.material("MeshBasicMaterial", cfg.truth_color, depthTest=False, transparent=True)
            self._send(cmd.set_object("/twin/truth", cmd.mesh(tv, tf, mat, render_order=10)))
        self._draw_vendor(vendor_pts)
        self._draw_magnified(magnified)

    def _magnified(self, world: np.ndarray, nearest: np.ndarray, max_error: float) -> np.ndarray | None:
        """The reconstruction's deviation from the truth magnified about the truth: each point's nearest truth
        point plus ``factor`` times the way from there to the point (world, m); None when not drawn."""
        cfg = self.config
        factor = cfg.magnify or geo.magnification(max_error, cfg.magnified_deviation)
        self.magnification = factor
        if not cfg.show_magnified or factor <= 1:
            return None
        return nearest + factor * (world - nearest)

    def _draw_magnified(self, points: np.ndarray | None) -> None:
        # over the translucent tube and under the truth: where the two part, the error shows
        self._magnified_shown = self._draw_centreline("/twin/magnified", points, self.config.magnify_color, 8,
                                                      self._magnified_shown)

    def _draw_centreline(self, path: str, points: np.ndarray | None, color: int, render_order: int,
                         shown: bool) -> bool:
        """A thin unlit centreline drawn over the translucent tube at ``path`` (world points, m), or the one
        ``shown`` there deleted when ``points`` is None; returns whether one is shown now."""
        cfg = self.config
        if points is None or len(points) < 2:
            if shown:
                self._send(cmd.delete(path))
            return False
        k = geo.subsample(len(points), cfg.max_rings)
        verts, faces = tube_mesh(points[k], cfg.truth_radius, 8)
        mat = cmd.material("MeshBasicMaterial", color, depthTest=False, transparent=True)
        self._send(cmd.set_object(path, cmd.mesh(verts, faces, mat, render_order=render_order)))
        return True

    def _draw_confidence(self, shape: Shape, points: np.ndarray, normals: np.ndarray, keep: np.ndarray) -> None:
        """The translucent confidence envelope around the tube, or none when the shape has no uncertainty."""
        cfg = self.config
        if shape.covariance is None:
            if self._confidence_shown:
                self._send(cmd.delete("/twin/confidence"))
                self._confidence_shown = False
            return
        radii = geo.envelope(shape, cfg.confidence_level, cfg.radius)[keep]
        verts, faces = tube_mesh(points, radii, cfg.sides, normals=normals)
        mat = cmd.material("MeshPhongMaterial", cfg.confidence_color, opacity=cfg.confidence_opacity,
                           depthWrite=False)
        self._send(cmd.set_object("/twin/confidence", cmd.mesh(verts, faces, mat, render_order=1)))
        self._confidence_shown = True

    def _draw_vendor(self, points: np.ndarray | None) -> None:
        # like the truth: unlit, over the translucent tube (under the truth and the gratings)
        was = self._vendor_shown
        self._vendor_shown = self._draw_centreline("/twin/vendor", points, self.config.vendor_color, 9, was)
        if self._vendor_shown and not was:
            # the object hangs under the node /twin/vendor, whose visibility (the page's scene controls, or
            # show_vendor) therefore survives the next frame's object
            self._send(cmd.set_property("/twin/vendor", "visible", bool(self.config.show_vendor)))

    def _draw_reconstruction(self) -> None:
        if self._last is None:
            return
        cfg = self.config
        colors = self._last["colors"]
        opacity = cfg.shape_opacity
        if self._stale:  # opaque grey: unmistakable (the truth is drawn over it anyway)
            colors, opacity = np.broadcast_to(_rgb(cfg.stale_color), colors.shape), 1.0
        mat = cmd.material("MeshPhongMaterial", 0xFFFFFF, opacity=opacity, vertex_colors=True, side=0,
                           depthWrite=opacity == 1.0)
        self._send(cmd.set_object("/twin/shape", cmd.mesh(self._last["verts"], self._last["faces"], mat, colors)))
        markers = self._last["markers"]
        self._send(cmd.set_object("/twin/gratings", cmd.points(
            markers, np.broadcast_to(_rgb(cfg.marker_color), markers.shape), cfg.marker_size * cfg.scale,
            render_order=11)))

    def _draw_fixture(self, fixture: np.ndarray) -> None:
        if fixture.ndim != 2 or fixture.shape[1] != 3 or len(fixture) < 2:
            raise ValueError(f"fixture must have shape (k >= 2, 3), got {fixture.shape}")
        if self._fixture is not None and self._fixture.shape == fixture.shape and np.array_equal(self._fixture,
                                                                                                  fixture):
            return  # unchanged: not sent again
        cfg = self.config
        ok = np.all(np.isfinite(fixture), axis=1)
        pts = fixture[ok][geo.subsample(int(ok.sum()), cfg.max_rings)]
        verts, faces = tube_mesh(pts, cfg.fixture_radius, cfg.sides)
        mat = cmd.material("MeshPhongMaterial", cfg.fixture_color, opacity=cfg.fixture_opacity, depthWrite=False)
        self._send(cmd.set_object("/twin/fixture", cmd.mesh(verts, faces, mat)))
        self._fixture = fixture.copy()

    def _frame(self, points: np.ndarray) -> None:
        """Centre the scene on ``points`` (world, m), put the camera where it sees them whole, place the scale."""
        cfg = self.config
        c = 0.5 * (points.min(axis=0) + points.max(axis=0))
        x = points - c
        self._centre = c
        self._extent = max(float(np.max(np.linalg.norm(x, axis=1))) + cfg.radius, 10 * cfg.radius)
        s = cfg.scale
        root = np.eye(4)
        root[:3, :3] *= s
        root[:3, 3] = -s * c
        self._send(cmd.set_transform("/twin", root))
        self._send(cmd.set_transform("/Axes", _translation(-s * c)))
        self._send(cmd.set_transform("/Grid", _translation([0.0, 0.0, s * (points[:, 2].min() - c[2])
                                                             - 0.2 * s * self._extent])))
        direction = geo.view_direction(points)
        eye = geo.camera_distance(self._extent * s, CAMERA_FOV_DEG) * direction
        # the scale bar lies below the catheter as seen from the camera, along the screen's horizontal
        up = np.array([0.0, 0.0, 1.0]) - direction[2] * direction
        up /= np.linalg.norm(up)
        right = np.cross(direction, up)
        self._bar_length = geo.nice_length(2 * self._extent)
        below = float(np.min(x @ up)) - 0.12 * self._extent
        start = c + below * up - 0.5 * self._bar_length * right
        bv, bf = geo.scale_bar(start, right, up, self._bar_length, 0.3e-3)
        self._send(cmd.set_object("/twin/scale", cmd.mesh(bv, bf, cmd.material("MeshBasicMaterial", cfg.scale_color))))
        # the camera hangs under /Cameras/default/rotated, turned +90° about x (three.js is y-up): a world
        # offset (x, y, z) is (x, z, −y) there
        self._send(cmd.set_property("/Cameras/default/rotated/<object>", "position",
                                    [float(eye[0]), float(eye[2]), float(-eye[1])]))
        self._camera = eye
        self._framed = True

    def camera(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Camera (eye in scene units relative to the catheter's centre, world centre in m, scale)."""
        return self._camera.copy(), self._centre.copy(), self.config.scale

    # ---------------------------------------------------------------- state and overlay
    def set_state(self, state: str, detail: str = "") -> None:
        """The stream's state: ``stale`` turns the reconstruction grey, anything else restores it."""
        stale = state == "stale"
        changed = state != self._state
        self._state, self._detail = state, detail
        if stale != self._stale:
            self._stale = stale
            self._draw_reconstruction()
        self._update_hud(time.monotonic(), force=changed)

    def set_info(self, **info) -> None:
        """Figures for the overlay: ``arrival_hz`` (frames received per second), ``rate_hz`` (the source's own
        rate), ``lost``, ``frames``, ``calibration`` (None removes one)."""
        for k, v in info.items():
            if v is None:
                self.info.pop(k, None)
            else:
                self.info[k] = v
        self._update_hud(time.monotonic(), force=True)

    def hud(self) -> dict:
        """The overlay's content: title, state, figures, colour bar and legend (what the page shows)."""
        cfg = self.config
        figures: list[list[str]] = []
        if self.errors is not None:
            how = {"kabsch": "after Kabsch registration", "base_pose": "at the given base pose"}.get(
                self.placement or "", "at the true base pose")
            figures += [["error vs truth", how]] + [[f"{k} error", f"{1e3 * self.errors[k]:.3f} mm"]
                                                    for k in ("max", "mean", "tip")]
        if self.vendor_errors is not None:
            figures += [["vs interrogator's shape", "after Kabsch registration"]] + [
                [f"{k} distance", f"{1e3 * self.vendor_errors[k]:.3f} mm"] for k in ("max", "mean")]
        if self.errors is not None and self._magnified_shown:
            figures.append(["magnified view", f"deviation × {self.magnification:g}"])
        if "arrival_hz" in self.info:
            figures.append(["arrival rate", f"{float(self.info['arrival_hz']):.1f} frames/s"])
        if "rate_hz" in self.info:
            figures.append(["source rate", f"{float(self.info['rate_hz']):.1f} Hz"])
        if "lost" in self.info:
            figures.append(["lost frames", f"{int(self.info['lost'])}"])
        if "frames" in self.info:
            figures.append(["frames", f"{int(self.info['frames'])}"])
        figures.append(["calibration", str(self.info.get("calibration", "none"))])
        if self._mode == "error":
            lo, hi = (1e3 * v for v in cfg.error_range)
            bar = {"label": "reconstruction: local error (mm)", "lo": f"{lo:g}", "mid": f"{(lo + hi) / 2:g}",
                   "hi": f"≥ {hi:g}"}
        else:
            lo, hi = cfg.curvature_range
            bar = {"label": "reconstruction: |curvature| (1/m)", "lo": f"{lo:g}", "mid": f"{(lo + hi) / 2:g}",
                   "hi": f"≥ {hi:g}"}
        bar["stops"] = geo.colorbar_stops()
        legend = []
        if self._mode == "error":
            legend.append([_css(cfg.truth_color), "truth (centreline, drawn on top)"])
        if self._mode == "error" and self._magnified_shown:
            legend.append([_css(cfg.magnify_color), f"reconstruction's deviation from the truth × "
                                                    f"{self.magnification:g} (magnified)"])
        if self.vendor_errors is not None:
            legend.append([_css(cfg.vendor_color), "interrogator's own shape (registered onto ours)"])
        legend += [["rgba(120,120,120,0.45)", "reconstruction (translucent tube, 8 Fr)"],
                   [_css(cfg.marker_color), "gratings"]]
        if self._fixture is not None:
            legend.append(["#f4f4f4", "fixture / sheath"])
        legend.append([_css(cfg.stale_color), "grey catheter: stale stream"])
        if self._bar_length:
            legend.append([_css(cfg.scale_color), f"scale bar: {1e3 * self._bar_length:g} mm"])
        loud = self._stale or self._state == "ended"  # the page must not look live when it is not
        state_text = self._state.upper() + (f" ({self._detail})" if self._detail else "") if loud else self._state
        out = {"title": self._label or "catheter-twin", "state": self._state, "state_text": state_text,
               "figures": figures, "colorbar": bar, "legend": legend}
        if self._mode == "error" and self._profile is not None:
            out["profile"] = self._profile
        return out

    def _update_hud(self, now: float, force: bool = False) -> None:
        if not self._framed or (not force and now - self._hud_at < 0.25):
            return
        content = self.hud()
        text = json.dumps(content, sort_keys=True)
        if text == self._hud_text:
            return
        self._client.hud(content)
        self._hud_text, self._hud_at = text, now

    # ---------------------------------------------------------------- output and end
    def save_html(self, path) -> Path:
        """Write the current scene as one self-contained HTML page; returns the path."""
        path = Path(path)
        path.write_text(self._client.static_html(), encoding="utf-8")
        return path

    def close(self) -> None:
        """Stop the server (an open page keeps the last picture) and release the socket. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            atexit.unregister(self.close)
        self._client.close()
        self._kill()

    def _kill(self) -> None:
        if self._proc.poll() is None:
            self._proc.kill()
        with contextlib.suppress(Exception):
            self._proc.wait(timeout=10)

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _drain(stream) -> None:
    with contextlib.suppress(Exception):
        while stream.read(4096):
            pass


def _profile(s: np.ndarray, error: np.ndarray, most: int) -> dict:
    """The error-along-the-catheter plot's data for the page: at most ``most`` points (each the largest error
    of its stretch of the catheter, at the stretch's middle, so no peak is lost), mm, with round axis ends."""
    edges = np.linspace(0, len(s), min(most, len(s)) + 1).astype(int)
    peak = np.maximum.reduceat(error, edges[:-1])
    s_mm, e_mm = 1e3 * np.asarray(s)[(edges[:-1] + edges[1:] - 1) // 2], 1e3 * peak
    return {"s": np.round(s_mm, 2).tolist(), "e": np.round(e_mm, 4).tolist(),
            "s_max": round(float(1e3 * s[-1]), 2), "e_max": geo.nice_ceiling(float(e_mm.max()) * 1.05 or 1e-3),
            "label": "local error (mm) along the catheter (mm)"}


def _translation(v) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = v
    return m


def keep_open(viewer: Viewer, stream: TextIO | None = None, poll: float = 0.5) -> None:
    """Keep the viewer's server running until Ctrl-C (or until the server is gone), then close it.

    For ``--keep-open`` and the demo: the run has ended, the page stays live for a browser opened late.
    """
    out = stream or sys.stderr
    if viewer.alive:
        print(f"twin viewer: still serving {viewer.url} — press Ctrl-C to quit", file=out, flush=True)
        try:
            while viewer.alive:
                time.sleep(poll)
        except KeyboardInterrupt:
            print(file=out)
    viewer.close()

