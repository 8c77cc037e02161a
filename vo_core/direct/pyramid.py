"""Image pyramid with gradients, as DSO's FrameHessian::makeImages.

Each level halves the previous one by 2x2 averaging (an odd last row or column is dropped first) and stores
intensity, central-difference gradients and the squared gradient magnitude. The three channels are packed
into one (h, w, 3) float32 array so that a single ``cv2.remap`` samples intensity and gradient together.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from vo_core.compiled import kernel
from vo_core.direct.config import PyramidConfig
from vo_core.geometry.camera import PinholeCamera


class PyramidLevel:
    """One level: its camera, its intensities and, made on first use, the packed (intensity, d/du, d/dv) image.

    A keyframe that is no longer the newest releases its packed images (``release_packed``): what reads it later
    (the window, the activation's depth refinement) reads the intensities, and its points carry their host
    pattern. At 640x480 a pyramid's packed images are 4.9 MB of the 6.5 (issue 17)."""

    def __init__(self, camera: PinholeCamera, intensity: np.ndarray):
        self.camera = camera
        self.intensity = intensity  # (h, w) float32, contiguous (cv2 would copy a strided view on every call)
        self._packed: np.ndarray | None = None

    @property
    def packed(self) -> np.ndarray:
        """(h, w, 3) float32: intensity, d/du, d/dv; made again if it was released."""
        return self.pack()

    def pack(self) -> np.ndarray:
        """The packed image, made now if it is not there (read once: the mapper may release it meanwhile)."""
        packed = self._packed
        if packed is None:
            packed = self._packed = _packed(self.intensity)
        return packed

    @property
    def holds_packed(self) -> bool:
        return self._packed is not None

    def release_packed(self) -> None:
        self._packed = None

    @property
    def grad_sq(self) -> np.ndarray:
        """|grad I|^2 per pixel (DSO's absSquaredGrad)."""
        return squared_gradient(self.packed)

    def sample(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Bilinear (intensity, du, dv) at float pixels (any shape); NaN outside the image."""
        return remap_points(self.packed, u, v).reshape(*np.shape(u), 3)

    def sample_intensity(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return remap_points(self.intensity, u, v).reshape(np.shape(u))


def squared_gradient(samples: np.ndarray) -> np.ndarray:
    """|grad I|^2 of packed (..., 3) samples (intensity, d/du, d/dv), in their float32. One compiled pass: numpy's
    two temporaries made a keyframe's pixel selection 1 ms slower."""
    return _squared_gradient(samples.reshape(-1, samples.shape[-1])).reshape(samples.shape[:-1])


@kernel
def _squared_gradient(samples):
    result = np.empty(len(samples), samples.dtype)
    for i in range(len(samples)):
        result[i] = samples[i, 1] * samples[i, 1] + samples[i, 2] * samples[i, 2]
    return result


_REMAP_COLUMNS = 4096  # cv2.remap needs maps narrower than SHRT_MAX: points are laid out in rows of this


def remap_points(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at the points (u, v), shape (N,) or (N, channels); NaN outside."""
    u = np.asarray(u, dtype=np.float32).reshape(-1)
    v = np.asarray(v, dtype=np.float32).reshape(-1)
    n = len(u)
    columns = max(min(n, _REMAP_COLUMNS), 1)
    rows = -(-n // columns) if n else 1
    map_u = np.full(rows * columns, -1e6, np.float32)
    map_v = np.full(rows * columns, -1e6, np.float32)
    map_u[:n], map_v[:n] = u, v
    out = cv2.remap(
        image, map_u.reshape(rows, columns), map_v.reshape(rows, columns), cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan,
    )
    channels = image.shape[2:] if image.ndim == 3 else ()
    return out.reshape(rows * columns, *channels)[:n]


@kernel
def _packed(image: np.ndarray) -> np.ndarray:
    """(h, w, 3) float32 intensity and central differences 0.5 (I[x+1] - I[x-1]) as DSO, zero gradients on the
    border rows and columns. One compiled pass: numpy's slices and np.dstack took most of the pyramid's time. Every
    value is written once (no zeroed array written again): 0.47 -> 0.21 ms at 640x480, the same numbers."""
    h, w = image.shape
    packed = np.empty((h, w, 3), np.float32)
    for y in range(h):
        row, out = image[y], packed[y]
        inner_row = 0 < y < h - 1
        for x in range(w):
            out[x, 0] = row[x]
            out[x, 1] = 0.5 * (row[x + 1] - row[x - 1]) if 0 < x < w - 1 else 0.0
            out[x, 2] = 0.5 * (image[y + 1, x] - image[y - 1, x]) if inner_row else 0.0
    return packed


@kernel
def _half(image: np.ndarray) -> np.ndarray:
    """2x2 block average of the even part of the image (DSO makeImages), summed in float32 in a fixed order."""
    h, w = image.shape[0] // 2, image.shape[1] // 2
    out = np.empty((h, w), np.float32)
    for y in range(h):
        top, bottom = image[2 * y], image[2 * y + 1]
        for x in range(w):
            out[y, x] = 0.25 * (top[2 * x] + bottom[2 * x] + top[2 * x + 1] + bottom[2 * x + 1])
    return out


def num_levels(width: int, height: int, config: PyramidConfig) -> int:
    """DSO's rule: keep halving while the current level has more than ``min_pixels_coarsest`` pixels."""
    levels = 1
    while levels < config.max_levels and width * height > config.min_pixels_coarsest:
        width, height = width // 2, height // 2
        levels += 1
    return levels


class ImagePyramid:
    """Levels 0 (full resolution) to n-1 of one image, with the camera of each level."""

    def __init__(self, image: np.ndarray, camera: PinholeCamera, config: PyramidConfig):
        image = np.ascontiguousarray(image, dtype=np.float32)
        count = num_levels(image.shape[1], image.shape[0], config)
        self.levels: list[PyramidLevel] = []
        level_camera = camera
        for level in range(count):
            if level > 0:
                image = _half(image)
                level_camera = dataclasses.replace(
                    level_camera.scaled(0.5), width=image.shape[1], height=image.shape[0]
                )
            self.levels.append(PyramidLevel(level_camera, image))

    def __len__(self) -> int:
        return len(self.levels)

    def pack(self) -> "ImagePyramid":
        """Make every level's packed image now (tracking reads them all)."""
        for level in self.levels:
            level.pack()
        return self

    def release_packed(self) -> None:
        for level in self.levels:
            level.release_packed()

    def __getitem__(self, level: int) -> PyramidLevel:
        return self.levels[level]


def to_level(uv: np.ndarray, level: int) -> np.ndarray:
    """Level-0 pixels to pixels of ``level`` (pixel centres: u_l = (u + 0.5) / 2^l - 0.5)."""
    return (np.asarray(uv, dtype=float) + 0.5) / (1 << level) - 0.5
