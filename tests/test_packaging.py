"""A wheel built from the sources carries the package data (the bundled sequence, the vocabulary): installed
outside the repository, ``fdmo run`` with no argument finds its sequence as a clone does."""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "README.md", "app", "vo_core")
FDMO_ENTRIES = ("fdmo", "__editable__", "vo_core", "app")  # an installed fdmo's entries in a site-packages


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """A wheel built by pip from a copy of the sources (an in-tree build would leave build/ in the checkout)."""
    root = tmp_path_factory.mktemp("packaging")
    (root / "source").mkdir()
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, root / "source" / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(REPO / name, root / "source" / name)
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", str(root / "source"), "--no-deps", "-q",
                            "-w", str(root / "dist")], capture_output=True, text=True, timeout=600)
    if built.returncode != 0 and "satisfies the requirement setuptools" in built.stderr:
        pytest.skip("the build backend (setuptools) cannot be fetched here")
    assert built.returncode == 0, built.stderr
    return next((root / "dist").glob("fdmo-*.whl"))


def test_the_wheel_holds_every_file_of_the_package_data(wheel):
    shipped = {path.relative_to(REPO).as_posix() for path in (REPO / "vo_core" / "data").rglob("*") if path.is_file()}
    assert any(name.endswith("rgb.txt") for name in shipped)
    assert shipped <= set(zipfile.ZipFile(wheel).namelist())


def test_the_installed_wheel_opens_the_bundled_sequence_outside_the_repository(wheel, tmp_path):
    environment = tmp_path / "venv"
    venv.create(environment, with_pip=True)
    python = environment / "bin" / "python"
    # The dependencies as installed here (this environment's site-packages, which may be a venv's own: a venv made
    # with system_site_packages sees only the base interpreter's), after the new environment's own packages.
    own = subprocess.run([str(python), "-c", "import site; print(site.getsitepackages()[0])"], check=True,
                         capture_output=True, text=True).stdout.strip()
    (Path(own) / "dependencies_here.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    env = _without_our_settings(os.environ)  # a PYTHONPATH to a checkout would hide the installed wheel
    subprocess.run([str(python), "-m", "pip", "install", "--no-deps", "-q", str(wheel)], check=True, timeout=300,
                   env=env)
    opened = subprocess.run(
        [str(python), "-c", "from vo_core.datasets import DEFAULT_SEQUENCE, open_sequence; "
                            "print(DEFAULT_SEQUENCE); print(len(open_sequence(DEFAULT_SEQUENCE)))"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert opened.returncode == 0, opened.stderr
    location, frames = opened.stdout.split()
    assert location.startswith(str(environment)) and frames == "80"


def test_the_quick_start_run_as_written_leaves_an_editable_install_working(tmp_path):
    """README's quick start in one environment: ``pip install . && fdmo run``, then ``pip install -e .``, then
    fdmo again (issue 47: the first run's kernels, compiled into site-packages/vo_core/*/__pycache__, outlived the
    uninstall and hid the editable install: No module named 'vo_core.geometry.lie'). The cheapest faithful version:
    the dependencies come from this environment (``--no-deps``; a fresh install of them takes minutes), the rest is
    as written. About 1.5 minutes: the first run compiles every kernel for the installed copy's sources."""
    python, site_packages = _environment_with_our_dependencies(tmp_path)
    fdmo = python.parent / "fdmo"
    work = tmp_path / "work"
    work.mkdir()
    env = _without_our_settings(os.environ)
    first_cache = tmp_path / "cache"

    _pip(python, "install", "--no-deps", str(_copy_of_the_sources(tmp_path / "source")), env=env)
    first_run = subprocess.run([str(fdmo), "run", "--no-rrd"], cwd=work,
                               env={**env, "XDG_CACHE_HOME": str(first_cache)}, capture_output=True, text=True,
                               timeout=600)
    assert first_run.returncode == 0, first_run.stderr
    assert list((first_cache / "fdmo" / "numba").rglob("*.nbi")), "the kernels were not cached in the user cache"
    assert not list((site_packages / "vo_core").rglob("*.nb[ic]")), "kernels were cached inside the package"

    _pip(python, "install", "--no-deps", "-e", str(REPO), env=env)
    assert not (site_packages / "vo_core").exists(), "the uninstalled copy left folders behind"
    imported = subprocess.run([str(python), "-c", "import vo_core, vo_core.geometry.lie; print(vo_core.__file__)"],
                              cwd=work, env=env, capture_output=True, text=True, timeout=120)
    assert imported.returncode == 0, imported.stderr
    assert Path(imported.stdout.strip()) == REPO / "vo_core" / "__init__.py"
    second_run = subprocess.run([str(fdmo), "run", "--no-rrd", "--quiet"], cwd=work, env=env, capture_output=True,
                                text=True, timeout=600)
    assert second_run.returncode == 0, second_run.stderr


def _environment_with_our_dependencies(root: Path) -> tuple[Path, Path]:
    """A fresh venv that also sees this environment's packages but not its fdmo: a folder of links to everything
    in this environment's site-packages except fdmo's own entries, listed in a .pth (seeing fdmo's dist-info, pip
    takes this environment's fdmo for the installed one and leaves the venv's copy in place). Returns the venv's
    python and its site-packages."""
    venv.create(root / "venv", with_pip=True)
    python = root / "venv" / "bin" / "python"
    own = Path(subprocess.run([str(python), "-c", "import site; print(site.getsitepackages()[0])"], check=True,
                              capture_output=True, text=True).stdout.strip())
    dependencies = root / "dependencies"
    dependencies.mkdir()
    for site_packages in map(Path, site.getsitepackages()):
        for entry in site_packages.iterdir():
            if not entry.name.startswith(FDMO_ENTRIES) and not (dependencies / entry.name).exists():
                (dependencies / entry.name).symlink_to(entry)
    (own / "dependencies_here.pth").write_text(f"{dependencies}\n")
    return python, own


def _copy_of_the_sources(root: Path) -> Path:
    """What ``pip install .`` builds from, copied (an in-tree build would leave build/ in the checkout)."""
    root.mkdir()
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, root / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(REPO / name, root / name)
    return root


def _without_our_settings(environment) -> dict[str, str]:
    """The environment less what points Python or numba elsewhere (a PYTHONPATH to a checkout would also show pip
    that checkout's fdmo.egg-info as the installed fdmo)."""
    return {name: value for name, value in environment.items()
            if name not in ("PYTHONPATH", "NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}


def _pip(python: Path, *arguments: str, env: dict[str, str]) -> None:
    done = subprocess.run([str(python), "-m", "pip", *arguments, "-q"], env=env, capture_output=True, text=True,
                          timeout=600)
    if done.returncode != 0 and "satisfies the requirement setuptools" in done.stderr:
        pytest.skip("the build backend (setuptools) cannot be fetched here")
    assert done.returncode == 0, done.stderr
