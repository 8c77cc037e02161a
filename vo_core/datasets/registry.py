"""Open a dataset as it is: detect its layout from the folder (or video file) and hand it to that loader."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Callable

from vo_core.datasets import euroc, image_folder, kitti, tum_mono, tum_rgbd, vamr, video
from vo_core.datasets.base import LoadOptions, Sequence, check_ground_truth_overlap
from vo_core.errors import InputError
from vo_core.trajectory import Trajectory, read_trajectory


@dataclass(frozen=True)
class Layout:
    name: str
    looks_for: str  # what detection looks for, for the "unknown layout" message
    detect: Callable[[Path], bool]
    load: Callable[[Path, LoadOptions], Sequence]


def _layout(module: ModuleType) -> Layout:
    return Layout(module.NAME, module.LOOKS_FOR, module.detect, module.load)


# In detection order: the most specific marker files first; a folder of images with a camera file is the fallback.
LAYOUTS: dict[str, Layout] = {
    layout.name: layout
    for layout in map(_layout, (euroc, tum_rgbd, tum_mono, kitti, vamr, image_folder, video))
}


def detect_layout(path: Path) -> Layout:
    for layout in LAYOUTS.values():
        if layout.detect(path):
            return layout
    looked_for = "; ".join(layout.looks_for for layout in LAYOUTS.values())
    raise InputError(f"{path}: unknown dataset layout (looked for: {looked_for})")


def open_sequence(
    path: str | Path,
    layout: str | None = None,
    camera_file: str | Path | None = None,
    undistort_output="crop",
    on_bad_image: str = "skip",
    read_ahead: int = 8,
    ground_truth_file: str | Path | None = None,
) -> Sequence:
    """Open the dataset at ``path`` (a folder, or a video file).

    ``layout`` forces one of ``LAYOUTS`` instead of detecting it; ``camera_file`` (camera YAML or DSO camera.txt)
    replaces the dataset's own calibration; ``undistort_output`` is DSO's rectification choice ("crop", "full",
    "none" or (width, height)); ``on_bad_image`` is "skip" (the frame comes with image None and an error) or
    "abort" (InputError); ``read_ahead`` frames are read on a background thread while iterating (0: none);
    ``ground_truth_file`` (camera-to-world poses: TUM, KITTI with a line per image, or EuRoC CSV) replaces the
    dataset's own ground truth.
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    if path.is_dir() and not any(path.iterdir()):
        raise InputError(f"{path}: the folder is empty")
    if camera_file is not None and not Path(camera_file).is_file():
        raise InputError(f"{camera_file}: camera file not found")
    options = LoadOptions(
        camera_file=None if camera_file is None else Path(camera_file),
        undistort_output=undistort_output,
        on_bad_image=on_bad_image,
        read_ahead=read_ahead,
    )
    sequence = _chosen_layout(path, layout).load(path, options)
    if ground_truth_file is not None:
        sequence.ground_truth = _ground_truth(Path(ground_truth_file), sequence.timestamps)
    return sequence


def _ground_truth(path: Path, timestamps) -> Trajectory:
    """A trajectory file for the sequence; a KITTI file has no timestamps: its lines are the images'."""
    ground_truth = read_trajectory(path, timestamps=timestamps)
    check_ground_truth_overlap(ground_truth, timestamps, path)
    return ground_truth


def _chosen_layout(path: Path, name: str | None) -> Layout:
    if name is None:
        return detect_layout(path)
    if name not in LAYOUTS:
        raise InputError(f"unknown layout '{name}' (available: {', '.join(LAYOUTS)})")
    if not LAYOUTS[name].detect(path):
        raise InputError(f"{path}: does not look like the {name} layout (looked for {LAYOUTS[name].looks_for})")
    return LAYOUTS[name]
