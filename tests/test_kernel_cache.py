"""Compiled kernels land in the user's cache (vo_core/kernel_cache.py), never beside the package's sources: left
there, they outlive pip's uninstall and hide an editable install (issue 47)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# A module of kernels outside the package, compiled through vo_core.compiled as the package's own are.
TINY_KERNEL = '''
from vo_core.compiled import kernel

@kernel
def twice(x):
    return 2.0 * x
'''


def run_python(code: str, cwd: Path, **environment: str) -> str:
    """``code`` in a fresh interpreter that imports this checkout's vo_core, with the user's NUMBA_CACHE_DIR and
    XDG_CACHE_HOME replaced by ``environment``."""
    env = {name: value for name, value in os.environ.items() if name not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    env.update(environment, PYTHONPATH=os.pathsep.join([str(REPO), str(cwd)]))
    done = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def cached_kernel_files(folder: Path) -> list[Path]:
    return [*folder.rglob("*.nbi"), *folder.rglob("*.nbc")]


def test_a_kernel_is_cached_in_the_user_cache_not_beside_its_module(tmp_path):
    (tmp_path / "tiny_kernels.py").write_text(TINY_KERNEL)
    cache = tmp_path / "xdg"
    printed = run_python("import tiny_kernels, numba; print(tiny_kernels.twice(2.0)); print(numba.config.CACHE_DIR)",
                         tmp_path, XDG_CACHE_HOME=str(cache))
    value, folder = printed.splitlines()
    assert value == "4.0" and Path(folder) == cache / "fdmo" / "numba"
    assert cached_kernel_files(cache / "fdmo" / "numba")
    assert not cached_kernel_files(tmp_path / "__pycache__")


def test_the_cache_is_under_the_home_without_xdg_cache_home(tmp_path):
    folder = run_python("import vo_core.compiled, numba; print(numba.config.CACHE_DIR)", tmp_path, HOME=str(tmp_path))
    assert Path(folder) == tmp_path / ".cache" / "fdmo" / "numba"


def test_the_users_own_numba_cache_dir_wins(tmp_path):
    folder = run_python("import vo_core.compiled, numba; print(numba.config.CACHE_DIR)", tmp_path,
                        NUMBA_CACHE_DIR=str(tmp_path / "mine"))
    assert Path(folder) == tmp_path / "mine"


def test_numba_imported_before_vo_core_still_caches_in_the_user_cache(tmp_path):
    (tmp_path / "tiny_kernels.py").write_text(TINY_KERNEL)
    cache = tmp_path / "xdg"
    run_python("import numba; import tiny_kernels; tiny_kernels.twice(1.0)", tmp_path, XDG_CACHE_HOME=str(cache))
    assert cached_kernel_files(cache / "fdmo" / "numba")
    assert not cached_kernel_files(tmp_path / "__pycache__")
