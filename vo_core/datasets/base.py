"""Frames and sequences: what every dataset layout turns its folder into.

A ``Sequence`` is a list of raw images (an ``ImageSource``), their timestamps, the raw camera and the
photometric calibration. Reading a frame rectifies the image once to the pinhole camera the odometry sees
(``Sequence.camera``) and, where a photometric calibration exists, computes the corrected irradiance
G^-1(I) / V before rectification, since the vignette lives in the raw image. As in DSO (PhotometricUndistorter::
processFrame) the exposure time is not divided out: it travels in ``Frame.exposure_ms`` to the direct method's
affine brightness model. Frames are read lazily; iteration reads ahead on a background thread.

``Frame.index`` is the frame's position in the ORIGINAL sequence: it does not change when the sequence is
cut, strided or reversed, so outputs and frame drops refer to the dataset's own frame numbers.
"""

from __future__ import annotations

import copy
import queue
import re
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import cv2
import numpy as np

from vo_core.errors import InputError
from vo_core.geometry.camera import CameraModel, PinholeCamera, camera_to_dict
from vo_core.geometry.photometric import PhotometricCalibration
from vo_core.geometry.undistorter import OutputSpec, Undistorter
from vo_core.trajectory import Trajectory, read_trajectory

if TYPE_CHECKING:
    from vo_core.datasets.calibration import CameraFile


BAD_IMAGE_POLICIES = ("skip", "abort")

# Layouts without timestamps (VAMR, plain image folders) get frame index x 0.1 s (issue 2, CLI contract).
NOMINAL_FRAME_RATE_HZ = 10.0


@dataclass
class Frame:
    """One image of a sequence, rectified to ``Sequence.camera``.

    ``image`` is uint8 gray (None when the file was unreadable and the policy is "skip"; ``error`` then says
    why). ``irradiance`` is the float32 image the direct method tracks: G^-1(raw) / V rectified in float where
    there is a photometric calibration or a distortion to remove, otherwise simply ``image`` as float32,
    converted on access. ``exposure_ms`` is the exposure time where the dataset records it (TUM monoVO), else
    None.
    """

    index: int
    timestamp: float
    image: np.ndarray | None
    exposure_ms: float | None = None
    path: str = ""
    error: str | None = None
    corrected_irradiance: np.ndarray | None = field(default=None, repr=False)

    @property
    def irradiance(self) -> np.ndarray | None:
        if self.corrected_irradiance is not None:
            return self.corrected_irradiance
        return None if self.image is None else self.image.astype(np.float32)


class ImageSource(Protocol):
    """The raw images of a sequence, by original index."""

    def __len__(self) -> int: ...

    def name(self, index: int) -> str:
        """Where image ``index`` comes from (a path), for messages and ``Frame.path``."""

    def read(self, index: int) -> np.ndarray | None:
        """Image ``index`` as uint8 gray, or None when it cannot be decoded."""


class ImageFiles:
    """Images stored one per file (every layout except zip archives and videos)."""

    def __init__(self, paths: list[Path]):
        self.paths = list(paths)

    def __len__(self) -> int:
        return len(self.paths)

    def name(self, index: int) -> str:
        return str(self.paths[index])

    def read(self, index: int) -> np.ndarray | None:
        return to_gray_u8(cv2.imread(str(self.paths[index]), cv2.IMREAD_UNCHANGED))


def to_gray_u8(image: np.ndarray | None) -> np.ndarray | None:
    """Decoded image (gray, BGR, BGRA; 8 or 16 bit) -> uint8 gray; None stays None."""
    if image is None:
        return None
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    return image if image.dtype == np.uint8 else None


def nominal_timestamps(count: int) -> np.ndarray:
    """index x 0.1 s, computed as index / 10: the double nearest to each value (19.9, not 19.900000000000002)."""
    return np.arange(count) / NOMINAL_FRAME_RATE_HZ


