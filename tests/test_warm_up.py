"""`twin warm-up` (twin/cli/warm_up_command.py) compiles what `twin live` and `twin replay` run.

The fast test runs it on the cache `make test` warmed (seconds). The slow one starts from an empty cache
(``NUMBA_CACHE_DIR`` in tmp_path, which the project's cache locators honour ahead of the in-tree cache) and then
asks numba, through ``NUMBA_DEBUG_CACHE``, whether a live session over synthetic:// recording HDF5 and MCAP, and
the replay of both, saved (so compiled) any kernel: none may."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from twin.cli import main

TWIN = [sys.executable, "-m", "twin.cli"]


def test_warm_up_runs_and_says_what_it_did(capsys):
    assert main(["warm-up"]) == 0
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("twin warm-up: the kernels are compiled and cached (") and captured.err.count(
        "\n") == 1
    assert main(["warm-up", "--quiet"]) == 0
    assert capsys.readouterr().err == ""


@pytest.mark.slow
def test_after_a_warm_up_from_an_empty_cache_live_and_replay_compile_nothing(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "NUMBA_DEBUG_CACHE": "1"}

    def twin(*argv: str) -> str:
        out = subprocess.run([*TWIN, *argv], capture_output=True, text=True, env=env, timeout=900)
        assert out.returncode == 0, out.stderr[-3000:]
        return out.stdout + out.stderr

    warm = twin("warm-up")
    assert "data saved" in warm  # it compiled: the cache was empty
    h5, mcap = tmp_path / "r.h5", tmp_path / "r.mcap"
    runs = {"live": twin("live", "synthetic://?rate=1000&frames=600&noise=0.001", "--record", str(h5),
                         "--record", str(mcap), "--json"),
            "replay h5": twin("replay", str(h5), "--json"),
            "replay mcap": twin("replay", str(mcap), "--json")}
    for what, text in runs.items():
        assert "data loaded" in text, what  # the kernels came from the cache …
        saved = [line for line in text.splitlines() if "data saved" in line]
        assert not saved, (what, saved[:5])  # … and none was compiled
