"""Ctrl-C, one rule for every command (README, "Exit status"; :func:`twin.cli.interrupted_status`).

Ctrl-C always ends a command cleanly (a summary when the run has one, never a traceback); the exit status is 130
when it cut a bounded run short (``--duration``/``--frames``, ``twin run``, ``twin study``, ``twin calibrate``,
the demo's run) and 0 when it stopped an open-ended one (``twin live``/``twin serve`` without a bound). Each case
is a real ``twin`` process sent a real SIGINT — to its whole process group, as a terminal's Ctrl-C is — once it
has printed the line that says it is running (no sleeps).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest

TWIN = [sys.executable, "-m", "twin.cli"]
ENV = {**os.environ, "MPLBACKEND": "Agg", "PYTHONUNBUFFERED": "1"}


class Running:
    """A ``twin`` process whose stdout and stderr are read as they come (status lines end in ``\\r`` too)."""

    def __init__(self, argv: list[str], cwd=None):
        self.proc = subprocess.Popen([*TWIN, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV,
                                     cwd=cwd, start_new_session=True)
        self.out, self.err = bytearray(), bytearray()
        self._changed = threading.Condition()
        self._readers = [threading.Thread(target=self._read, args=(s, b), daemon=True)
                         for s, b in ((self.proc.stdout, self.out), (self.proc.stderr, self.err))]
        for t in self._readers:
            t.start()

    def _read(self, stream, buf: bytearray) -> None:
        while chunk := os.read(stream.fileno(), 4096):
            with self._changed:
                buf += chunk
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def wait_for(self, pattern: str, where: str = "both", timeout: float = 240.0) -> None:
        """Until ``pattern`` (a regex) appears on stdout/stderr; fails if the process ends first (hang guard)."""
        rx = re.compile(pattern.encode())
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                text = {"out": self.out, "err": self.err}.get(where, self.out + self.err)
                if rx.search(text):
                    return
                assert self.proc.poll() is None, f"ended ({self.proc.returncode}) before {pattern!r}:\n{self.text}"
                assert time.monotonic() < deadline, f"no {pattern!r} within {timeout} s:\n{self.text}"
                self._changed.wait(0.5)

    def ctrl_c(self, timeout: float = 120.0) -> int:
        os.killpg(self.proc.pid, signal.SIGINT)  # the whole group, as a terminal does
        try:
            rc = self.proc.wait(timeout=timeout)
        finally:
            self.kill()
        for t in self._readers:
            t.join(timeout=10)
        return rc

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()

    @property
    def text(self) -> str:
        return (self.out + b"\n--- stderr ---\n" + self.err).decode(errors="replace")[-4000:]


@pytest.fixture
def running():
    procs: list[Running] = []

    def start(argv, cwd=None) -> Running:
        procs.append(Running(argv, cwd))
        return procs[-1]

    yield start
    for p in procs:
        p.kill()


def _clean(p: Running) -> None:
    assert "Traceback" not in p.text, p.text


@pytest.mark.parametrize("bound, status", [([], 0), (["--duration", "600"], 130), (["--frames", "100000000"], 130)])
def test_live_ends_with_its_summary_130_only_when_a_bound_was_cut_short(running, bound, status):
    p = running(["live", "synthetic://?rate=200", *bound])
    p.wait_for(r"\bframes [1-9]", "out")  # a status line with frames: the loop runs
    assert p.ctrl_c() == status, p.text
    _clean(p)
    assert "ended: interrupted" in p.out.decode()


@pytest.mark.parametrize("bound, status", [([], 0), (["--duration", "600"], 130)])
def test_serve_ends_with_its_summary_130_only_when_a_bound_was_cut_short(running, bound, status):
    p = running(["serve", "illumisense", "--port", "0", "--quiet", *bound])
    p.wait_for(r"serving .*Ctrl-C to stop", "out")
    assert p.ctrl_c() == status, p.text
    _clean(p)
    assert "stopped (interrupted)" in p.out.decode()


def test_demo_run_cut_short_prints_its_table_saying_so_and_exits_130(running):
    p = running(["demo", "--no-viewer", "--duration", "600"])
    p.wait_for(r"\r  (live|stale|starting) .* frames", "err")  # the live line: the run is under way
    assert p.ctrl_c() == 130, p.text
    _clean(p)
    out = p.out.decode()
    assert re.search(r"twin demo: .* — cut short by Ctrl-C after [\d.]+ s of 600 s", out), out
    assert "frames over ILLumiSense" in out


def test_run_is_bounded_one_line_and_130(running):
    p = running(["run", "static-shapes", "--shapes", "arc", "--repeats", "1", "--calibration", "nominal"])
    p.wait_for(r"\[1/1\] arc", "err")
    assert p.ctrl_c() == 130, p.text
    _clean(p)
    assert p.err.decode().rstrip().endswith("twin run: interrupted"), p.text


def test_calibrate_says_which_step_it_cut_and_writes_nothing(running, tmp_path):
    p = running(["calibrate", "sim://calibration", "--out", str(tmp_path / "cal.toml")])
    p.wait_for(r"step 1 \(straight\)", "err")
    assert p.ctrl_c() == 130, p.text
    _clean(p)
    assert re.search(r"twin calibrate: interrupted during the (straight|bend) step; \S+ not written", p.err.decode())
    assert not (tmp_path / "cal.toml").exists()


def test_study_keeps_its_finished_tasks_says_how_far_and_130(running, tmp_path):
    out = tmp_path / "study"
    p = running(["study", "sensor-design", "--workers", "1", "--out", str(out)])
    p.wait_for(r"\[1/\d+\] \w+ ok", "err")  # one task finished and written
    assert p.ctrl_c() == 130, p.text
    _clean(p)
    m = re.search(r"twin study: interrupted: (\d+) of (\d+) tasks done, kept in (\S+)/tasks", p.err.decode())
    assert m, p.text
    assert 1 <= int(m.group(1)) < int(m.group(2))
    assert len(list((out / "tasks").glob("*.json"))) >= int(m.group(1))