def natural_sort_key(name: str) -> list:
    """Sort key comparing digit runs as numbers, so that img2 comes before img10."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, for layouts whose calibration does not state it (KITTI, VAMR)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: unreadable or corrupt image (needed for the image size)")
    return image.shape[1], image.shape[0]


def check_files_exist(paths: list[Path], listed_in: Path) -> None:
    """A list file none of whose images exists is a wrong folder (or paths relative to somewhere else): refuse it.
    A few missing images are frames the camera or the disk lost: they are skipped when read, each with an event
    naming the file (or stop the run, with the "abort" policy), as unreadable ones are."""
    if paths and not any(path.is_file() for path in paths):
        raise InputError(f"{listed_in}: none of the {len(paths)} images it lists exists (first {paths[0]})")


def fill_numbering_gaps(paths: list[Path], numbers: np.ndarray, name_of,
                        first: int | None = None) -> tuple[list[Path], np.ndarray]:
    """Images named by frame number with numbers missing in between (a lost file): the missing frames get the path
    they should have (``name_of(number)``, beside the others), read as a missing image, so that every frame number
    keeps its frame and its timestamp. Returns the paths and the numbers from ``first`` (default: the smallest
    number) to the largest."""
    present = dict(zip(numbers.tolist(), paths))
    every = np.arange(numbers.min() if first is None else first, numbers.max() + 1)
    return [present.get(number, paths[0].parent / name_of(number)) for number in every.tolist()], every


def check_ground_truth_overlap(ground_truth: Trajectory, timestamps: np.ndarray, path: Path) -> None:
    """Ground truth whose time span does not meet the images' is a wrong file (or wrong units)."""
    if len(ground_truth) == 0:
        raise InputError(f"{path}: ground truth has no poses")
    first, last = ground_truth.timestamps[0], ground_truth.timestamps[-1]
    if last < timestamps.min() or first > timestamps.max():
        raise InputError(
            f"{path}: ground truth spans {first:.3f}..{last:.3f} s, which does not overlap the images "
            f"({timestamps.min():.3f}..{timestamps.max():.3f} s)"
        )


def tum_ground_truth(path: Path, timestamps: np.ndarray) -> Trajectory | None:
    """The ground truth in a TUM file at ``path``, where there is one, checked against the frames' times."""
    if not path.is_file():
        return None
    ground_truth = read_trajectory(path, format="tum")
    check_ground_truth_overlap(ground_truth, timestamps, path)
    return ground_truth


@dataclass(frozen=True)
class LoadOptions:
    """How ``open_sequence`` was asked to open a sequence (passed on to every layout's loader)."""

    camera_file: Path | None = None
    undistort_output: OutputSpec = "crop"  # "crop" | "full" | "none" | (width, height): DSO's choices
    on_bad_image: str = "skip"  # or "abort"
    read_ahead: int = 8

    def __post_init__(self) -> None:
        if self.on_bad_image not in BAD_IMAGE_POLICIES:
            raise InputError(f"on_bad_image must be one of {', '.join(BAD_IMAGE_POLICIES)}, not '{self.on_bad_image}'")


class FrameSelection:
    """The frames a sequence plays, as positions in its recording (``_selection``), and the views ``cut`` and
    ``reversed`` make of it, for the dataset sequences and the synthetic ones alike."""

    _selection: np.ndarray
    stride: int = 1  # every stride-th frame of the recording is played: a camera at 1/stride of its rate

    def cut(self, start: int | None = None, end: int | None = None, stride: int = 1):
        """Frames start..end-1 (positions in this view, Python slice rules), every ``stride``-th."""
        if stride < 1:
            raise InputError(f"stride must be a positive integer, not {stride}")
        selection = self._selection[slice(start, end, stride)]
        if len(selection) == 0:
            where = getattr(self, "root", self.name)  # a dataset's folder, a synthetic sequence's name
            raise InputError(f"{where}: cutting {len(self._selection)} frames to start={start}, end={end} leaves none")
        view = self._view(selection)
        view.stride = self.stride * stride
        return view

    def reversed(self):
        """The frames in reverse order (timestamps then decrease; frame indices stay the original ones)."""
        return self._view(self._selection[::-1])

    def _view(self, selection: np.ndarray):
        view = copy.copy(self)
        view._selection = selection
        return view


