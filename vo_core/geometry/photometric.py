"""Photometric calibration: inverse camera response, vignette and exposure time.

Image formation (Engel, Usenko, Cremers 2016, "A Photometrically Calibrated Benchmark for Monocular Visual
Odometry", eq. 1): I(x) = G(t V(x) B(x)), with G the response, V the vignette, t the exposure time and B the
scene irradiance. Inverting it, as DSO's PhotometricUndistorter does, gives the energy G^-1(I(x)) / V(x),
divided by t when the exposure is to be removed too. Without files the calibration is the identity (DSO's
photometric mode 1 with no calibration): images come out as float32, unchanged.

DSO's tracker keeps t apart and folds it into the affine brightness model (exposure ratio t_j / t_i); such a
consumer calls ``correct(image)`` without the exposure and passes the exposure on itself.

The vignette lives in the raw (distorted) image geometry: correct first, then rectify.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vo_core.errors import InputError

RESPONSE_LEVELS = 256  # one irradiance value per 8-bit pixel value (TUM monoVO pcalib.txt)
# DSO rescales G^-1 so that it spans the pixel range: pixel values 0 and 255 keep their meaning, and an identity
# response gives the image back unchanged (PhotometricUndistorter, "make it to 0..255 => 0..255").
RESPONSE_RANGE = 255.0


def _checked_response(values: np.ndarray, source: str) -> np.ndarray:
    """G^-1 as a float32 lookup table rescaled to [0, 255], or an InputError that names the source."""
    values = np.asarray(values, dtype=float)
    if values.shape != (RESPONSE_LEVELS,):
        raise InputError(f"{source}: expected {RESPONSE_LEVELS} values of the inverse response, found {values.size}")
    if not np.all(np.isfinite(values)):
        raise InputError(f"{source}: the inverse response has non-finite values")
    steps = np.diff(values)
    if np.any(steps <= 0.0):
        first = int(np.argmax(steps <= 0.0))
        raise InputError(
            f"{source}: the inverse response must be strictly increasing, "
            f"but value {first + 1} ({values[first + 1]:g}) does not exceed value {first} ({values[first]:g})"
        )
    return (RESPONSE_RANGE * (values - values[0]) / (values[-1] - values[0])).astype(np.float32)


def _checked_vignette(vignette: np.ndarray, source: str) -> np.ndarray:
    """V as float32 in (0, 1], or an InputError that names the source."""
    vignette = np.asarray(vignette, dtype=np.float32)
    if vignette.ndim != 2:
        raise InputError(f"{source}: the vignette must be a single-channel image, got shape {vignette.shape}")
    if not np.all(np.isfinite(vignette)) or vignette.min() <= 0.0 or vignette.max() > 1.0:
        raise InputError(
            f"{source}: vignette values must lie in (0, 1], found [{vignette.min():g}, {vignette.max():g}]"
        )
    return vignette


class PhotometricCalibration:
    """Turns 8-bit images into float32 energies: G^-1(I) / V, and / t when the exposure t (ms) is given.

    ``inverse_response``: (256,) strictly increasing G^-1 (any scale: it is rescaled to [0, 255] as DSO does),
    or None for a linear response. ``vignette``: (H, W) values in (0, 1], or None for no vignetting."""

    def __init__(self, inverse_response: np.ndarray | None = None, vignette: np.ndarray | None = None):
        self.inverse_response = (
            None if inverse_response is None else _checked_response(inverse_response, "inverse response")
        )
        self.vignette = None if vignette is None else _checked_vignette(vignette, "vignette")
        # Division by V, done once here as a multiplication per frame.
        self._inverse_vignette = None if self.vignette is None else 1.0 / self.vignette

    @classmethod
    def identity(cls) -> "PhotometricCalibration":
        return cls()

    @property
    def is_identity(self) -> bool:
        return self.inverse_response is None and self.vignette is None

    def correct(self, image: np.ndarray, exposure_ms: float | None = None) -> np.ndarray:
        """Energy G^-1(I) / (V t) as float32 (t = 1 when ``exposure_ms`` is None)."""
        if image.dtype != np.uint8 or image.ndim != 2:
            raise ValueError(f"photometric correction needs a 2-D uint8 image, got {image.dtype} {image.shape}")
        if self.vignette is not None and image.shape != self.vignette.shape:
            raise ValueError(f"image of shape {image.shape} does not match the vignette's {self.vignette.shape}")
        if exposure_ms is not None and not exposure_ms > 0.0:
            raise ValueError(f"exposure time must be positive, got {exposure_ms} ms")
        if self.inverse_response is None:
            energy = image.astype(np.float32)
        else:
            energy = cv2.LUT(image, self.inverse_response)
        if self._inverse_vignette is not None:
            energy *= self._inverse_vignette
        if exposure_ms is not None:
            energy *= np.float32(1.0 / exposure_ms)
        return energy


def _read_response(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"{path}: photometric calibration file not found")
    tokens = path.read_text().split()
    try:
        values = np.array([float(token) for token in tokens])
    except ValueError as exc:
        raise InputError(f"{path}: the inverse response must be numbers ({exc})") from exc
    _checked_response(values, str(path))  # errors name the file; the constructor rescales
    return values


def _read_vignette(path: Path, image_size: tuple[int, int] | None) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"{path}: vignette image not found")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"{path}: cannot decode the vignette image")
    if raw.ndim != 2 or raw.dtype not in (np.uint8, np.uint16):
        raise InputError(
            f"{path}: the vignette must be an 8 or 16 bit single-channel image, got {raw.dtype} {raw.shape}"
        )
    if image_size is not None and (raw.shape[1], raw.shape[0]) != tuple(image_size):
        raise InputError(
            f"{path}: the vignette is {raw.shape[1]}x{raw.shape[0]} but the images are {image_size[0]}x{image_size[1]}"
        )
    if raw.min() == 0:
        zeros = int(np.sum(raw == 0))
        raise InputError(f"{path}: the vignette has {zeros} zero pixels; it must be positive everywhere")
    # DSO normalizes by the brightest pixel: V = 1 where the lens attenuates least.
    return _checked_vignette(raw.astype(np.float32) / float(raw.max()), str(path))


def load_photometric_calibration(
    pcalib_path: str | Path | None,
    vignette_path: str | Path | None,
    image_size: tuple[int, int] | None = None,
) -> PhotometricCalibration:
    """Read TUM monoVO's pcalib.txt (256 values of G^-1) and vignette.png (8 or 16 bit); either may be None.

    ``image_size`` (width, height), when given, must be the vignette's size."""
    response = None if pcalib_path is None else _read_response(Path(pcalib_path))
    vignette = None if vignette_path is None else _read_vignette(Path(vignette_path), image_size)
    return PhotometricCalibration(response, vignette)
