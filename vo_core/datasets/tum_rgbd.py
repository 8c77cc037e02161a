"""TUM RGB-D benchmark layout (Sturm et al., IROS 2012): rgb/, rgb.txt, groundtruth.txt.

The archives carry no intrinsics. The published calibrations of the three Kinects are known here and chosen
from the ``# file: 'rgbd_dataset_freiburgN_....bag'`` header of rgb.txt, else from a folder name containing
``freiburgN``; a camera.yaml or camera.txt (DSO format) beside the data, or ``camera_file=``, overrides both.
Ground truth stays at its own timestamps (~100 Hz mocap): associating it with frames is the evaluator's job.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from vo_core.datasets.base import LoadOptions, Sequence, check_files_exist, tum_ground_truth
from vo_core.datasets.calibration import CameraFile, find_camera_file, load_camera_file
from vo_core.datasets.textfiles import check_increasing, parse_numbers, split_fields, text_lines
from vo_core.errors import InputError
from vo_core.geometry.camera import PinholeCamera, RadTanCamera

NAME = "tum_rgbd"
LOOKS_FOR = "rgb.txt (TUM RGB-D)"

# Published intrinsics of the colour cameras, 640x480 (vision.in.tum.de/data/datasets/rgbd-dataset/file_formats,
# "Intrinsic Camera Calibration of the Kinect"): fx fy cx cy, distortion d0..d4 = k1 k2 p1 p2 k3.
FREIBURG_CAMERAS = {
    1: RadTanCamera(640, 480, 517.3, 516.5, 318.6, 255.3, 0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    2: RadTanCamera(640, 480, 520.9, 521.0, 325.1, 249.7, 0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    3: PinholeCamera(640, 480, 535.4, 539.2, 320.1, 247.6),  # fr3 images are already undistorted
}
_FREIBURG = re.compile(r"freiburg(\d)")


def detect(path: Path) -> bool:
    return path.is_dir() and (path / "rgb.txt").is_file()


def load(path: Path, options: LoadOptions) -> Sequence:
    list_file = path / "rgb.txt"
    timestamps, image_paths = read_image_list(list_file)
    calibration = _calibration(path, list_file, options)
    return Sequence.of_image_files(path, NAME, options, calibration, image_paths, timestamps,
                                   tum_ground_truth(path / "groundtruth.txt", timestamps))


def read_image_list(list_file: Path) -> tuple[np.ndarray, list[Path]]:
    """rgb.txt: 'timestamp filename' per line, file names relative to the folder of the list."""
    entries = text_lines(list_file)
    if not entries:
        raise InputError(f"{list_file}: lists no images")
    timestamps, paths = [], []
    for number, line in entries:
        fields = split_fields(line)
        if len(fields) < 2:
            raise InputError(f"{list_file}:{number}: expected 'timestamp filename', found '{line}'")
        timestamps.append(parse_numbers(list_file, number, fields[:1])[0])
        paths.append(list_file.parent / fields[1])
    timestamps = np.array(timestamps)
    check_increasing(timestamps, list_file, [number for number, _ in entries])
    check_files_exist(paths, list_file)
    return timestamps, paths


def _calibration(folder: Path, list_file: Path, options: LoadOptions) -> CameraFile:
    camera_file = options.camera_file or find_camera_file(folder)
    if camera_file is not None:
        return load_camera_file(camera_file)
    number = _freiburg_in_header(list_file) or _freiburg_in(folder.name)
    if number not in FREIBURG_CAMERAS:
        raise InputError(
            f"{list_file}: cannot tell which TUM camera recorded this (no freiburg1/2/3 in the '# file:' header "
            f"or the folder name); put a camera.yaml beside it"
        )
    return CameraFile(FREIBURG_CAMERAS[number])


def _freiburg_in_header(list_file: Path) -> int | None:
    header = [line for line in list_file.read_text().splitlines() if line.startswith("#") and "file:" in line]
    return _freiburg_in(header[0]) if header else None


def _freiburg_in(text: str) -> int | None:
    match = _FREIBURG.search(text)
    return int(match.group(1)) if match else None
