"""The compiled function behind a numba dispatcher, for hot paths that call it with arguments of fixed types.

Calling a ``@njit`` function goes through its dispatcher, which works out the numba type of every argument and
looks up the matching compiled overload on every call. After a physics step has evicted that machinery from the
cache it costs ≈ 3 µs a call here (≈ 0.6 µs warm), as much as the arithmetic of the simulator's per-frame
kernels (docs/simulation.md §4). A caller whose arguments keep their types from call to call (buffers allocated
once, Python floats) can look the overload up once and call it directly: :meth:`numba.core.dispatcher.Dispatcher.
compile` returns it, loading it from numba's cache or compiling it.

The direct function converts its arguments without checking them (an array of another dtype or dimension is
read as if it were the expected one), so it is only for callers that own every argument's type.

Each array argument still costs ≈ 70–80 ns a call to unpack (numba wraps it in a reference-counted structure and
releases it after the call). Arrays that stay where they are for the caller's lifetime (buffers allocated once,
views of ``mjData``, whose arrays MuJoCo keeps in place) can instead travel as one integer array of their
addresses and sizes (:func:`addresses`), which the compiled function views again with :func:`numba.carray` and
:func:`float64_at`, :func:`int64_at`, :func:`int32_at` — one array to unpack instead of many. The caller keeps
every such array alive (a reference held beside the addresses) and never rebinds it.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np
from numba import types
from numba.extending import intrinsic

__all__ = ["addresses", "compiled_entry", "float64_at", "int32_at", "int64_at"]


def compiled_entry(dispatcher, *args) -> Callable:
    """The compiled overload of ``dispatcher`` (a ``@njit`` function) for the numba types of ``args`` (example
    arguments of the calls to come), callable directly with arguments of those types."""
    return dispatcher.compile(tuple(numba.typeof(a) for a in args))


def addresses(*arrays: np.ndarray) -> np.ndarray:
    """The addresses of C-contiguous ``arrays`` followed by their sizes, int64 (2 n,), for a compiled function that
    views them again (:func:`float64_at` and :func:`numba.carray`); the caller keeps the arrays alive."""
    for a in arrays:
        if not a.flags.c_contiguous:
            raise ValueError("addresses: every array must be C-contiguous")
    return np.array([a.ctypes.data for a in arrays] + [a.size for a in arrays], dtype=np.int64)


def _pointer_to(item):
    @intrinsic
    def at(typingctx, address):
        """A pointer to ``item`` at the integer ``address`` (for :func:`numba.carray`)."""
        if not isinstance(address, types.Integer):
            return None
        sig = types.CPointer(item)(address)

        def codegen(context, builder, signature, args):
            return builder.inttoptr(args[0], context.get_value_type(signature.return_type))

        return sig, codegen

    return at


float64_at = _pointer_to(types.float64)
int64_at = _pointer_to(types.int64)
int32_at = _pointer_to(types.int32)
