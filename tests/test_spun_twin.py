"""A spun fibre in the twin: the optics' exact helical path lengths against the linear model on a straight fibre
(noise and peak loss included), the grating-length average, and the SimInterrogator reading the rod's own twist
(docs/spun-fibers.md §6)."""

import numpy as np
import pytest

from sim_interrogator.optics import Optics, OpticsConfig
from sim_interrogator.setups import StaticShape
from sim_interrogator.sim import SimInterrogator
from twin import FiberModel, Reconstructor, spun

SPUN = FiberModel.spun(50.0)
RNG = np.random.default_rng(0)
K = RNG.uniform(-40, 40, (6, 18, 2))
TAU = RNG.uniform(-15, 15, (6, 18))


@pytest.mark.parametrize("cfg", [
    OpticsConfig(grating_length=0.0, seed=4),
    OpticsConfig.ideal(min_peak_separation=1.0, band=(1512.0, 1600.0), noise=1e-3, seed=5),
])
def test_the_spun_path_on_a_straight_fiber_is_the_linear_model_with_the_same_effects(cfg):
    """With Ω = 0 and τ = 0 the exact path length is the linear model, so the spun path (exact strains) and the
    design form must give the same wavelengths, noise, drift, quantisation and lost peaks from the same seed
    (both go through the one compiled effects kernel; the strains differ only by rounding)."""
    fiber = FiberModel.paper()
    a, b = Optics(fiber, cfg), Optics(fiber, cfg)
    k = K.copy()
    k[0, 7], k[0, 8] = [-60.0, 0.0], [60.0, 0.0]  # a kink: neighbouring peaks merge
    for t in (0.0, 0.5, 1.0):
        wa, sa = a.wavelengths(k, 1e-4, 3.0, t=t)
        wb, sb = b.spun_wavelengths(k, 0.0, 1e-4, 3.0, t=t)
        np.testing.assert_array_equal(sa, sb)
        np.testing.assert_allclose(wa, wb, rtol=0, atol=1e-9, equal_nan=True)
    assert sa.any() or cfg.min_peak_separation == 0


def test_ideal_spun_optics_are_the_exact_path_length_and_invert():
    o = Optics(SPUN, OpticsConfig.ideal(grating_length=0.0))
    w, status = o.wavelengths(K, 2e-4, 5.0, twist_rate=TAU)
    e = SPUN.strain_sensitivity * spun.exact_strain(SPUN, K, TAU, 2e-4) + 5.0 * SPUN.temperature_sensitivity
    np.testing.assert_allclose(w, SPUN.lambda0 * (1 + e), rtol=0, atol=1e-12)
    assert not status.any()
    sol = Reconstructor(SPUN, o.true_calibration()).curvature(w)
    # the reconstruction's residual model error (docs/spun-fibers.md §2): O(sin²α κ²/Ω) and −Ω ε_0 in τ
    np.testing.assert_allclose(sol.twist_rate, TAU - SPUN.spin_omega * 2e-4, atol=3e-3)
    np.testing.assert_allclose(sol.curvature, K, rtol=1e-4, atol=1e-4)
    # a straight-core call without twist still works for a spun fibre (τ = 0): what it reads as twist is the
    # linear model's second-order bending error, sin²α κ²/(4Ω) per grating (docs/spun-fibers.md §2; ≤ 3e-4
    # rad/m here); the next order is smaller by O(r κ) ≤ 2e-3, so 2e-6 rad/m is a bound with a margin of 3
    w0, _ = o.wavelengths(K[0])
    r, omega = max(SPUN.core_radii), SPUN.spin_omega
    sin2a = (r * omega) ** 2 / (1 + (r * omega) ** 2)
    predicted = sin2a * np.sum(K[0] ** 2, axis=-1) / (4 * omega)
    np.testing.assert_allclose(Reconstructor(SPUN).curvature(w0).twist_rate, predicted, rtol=0, atol=2e-6)


def test_the_grating_length_turns_the_cores_and_the_true_calibration_absorbs_it():
    """Over a 1 mm grating the cores turn by Ω l = 0.31 rad: the bending strain averages to sinc(Ω l/2) =
    0.9959 of its value; the true calibration's gain carries it."""
    o = Optics(SPUN, OpticsConfig.ideal(grating_length=1e-3))
    k = np.tile([25.0, -10.0], (18, 1))
    w, _ = o.wavelengths(k, twist_rate=np.full(18, 4.0))
    nominal = Reconstructor(SPUN).curvature(w)
    half = SPUN.spin_omega * 1e-3 / 2
    np.testing.assert_allclose(nominal.curvature, k * np.sin(half) / half, rtol=1e-5)
    true = Reconstructor(SPUN, o.true_calibration()).curvature(w)
    np.testing.assert_allclose(true.curvature, k, rtol=1e-5)
    # the twist column is scaled with the gain: 0.4 % of 4 rad/m
    np.testing.assert_allclose(true.twist_rate, 4.0, atol=0.02)


