"""A wheel built from the sources carries the package data (the bundled sequence, the vocabulary): installed
outside the repository, ``fdmo run`` with no argument finds its sequence as a clone does."""

from __future__ import annotations

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
    subprocess.run([str(python), "-m", "pip", "install", "--no-deps", "-q", str(wheel)], check=True, timeout=300)
    opened = subprocess.run(
        [str(python), "-c", "from vo_core.datasets import DEFAULT_SEQUENCE, open_sequence; "
                            "print(DEFAULT_SEQUENCE); print(len(open_sequence(DEFAULT_SEQUENCE)))"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert opened.returncode == 0, opened.stderr
    location, frames = opened.stdout.split()
    assert location.startswith(str(environment)) and frames == "80"
