"""Camera models. Pixel coordinates: (u, v) with (0, 0) the centre of the top-left pixel.

Every model offers ``project`` (camera-frame points (N, 3) -> pixels (N, 2)) and ``unproject``
(pixels (N, 2) -> points on the z = 1 plane, (N, 3)). The odometry itself only ever sees a
``PinholeCamera``: distorted images are rectified once by the undistorter before tracking.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
