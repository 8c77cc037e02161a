"""A plain folder of images with a camera file: the layout for the user's own recordings.

Images (png, jpg, bmp, pgm, tif) are taken in natural name order (img2 before img10). The camera is
camera.yaml (or camera.yml, or DSO's camera.txt) beside them, or ``camera_file=``. Optional: times.txt with one
timestamp in seconds per image (the first number of each line), otherwise frame i is at i x 0.1 s; and
groundtruth.txt in TUM format (camera-to-world).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vo_core.datasets.base import (
    ImageFiles,
    LoadOptions,
    Sequence,
    check_ground_truth_overlap,
    natural_sort_key,
    nominal_timestamps,
)
from vo_core.datasets.calibration import find_camera_file, load_camera_file
from vo_core.datasets.textfiles import check_increasing, read_table
from vo_core.errors import InputError
from vo_core.trajectory import read_trajectory

NAME = "image_folder"
LOOKS_FOR = "image files with camera.yaml (image folder)"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")


def detect(path: Path) -> bool:
    return path.is_dir() and bool(image_files(path))


def image_files(folder: Path) -> list[Path]:
    """The image files of a folder in natural order (digit runs compared as numbers)."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: natural_sort_key(p.name))


def load(path: Path, options: LoadOptions) -> Sequence:
    image_paths = image_files(path)
    calibration = load_camera_file(_camera_file(path, options))
    timestamps = _timestamps(path / "times.txt", len(image_paths))
    ground_truth = None
    if (path / "groundtruth.txt").is_file():
        ground_truth = read_trajectory(path / "groundtruth.txt", format="tum")
        check_ground_truth_overlap(ground_truth, timestamps, path / "groundtruth.txt")
    return Sequence(
        name=path.name,
        layout=NAME,
        root=path,
        raw_camera=calibration.camera,
        images=ImageFiles(image_paths),
        timestamps=timestamps,
        options=options,
        ground_truth=ground_truth,
        calibration_output=calibration.output,
    )


def _camera_file(folder: Path, options: LoadOptions) -> Path:
    camera_file = options.camera_file or find_camera_file(folder)
    if camera_file is not None:
        return camera_file
    raise InputError(f"{folder}: a folder of images needs camera.yaml beside them (or pass a camera file)")


def _timestamps(times_file: Path, count: int) -> np.ndarray:
    if not times_file.is_file():
        return nominal_timestamps(count)
    timestamps = read_table(times_file, 1)[:, 0]
    if len(timestamps) != count:
        raise InputError(f"{times_file}: {len(timestamps)} timestamps for {count} images")
    check_increasing(timestamps, times_file)
    return timestamps
