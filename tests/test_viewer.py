"""The browser viewer: its numpy geometry (without meshcat), meshcat's command format, the scene server run as
``python -m twin.viewer.server`` (loopback only, meshcat's own client understood, browsers fed over the
websocket), the Viewer (error colours, the truth on top, overlay figures, rate limiter, stale display, clean
shutdown, never a hang), the interrogator's own shape (registered as its reported distance is, toggled), the
live sink, the command-line flags — and a real browser (Debian's headless chromium) rendering the live page and
the static export, checked pixel by pixel.

No timing asserts (speed lives in `twin bench`); waits are generous and only outcomes are checked. Every
viewer is closed by a fixture finalizer, which also checks that its server process is gone.
"""

from __future__ import annotations

import asyncio
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import types
import urllib.request

import numpy as np
import pytest
from conftest import require_tool
from io_helpers import wait_until

from twin import Reconstructor
from twin.frames import Frame, Shape, Truth
from twin.io.illumisense import VendorSensor
from twin.io.illumisense.vendor import VENDOR_FROM_BASE
from twin.live import LiveLoop, LiveStatus, latest_usable
from twin.reference_errors import vendor_distance
from twin.synthetic import SyntheticSource
from twin.viewer import CAMERA_FOV_DEG, Viewer, ViewerConfig, ViewerError, ViewerSink, keep_open
from twin.viewer import commands as cmd
from twin.viewer import geometry as geo

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg", "PYTHONUNBUFFERED": "1"}
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


# ------------------------------------------------------------------------------------------------ helpers
def arc(kappa: float = 20.0, length: float = 0.17, n: int = 171, gratings: int = 18, k_max: float = 60.0) -> Shape:
    """A planar arc in the base frame (tangent +z at the base, bending towards +x = d1), with grating
    curvatures ramping from 0 to ``k_max``."""
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


def truth_of(shape: Shape, R=POSE_R, p=POSE_P, fixture: bool = True, offset: float = 0.0) -> Truth:
    """The shape placed at (R, p); with ``offset`` (m), the truth's points except the base moved along the
    base's d2 (normal to the arc's plane), so the reconstruction placed at the base is ``offset`` off."""
    world = shape.positions @ R.T + p
    moved = world + offset * (shape.s > 0)[:, None] * R[:, 1]
    return Truth(s=shape.s, positions=moved, frames=R @ shape.frames, fixture=world.copy() if fixture else None)


def vendor_of(shape: Shape, kappa: float = 21.0) -> VendorSensor:
    """The interrogator's shape of the same fibre, bent a little more (``kappa`` 1/m instead of the arc's 20),
    as ILLumiSense sends it: 1 mm points in the vendor frame, moved away from ours."""
    other = arc(kappa=kappa)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    pts = other.positions @ VENDOR_FROM_BASE.T @ R.T + [0.3, -0.2, 0.1]
    k = np.hypot(*other.curvature.T)
    return VendorSensor(k, np.zeros_like(k), pts)


def centreline(obj: dict, sides: int = 8) -> np.ndarray:
    """The centre of each ring of a tube mesh sent by the viewer (n, 3)."""
    verts = attribute(obj, "position")
    n = (len(verts) - 2 * (sides + 1)) // sides
    return verts[: n * sides].reshape(n, sides, 3).mean(axis=1)


class Spy:
    """Records the commands the viewer sends to its server, decoded: (type, path, command dict)."""

    def __init__(self, viewer: Viewer):
        import umsgpack

        self.sent: list[tuple[str, str, dict]] = []
        client = viewer._client  # our own client: wrap its sends
        send, send_many = client.send, client.send_many

        def record(command):
            kind, path, data = command
            self.sent.append((kind, path, umsgpack.unpackb(data)))

        def spy_send(command):
            record(command)
            return send(command)

        def spy_send_many(commands):
            for c in commands:
                record(c)
            return send_many(commands)

        client.send, client.send_many = spy_send, spy_send_many

    def objects(self, path: str) -> list[dict]:
        return [c["object"] for kind, p, c in self.sent if kind == "set_object" and p == path]

    def clear(self) -> None:
        self.sent.clear()


def attribute(obj: dict, name: str) -> np.ndarray:
    """A geometry attribute of a decoded object as (n, itemSize) floats."""
    a = obj["geometries"][0]["data"]["attributes"][name]
    return np.frombuffer(a["array"].data, dtype=np.float32).reshape(-1, a["itemSize"]).astype(np.float64)


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
        v = Viewer(ViewerConfig(**{"web_port": 0, **config}), announce=None)
        made.append(v)
        return v

    yield make
    for v in made:
        v.close()
        assert gone(v.server_pid), f"viewer server {v.server_pid} still running"


