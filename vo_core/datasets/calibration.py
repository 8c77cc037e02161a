"""Camera calibration files: the project's camera YAML and DSO's camera.txt.

A camera YAML (``model: pinhole|radtan|equidistant|fov``, ``intrinsics: [fx, fy, cx, cy]``,
``distortion: [...]``, ``resolution: [w, h]``) is read by ``vo_core.geometry.camera.camera_from_dict``.

DSO's camera.txt (JakobEngel/dso, README "Geometric Calibration File"; TUM monoVO ships one per sequence) is:

    line 1: [FOV|Pinhole|RadTan|EquiDistant|KannalaBrandt] fx fy cx cy dist...   (no prefix: 5 numbers are FOV,
            or pinhole when the fifth is 0; 8 numbers are RadTan)
    line 2: input width height
    line 3: crop | full | none | fx fy cx cy 0          (DSO's rectification choice)
    line 4: output width height

Lines 3-4 are kept as the file's rectification target when they give "crop" at some size or an explicit
pinhole (relative, like line 1); "full" and "none" are left to the caller (``open_sequence(undistort_output=)``).
Intrinsics with cx < 1 and cy < 1 are "relative" (TUM monoVO): fx * w, fy * h, cx * w - 0.5, cy * h - 0.5,
the -0.5 moving DSO's pixel-corner origin to our pixel-centre origin (dso/src/util/Undistort.cpp).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vo_core.datasets.textfiles import parse_numbers, read_yaml, split_fields, text_lines
from vo_core.errors import InputError
from vo_core.geometry.camera import (
    CameraModel,
    EquidistantCamera,
    FovCamera,
    PinholeCamera,
    RadTanCamera,
    camera_from_dict,
)

YAML_SUFFIXES = (".yaml", ".yml")
CAMERA_FILE_NAMES = ("camera.yaml", "camera.yml", "camera.txt")  # looked for beside the data, in this order

# DSO's model keywords -> number of parameters after the keyword
_DSO_MODELS = {
    "fov": 5,
    "pinhole": 5,
    "radtan": 8,
    "equidistant": 8,
    "kannalabrandt": 8,  # the same polynomial in theta as the equidistant (OpenCV fisheye) model
}


@dataclass(frozen=True)
class CameraFile:
    """A camera read from a file, and the rectification target the file asks for, if any: a (width, height) for
    DSO's "crop" at that size, or a PinholeCamera."""

    camera: CameraModel
    output: tuple[int, int] | PinholeCamera | None = None


def find_camera_file(folder: Path) -> Path | None:
    """The calibration file beside a dataset's images, if there is one."""
    return next((folder / name for name in CAMERA_FILE_NAMES if (folder / name).is_file()), None)


def load_camera_file(path: Path) -> CameraFile:
    """A camera from a YAML file (by suffix) or a DSO camera.txt (anything else)."""
    path = Path(path)
    if path.suffix.lower() in YAML_SUFFIXES:
        return CameraFile(camera_from_yaml(path))
    return read_dso_camera(path)


def camera_from_yaml(path: Path) -> CameraModel:
    return camera_from_dict(read_yaml(path), source=str(path))


def read_dso_camera(path: Path) -> CameraFile:
    lines = text_lines(path)
    if len(lines) < 2:
        raise InputError(f"{path}: a DSO camera file needs at least 2 lines (intrinsics, input width height)")
    model, params = _model_and_parameters(path, *lines[0])
    width, height = _image_size(path, *lines[1])
    if params[2] < 1 and params[3] < 1:  # relative format (Undistort::readFromFile)
        params[:4] = _absolute_intrinsics(params[:4], width, height)
    if params[0] <= 0 or params[1] <= 0:
        raise InputError(f"{path}:{lines[0][0]}: focal lengths must be positive, got fx={params[0]}, fy={params[1]}")
    output = _rectification_target(path, lines[2], lines[3]) if len(lines) >= 4 else None
    return CameraFile(_dso_camera(model, width, height, params), output)


def _absolute_intrinsics(relative: np.ndarray, width: int, height: int) -> np.ndarray:
    fx, fy, cx, cy = relative
    return np.array([fx * width, fy * height, cx * width - 0.5, cy * height - 0.5])


def _rectification_target(path: Path, mode_line: tuple[int, str], size_line: tuple[int, str]):
    """Lines 3-4: "crop" at a size -> (width, height); "fx fy cx cy 0" (relative) -> that PinholeCamera."""
    (mode_number, mode), size = mode_line, _image_size(path, *size_line)
    if mode.lower() == "crop":
        return size
    if mode.lower() in ("full", "none"):
        return None
    fx, fy, cx, cy = _absolute_intrinsics(parse_numbers(path, mode_number, split_fields(mode), 4), *size)
    if fx <= 0 or fy <= 0:
        raise InputError(f"{path}:{mode_number}: output focal lengths must be positive")
    return PinholeCamera(size[0], size[1], fx, fy, cx, cy)


def _model_and_parameters(path: Path, line_number: int, line: str) -> tuple[str, np.ndarray]:
    """Line 1: an optional model keyword and its numbers; without a keyword DSO tells the model by the count."""
    fields = split_fields(line)
    keyword = fields[0].lower() if fields and not _is_number(fields[0]) else None
    values = fields[1:] if keyword else fields
    if keyword is not None and keyword not in _DSO_MODELS:
        raise InputError(f"{path}:{line_number}: unknown camera model '{fields[0]}'")
    model = keyword or {5: "fov", 8: "radtan"}.get(len(values))
    if model is None:
        raise InputError(f"{path}:{line_number}: expected 5 (FOV/pinhole) or 8 (RadTan) numbers")
    return model, parse_numbers(path, line_number, values, _DSO_MODELS[model])


def _dso_camera(model: str, width: int, height: int, params) -> CameraModel:
    fx, fy, cx, cy = (float(value) for value in params[:4])
    dist = [float(value) for value in params[4:]]
    if model == "pinhole" or (model == "fov" and dist[0] == 0.0):
        return PinholeCamera(width, height, fx, fy, cx, cy)
    if model == "fov":
        return FovCamera(width, height, fx, fy, cx, cy, dist[0])
    if model == "radtan":
        return RadTanCamera(width, height, fx, fy, cx, cy, *dist)
    return EquidistantCamera(width, height, fx, fy, cx, cy, *dist)


def _image_size(path: Path, line_number: int, line: str) -> tuple[int, int]:
    values = parse_numbers(path, line_number, split_fields(line), 2)
    if not all(value > 0 and float(value).is_integer() for value in values):  # NaN and infinity are not
        raise InputError(f"{path}:{line_number}: image size must be two positive integers, got '{line}'")
    return int(values[0]), int(values[1])


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
