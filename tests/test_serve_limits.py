"""Limits of `twin serve` and its servers against careless users and hostile local clients (issue 23, B12, B14).

Everything on 127.0.0.1, bounded in count and time; the time bounds are hang guards, never speed limits.
"""

from __future__ import annotations

import pytest

from twin.cli import main


@pytest.mark.parametrize(("argv", "names"), [
    (["serve", "illumisense", "--port", "70000"], "--port"),
    (["serve", "hyperion", "--port", "-1"], "--port"),
    (["serve", "illumisense", "--port", "0", "--duration", "nan"], "--duration"),
    (["serve", "illumisense", "--port", "0", "--duration", "-1"], "--duration"),
    (["serve", "illumisense", "--port", "0", "--duration", "inf"], "--duration"),
    (["serve", "illumisense", "--port", "0", "--rate", "nan"], "--rate"),
    (["live", "synthetic://?rate=100", "--frames", "5", "--print-rate", "-1"], "--print-rate"),
    (["live", "synthetic://?rate=100", "--frames", "5", "--print-rate", "nan"], "--print-rate"),
])
def test_impossible_numbers_get_one_line_and_status_2(argv, names, capsys):
    """B14: --port 70000 gave a traceback, --duration nan never stopped, -1 was accepted, --print-rate -1 too."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"twin {argv[0]}: error: {names} must be"), err
