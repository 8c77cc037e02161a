"""Rectify distorted images once, to a pinhole camera, with precomputed maps (DSO's Undistort, src/util/Undistort.cpp).

Output choices, as DSO's camera.txt line 3 (Engel et al., DSO code and TUM monoVO format):
- "crop": the largest pinhole view in which every pixel sees the raw image (DSO's makeOptimalK_crop);
- "full": a pinhole view that shows all of the raw image, with black where nothing was seen (DSO leaves this
  a todo; here: the bounding box of the unprojected raw image border);
- (width, height) or "WxH": crop's field of view at another resolution;
- a ``PinholeCamera``: that target, as given (DSO's line 3 "fx fy cx cy 0"; TUM monoVO's camera.txt uses it);
- "none": the raw camera's own pinhole intrinsics, distortion removed. (DSO's "none" passes the image through
  undistorted and lets the pinhole model ignore the distortion; we rectify instead, so that the pinhole the
  odometry sees is true.)
A raw ``PinholeCamera`` with "crop", "full" or "none" gives the identity: ``rectify`` returns its input.

Photometric maps live in the raw geometry: the vignette is an image like any other and rectifies the same way.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np

from vo_core.errors import InputError
from vo_core.geometry.camera import CameraModel, PinholeCamera

OutputSpec = str | tuple[int, int] | PinholeCamera
OUTPUT_MODES = ("crop", "full", "none")

# makeOptimalK_crop (DSO, Undistort.cpp): start 1% beyond the centre lines' extent, then shrink each side that
# sees outside the raw image by 0.5% per iteration; DSO gives up after 500 iterations.
CROP_START_MARGIN = 1.01
CROP_SHRINK_FACTOR = 0.995
CROP_MAX_ITERATIONS = 500
# Rays sampled along each centre line, evenly in angle so that wide lenses are covered up to 90 degrees.
CENTRE_LINE_SAMPLES = 100_000
# Map value for target pixels that see no raw pixel: far enough outside that bilinear reads only the border (0).
_OUTSIDE = -10.0


@dataclass(frozen=True)
class _Bounds:
    """A rectangle on the normalized image plane z = 1."""

    min_x: float
    max_x: float
    min_y: float
    max_y: float

    def pinhole(self, width: int, height: int) -> PinholeCamera:
        """The pinhole camera whose pixel centres (0, 0) and (w - 1, h - 1) see the rectangle's corners."""
        fx = float((width - 1) / (self.max_x - self.min_x))
        fy = float((height - 1) / (self.max_y - self.min_y))
        return PinholeCamera(width, height, fx, fy, -float(self.min_x) * fx, -float(self.min_y) * fy)


