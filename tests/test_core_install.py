"""A lab with hardware only: `pip install .` without extras gives a working sensing core (issue 10's acceptance).

Slow (it builds a fresh virtual environment): a reconstruction from Python, `twin live synthetic://`, `twin replay`
of an ILLumiSense log written here by hand, `twin jig-validate` on the real AMIRo table, `twin run real-jig` from
the installed package data (not a checkout: `tests/` is not copied); mujoco is absent, and a
command that needs the simulator names the extra in one line (exit status 2).
"""

import json
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
AMIRO = ROOT / "twin" / "data" / "jig" / "amiro"

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def core(tmp_path_factory):
    base = tmp_path_factory.mktemp("core")
    # a copy, so that the build leaves nothing in the checkout
    src = base / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".venv", ".git", "build", "*.egg-info", "__pycache__",
                                                             ".pytest_cache", ".ruff_cache", "tests"))
    env_dir = base / "venv"
    venv.create(env_dir, with_pip=True)
    py = env_dir / "bin" / "python"
    out = subprocess.run([str(py), "-m", "pip", "install", "--quiet", str(src)], capture_output=True, text=True,
                         timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    return env_dir / "bin"


def _log_line(seq: int, lam0: np.ndarray) -> str:
    """One ILLumiSense record as a lab logger saves it (channel blocks only), written field by field."""
    g, c = lam0.shape
    fields = ["2026/12/01", f"12:00:{seq % 60:02d}", str(seq), str(c)]
    for ch in range(c):
        fields += [str(ch + 1), str(g), "0", "0", "0", "0"]
        fields += [f"{v:.4f}" for v in lam0[:, ch]]
        fields += ["-20.00"] * g
    return "\t".join(fields) + "\r\n"


def _close(a, b, rel: float) -> bool:
    """Nested JSON values equal, numbers to ``rel`` (dicts, lists, strings, None, bools)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k], rel) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_close(x, y, rel) for x, y in zip(a, b, strict=True))
    if isinstance(a, int | float) and isinstance(b, int | float) and not isinstance(a, bool):
        return a == pytest.approx(b, rel=rel)
    return a == b


def test_the_core_works_without_extras(core, tmp_path):
    def run(*args, **kw):
        return subprocess.run([str(core / args[0]), *args[1:]], capture_output=True, text=True, cwd=tmp_path,
                              timeout=300, **kw)

    assert run("python", "-c", "import mujoco").returncode != 0
    for missing in ("h5py", "meshcat", "matplotlib"):
        assert run("python", "-c", f"import {missing}").returncode != 0, missing

    code = ("import numpy as np; from twin import FiberModel, Reconstructor, strain; f = FiberModel.paper(); "
            "s = Reconstructor(f)(strain.forward(f, np.tile([20.0, 0.0], (f.n_gratings, 1)))); "
            "print(s.positions[-1, 2])")
    out = run("python", "-c", code)
    assert out.returncode == 0, out.stderr
    # an arc of 20 1/m over 0.17 m ends at z = sin(3.4)/20
    assert abs(float(out.stdout) - np.sin(3.4) / 20) < 1e-5

    out = run("twin", "live", "synthetic://?rate=200&frames=100", "--json")
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)  # the source's 100 frames, all reconstructed, none lost
    assert summary["reason"] == "source ended" and summary["frames"] == 100
    assert summary["lost_samples"] == 0 and summary["frames_unusable"] == 0

    from twin import FiberModel

    lam0 = FiberModel.paper().lambda0
    log = tmp_path / "log.txt"
    log.write_text("".join(_log_line(k, lam0) for k in range(1, 31)))
    out = run("twin", "replay", str(log), "--json")
    assert out.returncode == 0, out.stderr
    assert '"frames": 30' in out.stdout

    argv = ["jig-validate", str(AMIRO / "poses.csv"), "--calibration", str(AMIRO / "calibration.toml"),
            "--fiber", str(AMIRO / "needle.toml"), "--json"]
    out = run("twin", *argv)
    assert out.returncode in (0, 1), out.stderr  # 1: the real needle misses the acceptance goal; not an error
    # the core install computes what the full install computes (the same table, calibration and code; only the
    # float rounding of another numpy/BLAS build may differ, far below 1e-9 relative), and the exit status
    # says what "passes" says (1 when a goal is missed; null: no goal to judge, status 0)
    full = subprocess.run([sys.executable, "-m", "twin.cli", *argv], capture_output=True, text=True, timeout=300)
    core_json, full_json = json.loads(out.stdout), json.loads(full.stdout)
    assert len(core_json["results"]) == len(full_json["results"]) > 0
    for a, b in zip(core_json["results"], full_json["results"], strict=True):
        assert a["model"] == b["model"] and a["passes"] == b["passes"]
        assert _close(a["validation"]["summary"], b["validation"]["summary"], rel=1e-9), a["model"]
    assert out.returncode == full.returncode == (1 if core_json["passes"] is False else 0)

    # issue 23 A9: the real jig table is package data, there after a non-editable install (no tests/ installed)
    out = run("twin", "run", "real-jig", "--seeds", "1", "--json")
    assert out.returncode in (0, 1), out.stderr  # 1: a ratio outside the factor with one seed; not an error
    real = json.loads(out.stdout)["real"]
    assert real["loro_kappa_error_1_per_m"] > 0 and real["rms_strain_residual"] > 0

    for command in (["run", "static-shapes"], ["demo"]):
        out = run("twin", *command)
        lines = out.stderr.strip().splitlines()
        assert out.returncode == 2 and len(lines) == 1, out.stderr
        assert "'sim' extra" in lines[0] and "pip install '.[sim]' from a catheter-twin checkout" in lines[0]
    out = run("twin", "live", "synthetic://", "--duration", "0.2", "--record", "r.h5")
    assert out.returncode == 2 and "'record' extra" in out.stderr
