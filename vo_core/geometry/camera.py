"""Camera models. Pixel coordinates: (u, v) with (0, 0) the centre of the top-left pixel.

Every model offers ``project`` (camera-frame points (N, 3) -> pixels (N, 2)) and ``unproject``
(pixels (N, 2) -> points on the z = 1 plane, (N, 3)). The odometry itself only ever sees a
``PinholeCamera``: distorted images are rectified once by the undistorter before tracking.

The distorted models map a ray to a point x_d on the distorted normalized plane, then to pixels by
u = fx x_d + cx, v = fy y_d + cy. Each is only valid on a range of rays (where its distortion is
monotonic, in front of the lens): rays outside it project to NaN and pixels that no ray of the range
reaches unproject to NaN, so that nothing downstream mistakes a fold of the polynomial for an image.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from vo_core.errors import InputError

# Newton's method inverts the distortions: quadratic convergence from the distorted point as a start
# takes well under 10 steps inside the valid range; the tolerance is on normalized coordinates
# (1e-12 is ~1e-9 px at fx ~ 1000).
NEWTON_MAX_ITERATIONS = 20
NEWTON_TOLERANCE = 1e-12
# A pixel whose inverse still misses by more than this (normalized units) is reached by no valid ray.
UNPROJECT_RESIDUAL_TOLERANCE = 1e-9


@runtime_checkable
class CameraModel(Protocol):
    """What every camera offers: image size, the pinhole part of the intrinsics, project and unproject."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray: ...

    @property
    def intrinsics(self) -> np.ndarray: ...

    def project(self, points_cam: np.ndarray) -> np.ndarray: ...

    def unproject(self, uv: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class PinholeCamera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def intrinsics(self) -> np.ndarray:
        """(fx, fy, cx, cy), as the compiled kernels take them."""
        return np.array([self.fx, self.fy, self.cx, self.cy])

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        points_cam = np.asarray(points_cam, dtype=float)
        z = points_cam[:, 2]
        return np.stack(
            [self.fx * points_cam[:, 0] / z + self.cx, self.fy * points_cam[:, 1] / z + self.cy], axis=1
        )

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=float)
        x = (uv[:, 0] - self.cx) / self.fx
        y = (uv[:, 1] - self.cy) / self.fy
        return np.stack([x, y, np.ones_like(x)], axis=1)

    def scaled(self, factor: float) -> "PinholeCamera":
        """The camera of an image resized by ``factor`` (0.5 for the next pyramid level).

        Pixel centres map as u' = factor * (u + 0.5) - 0.5, the convention of cv2.pyrDown / resize."""
        return PinholeCamera(
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
        )

    def in_image(self, uv: np.ndarray, border: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels at least ``border`` pixels inside the image."""
        return (
            (uv[:, 0] >= border)
            & (uv[:, 1] >= border)
            & (uv[:, 0] <= self.width - 1 - border)
            & (uv[:, 1] <= self.height - 1 - border)
        )


@dataclass(frozen=True)
class DistortedCamera:
    """Shared part of the distorted models: the pinhole intrinsics around a distortion of normalized coordinates.

    Subclasses define ``_distort_rays`` (rays (N, 3) -> distorted normalized (N, 2), NaN outside the
    valid range) and ``_undistort`` (distorted normalized (N, 2) -> normalized (N, 2) on z = 1, or NaN)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    model: ClassVar[str]

    @property
    def distortion(self) -> tuple[float, ...]:
        raise NotImplementedError

    @property
    def pinhole(self) -> PinholeCamera:
        """The same intrinsics without the distortion."""
        return PinholeCamera(self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    @property
    def K(self) -> np.ndarray:
        return self.pinhole.K

    @property
    def intrinsics(self) -> np.ndarray:
        return self.pinhole.intrinsics

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        distorted = self._distort_rays(np.asarray(points_cam, dtype=float))
        return distorted * [self.fx, self.fy] + [self.cx, self.cy]

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=float)
        distorted = (uv - [self.cx, self.cy]) / [self.fx, self.fy]
        xy = self._undistort(distorted)
        return np.column_stack([xy, np.where(np.isnan(xy[:, 0]), np.nan, 1.0)])

    def _distort_rays(self, points_cam: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _undistort(self, distorted: np.ndarray) -> np.ndarray:
        raise NotImplementedError


def _first_positive_root(coefficients: list[float]) -> float:
    """Smallest positive real root of sum_i c_i s^i (coefficients lowest order first), inf if none."""
    roots = np.roots(np.trim_zeros(np.asarray(coefficients[::-1], dtype=float), "f"))
    real = roots[np.abs(roots.imag) <= 1e-9 * np.maximum(1.0, np.abs(roots))].real  # a double root may split
    positive = real[real > 0.0]
    return float(positive.min()) if positive.size else np.inf


def _normalized_rays(points_cam: np.ndarray) -> np.ndarray:
    """x / z, y / z for points in front of the camera, NaN behind it."""
    z = points_cam[:, 2:3]
    in_front = z > 0.0
    return np.where(in_front, points_cam[:, :2] / np.where(in_front, z, 1.0), np.nan)


@dataclass(frozen=True)
class RadTanCamera(DistortedCamera):
    """Pinhole with radial-tangential distortion (Brown-Conrady; OpenCV's model, EuRoC's "radial-tangential").

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y,  r^2 = x^2 + y^2 (OpenCV docs, calib3d)."""

    k1: float
    k2: float
    p1: float
    p2: float
    k3: float = 0.0

    model: ClassVar[str] = "radtan"

    @property
    def distortion(self) -> tuple[float, ...]:
        return (self.k1, self.k2, self.p1, self.p2, self.k3)

    @cached_property
    def max_radius_squared(self) -> float:
        """r^2 where the radial factor r (1 + k1 r^2 + k2 r^4 + k3 r^6) stops increasing: the model's valid range.

        d/dr = 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6; beyond its first zero the polynomial folds back into the image."""
        return _first_positive_root([1.0, 3.0 * self.k1, 5.0 * self.k2, 7.0 * self.k3])

    def _distort(self, xy: np.ndarray) -> np.ndarray:
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        two_xy = 2.0 * x * y
        return np.column_stack(
            [
                x * radial + self.p1 * two_xy + self.p2 * (r2 + 2.0 * x * x),
                y * radial + self.p1 * (r2 + 2.0 * y * y) + self.p2 * two_xy,
            ]
        )

    def _jacobian(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """d x_d / d x, d x_d / d y (= d y_d / d x), d y_d / d y of ``_distort``."""
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        d_radial = 2.0 * (self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3))  # d radial / d r^2, times 2
        dxdx = radial + d_radial * x * x + 2.0 * self.p1 * y + 6.0 * self.p2 * x
        dxdy = d_radial * x * y + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        dydy = radial + d_radial * y * y + 6.0 * self.p1 * y + 2.0 * self.p2 * x
        return dxdx, dxdy, dydy

    def _in_range(self, xy: np.ndarray) -> np.ndarray:
        return np.sum(xy * xy, axis=1) <= self.max_radius_squared

    def _distort_rays(self, points_cam: np.ndarray) -> np.ndarray:
        xy = _normalized_rays(points_cam)
        return np.where(self._in_range(xy)[:, None], self._distort(xy), np.nan)

    def _undistort(self, distorted: np.ndarray) -> np.ndarray:
        """Newton's method on the 2x2 system distort(xy) = x_d, started at x_d."""
        xy = distorted.copy()
        for _ in range(NEWTON_MAX_ITERATIONS):
            residual = self._distort(xy) - distorted
            a, b, d = self._jacobian(xy)
            det = a * d - b * b
            step = np.column_stack([d * residual[:, 0] - b * residual[:, 1], a * residual[:, 1] - b * residual[:, 0]])
            step /= det[:, None]
            xy -= step
            if not np.max(np.abs(step), initial=0.0, where=np.isfinite(step)) > NEWTON_TOLERANCE:
                break
        converged = np.all(np.abs(self._distort(xy) - distorted) <= UNPROJECT_RESIDUAL_TOLERANCE, axis=1)
        return np.where((converged & self._in_range(xy))[:, None], xy, np.nan)


@dataclass(frozen=True)
class EquidistantCamera(DistortedCamera):
    """Kannala-Brandt equidistant fisheye (OpenCV's cv2.fisheye model, Kalibr's "equidistant").

    theta = angle of the ray to the optical axis, theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6
    + k4 theta^8), x_d = theta_d (x, y) / |(x, y)| (Kannala & Brandt 2006, eq. 6). Rays behind the image
    plane (theta > 90 deg) project too; only rays with theta < 90 deg unproject onto z = 1."""

    k1: float
    k2: float
    k3: float
    k4: float

    model: ClassVar[str] = "equidistant"

    @property
    def distortion(self) -> tuple[float, ...]:
        return (self.k1, self.k2, self.k3, self.k4)

    @cached_property
    def max_theta(self) -> float:
        """Largest ray angle where theta_d(theta) still increases (d theta_d / d theta = 0 beyond), at most pi."""
        s = _first_positive_root([1.0, 3.0 * self.k1, 5.0 * self.k2, 7.0 * self.k3, 9.0 * self.k4])
        return float(min(np.sqrt(s), np.pi))

    def _theta_d(self, theta: np.ndarray) -> np.ndarray:
        t2 = theta * theta
        return theta * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))

    def _distort_rays(self, points_cam: np.ndarray) -> np.ndarray:
        radius = np.hypot(points_cam[:, 0], points_cam[:, 1])
        theta = np.arctan2(radius, points_cam[:, 2])  # tolerates rays at and beyond 90 deg, unlike atan(r / z)
        scale = np.divide(self._theta_d(theta), radius, out=np.zeros_like(radius), where=radius > 0.0)
        distorted = points_cam[:, :2] * scale[:, None]
        return np.where((theta <= self.max_theta)[:, None], distorted, np.nan)

    def _undistort(self, distorted: np.ndarray) -> np.ndarray:
        """Newton's method on theta_d(theta) = |x_d|, monotonic on [0, max_theta]; then |x| = tan(theta)."""
        theta_d = np.hypot(distorted[:, 0], distorted[:, 1])
        reachable = theta_d <= self._theta_d(np.array([self.max_theta]))[0]
        theta = np.where(reachable, theta_d, 0.0)
        target = np.where(reachable, theta_d, 0.0)
        for _ in range(NEWTON_MAX_ITERATIONS):
            t2 = theta * theta
            slope = 1.0 + t2 * (3.0 * self.k1 + t2 * (5.0 * self.k2 + t2 * (7.0 * self.k3 + t2 * 9.0 * self.k4)))
            step = (self._theta_d(theta) - target) / slope
            theta = np.clip(theta - step, 0.0, self.max_theta)
            if not np.max(np.abs(step), initial=0.0) > NEWTON_TOLERANCE:
                break
        valid = reachable & (theta < np.pi / 2)
        scale = np.divide(np.tan(np.where(valid, theta, 0.0)), theta_d, out=np.ones_like(theta_d), where=theta_d > 0.0)
        return np.where(valid[:, None], distorted * scale[:, None], np.nan)