def _inside(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixels where bilinear interpolation reads only real pixels (NaN, from rays outside the model, is not)."""
    return (uv[:, 0] >= 0.0) & (uv[:, 0] <= width - 1) & (uv[:, 1] >= 0.0) & (uv[:, 1] <= height - 1)


def _rays(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x, y = np.broadcast_arrays(x, y)
    return np.column_stack([x, y, np.ones(x.shape)])


def _sees_raw_image(raw: CameraModel, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return _inside(raw.project(_rays(x, y)), raw.width, raw.height)


def _centre_line_extent(raw: CameraModel, axis: int) -> tuple[float, float]:
    """The interval around 0 of one normalized axis, along the line through the principal point, seen by the raw image.

    DSO keeps the first and last sample inside the image; we stop at the first one outside, going out from the
    centre, so that a distortion polynomial folding back into the image cannot extend the interval."""
    offsets = np.tan(np.linspace(0.0, np.pi / 2, CENTRE_LINE_SAMPLES, endpoint=False)[1:])
    extent = []
    for sign in (-1.0, 1.0):
        line = sign * offsets
        inside = _sees_raw_image(raw, line, 0.0) if axis == 0 else _sees_raw_image(raw, 0.0, line)
        count = len(inside) if inside.all() else int(np.argmin(inside))
        if count == 0:
            raise InputError(f"camera {raw!r}: the principal point is not inside the image, cannot rectify")
        extent.append(line[count - 1])
    return extent[0], extent[1]


def _full_bounds(raw: CameraModel) -> _Bounds:
    """Bounding box of the raw image border on the normalized plane (border pixels beyond 90 degrees are left out)."""
    u, v = np.arange(raw.width, dtype=float), np.arange(raw.height, dtype=float)
    border = np.concatenate(
        [
            np.column_stack([u, np.zeros_like(u)]),
            np.column_stack([u, np.full_like(u, raw.height - 1)]),
            np.column_stack([np.zeros_like(v), v]),
            np.column_stack([np.full_like(v, raw.width - 1), v]),
        ]
    )
    rays = raw.unproject(border)
    rays = rays[np.isfinite(rays[:, 0])]
    if len(rays) == 0:
        raise InputError(f"camera {raw!r}: no pixel of the image border unprojects, cannot rectify")
    return _Bounds(rays[:, 0].min(), rays[:, 0].max(), rays[:, 1].min(), rays[:, 1].max())


def _crop_bounds(raw: CameraModel) -> _Bounds:
    """DSO's makeOptimalK_crop: the largest rectangle on the normalized plane whose border the raw image sees.

    1. Start from the centre lines' extent, slightly enlarged. 2. While a side sees outside the raw image, shrink
    it; when both a vertical and a horizontal side do, shrink only the wider dimension."""
    if isinstance(raw, PinholeCamera):
        return _full_bounds(raw)  # without distortion the whole image is valid
    min_x, max_x = (CROP_START_MARGIN * e for e in _centre_line_extent(raw, 0))
    min_y, max_y = (CROP_START_MARGIN * e for e in _centre_line_extent(raw, 1))
    samples = 2 * max(raw.width, raw.height)  # denser than any output row or column
    for _ in range(CROP_MAX_ITERATIONS):
        ys, xs = np.linspace(min_y, max_y, samples), np.linspace(min_x, max_x, samples)
        out_left = not _sees_raw_image(raw, min_x, ys).all()
        out_right = not _sees_raw_image(raw, max_x, ys).all()
        out_top = not _sees_raw_image(raw, xs, min_y).all()
        out_bottom = not _sees_raw_image(raw, xs, max_y).all()
        if not (out_left or out_right or out_top or out_bottom):
            return _Bounds(min_x, max_x, min_y, max_y)
        if (out_left or out_right) and (out_top or out_bottom):
            if max_x - min_x > max_y - min_y:
                out_top = out_bottom = False
            else:
                out_left = out_right = False
        min_x *= CROP_SHRINK_FACTOR if out_left else 1.0
        max_x *= CROP_SHRINK_FACTOR if out_right else 1.0
        min_y *= CROP_SHRINK_FACTOR if out_top else 1.0
        max_y *= CROP_SHRINK_FACTOR if out_bottom else 1.0
    raise InputError(f"camera {raw!r}: no valid crop found in {CROP_MAX_ITERATIONS} iterations")


def _parse_output(output: OutputSpec) -> tuple[str, tuple[int, int] | None]:
    """("crop" | "full" | "none", None) or ("size", (width, height)), from a mode, "WxH" or a pair."""
    if isinstance(output, str):
        if output in OUTPUT_MODES:
            return output, None
        match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", output)
        size = (int(match.group(1)), int(match.group(2))) if match else None
    else:
        try:
            width, height = output
            size = (int(width), int(height)) if int(width) == width and int(height) == height else None
        except (TypeError, ValueError):
            size = None
    if size is None or min(size) < 2:
        raise InputError(f"undistort output {output!r}: expected crop, full, none, WxH or (width, height), sizes >= 2")
    return "size", size


def _target_camera(raw: CameraModel, output: OutputSpec) -> PinholeCamera:
    if isinstance(output, PinholeCamera):
        return raw if output == raw else output
    mode, size = _parse_output(output)
    if isinstance(raw, PinholeCamera) and mode in OUTPUT_MODES:
        return raw
    if mode == "none":
        return PinholeCamera(raw.width, raw.height, raw.fx, raw.fy, raw.cx, raw.cy)
    bounds = _full_bounds(raw) if mode == "full" else _crop_bounds(raw)
    width, height = size or (raw.width, raw.height)
    return bounds.pinhole(width, height)


class Undistorter:
    """Rectifies images of ``raw_camera`` into ``camera``, a pinhole, with maps computed once.

    ``rectify`` samples bilinearly (cv2.remap); target pixels that see nothing of the raw image are 0 and
    are marked False in ``valid_mask``."""

    def __init__(self, raw_camera: CameraModel, output: OutputSpec = "crop"):
        self.raw_camera = raw_camera
        self.camera = _target_camera(raw_camera, output)
        self.is_identity = self.camera is raw_camera
        self._map_x, self._map_y, self.valid_mask = self._build_maps()

    def _build_maps(self) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray]:
        target, raw = self.camera, self.raw_camera
        if self.is_identity:
            return None, None, np.ones((target.height, target.width), dtype=bool)
        u, v = np.meshgrid(np.arange(target.width, dtype=float), np.arange(target.height, dtype=float))
        raw_uv = raw.project(target.unproject(np.column_stack([u.ravel(), v.ravel()])))
        valid = _inside(raw_uv, raw.width, raw.height)
        raw_uv[~valid] = _OUTSIDE
        shape = (target.height, target.width)
        # Fixed-point maps: what cv2.remap converts float maps to anyway (1/32 px), without converting each frame.
        map_xy, map_fraction = cv2.convertMaps(
            raw_uv[:, 0].reshape(shape).astype(np.float32),
            raw_uv[:, 1].reshape(shape).astype(np.float32),
            cv2.CV_16SC2,
        )
        return map_xy, map_fraction, valid.reshape(shape)

    def rectify(self, image: np.ndarray) -> np.ndarray:
        """The image seen through ``camera``, same dtype (uint8, float32, ...); the input itself when identity."""
        if image.shape[:2] != (self.raw_camera.height, self.raw_camera.width):
            raise ValueError(
                f"image of {image.shape[1]}x{image.shape[0]} pixels given to an undistorter for "
                f"{self.raw_camera.width}x{self.raw_camera.height}"
            )
        if self.is_identity:
            return image
        return cv2.remap(
            image, self._map_x, self._map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
