"""Geometric bundle adjustment of the initialization window (paper 004 section 3.2).

Every frame the features were tracked through gets a pose (the intermediate ones from PnP on the two-view
structure), and all poses and points are refined together with the first pose held (the gauge). Points with
a severe reprojection error are removed and the adjustment repeated until none remain; then the "normal"
outliers (beyond 3 px) are removed and the survivors adjusted once more.

The solver is the shared windowed bundle adjustment (vo_core/geometry/bundle_adjustment.py): Levenberg-Marquardt
with the Schur complement of the points and a Huber loss.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vo_core.geometry.bundle_adjustment import BundleAdjustmentSettings, WindowProblem, adjust_window
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3, se3_inverse, so3_exp
from vo_core.init.config import GeometricBAConfig

MIN_PNP_POINTS = 6  # EPnP needs at least 4; a margin against degenerate sets


@dataclass
class WindowEstimate:
    poses_world_cam: np.ndarray  # (F, 4, 4); the first is the identity (world = first camera)
    points: np.ndarray  # (M, 3) in the first camera
    keep: np.ndarray  # (M,) bool over the input points: survived the outlier removal
    severe_removed: int
    outliers_removed: int
    rms_px: float


def initial_poses(camera: PinholeCamera, tracks: np.ndarray, points: np.ndarray, T_first_last: np.ndarray) -> np.ndarray:
    """Start values for every frame of the window: the first at identity, the last from two-view geometry, the
    ones between by PnP (EPnP) on the triangulated points, falling back to the last pose where PnP fails."""
    poses = [np.eye(4)]
    for uv in tracks[1:-1]:
        pose = T_first_last
        if len(points) >= MIN_PNP_POINTS:
            ok, rvec, tvec = cv2.solvePnP(
                np.ascontiguousarray(points, float), np.ascontiguousarray(uv, float), camera.K, None, flags=cv2.SOLVEPNP_EPNP
            )
            if ok:
                pose = se3_inverse(se3(so3_exp(rvec.ravel()), tvec.ravel()))
        poses.append(pose)
    poses.append(T_first_last)
    return np.stack(poses)


def _problem(poses: np.ndarray, points: np.ndarray, tracks: np.ndarray) -> WindowProblem:
    frames, count = tracks.shape[:2]
    fixed = np.zeros(frames, bool)
    fixed[0] = True
    return WindowProblem(
        poses, fixed, points, np.repeat(np.arange(frames), count), np.tile(np.arange(count), frames),
        tracks.reshape(-1, 2).astype(float),
    )


def adjust_with_outlier_removal(
    camera: PinholeCamera, poses: np.ndarray, points: np.ndarray, tracks: np.ndarray, config: GeometricBAConfig
) -> WindowEstimate:
    """``tracks`` (F, M, 2) observations of the M ``points`` in the F frames whose start values are ``poses``."""
    solver = BundleAdjustmentSettings(huber_px=config.huber_px, max_iterations=config.max_iterations)
    keep = np.ones(len(points), bool)
    points = points.copy()
    severe = outliers = 0
    threshold = config.severe_outlier_px
    while True:
        indices = np.flatnonzero(keep)
        solution = adjust_window(camera, _problem(poses, points[indices], tracks[:, indices]), solver)
        poses, points[indices] = solution.poses_world_cam, solution.points_world
        worst = solution.errors_after.reshape(len(poses), len(indices)).max(axis=0)
        bad = indices[~(worst <= threshold)]
        keep[bad] = False
        if not keep.any():
            break
        if threshold == config.severe_outlier_px:
            severe += len(bad)
            if len(bad) == 0:
                threshold = config.outlier_px  # no severe ones left: now the normal outliers
            continue
        outliers += len(bad)
        if len(bad) == 0 or not keep.any():
            break
    rms = float(np.sqrt(np.mean(solution.errors_after**2))) if len(solution.errors_after) else 0.0
    return WindowEstimate(poses, points, keep, severe, outliers, rms)