@dataclass(frozen=True)
class FovCamera(DistortedCamera):
    """Devernay-Faugeras field-of-view model (TUM monoVO camera.txt, DSO's UndistortFOV).

    r_d = atan(2 r tan(omega / 2)) / omega for the normalized radius r (Devernay & Faugeras 2001, eq. 13);
    the inverse r = tan(r_d omega) / (2 tan(omega / 2)) exists while r_d omega < pi / 2."""

    omega: float

    model: ClassVar[str] = "fov"

    @property
    def distortion(self) -> tuple[float, ...]:
        return (self.omega,)

    def _distort_rays(self, points_cam: np.ndarray) -> np.ndarray:
        xy = _normalized_rays(points_cam)
        if self.omega == 0.0:
            return xy
        r = np.hypot(xy[:, 0], xy[:, 1])
        r_d = np.arctan(r * 2.0 * np.tan(self.omega / 2.0)) / self.omega
        factor = np.divide(r_d, r, out=np.full_like(r, 2.0 * np.tan(self.omega / 2.0) / self.omega), where=r > 0.0)
        return xy * factor[:, None]

    def _undistort(self, distorted: np.ndarray) -> np.ndarray:
        if self.omega == 0.0:
            return distorted.copy()
        r_d = np.hypot(distorted[:, 0], distorted[:, 1])
        valid = r_d * self.omega < np.pi / 2
        r = np.tan(np.where(valid, r_d, 0.0) * self.omega) / (2.0 * np.tan(self.omega / 2.0))
        limit = self.omega / (2.0 * np.tan(self.omega / 2.0))  # r / r_d as r_d -> 0
        factor = np.divide(r, r_d, out=np.full_like(r, limit), where=r_d > 0.0)
        return np.where(valid[:, None], distorted * factor[:, None], np.nan)


