"""VAMR mini-project layout (UZH "Vision Algorithms for Mobile Robotics"): images/img_%05d.png, K.txt, poses.txt.

K.txt is a 3x3 matrix (comma or space separated); the images are rendered pinhole images without distortion.
poses.txt, where present, has one row-major 3x4 camera-to-world matrix per frame. The dataset has no
timestamps: frame i is at i x 0.1 s (``nominal_timestamps``), as in every output of the project. Image img_i is
frame i: a missing image is a frame skipped with an event, not a shift of the frames after it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vo_core.datasets.base import (
    LoadOptions,
    Sequence,
    fill_numbering_gaps,
    image_size,
    nominal_timestamps,
)
from vo_core.datasets.calibration import CameraFile, load_camera_file
from vo_core.datasets.textfiles import read_matrix, require_file
from vo_core.errors import InputError
from vo_core.geometry.camera import PinholeCamera
from vo_core.trajectory import Trajectory, read_trajectory

NAME = "vamr"
LOOKS_FOR = "images/img_00000.png with K.txt (VAMR)"
IMAGE_PATTERN = "img_[0-9][0-9][0-9][0-9][0-9].png"


def detect(path: Path) -> bool:
    return path.is_dir() and (path / "K.txt").is_file() and any((path / "images").glob(IMAGE_PATTERN))


def load(path: Path, options: LoadOptions) -> Sequence:
    found = sorted((path / "images").glob(IMAGE_PATTERN))
    numbers = np.array([int(p.stem[len("img_"):]) for p in found])
    image_paths, _ = fill_numbering_gaps(found, numbers, lambda number: f"img_{number:05d}.png", first=0)
    timestamps = nominal_timestamps(len(image_paths))
    if options.camera_file is not None:
        calibration = load_camera_file(options.camera_file)
    else:
        calibration = CameraFile(_camera(path / "K.txt", found[0]))
    return Sequence.of_image_files(path, NAME, options, calibration, image_paths, timestamps,
                                   _ground_truth(path / "poses.txt", timestamps))


def _camera(k_file: Path, first_image: Path) -> PinholeCamera:
    K = read_matrix(require_file(k_file, "intrinsics K.txt"), 3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise InputError(f"{k_file}: not an intrinsics matrix [fx 0 cx; 0 fy cy; 0 0 1]")
    width, height = image_size(first_image)
    return PinholeCamera(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])


def _ground_truth(poses_file: Path, timestamps: np.ndarray) -> Trajectory | None:
    if not poses_file.is_file():
        return None
    poses = read_trajectory(poses_file, format="kitti").poses
    if len(poses) < len(timestamps):
        raise InputError(f"{poses_file}: {len(poses)} poses for {len(timestamps)} images")
    return Trajectory(timestamps, poses[: len(timestamps)])
