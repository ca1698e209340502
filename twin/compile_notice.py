"""One line on a terminal when numba starts compiling: the wait of a first run after an install or an edit.

With a cold kernel cache (a fresh install, or an edit to any kernel source: :mod:`twin._jit_cache`) the first
``twin live``, ``twin replay``, ``twin demo`` … compiles the kernels it calls, tens of seconds with nothing on
the screen. numba fires its ``numba:compile`` event when it compiles a function and never when it loads one from
the cache, so a listener on that event speaks exactly when the wait happens, once per process.

Only to a terminal: the line is a note for a person waiting, not part of what a script reads (a command's error
stays the one line on stderr that its callers and tests rely on, whether or not the cache was warm).
"""

from __future__ import annotations

import sys
from typing import TextIO

__all__ = ["MESSAGE", "install"]

#: what the line says after ``twin COMMAND: ``
MESSAGE = ("compiling the numba kernels (first run after an install or an edit of a kernel: tens of seconds; "
           "later runs load them from the cache)")


def install(command: str, stream: TextIO | None = None) -> bool:
    """Say :data:`MESSAGE` on ``stream`` (stderr) the first time this process compiles a numba function.

    Parameters
    ----------
    command : str
        The command's name, the line's prefix (``twin COMMAND: …``).
    stream : text stream, optional
        Where the line goes; default ``sys.stderr``. Nothing is installed unless it is a terminal.

    Returns
    -------
    bool
        Whether the listener was installed (the stream is a terminal).
    """
    stream = sys.stderr if stream is None else stream
    try:
        if not stream.isatty():
            return False
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False
    from numba.core import event  # only here: `twin` on a pipe never pays numba's import for this

    class _Notice(event.Listener):
        said = False

        def on_start(self, ev: event.Event) -> None:
            if not self.said:  # numba compiles a kernel's callees inside its compile: one line in all
                self.said = True
                print(f"twin {command}: {MESSAGE}", file=stream, flush=True)

        def on_end(self, ev: event.Event) -> None:
            pass

    event.register("numba:compile", _Notice())
    return True
