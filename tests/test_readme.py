"""README.md's examples run as written, so they cannot rot.

A fenced block that follows the line ``<!-- readme-test -->`` in README.md is tested: ``sh`` blocks are the
lab session, run in order by one bash (``set -e``) in a fresh directory where ``.venv`` is this checkout's
virtual environment (the session starts by activating it, as a reader would after ``make demo``); ``python``
blocks run afterwards, in order, as one script in the same directory (they may use what the session wrote,
e.g. ``cal.toml``). The full run takes a few minutes of physics, so it is marked slow (``make test-slow``);
the fast test checks what can be checked without running: the blocks are there, the session activates the
environment, every ``twin`` command and option it uses exists, the Python compares with the truth and
compiles.
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
from pathlib import Path

import pytest
from conftest import require_tool

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MARKER = "<!-- readme-test -->"


def blocks(text: str) -> list[tuple[str, str]]:
    """(language, code) of every fenced block that follows the marker line (blank lines between allowed)."""
    out = []
    pattern = re.compile(re.escape(MARKER) + r"\s*\n```(\w+)[^\n]*\n(.*?)\n```", re.S)
    for m in pattern.finditer(text):
        out.append((m.group(1), m.group(2)))
    return out


def session() -> tuple[str, str]:
    found = blocks(README.read_text(encoding="utf-8"))
    shell = "\n".join(code for lang, code in found if lang in ("sh", "bash", "shell"))
    python = "\n\n".join(code for lang, code in found if lang == "python")
    return shell, python


def twin_commands(shell: str) -> list[list[str]]:
    """The ``twin …`` command lines of a shell block (continuations joined, comments and ``&`` dropped)."""
    joined = re.sub(r"\\\n\s*", " ", shell)
    out = []
    for line in joined.splitlines():
        line = line.split(" #", 1)[0].strip().rstrip("&").strip()
        if line.startswith("twin "):
            out.append(shlex.split(line.replace("$(", "").replace(")", "")))
    return out


def test_readme_examples_are_there_and_consistent(capsys):
    from twin.cli import main

    shell, python = session()
    assert shell and python, f"README.md has no blocks after {MARKER}"
    first = next(line for line in shell.splitlines() if line.strip())
    assert first.split("#")[0].strip() in (". .venv/bin/activate", "source .venv/bin/activate")
    # every command and long option of the session exists (its --help names it)
    commands = twin_commands(shell)
    assert len(commands) >= 5
    for argv in commands:
        with pytest.raises(SystemExit) as done:
            main([*argv[1:3 if argv[1] == "run" else 2], "--help"])
        helps = capsys.readouterr().out
        assert done.value.code == 0, argv
        for opt in argv:
            if opt.startswith("--"):
                assert opt.split("=")[0] in helps, (argv, opt)
    # the Python example compares a reconstruction with the truth, and compiles
    assert "shape_error(" in python and "frame.truth" in python
    compile(python, "README.md", "exec")


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_readme_session_and_python_run_as_written(tmp_path):
    shell, python = session()
    venv = ROOT / ".venv"
    require_tool((venv / "bin" / "activate").exists(), "no .venv in the checkout (make test creates it)")
    (tmp_path / ".venv").symlink_to(venv)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    env.update(MPLBACKEND="Agg", PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(["bash", "-e", "-c", shell], cwd=tmp_path, env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=700)
    finally:
        # the session's background server (and anything else it left) goes with its process group
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        proc.wait()
    assert proc.returncode == 0, out[-4000:]
    for made in ("cal.toml", "rec", "run.h5"):
        assert (tmp_path / made).exists(), made
    script = tmp_path / "readme_example.py"
    script.write_text(python, encoding="utf-8")
    run = subprocess.run([str(venv / "bin" / "python"), str(script)], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-4000:]


# ----------------------------------------------------------------------------- the results tables (issue 23 D)
def test_readme_results_tables_are_rendered_from_the_published_runs():
    """Every table between `<!-- results: NAME -->` markers is what scenarios.results_tables renders from the
    runs' JSON in docs/results/ (`make results` reruns them and rewrites the tables)."""
    from scenarios.results_tables import TABLES, differences, load, readme_tables, render

    text = README.read_text(encoding="utf-8")
    assert set(readme_tables(text)) == set(TABLES)
    assert differences(text, render(load())) == []


def test_results_tables_are_written_between_their_markers_only():
    from scenarios.results_tables import differences, readme_tables, write

    text = ("intro\n<!-- results: a -->\n<!-- /results -->\nmiddle | not a table\n"
            "<!-- results: b -->\n| old |\n|---|\n<!-- /results -->\nend\n")
    tables = {"a": "| x |\n|---|\n| 1 |", "b": "| y |\n|---|\n| 2 |"}
    out = write(text, tables)
    assert out == ("intro\n<!-- results: a -->\n| x |\n|---|\n| 1 |\n<!-- /results -->\nmiddle | not a table\n"
                   "<!-- results: b -->\n| y |\n|---|\n| 2 |\n<!-- /results -->\nend\n")
    assert readme_tables(out) == tables and differences(out, tables) == []
    assert differences(text, tables) == ["a", "b"]
    with pytest.raises(KeyError, match="unknown tables: b"):
        write(text, {"a": "| x |"})


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_rerunning_the_quickest_published_runs_gives_the_same_tables(tmp_path):
    """The published figures reproduce: the two quickest runs (tendon, temperature bath) rerun now render the
    README's tables unchanged."""
    import shutil

    from scenarios.results_tables import RESULTS, differences, load, render, rerun

    shutil.copytree(RESULTS, tmp_path / "results")
    rerun(["tendon", "temperature-bath"], tmp_path / "results", say=lambda msg: None)
    assert differences(README.read_text(encoding="utf-8"), render(load(tmp_path / "results"))) == []
