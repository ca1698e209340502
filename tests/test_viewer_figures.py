"""What the viewer's page says and shows (issue 23 A1, A2, A12): the calibration in use, a run that ended (its
final frame count, the measured arrival rate), and a sub-millimetre error made visible — the error along the
catheter as a plot, and the deviation from the truth magnified by a stated factor — checked in a real browser
(Debian's headless chromium), pixel by pixel.

No timing asserts: figures are compared with the loop's own summary, waits are hang guards.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from test_viewer import (
    CHROMIUM,
    H,
    W,
    arc,
    chromium,
    distance_to_polyline,
    gone,
    magenta,
    near,
    project,
    screenshot,
    truth_of,
)

from twin import Calibration, Reconstructor
from twin.cli import main
from twin.live import LiveLoop
from twin.synthetic import SyntheticSource
from twin.viewer import Viewer, ViewerConfig, ViewerSink
from twin.viewer import geometry as geo


@pytest.fixture
def viewer():
    v = Viewer(ViewerConfig(web_port=0, max_fps=float("inf")), announce=None)
    yield v
    v.close()
    assert gone(v.server_pid)


def need_chromium() -> None:
    if CHROMIUM is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing (.ci/run installs Debian's chromium)")
        pytest.skip("chromium is not installed")


# ------------------------------------------------------------------------------------------------------- A1
def test_a_replayed_recording_names_its_stored_calibration(tmp_path, capsys):
    """A1: `twin live replay://run.h5 --viewer` said "calibration none" when the recording stores one."""
    fiber = SyntheticSource().fiber
    Calibration(lambda0=fiber.lambda0 + 0.01).save(tmp_path / "cal.toml")
    run = tmp_path / "run.h5"
    assert main(["live", "synthetic://?rate=500", "--frames", "20", "--calibration", str(tmp_path / "cal.toml"),
                 "--record", str(run), "--quiet", "--json"]) == 0
    capsys.readouterr()
    assert main(["live", f"replay://{run}", "--frames", "10", "--viewer", "--quiet", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["viewer_calibration"] == f"the source's (replay://{run})"
    # given a file, it names the file; with neither, the viewer says none
    assert main(["live", f"replay://{run}", "--frames", "10", "--viewer", "--quiet", "--json", "--calibration",
                 str(tmp_path / "cal.toml")]) == 0
    assert json.loads(capsys.readouterr().out)["viewer_calibration"] == "cal.toml"
    assert main(["live", "synthetic://?rate=500", "--frames", "10", "--viewer", "--quiet", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["viewer_calibration"] == "none"


# ------------------------------------------------------------------------------------------------------- A2
def test_the_page_says_the_run_ended_with_the_terminals_frame_count_and_the_measured_rate(viewer):
    """A2: the page stayed "live" after the end, its frame count lagged the terminal's (449 vs 450), and it
    showed the nominal rate (50.0 Hz) while 13.5 frames/s arrived."""
    sink = ViewerSink(viewer, rate=5.0, close_viewer=False)  # a low drawing rate: the last frames are skipped
    src = SyntheticSource(rate=1000, pace=True)
    seen = []  # the final status every sink is given (the summary's is taken later, after the sinks closed)
    summary = LiveLoop(src, Reconstructor(src.fiber), [sink, lambda f, sh, st: seen.append(st)]).run(
        max_frames=300, handle_signals=False)
    s = seen[-1]
    assert summary.sink_errors == () and sink.errors == 0 and s.state == "ended"
    assert s.frames == summary.status.frames == 300
    hud = viewer.hud()
    figures = dict(hud["figures"])
    assert hud["state"] == "ended"
    assert hud["state_text"] == f"ENDED ({s.frames} frames in {s.elapsed:.1f} s)"
    assert figures["frames"] == str(s.frames)  # what the terminal's summary says
    assert figures["arrival rate"] == f"{s.frames / s.elapsed:.1f} frames/s"  # measured, over the run
    assert figures["source rate"] == f"{s.rate_hz:.1f} Hz"  # the source's own, said as such
    # the server holds it too: what a browser opening now is sent
    html = viewer._client.static_html()
    assert json.dumps(hud["state_text"]) in html and json.dumps(figures["arrival rate"]) in html


# ------------------------------------------------------------------------------------------------------ A12
def test_round_factors_and_axis_ends():
    assert geo.magnification(1e-4, 10e-3) == 100.0
    assert geo.magnification(3e-4, 10e-3) == 20.0  # 33.3 → 20 (1-2-5)
    assert geo.magnification(1.5e-3, 10e-3) == 5.0
    assert geo.magnification(2e-2, 10e-3) == 1.0 and geo.magnification(0.0, 10e-3) == 1.0
    assert geo.magnification(float("nan"), 10e-3) == 1.0
    assert [geo.nice_ceiling(v) for v in (0.105, 0.1, 0.3, 7.0, 1e-5)] == [0.2, 0.1, 0.5, 10.0, 1e-5]


def test_the_overlay_carries_the_error_along_the_catheter_and_the_stated_factor(viewer):
    shape = arc()
    truth = truth_of(shape, offset=1e-4)
    viewer.show(shape, truth)
    hud = viewer.hud()
    p = hud["profile"]
    # 0.1 mm everywhere but at the base (s = 0, where reconstruction and truth meet; the next point, 1 mm on,
    # is a little nearer the truth's first segment): each plotted point the largest error of its stretch
    assert len(p["s"]) == len(p["e"]) == viewer.config.profile_points  # 171 points in 120 stretches
    assert p["e"][0] == 0.0 and 0.09 < p["e"][1] <= 0.1
    np.testing.assert_allclose(p["e"][2:], 0.1, atol=1e-4)
    assert p["s"][0] < 2.0 and p["s"][-1] > 168.0 and p["s_max"] == 170.0 and p["e_max"] == 0.2
    assert viewer.magnification == 100.0 and dict(hud["figures"])["magnified view"] == "deviation × 100"
    assert any("× 100 (magnified)" in text for _, text in hud["legend"])
    viewer.show(shape)  # no truth: neither plot nor magnified view
    assert "profile" not in viewer.hud() and "magnified view" not in dict(viewer.hud()["figures"])


def red(img: np.ndarray) -> np.ndarray:
    """The plot's line (#e60000): the background, grid, viridis, magenta, orange, azure and the dark red text
    all fail it."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 0.8) & (g < 0.2) & (b < 0.2)