def test_spin_error_is_found_by_the_true_calibration():
    o = Optics(SPUN, OpticsConfig.ideal(spin_error=0.3))
    assert o.true_fiber.spin_rate == pytest.approx(50.3)
    assert o.true_calibration().spin_rate == pytest.approx(50.3)


def test_sim_interrogator_reads_the_rods_twist():
    """A spun fibre in a helix held by connect constraints, twisted by a known 8 rad/m (the rod's twist joints
    turned along it before the frame is read): the wavelengths carry the rod's own twist rate (the Darboux
    vector's tangential component), which the reconstruction recovers; the straight-core fibre sees none of it."""
    mujoco = pytest.importorskip("mujoco")
    sim = SimInterrogator(StaticShape("helix", "connect"), SPUN, OpticsConfig.ideal(), rate=200.0)
    name = sim.setup.rod_name
    n_edges = sim.reader.n_vertices - 1
    for e in range(n_edges):
        j = mujoco.mj_name2id(sim.model, mujoco.mjtObj.mjOBJ_JOINT, f"{name}_twist_{e}")
        if j >= 0:
            sim.data.qpos[sim.model.jnt_qposadr[j]] += 8.0 * sim.reader.edge_s[e]
    frame = sim.read()  # the first frame: no physics step, the imposed twist is read as it is
    truth = frame.truth
    assert np.all(np.abs(truth.twist - 8.0) < 0.5)
    rec = Reconstructor(SPUN, sim.optics.true_calibration())
    sol = rec.curvature(frame)
    # ideal optics, no noise: what is left is the linear model's error (docs/spun-fibers.md §2). In curvature:
    # a twist τ turns the helix and changes the bending gain by ≈ r²Ωτ (3e-6 at 8 rad/m), ≈ 1.3e-4 1/m at the
    # helix's 40 1/m; in twist: sin²α κ²/(4Ω), ≈ 1.5e-4 rad/m. Both bounds below are those predictions × 1.5
    r, omega = max(SPUN.core_radii), SPUN.spin_omega
    kappa = np.linalg.norm(truth.curvature, axis=-1).max()
    sin2a = (r * omega) ** 2 / (1 + (r * omega) ** 2)
    np.testing.assert_allclose(sol.curvature, truth.curvature, rtol=0,
                               atol=1.5 * r**2 * omega * np.abs(truth.twist).max() * kappa)
    np.testing.assert_allclose(sol.twist_rate, truth.twist, rtol=0, atol=1.5 * sin2a * kappa**2 / (4 * omega))
    tip = rec.twist_angle(frame)[-1]
    assert tip == pytest.approx(np.trapezoid(truth.twist, SPUN.grating_s), rel=0.02)


def test_spun_twist_scenario_small_run_measures_the_groove_twist():
    """One groove shape, ideal optics: the spun fibre with its twist measured beats itself with the twist ignored
    (the reconstruction placed by the rod's base pose, so the groove's sub-degree wind-up shows), and the JSON
    summary has the issue's keys with finite numbers."""
    from scenarios import spun_twist

    params = spun_twist.Params(shapes=("arc",), repeats=1, rotation=False, spin_rates=(50.0,), noises=(1e-3,),
                               optics="ideal")
    result = spun_twist.run_experiment(params)
    s = result["summary"]
    for key in ("max_error_mm_twist_measured", "max_error_mm_twist_ignored", "tip_twist_rms_error_deg",
                "straight_cores_max_error_mm"):
        assert isinstance(s[key], float) and np.isfinite(s[key])
    assert s["max_error_mm_twist_measured"] < 0.5 * s["max_error_mm_twist_ignored"]
    assert s["tip_twist_rms_error_deg"] < 0.05 * s["true_tip_twist_max_abs_deg"]
    row = result["resolution"]["table"][0]
    assert row["tau_std_rad_per_m"] == pytest.approx(2.49, abs=0.01)


def test_spun_twist_cli_refuses_a_straight_spin_rate(capsys):
    from twin.cli import main

    assert main(["run", "spun-twist", "--spin", "0"]) == 2
    assert "non-zero" in capsys.readouterr().err
