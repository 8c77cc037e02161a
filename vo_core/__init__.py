"""The odometry (FDMO and its halves, the baseline, datasets, evaluation); no UI."""

from vo_core.kernel_cache import use_user_kernel_cache

use_user_kernel_cache()  # before any module of the package imports numba (vo_core/kernel_cache.py says why)