class Sequence(FrameSelection):
    """A dataset sequence: lazily read frames, calibration and ground truth.

    ``len``, indexing and iteration see the current view (after ``cut``/``reversed``); ``Frame.index`` stays
    the original frame number. ``timestamps`` are the dataset's own, in seconds.
    """

    def __init__(
        self,
        *,
        name: str,
        layout: str,
        root: Path,
        raw_camera: CameraModel,
        images: ImageSource,
        timestamps: np.ndarray,
        options: LoadOptions,
        exposures_ms: np.ndarray | None = None,
        photometric: PhotometricCalibration | None = None,
        ground_truth: Trajectory | None = None,
        calibration_output: OutputSpec | None = None,
    ):
        if len(images) == 0:
            raise InputError(f"{root}: no images")
        if len(timestamps) != len(images):
            raise InputError(f"{root}: {len(images)} images but {len(timestamps)} timestamps")
        self.name = name
        self.layout = layout
        self.root = Path(root)
        self.raw_camera = raw_camera
        self.photometric = photometric or PhotometricCalibration.identity()
        self.ground_truth = ground_truth
        self.options = options
        self._images = images
        self._timestamps = np.asarray(timestamps, dtype=float)
        self._exposures_ms = None if exposures_ms is None else np.asarray(exposures_ms, dtype=float)
        self._undistorter = rectification(raw_camera, options.undistort_output, calibration_output, root)
        self._selection = np.arange(len(images))
        self._check_image_size()

    @classmethod
    def of_image_files(cls, root: Path, layout: str, options: LoadOptions, calibration: CameraFile,
                       image_paths: list[Path], timestamps: np.ndarray, ground_truth: Trajectory | None,
                       name: str | None = None) -> Sequence:
        """A sequence stored one image file per frame (every layout but zip archives and videos), with the camera
        of ``calibration``; named after its folder unless ``name`` is given."""
        return cls(name=name or root.name, layout=layout, root=root, raw_camera=calibration.camera,
                   images=ImageFiles(image_paths), timestamps=timestamps, options=options, ground_truth=ground_truth,
                   calibration_output=calibration.output)

    # ------------------------------------------------------------------------------------------- views

    @property
    def camera(self) -> PinholeCamera:
        """The rectified pinhole camera of every frame's ``image``: the camera the odometry sees."""
        return self._undistorter.camera

    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps[self._selection]

    @property
    def indices(self) -> np.ndarray:
        """Original frame numbers of the frames of this view, in order."""
        return self._selection.copy()

    def __len__(self) -> int:
        return len(self._selection)

    def __repr__(self) -> str:
        return (
            f"Sequence({self.name!r}, layout={self.layout!r}, frames={len(self)}, "
            f"camera={self.camera.width}x{self.camera.height}, ground_truth={self.ground_truth is not None})"
        )

    # ------------------------------------------------------------------------------------------ frames

    def __getitem__(self, position: int) -> Frame:
        return self._read(int(self._selection[position]))

    def __iter__(self) -> Iterator[Frame]:
        if self.options.read_ahead <= 0:
            return (self._read(int(index)) for index in self._selection)
        return _read_ahead(self._read, [int(index) for index in self._selection], self.options.read_ahead)

    def _read(self, index: int) -> Frame:
        timestamp = float(self._timestamps[index])
        exposure = None if self._exposures_ms is None else float(self._exposures_ms[index])
        path = self._images.name(index)
        raw = self._images.read(index)
        problem = self._problem_with(raw, path)
        if problem is not None:
            if self.options.on_bad_image == "abort":
                raise InputError(problem)
            return Frame(index, timestamp, None, exposure, path, error=problem)
        irradiance = None
        if not (self.photometric.is_identity and self._undistorter.is_identity):
            # rectified in float, as DSO does, not from the rounded uint8 image
            irradiance = self._undistorter.rectify(self.photometric.correct(raw))
        return Frame(index, timestamp, self._undistorter.rectify(raw), exposure, path, None, irradiance)

    def _check_image_size(self) -> None:
        """A calibration for another resolution would skip every frame: refuse it when the first image and the last
        have another size (one odd image among right ones is only a bad frame, skipped with an event)."""
        expected = (self.raw_camera.height, self.raw_camera.width)
        first = self._images.read(0)
        if first is None or first.shape == expected:
            return
        last = self._images.read(len(self._images) - 1)
        if last is None or last.shape == expected:
            return
        raise InputError(
            f"{self._images.name(0)}: the images are {first.shape[1]}x{first.shape[0]}, "
            f"but the camera calibration is for {self.raw_camera.width}x{self.raw_camera.height}"
        )

    def _problem_with(self, raw: np.ndarray | None, path: str) -> str | None:
        if raw is None:
            missing = isinstance(self._images, ImageFiles) and not Path(path).is_file()
            return f"{path}: {'no such image file' if missing else 'unreadable or corrupt image'}"
        expected = (self.raw_camera.height, self.raw_camera.width)
        if raw.shape != expected:
            return (
                f"{path}: image is {raw.shape[1]}x{raw.shape[0]}, "
                f"the camera calibration is for {expected[1]}x{expected[0]}"
            )
        return None

    # ---------------------------------------------------------------------------------------- describe

    def describe(self) -> dict[str, Any]:
        """What the loader found, JSON-serializable (``fdmo info`` prints it)."""
        timestamps = self.timestamps
        description: dict[str, Any] = {
            "name": self.name,
            "layout": self.layout,
            "root": str(self.root),
            "frames": len(self),
            "first_frame_index": int(self._selection[0]),
            "resolution": [self.camera.width, self.camera.height],
            "raw_camera": camera_to_dict(self.raw_camera),
            "camera": camera_to_dict(self.camera),
            "time_span_s": [float(timestamps.min()), float(timestamps.max())],
            "duration_s": float(timestamps.max() - timestamps.min()),
            "exposure_times": self._exposures_ms is not None,
            "photometric_calibration": not self.photometric.is_identity,
            "ground_truth": None,
        }
        if self.ground_truth is not None:
            gt_times = self.ground_truth.timestamps
            description["ground_truth"] = {
                "poses": len(self.ground_truth),
                "time_span_s": [float(gt_times[0]), float(gt_times[-1])],
            }
        return description


