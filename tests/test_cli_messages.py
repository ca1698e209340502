"""One-line messages a user reads (issue 23 A11): what they name, and how often; `twin run NAME --help` as text."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys

import pytest

from twin.cli import main, scenarios
from twin.cli.run_command import plain_help

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg"}


def _twin(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([*TWIN, *argv], capture_output=True, text=True, env=ENV, timeout=120)


def test_igtl_port_busy_is_one_line_naming_openigtlink_and_the_port():
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        out = _twin("live", "synthetic://", "--igtl", str(port), "--duration", "5")
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    assert lines[0] == (f"twin live: error: --igtl {port}: cannot serve OpenIGTLink on 127.0.0.1:{port}: "
                        "address already in use")


@pytest.mark.parametrize("scheme", ["illumisense", "hyperion"])
def test_a_connection_error_names_the_url_once(scheme):
    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]
    url = f"{scheme}://127.0.0.1:{port}?start_wait=0"
    out = _twin("live", url, "--quiet")
    err = out.stderr.strip().splitlines()[-1]
    assert out.returncode == 2
    assert err == f"twin live: error: {url}: cannot connect to 127.0.0.1:{port}: connection refused", err


def test_a_missing_serial_device_is_named_once_with_the_reason():
    out = _twin("live", "fispec:///dev/no-such-fispec", "--quiet")
    err = out.stderr.strip().splitlines()[-1]
    assert out.returncode == 2
    assert err == ("twin live: error: fispec:///dev/no-such-fispec: cannot open serial port '/dev/no-such-fispec': "
                   "no such file or directory"), err


def test_plain_help_drops_rest_markup_and_keeps_paragraphs_and_items():
    doc = """title: what it does (``--fixture tube``, :mod:`scenarios.x`, :func:`~a.b.fn`, **bold**, *it*).

    Second paragraph
    over two lines::

        indented block  kept
        as written

    * first item
      continued
    * second item
    """
    text = plain_help(doc, width=100)
    assert text.startswith("title: what it does (--fixture tube, scenarios.x, fn, bold, it).\n\n")
    assert "Second paragraph over two lines:\n\n" in text
    assert "    indented block  kept\n    as written" in text
    assert "\n\n  * first item continued\n  * second item" in text


@pytest.mark.parametrize("name", sorted(scenarios()))
def test_run_name_help_is_readable_text(name, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "100")
    with pytest.raises(SystemExit) as done:
        main(["run", name, "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    description = text.split("\n\n", 1)[1].split("\noptions:")[0]
    assert "``" not in text and not re.search(r":(mod|func|class|meth|data|attr):", text), text
    assert not re.search(r"(?<![*\w])\*\*\w", description)
    assert "\n\n" in description.strip() or len(description.strip().splitlines()) <= 8  # paragraphs kept
    assert max(len(line) for line in description.splitlines()) <= 100
