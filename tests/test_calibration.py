"""The two-step calibration (docs/math.md §4.2): reference wavelengths, intrinsic twist, guard rails, files."""

import numpy as np
import pytest

from twin import Calibration, CalibrationError, FiberModel, Reconstructor, shapes, strain
from twin.calibration import nominal_gain, scaled_core_angles, two_step

FIBER = FiberModel.paper()
S = FIBER.grating_s
PHI = np.deg2rad(25.0) * S / 0.17 + np.deg2rad(8.0) * np.sin(2 * np.pi * S / 0.17)  # docs/math.md §4.2's twist
SPREAD = np.random.default_rng(7).normal(scale=0.3, size=(18, 4))  # as-built λ0 offsets, nm


def pose(k, twist=PHI, n=1, noise=0.0, seed=0, **kw):
    w = strain.forward(FIBER, k, twist=twist, lambda0=FIBER.lambda0 + SPREAD, **kw)
    w = np.repeat(w[None], n, axis=0)
    return w + np.random.default_rng(seed).normal(scale=noise, size=w.shape) if noise else w


def arc(kappa=16.0, alpha=0.7):
    return np.tile(kappa * np.array([np.cos(alpha), np.sin(alpha)]), (18, 1))


def test_recovers_reference_and_twist_exactly_without_noise():
    cal, report = two_step(FIBER, pose(np.zeros((18, 2))), pose(arc()))
    np.testing.assert_allclose(cal.lambda0, FIBER.lambda0 + SPREAD, atol=1e-12)
    np.testing.assert_allclose(cal.twist, PHI - PHI[0], atol=1e-10)  # exact up to float rounding
    np.testing.assert_allclose(report.twist, cal.twist)
    assert report.sign_changes == 0 and report.n_straight == 1


def test_compensation_restores_accuracy_on_a_3d_shape():
    """Uncompensated, 25°+8° of twist costs millimetres (docs/math.md §4.1); compensated, the error is that of an
    untwisted fibre (≤ 0.05 mm noise-free)."""
    cal = Calibration.from_frames(FIBER, pose(np.zeros((18, 2))), pose(arc()))
    c = shapes.get("mixed")
    w = pose(c.curvature(S))[0]
    exact = c.positions(np.linspace(0, 0.17, 171))
    raw = Reconstructor(FIBER, Calibration(lambda0=cal.lambda0))(w)
    fixed = Reconstructor(FIBER, cal)(w)
    assert np.linalg.norm(raw.positions - exact, axis=1).max() > 2e-3
    # the remaining global roll is the twist at grating 0 (docs/math.md §4.2): undo it before comparing
    c0, s0 = np.cos(PHI[0]), np.sin(PHI[0])
    rot = np.array([[c0, -s0, 0], [s0, c0, 0], [0, 0, 1]])
    assert np.linalg.norm(fixed.positions @ rot.T - exact, axis=1).max() < 0.05e-3


def test_averaged_noisy_calibration_and_reported_noise():
    """1 pm noise, 100 frames at κ_cal = 16 1/m: angle noise ≈ σ_k/κ/√100 ≈ 2e-4 rad (docs/math.md §4.2, §6)."""
    cal, rep = two_step(FIBER, pose(np.zeros((18, 2)), n=100, noise=1e-3, seed=1),
                        pose(arc(), n=100, noise=1e-3, seed=2))
    err = np.abs(cal.twist - (PHI - PHI[0]))
    assert err.max() < 1.5e-3
    assert np.all(rep.twist_std > 0.5e-4) and np.all(rep.twist_std < 1e-3)
    assert np.mean(err[1:] < 4 * np.hypot(rep.twist_std[1:], rep.twist_std[0])) > 0.9  # the report covers it
    assert 0.5e-3 < np.median(rep.lambda0_std) < 1.5e-3  # the interrogator noise is what was measured


def test_inflection_is_refused_then_unwrapped_modulo_pi_on_request():
    k = np.outer(np.linspace(-20, 25, 18), [np.cos(0.3), np.sin(0.3)])  # an S-bend: sign change
    k[np.abs(k[:, 0]) < 6] *= 6 / np.abs(k[np.abs(k[:, 0]) < 6, 0])[:, None]  # keep |k| above the floor
    with pytest.raises(CalibrationError, match="flips at grating"):
        two_step(FIBER, pose(np.zeros((18, 2))), pose(k))
    cal, rep = two_step(FIBER, pose(np.zeros((18, 2))), pose(k), allow_sign_change=True)
    assert rep.sign_changes == 1
    np.testing.assert_allclose(cal.twist, PHI - PHI[0], atol=1e-10)


