"""How the hot loops are compiled (numba), in one place.

Every kernel is cached on disk (the first run compiles, later runs load it) and releases the interpreter's lock, so
tracking and mapping overlap on their threads as OpenCV's calls do. Division follows numpy: a division by zero gives
inf or NaN instead of raising ZeroDivisionError, so the machine code carries no zero test before each division (a
teddy window's linearization 6 % faster, the same numbers) and the kernels that can meet such values test for them.
"""

from __future__ import annotations

import numba


def kernel(function=None, *, parallel: bool = False, fastmath: bool = False):
    """``numba.njit`` with the project's flags: ``@kernel``, or ``@kernel(parallel=True)`` for a kernel with a
    ``numba.prange`` loop. ``fastmath`` lets the compiler reorder sums and assume no inf or NaN: only for a kernel
    whose every input is finite, and that says why it needs it."""
    jit = numba.njit(cache=True, nogil=True, error_model="numpy", parallel=parallel, fastmath=fastmath)
    return jit if function is None else jit(function)
