"""`twin warm-up`: compile the numba kernels ahead, so that the first `twin live` or `twin replay` does not wait.

numba compiles a kernel on its first call and keeps the machine code in its cache (:mod:`twin._jit_cache`):
after an install, or an edit of any kernel source, the first session would spend tens of seconds compiling
before its first shape. This command runs, on a few hundred frames, what such a session runs: `twin live` itself
over ``synthetic://`` (the forward model, the live loop and its books, the reconstruction, the confidence tube's
uncertainty and the figures against the truth), then ILLumiSense records through the driver's stream decoder
into the live loop (the scan of a record, sequence numbers, rates). It prints how long that took: seconds when
the cache was warm already. `make test` runs it before the tests so that no timed test compiles on its first
frames. Exit status 0.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import time

#: one-line help (read by `twin --help` without importing this module)
HELP = "compile the numba kernels ahead (a fresh install's first `twin live`/`twin replay` then starts at once)"

__all__ = ["add_arguments", "run", "warm_up"]

#: frames per pass: several batches of the live loop, each path met at least once
_FRAMES = 300


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quiet", action="store_true", help="print nothing")


def warm_up() -> None:
    """Run a short `twin live` over ``synthetic://`` and ILLumiSense records through the live loop (module
    docstring): every kernel they call is compiled, or loaded from the cache."""
    from twin.cli import live_command
    from twin.io import illumisense
    from twin.live import LiveLoop
    from twin.reconstruct import Reconstructor
    from twin.stream_bench import RecordPieces
    from twin.synthetic import SyntheticSource

    parser = argparse.ArgumentParser()
    live_command.add_arguments(parser)
    args = parser.parse_args([f"synthetic://?pace=max&noise=0.001&drop=0.01&frames={_FRAMES}", "--json",
                              "--quiet"])
    with contextlib.redirect_stdout(io.StringIO()):  # the run's summary is not this command's output
        status = live_command.run(args)
    if status != 0:
        raise RuntimeError(f"twin live over synthetic:// ended with status {status}")

    source = SyntheticSource(pace=False, frames=_FRAMES, cores=7, gratings=18, noise=0.001, truth=False)
    frames, fiber = list(source), source.fiber
    stream = b"".join(illumisense.encode_record(f) for f in frames)
    pieces = [stream[i:i + 4096] for i in range(0, len(stream), 4096)]  # as a socket returns them
    summary = LiveLoop(RecordPieces(pieces, fiber), Reconstructor(fiber), []).run(handle_signals=False)
    if summary.status.frames != len(frames):
        raise RuntimeError(f"warm-up: {summary.status.frames} of {len(frames)} ILLumiSense records reconstructed")


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    warm_up()
    if not args.quiet:
        print(f"twin warm-up: the kernels are compiled and cached ({time.perf_counter() - t0:.1f} s)",
              file=sys.stderr)
    return 0
