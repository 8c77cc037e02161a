"""Files shipped with the package: the bundled sequence and the feature vocabulary.

They live in ``vo_core/data/`` (``assets/`` at the repository's root points there), declared as package data in
pyproject.toml, so an editable install reads them in place and ``pip install .`` or a wheel carries them.
"""

from __future__ import annotations

from pathlib import Path

from vo_core.errors import InputError

ASSETS_DIR = Path(__file__).resolve().parent / "data"


def asset_path(relative: str | Path) -> Path:
    """The path of a shipped file or folder, e.g. ``asset_path("vocabulary/orb.npz")``; InputError if the
    installation does not have it."""
    path = ASSETS_DIR / relative
    if not path.exists():
        raise InputError(f"{path}: not installed with the package (expected under {ASSETS_DIR})")
    return path
