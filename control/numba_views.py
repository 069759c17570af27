"""Array views without a reference count, for the plant's inner loop (numba).

numba counts the references to every array it passes between compiled functions that it has
not inlined: an atomic increment and decrement of the array's owner per call, several per RK4
step of the plant. :func:`unowned` gives a view of the same memory with no owner, whose
counting is a test for a null pointer. The results are the same to the last bit; the plant's
closed loop runs 3-4 % faster (``benchmarks/closed_loop.py``).

The view must not outlive the array it was made from: use it only inside the compiled function
that holds that array for the whole time (:func:`pneutune.control.plant.dynamics.advance`).
"""

from __future__ import annotations

from typing import Any

import numba
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from pneutune.control.numba_cache import njit


@intrinsic
def _void_pointer(typingctx: Any, address: Any) -> Any:
    """An integer address as a ``void *`` (compiled only)."""
    sig = types.voidptr(address)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.inttoptr(args[0], cgutils.voidptr_t)

    return sig, codegen


@njit(cache=True, inline="always")
def unowned(a: Any) -> Any:
    """A view of the array ``a`` that numba does not reference-count (module docstring), or
    ``a`` itself when it is not C-contiguous; compiled only."""
    if not a.flags.c_contiguous:
        return a
    return numba.carray(_void_pointer(a.ctypes.data), a.shape, a.dtype)


__all__ = ["unowned"]