@pytest.mark.parametrize(
    ("straight", "bend", "message"),
    [
        (pose(np.zeros((18, 2))), pose(arc(kappa=2.0)), "bent only 2.00 1/m"),
        (pose(np.zeros((18, 2))), np.concatenate([pose(arc(16.0)), pose(arc(22.0))]), "hold the catheter still"),
        (pose(np.zeros((18, 2))), pose(arc())[..., :3], "expected frames of shape"),
    ],
)
def test_guard_rails(straight, bend, message):
    with pytest.raises(CalibrationError, match=message):
        two_step(FIBER, straight, bend)


def test_missing_peaks_in_calibration_frames():
    bend = pose(arc(), n=10)
    bend[:2, 4, 2] = np.nan  # occasional loss: averaged over
    cal, report = two_step(FIBER, pose(np.zeros((18, 2)), n=10), bend)
    # the frames are noise-free copies, so the 8 frames left at that peak carry the exact wavelength: the result
    # is the noise-free one (test_recovers_reference_and_twist_exactly_without_noise), to float rounding
    np.testing.assert_allclose(cal.lambda0, FIBER.lambda0 + SPREAD, atol=1e-12)
    np.testing.assert_allclose(cal.twist, PHI - PHI[0], atol=1e-10)
    assert report.n_straight == 10
    bend[:, 4, 2] = np.nan  # always lost: refused, naming the grating and core
    with pytest.raises(CalibrationError, match=r"grating 4 \(s = 40.0 mm\) core 2 lost its peak in 100%"):
        two_step(FIBER, pose(np.zeros((18, 2)), n=10), bend)


def test_identified_parameters_enter_the_design():
    cal = Calibration(delta_theta=1.039, gain=28.01e-6)
    angles = scaled_core_angles(FIBER, 1.039)
    np.testing.assert_allclose(angles, [0.0, 0.0, 1.039, 2.078])
    true = FIBER.replace(core_angles=angles, strain_sensitivity=0.777 * 28.01e-6 / nominal_gain(FIBER))
    k = shapes.get("rotating-bend").curvature(S)
    w = strain.forward(true, k)
    np.testing.assert_allclose(Reconstructor(FIBER, cal).curvature(w).curvature, k, atol=1e-8)
    assert np.abs(Reconstructor(FIBER).curvature(w).curvature - k).max() > 0.5


def test_toml_round_trip_and_mismatch(tmp_path):
    cal = Calibration(lambda0=FIBER.lambda0 + SPREAD, twist=PHI - PHI[0], delta_theta=1.039, gain=2.8e-5,
                      delta_theta_std=1e-4, gain_std=1e-8, provenance={"method": "test", "frames": 3})
    cal.save(tmp_path / "c.toml")
    back = Calibration.load(tmp_path / "c.toml")
    np.testing.assert_array_equal(back.lambda0, cal.lambda0)
    np.testing.assert_array_equal(back.twist, cal.twist)
    assert (back.delta_theta, back.gain, back.provenance) == (1.039, 2.8e-5, {"method": "test", "frames": 3})
    other = FiberModel.paper().replace(grating_s=FIBER.grating_s[:10], lambda0=FIBER.lambda0[:10])
    with pytest.raises(ValueError, match="made for another sensor"):
        Reconstructor(other, back)
    (tmp_path / "bad.toml").write_text("gain = 29.1\n")
    with pytest.raises(ValueError, match=r"bad.toml: Calibration.gain: expected a value in .* m \(r·S_ε"):
        Calibration.load(tmp_path / "bad.toml")


# ------------------------------------------------------------------ files (issue 11 item 10, issue 14: floats)


