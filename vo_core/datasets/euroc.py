"""EuRoC MAV / ASL layout (Burri et al., IJRR 2016): mav0/cam0/{data.csv, data/, sensor.yaml}.

Timestamps are nanoseconds in data.csv, converted to seconds. sensor.yaml gives the pinhole intrinsics, the
distortion (radial-tangential or equidistant) and T_BS, the camera (sensor) pose in the body (IMU) frame.
Ground truth is the body pose in the world: mav0/state_groundtruth_estimate0/data.csv (ASL CSV) or a
TUM-format ``*groundtruth*.txt`` beside mav0; camera poses are T_world_cam = T_world_body @ T_BS.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vo_core.datasets.base import LoadOptions, Sequence, check_files_exist, check_ground_truth_overlap
from vo_core.datasets.calibration import CameraFile, load_camera_file
from vo_core.datasets.textfiles import check_increasing, read_yaml, split_fields, text_lines
from vo_core.errors import InputError
from vo_core.geometry.camera import camera_from_dict
from vo_core.trajectory import Trajectory, read_trajectory, seconds_from_nanoseconds

NAME = "euroc"
LOOKS_FOR = "mav0/cam0/data.csv (EuRoC/ASL)"
CAMERA = "cam0"  # the left camera, as DSO and ORB-SLAM2 use for monocular EuRoC
_DISTORTION_MODELS = {"radial-tangential": "radtan", "radtan": "radtan", "equidistant": "equidistant"}


def detect(path: Path) -> bool:
    return _mav0(path) is not None


def _mav0(path: Path) -> Path | None:
    """The mav0 folder: ``path`` itself or its child (users point at either)."""
    for candidate in (path / "mav0", path):
        if (candidate / CAMERA / "data.csv").is_file():
            return candidate
    return None


def load(path: Path, options: LoadOptions) -> Sequence:
    mav0 = _mav0(path)
    camera_dir = mav0 / CAMERA
    timestamps, image_paths = read_image_list(camera_dir / "data.csv")
    sensor_file = camera_dir / "sensor.yaml"
    calibration, T_body_cam = read_sensor_yaml(sensor_file)
    if options.camera_file is not None:
        calibration = load_camera_file(options.camera_file)
    sequence_root = mav0.parent if path == mav0 else path
    return Sequence.of_image_files(path, NAME, options, calibration, image_paths, timestamps,
                                   _ground_truth(mav0, sequence_root, T_body_cam, timestamps), sequence_root.name)


def read_image_list(list_file: Path) -> tuple[np.ndarray, list[Path]]:
    """data.csv: 'timestamp [ns],filename' per line; images in data/ beside it."""
    timestamps, paths = [], []
    entries = text_lines(list_file)
    for number, line in entries:
        fields = split_fields(line)
        if len(fields) < 2 or not fields[0].isdecimal():
            raise InputError(f"{list_file}:{number}: expected 'timestamp_ns,filename', found '{line}'")
        timestamps.append(seconds_from_nanoseconds(fields[0]))
        paths.append(list_file.parent / "data" / fields[1])
    if not paths:
        raise InputError(f"{list_file}: lists no images")
    timestamps = np.array(timestamps)
    check_increasing(timestamps, list_file, [number for number, _ in entries])
    check_files_exist(paths, list_file)
    return timestamps, paths


def read_sensor_yaml(path: Path) -> tuple[CameraFile, np.ndarray]:
    """(camera, T_body_cam) from a camera's sensor.yaml."""
    content = read_yaml(path)
    for key in ("intrinsics", "resolution", "T_BS"):
        if key not in content:
            raise InputError(f"{path}: missing '{key}'")
    if content.get("camera_model", "pinhole") != "pinhole":
        raise InputError(f"{path}: camera_model '{content['camera_model']}' is not supported (pinhole only)")
    distortion_model = content.get("distortion_model", "radial-tangential")
    if distortion_model not in _DISTORTION_MODELS:
        raise InputError(f"{path}: unknown distortion_model '{distortion_model}'")
    camera = camera_from_dict(
        {
            "model": _DISTORTION_MODELS[distortion_model],
            "intrinsics": content["intrinsics"],
            "distortion": content.get("distortion_coefficients", []),
            "resolution": content["resolution"],
        },
        source=str(path),
    )
    return CameraFile(camera), _matrix_4x4(content["T_BS"], path)


def _matrix_4x4(entry, path: Path) -> np.ndarray:
    data = entry.get("data") if isinstance(entry, dict) else entry
    try:
        T = np.array(data, dtype=float).reshape(4, 4)
    except (TypeError, ValueError):
        raise InputError(f"{path}: T_BS must hold 16 numbers (a 4x4 matrix)") from None
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4):
        raise InputError(f"{path}: T_BS is not a rigid transform")
    return T


def _ground_truth(mav0: Path, sequence_root: Path, T_body_cam: np.ndarray, timestamps: np.ndarray):
    path = _ground_truth_file(mav0, sequence_root)
    if path is None:
        return None
    body = read_trajectory(path, format="euroc" if path.suffix == ".csv" else "tum")
    check_ground_truth_overlap(body, timestamps, path)
    # T_world_cam = T_world_body @ T_body_cam
    return Trajectory(body.timestamps, body.poses @ T_body_cam)


def _ground_truth_file(mav0: Path, sequence_root: Path) -> Path | None:
    native = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if native.is_file():
        return native
    beside = sorted(sequence_root.glob("*groundtruth*.txt"))
    return beside[0] if beside else None
