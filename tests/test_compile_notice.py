"""A cold kernel cache is said in one line on a terminal (twin/compile_notice.py), and only then.

Real pseudo-terminals and real numba compiles: a kernel module written here (numba's own cache locator, beside
it), run in fresh processes whose stderr is the pty's other end or a pipe."""

from __future__ import annotations

import os
import pty
import subprocess
import sys

from twin.compile_notice import MESSAGE

KERNEL = "from numba import njit\n\n@njit(cache=True)\ndef twice(x):\n    return 2.0 * x\n"
PROGRAM = """
import sys
from numba import njit
from twin import compile_notice

installed = compile_notice.install("check")
import kernel_here
print(installed, kernel_here.twice(1.5))
if "uncached" in sys.argv:
    njit(lambda x: x + 1.0)(1.0)   # a second compile in the same process
"""


def _run(tmp_path, *argv: str, tty: bool = True) -> tuple[str, str]:
    """(stdout, stderr) of PROGRAM run in a fresh process, its stderr a pseudo-terminal or a pipe."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    cmd = [sys.executable, str(tmp_path / "program.py"), *argv]
    if not tty:
        out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
        assert out.returncode == 0, out.stderr
        return out.stdout, out.stderr
    master, slave = pty.openpty()
    try:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=slave, env=env, text=True)
        os.close(slave)
        chunks = []
        while True:
            try:
                chunk = os.read(master, 4096)
            except OSError:  # EIO: the child closed its end
                break
            if not chunk:
                break
            chunks.append(chunk)
        stdout = proc.stdout.read()
        assert proc.wait(timeout=120) == 0, b"".join(chunks).decode()
    finally:
        os.close(master)
        proc.stdout.close()
    return stdout, b"".join(chunks).decode().replace("\r\n", "\n")


def test_one_line_when_compiling_none_when_loading_from_the_cache_none_on_a_pipe(tmp_path):
    (tmp_path / "kernel_here.py").write_text(KERNEL)
    (tmp_path / "program.py").write_text(PROGRAM)
    line = f"twin check: {MESSAGE}\n"

    stdout, stderr = _run(tmp_path, "uncached")  # cold: compiles `twice`, then a second function
    assert stdout == "True 3.0\n"
    assert stderr == line  # once, however many functions compile

    stdout, stderr = _run(tmp_path)  # warm: `twice` comes from the cache written by the first run
    assert stdout == "True 3.0\n" and stderr == ""

    stdout, stderr = _run(tmp_path, "uncached", tty=False)  # compiles, but stderr is a pipe: nothing said
    assert stdout == "False 3.0\n" and stderr == ""
