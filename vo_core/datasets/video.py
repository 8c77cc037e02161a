"""A video file (anything OpenCV's VideoCapture decodes) with a camera file.

Timestamps come from the container (each frame's presentation time, CAP_PROP_POS_MSEC), found by one pass
that grabs every frame without converting it; that pass also gives the exact frame count, which container
headers often state only approximately. The camera is ``camera_file=``, else <video stem>.yaml or camera.yaml
beside the video.
"""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np

from vo_core.datasets.base import LoadOptions, Sequence, to_gray_u8
from vo_core.datasets.calibration import load_camera_file
from vo_core.datasets.textfiles import check_increasing
from vo_core.errors import InputError

NAME = "video"
LOOKS_FOR = "a video file (.mp4, .avi, .mov, .mkv, ...)"
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv")
MILLISECONDS = 1e-3


def detect(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def load(path: Path, options: LoadOptions) -> Sequence:
    calibration = load_camera_file(_camera_file(path, options))
    frames = VideoFrames(path)
    check_increasing(frames.timestamps, path)
    return Sequence(
        name=path.stem,
        layout=NAME,
        root=path,
        raw_camera=calibration.camera,
        images=frames,
        timestamps=frames.timestamps,
        options=options,
        calibration_output=calibration.output,
    )


def _camera_file(video: Path, options: LoadOptions) -> Path:
    if options.camera_file is not None:
        return options.camera_file
    for candidate in (video.with_suffix(".yaml"), video.with_suffix(".yml"), video.parent / "camera.yaml"):
        if candidate.is_file():
            return candidate
    raise InputError(f"{video}: a video needs a camera file ({video.stem}.yaml or camera.yaml beside it)")


class VideoFrames:
    """Frames of a video by index. Reading in order (the read-ahead thread does) decodes each frame once;
    going back reopens the file and skips forward, which is exact where seeking by frame number is not."""

    def __init__(self, path: Path):
        self.path = path
        self._lock = threading.Lock()  # one VideoCapture, used by the read-ahead thread and by indexing
        self._capture = self._open()
        timestamps_ms = []
        while self._capture.grab():
            timestamps_ms.append(self._capture.get(cv2.CAP_PROP_POS_MSEC))
        if not timestamps_ms:
            raise InputError(f"{path}: the video has no decodable frames")
        self.timestamps = np.array(timestamps_ms) * MILLISECONDS
        self._capture = self._open()
        self._next = 0

    def _open(self) -> cv2.VideoCapture:
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise InputError(f"{self.path}: OpenCV cannot open this video")
        return capture

    def __len__(self) -> int:
        return len(self.timestamps)

    def name(self, index: int) -> str:
        return f"{self.path}#{index}"

    def read(self, index: int) -> np.ndarray | None:
        with self._lock:
            if index < self._next:
                self._capture.release()
                self._capture = self._open()
                self._next = 0
            while self._next < index:
                if not self._capture.grab():
                    return None
                self._next += 1
            ok, image = self._capture.read()
            self._next += 1
        return to_gray_u8(image) if ok else None