# ----------------------------------------------------------------------------------------------- YAML

# model name -> (class, accepted numbers of distortion coefficients)
_MODELS: dict[str, tuple[type, tuple[int, ...]]] = {
    "pinhole": (PinholeCamera, (0,)),
    RadTanCamera.model: (RadTanCamera, (4, 5)),
    EquidistantCamera.model: (EquidistantCamera, (4,)),
    FovCamera.model: (FovCamera, (1,)),
}


def _numbers(value: Any, counts: tuple[int, ...], key: str, what: str, source: str) -> list[float]:
    """A list of finite numbers of one of the accepted lengths, or an InputError that names the key."""
    if value is None and 0 in counts:
        return []
    try:
        numbers = [float(v) for v in value]
    except (TypeError, ValueError):
        numbers = None
    if numbers is None or len(numbers) not in counts or not np.all(np.isfinite(numbers)):
        expected = " or ".join(str(c) for c in counts)
        raise InputError(f"{source}: camera '{key}' must be {expected} numbers {what}, got {value!r}")
    return numbers


def camera_from_dict(d: Any, source: str = "camera") -> CameraModel:
    """A camera from ``{model, intrinsics: [fx, fy, cx, cy], distortion: [...], resolution: [w, h]}``.

    ``model`` is pinhole (no distortion), radtan ([k1, k2, p1, p2] or [k1, k2, p1, p2, k3]),
    equidistant ([k1, k2, k3, k4]) or fov ([omega]). ``source`` names the file in error messages."""
    if not isinstance(d, Mapping):
        raise InputError(f"{source}: a camera must be a mapping with model, intrinsics, resolution, got {d!r}")
    missing = [key for key in ("model", "intrinsics", "resolution") if key not in d]
    if missing:
        raise InputError(f"{source}: camera is missing {', '.join(missing)}")
    model = str(d["model"]).lower()
    if model not in _MODELS:
        raise InputError(f"{source}: unknown camera model {d['model']!r} (expected {', '.join(_MODELS)})")
    cls, distortion_counts = _MODELS[model]
    fx, fy, cx, cy = _numbers(d["intrinsics"], (4,), "intrinsics", "[fx, fy, cx, cy]", source)
    width, height = _numbers(d["resolution"], (2,), "resolution", "[width, height]", source)
    distortion = _numbers(d.get("distortion"), distortion_counts, "distortion", f"for model {model}", source)
    if fx <= 0.0 or fy <= 0.0:
        raise InputError(f"{source}: camera focal lengths must be positive, got fx={fx}, fy={fy}")
    if width <= 0 or height <= 0 or width != int(width) or height != int(height):
        raise InputError(f"{source}: camera resolution must be two positive integers, got {d['resolution']!r}")
    return cls(int(width), int(height), fx, fy, cx, cy, *distortion)


def camera_to_dict(camera: CameraModel) -> dict[str, Any]:
    """The inverse of ``camera_from_dict``, with plain Python numbers (safe for yaml.safe_dump)."""
    model = "pinhole" if isinstance(camera, PinholeCamera) else camera.model
    distortion = [] if isinstance(camera, PinholeCamera) else [float(v) for v in camera.distortion]
    return {
        "model": model,
        "intrinsics": [float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)],
        "distortion": distortion,
        "resolution": [int(camera.width), int(camera.height)],
    }
