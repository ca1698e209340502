"""The rod read at the sensor rate (models/_rod_kernels.py, models.rod_state.RodView): the small angles by their
series against the exact formulas, and a sleeping rod's read kept bit for bit."""

import numpy as np

from models import _rod_kernels
from models.fixtures import wake
from sim_interrogator.setups import StaticShape
from sim_interrogator.sim import SimInterrogator
from twin import so3

ULP = np.finfo(float).eps  # 2.2e-16


def test_sin_cos_series_within_rounding_up_to_its_bound():
    """sin and cos of |d| ≤ 0.5 rad by their series (truncation ≤ 2.1e-20 and 7.3e-19): within 2 ulp of the
    library's over the whole range, the ends included."""
    d = np.concatenate([np.linspace(-0.5, 0.5, 20001), [0.0, -0.0, 1e-300, 1e-8, 0.5, -0.5]])
    got = np.array([_rod_kernels._sin_cos_small(v) for v in d])
    np.testing.assert_allclose(got[:, 0], np.sin(d), rtol=2 * ULP, atol=0)
    np.testing.assert_allclose(got[:, 1], np.cos(d), rtol=0, atol=2 * ULP)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    return so3.exp(axis / np.linalg.norm(axis) * angle)


def _rod_state(rng, ne: int, bend: float, twist_spread: float, turn: float):
    """Inputs of frames_and_darboux for a rod of ``ne`` edges turning by up to ``bend`` rad per edge, MuJoCo's
    reference frames transported from slightly older tangents, and twist angles spanning ``twist_spread`` rad
    along it around ``turn`` rad (the clamped edge's is 0)."""
    t = np.empty((ne, 3))
    t[0] = [0.0, 0.0, 1.0]
    for e in range(1, ne):
        t[e] = _rotation(rng.normal(size=3), rng.uniform(0, bend)) @ t[e - 1]
    x = np.concatenate([[np.zeros(3)], np.cumsum(t * rng.uniform(1.5e-3, 2.5e-3, (ne, 1)), axis=0)])
    t_old = t + rng.normal(scale=1e-3, size=t.shape)
    t_old /= np.linalg.norm(t_old, axis=1, keepdims=True)
    u = np.cross(t_old, rng.normal(size=3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    plastic = np.concatenate([t_old, u], axis=1).ravel()
    # twisted along its length, and turned by ``turn`` against the clamped edge
    theta = turn + np.linspace(-0.5, 0.5, ne) * twist_spread + rng.normal(scale=1e-3, size=ne)
    theta[0] = 0.0  # the clamped edge has no joint
    site_x = rng.normal(size=3)
    return x, plastic, theta, site_x, rng.uniform(400, 700, ne - 1)


def test_series_read_is_the_exact_read_to_rounding():
    """The read with series (series_frames_and_darboux) against the exact one (frames_and_darboux) over rods that stay
    within the series' bounds, rods whose twist angles span more than 1 rad (exact sine and cosine for edges
    beyond ±0.5 rad of the middle: a long twist, or the rod turned against its clamped edge) and rods bent by up
    to 0.6 rad per edge (the exact logarithm beyond 0.298 rad): frames within 2e-15, Darboux vectors within 1e-12
    1/m (rounding of the frames over l̄ ≈ 2 mm)."""
    rng = np.random.default_rng(7)
    for bend, spread, turn, site in [(0.12, 1e-5, 0.0, True), (0.25, 0.9, 0.1, True), (0.1, 4.0, 0.0, True),
                                     (0.05, 0.1, 2.5, True), (0.6, 0.5, 0.0, True), (0.32, 0.5, 0.0, True),
                                     (0.05, 0.2, 0.0, False), (0.0, 0.0, 0.0, True)]:
        for _ in range(5):
            x, plastic, theta, site_x, inv_lbar = _rod_state(rng, 100, bend, spread, turn)
            if not site:
                site_x = np.zeros(3)
            ne = theta.size
            frames, darboux = np.empty((ne, 3, 3)), np.empty((ne - 1, 3))
            frames_s, darboux_s = np.empty((ne, 3, 3)), np.empty((ne - 1, 3))
            scratch = np.full((_rod_kernels.SCRATCH_ROWS, ne), np.nan)
            _rod_kernels.frames_and_darboux(x, plastic, theta, site_x, inv_lbar, frames, darboux)
            _rod_kernels.series_frames_and_darboux(x, plastic, theta, site_x, inv_lbar, frames_s, darboux_s, scratch)
            np.testing.assert_allclose(frames_s, frames, rtol=0, atol=2e-15)
            np.testing.assert_allclose(darboux_s, darboux, rtol=0, atol=1e-12)
            assert np.abs(darboux).max() > 0 or bend == 0.0


def _frames(sim: SimInterrogator, n: int) -> list:
    return [sim.read() for _ in range(n)]


def test_a_sleeping_rods_read_is_kept_bit_for_bit():
    """While MuJoCo reports the settled rod asleep, the view keeps its read (no fresh read, frame after frame)
    and every frame — wavelengths, status, timestamp, truth — is bit for bit that of the same twin made to read
    the rod afresh every frame; a changed input is read afresh although MuJoCo still reports the rod asleep, and
    a woken rod is read every frame."""
    def make():
        return SimInterrogator(StaticShape("helix", "connect", segments=40), rate=1000.0)

    kept, fresh = make(), make()
    for _ in range(30):  # MuJoCo puts the rod to sleep within ≈ 10 ms of settling
        kept.read()
        fresh.read()
    assert (kept.data.tree_asleep >= 0).all() and (fresh.data.tree_asleep >= 0).all()
    view, fresh_view = kept._optics_rod, fresh._optics_rod
    reads = view.reads
    for _ in range(40):
        fresh_view._header[0] = 0.0  # forget the kept inputs: the next read is fresh
        a, b = kept.read(), fresh.read()
        np.testing.assert_array_equal(a.wavelengths, b.wavelengths)
        np.testing.assert_array_equal(a.status, b.status)
        assert a.timestamp == b.timestamp
        for name in ("positions", "frames", "curvature", "twist", "temperature"):
            np.testing.assert_array_equal(getattr(a.truth, name), getattr(b.truth, name))
    assert view.reads == reads  # every one of the 40 reads kept
    assert fresh_view.reads >= reads + 40
    assert np.isfinite(a.wavelengths).any()

    # an input that changed is read afresh, MuJoCo's report notwithstanding (and the kept read then describes it)
    frames = view.frames.copy()
    view.positions[7, 0] += 1e-9
    view.compute()
    assert view.reads == reads + 1 and not np.array_equal(view.frames, frames)
    view.positions[7, 0] -= 1e-9
    view.compute()
    np.testing.assert_array_equal(view.frames, frames)

    wake(kept.model)
    _frames(kept, 3)
    reads = view.reads
    _frames(kept, 5)
    assert (kept.data.tree_asleep < 0).all() and view.reads == reads + 5