def rectification(raw_camera: CameraModel, requested: OutputSpec, calibration_output: OutputSpec | None,
                  source) -> Undistorter:
    """The rectification of the calibration's camera, to the calibration file's own target (TUM monoVO: 1280x1024
    cropped to 640x480) unless the caller asked for something other than the default "crop". Numbers that parse but
    describe no camera (a distortion of 1e300, a focal length of 1e-300) fail in its arithmetic: that is bad input
    from ``source``, said in one line."""
    output = calibration_output if requested == "crop" and calibration_output is not None else requested
    try:
        return Undistorter(raw_camera, output)
    except (ArithmeticError, ValueError, np.linalg.LinAlgError) as error:
        raise InputError(f"{source}: the camera calibration cannot be rectified ({error})") from None


_END = object()


def _read_ahead(read, indices: list[int], depth: int) -> Iterator[Frame]:
    """Yield ``read(i)`` for ``indices`` in order, reading up to ``depth`` frames ahead on a daemon thread.

    The thread stops when the consumer stops (the generator is closed or garbage-collected), and an error
    raised while reading (the "abort" policy) is re-raised in the consumer at the frame where it happened."""
    frames: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def offer(item) -> bool:
        while not stop.is_set():
            try:
                frames.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        for index in indices:
            try:
                item = read(index)
            except BaseException as error:  # handed to the consumer, raised there
                offer(error)
                return
            if not offer(item):
                return
        offer(_END)

    thread = threading.Thread(target=produce, name="frame-read-ahead", daemon=True)
    thread.start()
    try:
        while True:
            item = frames.get()
            if item is _END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        thread.join(timeout=1.0)
