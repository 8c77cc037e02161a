"""Bootstrap: the first landmarks from two frames a few apart (paper 003 II-A).

Corners detected in the first frame are tracked frame by frame with KLT; from ``min_frame_gap`` frames on,
each new frame is tried as the second view: the project's two-view reconstruction (homography or fundamental
matrix as ORB-SLAM chooses, the motion hypothesis that puts the points in front of both cameras,
vo_core/geometry/two_view.py; the paper runs an essential-matrix MSAC instead), then a two-view bundle
adjustment. A pair whose median bearing angle is too small is rejected and the next frame tried (the baseline
grows with time).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_core.front_ends.klt.config import BootstrapConfig, TriangulationConfig
from vo_core.geometry.bundle_adjustment import BundleAdjustmentSettings, WindowProblem, adjust_window
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.klt import CornerConfig, KltTracker, detect_corners
from vo_core.geometry.multiview import bearing_angles, reprojection_errors
from vo_core.geometry.two_view import TwoViewFailure, reconstruct


@dataclass
class BootstrapGeometry:
    """The relative pose of the second view (unit baseline) and the tracks it explains."""

    T_first_second: np.ndarray  # 4x4, camera-to-camera, |t| = 1
    inliers: np.ndarray  # (N,) bool over the input matches: consistent with the chosen two-view model
    points_first: np.ndarray  # (N, 3) triangulated points in the first camera (rows valid where ``triangulated``)
    triangulated: np.ndarray  # (N,) bool: inlier, in front of both views, reprojecting well
    median_parallax_deg: float  # median bearing angle of the triangulated points


def two_view_geometry(
    camera: PinholeCamera,
    uv_first: np.ndarray,
    uv_second: np.ndarray,
    config: BootstrapConfig,
    triangulation: TriangulationConfig,
    adjustment: BundleAdjustmentSettings,
    rng: np.random.Generator,
    uv_between: list[np.ndarray] | None = None,
) -> BootstrapGeometry:
    """Relative pose and structure from matched pixels of two calibrated views, or TwoViewFailure saying why not.
    ``uv_between``: the same tracks in the frames between, which tell a plane's two motions apart.

    The reconstruction's pose comes from a minimal sample; a two-view bundle adjustment over its triangulated
    points then lowers the error of the translation direction several times on the synthetic sequences
    (e.g. 3.7 to 0.6 degrees), which matters: the whole trajectory inherits it."""
    uv_first = np.asarray(uv_first, float)
    uv_second = np.asarray(uv_second, float)
    reconstruction = reconstruct(camera, uv_first, uv_second, config.two_view, rng, uv_between)
    points, triangulated = reconstruction.points_first.copy(), reconstruction.good.copy()
    T_first_second, points[triangulated] = _refine(
        camera, reconstruction.T_first_second, points[triangulated], uv_first[triangulated],
        uv_second[triangulated], adjustment,
    )
    for T_world_cam, uv in ((np.eye(4), uv_first), (T_first_second, uv_second)):
        error, depth = reprojection_errors(camera, T_world_cam, points, uv)
        triangulated &= (depth > triangulation.min_depth) & (error < triangulation.max_reprojection_px)
    if not triangulated.any():
        raise TwoViewFailure("no point reprojects well after the two-view bundle adjustment")
    angles = bearing_angles(camera, np.eye(4), uv_first[triangulated], T_first_second, uv_second[triangulated])
    return BootstrapGeometry(
        T_first_second, reconstruction.inliers, points, triangulated, float(np.degrees(np.median(angles)))
    )


def _refine(
    camera: PinholeCamera, T_first_second: np.ndarray, points: np.ndarray, uv_first: np.ndarray,
    uv_second: np.ndarray, adjustment: BundleAdjustmentSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """Two-view bundle adjustment with the first view held, rescaled back to a unit baseline (the scale is
    the one freedom two views leave)."""
    count = len(points)
    problem = WindowProblem(
        np.stack([np.eye(4), T_first_second]), np.array([True, False]), points,
        np.repeat([0, 1], count), np.tile(np.arange(count), 2), np.vstack([uv_first, uv_second]).astype(float),
    )
    solution = adjust_window(camera, problem, adjustment)
    T = solution.poses_world_cam[1]
    scale = 1.0 / np.linalg.norm(T[:3, 3])
    T[:3, 3] *= scale
    return T, solution.points_world * scale


@dataclass
class Bootstrap:
    """A successful bootstrap, in the frame of its first view."""

    first_frame_index: int
    second_frame_index: int
    T_first_second: np.ndarray  # unit baseline
    uv_first: np.ndarray  # (N, 2) every track that survived, in the first view
    uv_second: np.ndarray  # (N, 2) and in the second
    points_first: np.ndarray  # (N, 3) positions in the first camera
    triangulated: np.ndarray  # (N,) bool: which rows have a position (landmarks); the others are candidates
    median_parallax_deg: float


class Bootstrapper:
    """Follows the corners of a first frame until a later frame gives a good two-view reconstruction."""

    def __init__(
        self, camera: PinholeCamera, config: BootstrapConfig, corners: CornerConfig,
        triangulation: TriangulationConfig, adjustment: BundleAdjustmentSettings, tracker: KltTracker,
        seed: int = 0,
    ):
        self.camera = camera
        self.config = config
        self.corners = corners
        self.triangulation = triangulation
        self.adjustment = adjustment
        self.tracker = tracker
        self.seed = seed
        self.first_index = -1
        self.previous_index = -1
        self.previous_image: np.ndarray | None = None
        self.uv_first = np.empty((0, 2), np.float32)
        self.uv_between: list[np.ndarray] = []  # the tracks in every frame between the first and the current
        self.uv_current = np.empty((0, 2), np.float32)
        self.last_failure = ""

    def start(self, frame_index: int, image: np.ndarray) -> None:
        """Make ``image`` the first view: detect its corners."""
        self.first_index = self.previous_index = frame_index
        self.previous_image = image
        self.uv_first = detect_corners(image, self.corners, np.empty((0, 2)), self.corners.max_corners)
        self.uv_between = []
        self.uv_current = self.uv_first.copy()

    def step(self, frame_index: int, image: np.ndarray) -> Bootstrap | None:
        """Track into ``image`` and try it as the second view. None while waiting; ``last_failure`` says why,
        and ``should_restart`` whether this first frame should be given up."""
        uv, valid = self.tracker.track(self.previous_image, image, self.uv_current)
        if self.previous_index != self.first_index:  # the frame tracked from lies between the first and this one
            self.uv_between.append(self.uv_current)
        self.previous_index, self.previous_image = frame_index, image
        self.uv_between = [between[valid] for between in self.uv_between]
        self.uv_first, self.uv_current = self.uv_first[valid], uv[valid]
        gap = frame_index - self.first_index
        if len(self.uv_current) < self.config.min_tracks:
            self.last_failure = f"only {len(self.uv_current)} corners tracked since frame {self.first_index}"
            return None
        if gap < self.config.min_frame_gap:
            self.last_failure = ""
            return None
        # Seeded per frame, as the rest of the pipeline's random draws: a run is reproducible frame by frame.
        rng = np.random.default_rng([self.seed, frame_index])
        try:
            geometry = two_view_geometry(
                self.camera, self.uv_first, self.uv_current, self.config, self.triangulation, self.adjustment,
                rng, self.uv_between,
            )
        except TwoViewFailure as failure:
            self.last_failure = str(failure)
            return None
        problem = self._problem(geometry)
        self.last_failure = problem or ""
        if problem:
            return None
        return Bootstrap(
            self.first_index, frame_index, geometry.T_first_second,
            self.uv_first[geometry.inliers], self.uv_current[geometry.inliers],
            geometry.points_first[geometry.inliers], geometry.triangulated[geometry.inliers],
            geometry.median_parallax_deg,
        )

    def should_restart(self, frame_index: int) -> bool:
        """Too few tracks left, or waited too long for enough parallax: start over from this frame."""
        return (
            len(self.uv_current) < self.config.min_tracks
            or frame_index - self.first_index >= self.config.max_frame_gap
        )

    def _problem(self, geometry: BootstrapGeometry) -> str | None:
        inlier_ratio = geometry.inliers.mean()
        if inlier_ratio < self.config.min_inlier_ratio:
            return f"the two-view model explains only {100 * inlier_ratio:.0f}% of the tracks"
        if geometry.median_parallax_deg < self.config.min_median_parallax_deg:
            return f"median parallax {geometry.median_parallax_deg:.2f} deg is too small"
        if geometry.triangulated.sum() < self.config.min_landmarks:
            return f"only {geometry.triangulated.sum()} points triangulated"
        return None
