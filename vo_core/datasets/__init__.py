"""Datasets as they are published: one module per layout, a registry that detects the layout, and the bundled
default sequence (``DEFAULT_SEQUENCE``, TUM RGB-D fr3/teddy, 80 frames) that ``fdmo run`` uses without arguments."""

from pathlib import Path

from vo_core.datasets.base import Frame, Sequence
from vo_core.datasets.registry import LAYOUTS, open_sequence

# assets/ sits beside vo_core/ in the repository (the package is installed in place: pip install -e .)
DEFAULT_SEQUENCE = Path(__file__).resolve().parents[2] / "assets" / "rgbd_dataset_freiburg3_teddy_first80"

__all__ = ["DEFAULT_SEQUENCE", "LAYOUTS", "Frame", "Sequence", "open_sequence"]
