"""The meshcat viewer: scene content (tube geometry, grating colours, truth, fixture), placement, the rate
limiter, stale display, clean shutdown (no server left behind, no hang on a dead or frozen server), the live
sink and the command-line flags — and a real browser (Debian's headless chromium) rendering the live page and
the static export, checked pixel by pixel.

No timing asserts (speed lives in `twin bench`); waits are generous and only outcomes are checked. Every
viewer is closed by a fixture finalizer, which also checks that its server process is gone.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import types

import numpy as np
import pytest

from twin import Reconstructor
from twin.frames import Frame, Shape, Truth
from twin.io.synthetic import SyntheticSource
from twin.live import LiveLoop, LiveStatus
from twin.viewer import (
    CAMERA_FOV_DEG,
    Viewer,
    ViewerConfig,
    ViewerError,
    ViewerSink,
    _colormap_lut,
    curvature_colors,
    placement,
    tube_mesh,
)

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg", "PYTHONUNBUFFERED": "1"}
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


# ------------------------------------------------------------------------------------------------ helpers
def arc(kappa: float = 20.0, length: float = 0.17, n: int = 171, gratings: int = 18, k_max: float = 60.0) -> Shape:
    """A planar arc in the base frame (tangent +z at the base, bending towards +x = d1), with grating
    curvatures ramping from 0 to ``k_max`` (not the arc's: distinct marker colours along the catheter)."""
    s = np.linspace(0.0, length, n)
    c, sn = np.cos(kappa * s), np.sin(kappa * s)
    pos = np.stack([(1 - c) / kappa, 0 * s, sn / kappa], -1)
    d1 = np.stack([c, 0 * s, -sn], -1)
    d2 = np.tile([0.0, 1.0, 0.0], (n, 1))
    d3 = np.stack([sn, 0 * s, c], -1)
    gs = np.linspace(0.005, length - 0.005, gratings)
    k = np.stack([np.linspace(0.0, k_max, gratings), np.zeros(gratings)], -1)
    return Shape(s=s, positions=pos, frames=np.stack([d1, d2, d3], -1), curvature=k, grating_s=gs,
                 valid=np.ones(gratings, bool))


#: a base pose that stands the arc in a tilted vertical plane away from the origin
POSE_R = np.array([[0.0, -0.6, 0.8], [0.0, 0.8, 0.6], [-1.0, 0.0, 0.0]]).T @ np.array(
    [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
POSE_P = np.array([0.10, -0.05, 0.30])


def truth_of(shape: Shape, R=POSE_R, p=POSE_P, fixture: bool = True) -> Truth:
    world = shape.positions @ R.T + p
    return Truth(s=shape.s, positions=world, frames=R @ shape.frames,
                 fixture=world.copy() if fixture else None)


class Spy:
    """Records the commands the viewer sends to its server: (type, path, command)."""

    def __init__(self, viewer: Viewer):
        self.sent: list[tuple[str, str, object]] = []
        window = viewer.vis.window
        original = window.send

        def send(command):
            self.sent.append((type(command).__name__, command.path.lower(), command))
            return original(command)

        window.send = send

    def objects(self, path: str) -> list:
        return [c.object for kind, p, c in self.sent if kind == "SetObject" and p == path]

    def clear(self) -> None:
        self.sent.clear()


def gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


@pytest.fixture
def make_viewer():
    """Viewer factory; every viewer is closed at the end and its server checked gone."""
    made: list[Viewer] = []

    def make(**config) -> Viewer:
        v = Viewer(ViewerConfig(**config), announce=None)
        made.append(v)
        return v

    yield make
    for v in made:
        v.close()
        assert gone(v.server_pid), f"meshcat server {v.server_pid} still running"


# ------------------------------------------------------------------------------------------------ geometry
def test_tube_mesh_is_a_closed_tube_of_the_radius_with_outward_faces():
    shape = arc()
    pts, r, sides = shape.positions, 1.3e-3, 12
    verts, faces = tube_mesh(pts, r, sides, normals=shape.frames[:, :, 0])
    n = len(pts)
    assert verts.shape == (n * sides + 2 * (sides + 1), 3)
    assert faces.shape == (2 * (n - 1) * sides + 2 * sides, 3) and faces.max() < len(verts)
    rings = verts[: n * sides].reshape(n, sides, 3)
    # every ring vertex lies at the radius from its centreline point, in the normal plane (float64: 1e-12 m)
    off = rings - pts[:, None, :]
    np.testing.assert_allclose(np.linalg.norm(off, axis=-1), r, rtol=1e-9)
    # in the plane normal to the centreline's chord tangent: exactly the material frame's inside (central
    # differences, O(h²κ²) ≈ 1e-4 rad), within h·κ/2 = 0.01 rad at the one-sided ends
    along = np.abs(np.einsum("nsk,nk->ns", off, shape.frames[:, :, 2])) / r
    assert along[1:-1].max() < 2e-4 and along.max() < 0.011
    # side faces point away from the centreline (outward winding: lit correctly with one-sided materials)
    tri = verts[faces[: 2 * (n - 1) * sides]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centre = tri.mean(axis=1)
    nearest = pts[np.argmin(np.linalg.norm(centre[:, None] - pts[None], axis=-1), axis=1)]
    assert np.all(np.einsum("fk,fk->f", normal, centre - nearest) > 0)
    # without frames: rotation-minimising frames give the same tube surface (rings may turn about the axis)
    v2, _ = tube_mesh(pts, r, sides)
    off2 = v2[: n * sides].reshape(n, sides, 3) - pts[:, None, :]
    np.testing.assert_allclose(np.linalg.norm(off2, axis=-1), r, rtol=1e-9)


def test_tube_mesh_rejects_bad_input():
    with pytest.raises(ValueError, match="shape"):
        tube_mesh(np.zeros((1, 3)), 1e-3)
    with pytest.raises(ValueError, match="NaN"):
        tube_mesh(np.full((3, 3), np.nan), 1e-3)


def test_curvature_colours_follow_the_colormap_and_grey_out_invalid_gratings():
    lut = _colormap_lut("viridis")
    k = np.array([[0.0, 0.0], [35.0, 0.0], [0.0, -70.0], [200.0, 0.0], [np.nan, np.nan], [10.0, 0.0]])
    valid = np.array([True, True, True, True, False, False])
    rgb = curvature_colors(k, valid, (0.0, 70.0), "viridis")
    np.testing.assert_allclose(rgb[0], lut[0])
    np.testing.assert_allclose(rgb[1], lut[128], atol=1e-12)  # |k| = 35 of 70: the middle entry (rounded)
    np.testing.assert_allclose(rgb[2], lut[-1])  # the norm of the vector, not a component
    np.testing.assert_allclose(rgb[3], lut[-1])  # clipped
    np.testing.assert_allclose(rgb[4:], 0.5)  # unsolved gratings are grey


def test_placement_uses_the_given_pose_then_the_truth_base_then_kabsch():
    shape = arc()
    truth = truth_of(shape)
    R, p, how = placement(shape, truth)
    assert how == "truth_base"
    np.testing.assert_allclose(shape.positions @ R.T + p, truth.positions, atol=1e-12)
    R, p, how = placement(shape, Truth(s=truth.s, positions=truth.positions))  # no frames: register
    assert how == "kabsch"
    np.testing.assert_allclose(shape.positions @ R.T + p, truth.positions, atol=1e-9)
    R, p, how = placement(shape, truth, base_pose=(np.eye(3), np.ones(3)))
    assert how == "base_pose" and np.array_equal(p, np.ones(3))
    assert placement(shape)[2] == "base_frame"
    with pytest.raises(ValueError, match="base_pose"):
        placement(shape, base_pose=(np.eye(2), np.zeros(3)))


# ------------------------------------------------------------------------------------------------ the scene
def test_scene_content_tube_markers_truth_fixture(make_viewer):
    v = make_viewer(max_fps=float("inf"))
    spy = Spy(v)
    shape = arc()
    truth = truth_of(shape)
    assert v.show(shape, truth, label="arc")
    cfg = v.config
    # one mesh message for the reconstruction, with the catheter's radius around the placed centreline
    (mesh,) = spy.objects("/twin/shape")
    verts = mesh.geometry.vertices.astype(np.float64)
    n = len(shape.s)
    assert verts.shape == (n * cfg.sides + 2 * (cfg.sides + 1), 3)
    rings = verts[: n * cfg.sides].reshape(n, cfg.sides, 3)
    # float32 on the wire: ~1e-7 relative of ~0.3 m coordinates, so 1e-7 m on the radius
    np.testing.assert_allclose(np.linalg.norm(rings - truth.positions[:, None], axis=-1), cfg.radius, atol=2e-7)
    assert mesh.material.color == cfg.shape_color
    # one points message: a marker per grating, coloured by |curvature|
    (points,) = spy.objects("/twin/gratings")
    pos = np.asarray(points.geometry.position, dtype=np.float64).T
    assert pos.shape == (len(shape.grating_s), 3)
    expected = np.stack([np.interp(shape.grating_s, truth.s, truth.positions[:, k]) for k in range(3)], -1)
    np.testing.assert_allclose(pos, expected, atol=1e-6)  # linear interpolation on 1 mm points, float32
    colors = np.asarray(points.geometry.color, dtype=np.float64).T
    np.testing.assert_allclose(colors, curvature_colors(shape.curvature, shape.valid, cfg.curvature_range),
                               atol=1e-6)
    assert colors[0, 2] > colors[0, 1] and colors[-1, 1] > colors[-1, 2]  # viridis: purple to yellow
    # truth as a thinner tube of its own colour; the fixture faint and translucent
    (tr,) = spy.objects("/twin/truth")
    assert tr.material.color == cfg.truth_color
    tv = tr.geometry.vertices.astype(np.float64)
    assert np.linalg.norm(tv[0] - truth.positions[0]) == pytest.approx(cfg.truth_radius, abs=1e-7)
    (fx,) = spy.objects("/twin/fixture")
    assert fx.material.opacity == cfg.fixture_opacity < 0.5 and fx.material.transparent
    # the label, and the root node that centres and scales the scene
    assert len(spy.objects("/label")) == 1
    roots = [c for kind, p, c in spy.sent if kind == "SetTransform" and p == "/twin"]
    assert roots and roots[-1].matrix[0, 0] == cfg.scale

    # the next frame: the reconstruction and truth again, one message each; the unchanged fixture and
    # label are not sent again, and the camera is not moved
    spy.clear()
    assert v.show(shape, truth)
    paths = [p for kind, p, _ in spy.sent]
    assert sorted(paths) == ["/twin/gratings", "/twin/shape", "/twin/truth"]
    # a new fixture is sent
    moved = Truth(s=truth.s, positions=truth.positions, frames=truth.frames, fixture=truth.fixture + 0.001)
    spy.clear()
    v.show(shape, moved)
    assert len(spy.objects("/twin/fixture")) == 1


def test_exaggerate_scales_the_deviation_from_the_truth(make_viewer):
    v = make_viewer(max_fps=float("inf"), exaggerate=10.0)
    spy = Spy(v)
    shape = arc()
    truth = truth_of(shape)
    bent = Truth(s=truth.s, positions=truth.positions + np.array([0.0, 0.0, 1e-4]), frames=truth.frames)  # 0.1 mm off
    v.show(shape, bent, base_pose=(POSE_R, POSE_P))
    (mesh,) = spy.objects("/twin/shape")
    centre = mesh.geometry.vertices[: v.config.sides].astype(np.float64).mean(axis=0)  # first ring's centre
    np.testing.assert_allclose(centre, bent.positions[0] - 10 * np.array([0.0, 0.0, 1e-4]), atol=1e-6)


def test_rate_limiter_drops_frames_sooner_than_max_fps(make_viewer):
    v = make_viewer(max_fps=20.0)
    shape = arc()
    assert v.show(shape)
    assert not v.ready() and not v.show(shape)  # within 50 ms of the last
    assert v.frames_skipped == 1 and v.frames_shown == 1
    assert v.show(shape, force=True)
    time.sleep(0.12)
    assert v.ready() and v.show(shape)
    assert v.frames_shown == 3
    with pytest.raises(ValueError, match="batch"):
        v.show(Shape(s=shape.s, positions=shape.positions[None], frames=shape.frames[None],
                     curvature=shape.curvature[None], grating_s=shape.grating_s, valid=shape.valid[None]),
               force=True)


def test_stale_state_greys_the_catheter_and_labels_it(make_viewer):
    v = make_viewer()
    spy = Spy(v)
    v.show(arc(), label="arc")
    spy.clear()
    v.set_state("stale", "no data for 2 s")
    (mesh,) = spy.objects("/twin/shape")
    assert mesh.material.color == v.config.stale_color
    (points,) = spy.objects("/twin/gratings")
    assert np.allclose(np.asarray(points.geometry.color).T, (0x8C / 255,) * 3, atol=1e-6)
    assert len(spy.objects("/label")) == 1  # label redrawn: "arc · STALE (no data for 2 s)"
    spy.clear()
    v.set_state("stale", "no data for 2 s")  # nothing changed: nothing sent
    assert spy.sent == []
    v.set_state("live")
    (mesh,) = spy.objects("/twin/shape")
    assert mesh.material.color == v.config.shape_color


def test_save_html_is_a_self_contained_page(make_viewer, tmp_path):
    v = make_viewer()
    v.show(arc(), label="arc")
    page = v.save_html(tmp_path / "scene.html").read_text()
    assert "MeshCat.Viewer" in page and "octet-binary;base64" in page and "http" not in page.split("<script>")[0]


# ------------------------------------------------------------------------------------------------ shutdown
def test_close_kills_the_server_and_later_calls_fail_cleanly(make_viewer):
    v = make_viewer()
    pid = v.server_pid
    v.show(arc())
    v.close()
    assert gone(pid) and v.closed
    v.close()  # idempotent
    with pytest.raises(ViewerError, match="closed"):
        v.show(arc(), force=True)


def test_a_dead_or_frozen_server_raises_instead_of_hanging(make_viewer):
    v = make_viewer()
    os.kill(v.server_pid, signal.SIGKILL)
    v._proc.wait(timeout=10)
    with pytest.raises(ViewerError, match="exited"):
        v.show(arc())
    assert v.broken

    frozen = make_viewer(timeout=0.5)
    os.kill(frozen.server_pid, signal.SIGSTOP)
    try:
        t0 = time.monotonic()
        with pytest.raises(ViewerError, match="did not answer"):
            frozen.show(arc())
        assert time.monotonic() - t0 < 30  # bounded by the 0.5 s timeout (generous: no timing assert)
        with pytest.raises(ViewerError):  # given up on: no second wait
            frozen.show(arc(), force=True)
    finally:
        os.kill(frozen.server_pid, signal.SIGCONT)


# ------------------------------------------------------------------------------------------------ live sink
def status(state: str = "live", n: int = 0, age: float = 0.0) -> LiveStatus:
    return LiveStatus(state=state, flags=np.zeros(n, np.uint8), last_valid_age=age)


def test_sink_draws_the_latest_usable_frame_keeps_a_dropped_one_and_greys_when_stale(make_viewer):
    v = make_viewer(max_fps=float("inf"))
    spy = Spy(v)
    sink = ViewerSink(v, rate=1000.0, close_viewer=False)
    one = arc()
    two = arc(kappa=10.0)
    batch = Shape(s=one.s, positions=np.stack([one.positions, two.positions, np.full_like(one.positions, np.nan)]),
                  frames=np.stack([one.frames, two.frames, one.frames]), curvature=np.stack([one.curvature] * 3),
                  grating_s=one.grating_s, valid=np.ones((3, 18), bool))
    w = np.zeros((18, 4))
    truth = truth_of(two)
    frames = [Frame(w), Frame(w, truth=truth), Frame(w)]  # the last one unusable (NaN shape)
    flags = np.array([0, 0, 4], np.uint8)
    sink(frames, batch, LiveStatus(state="live", flags=flags))
    assert sink.frames_shown == 1 and v.placement == "truth_base"  # frame 1, drawn with its truth
    (mesh,) = spy.objects("/twin/shape")
    assert np.allclose(mesh.geometry.vertices[: v.config.sides].mean(axis=0), truth.positions[0], atol=1e-6)
    # a frame arriving within the sink's period is kept and drawn at the next heartbeat
    sink.period = 0.2
    sink._due = time.monotonic() + 0.1
    sink(frames[:1], batch[:1], status(n=1))
    assert sink.frames_shown == 1
    time.sleep(0.15)
    sink([], None, status())
    assert sink.frames_shown == 2
    spy.clear()
    sink([], None, status("stale", age=1.0))
    assert spy.objects("/twin/shape")[0].material.color == v.config.stale_color
    assert sink.errors == 0


def test_sink_never_raises_and_counts_errors(make_viewer):
    v = make_viewer()
    report = io.StringIO()
    sink = ViewerSink(v, close_viewer=True, stream=report)
    os.kill(v.server_pid, signal.SIGKILL)
    v._proc.wait(timeout=10)
    shapes = Shape(s=arc().s, positions=arc().positions[None], frames=arc().frames[None],
                   curvature=arc().curvature[None], grating_s=arc().grating_s, valid=np.ones((1, 18), bool))
    sink([Frame(np.zeros((18, 4)))], shapes, status(n=1))  # the server is gone: counted, not raised
    sink([Frame(np.zeros((18, 4)))], shapes, status(n=1))  # a broken viewer is left alone
    assert sink.errors == 1 and "exited" in sink.last_error
    assert report.getvalue().count("viewer:") == 1  # reported once, on stderr in the live command
    sink.close()
    assert v.closed


def test_sink_in_the_live_loop_at_1_khz_draws_at_most_its_rate(make_viewer):
    v = make_viewer()
    sink = ViewerSink(v, rate=30.0)
    src = SyntheticSource(rate=1000, pace=True)
    summary = LiveLoop(src, Reconstructor(src.fiber), [sink]).run(duration=1.5, handle_signals=False)
    assert summary.sink_errors == () and sink.errors == 0
    assert summary.status.frames > 500
    # the limiter's contract (an upper bound, not a speed goal): one frame per 1/30 s slot, plus the first
    assert 1 <= sink.frames_shown <= 30 * summary.duration + 2
    assert v.placement == "truth_base"  # the synthetic source carries truth with frames
    assert v.closed and gone(v.server_pid)  # the loop closed the sink, which closed the viewer


# ------------------------------------------------------------------------------------------------ command line
def test_take_viewer_options_anywhere_among_the_scenario_options():
    from twin.cli.run import take_viewer_options

    assert take_viewer_options(["--shapes", "arc", "--viewer", "--json"]) == (["--shapes", "arc", "--json"],
                                                                             True, None)
    assert take_viewer_options(["--viewer-rate", "12", "-x"]) == (["-x"], True, 12.0)
    assert take_viewer_options(["--viewer-rate=5"]) == ([], True, 5.0)
    assert take_viewer_options(["--json"]) == (["--json"], False, None)
    assert take_viewer_options(["--", "--viewer"]) == (["--", "--viewer"], False, None)
    for bad in (["--viewer-rate"], ["--viewer-rate", "fast"], ["--viewer-rate", "0"]):
        with pytest.raises(ValueError, match="viewer-rate"):
            take_viewer_options(bad)


def test_twin_run_passes_a_viewer_to_the_scenario(monkeypatch, capsys):
    """`twin run NAME --viewer`: the scenario gets ``args.viewer`` (None without the flag), its parser never
    sees the flag, and the viewer is closed when the scenario returns."""
    from twin import cli

    seen = {}
    probe = types.ModuleType("_viewer_probe")
    probe.__doc__ = "probe"
    probe.add_arguments = lambda parser: parser.add_argument("--n", type=int, default=0)

    def run(args):
        seen["viewer"], seen["n"] = args.viewer, args.n
        if args.viewer is not None:
            seen["pid"] = args.viewer.server_pid
            args.viewer.show(arc(), label="probe")
        return 0

    probe.run = run
    monkeypatch.setitem(sys.modules, "_viewer_probe", probe)
    from twin import registry

    registry.register("twin.scenarios", "viewer-probe", "_viewer_probe")
    assert cli.main(["run", "viewer-probe", "--n", "3", "--viewer", "--viewer-rate", "10"]) == 0
    v = seen["viewer"]
    assert isinstance(v, Viewer) and v.config.max_fps == 10.0 and seen["n"] == 3
    assert v.closed and gone(seen["pid"])
    assert "twin viewer: open http://127.0.0.1:" in capsys.readouterr().err
    assert cli.main(["run", "--viewer", "viewer-probe"]) == 0 and seen["viewer"].closed
    assert cli.main(["run", "viewer-probe"]) == 0 and seen["viewer"] is None
    registry.unregister("twin.scenarios", "viewer-probe")


def test_twin_live_viewer_flag():
    out = subprocess.run([*TWIN, "live", "synthetic://?rate=1000", "--viewer", "--duration", "1.5", "--json",
                          "--quiet"], capture_output=True, text=True, timeout=120, env=ENV)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)  # the viewer prints nothing on stdout: --json stays parseable
    assert summary["viewer_frames"] >= 1 and summary["viewer_errors"] == 0
    assert "twin viewer: open http://127.0.0.1:" in out.stderr


# ------------------------------------------------------------------------------------------------ a real browser
CHROMIUM_FLAGS = [
    "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
    "--force-device-scale-factor=1", "--hide-scrollbars", "--window-size=800,600", "--virtual-time-budget=3000",
]
W, H = 800, 600


def screenshot(url: str, tmp_path, name: str) -> np.ndarray:
    """Render ``url`` in headless chromium; RGB (H, W, 3) floats in [0, 1]."""
    import matplotlib.image

    out = tmp_path / f"{name}.png"
    profile = tmp_path / f"profile-{name}"
    run = subprocess.run([CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--screenshot={out}", url],
                         capture_output=True, text=True, timeout=90)
    assert run.returncode == 0 and out.exists(), run.stderr[-2000:]
    img = matplotlib.image.imread(out)[..., :3]
    assert img.shape == (H, W, 3)
    return img


def project(viewer: Viewer, world: np.ndarray) -> np.ndarray:
    """Pixel coordinates (n, 2) of world points (m) in the browser's 800×600 view: meshcat's perspective
    camera (vertical fov 75°) at the framed eye, looking at the scene origin (the catheter's centre), +z up."""
    eye, centre, scale = viewer.camera()
    q = scale * (world - centre)
    f = -eye / np.linalg.norm(eye)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    d = q - eye
    x, y, z = d @ r, d @ u, d @ f
    t = np.tan(np.radians(CAMERA_FOV_DEG) / 2)
    return np.stack([(x / (z * t * W / H) + 1) / 2 * W, (1 - y / (z * t)) / 2 * H], -1)


def orange(img: np.ndarray) -> np.ndarray:
    """Pixels of the catheter's orange (0xFF7F0E under Phong lighting): red-dominant, green about half, no
    blue. The sky-blue background, grey grid, green truth and viridis markers all fail it."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 0.35) & (g > 0.25 * r) & (g < 0.75 * r) & (b < 0.35 * r)


def grey(img: np.ndarray) -> np.ndarray:
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (np.abs(r - g) < 0.06) & (np.abs(g - b) < 0.06) & (r > 0.2) & (r < 0.85)


def near(mask: np.ndarray, px: np.ndarray, radius: int = 4) -> np.ndarray:
    """For each pixel position, whether ``mask`` has a pixel within ``radius`` (a square window)."""
    out = []
    for x, y in np.rint(px).astype(int):
        win = mask[max(0, y - radius): y + radius + 1, max(0, x - radius): x + radius + 1]
        out.append(bool(win.any()))
    return np.array(out)


def distance_to_polyline(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(np.einsum("pik,ik->pi", points[:, None] - a[None], ab) / np.einsum("ik,ik->i", ab, ab), 0, 1)
    closest = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(points[:, None] - closest, axis=-1), axis=1)


@pytest.mark.timeout(300)
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (.ci/run installs Debian's chromium)")
def test_browser_renders_the_catheter_where_it_is_and_greys_it_when_stale(make_viewer, tmp_path):
    """Headless chromium (software WebGL) renders the live page; the orange catheter must be drawn along
    the projected centreline, fill the view, carry the markers' colours, and turn grey when stale."""
    v = make_viewer()
    shape = arc()
    v.show(shape, base_pose=(POSE_R, POSE_P), label="arc R50")
    world = shape.positions @ POSE_R.T + POSE_P
    px = project(v, world)
    assert np.all((px > 0) & (px < [W, H]))  # the framing keeps the whole catheter in view

    img = screenshot(v.url, tmp_path, "live")
    mask = orange(img)
    if not mask.any():  # a slow first start of chromium may shoot before the scene arrives: once more
        img = screenshot(v.url, tmp_path, "live-again")
        mask = orange(img)
    # along the catheter: orange within 4 px of ≥ 90 % of the projected centreline samples (the rest may be
    # covered by the grating markers, drawn on top)
    assert near(mask, px).mean() >= 0.9
    # and nowhere else: ≥ 97 % of the orange pixels lie within the projected tube (+ 4 px of antialiasing)
    ys, xs = np.nonzero(mask)
    half_width = v.config.radius * H / (2 * np.tan(np.radians(CAMERA_FOV_DEG) / 2) * np.linalg.norm(
        v.camera()[0]) / v.config.scale) + 4
    far = distance_to_polyline(np.stack([xs, ys], -1).astype(float), px) > half_width + 2
    assert far.mean() <= 0.03
    # the camera frames the catheter: it spans a good part of the picture
    assert (xs.max() - xs.min()) > 0.3 * W or (ys.max() - ys.min()) > 0.45 * H
    # markers: unlit, drawn on top, so the pixel at the last grating is the colormap's end (|k| = 60 of 70)
    g_px = project(v, np.stack([np.interp(shape.grating_s, shape.s, world[:, k]) for k in range(3)], -1))
    expected = curvature_colors(shape.curvature, shape.valid, v.config.curvature_range)
    for i in (0, len(g_px) - 1):
        x, y = np.rint(g_px[i]).astype(int)
        patch = img[y - 1: y + 2, x - 1: x + 2].reshape(-1, 3)
        assert np.min(np.abs(patch - expected[i]).max(axis=1)) < 0.08, (i, patch, expected[i])

    v.set_state("stale", "no data for 2 s")
    stale = screenshot(v.url, tmp_path, "stale")
    on_line = near(orange(stale), px)
    assert on_line.mean() <= 0.05  # the orange is gone…
    assert near(grey(stale), px).mean() >= 0.9  # …and the catheter is grey where it was


@pytest.mark.timeout(300)
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (.ci/run installs Debian's chromium)")
def test_browser_renders_the_static_export(make_viewer, tmp_path):
    v = make_viewer()
    shape = arc(kappa=12.0)
    truth = truth_of(shape)
    v.show(shape, truth, label="export")
    page = v.save_html(tmp_path / "scene.html")
    px = project(v, truth.positions)
    v.close()  # the page must not need the server
    img = screenshot(page.as_uri(), tmp_path, "static")
    assert near(orange(img), px).mean() >= 0.9
