"""Camera pose from 3D-2D matches: P3P inside RANSAC, then Levenberg-Marquardt on the inliers
(paper 003 II-B.1, where MATLAB's estimateWorldCameraPose runs P3P inside MSAC)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3, se3_inverse
from vo_core.klt.config import PoseConfig
from vo_core.klt.triangulation import reprojection_errors


@dataclass
class PoseEstimate:
    T_world_cam: np.ndarray
    inliers: np.ndarray  # (N,) bool over the matches, after refinement


def estimate_pose(
    camera: PinholeCamera, points_world: np.ndarray, uv: np.ndarray, config: PoseConfig
) -> PoseEstimate | None:
    """The pose that best explains the matches, or None when RANSAC finds no consensus of ``min_inliers``."""
    if len(points_world) < max(config.min_inliers, 4):
        return None
    object_points = np.ascontiguousarray(points_world, np.float64)
    image_points = np.ascontiguousarray(uv, np.float64)
    found, rvec, tvec, ransac_inliers = cv2.solvePnPRansac(
        object_points, image_points, camera.K, None,
        iterationsCount=config.ransac_iterations, reprojectionError=config.ransac_threshold_px,
        confidence=config.ransac_confidence, flags=cv2.SOLVEPNP_P3P,
    )
    if not found or ransac_inliers is None or len(ransac_inliers) < config.min_inliers:
        return None
    chosen = ransac_inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(object_points[chosen], image_points[chosen], camera.K, None, rvec, tvec)
    T_world_cam = se3_inverse(se3(cv2.Rodrigues(rvec)[0], tvec.ravel()))
    error, depth = reprojection_errors(camera, T_world_cam, points_world, uv)
    inliers = (depth > 0) & (error < config.ransac_threshold_px)
    if inliers.sum() < config.min_inliers or inliers.mean() < config.min_inlier_ratio:
        return None
    return PoseEstimate(T_world_cam, inliers)
