"""The meshcat viewer: scene content, rate limiting, clean shutdown, and the picture in a real headless
Chromium (installed by .ci/run; the browser test is skipped, saying why, only where Chromium is absent)."""

import os
import shutil
import subprocess
import time

import numpy as np
import pytest

from twin.frames import Shape, Truth
from twin.viewer import Viewer, ViewerConfig, curvature_colors, tube_mesh

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def arc(k: float = 20.0, length: float = 0.17, n: int = 171, n_g: int = 18) -> Shape:
    """A planar arc bending toward +x, with exact material frames; curvature rising along the gratings."""
    s = np.linspace(0, length, n)
    pos = np.stack([(1 - np.cos(k * s)) / k, 0 * s, np.sin(k * s) / k], -1)
    d1 = np.stack([np.cos(k * s), 0 * s, -np.sin(k * s)], -1)
    d2 = np.tile([0.0, 1.0, 0.0], (n, 1))
    d3 = np.stack([np.sin(k * s), 0 * s, np.cos(k * s)], -1)
    g = np.linspace(0.0, length, n_g)
    kv = np.stack([np.linspace(0, 60, n_g), 0 * g], -1)
    return Shape(s=s, positions=pos, frames=np.stack([d1, d2, d3], -1), curvature=kv, grating_s=g,
                 valid=np.ones(n_g, bool))


@pytest.fixture
def viewer():
    v = Viewer(ViewerConfig(max_fps=1e6), announce=None)
    yield v
    v.close()


def test_tube_mesh_is_a_closed_sweep():
    shape = arc()
    verts, faces = tube_mesh(shape.positions, radius=1.3e-3, sides=12)
    assert verts.shape[1] == 3 and faces.shape[1] == 3 and faces.max() < len(verts)
    # every vertex sits on the tube: its distance to the centreline is the radius (to the sweep's rounding)
    d = np.min(np.linalg.norm(verts[:, None, :] - shape.positions[None, ::1, :], axis=-1), axis=1)
    assert np.all(d <= 1.3e-3 + 1e-9) and np.median(d) == pytest.approx(1.3e-3, rel=0.05)


def test_grating_colours_follow_curvature():
    k = np.stack([np.linspace(0, 70, 8), np.zeros(8)], -1)
    valid = np.ones(8, bool)
    valid[3] = False
    c = np.asarray(curvature_colors(k, valid))
    assert c.shape[0] == 8
    assert not np.allclose(c[0], c[-1])  # the two ends of the colormap differ
    assert np.allclose(c[3], c[3].mean())  # an unsolved grating is grey


def test_rate_limit_and_close(viewer):
    limited = Viewer(ViewerConfig(max_fps=2.0), announce=None)
    try:
        shown = [limited.show(arc()) for _ in range(20)]
        assert shown[0] and sum(shown) < 5  # 20 calls within far less than a second: most skipped
        assert limited.frames_skipped >= 15
    finally:
        pid = limited.server_pid
        limited.close()
    assert not _alive(pid)  # the server process is gone (killed and reaped)


def _alive(pid: int, wait: float = 5.0) -> bool:
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        time.sleep(0.1)
    return True


def test_placement_with_truth(viewer):
    shape = arc()
    rot = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]).T
    truth = Truth(s=shape.s, positions=shape.positions @ rot.T + [0.1, 0.05, 0.2])
    assert viewer.show(shape, truth, label="arc")
    assert viewer.placement is not None


def _screenshot(url: str, out, tmp_path) -> np.ndarray:
    import matplotlib.image as mi

    cmd = [CHROMIUM, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
           "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
           f"--user-data-dir={tmp_path / 'profile'}", "--force-device-scale-factor=1", "--hide-scrollbars",
           f"--screenshot={out}", "--window-size=800,600", "--virtual-time-budget=4000", url]
    subprocess.run(cmd, capture_output=True, timeout=120, check=False)
    assert out.exists(), "chromium wrote no screenshot"
    return mi.imread(out)[..., :3]


def _orange(img: np.ndarray) -> np.ndarray:
    """Pixels of the reconstruction's colour (0xFF7F0E, shaded by the lights)."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 0.4) & (g > 0.25 * r) & (g < 0.75 * r) & (b < 0.35 * r)


@pytest.mark.timeout(300)
@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (.ci/run installs it)")
def test_picture_in_a_real_browser(viewer, tmp_path):
    """Render the live viewer page in headless Chromium: the catheter's orange tube must cover a stretch of
    the picture where the camera frames it (the middle of the image), and turn grey when the stream is
    stale."""
    viewer.show(arc(), label="arc")
    live = _screenshot(viewer.url, tmp_path / "live.png", tmp_path)
    o = _orange(live)
    assert o.sum() > 500, f"only {o.sum()} catheter-coloured pixels"
    ys, xs = np.nonzero(o)
    # framed on the catheter: the tube spans a good part of the view, around the centre
    assert xs.max() - xs.min() > 80 or ys.max() - ys.min() > 80
    assert 100 < xs.mean() < 700 and 75 < ys.mean() < 525
    viewer.set_state("stale", "no data")
    stale = _screenshot(viewer.url, tmp_path / "stale.png", tmp_path)
    assert _orange(stale).sum() < 0.1 * o.sum()  # recoloured grey
