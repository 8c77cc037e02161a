"""KITTI odometry layout (Geiger et al., CVPR 2012): image_0/ (or image_2/), times.txt, calib.txt, poses/NN.txt.

Images are already rectified: the camera is the left 3x4 projection matrix of calib.txt (P0 for image_0, P2 for
image_2). times.txt holds seconds from the start, one line per frame. Ground truth, where present, is one
row-major 3x4 camera-to-world matrix per frame in poses/NN.txt; NN is the sequence number, taken from the
folder name (``00``, ``kitti00_first100``) or the only file in poses/. Image NNNNNN.png is frame NNNNNN of
times.txt and of the poses, so a folder holding only the first images of a sequence still lines up; an image missing
among them is a frame skipped with an event, not a frame less.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from vo_core.datasets.base import LoadOptions, Sequence, fill_numbering_gaps, image_size
from vo_core.datasets.calibration import CameraFile, load_camera_file
from vo_core.datasets.textfiles import (
    check_increasing,
    data_line_numbers,
    parse_numbers,
    read_table,
    split_fields,
    text_lines,
)
from vo_core.errors import InputError
from vo_core.geometry.camera import PinholeCamera
from vo_core.trajectory import Trajectory, read_trajectory

NAME = "kitti"
LOOKS_FOR = "image_0/ or image_2/ with times.txt (KITTI odometry)"
IMAGE_FOLDERS = {"image_0": "P0", "image_2": "P2"}  # left gray first (monocular KITTI as DSO/ORB-SLAM2 run it)
_SEQUENCE_NUMBER = re.compile(r"(\d{2})")


def detect(path: Path) -> bool:
    return path.is_dir() and (path / "times.txt").is_file() and _image_folder(path) is not None


def _image_folder(path: Path) -> Path | None:
    for name in IMAGE_FOLDERS:
        if (path / name).is_dir():
            return path / name
    return None


def load(path: Path, options: LoadOptions) -> Sequence:
    image_folder = _image_folder(path)
    image_paths = sorted(image_folder.glob("*.png"))
    if not image_paths:
        raise InputError(f"{image_folder}: no PNG images")
    digits = len(image_paths[0].stem)
    image_paths, frame_numbers = fill_numbering_gaps(image_paths, _frame_numbers(image_paths),
                                                     lambda number: f"{number:0{digits}d}.png")
    times_file = path / "times.txt"
    timestamps = _per_frame(read_table(times_file, 1)[:, 0], frame_numbers, times_file)
    check_increasing(timestamps, times_file, np.array(data_line_numbers(times_file))[frame_numbers])
    if options.camera_file is not None:
        calibration = load_camera_file(options.camera_file)
    else:
        calibration = CameraFile(_camera(path / "calib.txt", IMAGE_FOLDERS[image_folder.name], image_paths[0]))
    return Sequence.of_image_files(path, NAME, options, calibration, image_paths, timestamps,
                                   _ground_truth(path, frame_numbers, timestamps))


def _frame_numbers(image_paths: list[Path]) -> np.ndarray:
    misnamed = [p for p in image_paths if not p.stem.isdigit()]
    if misnamed:
        raise InputError(f"{misnamed[0]}: KITTI image names are frame numbers (000000.png)")
    return np.array([int(p.stem) for p in image_paths])


def _per_frame(values: np.ndarray, frame_numbers: np.ndarray, path: Path) -> np.ndarray:
    if frame_numbers.max() >= len(values):
        raise InputError(f"{path}: has {len(values)} entries, but the images go up to frame {frame_numbers.max()}")
    return values[frame_numbers]


def _camera(calib_file: Path, key: str, first_image: Path) -> PinholeCamera:
    """The pinhole camera of projection matrix ``key`` ("P0: 12 numbers") in calib.txt; the image size is not
    in calib.txt and varies by sequence (1241x376, 1226x370, ...), so it is read from the first image."""
    if not calib_file.is_file():
        raise InputError(f"{calib_file}: calibration not found (KITTI needs calib.txt, or pass a camera file)")
    matrices = {}
    for number, line in text_lines(calib_file):
        fields = split_fields(line)
        matrices[fields[0].rstrip(":")] = (number, fields[1:])
    if key not in matrices:
        raise InputError(f"{calib_file}: no {key} projection matrix")
    number, fields = matrices[key]
    P = parse_numbers(calib_file, number, fields, 12).reshape(3, 4)
    if P[0, 0] <= 0 or P[1, 1] <= 0:
        raise InputError(f"{calib_file}:{number}: {key} has non-positive focal lengths")
    width, height = image_size(first_image)
    return PinholeCamera(width, height, P[0, 0], P[1, 1], P[0, 2], P[1, 2])


def _ground_truth(path: Path, frame_numbers: np.ndarray, timestamps: np.ndarray) -> Trajectory | None:
    poses_file = _poses_file(path)
    if poses_file is None:
        return None
    poses = _per_frame(read_trajectory(poses_file, format="kitti").poses, frame_numbers, poses_file)
    return Trajectory(timestamps, poses)


def _poses_file(path: Path) -> Path | None:
    """poses/NN.txt beside the images, or dataset/poses/NN.txt for the official dataset/sequences/NN/ tree."""
    match = _SEQUENCE_NUMBER.search(path.name)
    for poses_dir in (path / "poses", path.parent.parent / "poses"):
        if match and (poses_dir / f"{match.group(1)}.txt").is_file():
            return poses_dir / f"{match.group(1)}.txt"
    candidates = sorted((path / "poses").glob("*.txt")) if (path / "poses").is_dir() else []
    return candidates[0] if len(candidates) == 1 else None