# ------------------------------------------------------------------------------------------------ geometry
def test_geometry_and_the_viewer_import_without_meshcat_zmq_tornado():
    code = ("import sys\n"
            "for m in ('meshcat', 'zmq', 'tornado', 'umsgpack', 'matplotlib'): sys.modules[m] = None\n"
            "import numpy as np\n"
            "from twin.viewer import geometry as geo, Viewer\n"
            "import twin.igtl\n"
            "v, f = geo.tube_mesh(np.array([[0, 0, 0], [0, 0, 1.0]]), 0.1, 6)\n"
            "assert v.shape == (26, 3) and f.shape == (24, 3)\n"
            "try:\n    Viewer()\nexcept ImportError as e:\n    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=ENV)
    assert out.returncode == 0, out.stderr
    assert "the browser viewer needs the 'viewer' extra" in out.stdout  # one line naming the extra


def test_tube_mesh_is_a_closed_tube_of_the_radius_with_outward_faces():
    shape = arc()
    pts, r, sides = shape.positions, 1.3e-3, 12
    verts, faces = geo.tube_mesh(pts, r, sides, normals=shape.frames[:, :, 0])
    n = len(pts)
    assert verts.shape == (n * sides + 2 * (sides + 1), 3)
    assert faces.shape == (2 * (n - 1) * sides + 2 * sides, 3) and faces.max() < len(verts)
    rings = verts[: n * sides].reshape(n, sides, 3)
    off = rings - pts[:, None, :]
    np.testing.assert_allclose(np.linalg.norm(off, axis=-1), r, rtol=1e-9)
    # in the plane normal to the centreline (central differences: O(h²κ²) ≈ 1e-4 rad; h·κ/2 at the ends)
    along = np.abs(np.einsum("nsk,nk->ns", off, shape.frames[:, :, 2])) / r
    assert along[1:-1].max() < 2e-4 and along.max() < 0.011
    tri = verts[faces[: 2 * (n - 1) * sides]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centre = tri.mean(axis=1)
    nearest = pts[np.argmin(np.linalg.norm(centre[:, None] - pts[None], axis=-1), axis=1)]
    assert np.all(np.einsum("fk,fk->f", normal, centre - nearest) > 0)  # outward winding
    v2, _ = geo.tube_mesh(pts, r, sides)  # rotation-minimising frames: the same surface
    off2 = v2[: n * sides].reshape(n, sides, 3) - pts[:, None, :]
    np.testing.assert_allclose(np.linalg.norm(off2, axis=-1), r, rtol=1e-9)
    colors = geo.tube_colors(np.arange(n * 3, dtype=float).reshape(n, 3), sides)
    assert colors.shape == verts.shape and np.array_equal(colors[sides], [3.0, 4.0, 5.0])  # ring 1
    assert np.array_equal(colors[-1], [3 * n - 3, 3 * n - 2, 3 * n - 1])  # end cap: the last ring's colour


def with_covariance(shape: Shape, sigma_tip: float = 1e-4) -> Shape:
    """``shape`` with an isotropic lateral covariance σ(s)² (I − t tᵀ), σ growing linearly to ``sigma_tip``."""
    t = shape.frames[..., :, 2]
    sig = sigma_tip * shape.s / shape.s[-1]
    cov = sig[:, None, None] ** 2 * (np.eye(3) - t[..., :, None] * t[..., None, :])
    return Shape(s=shape.s, positions=shape.positions, frames=shape.frames, curvature=shape.curvature,
                 grating_s=shape.grating_s, valid=shape.valid, covariance=cov)


def test_tube_mesh_takes_a_radius_per_point_and_the_envelope_adds_the_confidence_radius():
    shape = with_covariance(arc())
    # an isotropic lateral error: the 95 % radius is σ √(−2 ln 0.05) (Rayleigh)
    r = geo.envelope(shape, 0.95, 1.3e-3)
    np.testing.assert_allclose(r, 1.3e-3 + 1e-4 * shape.s / shape.s[-1] * np.sqrt(-2 * np.log(0.05)), rtol=1e-6)
    verts, _ = geo.tube_mesh(shape.positions, r, 12, normals=shape.frames[:, :, 0])
    rings = verts[: len(r) * 12].reshape(len(r), 12, 3) - shape.positions[:, None, :]
    np.testing.assert_allclose(np.linalg.norm(rings, axis=-1), r[:, None] * np.ones(12), rtol=1e-9)
    with pytest.raises(ValueError, match="one per point"):
        geo.tube_mesh(shape.positions, r[:-1])
    with pytest.raises(ValueError, match=">= 0"):
        geo.tube_mesh(shape.positions, -r)


def test_tube_mesh_rejects_bad_input():
    with pytest.raises(ValueError, match="shape"):
        geo.tube_mesh(np.zeros((1, 3)), 1e-3)
    with pytest.raises(ValueError, match="NaN"):
        geo.tube_mesh(np.full((3, 3), np.nan), 1e-3)


def test_colormap_interpolates_the_anchors_clips_and_greys_nan():
    a = geo.VIRIDIS
    rgb = geo.colormap([0.0, 1.0, 0.5, 1.0 / 16, -3.0, 9.0, np.nan], 0.0, 1.0)
    np.testing.assert_allclose(rgb[0], a[0])
    np.testing.assert_allclose(rgb[1], a[-1])
    np.testing.assert_allclose(rgb[2], a[4])  # the middle anchor of nine
    np.testing.assert_allclose(rgb[3], (a[0] + a[1]) / 2)  # halfway between the first two
    np.testing.assert_allclose(rgb[4], a[0])
    np.testing.assert_allclose(rgb[5], a[-1])
    np.testing.assert_allclose(rgb[6], 0.5)
    assert geo.colorbar_stops()[0] == "#440154" and geo.colorbar_stops()[-1] == "#fde725"  # viridis' ends
    with pytest.raises(ValueError, match="increasing"):
        geo.colormap([0.0], 1.0, 1.0)


def test_scale_bar_is_a_round_length_with_end_ticks():
    assert geo.nice_length(0.17) == pytest.approx(0.02)  # a quarter is 42.5 mm: 20 mm
    assert geo.nice_length(0.5) == pytest.approx(0.1)
    assert geo.nice_length(0.2) == pytest.approx(0.05)
    assert geo.nice_length(1.0) == pytest.approx(0.2)
    v, f = geo.scale_bar([0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.02, 3e-4)
    assert f.max() < len(v)
    np.testing.assert_allclose([v[:, 0].min(), v[:, 0].max()], [-3e-4, 0.02 + 3e-4], atol=1e-12)
    np.testing.assert_allclose([v[:, 2].min(), v[:, 2].max()], [-0.12 * 0.02, 0.12 * 0.02], atol=1e-12)


def test_local_error_is_the_distance_to_the_truth_polyline():
    truth = np.stack([np.zeros(11), np.zeros(11), np.linspace(0, 0.1, 11)], -1)
    pts = np.array([[1e-4, 0.0, 0.05], [0.0, -3e-4, 0.033], [0.0, 0.0, 0.12], [2e-3, 2e-3, 0.0]])
    np.testing.assert_allclose(geo.local_error(pts, truth), [1e-4, 3e-4, 0.02, np.hypot(2e-3, 2e-3)], rtol=1e-12)


def test_placement_uses_the_given_pose_then_the_truth_base_then_kabsch():
    shape = arc()
    truth = truth_of(shape)
    R, p, how = geo.placement(shape, truth)
    assert how == "truth_base"
    np.testing.assert_allclose(shape.positions @ R.T + p, truth.positions, atol=1e-12)
    R, p, how = geo.placement(shape, Truth(s=truth.s, positions=truth.positions))
    assert how == "kabsch"
    np.testing.assert_allclose(shape.positions @ R.T + p, truth.positions, atol=1e-9)
    R, p, how = geo.placement(shape, truth, base_pose=(np.eye(3), np.ones(3)))
    assert how == "base_pose" and np.array_equal(p, np.ones(3))
    assert geo.placement(shape)[2] == "base_frame"
    with pytest.raises(ValueError, match="base_pose"):
        geo.placement(shape, base_pose=(np.eye(2), np.zeros(3)))


def test_latest_usable_skips_unusable_and_nan_frames():
    one = arc()
    pos = np.stack([one.positions, one.positions, np.full_like(one.positions, np.nan), one.positions])
    shapes = Shape(s=one.s, positions=pos, frames=np.stack([one.frames] * 4), curvature=np.stack([one.curvature] * 4),
                   grating_s=one.grating_s, valid=np.ones((4, 18), bool))
    assert latest_usable(shapes, np.array([0, 0, 0, 4], np.uint8), 4) == 1  # 3 unusable, 2 NaN
    assert latest_usable(shapes, np.zeros(4, np.uint8), 4) == 3
    assert latest_usable(shapes, np.array([4, 4, 0, 4], np.uint8), 4) is None


# ------------------------------------------------------------------------------------------------ wire format
def test_commands_are_meshcat_messages_with_typed_arrays():
    import umsgpack

    kind, path, data = cmd.set_transform("/twin", np.arange(16.0).reshape(4, 4))
    msg = umsgpack.unpackb(data)
    assert (kind, path, msg["type"], msg["path"]) == ("set_transform", "/twin", "set_transform", "/twin")
    assert msg["matrix"] == np.arange(16.0).reshape(4, 4).T.ravel().tolist()  # column-major, as three.js reads
    verts = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    obj = umsgpack.unpackb(cmd.set_object("/twin/x", cmd.mesh(verts, [[0, 1, 2]], cmd.material()))[2])["object"]
    pos = obj["geometries"][0]["data"]["attributes"]["position"]
    assert pos["array"].type == 0x17 and pos["itemSize"] == 3  # Float32Array, x y z together
    np.testing.assert_array_equal(np.frombuffer(pos["array"].data, np.float32).reshape(-1, 3), verts)
    index = obj["geometries"][0]["data"]["index"]
    assert index["array"].type == 0x16 and np.frombuffer(index["array"].data, np.uint32).tolist() == [0, 1, 2]
    assert obj["object"]["geometry"] == obj["geometries"][0]["uuid"]
    assert obj["object"]["material"] == obj["materials"][0]["uuid"]


# ------------------------------------------------------------------------------------------------ the server
def start_server(*extra: str) -> tuple[subprocess.Popen, dict]:
    proc = subprocess.Popen([sys.executable, "-m", "twin.viewer.server", "--web-port", "0", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    return proc, json.loads(proc.stdout.readline())


def listening_addresses(port: int) -> set[str]:
    """Local addresses (hex, as /proc/net/tcp writes them) listening on ``port``."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as f:
            for line in f.readlines()[1:]:
                local, _, state = line.split()[1:4]
                addr, p = local.split(":")
                if int(p, 16) == port and state == "0A":
                    found.add(addr)
    return found


def test_server_module_binds_loopback_and_speaks_meshcat():
    proc, urls = start_server()
    try:
        web_port = int(urls["web_url"].split(":")[2].split("/")[0])
        zmq_port = int(urls["zmq_url"].rsplit(":", 1)[1])
        assert urls["web_url"].startswith("http://127.0.0.1:") and urls["zmq_url"].startswith("tcp://127.0.0.1:")
        assert listening_addresses(web_port) == {"0100007F"} and listening_addresses(zmq_port) == {"0100007F"}
        page = urllib.request.urlopen(urls["web_url"], timeout=10).read().decode()
        assert "MeshCat.Viewer" in page and 'src="main.min.js"' in page and "/ws" in page
        js = urllib.request.urlopen(urls["web_url"] + "main.min.js", timeout=10).read()
        assert len(js) > 100_000  # meshcat's viewer, served from the installed package

        # meshcat's own client understands our server (the same wire format)
        import meshcat
        import meshcat.geometry as g

        vis = meshcat.Visualizer(zmq_url=urls["zmq_url"])
        vis["box"].set_object(g.Box([0.1, 0.1, 0.1]))

        # a browser connecting later gets the scene first, then the overlay, over the websocket
        from twin.viewer.client import SceneClient

        client = SceneClient(urls["zmq_url"])
        client.send(cmd.set_transform("/twin", np.eye(4)))
        client.hud({"title": "probe"})
        got = asyncio.run(websocket_messages(urls["web_url"].replace("http", "ws").replace("/static/", "/ws"), 3))
        binary = [m for m in got if isinstance(m, bytes)]
        assert len(binary) == 2 and json.loads(next(m for m in got if isinstance(m, str))) == {"title": "probe"}
        html = client.static_html()
        assert "MeshCat.Viewer" in html and "probe" in html and 'src="main.min.js"' not in html
        client.close()
    finally:
        proc.kill()
        proc.wait()


async def websocket_messages(url: str, n: int) -> list:
    import tornado.websocket

    conn = await tornado.websocket.websocket_connect(url)
    out = [await asyncio.wait_for(conn.read_message(), 10) for _ in range(n)]
    conn.close()
    return out


def test_server_exits_when_its_parent_is_gone():
    code = ("import subprocess, sys, os\n"
            "p = subprocess.Popen([sys.executable, '-m', 'twin.viewer.server', '--web-port', '0', '--parent',"
            " str(os.getpid())], stdout=subprocess.PIPE, start_new_session=True)\n"
            "p.stdout.readline(); print(p.pid)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=ENV)
    pid = int(out.stdout.strip())
    deadline = time.monotonic() + 20
    while not gone(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert gone(pid)


# ------------------------------------------------------------------------------------------------ the scene
def test_scene_shows_error_colours_truth_on_top_and_the_figures(make_viewer):
    v = make_viewer(max_fps=float("inf"))
    spy = Spy(v)
    shape = arc()
    truth = truth_of(shape, offset=1e-4)  # the reconstruction (placed at the base) is 0.1 mm off the truth
    assert v.show(shape, truth, label="arc")
    cfg = v.config
    # the errors, exact: 0.1 mm everywhere except the base
    assert v.errors["max"] == pytest.approx(1e-4, rel=1e-9) and v.errors["tip"] == pytest.approx(1e-4, rel=1e-9)
    # the mean: 0 at the base, ≤ 0.1 mm at s = 1 mm (nearer the truth's slanted first segment), 0.1 mm beyond
    assert 1e-4 * 169 / 171 < v.errors["mean"] < 1e-4 * 170 / 171 + 1e-15
    (mesh,) = spy.objects("/twin/shape")
    verts = attribute(mesh, "position")
    n = len(shape.s)
    rings = verts[: n * cfg.sides].reshape(n, cfg.sides, 3)
    placed = shape.positions @ POSE_R.T + POSE_P
    np.testing.assert_allclose(np.linalg.norm(rings - placed[:, None], axis=-1), cfg.radius, atol=2e-7)
    # coloured by local error: 0.1 of the 1 mm range, the base at 0
    colors = attribute(mesh, "color")
    np.testing.assert_allclose(colors[cfg.sides * 50], geo.colormap([1e-4], *cfg.error_range)[0], atol=1e-6)
    np.testing.assert_allclose(colors[0], geo.VIRIDIS[0], atol=1e-6)
    mat = mesh["materials"][0]
    assert mat["vertexColors"] and mat["transparent"] and mat["opacity"] == cfg.shape_opacity < 1
    # the truth: its own colour, unlit, without depth test and drawn after the tube
    (tr,) = spy.objects("/twin/truth")
    tm = tr["materials"][0]
    assert tm["type"] == "MeshBasicMaterial" and tm["color"] == cfg.truth_color and tm["depthTest"] is False
    assert tr["object"]["renderOrder"] > mesh["object"]["renderOrder"]
    tv = attribute(tr, "position")
    assert np.linalg.norm(tv[0] - truth.positions[0]) == pytest.approx(cfg.truth_radius, abs=1e-7)
    (points,) = spy.objects("/twin/gratings")
    assert len(attribute(points, "position")) == len(shape.grating_s)
    (fx,) = spy.objects("/twin/fixture")
    assert fx["materials"][0]["opacity"] == cfg.fixture_opacity < 0.5
    (bar,) = spy.objects("/twin/scale")
    assert np.ptp(attribute(bar, "position"), axis=0).max() == pytest.approx(0.02 + 6e-4, abs=1e-5)  # 20 mm
    # the overlay: figures and legend
    hud = v.hud()
    figures = dict(hud["figures"])
    assert figures["max error"] == "0.100 mm" and figures["tip error"] == "0.100 mm"
    assert figures["error vs truth"] == "at the true base pose" and figures["calibration"] == "none"
    assert hud["title"] == "arc" and "local error (mm)" in hud["colorbar"]["label"]
    assert ["#ff00ff", "truth (centreline, drawn on top)"] in hud["legend"]
    assert any("scale bar: 20 mm" in text for _, text in hud["legend"])

    # the next frame: shape, gratings and truth again; the unchanged fixture and the scale are not resent
    spy.clear()
    assert v.show(shape, truth)
    assert sorted(p for _, p, _ in spy.sent) == ["/twin/gratings", "/twin/magnified", "/twin/shape",
                                                 "/twin/truth"]
    # without a truth: coloured by curvature, no error figures
    spy.clear()
    v.show(shape, force=True)
    assert v.errors is None and "curvature" in v.hud()["colorbar"]["label"]
    assert "max error" not in dict(v.hud()["figures"]) and spy.objects("/twin/truth") == []


def test_vendor_shape_is_drawn_registered_as_its_distance_is_reported(make_viewer):
    v = make_viewer(max_fps=float("inf"))
    spy = Spy(v)
    shape = arc()
    truth = truth_of(shape, offset=1e-4)
    block = vendor_of(shape)
    assert v.show(shape, truth, vendor=(block,))
    (obj,) = spy.objects("/twin/vendor")
    mat = obj["materials"][0]
    assert mat["type"] == "MeshBasicMaterial" and mat["color"] == v.config.vendor_color and mat["depthTest"] is False
    # drawn where the reported registration puts it: our placed points' distances to the drawn vendor
    # centreline are the reported ones (float32 vertices: 1e-7 m)
    placed = shape.positions @ POSE_R.T + POSE_P
    drawn = centreline(obj)
    assert len(drawn) == len(block.positions)
    d = geo.local_error(placed, drawn)
    reported = vendor_distance(shape.positions, shape.s, block.positions, block.s)
    assert reported.max > 5e-4  # a distance one can see, not a coincidence at zero
    assert d.max() == pytest.approx(reported.max, abs=2e-7) and d.mean() == pytest.approx(reported.mean, abs=2e-7)
    assert v.vendor_errors["max"] == pytest.approx(reported.max, rel=1e-12)
    assert ("set_property", "/twin/vendor") in [(k, p) for k, p, _ in spy.sent]  # visible, once
    hud = v.hud()
    figures = dict(hud["figures"])
    assert figures["max distance"] == f"{1e3 * reported.max:.3f} mm" and "vs interrogator's shape" in figures
    assert [f"#{v.config.vendor_color:06x}", "interrogator's own shape (registered onto ours)"] in hud["legend"]
    # the truth is still on top of it
    assert spy.objects("/twin/truth")[0]["object"]["renderOrder"] > obj["object"]["renderOrder"]
    # the next frame: redrawn, the visibility (the page's toggle) left alone
    spy.clear()
    v.show(shape, truth, vendor=(block,))
    assert len(spy.objects("/twin/vendor")) == 1 and "set_property" not in [k for k, _, _ in spy.sent]
    # a frame without one: removed, and gone from the overlay
    spy.clear()
    v.show(shape, truth)
    assert ("delete", "/twin/vendor") in [(k, p) for k, p, _ in spy.sent] and spy.objects("/twin/vendor") == []
    assert v.vendor_errors is None and "max distance" not in dict(v.hud()["figures"])
    assert not any("interrogator" in text for _, text in v.hud()["legend"])
    spy.clear()
    v.show(shape, truth)
    assert spy.sent and all(p != "/twin/vendor" for _, p, _ in spy.sent)  # deleted once

    # show_vendor=False: sent hidden (the page's scene controls switch it on); another sensor picked
    hidden = make_viewer(max_fps=float("inf"), show_vendor=False, vendor_sensor=1)
    spy = Spy(hidden)
    hidden.show(shape, vendor=(vendor_of(shape, 30.0), block))
    (prop,) = [c for k, p, c in spy.sent if k == "set_property" and p == "/twin/vendor"]
    assert prop["property"] == "visible" and prop["value"] is False
    assert hidden.vendor_errors["max"] == pytest.approx(reported.max, rel=1e-12)  # sensor 1 = block
    hidden.show(shape, vendor=(block,), force=True)  # no sensor 1: nothing drawn
    assert hidden.vendor_errors is None


def test_rate_limiter_drops_frames_sooner_than_max_fps(make_viewer):
    # 0.5 frames/s: the 2 s between two frames is far longer than any stall between two lines of this test,
    # and the wait for the next one is a condition with a hang guard, not a sleep
    v = make_viewer(max_fps=0.5)
    shape = arc()
    assert v.show(shape)
    assert not v.ready() and not v.show(shape)
    assert v.frames_skipped == 1 and v.frames_shown == 1
    t_forced = time.monotonic()
    assert v.show(shape, force=True)
    assert wait_until(v.ready, timeout=30.0)
    assert time.monotonic() - t_forced >= 2.0  # never ready before its period (a load only delays it)
    assert v.show(shape)
    assert v.frames_shown == 3
    with pytest.raises(ValueError, match="batch"):
        v.show(Shape(s=shape.s, positions=shape.positions[None], frames=shape.frames[None],
                     curvature=shape.curvature[None], grating_s=shape.grating_s, valid=shape.valid[None]),
               force=True)


def test_stale_state_greys_the_catheter_and_says_so(make_viewer):
    v = make_viewer()
    spy = Spy(v)
    v.show(arc(), label="arc")
    spy.clear()
    v.set_state("stale", "no data for 2 s")
    (mesh,) = spy.objects("/twin/shape")
    np.testing.assert_allclose(attribute(mesh, "color"), 0x8C / 255, atol=1e-6)
    assert v.hud()["state_text"] == "STALE (no data for 2 s)"
    spy.clear()
    v.set_state("stale", "no data for 2 s")  # nothing changed: nothing sent
    assert spy.sent == []
    v.set_state("live")
    (mesh,) = spy.objects("/twin/shape")
    assert not np.allclose(attribute(mesh, "color"), 0x8C / 255)


def test_save_html_is_a_self_contained_page(make_viewer, tmp_path):
    v = make_viewer()
    v.show(arc(), label="arc")
    page = v.save_html(tmp_path / "scene.html").read_text()
    assert "MeshCat.Viewer" in page and "handle_command_bytearray" in page and "http" not in page.split("<script>")[0]


# ------------------------------------------------------------------------------------------------ shutdown
def test_close_kills_the_server_and_later_calls_fail_cleanly(make_viewer):
    v = make_viewer()
    pid = v.server_pid
    v.show(arc())
    v.close()
    assert gone(pid) and v.closed
    v.close()
    with pytest.raises(ViewerError, match="closed"):
        v.show(arc(), force=True)


def test_a_dead_or_frozen_server_raises_instead_of_hanging(make_viewer):
    v = make_viewer()
    os.kill(v.server_pid, signal.SIGKILL)
    v._proc.wait(timeout=10)
    with pytest.raises(ViewerError, match="exited"):
        v.show(arc())
    assert v.broken and not v.alive

    frozen = make_viewer(timeout=0.5)
    os.kill(frozen.server_pid, signal.SIGSTOP)
    try:
        with pytest.raises(ViewerError, match="did not answer"):
            frozen.show(arc())
        with pytest.raises(ViewerError):  # given up on: no second wait
            frozen.show(arc(), force=True)
    finally:
        os.kill(frozen.server_pid, signal.SIGCONT)


def test_keep_open_serves_until_the_server_is_gone(make_viewer):
    v = make_viewer()
    v.show(arc())
    killer = threading.Timer(1.0, os.kill, (v.server_pid, signal.SIGKILL))
    killer.start()
    out = io.StringIO()
    keep_open(v, out, poll=0.1)  # returns when the server is gone (or on Ctrl-C)
    assert "Ctrl-C" in out.getvalue() and v.closed


# ------------------------------------------------------------------------------------------------ live sink
def status(state: str = "live", n: int = 0, age: float = 0.0) -> LiveStatus:
    return LiveStatus(state=state, flags=np.zeros(n, np.uint8), last_valid_age=age)


def test_sink_draws_the_latest_usable_frame_and_keeps_a_dropped_one(make_viewer):
    v = make_viewer(max_fps=float("inf"))
    spy = Spy(v)
    sink = ViewerSink(v, rate=1000.0, close_viewer=False)
    one, two = arc(), arc(kappa=10.0)
    batch = Shape(s=one.s, positions=np.stack([one.positions, two.positions, np.full_like(one.positions, np.nan)]),
                  frames=np.stack([one.frames, two.frames, one.frames]), curvature=np.stack([one.curvature] * 3),
                  grating_s=one.grating_s, valid=np.ones((3, 18), bool))
    w = np.zeros((18, 4))
    truth = truth_of(two)
    frames = [Frame(w), Frame(w, truth=truth, vendor=(vendor_of(two),)), Frame(w)]
    sink(frames, batch, LiveStatus(state="live", flags=np.array([0, 0, 4], np.uint8), rate_hz=99.5,
                                   lost_samples=3))
    assert sink.frames_shown == 1 and v.placement == "truth_base"
    assert len(spy.objects("/twin/vendor")) == 1 and v.vendor_errors is not None  # the frame's vendor shape
    (mesh,) = spy.objects("/twin/shape")
    assert np.allclose(attribute(mesh, "position")[: v.config.sides].mean(axis=0), truth.positions[0], atol=1e-6)
    figures = dict(v.hud()["figures"])
    assert figures["source rate"] == "99.5 Hz" and figures["lost frames"] == "3"
    # not due: the frame is held, not drawn (due in a minute, so no stall can make it due meanwhile) …
    sink.latest.due = time.monotonic() + 60.0
    sink(frames[:1], batch[:1], status(n=1))
    assert sink.frames_shown == 1
    # … and once due, a heartbeat without frames draws the held one
    sink.latest.due = time.monotonic()
    sink([], None, status())
    assert sink.frames_shown == 2
    spy.clear()
    sink([], None, status("stale", age=1.0))
    np.testing.assert_allclose(attribute(spy.objects("/twin/shape")[0], "color"), 0x8C / 255, atol=1e-6)
    assert sink.errors == 0


def test_confidence_envelope_is_drawn_translucent_and_removed_without_uncertainty(make_viewer):
    """A shape carrying its uncertainty gets a translucent envelope of radius tube + 95 % radius around the
    tube; the next shape without one removes it. The sink propagates the drawn shape with its Uncertainty."""
    from twin import FiberModel, strain
    from twin.uncertainty import ModelError, Uncertainty

    v = make_viewer(max_fps=float("inf"))
    spy = Spy(v)
    shape = with_covariance(arc())
    cfg = v.config
    assert v.show(shape, truth_of(shape))
    (env,) = spy.objects("/twin/confidence")
    n = len(shape.s)
    rings = attribute(env, "position")[: n * cfg.sides].reshape(n, cfg.sides, 3)
    placed = shape.positions @ POSE_R.T + POSE_P
    expected = geo.envelope(shape, cfg.confidence_level, cfg.radius)
    np.testing.assert_allclose(np.linalg.norm(rings - placed[:, None], axis=-1), expected[:, None] * np.ones(
        cfg.sides), atol=2e-7)  # float32 on the wire
    mat = env["materials"][0]
    assert mat["transparent"] and mat["opacity"] == cfg.confidence_opacity < 0.5 and mat["depthWrite"] is False
    spy.clear()
    assert v.show(arc(), force=True)
    assert spy.objects("/twin/confidence") == [] and ("delete", "/twin/confidence") in [(k, p) for k, p, _ in spy.sent]
    # the sink: the drawn frame's shape gets its uncertainty
    fiber = FiberModel.paper()
    w = strain.forward(fiber, np.tile([20.0, 0.0], (fiber.n_gratings, 1)))
    rec = Reconstructor(fiber)
    sink = ViewerSink(v, rate=1000.0, close_viewer=False, uncertainty=Uncertainty(rec, model_error=ModelError(0.05)))
    spy.clear()
    sink([Frame(w)], rec(w[None]), LiveStatus(state="live", flags=np.zeros(1, np.uint8)))
    assert sink.frames_shown == 1 and sink.errors == 0 and len(spy.objects("/twin/confidence")) == 1


def test_sink_never_raises_and_counts_errors(make_viewer):
    v = make_viewer()
    report = io.StringIO()
    sink = ViewerSink(v, close_viewer=True, stream=report)
    os.kill(v.server_pid, signal.SIGKILL)
    v._proc.wait(timeout=10)
    shapes = Shape(s=arc().s, positions=arc().positions[None], frames=arc().frames[None],
                   curvature=arc().curvature[None], grating_s=arc().grating_s, valid=np.ones((1, 18), bool))
    sink([Frame(np.zeros((18, 4)))], shapes, status(n=1))
    sink([Frame(np.zeros((18, 4)))], shapes, status(n=1))
    assert sink.errors == 1 and "exited" in sink.last_error
    assert report.getvalue().count("viewer:") == 1
    sink.close()
    assert v.closed


def test_sink_in_the_live_loop_at_1_khz_draws_at_most_its_rate(make_viewer):
    v = make_viewer()
    sink = ViewerSink(v, rate=30.0)
    src = SyntheticSource(rate=1000, pace=True)
    # bounded by a frame count, not a time (a cold start on a loaded machine cannot leave it without frames)
    summary = LiveLoop(src, Reconstructor(src.fiber), [sink]).run(duration=120.0, max_frames=1500,
                                                                  handle_signals=False)
    assert summary.sink_errors == () and sink.errors == 0
    assert summary.reason == "frames" and summary.status.frames == 1500
    assert 1 <= sink.frames_shown <= 30 * summary.duration + 2
    assert v.placement == "truth_base" and v.errors is not None
    assert v.closed and gone(v.server_pid)


# ------------------------------------------------------------------------------------------------ command line
def test_the_viewer_options_are_read_by_argparse_anywhere_among_the_scenario_options(monkeypatch, capsys):
    """`twin run NAME`'s viewer options are declared on the scenario's parser as on `twin run`'s (one parser, no
    hand-made second one): anywhere among the scenario's options, ``=`` or not, listed in the scenario's --help
    with their help, bad values one line; the scenario's args keep only ``viewer``."""
    from twin import cli, registry

    seen = {}
    probe = types.ModuleType("_viewer_options_probe")
    probe.__doc__ = "probe"
    probe.add_arguments = lambda parser: parser.add_argument("--n", type=int, default=0)

    def run(args):
        seen.update(vars(args))
        seen["fps"] = None if args.viewer is None else args.viewer.config.max_fps
        return 0

    probe.run = run
    monkeypatch.setitem(sys.modules, "_viewer_options_probe", probe)
    registry.register("twin.scenarios", "viewer-options-probe", "_viewer_options_probe")
    try:
        for options, fps in ((["--n", "3", "--viewer-rate", "12"], 12.0), (["--viewer-rate=5", "--n", "3"], 5.0),
                             (["--n", "3", "--viewer"], 30.0), (["--n", "3"], None)):
            seen.clear()
            assert cli.main(["run", "viewer-options-probe", *options]) == 0
            assert seen["fps"] == fps and seen["n"] == 3 and set(seen) == {"n", "viewer", "fps"}, options
        capsys.readouterr()
        with pytest.raises(SystemExit) as help_exit:
            cli.main(["run", "viewer-options-probe", "--help"])
        assert help_exit.value.code == 0
        text = " ".join(capsys.readouterr().out.split())
        assert "--viewer-rate HZ most frames the viewer draws per second" in text and "--keep-open" in text
        assert cli.main(["run", "viewer-options-probe", "--viewer-rate", "0"]) == 2
        assert capsys.readouterr().err.strip() == ("twin run: error: --viewer-rate must be a positive number of "
                                                   "frames per second, got 0.0")
        for bad in (["--viewer-rate"], ["--viewer-rate", "fast"]):
            with pytest.raises(SystemExit) as bad_exit:
                cli.main(["run", "viewer-options-probe", *bad])
            assert bad_exit.value.code == 2 and "argument --viewer-rate" in capsys.readouterr().err
    finally:
        registry.unregister("twin.scenarios", "viewer-options-probe")


def test_twin_run_passes_a_viewer_to_the_scenario(monkeypatch, capsys):
    from twin import cli, registry

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
    registry.register("twin.scenarios", "viewer-probe", "_viewer_probe")
    try:
        assert cli.main(["run", "viewer-probe", "--n", "3", "--viewer", "--viewer-rate", "10"]) == 0
        v = seen["viewer"]
        assert isinstance(v, Viewer) and v.config.max_fps == 10.0 and seen["n"] == 3
        assert v.closed and gone(seen["pid"])
        assert "twin viewer: open http://127.0.0.1:" in capsys.readouterr().err
        assert cli.main(["run", "--viewer", "viewer-probe"]) == 0 and seen["viewer"].closed
        assert cli.main(["run", "viewer-probe"]) == 0 and seen["viewer"] is None
    finally:
        registry.unregister("twin.scenarios", "viewer-probe")


def test_twin_run_help_shows_the_common_options():
    out = subprocess.run([*TWIN, "run", "--help"], capture_output=True, text=True, timeout=60, env=ENV)
    assert out.returncode == 0
    for option in ("--json", "--report", "--calibration", "--viewer", "--keep-open"):
        assert option in out.stdout, option


def test_twin_live_viewer_flag():
    out = subprocess.run([*TWIN, "live", "synthetic://?rate=1000", "--viewer", "--duration", "1.5", "--json",
                          "--quiet"], capture_output=True, text=True, timeout=120, env=ENV)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert summary["viewer_frames"] >= 1 and summary["viewer_errors"] == 0
    assert "twin viewer: open http://127.0.0.1:" in out.stderr


def test_twin_live_keep_open_serves_after_the_run_until_ctrl_c():
    proc = subprocess.Popen([*TWIN, "live", "synthetic://?rate=200", "--viewer", "--keep-open", "--duration", "1",
                             "--json", "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        url = None
        deadline = time.monotonic() + 90
        while True:
            line = proc.stderr.readline()
            assert line and time.monotonic() < deadline, "no 'still serving' line"
            if "open http" in line:
                url = line.split("open ", 1)[1].strip()
            if "still serving" in line:
                break
        summary = json.loads(proc.stdout.readline())  # the run is over…
        assert summary["reason"] == "duration"
        time.sleep(1.0)
        assert "MeshCat.Viewer" in urllib.request.urlopen(url, timeout=10).read().decode()  # …the page is served
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# ------------------------------------------------------------------------------------------------ a real browser
CHROMIUM_FLAGS = [
    "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
    "--force-device-scale-factor=1", "--hide-scrollbars", "--window-size=800,600", "--virtual-time-budget=3000",
]
W, H = 800, 600


def chromium(url: str, tmp_path, name: str, *what: str) -> subprocess.CompletedProcess:
    profile = tmp_path / f"profile-{name}"
    run = subprocess.run([CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *what, url],
                         capture_output=True, text=True, timeout=90)
    assert run.returncode == 0, run.stderr[-2000:]
    return run


def screenshot(url: str, tmp_path, name: str) -> np.ndarray:
    """Render ``url`` in headless chromium; RGB (H, W, 3) floats in [0, 1]."""
    import matplotlib.image

    out = tmp_path / f"{name}.png"
    chromium(url, tmp_path, name, f"--screenshot={out}")
    img = matplotlib.image.imread(out)[..., :3]
    assert img.shape == (H, W, 3)
    return img


def project(viewer: Viewer, world: np.ndarray) -> np.ndarray:
    """Pixel coordinates (n, 2) of world points (m) in the 800×600 view: meshcat's perspective camera
    (vertical fov 75°) at the framed eye, looking at the scene origin (the catheter's centre), +z up."""
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


def magenta(img: np.ndarray) -> np.ndarray:
    """Pixels of the truth's colour (0xFF00FF, unlit): the background, grid, viridis and grey all fail it."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 0.75) & (b > 0.75) & (g < 0.35)


def grey(img: np.ndarray) -> np.ndarray:
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (np.abs(r - g) < 0.06) & (np.abs(g - b) < 0.06) & (r > 0.2) & (r < 0.85)


def near(mask: np.ndarray, px: np.ndarray, radius: int = 4) -> np.ndarray:
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


@pytest.fixture
def chromium_present():
    require_tool(CHROMIUM is not None, "chromium is not installed (.ci/run installs Debian's chromium)")


needs_chromium = pytest.mark.usefixtures("chromium_present")


@pytest.mark.timeout(300)
@needs_chromium
def test_browser_shows_the_truth_at_a_tenth_of_a_millimetre_and_the_figures(make_viewer, tmp_path):
    """At 0.1 mm error the truth (magenta, on top) is drawn along its projected centreline and nowhere else;
    the overlay shows the error figures; a stale stream greys the catheter."""
    v = make_viewer()
    shape = arc()
    truth = truth_of(shape, offset=1e-4, fixture=False)
    v.show(shape, truth, label="arc R50")
    v.set_info(rate_hz=100.0, lost=0)
    px = project(v, truth.positions)
    assert np.all((px > 0) & (px < [W, H]))  # the framing keeps the whole catheter in view

    img = screenshot(v.url, tmp_path, "live")
    mask = magenta(img)
    if not mask.any():  # a slow first start of chromium may shoot before the scene arrives: once more
        img = screenshot(v.url, tmp_path, "live-again")
        mask = magenta(img)
    # the overlay panels (top left, bottom left) may cover part of the catheter: count what they leave
    assert near(mask, px).mean() >= 0.8
    ys, xs = np.nonzero(mask)
    swatch = (xs < 340) & (ys > 420)  # the legend (bottom left) shows the truth's colour too
    assert swatch.any() and near(mask, px).mean() >= 0.8
    assert distance_to_polyline(np.stack([xs, ys], -1)[~swatch].astype(float), px).max() <= 6  # nowhere else
    assert (xs.max() - xs.min()) > 0.3 * W or (ys.max() - ys.min()) > 0.45 * H  # framed: a good part of the view
    # around the truth, the translucent tube: neither background nor truth on both sides of the line
    dom = chromium(v.url, tmp_path, "dom", "--dump-dom").stdout
    assert "max error" in dom and "0.100 mm" in dom and "local error (mm)" in dom and "scale bar: 20 mm" in dom
    assert "100.0 Hz" in dom

    v.set_state("stale", "no data for 2 s")
    stale = screenshot(v.url, tmp_path, "stale")
    assert near(grey(stale), px, radius=6).mean() >= 0.8  # the tube is grey where it was
    assert near(magenta(stale), px).mean() >= 0.8  # and the truth still shows


@pytest.mark.timeout(300)
@needs_chromium
def test_browser_renders_the_static_export(make_viewer, tmp_path):
    v = make_viewer()
    shape = arc(kappa=12.0)
    truth = truth_of(shape, offset=1e-4)
    v.show(shape, truth, label="export")
    page = v.save_html(tmp_path / "scene.html")
    px = project(v, truth.positions)
    v.close()  # the page must not need the server
    img = screenshot(page.as_uri(), tmp_path, "static")
    assert near(magenta(img), px).mean() >= 0.8
    dom = chromium(page.as_uri(), tmp_path, "static-dom", "--dump-dom").stdout
    assert "0.100 mm" in dom


def orange(img: np.ndarray) -> np.ndarray:
    """Pixels of the vendor shape's colour (0xFF8000, unlit): background, grid, viridis, grey, magenta fail it."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 0.85) & (g > 0.35) & (g < 0.65) & (b < 0.25)


@pytest.mark.timeout(300)
@needs_chromium
def test_browser_shows_the_vendor_shape_when_present_and_not_otherwise(make_viewer, tmp_path):
    """The interrogator's shape (orange, registered onto ours) is drawn along its projected centreline and
    nowhere else, named in the legend; a frame without one leaves no orange pixel."""
    from twin.reference_errors import vendor_in_base

    v = make_viewer()
    shape = arc()
    block = vendor_of(shape)
    v.show(shape, vendor=(block,), label="vendor")
    base, e = vendor_in_base(shape.positions, shape.s, block.positions, block.s)
    assert e.max > 5e-4 and v.placement == "base_frame"  # no truth: the scene is our base frame
    px = project(v, base)
    assert np.all((px > 0) & (px < [W, H]))

    img = screenshot(v.url, tmp_path, "vendor")
    mask = orange(img)
    if not mask.any():  # a slow first start of chromium may shoot before the scene arrives: once more
        img = screenshot(v.url, tmp_path, "vendor-again")
        mask = orange(img)
    assert near(mask, px).mean() >= 0.8
    ys, xs = np.nonzero(mask)
    swatch = (xs < 340) & (ys > 380)  # the legend (bottom left) shows its colour too
    assert swatch.any()
    assert distance_to_polyline(np.stack([xs, ys], -1)[~swatch].astype(float), px).max() <= 6  # nowhere else
    dom = chromium(v.url, tmp_path, "vendor-dom", "--dump-dom").stdout
    assert "interrogator's own shape" in dom and f"{1e3 * e.max:.3f} mm" in dom

    v.show(shape, force=True)  # the next frame has no vendor shape
    plain = screenshot(v.url, tmp_path, "plain")
    assert not orange(plain).any()


@pytest.mark.timeout(300)
@needs_chromium
def test_browser_shows_the_confidence_envelope_around_the_tube(make_viewer, tmp_path):
    """A shape with a 3 mm lateral 1σ at the tip: the page with the envelope differs from the page without it
    only within the envelope's projected radius of the centreline, and near the tip beyond the tube's own."""
    v = make_viewer()
    plain = arc()
    shape = with_covariance(plain, sigma_tip=3e-3)
    truth = truth_of(plain, offset=1e-4, fixture=False)
    v.show(shape, truth, label="envelope")  # frames the camera
    world = plain.positions @ POSE_R.T + POSE_P
    px = project(v, world)
    radius = geo.envelope(shape, v.config.confidence_level, v.config.radius)

    def projected(r: np.ndarray) -> np.ndarray:  # pixels per radius, the larger of two normal directions
        ends = [project(v, world + r[:, None] * (shape.frames[:, :, a] @ POSE_R.T)) for a in (0, 1)]
        return np.max([np.linalg.norm(e - px, axis=-1) for e in ends], axis=0)

    def compare(attempt: int) -> tuple[int, float, int]:
        v.show(shape, truth, label="envelope", force=True)
        with_env = screenshot(v.url, tmp_path, f"envelope-{attempt}")
        v.show(plain, truth, label="envelope", force=True)
        without = screenshot(v.url, tmp_path, f"plain-{attempt}")
        ys, xs = np.nonzero(np.abs(with_env - without).max(axis=-1) > 0.04)
        pts = np.stack([xs, ys], -1).astype(float)
        d_tip = distance_to_polyline(pts, px[-30:])
        beyond = (d_tip > projected(np.full(len(radius), v.config.radius))[-30:].max() + 3) & (
            d_tip < projected(radius)[-30:].max())
        return len(pts), float(distance_to_polyline(pts, px).max()) if len(pts) else 0.0, int(beyond.sum())

    changed, farthest, beyond = compare(0)
    if changed <= 200 or beyond <= 50:  # a slow chromium may shoot before the scene arrives: once more
        changed, farthest, beyond = compare(1)
    # nothing changed away from the envelope (10 px: the radius is projected along two normals only, and the
    # flat end caps and the perspective widen it by a few pixels); near the tip it shows beyond the tube
    assert changed > 200 and farthest <= projected(radius).max() + 10
    assert beyond > 50
