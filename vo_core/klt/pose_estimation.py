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
    camera: PinholeCamera, points_world: np.ndarray, uv: np.ndarray, config: PoseConfig, T_world_guess: np.ndarray
) -> PoseEstimate | None:
    """The pose that best explains the matches, or None when RANSAC finds no consensus of ``min_inliers``.

    The RANSAC inliers are refined twice, from RANSAC's own pose and from ``T_world_guess`` (the motion
    model's prediction), and the refinement with more inliers wins: OpenCV re-estimates RANSAC's final
    pose from all inliers with EPnP, which now and then lands far from them (seen on KITTI: 148 inliers,
    none of them within 2 px of the returned pose)."""
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
    best = None
    for start in (se3(cv2.Rodrigues(rvec)[0], tvec.ravel()), se3_inverse(T_world_guess)):
        rvec, tvec = cv2.solvePnPRefineLM(
            object_points[chosen], image_points[chosen], camera.K, None,
            cv2.Rodrigues(start[:3, :3])[0], start[:3, 3].reshape(3, 1).copy(),
        )
        T_world_cam = se3_inverse(se3(cv2.Rodrigues(rvec)[0], tvec.ravel()))
        error, depth = reprojection_errors(camera, T_world_cam, points_world, uv)
        inliers = (depth > 0) & (error < config.ransac_threshold_px)
        if best is None or inliers.sum() > best.inliers.sum():
            best = PoseEstimate(T_world_cam, inliers)
    if best.inliers.sum() < config.min_inliers or best.inliers.mean() < config.min_inlier_ratio:
        return None
    return best