def test_a_calibration_for_another_fiber_names_both_files(tmp_path, capsys):
    from twin.cli import main

    other = FiberModel.paper().replace(grating_s=0.01 * np.arange(3), lambda0=FiberModel.paper().lambda0[:3])
    other.save(tmp_path / "other.toml")
    Calibration(lambda0=other.lambda0).save(tmp_path / "cal.toml")
    FiberModel.paper().save(tmp_path / "fiber.toml")
    code = main(["live", "synthetic://?rate=1000&pace=max", "--fiber", str(tmp_path / "fiber.toml"),
                 "--calibration", str(tmp_path / "cal.toml"), "--frames", "3", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err
    assert f"{tmp_path / 'cal.toml'}: calibration field lambda0 has shape (3, 4)" in err
    assert f"fibre model ({tmp_path / 'fiber.toml'}) has 18 gratings × 4 cores" in err


@pytest.mark.parametrize("line, field", [("delta_theta = true", "delta_theta"), ("twist = {a = 1}", "twist"),
                                         ("gain = [2.9e-5]", "gain"), ("provenance = 3", "provenance")])
def test_a_wrong_type_in_a_calibration_file_names_file_and_field(tmp_path, line, field):
    path = tmp_path / "cal.toml"
    path.write_text(line + "\n")
    with pytest.raises(ValueError, match=rf"^{path}: {field}: expected "):
        Calibration.load(path)


def test_calibration_files_round_trip_exactly(tmp_path):
    awkward = np.array([0.1 + 0.2, 1 / 3, 1e-300, 5e-324, -0.0, 1510.1080899999997, 2.0**-30, 1e16 + 2])
    # lambda0 within the Bragg range (200–3000 nm, issue 23 B16), its digits still awkward
    cal = Calibration(lambda0=np.abs(awkward[:, None]) % 1000 + 1500.0, twist=awkward, delta_theta=1 / 3,
                      gain=2.9e-5 / 3, provenance={"note": "round trip"})
    cal.save(tmp_path / "cal.toml")
    back = Calibration.load(tmp_path / "cal.toml")
    for name in ("lambda0", "twist"):
        a, b = getattr(cal, name), getattr(back, name)
        assert a.tobytes() == b.tobytes()  # bit for bit, the sign of -0.0 included
    assert back.delta_theta == cal.delta_theta and back.gain == cal.gain


def test_two_step_lambda0_carries_the_mean_not_its_summation_error(tmp_path):
    """Issue 14: cal.toml held values like 1510.1080899999997 — one ulp off the mean 1510.10809 of
    wavelengths quantised at 1e-4 nm, left by summing in binary."""
    fiber = FiberModel.paper()
    rng = np.random.default_rng(3)
    k_bend = np.tile([20.0, 3.0], (fiber.n_gratings, 1))
    straight = np.round((strain.forward(fiber, np.zeros((18, 2))) + 1e-3 * rng.standard_normal((100, 18, 4))) * 1e4)
    bend = np.round((strain.forward(fiber, k_bend) + 1e-3 * rng.standard_normal((100, 18, 4))) * 1e4)
    cal, _ = two_step(fiber, straight / 1e4, bend / 1e4)
    exact = straight.mean(axis=0, dtype=np.float64) / 1e4  # integers sum exactly: the true decimal mean
    np.testing.assert_allclose(cal.lambda0, exact, rtol=0, atol=5e-10)  # 1e-9 nm resolution, nothing more lost
    cal.save(tmp_path / "cal.toml")
    import re

    values = re.findall(r"\b1[5-6]\d\d\.(\d+)", (tmp_path / "cal.toml").read_text())
    assert len(values) == 72 and max(len(v) for v in values) <= 9  # no 1510.1080899999997
    assert Calibration.load(tmp_path / "cal.toml").lambda0.tobytes() == cal.lambda0.tobytes()


def test_a_calibration_in_micrometres_fails_in_one_line(tmp_path):
    """Issue 23 B16: `lambda0` had no range check; a calibration in µm ran, exit 0, every frame unusable."""
    import subprocess
    import sys

    import tomli_w
    from io_helpers import synthetic_frames

    from twin.io.record import Recorder

    data = Calibration(lambda0=FIBER.lambda0).to_dict()
    data["lambda0"] = (np.asarray(data["lambda0"]) * 1e-3).tolist()  # µm
    (tmp_path / "um.toml").write_text(tomli_w.dumps(data))
    with pytest.raises(ValueError, match=rf"^{tmp_path / 'um.toml'}: Calibration.lambda0: grating 0 core 0 has "
                                         r"1.51 nm; expected a Bragg wavelength in nm \(200–3000\)"):
        Calibration.load(tmp_path / "um.toml")
    rec = tmp_path / "r.h5"
    with Recorder(rec, fiber=FiberModel.paper()) as r:
        r.append(synthetic_frames(5))
    proc = subprocess.run([sys.executable, "-m", "twin.cli", "replay", str(rec), "--calibration",
                           str(tmp_path / "um.toml")], capture_output=True, text=True, timeout=100)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "um.toml" in proc.stderr, proc.stderr


def test_a_spun_fiber_of_one_grating_fails_naming_the_field(tmp_path):
    """Issue 23, also seen: numpy's bare "Singular matrix" (the spin-rate fit of a one-grating spun fibre)."""
    from twin.calibration import CalibrationError
    from twin.synthetic import SyntheticSource

    FIBER.replace(grating_s=[0.05], lambda0=FIBER.lambda0[:1], spin_rate=10.0).save(tmp_path / "one.toml")
    one = FiberModel.load(tmp_path / "one.toml")
    bend = np.stack([f.wavelengths for f in SyntheticSource(fiber=one, pace=False, frames=20, kappa_amp=0, spin=0)])
    with pytest.raises(CalibrationError, match=rf"^{tmp_path / 'one.toml'}: FiberModel.grating_s: a spun fibre's "
                                               "spin rate .* needs 2 or more; this one has 1"):
        two_step(one, one.lambda0[None] + np.zeros((5, 1, 4)), bend)
