"""Where numba keeps the compiled kernels: in the user's cache, never beside the installed package.

Left to itself, numba caches a kernel in the ``__pycache__`` beside its source file. Inside an installed package
those folders outlive ``pip uninstall`` (pip removes only the files it installed), and Python then takes the
leftover ``site-packages/vo_core`` as a namespace package that hides an editable install's (issue 47: after the
quick start's two commands, ``No module named 'vo_core.geometry.lie'``). numba reads ``NUMBA_CACHE_DIR`` when it is
imported, so vo_core's ``__init__`` sets it before any of its modules imports numba; a user's own setting wins.
"""

from __future__ import annotations

import os
from pathlib import Path

CACHE_VARIABLE = "NUMBA_CACHE_DIR"


def kernel_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/fdmo/numba``, or ``~/.cache/fdmo/numba`` (the XDG default; a relative XDG_CACHE_HOME is
    ignored, as the specification says)."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    return (Path(base) if os.path.isabs(base) else Path.home() / ".cache") / "fdmo" / "numba"


def use_user_kernel_cache() -> str:
    """Sets ``NUMBA_CACHE_DIR`` to ``kernel_cache_dir()`` unless the user set it; returns the folder in force.
    Child processes (the feature half's, fdmo bench's cells) inherit it."""
    return os.environ.setdefault(CACHE_VARIABLE, str(kernel_cache_dir()))
