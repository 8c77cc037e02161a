"""TUM monoVO layout (Engel, Usenko, Cremers, "A Photometrically Calibrated Benchmark For Monocular Visual
Odometry", 2016): images/ or images.zip, times.txt, camera.txt, pcalib.txt, vignette.png, groundtruthSync.txt.

times.txt has 'id timestamp exposure_ms' per frame. camera.txt is DSO's format (FOV model, relative intrinsics,
usually "crop" to 640x480). The photometric calibration (inverse response, vignette) is used where present.
groundtruthSync.txt (TUM format, one line per frame) has poses only for the start and end segments seen by the
motion capture; the other lines are NaN and are dropped.
"""

from __future__ import annotations

import threading
import zipfile
from pathlib import Path

import cv2
import numpy as np

from vo_core.datasets.base import (
    ImageFiles,
    LoadOptions,
    Sequence,
    check_ground_truth_overlap,
    natural_sort_key,
    to_gray_u8,
)
from vo_core.datasets.calibration import load_camera_file
from vo_core.datasets.image_folder import IMAGE_SUFFIXES, image_files
from vo_core.datasets.textfiles import check_increasing, data_line_numbers, read_table
from vo_core.errors import InputError
from vo_core.geometry.photometric import load_photometric_calibration
from vo_core.trajectory import Trajectory, read_trajectory

NAME = "tum_mono"
LOOKS_FOR = "times.txt + camera.txt + images/ or images.zip (TUM monoVO)"


def detect(path: Path) -> bool:
    return (
        path.is_dir()
        and (path / "times.txt").is_file()
        and (path / "camera.txt").is_file()
        and ((path / "images").is_dir() or (path / "images.zip").is_file())
    )


def load(path: Path, options: LoadOptions) -> Sequence:
    images = _images(path)
    times_file = path / "times.txt"
    times = read_table(times_file, 3)  # id, timestamp (s), exposure (ms)
    if len(times) != len(images):
        raise InputError(f"{times_file}: {len(times)} lines for {len(images)} images")
    check_increasing(times[:, 1], times_file, data_line_numbers(times_file))
    calibration = load_camera_file(options.camera_file or path / "camera.txt")
    camera = calibration.camera
    photometric = load_photometric_calibration(
        _if_present(path / "pcalib.txt"), _if_present(path / "vignette.png"), (camera.width, camera.height)
    )
    return Sequence(
        name=path.name,
        layout=NAME,
        root=path,
        raw_camera=camera,
        images=images,
        timestamps=times[:, 1],
        exposures_ms=times[:, 2],
        options=options,
        photometric=photometric,
        ground_truth=_ground_truth(path / "groundtruthSync.txt", times[:, 1]),
        calibration_output=calibration.output,
    )


def _if_present(path: Path) -> Path | None:
    return path if path.is_file() else None


def _images(path: Path):
    if (path / "images").is_dir():
        return ImageFiles(image_files(path / "images"))
    return ZipImages(path / "images.zip")


class ZipImages:
    """Images inside a zip archive (TUM monoVO ships images.zip), decoded in memory."""

    def __init__(self, zip_path: Path):
        self.zip_path = zip_path
        try:
            self._archive = zipfile.ZipFile(zip_path)
        except (zipfile.BadZipFile, OSError) as error:
            raise InputError(f"{zip_path}: not a readable zip archive ({error})") from None
        names = [n for n in self._archive.namelist() if Path(n).suffix.lower() in IMAGE_SUFFIXES]
        self.members = sorted(names, key=natural_sort_key)
        self._lock = threading.Lock()  # a ZipFile is not safe to read from two threads at once

    def __len__(self) -> int:
        return len(self.members)

    def name(self, index: int) -> str:
        return f"{self.zip_path}:{self.members[index]}"

    def read(self, index: int) -> np.ndarray | None:
        try:
            with self._lock:
                data = self._archive.read(self.members[index])
        except (zipfile.BadZipFile, OSError):
            return None
        return to_gray_u8(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED))


def _ground_truth(path: Path, timestamps: np.ndarray) -> Trajectory | None:
    if not path.is_file():
        return None
    ground_truth = read_trajectory(path, format="tum")  # drops the all-NaN lines of frames without a pose
    check_ground_truth_overlap(ground_truth, timestamps, path)
    return ground_truth
