"""Datasets as they are published: one module per layout, a registry that detects the layout, and the bundled
default sequence (``DEFAULT_SEQUENCE``, TUM RGB-D fr3/teddy, 80 frames) that ``fdmo run`` uses without arguments."""

from vo_core.assets import ASSETS_DIR
from vo_core.datasets.base import Frame, Sequence
from vo_core.datasets.registry import LAYOUTS, open_sequence

DEFAULT_SEQUENCE = ASSETS_DIR / "rgbd_dataset_freiburg3_teddy_first80"  # shipped with the package (vo_core/data/)

__all__ = ["DEFAULT_SEQUENCE", "LAYOUTS", "Frame", "Sequence", "open_sequence"]
