"""Names and registration (docs/architecture.md, "Names and registration"): one file name for one job, one
spelling (``fiber``) in identifiers and file names, and one registration mechanism (entry points read by
:mod:`twin.registry`). Also the one rule for independent checks whose tool is missing (tests/conftest.py)."""

from __future__ import annotations

import ast
import inspect
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

from twin import registry

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("twin", "models", "sim_interrogator", "scenarios")
#: file names that may repeat because they are the same role in parallel packages: a package's ``__init__`` and
#: ``__main__``, and ``bench.py``, a package's part of `twin bench` (twin/bench.py: the runner and the
#: ``reconstruct`` section; sim_interrogator/bench.py: the ``sim`` section), and a protocol package's ``codec.py`` and
#: ``driver.py`` (twin/io/illumisense/, hyperion/, fispec/) and its ``stream.py`` (the stream decoder that
#: resynchronises: illumisense/, hyperion/)
SHARED_ROLES = {"__init__.py", "__main__.py", "bench.py", "codec.py", "driver.py", "stream.py"}


def _modules():
    for package in PACKAGES:
        yield from sorted((ROOT / package).rglob("*.py"))


def test_no_two_modules_share_a_file_name_unless_they_play_the_same_role():
    by_name = defaultdict(list)
    for path in _modules():
        by_name[path.name].append(str(path.relative_to(ROOT)))
    clashes = {name: paths for name, paths in by_name.items() if len(paths) > 1 and name not in SHARED_ROLES}
    assert not clashes, clashes


def _identifiers(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            yield node.lineno, node.name
        elif isinstance(node, ast.Name):
            yield node.lineno, node.id
        elif isinstance(node, ast.Attribute):
            yield node.lineno, node.attr
        elif isinstance(node, ast.arg):
            yield node.lineno, node.arg
        elif isinstance(node, ast.keyword) and node.arg:
            yield node.value.lineno, node.arg
        elif isinstance(node, ast.alias):
            yield node.lineno, node.asname or node.name


def test_identifiers_and_file_names_say_fiber():
    """Prose may say "fibre"; names of files, modules, classes, functions, variables, arguments do not."""
    bad = [str(p.relative_to(ROOT)) for p in ROOT.glob("*/**/*") if "fibre" in p.name.lower()
           and ".venv" not in p.parts and ".git" not in p.parts]
    for path in [*_modules(), *sorted((ROOT / "tests").glob("*.py"))]:
        for line, name in _identifiers(ast.parse(path.read_text(encoding="utf-8"))):
            if "fibre" in name.lower():
                bad.append(f"{path.relative_to(ROOT)}:{line} {name}")
    assert not bad, "\n".join(bad)


def test_every_command_is_an_entry_point_with_its_help_and_its_two_functions():
    commands = registry.entries("twin.commands")
    # the core's commands are registered like the others (no second list in twin/cli)
    assert {"run", "bench", "live", "replay", "calibrate", "identify", "jig-calibrate", "jig-validate", "demo",
            "serve", "study"} <= set(commands)
    for name in commands:
        help_text = registry.summary("twin.commands", name)
        assert help_text and "\n" not in help_text, name
        module = registry.load("twin.commands", name)
        assert callable(module.add_arguments) and callable(module.run), name
        # the help read from the source without importing is the module's own HELP
        own = module.HELP[name] if isinstance(module.HELP, dict) else module.HELP
        assert own == help_text


def test_twin_help_lists_every_command_with_its_help(capsys):
    from twin.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps the help lines
    for name in registry.entries("twin.commands"):
        assert f" {name} " in out and " ".join(registry.summary("twin.commands", name).split()) in out, name


def test_every_simulated_setup_is_an_entry_point_naming_a_setup_of_that_name():
    from sim_interrogator.setups import Setup

    setups = registry.entries("twin.sim_setups")
    assert {"static", "calibration", "sheath-rotate", "sheath-cycle", "sheath-path", "tendon", "bath",
            "fiber-static", "fiber-sheath-cycle"} <= set(setups)
    for name in setups:
        cls = registry.load("twin.sim_setups", name)
        assert inspect.isclass(cls) and issubclass(cls, Setup) and cls.name == name, name


def test_an_unknown_simulated_setup_lists_the_registered_ones():
    from sim_interrogator.sim_source import open_sim

    with pytest.raises(ValueError) as err:
        open_sim("sim://nonesuch")
    assert "unknown simulated setup 'nonesuch'" in str(err.value)
    assert ", ".join(registry.entries("twin.sim_setups")) in str(err.value)


CHECK = """
from conftest import require_tool

def test_needs_a_missing_tool():
    require_tool(False, "nonesuch is not installed")
"""


@pytest.mark.parametrize(("ci", "outcome"), [("true", "1 failed"), ("", "1 skipped")])
def test_a_missing_independent_tool_fails_under_ci_and_skips_outside(tmp_path, ci, outcome):
    """tests/conftest.py's rule, run as pytest runs it: CI=true turns the skip of a missing tool into a failure."""
    (tmp_path / "test_probe.py").write_text(CHECK)
    env = {**os.environ, "CI": ci, "PYTHONPATH": str(ROOT / "tests")}
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                          str(tmp_path / "test_probe.py")], capture_output=True, text=True, cwd=tmp_path, env=env,
                         timeout=120)
    assert outcome in out.stdout, out.stdout + out.stderr
    if ci:  # the failure says what is missing and why it is not a skip
        assert "nonesuch is not installed (CI=true" in out.stdout, out.stdout
