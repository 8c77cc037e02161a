"""A plain folder of images with a camera file: the layout for the user's own recordings.

The images (png, jpg, bmp, pgm, ppm, tif) are those of the folder's ``images/`` subfolder if it has any, else
those of the folder itself. The camera is camera.yaml (or camera.yml, or DSO's camera.txt) in the folder or beside
the images, or ``camera_file=``. Ground truth, optional: groundtruth.txt in TUM format (camera-to-world) in the
folder.

Timestamps, by the first rule that applies:

1. ``times.txt`` in the folder or beside the images: the first number of each line, in seconds, a line per image;
2. file names that are all times: a number of at least 1e12 is nanoseconds (EuRoC, ROS exports:
   ``1403715274302142976.png``), a smaller one with a decimal point is seconds (TUM: ``1341841873.273798.png``);
   the images are then taken in time order;
3. otherwise frame i is at i x 0.1 s, the images in natural name order (img2 before img10). Smaller integers
   (``000042.png``) are frame numbers, not times.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from vo_core.datasets.base import (
    LoadOptions,
    Sequence,
    natural_sort_key,
    nominal_timestamps,
    tum_ground_truth,
)
from vo_core.datasets.calibration import find_camera_file, load_camera_file
from vo_core.datasets.textfiles import check_increasing, data_line_numbers, read_table
from vo_core.errors import InputError
from vo_core.trajectory import MIN_NANOSECOND_TIMESTAMP, seconds_from_nanoseconds

NAME = "image_folder"
LOOKS_FOR = "image files, or images/, with camera.yaml (image folder)"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")
IMAGES_SUBFOLDER = "images"
TIMES_FILE = "times.txt"
_NUMBER = re.compile(r"\d{1,20}(\.\d+)?")  # nanoseconds since 1970 have 19 digits


def detect(path: Path) -> bool:
    return path.is_dir() and _image_folder(path) is not None


def _image_folder(path: Path) -> Path | None:
    """Where the images are: images/ if it has any, else the folder itself if it has any."""
    for folder in (path / IMAGES_SUBFOLDER, path):
        if folder.is_dir() and image_files(folder):
            return folder
    return None


def image_files(folder: Path) -> list[Path]:
    """The image files of a folder in natural order (digit runs compared as numbers)."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: natural_sort_key(p.name))


def load(path: Path, options: LoadOptions) -> Sequence:
    image_folder = _image_folder(path)
    image_paths, timestamps = _images_and_timestamps(path, image_folder)
    calibration = load_camera_file(_camera_file(path, image_folder, options))
    return Sequence.of_image_files(path, NAME, options, calibration, image_paths, timestamps,
                                   tum_ground_truth(path / "groundtruth.txt", timestamps))


def _images_and_timestamps(folder: Path, image_folder: Path) -> tuple[list[Path], np.ndarray]:
    """The images in order and their timestamps, by the rules of the module's docstring."""
    image_paths = image_files(image_folder)
    times_file = _times_file(folder, image_folder)
    if times_file is not None:
        return image_paths, _listed_timestamps(times_file, len(image_paths))
    named = [_time_in_name(path.stem) for path in image_paths]
    if None in named:
        return image_paths, nominal_timestamps(len(image_paths))
    order = np.argsort(named, kind="stable")
    timestamps = np.array(named)[order]
    check_increasing(timestamps, image_folder)  # two names for one time (1.5.png and 1.50.png)
    return [image_paths[i] for i in order], timestamps


def _camera_file(folder: Path, image_folder: Path, options: LoadOptions) -> Path:
    camera_file = options.camera_file or find_camera_file(folder) or find_camera_file(image_folder)
    if camera_file is not None:
        return camera_file
    raise InputError(f"{folder}: a folder of images needs camera.yaml beside them (or pass a camera file)")


def _times_file(folder: Path, image_folder: Path) -> Path | None:
    return next((f / TIMES_FILE for f in (folder, image_folder) if (f / TIMES_FILE).is_file()), None)


def _listed_timestamps(times_file: Path, count: int) -> np.ndarray:
    timestamps = read_table(times_file, 1)[:, 0]
    if len(timestamps) != count:
        raise InputError(f"{times_file}: {len(timestamps)} timestamps for {count} images")
    check_increasing(timestamps, times_file, data_line_numbers(times_file))
    return timestamps


def _time_in_name(stem: str) -> float | None:
    """Seconds if the name is a time (rule 2 of the module's docstring), else None."""
    if not _NUMBER.fullmatch(stem):
        return None
    if float(stem) >= MIN_NANOSECOND_TIMESTAMP:
        return seconds_from_nanoseconds(stem)
    return float(stem) if "." in stem else None
