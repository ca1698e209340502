"""The compiled function behind a numba dispatcher, for hot paths that call it with arguments of fixed types.

Calling a ``@njit`` function goes through its dispatcher, which works out the numba type of every argument and
looks up the matching compiled overload on every call. After a physics step has evicted that machinery from the
cache it costs ≈ 3 µs a call here (≈ 0.6 µs warm), as much as the arithmetic of the simulator's per-frame
kernels (docs/simulation.md §4). A caller whose arguments keep their types from call to call (buffers allocated
once, Python floats) can look the overload up once and call it directly: :meth:`numba.core.dispatcher.Dispatcher.
compile` returns it, loading it from numba's cache or compiling it.

The direct function converts its arguments without checking them (an array of another dtype or dimension is
read as if it were the expected one), so it is only for callers that own every argument's type.
"""

from __future__ import annotations

from collections.abc import Callable

import numba

__all__ = ["compiled_entry"]


def compiled_entry(dispatcher, *args) -> Callable:
    """The compiled overload of ``dispatcher`` (a ``@njit`` function) for the numba types of ``args`` (example
    arguments of the calls to come), callable directly with arguments of those types."""
    return dispatcher.compile(tuple(numba.typeof(a) for a in args))
