"""A live camera (``fdmo run camera:N --camera calib.yaml``): the frames OpenCV's VideoCapture delivers, as a camera
delivers them.

``LiveCamera`` grabs on a thread of its own and keeps only the newest frame, rectified with the calibration's
undistorter (as a dataset's frames are), numbered from 0 and stamped with the seconds since the camera opened.
``LivePlayer`` hands the run the newest frame each time the odometry is ready, as ``--realtime`` does with a
recorded sequence: the frames that arrived meanwhile are dropped and announced (``frames_dropped``, source
``realtime``). A pass ends at Ctrl-C or when the camera stops delivering frames.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np

from app.kernel_build import playing_clock
from app.player import REALTIME_SOURCE, PlaybackState
from vo_core.datasets.base import Frame, rectification, to_gray_u8
from vo_core.datasets.calibration import load_camera_file
from vo_core.errors import InputError
from vo_core.events import Event, EventKind
from vo_core.geometry.undistorter import Undistorter

LIVE_PREFIX = "camera"
FIRST_FRAME_TIMEOUT_S = 10.0  # a camera that delivers nothing for this long after opening is not working
FRAME_TIMEOUT_S = 2.0  # ... or after its last frame: the pass ends (unplugged, end of a virtual camera's stream)


def live_device(source: str) -> int | None:
    """The device number of ``camera:N``; None for any other source."""
    kind, separator, device = str(source).partition(":")
    if kind != LIVE_PREFIX or not separator:
        return None
    if not device.isdigit():
        raise InputError(f"{source}: expected camera:N, N the number OpenCV gives the camera (0 for the first)")
    return int(device)


def live_undistorter(device: int, calibration_file: Path | None, undistort_output="crop") -> Undistorter:
    """The rectification of a live camera, from its calibration file (as a dataset's: the file's own output size
    unless another than DSO's "crop" is asked for)."""
    if calibration_file is None:
        raise InputError(f"{LIVE_PREFIX}:{device}: a live camera needs its calibration (--camera FILE)")
    calibration = load_camera_file(Path(calibration_file))
    return rectification(calibration.camera, undistort_output, calibration.output, calibration_file)


class LiveCamera:
    """The newest rectified frame of camera ``device``; ``camera`` is the rectified pinhole camera."""

    layout = "camera"
    ground_truth = None

    def __init__(self, device: int, undistorter: Undistorter):
        self.undistorter = undistorter
        self.raw_camera = undistorter.raw_camera
        self.name = f"{LIVE_PREFIX}{device}"
        self.device = device
        self._capture = cv2.VideoCapture(device)
        if not self._capture.isOpened():
            raise InputError(f"{LIVE_PREFIX}:{device}: OpenCV cannot open this camera")
        self._condition = threading.Condition()
        self._newest: Frame | None = None
        self._count = 0
        self._ended = False
        self._error: InputError | None = None
        self._opened = time.monotonic()
        self._thread = threading.Thread(target=self._grab, name=f"fdmo-{self.name}", daemon=True)
        self._thread.start()

    @property
    def camera(self):
        return self.undistorter.camera

    def __len__(self) -> int:
        """Frames delivered so far."""
        return self._count

    def newest_after(self, index: int, timeout_s: float) -> Frame | None:
        """The newest frame with a number above ``index``, waiting for one up to ``timeout_s``; None when the camera
        stopped delivering."""
        with self._condition:
            self._condition.wait_for(lambda: self._ended or (self._newest is not None and self._newest.index > index),
                                     timeout=timeout_s)
            if self._error is not None:
                raise self._error
            newest = self._newest
            return newest if newest is not None and newest.index > index else None

    def close(self) -> None:
        with self._condition:
            self._ended = True
            self._condition.notify_all()
        self._thread.join(timeout=FRAME_TIMEOUT_S)
        self._capture.release()

    def _grab(self) -> None:
        while not self._ended:
            ok, image = self._capture.read()
            stamp = time.monotonic() - self._opened
            if not ok or image is None:
                break
            frame = self._rectified(image, stamp)
            with self._condition:
                self._newest = frame
                self._count += 1
                self._condition.notify_all()
                if self._error is not None:
                    break
        with self._condition:
            self._ended = True
            self._condition.notify_all()

    def _rectified(self, image: np.ndarray, stamp: float) -> Frame:
        gray = to_gray_u8(image)
        expected = (self.raw_camera.height, self.raw_camera.width)
        if gray.shape != expected and self._error is None:
            self._error = InputError(f"{LIVE_PREFIX}:{self.device}: the camera delivers {gray.shape[1]}x{gray.shape[0]}"
                                     f" images, but the calibration is for {expected[1]}x{expected[0]}")
            return Frame(self._count, stamp, None, error=str(self._error))
        return Frame(self._count, stamp, self.undistorter.rectify(gray), path=f"{LIVE_PREFIX}:{self.device}")


class LivePlayer(PlaybackState):
    """The newest frame of a ``LiveCamera`` each time the run asks (the interface of app.player.Player that a run
    uses). ``realtime``: frames the odometry had no time for are dropped, as with ``--realtime``."""

    realtime = True

    def __init__(self, camera: LiveCamera):
        super().__init__()
        self.camera = camera
        self._started: float | None = None

    def wait_for_restart(self) -> bool:
        return False

    def playing_time(self) -> float:
        return 0.0 if self._started is None else playing_clock() - self._started

    def stop(self) -> None:
        self._stopped = True

    def play(self, on_event: Callable[[Event], None] | None = None) -> Iterator[Frame]:
        self._started = playing_clock()
        last = -1
        while not self._stopped:
            frame = self.camera.newest_after(last, FIRST_FRAME_TIMEOUT_S if last < 0 else FRAME_TIMEOUT_S)
            if frame is None:
                if last < 0:
                    raise InputError(f"{LIVE_PREFIX}:{self.camera.device}: no frame from the camera in "
                                     f"{FIRST_FRAME_TIMEOUT_S:.0f} s")
                self._finished = True
                return
            if frame.index > last + 1 and on_event is not None:
                missed = frame.index - last - 1
                on_event(Event(EventKind.FRAMES_DROPPED, last + 1, frame.timestamp, {
                    "count": missed, "requested": missed, "first_frame": last + 1, "last_frame": frame.index - 1,
                    "source": REALTIME_SOURCE}))
            last = frame.index
            yield frame
