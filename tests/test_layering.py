"""The architecture holds: imports flow scenarios → sim_interrogator → models → twin, never back, and the sensing
core imports without the optional packages."""

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: package → packages it must never import
FORBIDDEN = {
    "twin": {"models", "sim_interrogator", "scenarios"},
    "models": {"sim_interrogator", "scenarios"},
    "sim_interrogator": {"scenarios"},
}
OPTIONAL = ("mujoco", "meshcat", "matplotlib", "h5py", "dask", "distributed", "pyarrow", "zmq", "tornado", "umsgpack",
            "mcap", "zstandard", "lz4", "foxglove", "rosbags", "mcap_ros2")


def _imports(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module


def test_no_import_points_back_up_the_layers():
    bad = []
    for package, forbidden in FORBIDDEN.items():
        for path in sorted((ROOT / package).rglob("*.py")):
            for line, name in _imports(path):
                if name.split(".")[0] in forbidden:
                    bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    assert not bad, "\n".join(bad)


def test_the_core_names_no_module_above_it_in_strings():
    """Schemes, scenarios and commands above the core register through entry points, not strings in twin/."""
    bad = []
    for path in sorted((ROOT / "twin").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                text = node.value.strip()
                if any(text.startswith(f"{p}.") or text.startswith(f"{p}:") for p in FORBIDDEN["twin"]):
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno} {text!r}")
    assert not bad, "\n".join(bad)


BLOCK = f"""
import importlib, importlib.abc, pkgutil, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {OPTIONAL!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, Block())
import twin
names = [m.name for m in pkgutil.walk_packages(twin.__path__, "twin.") if not m.name.endswith("__main__")]
for name in names:
    importlib.import_module(name)
assert not any(m.split(".")[0] in {OPTIONAL!r} for m in sys.modules), "an optional package got imported"
print(len(names))
"""


def test_every_twin_module_imports_without_the_optional_packages():
    out = subprocess.run([sys.executable, "-c", BLOCK], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.strip()) > 30


def test_a_command_that_needs_a_missing_extra_says_which_in_one_line():
    code = BLOCK.split("import twin\n")[0] + "from twin.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    out = subprocess.run([sys.executable, "-c", code, "run", "static-shapes"], capture_output=True, text=True,
                         cwd=ROOT, timeout=120)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "'sim' extra" in lines[0], out.stderr
    # the hint installs the way the README does, from a checkout (issue 23 A11), and the README quotes it
    assert lines[0].endswith("pip install '.[sim]' from a catheter-twin checkout"), lines[0]
    readme = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    assert lines[0] in readme


def test_no_scenario_imports_another():
    """Scenarios share code through scenarios/_common and scenarios/report.py only."""
    shared = {"scenarios._common", "scenarios.report", "scenarios.studies"}
    bad = []
    for path in sorted((ROOT / "scenarios").glob("*.py")):
        for line, name in _imports(path):
            if name.startswith("scenarios.") and not any(name == s or name.startswith(s + ".") for s in shared):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    assert not bad, "\n".join(bad)
