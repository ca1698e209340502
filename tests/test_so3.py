"""The compiled SO(3) exponential and logarithm (twin.so3) against scipy's Rotation."""

import numpy as np
from scipy.spatial.transform import Rotation

from twin import so3


def test_exp_matches_scipy_and_log_inverts_it():
    rng = np.random.default_rng(0)
    # angles from 0 through the Taylor branch (t < 0.2) to near π
    phi = rng.normal(size=(500, 3))
    phi *= (np.geomspace(1e-9, 3.1, 500) / np.linalg.norm(phi, axis=1))[:, None]
    r = so3.exp(phi)
    assert np.abs(r - Rotation.from_rotvec(phi).as_matrix()).max() < 1e-14
    assert np.abs(so3.log(r) - phi).max() < 1e-12
    assert so3.exp(phi.reshape(50, 10, 3)).shape == (50, 10, 3, 3)


def test_exp_of_a_quarter_turn_about_z():
    r = so3.exp([0.0, 0.0, np.pi / 2])
    assert np.allclose(r, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)


def test_exp_coefficients_series_joins_closed_form():
    # at the branch point t = 0.2 the Taylor series and the closed form agree to rounding
    t2 = 0.04
    below = so3.exp_coefficients(t2 * (1 - 1e-12))
    above = so3.exp_coefficients(t2)
    assert np.allclose(below, above, rtol=1e-12, atol=0)
