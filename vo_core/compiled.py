"""How the hot loops are compiled (numba), in one place.

Every kernel is cached on disk in the user's cache, never in the package (vo_core/kernel_cache.py; the first run
compiles, later runs load it), and releases the interpreter's lock, so tracking and mapping overlap on their threads
as OpenCV's calls do. Division follows numpy: a division by zero gives
inf or NaN instead of raising ZeroDivisionError, so the machine code carries no zero test before each division (a
teddy window's linearization 6 % faster, the same numbers) and the kernels that can meet such values test for them.

No kernel uses fastmath, though it made the window's linearization 7-13 % faster: with FMA contraction and
reassociation allowed, a kernel's numbers depend on how it was compiled, and the same input must give the same
trajectory. Measured twice: a shared helper (warp_ray, bilinear3, inside) is compiled once per process with the
flags of the first kernel that calls it, so a fastmath caller changed the tracker's arithmetic depending on which
kernel compiled first; and with fastmath on the window's linearization alone, the run that compiled it and the runs
that loaded it from the cache gave teddy trajectories 1e-15 apart at the start, then chaotically more.
"""

from __future__ import annotations

import os

import numba

from vo_core.kernel_cache import CACHE_VARIABLE

# A numba imported before vo_core (by the caller's own code) read its settings before vo_core/__init__.py set the
# cache folder: the kernels below are placed by this setting when they are decorated.
if not numba.config.CACHE_DIR:
    numba.config.CACHE_DIR = os.environ[CACHE_VARIABLE]


def kernel(function=None, *, parallel: bool = False):
    """``numba.njit`` with the project's flags: ``@kernel``, or ``@kernel(parallel=True)`` for a kernel with a
    ``numba.prange`` loop."""
    jit = numba.njit(cache=True, nogil=True, error_model="numpy", parallel=parallel)
    return jit if function is None else jit(function)