def azure(img: np.ndarray) -> np.ndarray:
    """The magnified view's colour (0x0090FF, unlit)."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r < 0.2) & (g > 0.4) & (g < 0.7) & (b > 0.85)


@pytest.mark.timeout(300)
def test_browser_shows_a_tenth_of_a_millimetre_as_a_plot_and_magnified(viewer, tmp_path):
    """A12: at 0.1 mm the magenta truth hides inside the tube. Now the page plots the error along the catheter
    (a flat red line halfway up a 0–0.2 mm axis) and draws the reconstruction's deviation magnified 100 times
    about the truth: 10 mm off, where the test's own geometry puts it (the arc's points moved by 100 × 0.1 mm
    along the base's d2, away from the truth)."""
    need_chromium()
    shape = arc()
    truth = truth_of(shape, offset=1e-4, fixture=False)
    viewer.show(shape, truth, label="tenth of a millimetre")
    assert viewer.magnification == 100.0
    world = shape.positions @ truth.frames[0].T + truth.positions[0]  # placed at the truth's base
    expected = truth.positions + 100.0 * (world - truth.positions)
    px = project(viewer, expected)
    assert np.all((px > 0) & (px < [W, H]))

    img = screenshot(viewer.url, tmp_path, "magnified")
    if not azure(img).any():  # a slow first start of chromium may shoot before the scene arrives: once more
        img = screenshot(viewer.url, tmp_path, "magnified-again")
    mask = azure(img)
    ys, xs = np.nonzero(mask)
    swatch = (xs < 420) & (ys > 380)  # the legend (bottom left) shows its colour too
    assert near(mask, px[1:]).mean() >= 0.8  # drawn along the magnified curve…
    off = distance_to_polyline(np.stack([xs, ys], -1)[~swatch].astype(float), px)
    assert off.max() <= 6  # …and nowhere else
    assert distance_to_polyline(px[len(px) // 2:], project(viewer, truth.positions)).min() > 8  # apart, visibly
    assert near(magenta(img), project(viewer, truth.positions)).mean() >= 0.8  # the truth still on top

    # the plot: a box 280×130 at 28 px from the top, 10 px from the right; plot area x 44..270,
    # y 24 (0.2 mm)..104 (0)
    ry, rx = np.nonzero(red(img))
    left, top = W - 10 - 280, 28
    inside = (rx >= left) & (ry >= top) & (ry < top + 130)
    assert inside.sum() > 100 and inside.mean() > 0.95
    row = np.median(ry[inside]) - top
    assert abs(row - (104 - 80 * 0.1 / 0.2)) <= 2  # 0.1 mm of 0.2
    assert rx[inside].min() - left <= 48 and rx[inside].max() - left >= 266  # along the whole catheter
    dom = chromium(viewer.url, tmp_path, "magnified-dom", "--dump-dom").stdout
    assert "local error (mm) along the catheter (mm)" in dom and "deviation × 100" in dom
